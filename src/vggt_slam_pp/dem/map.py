"""The DEM of the whole map: one layer per submap, re-rasterised when the back-end moves it, and the
fused global DEM for display and export (SPEC 3.6).

Each submap's points stay in the submap frame; the layer is rasterised with the submap's current
world pose. :meth:`DemMap.update_pose` re-rasterises a layer only when the pose moved by more than
``min_shift_px`` pixels at the layer's extent (rotation, translation and scale all count).
The fused DEM takes, per pixel, the maximum over layers of their heights (a conservative surface:
the top of what any submap saw).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from vggt_slam_pp.dem.raster import DemConfig, DemGrid, DemLayer, rasterize
from vggt_slam_pp.errors import DemError
from vggt_slam_pp.geometry.lie import transform_points

log = logging.getLogger(__name__)


@dataclass
class _Entry:
    points: np.ndarray  # [N,3] submap frame
    pose: np.ndarray  # T_world_submap used for the current layer
    layer: DemLayer


@dataclass
class DemMap:
    grid: DemGrid
    config: DemConfig = field(default_factory=DemConfig)
    min_shift_px: float = 0.5
    entries: dict[int, _Entry] = field(default_factory=dict)

    def add(self, submap_id: int, points_submap: np.ndarray, T_world_submap: np.ndarray) -> DemLayer:
        layer = rasterize(transform_points(T_world_submap, points_submap), self.grid, submap_id,
                          self.config.reducer, self.config.tau)
        self.entries[submap_id] = _Entry(np.asarray(points_submap, np.float64), np.array(T_world_submap), layer)
        return layer

    def layer(self, submap_id: int) -> DemLayer:
        if submap_id not in self.entries:
            raise DemError(f"no DEM layer for submap {submap_id}")
        return self.entries[submap_id].layer

    def update_pose(self, submap_id: int, T_world_submap: np.ndarray) -> bool:
        """Re-rasterise the layer if the new pose moves its points by >= ``min_shift_px``; returns
        whether it did."""
        e = self.entries[submap_id]
        pts = e.points
        if len(pts) > 2000:
            pts = pts[np.linspace(0, len(pts) - 1, 2000).astype(int)]
        shift = np.linalg.norm(transform_points(T_world_submap, pts) - transform_points(e.pose, pts), axis=1).max()
        if shift < self.min_shift_px * self.grid.mpp:
            return False
        self.add(submap_id, e.points, T_world_submap)
        return True

    def fused(self) -> tuple[np.ndarray, tuple[int, int]]:
        """Global heights [H,W] (max over layers, NaN empty) and its origin pixel (iu, iv)."""
        if not self.entries:
            raise DemError("the DEM map is empty")
        return fuse_layers((e.layer.origin_px, e.layer.heights) for e in self.entries.values())


def fuse_layers(layers) -> tuple[np.ndarray, tuple[int, int]]:
    """Max over layers given as (origin_px (iu, iv), heights [H,W]) -> (heights [H,W] float32, NaN empty;
    origin pixel). Layers may be any float dtype (e.g. float16 when stored compactly)."""
    layers = list(layers)
    if not layers:
        raise DemError("no DEM layers to fuse")
    u0 = min(o[0] for o, _ in layers)
    v0 = min(o[1] for o, _ in layers)
    u1 = max(o[0] + h.shape[1] for o, h in layers)
    v1 = max(o[1] + h.shape[0] for o, h in layers)
    out = np.full((v1 - v0, u1 - u0), -np.inf, np.float32)
    for (u, v), h in layers:
        view = out[v - v0:v - v0 + h.shape[0], u - u0:u - u0 + h.shape[1]]
        np.fmax(view, h.astype(np.float32, copy=False), out=view)
    out[~np.isfinite(out)] = np.nan
    return out, (u0, v0)
