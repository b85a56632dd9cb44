"""Loop registration and verification (SPEC 3.10: the paper is silent; this is our decision).

For a loop candidate (query submap i, match j), all in the current world estimate:

1. **Planar guess.** Mutual nearest neighbours between i's chip descriptors and j's tile descriptors
   give 2-D correspondences between tile centres in the DEM plane; RANSAC over 2-point rigid
   hypotheses (yaw + translation, inlier radius ``ransac_radius_tiles``) gives a planar motion. The
   identity (the odometry's own guess) is always tried as well, and so are the best ``search_peaks``
   distinct alignments of a DEM structure search (:func:`dem_search`; a peak after the first only counts
   with ``alternative_min_structure_overlap``: on repetitive streets the best correlation is often a
   look-alike one building away).
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
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse, sim3_log, so3_exp, transform_points
from vggt_slam_pp.vpr.geometry import GeometryConfig, Structure, structure_peaks

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegistrationConfig:
    ransac_radius_tiles: float = 1.5
    ransac_iterations: int = 500
    min_planar_inliers: int = 4
    icp_iterations: int = 12
    icp_radius_tiles: float = 2.0
    inlier_radius_tiles: float = 0.2
    max_points: int = 4000
    structure_height_tiles: float = 0.15  # points this far above the ground are "structure"
    min_structure_points: int = 50
    min_overlap: float = 0.2
    min_structure_overlap: float = 0.25  # wrong candidates measured <= 0.16 (bench loops scenes)
    max_residual_tiles: float = 0.15
    min_vote_margin: float = 0.0  # score(candidate) - score(next); 0 disables
    max_scale_change: float = 0.2  # |log s| of the correction
    search_cell_tiles: float = 0.2  # DEM search: occupancy-image cell
    search_max_yaw_deg: float = 15.0
    search_yaw_step_deg: float = 1.0
    search_max_shift_tiles: float = 5.0
    search_peaks: int = 2  # distinct DEM-search alignments refined by ICP (the best first; a third
    # accepted repetitive-structure look-alikes on other bench worlds)
    alternative_min_structure_overlap: float = 0.35  # a peak after the first counts only with this much
    normals_k: int = 10
    min_trans_sigma_tiles: float = 0.02  # loop information: sigma of the best-constrained translation
    floor_rot_sigma: float = 0.1  # loop information: weak prior per ICP parameter (rad, tiles, log-scale)
    floor_trans_sigma_tiles: float = 5.0
    floor_scale_sigma: float = 0.1


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
    guess: str  # "odometry", "dem_search" or "planar"
    constraint_ratio: float = 0.0  # weakest / strongest in-plane translation information of the ICP
    information: np.ndarray | None = None  # 7x7, in the pose graph's tangent of T_match_query
    source: str = "retrieval"  # where the candidate came from: "retrieval", "proximity" or "injected"

    def to_dict(self) -> dict:
        return {"query": self.query, "match": self.match, "accepted": self.accepted, "reason": self.reason,
                "overlap": self.overlap, "structure_overlap": self.structure_overlap, "residual": self.residual,
                "planar_inliers": self.planar_inliers, "score": self.score, "guess": self.guess,
                "constraint_ratio": self.constraint_ratio, "source": self.source}


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


def point_normals(points: np.ndarray, tree: cKDTree, k: int = 10) -> np.ndarray:
    """[N,3] unit normals: the least-variance direction of each point's ``k`` nearest neighbours."""
    _, nn = tree.query(points, min(k, len(points)))
    nb = points[nn]
    nb = nb - nb.mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))
    return vec[:, :, 0]


