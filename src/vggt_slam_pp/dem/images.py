"""DEM images: the encoder's input, the colour hillshade for people, and export (SPEC 3.6).

Encoder image: percentile normalisation (0.5 / 99.5 % of the layer's heights) to N in [0, 1], then
Sobel edge darkening ``I = N * (1 - alpha * |grad N| / p99(|grad N|))``, clipped to [0, 1]; empty (NaN)
pixels are white (1). A layer with a single height (flat, or one point) has no spread: its
normalised heights are 0.5, so its image is uniform grey.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from vggt_slam_pp.dem.plane import GroundPlane
from vggt_slam_pp.errors import DemError


def fill_holes(heights: np.ndarray, radius_px: int) -> np.ndarray:
    """Fill empty pixels that have data within ``radius_px`` (box window) with the mean of that data.

    Points sparser than the grid (far ground, a subsampled backbone) leave empty pixels between
    image rows; left empty they draw a stripe texture that depends on the camera, not on the place.
    Valid pixels are unchanged; larger holes stay NaN. ``radius_px`` 0 returns the input.
    """
    if radius_px <= 0:
        return heights
    valid = np.isfinite(heights)
    k = (2 * radius_px + 1, 2 * radius_px + 1)
    total = cv2.boxFilter(np.where(valid, heights, 0.0).astype(np.float32), -1, k, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(valid.astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        filled = np.where(count > 0.5, total / count, np.nan)
    return np.where(valid, heights, filled).astype(np.float32)


def normalized_heights(heights: np.ndarray, percentiles: tuple[float, float] = (0.5, 99.5)) -> np.ndarray:
    """Heights [H,W] (NaN = empty) -> [0,1] by the given percentiles of the valid heights; NaN kept."""
    valid = np.isfinite(heights)
    out = np.full(heights.shape, np.nan, np.float32)
    if not valid.any():
        return out
    lo, hi = np.percentile(heights[valid], percentiles)
    if hi - lo <= 1e-12:
        out[valid] = 0.5
    else:
        out[valid] = np.clip((heights[valid] - lo) / (hi - lo), 0.0, 1.0)
    return out


def gradient_magnitude(normalized: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude of a normalised height image (empty pixels treated as their mean)."""
    img = np.where(np.isfinite(normalized), normalized, np.nanmean(normalized) if np.isfinite(normalized).any()
                   else 0.0).astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(gx * gx + gy * gy)


def encoder_image(heights: np.ndarray, alpha_edge: float = 0.95,
                  percentiles: tuple[float, float] = (0.5, 99.5)) -> np.ndarray:
    """The encoder's input image [H,W] float32 in [0,1] (NaN -> white)."""
    n = normalized_heights(heights, percentiles)
    g = gradient_magnitude(n)
    valid = np.isfinite(n)
    p99 = float(np.percentile(g[valid], 99)) if valid.any() else 0.0
    dark = alpha_edge * g / p99 if p99 > 1e-12 else np.zeros_like(g)
    img = np.clip(np.where(valid, n, 1.0) * (1.0 - dark), 0.0, 1.0)
    img[~valid] = 1.0
    return img.astype(np.float32)


_RAMP_LOW, _RAMP_HIGH = np.array([240, 220, 90], float), np.array([20, 90, 30], float)  # RGB: ground, high


def height_ramp(t: np.ndarray) -> np.ndarray:
    """Normalised heights [...] in [0,1] -> RGB [..., 3] float: yellow (ground) to dark green (high)."""
    t = np.asarray(t, float)[..., None]
    return (1 - t) * _RAMP_LOW + t * _RAMP_HIGH


def hillshade_rgb(heights: np.ndarray, azimuth_deg: float = 315.0, altitude_deg: float = 45.0,
                  mpp: float = 1.0) -> np.ndarray:
    """Colour image for people [H,W,3] uint8: yellow (ground) to dark green (high), Lambertian hillshade;
    empty pixels white."""
    n = normalized_heights(heights)
    valid = np.isfinite(n)
    z = np.where(valid, heights, np.nanmedian(heights) if valid.any() else 0.0).astype(np.float32)
    gx = cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3) / np.float32(8 * mpp)
    gy = cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3) / np.float32(8 * mpp)
    az, alt = np.radians(azimuth_deg), np.radians(altitude_deg)
    light = np.array([np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az), np.sin(alt)], np.float32)
    # Lambert with the unit normal (-gx, -gy, 1) / |.|, one float32 image at a time (city-scale DEMs)
    shade = (light[2] - light[0] * gx - light[1] * gy) / np.sqrt(gx * gx + gy * gy + 1.0)
    del gx, gy
    shade = np.float32(0.35) + np.float32(0.65) * np.clip(shade, 0.0, 1.0)
    t = np.nan_to_num(n, nan=0.0)
    rgb = np.empty((*heights.shape, 3), np.uint8)
    for ch in range(3):  # height_ramp, one channel at a time
        low, high = np.float32(_RAMP_LOW[ch]), np.float32(_RAMP_HIGH[ch])
        rgb[..., ch] = np.clip(((1 - t) * low + t * high) * shade, 0, 255).astype(np.uint8)
        rgb[..., ch][~valid] = 255
    return rgb


def export_dem(folder: str | Path, heights: np.ndarray, mpp: float, plane: GroundPlane,
               origin_px: tuple[int, int], name: str = "dem") -> dict[str, Path]:
    """Write ``<name>_color.png``, ``<name>_gray.png`` (encoder image) and ``<name>.npz`` (heights,
    mpp, plane, origin) into ``folder``; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if heights.ndim != 2:
        raise DemError(f"DEM heights must be [H,W], got {heights.shape}")
    paths = {"color": folder / f"{name}_color.png", "gray": folder / f"{name}_gray.png",
             "array": folder / f"{name}.npz"}
    cv2.imwrite(str(paths["color"]), cv2.cvtColor(hillshade_rgb(heights, mpp=mpp), cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(paths["gray"]), np.round(encoder_image(heights) * 255).astype(np.uint8))
    tmp = paths["array"].with_suffix(".tmp.npz")
    np.savez_compressed(tmp, heights=heights.astype(np.float32), mpp=mpp, origin_px=np.array(origin_px),
                        plane=json.dumps(plane.to_dict()))
    tmp.replace(paths["array"])
    return paths
