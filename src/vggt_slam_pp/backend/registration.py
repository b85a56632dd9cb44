"""Loop registration and verification (SPEC 3.10: the paper is silent; this is our decision).

For a loop candidate (query submap i, match j), all in the current world estimate:

1. **Planar guess.** Mutual nearest neighbours between i's chip descriptors and j's tile descriptors
   give 2-D correspondences between tile centres in the DEM plane; RANSAC over 2-point rigid
   hypotheses (yaw + translation, inlier radius ``ransac_radius_tiles``) gives a planar motion. The
   identity (the odometry's own guess) is always tried as well.
2. **3-D refinement.** ICP with scale (Umeyama on nearest neighbours, the rejection radius shrinking
   from ``icp_radius_tiles`` to ``inlier_radius_tiles``) of i's points onto j's, from each guess.
3. **Verification.** With the best refinement: ``overlap`` (share of i's points with a neighbour in j
   within the inlier radius), ``structure_overlap`` (the same for points above the ground: flat ground
   aligns anywhere, so it is not evidence), the RMS ``residual`` of the inliers and the candidate's
   vote margin over the next candidate. Accepted only when all pass; a rejected candidate keeps its
   reason.

Distances are in tiles (``tile_size``: 2 m when metric, a fraction of the scene depth otherwise), so
the thresholds follow the scene's unit.

Returns ``T_ji`` in the graph's convention: the measurement between nodes j and i is
``T_world_j^-1 C T_world_i`` with ``C`` the correction found in the world frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from vggt_slam_pp.dem.plane import GroundPlane
from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.geometry.alignment import umeyama
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse, transform_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegistrationConfig:
    ransac_radius_tiles: float = 1.5
    ransac_iterations: int = 500
    min_planar_inliers: int = 4
    icp_iterations: int = 25
    icp_radius_tiles: float = 2.0
    inlier_radius_tiles: float = 0.2
    max_points: int = 4000
    structure_height_tiles: float = 0.15  # points this far above the ground are "structure"
    min_structure_points: int = 50
    min_overlap: float = 0.3
    min_structure_overlap: float = 0.35
    max_residual_tiles: float = 0.12
    min_vote_margin: float = 0.0  # score(candidate) - score(next); 0 disables
    max_scale_change: float = 0.2  # |log s| of the correction


@dataclass(frozen=True)
class LoopResult:
    query: int
    match: int
    accepted: bool
    reason: str
    T_match_query: np.ndarray | None  # the edge measurement T_world_match^-1 C T_world_query
    correction: np.ndarray | None  # C, in the world frame
    overlap: float
    structure_overlap: float
    residual: float  # world units
    planar_inliers: int
    score: float
    guess: str  # "planar" or "odometry"

    def to_dict(self) -> dict:
        return {"query": self.query, "match": self.match, "accepted": self.accepted, "reason": self.reason,
                "overlap": self.overlap, "structure_overlap": self.structure_overlap, "residual": self.residual,
                "planar_inliers": self.planar_inliers, "score": self.score, "guess": self.guess}


def planar_ransac(src_uv: np.ndarray, dst_uv: np.ndarray, radius: float, iterations: int = 500,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rigid 2-D motion ``dst ~ R src + t`` from paired points [N,2] with outliers.

    Returns (3x3 homogeneous matrix, inlier mask [N]); identity and no inliers when N < 2.
    """
    n = len(src_uv)
    best_T, best = np.eye(3), np.zeros(n, bool)
    if n < 2:
        return best_T, best
    rng = np.random.default_rng(seed)
    for _ in range(iterations):
        a, b = rng.choice(n, 2, replace=False)
        ds, dd = src_uv[b] - src_uv[a], dst_uv[b] - dst_uv[a]
        if np.linalg.norm(ds) < 1e-9 or abs(np.linalg.norm(ds) - np.linalg.norm(dd)) > radius:
            continue
        th = np.arctan2(dd[1], dd[0]) - np.arctan2(ds[1], ds[0])
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        t = dst_uv[a] - R @ src_uv[a]
        inl = np.linalg.norm(src_uv @ R.T + t - dst_uv, axis=1) < radius
        if inl.sum() > best.sum():
            best, best_T = inl, np.block([[R, t[:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])
    if best.sum() >= 2:  # least-squares refit on the inliers
        s, d = src_uv[best], dst_uv[best]
        ms, md = s.mean(0), d.mean(0)
        U, _, Vt = np.linalg.svd((d - md).T @ (s - ms))
        R = U @ np.diag([1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        best_T = np.block([[R, (md - R @ ms)[:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])
        best = np.linalg.norm(src_uv @ R.T + best_T[:2, 2] - dst_uv, axis=1) < radius
    return best_T, best


def planar_to_world(plane: GroundPlane, T2: np.ndarray) -> np.ndarray:
    """Lift a 2-D rigid motion of canonical (u, v) to a 4x4 world transform (heights kept)."""
    A = np.eye(4)
    A[:2, :2], A[:2, 3] = T2[:2, :2], T2[:2, 2]
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = plane.R, plane.origin  # canonical -> world: x = R c + origin
    return W @ A @ np.linalg.inv(W)


def mutual_matches(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of mutual nearest neighbours by cosine between rows of a [A,D] and b [B,D]."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    sim = a @ b.T
    ab, ba = sim.argmax(1), sim.argmax(0)
    ia = np.nonzero(ba[ab] == np.arange(len(a)))[0]
    return ia, ab[ia]


def _subsample(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.random.default_rng(seed).choice(len(points), n, replace=False)]


def icp_sim3(src: np.ndarray, tree: cKDTree, dst: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Sim(3) ``T`` with ``T src ~ dst`` by ICP: one rigid Umeyama on nearest neighbours per radius,
    then one fit with scale at the last radius. (Fitting the scale in every round lets a cloud that
    is mostly ground shrink onto itself: distances fall as the scale does.)"""
    T = np.eye(4)
    for k, r in enumerate([*radii, radii[-1]]):
        cur = transform_points(T, src)
        d, j = tree.query(cur, distance_upper_bound=r)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        try:
            T = umeyama(src[ok], dst[j[ok]], with_scale=k == len(radii))
        except GeometryError:
            break
    return T


def register_loop(query: int, match: int, points_query: np.ndarray, points_match: np.ndarray,
                  plane: GroundPlane, tile_size: float, T_world_query: np.ndarray, T_world_match: np.ndarray,
                  chip_uv: np.ndarray | None = None, tile_uv: np.ndarray | None = None, score: float = 0.0,
                  margin: float = np.inf, config: RegistrationConfig | None = None) -> LoopResult:
    """Register and verify one loop candidate (see the module docstring).

    Args:
        points_query, points_match: [N,3], [M,3] points in the world frame (current estimate).
        chip_uv, tile_uv: [K,2] matched chip / tile centres in canonical plane coordinates (may be empty).
        margin: the candidate's vote margin over the next candidate.
    """
    c = config or RegistrationConfig()
    unit = float(tile_size)

    def reject(reason: str, **kw) -> LoopResult:
        base = dict(T_match_query=None, correction=None, overlap=0.0, structure_overlap=0.0, residual=np.inf,
                    planar_inliers=0, score=score, guess="none")
        base.update(kw)
        return LoopResult(query, match, False, reason, **base)

    if len(points_query) < c.min_structure_points or len(points_match) < c.min_structure_points:
        return reject("too few points")
    if c.min_vote_margin > 0 and margin < c.min_vote_margin:
        return reject(f"vote margin {margin:.3f} < {c.min_vote_margin}")
    src = _subsample(np.asarray(points_query, float), c.max_points, query)
    dst = np.asarray(points_match, float)
    tree = cKDTree(dst)
    h_dst = plane.to_canonical(dst)[:, 2]
    ground = float(np.median(h_dst))
    struct_dst = dst[h_dst > ground + c.structure_height_tiles * unit]
    struct_tree = cKDTree(struct_dst) if len(struct_dst) >= c.min_structure_points else None

    guesses = {"odometry": np.eye(4)}
    n_planar = 0
    if chip_uv is not None and tile_uv is not None and len(chip_uv) >= 2:
        T2, inl = planar_ransac(np.asarray(chip_uv, float), np.asarray(tile_uv, float),
                                c.ransac_radius_tiles * unit, c.ransac_iterations, seed=query * 7919 + match)
        n_planar = int(inl.sum())
        if n_planar >= c.min_planar_inliers:
            guesses["planar"] = planar_to_world(plane, T2)
    radii = np.geomspace(c.icp_radius_tiles, c.inlier_radius_tiles, c.icp_iterations) * unit
    r_in = c.inlier_radius_tiles * unit
    best = None
    for name, G in guesses.items():
        g_src = transform_points(G, src)
        T = icp_sim3(g_src, tree, dst, radii) @ G
        cur = transform_points(T, src)
        d, _ = tree.query(cur, distance_upper_bound=r_in)
        inl = np.isfinite(d)
        overlap = float(inl.mean())
        residual = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else np.inf
        h = plane.to_canonical(cur)[:, 2]
        struct_src = cur[h > ground + c.structure_height_tiles * unit]
        if struct_tree is not None and len(struct_src) >= c.min_structure_points:
            ds, _ = struct_tree.query(struct_src, distance_upper_bound=r_in)
            s_overlap = float(np.isfinite(ds).mean())
        else:
            s_overlap = 0.0
        cand = (s_overlap, overlap, residual, T, name)
        if best is None or (cand[0], cand[1]) > (best[0], best[1]):
            best = cand
    s_overlap, overlap, residual, C, name = best
    kw = dict(overlap=overlap, structure_overlap=s_overlap, residual=residual, planar_inliers=n_planar, guess=name)
    s, _, _ = decompose_sim3(C)
    if abs(np.log(s)) > c.max_scale_change:
        return reject(f"scale change {float(s):.2f} too large", **kw)
    if overlap < c.min_overlap:
        return reject(f"overlap {overlap:.2f} < {c.min_overlap}", **kw)
    if s_overlap < c.min_structure_overlap:
        return reject(f"structure overlap {s_overlap:.2f} < {c.min_structure_overlap}", **kw)
    if residual > c.max_residual_tiles * unit:
        return reject(f"residual {residual:.3f} > {c.max_residual_tiles * unit:.3f}", **kw)
    T_mq = sim3_inverse(T_world_match) @ C @ T_world_query
    return LoopResult(query, match, True, "accepted", T_mq, C, score=score, **kw)