def icp_point_to_plane(src: np.ndarray, tree: cKDTree, dst: np.ndarray, normals: np.ndarray, radii: np.ndarray,
                       scale_rounds: int = 3, damping: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sim(3) ``T`` with ``T src ~ dst`` by point-to-plane ICP, one damped Gauss-Newton step per radius.

    Residuals ``n_q . (p - q)`` with Cauchy weights (width: the radius / 4); unknowns: rotation, translation
    and, in the last ``scale_rounds`` rounds only, log-scale about the matched points' centroid (a free
    scale from a far guess lets the cloud shrink onto itself). Unlike point-to-point ICP, points on flat ground
    constrain only height, tilt and scale, so a ground-dominated cloud does not hold the in-plane motion
    at the initial guess. Returns ``T``, the 7x7 Gauss-Newton information ``J^T W J`` of the last step
    (order: rotation, translation, log-scale; see :func:`icp_step`), whose small eigenvalues are the
    poorly constrained directions, and the centre ``m`` [3] (world) that step was taken about.
    """
    T = np.eye(4)
    H = np.zeros((7, 7))
    m = src.mean(0)
    for it, r in enumerate(radii):
        cur = transform_points(T, src)
        d, j = tree.query(cur, distance_upper_bound=r)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        p, q, n = cur[ok], dst[j[ok]], normals[j[ok]]
        m = p.mean(0)
        pc = p - m
        res = np.einsum("ij,ij->i", n, p - q)
        J = np.hstack([np.cross(pc, n), n, np.einsum("ij,ij->i", n, pc)[:, None]])
        w = 1.0 / (1.0 + (res / (r / 4.0)) ** 2)
        H = (J * w[:, None]).T @ J
        dim = 7 if it >= len(radii) - scale_rounds else 6
        A = H[:dim, :dim] + damping * np.trace(H[:dim, :dim]) / dim * np.eye(dim)
        x = np.zeros(7)
        x[:dim] = -np.linalg.solve(A, (J[:, :dim] * w[:, None]).T @ res)
        T = icp_step(x, m) @ T
    return T, H, m


def icp_step(x: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The 4x4 motion ``p -> exp(x_6) R(x_0:3) (p - centre) + centre + x_3:6`` of one ICP step."""
    s = float(np.exp(x[6]))
    R = so3_exp(x[:3])
    step = np.eye(4)
    step[:3, :3] = s * R
    step[:3, 3] = centre + x[3:6] - s * R @ centre
    return step


def loop_information(H: np.ndarray, centre: np.ndarray, C: np.ndarray, T_world_match: np.ndarray,
                     T_world_query: np.ndarray, trans_sigma: float, floor_sigmas: np.ndarray) -> np.ndarray:
    """7x7 information of the loop measurement ``Z = T_world_match^-1 C T_world_query`` in the pose
    graph's tangent (``[omega, u, lambda]`` of ``Z^-1 Z'``), from the ICP information ``H`` (world
    frame, about ``centre``).

    ``H``'s shape is kept (directions the structure does not constrain, e.g. along a street of parallel
    facades, stay weak) and its scale is set so the best-constrained translation direction has
    ``trans_sigma``: the point residuals are far from independent, so ``H`` itself is overconfident.
    ``floor_sigmas`` [7] adds a weak prior per ICP parameter, keeping the matrix positive-definite.
    The Jacobian from the ICP parameters to the graph's tangent is taken by central differences.
    """
    Zi = sim3_inverse(sim3_inverse(T_world_match) @ C @ T_world_query)
    A = np.zeros((7, 7))
    h = 1e-6
    for k in range(7):
        x = np.zeros(7)
        x[k] = h
        plus = sim3_log(Zi @ sim3_inverse(T_world_match) @ icp_step(x, centre) @ C @ T_world_query)
        minus = sim3_log(Zi @ sim3_inverse(T_world_match) @ icp_step(-x, centre) @ C @ T_world_query)
        A[:, k] = (plus - minus) / (2 * h)
    top = float(np.linalg.eigvalsh(H[3:6, 3:6]).max())
    Hn = H / (max(top, 1e-12) * trans_sigma**2) + np.diag(1.0 / np.asarray(floor_sigmas, float) ** 2)
    Ai = np.linalg.inv(A)
    info = Ai.T @ Hn @ Ai
    return 0.5 * (info + info.T)


