"""Encoders: a DEM image -> a dense grid of patch features (SPEC 3.7), computed once per layer.

* ``hog`` (weight-free): per ``patch_px`` patch a histogram of gradient orientations (9 unsigned
  bins) in each of its 2x2 cells, weighted by gradient magnitude (OpenCV Sobel / cartToPolar), each
  patch block L2-normalised: 36-D.
* ``dinov2``: our DINOv2 ViT (ViT-B/14 by default, 768-D patch tokens) on the grey image replicated
  to 3 channels and ImageNet-normalised; ``value_facet`` gives the VLAD features (value facet of a
  late block, AnyLoc).

Images are padded (white) to a multiple of ``patch_px``; features are [rows, cols, D] float32 with one
cell per ``patch_px`` x ``patch_px`` pixel patch.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import cv2
import numpy as np

from vggt_slam_pp.errors import RetrievalError


def pad_to_multiple(image: np.ndarray, m: int, value: float = 1.0) -> np.ndarray:
    H, W = image.shape[:2]
    ph, pw = (-H) % m, (-W) % m
    if ph or pw:
        image = np.pad(image, ((0, ph), (0, pw)), constant_values=value)
    return image


class Encoder(ABC):
    name: str = "encoder"
    patch_px: int = 14
    dim: int = 0

    @abstractmethod
    def encode(self, image: np.ndarray) -> np.ndarray:
        """Image [H,W] float in [0,1] -> features [ceil(H/p), ceil(W/p), dim] float32."""

    def vlad_features(self, image: np.ndarray) -> np.ndarray:
        """Dense features used for VLAD (default: the same as :meth:`encode`)."""
        return self.encode(image)

    @classmethod
    def from_config(cls, weights: str | None = None) -> Encoder:
        """The encoder a run configures (``BackendConfig.encoder_weights``: for encoders with weights)."""
        return cls()


class HogEncoder(Encoder):
    name = "hog"

    def __init__(self, patch_px: int = 14, bins: int = 9) -> None:
        if patch_px % 2:
            raise RetrievalError("hog patch size must be even (2x2 cells per patch)")
        self.patch_px, self.bins = patch_px, bins
        self.dim = 4 * bins

    def encode(self, image: np.ndarray) -> np.ndarray:
        img = pad_to_multiple(np.asarray(image, np.float32), self.patch_px)
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
        mag, ang = cv2.cartToPolar(gx, gy)
        ang = np.mod(ang, np.pi)  # unsigned orientation
        b = np.minimum((ang / np.pi * self.bins).astype(np.int64), self.bins - 1)
        H, W = img.shape
        c = self.patch_px // 2
        cy, cx = np.mgrid[0:H, 0:W]
        cell = (cy // c) * (W // c) + (cx // c)
        hist = np.bincount((cell * self.bins + b).reshape(-1), weights=mag.reshape(-1),
                           minlength=(H // c) * (W // c) * self.bins).reshape(H // c, W // c, self.bins)
        rows, cols = H // self.patch_px, W // self.patch_px
        blocks = hist.reshape(rows, 2, cols, 2, self.bins).transpose(0, 2, 1, 3, 4).reshape(rows, cols, -1)
        norm = np.linalg.norm(blocks, axis=2, keepdims=True)
        return (blocks / np.maximum(norm, 1e-6)).astype(np.float32)


class DinoV2Encoder(Encoder):
    name = "dinov2"
    patch_px = 14

    @classmethod
    def from_config(cls, weights: str | None = None) -> DinoV2Encoder:
        return cls(weights=weights)

    def __init__(self, model=None, name: str = "dinov2_vitb14", weights: str | None = None, device: str = "cpu",
                 value_layer: int | None = None, allow_download: bool = True) -> None:
        import torch

        if model is None:
            from vggt_slam_pp.models.weights import load_dinov2

            model = load_dinov2(name, weights, device=device, allow_download=allow_download)
        self.model = model.eval()
        self.device = torch.device(device)
        self.dim = model.embed_dim
        depth = len(model.blocks)
        self.value_layer = value_layer if value_layer is not None else depth - 2  # a late layer (AnyLoc)

    def _input(self, image: np.ndarray):
        import torch

        from vggt_slam_pp.models.dinov2 import IMAGENET_MEAN, IMAGENET_STD

        img = pad_to_multiple(np.asarray(image, np.float32), self.patch_px)
        x = torch.from_numpy(img)[None, None].expand(1, 3, *img.shape).to(self.device)
        mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 3, 1, 1)
        return (x - mean) / std, img.shape

    def encode(self, image: np.ndarray) -> np.ndarray:
        import torch

        x, (H, W) = self._input(image)
        with torch.inference_mode():
            tokens = self.model.forward_features(x)["x_norm_patchtokens"][0]
        return tokens.reshape(H // 14, W // 14, -1).float().cpu().numpy()

    def vlad_features(self, image: np.ndarray) -> np.ndarray:
        import torch

        x, (H, W) = self._input(image)
        with torch.inference_mode():
            v = self.model.get_facets(x, [self.value_layer], "value", patches_only=True)[self.value_layer][0]
        return v.reshape(H // 14, W // 14, -1).float().cpu().numpy()


def make_encoder(name: str, **kwargs) -> Encoder:
    """The encoder registered as ``name`` (:data:`vggt_slam_pp.plugins.ENCODERS`) built with ``kwargs``."""
    from vggt_slam_pp.plugins import ENCODERS, load

    return load(ENCODERS, name, "encoder", RetrievalError)(**kwargs)
