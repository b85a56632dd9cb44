"""Rasterising submaps into the global DEM grid (SPEC 3.6).

One global grid for every layer: metres-per-pixel ``mpp = tile_size / tile_px``; global pixel
``(iu, iv) = floor(u / mpp), floor(v / mpp)`` of the canonical coordinates; tiles are ``tile_px``
squares keyed by ``(submap, Iu, Iv)`` with ``Iu = floor(iu / tile_px)``. A :class:`DemLayer` covers the
tile-aligned bounding box of its submap's points; rows are ``v``, columns ``u``.

Reducers per pixel: ``mean``, ``max`` and ``softmax`` (default): ``sum_i w_i h_i / sum_i w_i`` with
``w_i = exp((h_i - max_p) / tau)`` — shifted by the pixel's maximum (``np.maximum.at``), so no
exponent is positive and the highest point has weight 1: stable for any height spread. Only
``bincount``-style passes, no sorting. Empty pixels are NaN.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.dem.plane import GroundPlane
from vggt_slam_pp.errors import DemError

log = logging.getLogger(__name__)

REDUCERS = ("softmax", "mean", "max")


@dataclass(frozen=True)
class DemConfig:
    tile_size: float | str = 2.0  # world units, or "auto" (a fraction of the median camera depth: see
    # BackendConfig.grid_submaps)
    auto_tile_fraction: float = 0.25
    tile_px: int = 28
    reducer: str = "softmax"
    tau: float = 0.02
    alpha_edge: float = 0.95
    percentiles: tuple[float, float] = (0.5, 99.5)
    fill_radius_px: int = 3  # encoder input only: empty pixels with data this close are filled


@dataclass(frozen=True)
class DemGrid:
    """The global grid: ground plane, metres per pixel and tile size in pixels."""

    plane: GroundPlane
    mpp: float
    tile_px: int

    @classmethod
    def create(cls, plane: GroundPlane, config: DemConfig, median_depth: float | None = None) -> DemGrid:
        if config.tile_size == "auto":
            if median_depth is None or not np.isfinite(median_depth) or median_depth <= 0:
                raise DemError("tile_size 'auto' needs the submaps' median camera depth")
            tile = config.auto_tile_fraction * median_depth
        else:
            tile = float(config.tile_size)
        if tile <= 0 or config.tile_px < 1:
            raise DemError(f"bad grid: tile_size {tile}, tile_px {config.tile_px}")
        return cls(plane, tile / config.tile_px, int(config.tile_px))

    @property
    def tile_size(self) -> float:
        return self.mpp * self.tile_px


@dataclass(frozen=True, eq=False)
class DemLayer:
    """One submap's heights in the global grid.

    Attributes:
        submap_id: the submap.
        heights: [H,W] float32 heights above the plane (NaN = empty); row = v, column = u.
        counts: [H,W] int32 points per pixel.
        origin_px: global pixel (iu, iv) of ``heights[0, 0]`` (multiples of ``tile_px``).
        mpp, tile_px: the grid's.
    """

    submap_id: int
    heights: np.ndarray
    counts: np.ndarray
    origin_px: tuple[int, int]
    mpp: float
    tile_px: int

    @property
    def tiles_shape(self) -> tuple[int, int]:
        """(rows, cols) of tiles."""
        return self.heights.shape[0] // self.tile_px, self.heights.shape[1] // self.tile_px

    @property
    def origin_tile(self) -> tuple[int, int]:
        return self.origin_px[0] // self.tile_px, self.origin_px[1] // self.tile_px

    def tile_keys(self) -> np.ndarray:
        """[T,2] global tile indices (Iu, Iv) of every tile of the layer, row-major over (v, u)."""
        rows, cols = self.tiles_shape
        iv, iu = np.mgrid[0:rows, 0:cols]
        return np.stack([iu.reshape(-1) + self.origin_tile[0], iv.reshape(-1) + self.origin_tile[1]], axis=1)

    def tile_occupancy(self) -> np.ndarray:
        """[rows, cols] fraction of non-empty pixels per tile."""
        rows, cols = self.tiles_shape
        full = np.isfinite(self.heights).reshape(rows, self.tile_px, cols, self.tile_px)
        return full.mean(axis=(1, 3))


def pixel_indices(canonical: np.ndarray, mpp: float) -> tuple[np.ndarray, np.ndarray]:
    """Global pixel indices (iu, iv) [N] int64 of canonical points [N,3]."""
    return (np.floor(canonical[:, 0] / mpp).astype(np.int64), np.floor(canonical[:, 1] / mpp).astype(np.int64))


def rasterize(points_world: np.ndarray, grid: DemGrid, submap_id: int = 0, reducer: str = "softmax",
              tau: float = 0.02) -> DemLayer:
    """Rasterise world points [N,3] into a :class:`DemLayer` of ``grid``."""
    if reducer not in REDUCERS:
        raise DemError(f"unknown reducer {reducer!r}; choose one of {', '.join(REDUCERS)}")
    P = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(P.sum()):  # one reduction; NaN/inf propagate into the sum
        P = P[np.isfinite(P).all(axis=1)]
    if len(P) == 0:
        raise DemError(f"submap {submap_id}: no points to rasterise (empty layer)")
    canon = grid.plane.to_canonical(P)
    iu, iv = pixel_indices(canon, grid.mpp)
    t = grid.tile_px
    u0 = (iu.min() // t) * t
    v0 = (iv.min() // t) * t
    W = int(((iu.max() - u0) // t + 1) * t)
    H = int(((iv.max() - v0) // t + 1) * t)
    iv -= v0
    iv *= W
    iu -= u0
    iv += iu
    heights, counts = reduce_heights(iv, canon[:, 2], H * W, reducer, tau)
    return DemLayer(submap_id, heights.reshape(H, W).astype(np.float32), counts.reshape(H, W).astype(np.int32),
                    (int(u0), int(v0)), grid.mpp, t)


def reduce_heights(flat: np.ndarray, h: np.ndarray, size: int, reducer: str, tau: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel reduction of heights ``h`` [N] at flat pixel indices [N] -> (values [size], counts [size])."""
    counts = np.bincount(flat, minlength=size)
    empty = counts == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        if reducer == "mean":
            out = np.bincount(flat, weights=h, minlength=size) / counts
        elif reducer == "max":
            out = np.full(size, -np.inf)
            np.maximum.at(out, flat, h)
        else:
            if tau <= 0:
                raise DemError(f"softmax temperature must be positive, got {tau}")
            mx = np.full(size, -np.inf)
            np.maximum.at(mx, flat, h)  # exact per-pixel shift: every exponent <= 0, the max has weight 1
            w = h - mx[flat]
            w *= 1.0 / tau
            np.exp(w, out=w)
            out = np.bincount(flat, weights=w * h, minlength=size) / np.bincount(flat, weights=w, minlength=size)
    out[empty] = np.nan
    return out, counts


