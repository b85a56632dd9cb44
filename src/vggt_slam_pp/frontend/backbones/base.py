"""The backbone interface: keyframes of one submap in, a :class:`SubmapPrediction` out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np

from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.io.frames import Frame


class Backbone(ABC):
    """Reconstructs a submap from its keyframes (frame 0 defines the submap frame).

    Implementations never raise for a frame they cannot reconstruct: they mark it ``valid=False`` and
    log why. They raise :class:`~vggt_slam_pp.errors.FrontendError` only when nothing can be done.
    """

    name: str = "backbone"
    dense: bool = True
    metric: bool = False  # predictions in metres (the back-end's DEM tile is then 2 m, else "auto")

    @abstractmethod
    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        """``frames`` (S >= 1 keyframes, in order) -> prediction for those frames."""

    def committed(self, frame_indices: Sequence[int]) -> None:  # noqa: B027 - optional hook
        """The front-end kept the prediction whose keyframes start with ``frame_indices`` as a submap
        (a backbone that builds on the previous submap, like anchored COLMAP, remembers that one)."""

    def describe(self) -> dict:
        """What the backbone estimated for the whole run, for the report (e.g. the shared camera)."""
        return {}

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release resources (models, temporary folders)."""


def pixel_grid(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel coordinates (u, v) of a regular grid, row-major: two [N] int64 arrays."""
    v, u = np.mgrid[0:height:stride, 0:width:stride]
    return u.reshape(-1).astype(np.int64), v.reshape(-1).astype(np.int64)


def dense_observations(points_cam_to_submap: np.ndarray, depth: np.ndarray, conf: np.ndarray,
                       K: np.ndarray, to_original: np.ndarray, stride: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Observations of one dense frame: unproject ``depth`` [H,W] with ``K`` on a pixel grid, move the
    camera points into the submap with ``points_cam_to_submap`` (T_submap_cam [4,4]).

    Returns (points [N,3] float32 submap frame, conf [N] float32, pixels [N,2] float32 original image,
    keys [N] int64 = v*W + u on the network grid); pixels without positive finite depth are skipped.
    """
    H, W = depth.shape
    u, v = pixel_grid(H, W, stride)
    d = depth[v, u].astype(np.float64)
    ok = np.isfinite(d) & (d > 0)
    u, v, d = u[ok], v[ok], d[ok]
    x = (u - K[0, 2]) * d / K[0, 0]
    y = (v - K[1, 2]) * d / K[1, 1]
    cam = np.stack([x, y, d], axis=1)
    T = points_cam_to_submap
    pts = cam @ T[:3, :3].T + T[:3, 3]
    uv1 = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
    pix = (uv1 @ to_original.T)[:, :2]
    return (pts.astype(np.float32), conf[v, u].astype(np.float32), pix.astype(np.float32), v * W + u)