def dem_search(src: np.ndarray, dst: np.ndarray, plane: GroundPlane, ground: float, height: float, cell: float,
               max_yaw_deg: float, yaw_step_deg: float, max_shift: float, count: int = 1
               ) -> list[tuple[np.ndarray, float]]:
    """Planar motions (yaw, shift) aligning the structure of ``src`` onto ``dst``: exhaustive yaw and
    normalised cross-correlation of their structure-occupancy images in the ground plane.

    Points higher than ``ground + height`` are rasterised into ``cell``-sized occupancy images (blurred by
    one cell); for each yaw about the source structure's centroid, the shifts within ``max_shift`` that
    maximise the normalised correlation (OpenCV ``TM_CCORR_NORMED``). Returns up to ``count`` distinct
    alignments, best first: (4x4 world motion, score in [0, 1]); empty when either side has too little
    structure. Repetitive structure (a row of similar buildings) gives several peaks of similar height,
    and which one wins can flip with a few decimetres of drift, so the caller refines more than one.
    """
    cs, cd = plane.to_canonical(src), plane.to_canonical(dst)
    us, ud = cs[cs[:, 2] > ground + height, :2], cd[cd[:, 2] > ground + height, :2]
    # the same correlation as place recognition's re-ranking, on points (weight 1 each) in world units
    search = GeometryConfig(cell_tiles=cell, max_yaw_deg=max_yaw_deg, yaw_step_deg=yaw_step_deg,
                            max_shift_tiles=max_shift, min_cells=10)
    out = []
    for g in structure_peaks(Structure(us, np.ones(len(us))), Structure(ud, np.ones(len(ud))), 1.0, search, count,
                             min_separation_tiles=5 * cell):
        if g.score <= 0:
            continue
        yaw = np.radians(g.yaw_deg)
        R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        centre = us.mean(0)
        T2 = np.eye(3)
        T2[:2, :2], T2[:2, 2] = R, centre - R @ centre + g.shift
        out.append((planar_to_world(plane, T2), g.score))
    return out


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
    guesses = {"odometry": np.eye(4)}
    n_planar = 0
    if chip_uv is not None and tile_uv is not None and len(chip_uv) >= 2:
        T2, inl = planar_ransac(np.asarray(chip_uv, float), np.asarray(tile_uv, float),
                                c.ransac_radius_tiles * unit, c.ransac_iterations, seed=query * 7919 + match)
        n_planar = int(inl.sum())
        if n_planar >= c.min_planar_inliers:
            guesses["planar"] = planar_to_world(plane, T2)
    # cheap early exit: footprints further apart than the search reaches (most wrong candidates)
    reach = (c.search_max_shift_tiles + c.icp_radius_tiles) * unit
    c_dst = plane.to_canonical(dst)
    lo, hi = c_dst[:, :2].min(0) - reach, c_dst[:, :2].max(0) + reach
    if not any(np.any(np.all((uv >= lo) & (uv <= hi), axis=1))
               for uv in (plane.to_canonical(transform_points(G, src))[:, :2] for G in guesses.values())):
        return reject("footprints too far apart in the current estimate", planar_inliers=n_planar)
    tree = cKDTree(dst)
    h_dst = c_dst[:, 2]
    ground = float(np.median(h_dst))
    struct_dst = dst[h_dst > ground + c.structure_height_tiles * unit]
    struct_tree = cKDTree(struct_dst) if len(struct_dst) >= c.min_structure_points else None
    peaks = dem_search(src, dst, plane, ground, c.structure_height_tiles * unit, c.search_cell_tiles * unit,
                       c.search_max_yaw_deg, c.search_yaw_step_deg, c.search_max_shift_tiles * unit, c.search_peaks)
    for k, (G, _) in enumerate(peaks):
        guesses["dem_search" if k == 0 else f"dem_search_{k + 1}"] = G
    alternatives = {f"dem_search_{k + 1}" for k in range(1, len(peaks))}
    # a guess is worth refining only if enough of the query lies within the ICP's first radius
    guesses = {k: G for k, G in guesses.items()
               if np.isfinite(tree.query(transform_points(G, src), distance_upper_bound=c.icp_radius_tiles * unit)[0]
                              ).mean() >= 0.5 * c.min_overlap}
    if not guesses:
        return reject(f"overlap < {0.5 * c.min_overlap:.2f} at every initial guess", planar_inliers=n_planar)
    radii = np.geomspace(c.icp_radius_tiles, c.inlier_radius_tiles, c.icp_iterations) * unit
    r_in = c.inlier_radius_tiles * unit
    normals = point_normals(dst, tree, c.normals_k)
    best = None
    for name, G in guesses.items():
        g_src = transform_points(G, src)
        T, H, centre = icp_point_to_plane(g_src, tree, dst, normals, radii)
        T = T @ G
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
        if name in alternatives and s_overlap < c.alternative_min_structure_overlap:
            continue  # a weaker correlation peak has to show more structure than the primary guesses
        cand = (s_overlap, overlap, residual, T, name, H, centre)
        if best is None or (cand[0], cand[1]) > (best[0], best[1]):
            best = cand
    if best is None:
        return reject(f"structure overlap < {c.alternative_min_structure_overlap} at every DEM-search peak",
                      planar_inliers=n_planar)
    s_overlap, overlap, residual, C, name, H, centre = best
    ev = np.linalg.eigvalsh(plane.R[:2] @ H[3:6, 3:6] @ plane.R[:2].T)  # in-plane translation information
    constraint = float(ev[0] / max(ev[1], 1e-12))
    kw = dict(overlap=overlap, structure_overlap=s_overlap, residual=residual, planar_inliers=n_planar, guess=name,
              constraint_ratio=constraint)
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
    info = loop_information(H, centre, C, T_world_match, T_world_query, max(residual, c.min_trans_sigma_tiles * unit),
                            np.r_[[c.floor_rot_sigma] * 3, [c.floor_trans_sigma_tiles * unit] * 3, c.floor_scale_sigma])
    return LoopResult(query, match, True, "accepted", T_mq, C, score=score, information=info, **kw)