def fuse_layers(layers) -> tuple[np.ndarray, tuple[int, int]]:
    """Max over layers given as (origin_px (iu, iv), heights [H,W]) -> (heights [H,W] float32, NaN empty;
    origin pixel). Layers may be any float dtype and any iterable (a generator: one layer in memory at a
    time); the canvas grows by half its size at least when a layer falls outside it."""
    out: np.ndarray | None = None
    u0 = v0 = 0
    box = (0, 0, 0, 0)  # union of the layers' boxes (u0, v0, u1, v1)
    for (u, v), h in layers:
        u, v = int(u), int(v)
        rows, cols = h.shape
        box = (u, v, u + cols, v + rows) if out is None else \
            (min(box[0], u), min(box[1], v), max(box[2], u + cols), max(box[3], v + rows))
        if out is None:
            out, u0, v0 = np.full((rows, cols), -np.inf, np.float32), int(u), int(v)
        elif u < u0 or v < v0 or u + cols > u0 + out.shape[1] or v + rows > v0 + out.shape[0]:
            grow_u, grow_v = out.shape[1] // 2, out.shape[0] // 2
            nu0 = min(u0 - grow_u, u) if u < u0 else u0
            nv0 = min(v0 - grow_v, v) if v < v0 else v0
            nu1 = max(u0 + out.shape[1] + grow_u, u + cols) if u + cols > u0 + out.shape[1] else u0 + out.shape[1]
            nv1 = max(v0 + out.shape[0] + grow_v, v + rows) if v + rows > v0 + out.shape[0] else v0 + out.shape[0]
            grown = np.full((nv1 - nv0, nu1 - nu0), -np.inf, np.float32)
            grown[v0 - nv0:v0 - nv0 + out.shape[0], u0 - nu0:u0 - nu0 + out.shape[1]] = out
            out, u0, v0 = grown, nu0, nv0
        view = out[v - v0:v - v0 + rows, u - u0:u - u0 + cols]
        np.fmax(view, h.astype(np.float32, copy=False), out=view)
    if out is None:
        raise DemError("no DEM layers to fuse")
    cu0, cv0, cu1, cv1 = box  # the canvas may have grown past the layers: crop to their union
    out = out[cv0 - v0:cv1 - v0, cu0 - u0:cu1 - u0].copy()
    out[~np.isfinite(out)] = np.nan
    return out, (cu0, cv0)
