"""Sim(3) odometry between consecutive submaps through their shared overlap frames (SPEC 3.5).

The overlap frames are the previous submap's last keyframes and the current submap's first ones (one
for dense backbones, as in the paper; several for sparse ones, see ``FrontendConfig.overlap``). Their
observations carry the same ``keys`` in both predictions, which gives 3-D/3-D correspondences. Only
frames registered (``valid``) in both submaps are used.

* ``points`` (dense backbones): robust Sim(3) (RANSAC over Umeyama + refit) on the corresponding
  points of every shared frame, ``T_prev_curr`` maps current-submap points into the previous submap.
* ``joint`` (COLMAP submaps, global mapper): the backbone joined the two reconstructions in one bundle
  adjustment and placed each by all its cameras (``info["joint_link"]``,
  :mod:`vggt_slam_pp.frontend.backbones.colmap_joint`); used when present.
* ``pose_scale`` (sparse backbones, as measured on COLMAP submaps): rotation and translation from the
  shared frames' own poses in both submaps (rotations averaged, camera centres aligned), scale from the
  median ratio of the corresponding points' distances to their camera, pooled over the shared frames
  (robust to a few bad points). With one shared frame this is ``T_prev_cam · S(s) · T_cam_curr``.

When no shared frame gives enough correspondences the edge *degrades*: :func:`extrapolated_edge`
(the overlap camera assumed to coincide, scale from the two submaps' median depths) with
``degraded=True`` and its ``cause``; the back-end gives such edges a large uncertainty. The front-end
first tries to avoid this (:mod:`vggt_slam_pp.frontend.frontend`: retries and bridging).

Chaining: ``T_world_curr = T_world_prev · T_prev_curr`` with the first submap's frame as the world.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.frontend.types import OdometryEdge, SubmapPrediction
from vggt_slam_pp.geometry import make_sim3, sim3_inverse
from vggt_slam_pp.geometry.alignment import estimate_sim3_robust
from vggt_slam_pp.geometry.lie import rotation_angle, se3_inverse, transform_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryConfig:
    method: str = "auto"  # "auto" (points for dense backbones, pose_scale for sparse), "points", "pose_scale"
    relative_threshold: float = 0.02  # RANSAC inlier threshold relative to the points' spread
    max_correspondences: int = 20000  # random subset for speed (seeded)
    min_correspondences: int = 20
    max_disagreement_deg: float = 1.0  # shared keyframes' relative rotations must agree to this
    max_joint_scale_change: float = 0.05  # a joint link is refused (the shared keyframes' link kept) when its scale
    max_joint_turn_deg: float = 2.0  # or rotation differs from theirs by more (measured: within 1.1 % and 0.3 deg when
    # sound; 11 % and 10 deg once on a rendered drive)
    seed: int = 0


@dataclass(frozen=True)
class SharedFrame:
    """One keyframe reconstructed in both submaps: its positions and its key-matched points."""

    prev_pos: int  # index in the previous submap
    curr_pos: int  # index in the current submap
    p_prev: np.ndarray  # [M,3] points in the previous submap's frame
    p_curr: np.ndarray  # [M,3] the same observations in the current submap's frame


def shared_frames(prev: SubmapPrediction, curr: SubmapPrediction) -> list[SharedFrame]:
    """Keyframes of ``curr`` that ``prev`` also holds and that are valid in both, with their
    key-matched point pairs (in submap order)."""
    where = {int(f): i for i, f in enumerate(prev.frame_indices)}
    out = []
    for ic, f in enumerate(curr.frame_indices):
        ip = where.get(int(f))
        if ip is None or not (prev.valid[ip] and curr.valid[ic]):
            continue
        _, a, b = np.intersect1d(prev.keys[ip], curr.keys[ic], assume_unique=False, return_indices=True)
        out.append(SharedFrame(ip, ic, prev.points[ip][a], curr.points[ic][b]))
    return out


def estimate_edge(prev_id: int, prev: SubmapPrediction, curr_id: int, curr: SubmapPrediction,
                  config: OdometryConfig | None = None) -> OdometryEdge:
    """``T_prev_curr`` with its residual and inlier ratio; degrades (logged, ``degraded=True`` with a
    ``cause``) instead of raising when the shared frames do not link the submaps."""
    c = config or OdometryConfig()
    if not np.isin(curr.frame_indices, prev.frame_indices).any():
        raise GeometryError(f"submaps {prev_id} and {curr_id} do not share an overlap frame")
    method = c.method if c.method != "auto" else ("points" if curr.dense else "pose_scale")
    every = shared_frames(prev, curr)
    shared = [s for s in every if len(s.p_prev)]
    n = int(sum(len(s.p_prev) for s in shared))
    disagreement = link_problem(prev, curr, c, every)
    if n < c.min_correspondences:
        return extrapolated_edge(prev_id, prev, curr_id, curr, disagreement, n)
    try:
        edge = _fit(prev_id, prev, curr_id, curr, shared, n, method, c)
    except GeometryError as exc:
        return extrapolated_edge(prev_id, prev, curr_id, curr, str(exc), n)
    if disagreement:
        log.warning("odometry %d -> %d degraded: %s", prev_id, curr_id, disagreement)
        return replace(edge, degraded=True, cause=disagreement)
    return edge


def _fit(prev_id, prev, curr_id, curr, shared: list[SharedFrame], n: int, method: str,
         c: OdometryConfig) -> OdometryEdge:
    if method == "points":
        p_prev = np.concatenate([s.p_prev for s in shared])
        p_curr = np.concatenate([s.p_curr for s in shared])
        if n > c.max_correspondences:
            pick = np.random.default_rng(c.seed).choice(n, c.max_correspondences, replace=False)
            p_prev, p_curr = p_prev[pick], p_curr[pick]
        fit = estimate_sim3_robust(p_curr, p_prev, relative_threshold=c.relative_threshold, seed=c.seed)
        return OdometryEdge(prev_id, curr_id, fit.T_dst_src, fit.rmse, fit.inlier_ratio, n, "points",
                            shared_frames=len(shared))
    anchor = set(curr.info.get("anchor_frames", []))
    if method == "pose_scale" and len(shared) >= 2 and \
            all(int(prev.frame_indices[f.prev_pos]) in anchor for f in shared):
        return _anchored(prev_id, prev, curr_id, curr, shared, n)
    if method == "pose_scale":
        edge = _pose_scale(prev_id, prev, curr_id, curr, shared, n)
        link = curr.info.get("joint_link")
        if link and link["prev_frames"] == sorted(int(f) for f in prev.frame_indices):
            joint = _joint(prev_id, prev, curr_id, curr, shared, n, np.asarray(link["T_prev_curr"], np.float64),
                           float(link.get("residual", np.nan)), float(link.get("relative_residual", np.nan)))
            D = sim3_inverse(edge.T_prev_curr) @ joint.T_prev_curr
            scale = abs(float(np.log(np.cbrt(np.linalg.det(D[:3, :3])))))
            R = D[:3, :3] / np.cbrt(np.linalg.det(D[:3, :3]))
            turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
            if scale <= c.max_joint_scale_change and turn <= c.max_joint_turn_deg:
                return joint
            log.warning("odometry %d -> %d: the joint link differs from the shared keyframes' by %.1f %% in scale and "
                        "%.1f deg; linked by the shared keyframes", prev_id, curr_id, 100 * scale, turn)
        return edge
    raise GeometryError(f"unknown odometry method {method!r}")


def link_problem(prev: SubmapPrediction, curr: SubmapPrediction, config: OdometryConfig | None = None,
                 shared: list[SharedFrame] | None = None) -> str:
    """Why the shared keyframes cannot link the two submaps soundly ("" when they can): too few
    correspondences, or reconstructions that disagree on the shared keyframes' relative rotations.
    ``shared``: :func:`shared_frames` of the pair, when already computed."""
    c = config or OdometryConfig()
    shared = shared_frames(prev, curr) if shared is None else shared
    n = sum(len(s.p_prev) for s in shared)
    if n < c.min_correspondences:
        return _link_cause(prev, curr, n)
    worst = overlap_disagreement(prev, curr, shared)
    if worst > c.max_disagreement_deg:
        return f"the submaps disagree by {worst:.1f} deg on the overlap keyframes' relative rotation"
    return ""


def overlap_disagreement(prev: SubmapPrediction, curr: SubmapPrediction,
                         shared: list[SharedFrame] | None = None) -> float:
    """Largest disagreement (degrees) between the two submaps on the relative rotation of a pair of
    shared keyframes; NaN with fewer than two shared keyframes. Two sound reconstructions agree to a
    fraction of a degree (0.01-0.06 deg measured); a broken one (a wrong initial pair, a turn folded
    onto itself) disagrees by degrees while every frame still counts as registered."""
    shared = shared_frames(prev, curr) if shared is None else shared
    worst = float("nan")
    for a in range(len(shared)):
        for b in range(a + 1, len(shared)):
            Rp = prev.T_cam_submap[shared[a].prev_pos][:3, :3] @ prev.T_cam_submap[shared[b].prev_pos][:3, :3].T
            Rc = curr.T_cam_submap[shared[a].curr_pos][:3, :3] @ curr.T_cam_submap[shared[b].curr_pos][:3, :3].T
            Rp, Rc = Rp / np.cbrt(np.linalg.det(Rp)), Rc / np.cbrt(np.linalg.det(Rc))
            # from the rotation's log, not arccos of its trace: that is 1e-6 deg off for identical rotations
            worst = float(np.nanmax([worst, np.degrees(rotation_angle(Rp @ Rc.T))]))
    return worst


def _link_cause(prev: SubmapPrediction, curr: SubmapPrediction, n: int) -> str:
    common = [int(f) for f in curr.frame_indices if f in set(prev.frame_indices.tolist())]
    pos_p = {int(f): i for i, f in enumerate(prev.frame_indices)}
    pos_c = {int(f): i for i, f in enumerate(curr.frame_indices)}
    unreg = [f for f in common if not (prev.valid[pos_p[f]] and curr.valid[pos_c[f]])]
    if unreg and len(unreg) == len(common):
        return f"overlap frame(s) {unreg} not registered in both submaps"
    return f"only {n} correspondences in the overlap frame(s) {common}"


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations [K,3,3]."""
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _pose_scale(prev_id, prev, curr_id, curr, shared: list[SharedFrame], n: int) -> OdometryEdge:
    ratios, Rs, c_prev, c_curr, p_prev, p_curr = [], [], [], [], [], []
    for f in shared:
        T_cam_prev, T_cam_curr = prev.T_cam_submap[f.prev_pos], curr.T_cam_submap[f.curr_pos]
        d_prev = np.linalg.norm(transform_points(T_cam_prev, f.p_prev), axis=1)
        d_curr = np.linalg.norm(transform_points(T_cam_curr, f.p_curr), axis=1)
        ok = (d_prev > 1e-9) & (d_curr > 1e-9)
        if ok.sum() < 3:
            continue
        ratios.append(d_prev[ok] / d_curr[ok])
        p_prev.append(f.p_prev[ok])
        p_curr.append(f.p_curr[ok])
        Rs.append(T_cam_prev[:3, :3].T @ T_cam_curr[:3, :3])  # R_prev_curr seen through this frame
        c_prev.append(sim3_inverse(T_cam_prev)[:3, 3])
        c_curr.append(sim3_inverse(T_cam_curr)[:3, 3])
    if not Rs:
        raise GeometryError("no points with positive depth in the overlap frames")
    ratios = np.concatenate(ratios)
    s = float(np.median(ratios))
    R = _mean_rotation(np.array(Rs))
    t = np.median(np.array(c_prev) - s * np.array(c_curr) @ R.T, axis=0)  # c_prev = s R c_curr + t
    T = make_sim3(s, R, t)
    r = np.linalg.norm(transform_points(T, np.concatenate(p_curr)) - np.concatenate(p_prev), axis=1)
    inl = np.abs(np.log(ratios / s)) < 0.05
    resid = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    return OdometryEdge(prev_id, curr_id, T, resid, float(inl.mean()), n, "pose_scale", shared_frames=len(Rs))


