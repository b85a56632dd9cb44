"""Geometric re-ranking of loop candidates: DEM structure correlation over yaw and shift.

Descriptor votes (HNSW, VLAD) say which submaps *look* alike; on repetitive or drifting maps the best
vote is often a look-alike. This stage checks the layout: for each candidate, the query layer's
structure (pixels higher than the layer's ground by ``height``) is rotated by yaws within ``max_yaw_deg``
(odometry drift at a revisit: measured up to ~15 deg) and slid within ``max_shift`` of its current
place over the candidate's structure; the best normalised cross-correlation (OpenCV
``TM_CCORR_NORMED`` of occupancy images with ``cell``-sized pixels, blurred by one cell) is the
candidate's geometric score in [0, 1], with the yaw and shift that gave it.

Structure is kept per layer as occupied ``cell`` centres with counts in canonical plane coordinates
(a few hundred points per submap), so scoring a candidate needs no layer images in memory.
Ground = a low percentile of the layer's heights (the planar-canonical frame makes the ground level).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vggt_slam_pp.dem.raster import DemLayer
from vggt_slam_pp.vpr.vlad import LoopCandidate


@dataclass(frozen=True)
class GeometryConfig:
    height_tiles: float = 0.25  # structure = higher than the ground by this many tiles (0.5 m at 2 m tiles)
    ground_percentile: float = 20.0
    cell_tiles: float = 0.25  # correlation pixel (0.5 m)
    max_yaw_deg: float = 20.0
    yaw_step_deg: float = 2.0
    max_shift_tiles: float = 8.0  # 16 m
    min_cells: int = 20  # fewer structure cells on either side: score 0
    min_score: float = 0.0  # candidates below are dropped (0 keeps every covisible submap)


@dataclass(frozen=True)
class Structure:
    """A layer's structure: occupied cell centres [N,2] (canonical u, v) and their pixel counts [N]."""

    uv: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


@dataclass(frozen=True)
class GeometricMatch:
    score: float  # normalised cross-correlation in [0, 1]
    yaw_deg: float  # rotation of the query about its structure's centroid
    shift: np.ndarray  # [2] canonical (u, v) translation after the rotation


def layer_structure(layer: DemLayer, tile_size: float, config: GeometryConfig | None = None) -> Structure:
    """Structure cells of a DEM layer (empty when the layer has no data)."""
    c = config or GeometryConfig()
    h = layer.heights
    valid = np.isfinite(h)
    if not valid.any():
        return Structure(np.zeros((0, 2), np.float32), np.zeros(0, np.float32))
    ground = float(np.percentile(h[valid], c.ground_percentile))
    iv, iu = np.nonzero(valid & (h > ground + c.height_tiles * tile_size))
    uv = (np.c_[iu, iv] + np.asarray(layer.origin_px) + 0.5) * layer.mpp
    cell = c.cell_tiles * tile_size
    keys, counts = np.unique(np.floor(uv / cell).astype(np.int64), axis=0, return_counts=True)
    return Structure(((keys + 0.5) * cell).astype(np.float32), counts.astype(np.float32))


def _image(uv: np.ndarray, w: np.ndarray, lo: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    keep = np.all((ij >= 0) & (ij < np.asarray(shape)), axis=1)
    img = np.bincount(ij[keep, 0] * shape[1] + ij[keep, 1], w[keep], shape[0] * shape[1]).reshape(shape)
    img = np.minimum(img, 3.0).astype(np.float32)  # a cell with >= 3 structure pixels counts fully: walls do not outweigh posts
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def match_structure(query: Structure, match: Structure, tile_size: float,
                    config: GeometryConfig | None = None) -> GeometricMatch:
    """Best normalised correlation of ``query``'s structure (rotated, shifted) over ``match``'s."""
    return structure_peaks(query, match, tile_size, config, count=1)[0]


def structure_peaks(query: Structure, match: Structure, tile_size: float, config: GeometryConfig | None = None,
                    count: int = 3, min_separation_tiles: float = 1.0) -> list[GeometricMatch]:
    """The ``count`` best distinct alignments of ``query``'s structure over ``match``'s, best first.

    Each yaw contributes the local maxima of its correlation image; alignments closer than
    ``min_separation_tiles`` in shift (at any yaw) to a better one are dropped, so the list holds
    alternatives, not neighbours of the best. Always at least one entry (score 0 when either side has
    too little structure).
    """
    c = config or GeometryConfig()
    none = GeometricMatch(0.0, 0.0, np.zeros(2))
    if len(query) < c.min_cells or len(match) < c.min_cells:
        return [none]
    cell = c.cell_tiles * tile_size
    k = int(np.ceil(c.max_shift_tiles / c.cell_tiles))
    centre = np.average(query.uv, axis=0, weights=query.weight)
    found: list[GeometricMatch] = []
    for yaw in np.arange(-c.max_yaw_deg, c.max_yaw_deg + 1e-9, c.yaw_step_deg):
        a = np.radians(yaw)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        rs = (query.uv - centre) @ R.T + centre
        lo = rs.min(0)
        shape = tuple(int(x) for x in np.ceil((rs.max(0) - lo) / cell) + 1)
        if shape[0] * shape[1] > 1_000_000:  # a footprint this large is not one place
            return [none]
        template = _image(rs, query.weight, lo, cell, shape)
        target = _image(match.uv, match.weight, lo - k * cell, cell, (shape[0] + 2 * k, shape[1] + 2 * k))
        if not target.any():
            continue
        corr = cv2.matchTemplate(target, template, cv2.TM_CCORR_NORMED)
        if count == 1:
            peaks = [np.unravel_index(int(np.argmax(corr)), corr.shape)]
        else:  # local maxima (3x3), best first
            is_max = (corr >= cv2.dilate(corr, np.ones((3, 3), np.uint8))) & (corr > 0)
            ii, jj = np.nonzero(is_max)
            order = np.argsort(-corr[ii, jj])[: 4 * count]
            peaks = list(zip(ii[order], jj[order], strict=True))
        found += [GeometricMatch(float(corr[i, j]), float(yaw), np.array([i - k, j - k], float) * cell)
                  for i, j in peaks if corr[i, j] > 0]
    found.sort(key=lambda g: -g.score)
    out: list[GeometricMatch] = []
    for g in found:
        if all(np.linalg.norm(g.shift - o.shift) >= min_separation_tiles * tile_size for o in out):
            out.append(g)
            if len(out) == count:
                break
    return out or [none]


def rerank_candidates(query_submap: int, query: Structure, gallery: dict[int, Structure],
                      appearance: list[LoopCandidate], tile_size: float,
                      config: GeometryConfig | None = None) -> list[LoopCandidate]:
    """Every covisible submap (``gallery``: submap -> structure) scored by :func:`match_structure`;
    its VLAD score and votes (``appearance``; 0 when VLAD gave it none) are kept. Sorted by geometric
    score, then VLAD score; those below ``min_score`` are dropped."""
    c = config or GeometryConfig()
    by_match = {a.match: a for a in appearance}
    out = []
    for m, s in gallery.items():
        g = match_structure(query, s, tile_size, c)
        a = by_match.get(m)
        if g.score >= c.min_score and (g.score > 0 or a is not None):
            out.append(LoopCandidate(query_submap, m, a.score if a else 0.0, a.votes if a else 0, g.score))
    return sorted(out, key=lambda x: (-x.geometry, -x.score))
