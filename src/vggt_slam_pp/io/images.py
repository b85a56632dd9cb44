"""Reading colour and depth images into the package's array conventions."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from vggt_slam_pp.errors import InputError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".jp2")

__all__ = ["IMAGE_EXTENSIONS", "read_rgb", "to_rgb_uint8", "read_depth", "write_depth_png"]


def to_rgb_uint8(img: np.ndarray, source: str = "image") -> np.ndarray:
    """Convert an OpenCV-decoded array (gray, BGR, BGRA; 8 or 16 bit) to RGB uint8 ``[H, W, 3]``."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        f = img.astype(np.float32)
        f = f / max(float(np.nanmax(f)), 1e-12) if f.max() > 1.0 else f
        img = np.clip(np.nan_to_num(f) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim == 3 and img.shape[2] == 1:
        return np.repeat(img, 3, axis=2)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    raise InputError(f"unsupported image layout {img.shape} in {source}")


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read any image OpenCV decodes as RGB uint8 ``[H, W, 3]``; grayscale is replicated to 3 channels.

    Raises:
        InputError: the file is missing or cannot be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"cannot read image (corrupt or unsupported format): {path}")
    return to_rgb_uint8(img, str(path))


def read_depth(path: str | os.PathLike, scale: float, invalid_value: int | None = None) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres ``[H, W]``: ``depth = raw / scale``; 0 means unknown.

    Args:
        scale: raw units per metre (TUM: 5000, 7-Scenes: 1000, Virtual KITTI 2: 100).
        invalid_value: raw value that also means "unknown" (7-Scenes uses 65535).
    """
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"cannot read depth image: {path}")
    if raw.ndim != 2:
        raise InputError(f"depth image must be single-channel, got shape {raw.shape}: {path}")
    depth = raw.astype(np.float32) / np.float32(scale)
    if invalid_value is not None:
        depth[raw == invalid_value] = 0.0
    return depth


def write_depth_png(path: str | os.PathLike, depth: np.ndarray, scale: float) -> None:
    """Write metres ``[H, W]`` as a 16-bit PNG (``raw = round(depth * scale)``); out-of-range or unknown
    depths (NaN, <= 0, or above ``65535 / scale``) are stored as 0."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    raw = np.round(d * scale)
    raw[(raw <= 0) | (raw > 65535)] = 0
    if not cv2.imwrite(str(path), raw.astype(np.uint16)):
        raise InputError(f"cannot write depth image: {path}")
