"""VGGT input preprocessing: resize to 518 wide (``crop``) or to fit 518x518 (``pad``).

Matches the reference ``load_and_preprocess_images`` bit for bit when Pillow's bicubic resize is used:
RGBA is composited onto white; sizes use Python's round-half-to-even to a multiple of 14; crop keeps
the central 518 rows of tall images; pad centres the image on white (1.0); images of one call that end
up with different shapes are all padded (white, centred) to the largest height and width.

Every image also gets a :class:`PreprocessInfo` so network-pixel coordinates map back to the original
image. Pixel coordinates follow OpenCV (pixel centres at integers); a resize by ``s`` maps the image's
corner-based extent exactly, so ``x_orig = (x_net + 0.5 - offset_x) / scale_x - 0.5`` (same for y).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from vggt_slam_pp.errors import ModelError

log = logging.getLogger(__name__)

TARGET_SIZE = 518
MODES = ("crop", "pad")


@dataclass(frozen=True)
class PreprocessInfo:
    """Mapping of one image into the network input (OpenCV pixel centres at integers):
    ``x_net + 0.5 = (x_orig + 0.5) * scale_x + offset_x``; offsets are the crop (negative) or pad."""

    original_hw: tuple[int, int]
    network_hw: tuple[int, int]
    scale_x: float
    scale_y: float
    offset_x: float
    offset_y: float

    def to_original(self, xy: np.ndarray) -> np.ndarray:
        """Network pixel coordinates [..., 2] (x, y) -> original image pixels."""
        xy = np.asarray(xy, dtype=np.float64)
        return (xy + 0.5 - [self.offset_x, self.offset_y]) / [self.scale_x, self.scale_y] - 0.5

    def to_original_matrix(self) -> np.ndarray:
        """3x3 affine map of homogeneous network pixels (x, y, 1) to original pixels."""
        sx, sy, ox, oy = self.scale_x, self.scale_y, self.offset_x, self.offset_y
        return np.array([[1 / sx, 0, (0.5 - ox) / sx - 0.5], [0, 1 / sy, (0.5 - oy) / sy - 0.5], [0, 0, 1]])

    def intrinsics_to_original(self, K: np.ndarray) -> np.ndarray:
        """A 3x3 intrinsic matrix at network resolution -> the same camera in original pixels."""
        return self.to_original_matrix() @ np.asarray(K, dtype=np.float64)


def _to_pil(image) -> Image.Image:
    if isinstance(image, Image.Image):
        img = image
    elif isinstance(image, (str, Path)):
        try:
            img = Image.open(image)
            img.load()
        except (OSError, ValueError) as exc:
            raise ModelError(f"cannot read image {image}: {exc}") from exc
    else:
        arr = np.asarray(image)
        if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (1, 3, 4)):
            raise ModelError(f"expected a uint8 HxW, HxWx3 or HxWx4 image, got {arr.dtype} {arr.shape}")
        img = Image.fromarray(arr[..., 0] if arr.ndim == 3 and arr.shape[2] == 1 else arr)
    if img.mode == "RGBA":
        img = Image.alpha_composite(Image.new("RGBA", img.size, (255, 255, 255, 255)), img)
    return img.convert("RGB")


def _network_size(w0: int, h0: int, mode: str, target: int) -> tuple[int, int]:
    if mode == "pad" and h0 > w0:
        return round(w0 * target / h0 / 14) * 14, target
    return target, round(h0 * target / w0 / 14) * 14


def preprocess_images(images: Sequence, mode: str = "crop", target_size: int = TARGET_SIZE
                      ) -> tuple[torch.Tensor, list[PreprocessInfo]]:
    """Images (paths, PIL images or uint8 arrays HxWx{3,4}) -> ([N,3,H,W] float32 in [0,1], infos)."""
    if mode not in MODES:
        raise ModelError(f"unknown preprocessing mode {mode!r}; expected 'crop' or 'pad'")
    if len(images) == 0:
        raise ModelError("no images to preprocess")
    tensors, infos = [], []
    for image in images:
        img = _to_pil(image)
        w0, h0 = img.size
        nw, nh = _network_size(w0, h0, mode, target_size)
        arr = np.asarray(img.resize((nw, nh), Image.Resampling.BICUBIC), dtype=np.float32) / 255.0
        t = torch.from_numpy(arr).permute(2, 0, 1)
        ox = oy = 0.0
        if mode == "crop" and nh > target_size:
            top = (nh - target_size) // 2
            t = t[:, top:top + target_size]
            oy = -float(top)
        elif mode == "pad":
            top, left = (target_size - nh) // 2, (target_size - nw) // 2
            t = torch.nn.functional.pad(t, (left, target_size - nw - left, top, target_size - nh - top),
                                        value=1.0)
            ox, oy = float(left), float(top)
        tensors.append(t)
        infos.append(PreprocessInfo((h0, w0), tuple(t.shape[1:]), nw / w0, nh / h0, ox, oy))
    shapes = {tuple(t.shape[1:]) for t in tensors}
    if len(shapes) > 1:
        log.warning("images have different shapes after preprocessing %s; padding to the largest", sorted(shapes))
        H = max(s[0] for s in shapes)
        W = max(s[1] for s in shapes)
        for i, t in enumerate(tensors):
            top, left = (H - t.shape[1]) // 2, (W - t.shape[2]) // 2
            tensors[i] = torch.nn.functional.pad(t, (left, W - t.shape[2] - left, top, H - t.shape[1] - top),
                                                 value=1.0)
            inf = infos[i]
            infos[i] = PreprocessInfo(inf.original_hw, (H, W), inf.scale_x, inf.scale_y,
                                      inf.offset_x + left, inf.offset_y + top)
    return torch.stack(tensors), infos
