"""Structure-aware tile and chip descriptors (SPEC 3.7).

``v_k = sum_j w_j m_j f(p_j) / sum_j w_j m_j`` over feature cells j, with ``w_j`` a Gaussian of the
distance from cell j's centre to tile k's centre (sigma = 2 tiles) and ``m_j`` the normalised local
gradient magnitude of the DEM (empty cells 0, flat cells ``m_floor``), L2-normalised.

* gallery tiles: the window is the 9x9-tile neighbourhood centred on the tile;
* query chips: the same formula with the window spanning the whole submap layer.

A tile is 2x2 feature cells when ``tile_px = 2 * patch_px`` (28 px and 14 px by default). The
Gaussian is separable, so the sums are two 1-D passes over strided slices: cost O(cells x window).
"""

from __future__ import annotations

import numpy as np

from vggt_slam_pp.dem.images import gradient_magnitude, normalized_heights
from vggt_slam_pp.errors import RetrievalError


def cell_weights(heights: np.ndarray, patch_px: int, m_floor: float = 1e-3) -> np.ndarray:
    """m_j per feature cell [rows, cols]: mean gradient magnitude of the normalised heights over the
    cell / its 99th percentile over valid cells, clipped to [m_floor, 1]; 0 for empty cells."""
    n = normalized_heights(heights)
    g = gradient_magnitude(n)
    valid = np.isfinite(n)
    g = np.where(valid, g, 0.0)
    H, W = heights.shape
    ph, pw = (-H) % patch_px, (-W) % patch_px
    g = np.pad(g, ((0, ph), (0, pw)))
    v = np.pad(valid, ((0, ph), (0, pw)))
    rows, cols = g.shape[0] // patch_px, g.shape[1] // patch_px
    gsum = g.reshape(rows, patch_px, cols, patch_px).mean(axis=(1, 3))
    frac = v.reshape(rows, patch_px, cols, patch_px).mean(axis=(1, 3))
    occupied = frac > 0.5
    if not occupied.any():
        return np.zeros((rows, cols), np.float32)
    p99 = float(np.percentile(gsum[occupied], 99))
    m = np.clip(gsum / p99, m_floor, 1.0) if p99 > 1e-12 else np.full_like(gsum, m_floor)
    return np.where(occupied, m, 0.0).astype(np.float32)


def _gauss_pass(a: np.ndarray, axis: int, cells_per_tile: int, n_tiles: int, radius_cells: int | None,
                sigma_cells: float) -> np.ndarray:
    """out[t] = sum_d g(d) a[c*t + d] along ``axis`` over offsets d (tile centre at c*t + c/2)."""
    c = cells_per_tile
    n = a.shape[axis]
    lo, hi = (-radius_cells + c // 2, radius_cells + c // 2) if radius_cells is not None else (-n, n)
    shape = list(a.shape)
    shape[axis] = n_tiles
    out = np.zeros(shape, dtype=np.float32)
    centre_off = c / 2.0
    for d in range(lo, hi):
        w = np.exp(-((d + 0.5 - centre_off) ** 2) / (2 * sigma_cells**2))
        t0 = max(0, -(d // c))  # tiles t whose cell c*t + d exists: 0 <= c*t + d < n
        t1 = min(n_tiles, (n - 1 - d) // c + 1)
        if t1 <= t0:
            continue
        src = np.take(a, np.arange(t0, t1) * c + d, axis=axis)
        idx = [slice(None)] * a.ndim
        idx[axis] = slice(t0, t1)
        out[tuple(idx)] += w * src
    return out


def aggregate(features: np.ndarray, weights: np.ndarray, cells_per_tile: int = 2, window_tiles: int | None = 9,
              sigma_tiles: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors of every tile of a layer.

    Args:
        features: [rows, cols, D] dense cell features.
        weights: [rows, cols] m_j.
        window_tiles: 9 for gallery tiles (9x9-tile neighbourhood), None for chips (whole layer).

    Returns:
        (descriptors [Tr, Tc, D] L2-normalised, support [Tr, Tc] = sum_j w_j m_j; 0 where undefined).
    """
    rows, cols, _ = features.shape
    if weights.shape != (rows, cols):
        raise RetrievalError(f"weights {weights.shape} do not match features {features.shape[:2]}")
    c = cells_per_tile
    tr, tc = rows // c, cols // c
    radius = None if window_tiles is None else (window_tiles * c) // 2
    sigma = sigma_tiles * c
    A = features[: tr * c, : tc * c] * weights[: tr * c, : tc * c, None]
    Wm = weights[: tr * c, : tc * c, None]
    num = _gauss_pass(_gauss_pass(A, 0, c, tr, radius, sigma), 1, c, tc, radius, sigma)
    den = _gauss_pass(_gauss_pass(Wm, 0, c, tr, radius, sigma), 1, c, tc, radius, sigma)[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        desc = num / den[..., None]
    norm = np.linalg.norm(desc, axis=2, keepdims=True)
    ok = (den > 1e-9) & (norm[..., 0] > 1e-12)
    desc = np.where(ok[..., None], desc / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)
    return desc, np.where(ok, den, 0.0).astype(np.float32)