def _joint(prev_id, prev, curr_id, curr, shared: list[SharedFrame], n: int, T: np.ndarray,
           residual: float, relative: float) -> OdometryEdge:
    """The backbone linked the two submaps by one bundle adjustment of both (``info["joint_link"]``,
    frontend/backbones/colmap_joint.py). Residual: the link's own, how far the two submaps' cameras are from
    the joint model once placed (previous submap units); without it, the shared points' RMS residual under
    ``T``; ``relative``: that residual over the cameras' spread. Inlier ratio: the shared points' depth ratios
    within 5 % of its scale."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    p_prev = np.concatenate([f.p_prev for f in shared])
    p_curr = np.concatenate([f.p_curr for f in shared])
    ratios = np.concatenate([np.linalg.norm(transform_points(prev.T_cam_submap[f.prev_pos], f.p_prev), axis=1) /
                             np.maximum(np.linalg.norm(transform_points(curr.T_cam_submap[f.curr_pos], f.p_curr),
                                                       axis=1), 1e-12) for f in shared])
    inl = np.abs(np.log(np.maximum(ratios, 1e-12) / s)) < 0.05
    if not np.isfinite(residual):
        r = np.linalg.norm(transform_points(T, p_curr) - p_prev, axis=1)
        residual = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    return OdometryEdge(prev_id, curr_id, T, residual, float(inl.mean()), n, "joint", shared_frames=len(shared),
                        relative_residual=relative)


def _anchored(prev_id, prev, curr_id, curr, shared: list[SharedFrame], n: int) -> OdometryEdge:
    """The current submap was reconstructed with the shared keyframes' poses held fixed from the
    previous one (``info["anchor_frames"]``): the Sim(3) that maps the shared cameras onto each other
    (Umeyama on the camera centres, rotation from the poses) is exact up to rounding."""
    c_prev = np.array([sim3_inverse(prev.T_cam_submap[f.prev_pos])[:3, 3] for f in shared])
    c_curr = np.array([sim3_inverse(curr.T_cam_submap[f.curr_pos])[:3, 3] for f in shared])
    spread_curr = np.sqrt(((c_curr - c_curr.mean(0)) ** 2).sum())
    if spread_curr <= 1e-9:
        raise GeometryError("anchored keyframes coincide")
    s = float(np.sqrt(((c_prev - c_prev.mean(0)) ** 2).sum()) / spread_curr)
    R = _mean_rotation(np.array([prev.T_cam_submap[f.prev_pos][:3, :3].T @ curr.T_cam_submap[f.curr_pos][:3, :3]
                                 for f in shared]))
    t = np.mean(c_prev - s * c_curr @ R.T, axis=0)
    T = make_sim3(s, R, t)
    resid = float(np.sqrt(np.mean(np.sum((c_prev - (s * c_curr @ R.T + t)) ** 2, axis=1))))
    return OdometryEdge(prev_id, curr_id, T, resid, 1.0, n, "anchored", shared_frames=len(shared))


def _median_depth(pred: SubmapPrediction, positions) -> float:
    d = [np.linalg.norm(pred.camera_points(i), axis=1) for i in positions if pred.valid[i] and len(pred.points[i])]
    d = np.concatenate(d) if d else np.zeros(0)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else float("nan")


def extrapolated_edge(prev_id: int, prev: SubmapPrediction, curr_id: int, curr: SubmapPrediction,
                      cause: str, n: int = 0) -> OdometryEdge:
    """The last resort, flagged ``degraded``: the first shared keyframe's camera is assumed to be where
    the previous submap put it (its pose there, or the nearest registered neighbour's), and the scale is
    the ratio of the two submaps' median point depths on the keyframes they share (both have points
    there), else around the overlap (the previous submap's last and the current one's first keyframes),
    1 when unknown."""
    where = {int(f): i for i, f in enumerate(prev.frame_indices)}
    ic = next((i for i, f in enumerate(curr.frame_indices) if int(f) in where and curr.valid[i]), None)
    if ic is None:
        ic = next(i for i, f in enumerate(curr.frame_indices) if int(f) in where)
    ip = where[int(curr.frame_indices[ic])]
    both = [(where[int(f)], i) for i, f in enumerate(curr.frame_indices) if int(f) in where
            and prev.valid[where[int(f)]] and len(prev.points[where[int(f)]]) and curr.valid[i] and len(curr.points[i])]
    d_prev = _median_depth(prev, [a for a, _ in both])
    d_curr = _median_depth(curr, [b for _, b in both])
    if not (np.isfinite(d_prev) and np.isfinite(d_curr)):
        k = max(1, min(4, prev.num_frames // 2, curr.num_frames // 2))
        d_prev = _median_depth(prev, range(prev.num_frames - k, prev.num_frames))
        d_curr = _median_depth(curr, range(k))
    s = d_prev / d_curr if np.isfinite(d_prev) and np.isfinite(d_curr) and d_curr > 0 else 1.0
    T = se3_inverse(prev.T_cam_submap[ip]) @ make_sim3(s, np.eye(3), np.zeros(3)) @ curr.T_cam_submap[ic]
    log.warning("odometry %d -> %d degraded (%s): motion extrapolated through frame %d, scale %.3g from "
                "median depths; the back-end gives it a large uncertainty", prev_id, curr_id, cause,
                int(curr.frame_indices[ic]), s)
    return OdometryEdge(prev_id, curr_id, T, float("nan"), 0.0, n, "extrapolated", degraded=True, cause=cause)


def chain(edges: list[OdometryEdge]) -> list[np.ndarray]:
    """World poses ``T_world_submap`` of submaps 0..len(edges) (submap 0 = world)."""
    poses = [np.eye(4)]
    for e in edges:
        poses.append(poses[-1] @ e.T_prev_curr)
    return poses


def with_cause(edge: OdometryEdge, note: str) -> OdometryEdge:
    """``edge`` with ``note`` appended to its cause (how it was recovered, for the report)."""
    return replace(edge, cause=f"{edge.cause}; {note}" if edge.cause else note)
