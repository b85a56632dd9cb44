"""Sim(3) odometry between consecutive submaps through their shared overlap frame (SPEC 3.5).

The overlap frame is the previous submap's last keyframe and the current submap's first. Its
observations carry the same ``keys`` in both predictions, which gives 3-D/3-D correspondences.

* ``points`` (dense backbones): robust Sim(3) (RANSAC over Umeyama + refit) on the corresponding
  points, ``T_prev_curr`` maps current-submap points into the previous submap.
* ``pose_scale`` (sparse backbones, as measured on COLMAP submaps): rotation and translation from the
  overlap frame's own pose in both submaps, scale from the median ratio of the corresponding points'
  distances to that camera (robust to a few bad points), so
  ``T_prev_curr = T_prev_cam · S(s) · T_cam_curr``.

Chaining: ``T_world_curr = T_world_prev · T_prev_curr`` with the first submap's frame as the world.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.frontend.types import OdometryEdge, SubmapPrediction
from vggt_slam_pp.geometry import make_sim3, sim3_inverse
from vggt_slam_pp.geometry.alignment import estimate_sim3_robust
from vggt_slam_pp.geometry.lie import se3_inverse, transform_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryConfig:
    method: str = "auto"  # "auto" (points for dense backbones, pose_scale for sparse), "points", "pose_scale"
    relative_threshold: float = 0.02  # RANSAC inlier threshold relative to the points' spread
    max_correspondences: int = 20000  # random subset for speed (seeded)
    min_correspondences: int = 20
    seed: int = 0


def overlap_correspondences(prev: SubmapPrediction, curr: SubmapPrediction) -> tuple[np.ndarray, np.ndarray]:
    """Points of the overlap frame in (prev submap, curr submap) coordinates, paired by key: [M,3] x 2."""
    kp, kc = prev.keys[-1], curr.keys[0]
    _, ip, ic = np.intersect1d(kp, kc, assume_unique=False, return_indices=True)
    return prev.points[-1][ip], curr.points[0][ic]


def estimate_edge(prev_id: int, prev: SubmapPrediction, curr_id: int, curr: SubmapPrediction,
                  config: OdometryConfig | None = None) -> OdometryEdge:
    """``T_prev_curr`` with its residual and inlier ratio; degrades (logged) instead of raising."""
    c = config or OdometryConfig()
    if prev.frame_indices[-1] != curr.frame_indices[0]:
        raise GeometryError(f"submaps {prev_id} and {curr_id} do not share an overlap frame")
    method = c.method if c.method != "auto" else ("points" if curr.dense else "pose_scale")
    p_prev, p_curr = overlap_correspondences(prev, curr)
    n = len(p_prev)
    if n > c.max_correspondences:
        pick = np.random.default_rng(c.seed).choice(n, c.max_correspondences, replace=False)
        p_prev, p_curr = p_prev[pick], p_curr[pick]
    if len(p_prev) < c.min_correspondences:
        return _degraded(prev_id, prev, curr_id, curr, n, f"only {n} correspondences in the overlap frame")
    try:
        if method == "points":
            fit = estimate_sim3_robust(p_curr, p_prev, relative_threshold=c.relative_threshold, seed=c.seed)
            return OdometryEdge(prev_id, curr_id, fit.T_dst_src, fit.rmse, fit.inlier_ratio, n, "points")
        if method == "pose_scale":
            return _pose_scale(prev_id, prev, curr_id, curr, p_prev, p_curr, n)
    except GeometryError as exc:
        return _degraded(prev_id, prev, curr_id, curr, n, str(exc))
    raise GeometryError(f"unknown odometry method {method!r}")


def _pose_scale(prev_id, prev, curr_id, curr, p_prev, p_curr, n) -> OdometryEdge:
    T_cam_prev = prev.T_cam_submap[-1]  # overlap camera in the previous submap
    T_cam_curr = curr.T_cam_submap[0]
    d_prev = np.linalg.norm(transform_points(T_cam_prev, p_prev), axis=1)
    d_curr = np.linalg.norm(transform_points(T_cam_curr, p_curr), axis=1)
    ok = (d_prev > 1e-9) & (d_curr > 1e-9)
    if ok.sum() < 3:
        raise GeometryError("no points with positive depth in the overlap frame")
    ratios = d_prev[ok] / d_curr[ok]
    s = float(np.median(ratios))
    T = sim3_inverse(T_cam_prev) @ make_sim3(s, np.eye(3), np.zeros(3)) @ T_cam_curr
    r = np.linalg.norm(transform_points(T, p_curr) - p_prev, axis=1)
    inl = np.abs(np.log(ratios / s)) < 0.05
    resid = float(np.sqrt(np.mean(r[ok][inl] ** 2))) if inl.any() else float("nan")
    return OdometryEdge(prev_id, curr_id, T, resid, float(inl.mean()), n, "pose_scale")


def _degraded(prev_id, prev, curr_id, curr, n, why: str) -> OdometryEdge:
    """Without usable correspondences: assume the overlap camera coincides in both submaps, scale 1."""
    log.warning("odometry %d -> %d degraded (%s): using the overlap frame's poses with scale 1",
                prev_id, curr_id, why)
    T = se3_inverse(prev.T_cam_submap[-1]) @ curr.T_cam_submap[0]
    return OdometryEdge(prev_id, curr_id, T, float("nan"), 0.0, n, "identity", degraded=True)


def chain(edges: list[OdometryEdge]) -> list[np.ndarray]:
    """World poses ``T_world_submap`` of submaps 0..len(edges) (submap 0 = world)."""
    poses = [np.eye(4)]
    for e in edges:
        poses.append(poses[-1] @ e.T_prev_curr)
    return poses
