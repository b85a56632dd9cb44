"""Loop registration and verification (SPEC 3.10: the paper is silent; this is our decision).

A loop candidate (query submap q, match m) is registered from the two submaps' own points, each in
its own frame; the result is the measurement ``T_match_query`` itself. The current estimate gives
a first up direction (the ground plane's normal in each frame; each submap's own ground refines it:
:func:`~vggt_slam_pp.backend.search.own_up`), the unit (``tile_size`` in each submap's
scale), one initial guess among the others and, through :class:`LoopBounds`, how far odometry can
have drifted; nothing else. Where both submaps' keyframe cameras stand at one height above their own
ground (:func:`~vggt_slam_pp.backend.search.camera_height`, measured once per submap by the back-end: a
car, a walker, a robot), the ratio of the two heights is the loop's scale: the search covers only scales near it, the estimate's guesses are
rescaled to it, and a result at another scale is refused (``RegistrationConfig.height_cue``).

0. **Clean-up.** Isolated points (flying pixels: a wrong depth in mid-air) are removed
   (:func:`remove_isolated`): they would count as structure everywhere.
1. **Initial guesses.** The current estimate ("odometry"); with >= 4 inliers, a 2-point planar RANSAC
   of mutual-NN chip/tile descriptor matches ("planar"); and the ``search_peaks`` best alignments of
   the estimate-free search (:mod:`vggt_slam_pp.backend.search`: every yaw, scale and shift within
   the bounds, scored by free-space consistency; "search_k").
2. **3-D refinement.** Point-to-plane ICP (the rejection radius shrinking from ``icp_radius_tiles`` to
   ``inlier_radius_tiles``, then ``icp_final_iterations`` more at the inlier radius; log-scale free in
   the last ``icp_scale_rounds``; loosely mutual pairs only, ``icp_reciprocity``) of q's points onto m's, from each
   guess. ICP fits all of q's structure and
   at most ``icp_max_flat_points`` of its other points: flat ground constrains only height, tilt and scale,
   and as most of a submap it would outweigh the structure that fixes the in-plane motion. A fit with less than
   ``icp_check_share`` of the verification's structure overlap at the inlier radius before round
   ``icp_check_iteration`` stops there (it would not verify: most guesses of a revisit are such fits).
3. **Verification**, on the best refinement (by free-space agreement x structure overlap):
   ``overlap`` (share of q's points with a neighbour in m within the inlier radius),
   ``structure_overlap`` (the same for points above the ground: flat ground aligns anywhere),
   ``agreement`` (:func:`~vggt_slam_pp.backend.search.free_space_agreement`: no building where the
   other submap saw open ground), both weighted by colour when the points have it (structure agrees as
   far as its hue matches), the query's ground on the match's (the query's structure and ground are
   classified in its own frame; a fit that lifts its ground off the match's is refused), the RMS
   ``residual``, the bounds (scale, yaw and shift of the
   correction), and no distinct alignment nearly as good (``ambiguity_ratio``: repetitive structure).
   A rejected candidate keeps its reason. Where the cameras' heights have not measured its scale, a
   verified loop's scale is then made symmetric (``symmetric_scale``, :func:`symmetric_scale`). The back-end
   then asks for a cycle-consistent second loop
   or a correction within one sigma of the drift model before the loop enters the graph
   (:mod:`vggt_slam_pp.backend.backend`).

Distances are in tiles (2 m when metric, a fraction of the scene depth otherwise), so the thresholds
follow the scene's unit. ``correction`` is ``C = T_world_match T_match_query T_world_query^-1``, the
change the loop asks of the query's pose in the world frame.
"""

from __future__ import annotations

import collections
import hashlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from vggt_slam_pp.backend.appearance import LANDMARKS_GUESS, ImageCheck
from vggt_slam_pp.backend.search import (
    SearchConfig,
    colour_match,
    footprint_overlap,
    free_space_agreement,
    hue_vectors,
    own_up,
    search_alignments,
    up_frame,
)
from vggt_slam_pp.dem.plane import GroundPlane
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse, sim3_log, so3_exp, transform_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegistrationConfig:
    ransac_radius_tiles: float = 1.5
    ransac_iterations: int = 500
    min_planar_inliers: int = 4
    icp_iterations: int = 12  # the rejection radius shrinks over these, then
    icp_final_iterations: int = 6  # these at the inlier radius
    icp_scale_rounds: int = 3  # the last rounds solve for scale too (more: a partial overlap shrinks onto itself)
    icp_scale_at_cue: bool = True  # where the cameras' heights are measured to hold, ICP keeps the guesses at
    # their scale instead (the landmarks' guess keeps its own, measured scale and refines it): their ratio is
    # nearer the truth than ICP's scale on a partial overlap (docs/backend.md, "registration")
    images_second_opinion: bool = True  # a loop verified from the points' guesses that the images could confirm but
    # do not is refined from the landmarks' guess too; where that fit verifies, the images confirm it and the points
    # cannot tell it from theirs (within two ICP radii, ranked within ambiguity_ratio), it is the loop
    # (docs/backend.md, "appearance")
    symmetric_scale: bool = True  # where the cameras' heights have not measured the loop's scale (a flying or
    # hand-held camera, a short recording), a verified loop's scale is the mean (in log) of ICP's from the query
    # onto the match and from the match back onto the query: each direction shrinks the cloud it moves onto the
    # other's overlap (held-out-like V1_02, realistic seed 2: loops' log-scale error median -0.035, mean -0.084;
    # docs/backend.md, "registration")
    icp_radius_tiles: float = 2.0
    icp_check_iteration: int = 8  # a fit whose structure overlap at the inlier radius is then still below
    icp_check_share: float = 0.4  # this share of min_structure_overlap is dropped (0: never): of 1,823 fits on
    # the bench worlds, 451 ended at >= min_structure_overlap, one of them from below 0.1 here (docs/backend.md)
    icp_reciprocity: float = 0.25  # an ICP pair holds only where the query point lies within this share of the
    # radius of the match point's own nearest query point: past the overlap's edge, many query points pair with the
    # match's last points and pull the query towards more overlap (0: every pair holds; docs/backend.md)
    inlier_radius_tiles: float = 0.2
    max_points: int = 4000
    icp_max_flat_points: int = 500  # ICP fits every structure point and at most this many others (drawn at
    # random, seeded; 0: all): flat ground fixes only height, tilt and scale, and would outweigh the structure
    ground_percentile: float = 20.0  # a submap's ground level: this percentile of its heights
    structure_height_tiles: float = 0.15  # points this far above the ground are "structure"
    min_structure_points: int = 50
    min_overlap: float = 0.2
    min_structure_overlap: float = 0.25  # wrong candidates measured <= 0.16 (bench loops scenes)
    min_footprint_overlap: float = 0.3  # share of the smaller footprint (one-tile ground cells) the two share at
    # the result: a revisit as bench loops defines one (search.footprint_overlap; 0: not tested)
    footprint_min_points: int = 3  # a cell is in a footprint with this many points
    max_residual_tiles: float = 0.15
    min_vote_margin: float = 0.0  # score(candidate) - score(next); 0 disables
    search: SearchConfig = field(default_factory=SearchConfig)  # no initial guess: backend/search.py
    search_peaks: int = 4  # its best alignments refined by ICP (besides the current estimate's guess)
    # what odometry can have drifted between the two submaps (LoopBounds, 3 sigma of a random walk)
    max_scale_change: float = 0.7  # |log s| of the correction: never more than a factor 2
    scale_sigma_per_submap: float = 0.05  # odometry log-scale drift per submap
    min_scale_bound: float = 0.1
    yaw_sigma_per_submap_deg: float = 1.5
    min_yaw_bound_deg: float = 10.0
    translation_drift: float = 0.06  # the query may have moved this share of the path between the two
    min_translation_bound_tiles: float = 3.0
    loop_hop_tiles: float = 2.0  # an accepted loop on the drift path (LoopCloser.bounds) adds this much translation
    # (and one submap of scale and yaw random walk): what a loop's own registration error can be
    degraded_log_scale: float = 0.3  # each degraded (extrapolated) odometry edge in between adds these
    degraded_yaw_deg: float = 30.0
    degraded_steps: float = 2.0  # times that edge's own length
    agreement_cell_tiles: float = 0.25  # free-space agreement (backend/search.py): its cell
    min_agreement: float = 0.6  # share of structure cells consistent with the other side's observations
    min_agreement_cells: int = 10
    ambiguity_ratio: float = 0.85  # a distinct alignment this close to the best (agreement x structure
    # overlap): ambiguous
    normals_k: int = 10
    own_up: bool = True  # each submap levelled by its own ground (search.own_up), not by the estimate's up
    max_up_tilt_deg: float = 15.0  # how far its own ground's normal may be from the estimate's up
    height_cue: bool = True  # cameras at one height above their ground in both submaps: their ratio is the
    # loop's scale (search.camera_height), searched within and verified against height_cue_tolerance
    height_cue_tolerance: float = 0.1  # |log s| between the loop's scale and the cameras' height ratio
    height_cue_unmeasured_tolerance: float = 0.2  # the same while the recording's heights are not yet measured
    # to hold (Map.height_cue); the guesses are then not rescaled to the cue either
    icp_scale_reach: float = 0.05  # how far ICP's scale rounds may move a guess's |log s| (guesses further
    # beyond the limits are not refined)
    height_cue_max_spread: float = 0.1  # robust spread (1.48 MAD / median) of a submap's camera heights for a
    # steady height
    height_cue_min_tiles: float = 0.2  # lower cameras give no cue (a ratio of tiny heights is noise)
    height_max_points: int = 20_000  # points (evenly subsampled) a submap's ground plane is fitted to
    use_colour: bool = True  # structure agrees by its image colour too (when the points have colours)
    full_saturation: float = 0.08  # chromaticity distance from grey at which a point's hue counts fully
    min_trans_sigma_tiles: float = 0.02  # loop information: sigma of the best-constrained translation
    floor_rot_sigma: float = 0.1  # loop information: weak prior per ICP parameter (rad, tiles, log-scale)
    floor_trans_sigma_tiles: float = 5.0
    floor_scale_sigma: float = 0.1


@dataclass(frozen=True)
class LoopBounds:
    """How far odometry can have drifted between two submaps: the loop's correction may change the
    query's scale by at most ``max_log_scale`` (|log s|), turn it by ``max_yaw_deg`` about the up axis
    and move its centroid by ``max_translation`` (world units). The search covers exactly this."""

    max_log_scale: float
    max_translation: float
    max_yaw_deg: float = 180.0


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
    guess: str  # the initial guess that won: "odometry", "planar", "search_k"; "images" for a loop registered
    # from images (backend/image_loops.py), whose overlap / structure_overlap are the shares of the query's /
    # match's keyframes registered, planar_inliers and agreement_cells the verified matches across, and
    # agreement 1 - the relative camera-centre residual
    constraint_ratio: float = 0.0  # weakest / strongest in-plane translation information of the ICP
    information: np.ndarray | None = None  # 7x7, in the pose graph's tangent of T_match_query
    source: str = "retrieval"  # where the candidate came from: "retrieval", "proximity" or "injected"
    agreement: float = 0.0  # free-space agreement of the two submaps at the result
    agreement_cells: int = 0  # structure cells it was measured on
    scale_cue: float = 0.0  # the scale the two submaps' camera heights gave, once measured to hold (0: none or a loose
    # bound only, Map.height_cue); an accepted loop agrees with it
    appearance: int = -1  # query landmarks whose image feature the match shows at the aligned place (-1: not
    # measured; backend/appearance.py)
    appearance_comparable: int = -1  # query landmarks the alignment brings near a match landmark seen from a
    # similar direction (-1: not measured)
    images_confirm: bool = False  # the landmarks' own alignment is this loop's (ImageCheck.confirms)
    footprint_overlap: float = -1.0  # share of ground the two cover at the result (-1: not measured)
    seconds: float = 0.0  # CPU time of its registration and verification (the back-end's thread)

    def to_dict(self) -> dict:
        return {"query": self.query, "match": self.match, "accepted": self.accepted, "reason": self.reason,
                "overlap": self.overlap, "structure_overlap": self.structure_overlap, "residual": self.residual,
                "planar_inliers": self.planar_inliers, "score": self.score, "guess": self.guess,
                "constraint_ratio": self.constraint_ratio, "source": self.source,
                "agreement": self.agreement, "agreement_cells": self.agreement_cells, "scale_cue": self.scale_cue,
                "appearance": self.appearance, "appearance_comparable": self.appearance_comparable,
                "images_confirm": self.images_confirm, "footprint_overlap": self.footprint_overlap,
                "seconds": self.seconds,
                **({"T_match_query": self.T_match_query.tolist()} if self.T_match_query is not None else {}),
                **({"information": self.information.tolist()} if self.information is not None else {})}


def drift_bounds(config: RegistrationConfig, submaps: int, path: float, tile_size: float,
                 degraded_steps: list[float] | None = None) -> LoopBounds:
    """What odometry can have drifted over ``submaps`` odometry edges covering ``path`` (world units): 3
    sigma of a random walk in log-scale and yaw (``scale_sigma_per_submap``, ``yaw_sigma_per_submap_deg``,
    with floors) and ``translation_drift`` of the path (at least ``min_translation_bound_tiles``). Each
    degraded (extrapolated) edge in between, of length ``degraded_steps[k]``, adds ``degraded_log_scale``,
    ``degraded_yaw_deg`` and ``degraded_steps`` times its length; the physical limits cap the result."""
    c = config
    walk = 3.0 * np.sqrt(max(submaps, 1))
    log_s = max(c.min_scale_bound, walk * c.scale_sigma_per_submap)
    yaw = max(c.min_yaw_bound_deg, walk * c.yaw_sigma_per_submap_deg)
    trans = max(c.translation_drift * path, c.min_translation_bound_tiles * tile_size)
    for step in degraded_steps or []:
        log_s += c.degraded_log_scale
        yaw += c.degraded_yaw_deg
        trans += c.degraded_steps * step
    return LoopBounds(min(log_s, c.max_scale_change), trans, min(yaw, 180.0))


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
    a = rng.integers(0, n, iterations)
    b = (a + rng.integers(1, n, iterations)) % n  # a pair of distinct points, uniformly
    # every hypothesis at once: the motion that takes pair (a, b) of src onto dst, if their lengths agree
    ds, dd = src_uv[b] - src_uv[a], dst_uv[b] - dst_uv[a]
    len_s, len_d = np.linalg.norm(ds, axis=1), np.linalg.norm(dd, axis=1)
    usable = (len_s >= 1e-9) & (np.abs(len_s - len_d) <= radius)
    th = np.arctan2(dd[:, 1], dd[:, 0]) - np.arctan2(ds[:, 1], ds[:, 0])
    R = np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], 1)  # [I,2,2]
    t = dst_uv[a] - np.einsum("kij,kj->ki", R, src_uv[a])
    inliers = np.linalg.norm(np.einsum("kij,nj->kni", R, src_uv) + t[:, None] - dst_uv[None], axis=2) < radius
    counts = np.where(usable, inliers.sum(1), 0)
    k = int(np.argmax(counts))  # the first hypothesis with the most inliers
    if counts[k] > 0:
        best, best_T = inliers[k], np.block([[R[k], t[k][:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])
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


def _subsample(n_points: int, n: int, seed: int) -> np.ndarray:
    """Indices of at most ``n`` of ``n_points`` points, drawn at random (seeded)."""
    if n_points <= n:
        return np.arange(n_points)
    return np.random.default_rng(seed).choice(n_points, n, replace=False)


def remove_isolated(points: np.ndarray, k: int = 4, factor: float = 3.0) -> np.ndarray:
    """Indices of the points [N,3] whose distance to their ``k``-th neighbour is at most ``factor`` times
    the median such distance: flying pixels (a wrong depth far from any surface) would otherwise stand
    above the ground as "structure" everywhere and make any alignment look supported."""
    if len(points) <= k + 1:
        return np.arange(len(points))
    d = cKDTree(points).query(points, k + 1)[0][:, -1]
    return np.nonzero(d <= factor * max(float(np.median(d)), 1e-12))[0]


class _Reused:
    """What registration derives from one submap's points in its own frame, kept for the next candidates: a
    submap's points never change, and consecutive queries register the same matches again; ``size`` entries,
    least recently used first out; keyed by the submap id, what was derived (with its parameters) and a
    fingerprint of its points."""

    def __init__(self, size: int = 16) -> None:
        self.size = size
        self._items: collections.OrderedDict = collections.OrderedDict()

    def get(self, sid: int, points: np.ndarray, what: tuple, make):
        sample = np.ascontiguousarray(points[:: max(1, len(points) // 64)])
        key = (sid, what, len(points), hashlib.blake2b(sample.tobytes(), digest_size=16).digest())
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = make()
        if isinstance(value, np.ndarray):
            value.setflags(write=False)  # shared by every caller that asks again
        self._items[key] = value
        while len(self._items) > self.size:
            self._items.popitem(last=False)
        return value


_REUSED = _Reused(16)  # a match's KD-tree and normals: ~100 bytes a point, a few submaps' worth
_REUSED_SMALL = _Reused(128)  # a submap's points kept (int32 indices) and its own up: ~40 kB a submap


def point_normals(points: np.ndarray, tree: cKDTree, k: int = 10) -> np.ndarray:
    """[N,3] unit normals: the least-variance direction of each point's ``k`` nearest neighbours."""
    _, nn = tree.query(points, min(k, len(points)))
    nb = points[nn]
    nb = nb - nb.mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))
    return vec[:, :, 0]


def icp_point_to_plane(src: np.ndarray, tree: cKDTree, dst: np.ndarray, normals: np.ndarray, radii: np.ndarray,
                       scale_rounds: int = 3, damping: float = 1e-3, check: tuple[int, Callable] | None = None,
                       anchors: tuple[np.ndarray, np.ndarray] | None = None, reciprocity: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Sim(3) ``T`` with ``T src ~ dst`` by point-to-plane ICP, one damped Gauss-Newton step per radius.

    Residuals ``n_q . (p - q)`` with Cauchy weights (width: the radius / 4); unknowns: rotation, translation
    and, in the last ``scale_rounds`` rounds only, log-scale about the matched points' centroid (a free
    scale from a far guess lets the cloud shrink onto itself). Unlike point-to-point ICP, points on flat ground
    constrain only height, tilt and scale, so a ground-dominated cloud does not hold the in-plane motion
    at the initial guess. Returns ``T``, the 7x7 Gauss-Newton information ``J^T W J`` of the last step
    (order: rotation, translation, log-scale; see :func:`icp_step`), whose small eigenvalues are the
    poorly constrained directions, and the centre ``m`` [3] (world) that step was taken about.
    ``check`` = (iteration k, test): before step k, ``test(T)`` decides whether the fit is worth finishing;
    None when it is not (a hopeless initial guess stops there).
    ``anchors`` = ([A,3] source points, [A,3] their known correspondences in ``dst``'s frame): pairs that are
    matched by something other than closeness (image features), each a point-to-point residual with the
    same robust weights; they hold the in-plane motion that a ground-dominated cloud leaves free, and the
    returned information counts them (a loop refined with them is constrained in-plane by its images).
    ``reciprocity`` > 0: a pair holds only where the match's point has, as its own nearest query point, one within
    that share of the round's radius of the pair's query point (a loose mutual nearest neighbour; 0: every pair
    within the radius holds). Past the overlap's edge many query points pair with the match's last points, and on
    a partial overlap they pull the query towards more overlap; mutual pairs keep one of them.
    """
    T = np.eye(4)
    H = np.zeros((7, 7))
    m = src.mean(0)
    for it, r in enumerate(radii):
        if check is not None and it == check[0] and not check[1](T):
            return None
        cur = transform_points(T, src)
        d, j = tree.query(cur, distance_upper_bound=r)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        p, q, n = cur[ok], dst[j[ok]], normals[j[ok]]
        m = p.mean(0)
        pc = p - m
        res = np.einsum("ij,ij->i", n, p - q)
        if reciprocity > 0:  # a pair holds where the match's point has its query point (nearly) as its nearest
            targets, which = np.unique(j[ok], return_inverse=True)
            back = cKDTree(p).query(dst[targets])[1]
            held = np.linalg.norm(p[back[which]] - p, axis=1) <= reciprocity * r
            if held.sum() < 10:
                break
            pc, n, res = pc[held], n[held], res[held]
        J = np.hstack([np.cross(pc, n), n, np.einsum("ij,ij->i", n, pc)[:, None]])
        w = 1.0 / (1.0 + (res / (r / 4.0)) ** 2)
        if anchors is not None:
            pa = transform_points(T, anchors[0]) - m
            res_a = pa + m - anchors[1]  # [A,3]
            w_a = 1.0 / (1.0 + (np.linalg.norm(res_a, axis=1) / (r / 4.0)) ** 2)
            e = np.eye(3)
            J_a = np.concatenate([np.hstack([np.cross(pa, e[k]), np.tile(e[k], (len(pa), 1)), pa[:, k:k + 1]])
                                  for k in range(3)])  # [3A,7], component-major
            J, res, w = np.vstack([J, J_a]), np.r_[res, res_a.T.ravel()], np.r_[w, np.tile(w_a, 3)]
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


def correction_size(C: np.ndarray, point: np.ndarray) -> tuple[float, float, float]:
    """(|log scale|, rotation angle in degrees, displacement of ``point`` [3]) of a world-frame correction."""
    s, R, _ = decompose_sim3(C)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return abs(float(np.log(s))), angle, float(np.linalg.norm(transform_points(C, point[None])[0] - point))


@dataclass(frozen=True)
class _Fit:
    """One initial guess refined by ICP, with its verification figures."""

    rank: float  # free-space agreement x structure overlap: which fit the loop takes
    structure_overlap: float
    overlap: float
    residual: float  # match-frame units
    Z: np.ndarray  # T_icp @ G: query frame -> match frame
    T_icp: np.ndarray
    G: np.ndarray
    guess: str
    H: np.ndarray  # ICP information (match frame, about ``centre``)
    centre: np.ndarray
    agreement: float
    cells: int
    lifted: float  # the query's ground above the match's where both saw ground (match-frame units)


def _ground_offset(src_ground: np.ndarray, dst_ground_tree: cKDTree, dst_ground_h: np.ndarray, unit: float,
                   min_pairs: int = 20) -> float:
    """Median height of ``src_ground`` [N,3] (levelled, the match's frame) above the match's ground points
    (``dst_ground_tree`` over their ground coordinates, heights ``dst_ground_h``) within one tile: how far
    an alignment lifts the query's ground off the match's (0 where fewer than ``min_pairs`` meet). Local,
    so that sloping ground is no offset."""
    if len(src_ground) == 0 or dst_ground_tree.n == 0:
        return 0.0
    d, j = dst_ground_tree.query(src_ground[:, :2], distance_upper_bound=unit)
    near = np.isfinite(d)
    if near.sum() < min_pairs:
        return 0.0
    return float(np.median(src_ground[near, 2] - dst_ground_h[j[near]]))


def symmetric_scale(Z: np.ndarray, src: np.ndarray, dst: np.ndarray, radius: float, iterations: int,
                    normals_k: int = 10, dst_tree: cKDTree | None = None, reciprocity: float = 0.0) -> np.ndarray:
    """``Z`` (T_match_query, from ICP of the query's points ``src`` [N,3] onto the match's ``dst`` [M,3]) with
    its scale replaced by the mean in log-scale of its own and the reverse fit's: the match's points, brought
    into the query's frame by ``Z^-1``, fitted back onto the query's by ``iterations`` rounds of point-to-plane
    ICP at ``radius`` (match units) with scale free. A fit with free scale shrinks the cloud it moves onto the
    part of the other that overlaps it (points past the overlap's edge pull inwards), so the two directions
    err in opposite ways; the rescaling is about the query's overlapping points, which stay in place.
    ``dst_tree``: ``dst``'s KD-tree, where the caller has it. Returns ``Z`` unchanged where either fit has
    fewer than 10 pairs. ``reciprocity``: that of :func:`icp_point_to_plane`, for the reverse fit."""
    s_z = float(decompose_sim3(Z)[0])
    r_q = radius / s_z  # the same radius in the query's units
    tree_q = cKDTree(src)
    back = transform_points(sim3_inverse(Z), dst)
    near = np.isfinite(tree_q.query(back, distance_upper_bound=2.0 * r_q)[0])
    if near.sum() < 10:
        return Z
    fit = icp_point_to_plane(back[near], tree_q, src, point_normals(src, tree_q, normals_k),
                             np.full(iterations, r_q), scale_rounds=iterations, reciprocity=reciprocity)
    d = (dst_tree or cKDTree(dst)).query(transform_points(Z, src), distance_upper_bound=radius)[0]
    if fit is None or np.isfinite(d).sum() < 10:
        return Z
    s_back = float(decompose_sim3(fit[0])[0])  # the reverse fit's scale on the match's points
    return Z @ _scaled_about(src[np.isfinite(d)].mean(0), 1.0 / np.sqrt(s_back))


def _scaled_about(centre: np.ndarray, k: float) -> np.ndarray:
    """The similarity [4,4] that scales by ``k`` about ``centre`` [3]."""
    S = np.diag([k, k, k, 1.0])
    S[:3, 3] = (1.0 - k) * np.asarray(centre, float)
    return S


def register_loop(query: int, match: int, points_query: np.ndarray, points_match: np.ndarray,
                  T_world_query: np.ndarray, T_world_match: np.ndarray, plane: GroundPlane, tile_size: float,
                  chip_uv: np.ndarray | None = None, tile_uv: np.ndarray | None = None, score: float = 0.0,
                  margin: float = np.inf, bounds: LoopBounds | None = None,
                  config: RegistrationConfig | None = None, colors_query: np.ndarray | None = None,
                  colors_match: np.ndarray | None = None, height_query: float | None = None,
                  height_match: float | None = None, images: ImageCheck | None = None,
                  height_measured: bool = True) -> LoopResult:
    """Register and verify one loop candidate (see the module docstring).

    Args:
        points_query, points_match: [N,3], [M,3] points, each in its own submap's frame.
        T_world_query, T_world_match: the current estimate; it gives the up direction (the ground plane's
            normal), the unit (``tile_size``, world units, in each submap's scale) and one initial guess
            among the others; the result does not depend on it otherwise.
        chip_uv, tile_uv: [K,2] matched chip / tile centres in canonical plane coordinates (may be empty).
        margin: the candidate's vote margin over the next candidate.
        bounds: what odometry can have drifted between the two (None: the physical limits only).
        colors_query, colors_match: [N,3], [M,3] uint8 image colours of the points (optional): structure
            then agrees by its hue too (:func:`~vggt_slam_pp.backend.search.hue_vectors`).
        height_query, height_match: each submap's cameras' height above its own ground, in its own units
            (:func:`~vggt_slam_pp.backend.search.camera_height`; optional): with both, their ratio is the
            loop's scale (``RegistrationConfig.height_cue``).
        images: the two submaps' image landmarks (:class:`~vggt_slam_pp.backend.appearance.ImageCheck`;
            optional): where they can judge the result and disagree with it, it is refused ("images
            disagree"); where the point guesses fail to verify, the alignment the landmarks agree on is one
            more guess (``landmarks``; not rescaled to the height cue: its scale is measured), if ICP could
            still bring it within the bounds and the cue, and its ICP holds the landmark pairs that agree on
            it (``anchors``); a verified loop records whether that alignment confirms it
            (``LoopResult.images_confirm``, :meth:`~vggt_slam_pp.backend.appearance.ImageCheck.confirms`).
            Where the points verify a loop that alignment could confirm but does not, it is refined from that
            guess alone too, and that fit is the loop if it verifies, is confirmed and the points cannot tell it
            from theirs (``RegistrationConfig.images_second_opinion``).
        height_measured: whether the recording's heights have been measured to hold steady
            (:meth:`~vggt_slam_pp.backend.map.Map.height_cue`). If not, the cue is only a loose bound
            (``height_cue_unmeasured_tolerance``) and the guesses keep their own scale.
    """
    c = config or RegistrationConfig()
    s_m, R_m, _ = decompose_sim3(T_world_match)
    s_q, R_q, _ = decompose_sim3(T_world_query)
    unit = float(tile_size) / float(s_m)  # one tile in the match's frame
    unit_q = float(tile_size) / float(s_q)  # one tile in the query's frame
    bounds = bounds or LoopBounds(c.max_scale_change, np.inf)
    max_log_scale = min(bounds.max_log_scale, c.max_scale_change)

    def reject(reason: str, **kw) -> LoopResult:
        base = dict(T_match_query=None, correction=None, overlap=0.0, structure_overlap=0.0, residual=np.inf,
                    planar_inliers=0, score=score, guess="none")
        base.update(kw)
        return LoopResult(query, match, False, reason, **base)

    if len(points_query) < c.min_structure_points or len(points_match) < c.min_structure_points:
        return reject("too few points")
    if c.min_vote_margin > 0 and margin < c.min_vote_margin:
        return reject(f"vote margin {margin:.3f} < {c.min_vote_margin}")
    T0 = sim3_inverse(T_world_match) @ T_world_query  # query frame -> match frame, current estimate
    points_query, points_match = np.asarray(points_query, float), np.asarray(points_match, float)
    keep_q = _REUSED_SMALL.get(query, points_query, ("isolated",),
                               lambda: remove_isolated(points_query).astype(np.int32))
    keep_q = keep_q[_subsample(len(keep_q), c.max_points, query)]
    keep_m = _REUSED_SMALL.get(match, points_match, ("isolated",),
                               lambda: remove_isolated(points_match).astype(np.int32))
    src, dst = points_query[keep_q], points_match[keep_m]
    hue_src = hue_vectors(None if colors_query is None else np.asarray(colors_query)[keep_q], len(src),
                          c.full_saturation)
    hue_dst = hue_vectors(None if colors_match is None else np.asarray(colors_match)[keep_m], len(dst),
                          c.full_saturation)
    guesses = {"odometry": T0}
    n_planar = 0
    if chip_uv is not None and tile_uv is not None and len(chip_uv) >= 2:
        T2, inl = planar_ransac(np.asarray(chip_uv, float), np.asarray(tile_uv, float),
                                c.ransac_radius_tiles * tile_size, c.ransac_iterations, seed=query * 7919 + match)
        n_planar = int(inl.sum())
        if n_planar >= c.min_planar_inliers:
            guesses["planar"] = sim3_inverse(T_world_match) @ planar_to_world(plane, T2) @ T_world_query
    up_q, up_m = R_q.T @ plane.normal, R_m.T @ plane.normal  # the estimate's up, in each submap's frame
    if c.own_up:  # each submap's up from its own ground: the estimate's drifts (module docstring)
        # the same for every candidate of a query, and for a match until the graph moves it
        up_q = _REUSED_SMALL.get(query, points_query, ("up", up_q.tobytes(), unit_q, c.max_up_tilt_deg, c.max_points),
                                 lambda: own_up(src, up_q, unit_q, c.max_up_tilt_deg, seed=query))
        up_m = _REUSED_SMALL.get(match, points_match, ("up", up_m.tobytes(), unit, c.max_up_tilt_deg),
                                 lambda: own_up(dst, up_m, unit, c.max_up_tilt_deg, seed=match))
    cue = None

    def at_cue_scale(G: np.ndarray) -> np.ndarray:
        """Guess ``G`` rescaled to the cameras' height ratio about the query's centroid."""
        return G @ _scaled_about(src.mean(0), cue[0] / decompose_sim3(G)[0])

    if c.height_cue and height_query is not None and height_match is not None:
        cue = (height_match / height_query, c.height_cue_tolerance if height_measured else
               c.height_cue_unmeasured_tolerance)
        # the estimate's guesses at the cameras' scale, about the query's centroid (heights measured to hold)
        for k in list(guesses) if height_measured else ():
            guesses[k] = at_cue_scale(guesses[k])

    def off_cue(T: np.ndarray, slack: float = 0.0) -> bool:
        """Whether ``T``'s scale lies outside the cameras' height cue, widened by ``slack`` in log-scale (False
        without one)."""
        return cue is not None and abs(float(np.log(decompose_sim3(T)[0] / cue[0]))) > cue[1] + slack

    def outside_bounds(Z: np.ndarray, reach: float = 0.0) -> str | None:
        """Why alignment ``Z`` (T_match_query) lies beyond the cameras' height cue or what odometry allows, or
        None. ``reach`` > 0 widens every limit by that many ICP refinements (how far ICP may still move a
        guess: its first radius, a yaw step, ``icp_scale_reach`` in log-scale): a guess beyond that cannot
        end within the limits."""
        C = T_world_match @ Z @ sim3_inverse(T_world_query)  # the correction, world frame
        log_s, turned, moved = correction_size(C, transform_points(T_world_query, src.mean(0)[None])[0])
        if off_cue(Z, reach * c.icp_scale_reach):
            return f"scale x{decompose_sim3(Z)[0]:.2f} against x{cue[0]:.2f} from the cameras' heights"
        if log_s > max_log_scale + reach * c.icp_scale_reach:
            return f"scale change x{np.exp(log_s):.2f} beyond what odometry allows (x{np.exp(max_log_scale):.2f})"
        slack = (1.0 + reach) * c.icp_radius_tiles * tile_size  # the search bounds the initial guesses; ICP may
        # move a little further
        if moved > bounds.max_translation + slack:
            return f"moves the submap {moved:.1f} > {bounds.max_translation:.1f} that odometry allows"
        if turned > bounds.max_yaw_deg + (1.0 + reach) * c.search.yaw_step_deg:
            return f"turns the submap {turned:.0f} deg > {bounds.max_yaw_deg:.0f} that odometry allows"
        return None

    found = search_alignments(src, dst, up_q, up_m, unit, T0, max_log_scale, bounds.max_yaw_deg,
                              bounds.max_translation / float(s_m), c.search_peaks, c.search, hue_src, hue_dst, cue)
    at_cue = cue is not None and height_measured and c.icp_scale_at_cue
    for k, (G, _) in enumerate(found):  # searched within the cue's tolerance; at the cue where ICP holds it
        guesses[f"search_{k + 1}"] = at_cue_scale(G) if at_cue else G
    tree = _REUSED.get(match, points_match, ("tree",), lambda: cKDTree(dst))
    # the query's structure and ground as its own ground plane sees them: a wrong scale or height that
    # lifts its ground onto the match's buildings must not turn that ground into "structure"
    h_src = (src @ up_frame(up_q).T)[:, 2]
    ground_src = float(np.percentile(h_src, c.ground_percentile))
    own_structure = h_src > ground_src + c.structure_height_tiles * unit_q
    own_ground = h_src <= ground_src
    own_structure_hue, n_own_structure = hue_src[own_structure], int(own_structure.sum())
    level = up_frame(up_m)  # the match's frame levelled: height is the last coordinate
    levelled_dst = dst @ level.T
    h_dst = levelled_dst[:, 2]
    ground = float(np.percentile(h_dst, c.ground_percentile))
    is_structure = h_dst > ground + c.structure_height_tiles * unit
    dst_ground = h_dst <= ground
    struct_tree = cKDTree(dst[is_structure]) if is_structure.sum() >= c.min_structure_points else None
    if struct_tree is None or n_own_structure < c.min_structure_points:
        return reject(f"structure overlap 0.00 < {c.min_structure_overlap}: too little structure "
                      f"({n_own_structure} / {int(is_structure.sum())} points)", planar_inliers=n_planar)
    reach = c.icp_radius_tiles * unit  # the ICP's first radius: how far it can pull a point

    def within_reach(G: np.ndarray) -> bool:
        """Whether ICP from guess ``G`` can reach verification: enough of the query within its first radius
        of the match, and enough of the query's structure within it of the match's structure (ICP refines
        locally: structure it cannot reach will not overlap at the inlier radius; measured on 1,538 guesses
        of 410 revisit candidates: every guess that ended at structure overlap >= 0.25 started at >= 0.36)."""
        cur = transform_points(G, src)
        d_s = struct_tree.query(cur[own_structure], distance_upper_bound=reach)[0]  # the smaller, more selective test
        if np.isfinite(d_s).mean() < c.min_structure_overlap:
            return False
        return bool(np.isfinite(tree.query(cur, distance_upper_bound=reach)[0]).mean() >= 0.5 * c.min_overlap)

    struct_hue = hue_dst[is_structure]
    radii = np.r_[np.geomspace(c.icp_radius_tiles, c.inlier_radius_tiles, c.icp_iterations),
                  [c.inlier_radius_tiles] * c.icp_final_iterations] * unit
    r_in = c.inlier_radius_tiles * unit
    same_place = 2 * c.icp_radius_tiles * unit  # two alignments further apart place the query elsewhere

    def apart(A: np.ndarray, B: np.ndarray) -> float:
        """How far alignments ``A`` and ``B`` [4,4] place the query's centroid from each other (match frame)."""
        centre = src.mean(0)[None]
        return float(np.linalg.norm(transform_points(A, centre) - transform_points(B, centre)))

    shared: dict = {}  # what every attempt derives alike, made once a guess is within reach: the match's ground
    # tree and normals, the query's points ICP fits, and the fits by their guess

    def attempt(guesses: dict[str, np.ndarray]) -> LoopResult:
        """Refine every guess within ICP's reach, rank the fits and verify the best (module docstring)."""
        # a guess is worth refining only if enough of the query, and of its structure, lies within ICP's reach
        guesses = {k: G for k, G in guesses.items() if within_reach(G)}
        if not guesses:
            return reject(f"overlap < {0.5 * c.min_overlap:.2f} or structure overlap < {c.min_structure_overlap} "
                          "within the ICP's reach at every initial guess", planar_inliers=n_planar)
        if not shared:
            shared["ground_dst_tree"] = cKDTree(levelled_dst[dst_ground, :2])
            shared["normals"] = _REUSED.get(match, points_match, ("normals", c.normals_k),
                                            lambda: point_normals(dst, tree, c.normals_k))
            fit_idx = np.arange(len(src))
            if 0 < c.icp_max_flat_points < int((~own_structure).sum()):
                flat = np.flatnonzero(~own_structure)
                fit_idx = np.sort(np.r_[np.flatnonzero(own_structure),
                                        flat[_subsample(len(flat), c.icp_max_flat_points, query)]])
            shared["fit_idx"] = fit_idx
            shared["fits"] = {}  # guesses that start alike (search peaks refined to one alignment) end alike
        ground_dst_tree, normals, fit_idx = shared["ground_dst_tree"], shared["normals"], shared["fit_idx"]
        fits: dict[bytes, _Fit | None] = shared["fits"]
        refined = []
        for name, G in guesses.items():
            key = G.tobytes()
            if key in fits:
                if fits[key] is not None:
                    refined.append(replace(fits[key], guess=name))
                continue
            fits[key] = None
            start = transform_points(G, src)

            def promising(T: np.ndarray, start: np.ndarray = start) -> bool:
                """Whether enough of the query's structure lies on the match's at the inlier radius yet."""
                d_s = struct_tree.query(transform_points(T, start[own_structure]), distance_upper_bound=r_in)[0]
                return bool(np.isfinite(d_s).mean() >= c.icp_check_share * c.min_structure_overlap)

            la = images.alignment if images is not None and name == LANDMARKS_GUESS else None
            rounds = 0 if at_cue and name != LANDMARKS_GUESS else c.icp_scale_rounds  # the cameras' scale held
            fit = icp_point_to_plane(start[fit_idx], tree, dst, normals, radii, rounds,
                                     check=(c.icp_check_iteration, promising) if c.icp_check_share > 0 else None,
                                     anchors=None if la is None else (transform_points(G, la.query_xyz), la.match_xyz),
                                     reciprocity=c.icp_reciprocity)
            if fit is None:
                log.debug("loop %d->%d guess %s: structure overlap below %.2f after %d ICP iterations", query, match,
                          name, c.icp_check_share * c.min_structure_overlap, c.icp_check_iteration)
                continue
            T, H, centre = fit
            cur = transform_points(T @ G, src)
            d, _ = tree.query(cur, distance_upper_bound=r_in)
            inl = np.isfinite(d)
            residual = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else np.inf
            lifted = _ground_offset(cur[own_ground] @ level.T, ground_dst_tree, levelled_dst[dst_ground, 2], unit)
            # the share of q's structure on m's structure, each point weighted by how its colour matches
            d_s, j = struct_tree.query(cur[own_structure], distance_upper_bound=r_in)
            near = np.isfinite(d_s)
            s_overlap = float(colour_match(own_structure_hue[near], struct_hue[j[near]]).sum() / n_own_structure)
            agree, cells = free_space_agreement(cur @ level.T, levelled_dst, c.agreement_cell_tiles * unit,
                                                ground + c.structure_height_tiles * unit, src_hue=hue_src,
                                                dst_hue=hue_dst, src_structure=own_structure)
            if cells < c.min_agreement_cells:
                agree = 0.0
            grounded = abs(lifted) <= c.structure_height_tiles * unit
            if off_cue(T @ G):
                grounded = False  # ICP left the cameras' scale: ranked last (and rejected if nothing is better)
            refined.append(_Fit(agree * s_overlap * grounded, s_overlap, float(inl.mean()), residual, T @ G, T, G, name,
                                H, centre, agree, cells, lifted))
            fits[key] = refined[-1]
            log.debug("loop %d->%d guess %s: free-space agreement %.2f (%d cells), structure overlap %.2f, overlap %.2f",
                      query, match, name, agree, cells, s_overlap, refined[-1].overlap)
        if not refined:
            return reject(f"structure overlap < {c.icp_check_share * c.min_structure_overlap:.2f} after "
                          f"{c.icp_check_iteration} ICP iterations at every initial guess", planar_inliers=n_planar)
        refined.sort(key=lambda f: (-f.rank, -f.overlap, f.residual))  # ties (all verified): the tighter fit
        best = refined[0]
        s_overlap, overlap, residual, Z, agree, cells = (best.structure_overlap, best.overlap, best.residual, best.Z,
                                                          best.agreement, best.cells)
        H = best.H
        ev = np.linalg.eigvalsh(level[:2] @ H[3:6, 3:6] @ level[:2].T)  # in-plane translation information
        constraint = float(ev[0] / max(ev[1], 1e-12))
        kw = dict(overlap=overlap, structure_overlap=s_overlap, agreement=agree, agreement_cells=cells,
                  residual=residual * float(s_m), planar_inliers=n_planar, guess=best.guess, constraint_ratio=constraint,
                  scale_cue=cue[0] if cue is not None and height_measured else 0.0)
        C = T_world_match @ Z @ sim3_inverse(T_world_query)  # the correction, world frame
        if overlap < c.min_overlap:
            return reject(f"overlap {overlap:.2f} < {c.min_overlap}", **kw)
        if s_overlap < c.min_structure_overlap:
            return reject(f"structure overlap {s_overlap:.2f} < {c.min_structure_overlap}", **kw)
        if abs(best.lifted) > c.structure_height_tiles * unit:
            return reject(f"grounds disagree: the query's lies {best.lifted * s_m:.2f} above the match's", **kw)
        if agree < c.min_agreement:
            return reject(f"free space disagrees: agreement {agree:.2f} < {c.min_agreement}", **kw)
        if residual > c.max_residual_tiles * unit:
            return reject(f"residual {residual * s_m:.3f} > {c.max_residual_tiles * tile_size:.3f}", **kw)
        beyond = outside_bounds(Z)
        if beyond:
            return reject(beyond, **kw)
        # every point, not the subsample ICP fits: a sparse cloud's footprint would lose its far cells
        shared_ground = footprint_overlap(transform_points(Z, points_query) @ level.T, points_match @ level.T, unit,
                                          c.footprint_min_points)
        kw.update(footprint_overlap=shared_ground)
        if shared_ground < c.min_footprint_overlap:
            return reject(f"footprints overlap {shared_ground:.2f} < {c.min_footprint_overlap}", **kw)
        for other in refined[1:]:  # a distinct alignment nearly as good: repetitive structure, ambiguous
            if apart(other.Z, Z) > same_place and other.rank >= c.ambiguity_ratio * best.rank:
                return reject(f"ambiguous: guess {other.guess} aligns elsewhere nearly as well ({other.rank:.2f} against "
                              f"{best.rank:.2f})", **kw)
        T_icp = best.T_icp
        if c.symmetric_scale and not (cue is not None and height_measured):  # no measured scale holds ICP's
            Z_sym = symmetric_scale(Z, src, dst, r_in, c.icp_final_iterations, c.normals_k, dst_tree=tree,
                                    reciprocity=c.icp_reciprocity)
            if outside_bounds(Z_sym) is None:  # the verified limits hold for the loop that enters the graph
                Z, T_icp = Z_sym, Z_sym @ sim3_inverse(best.G)
                C = T_world_match @ Z @ sim3_inverse(T_world_query)
        if images is not None:
            support = images.support(Z)
            kw.update(appearance=support.agreeing, appearance_comparable=support.comparable)
            if images.disagrees(support):
                return reject(f"images disagree: {support.agreeing} of {support.comparable} comparable landmarks "
                              "agree", **kw)
            kw.update(images_confirm=images.confirms(Z))
        info = loop_information(H, best.centre, T_icp, np.eye(4), best.G, max(residual, c.min_trans_sigma_tiles * unit),
                                np.r_[[c.floor_rot_sigma] * 3, [c.floor_trans_sigma_tiles * unit] * 3, c.floor_scale_sigma])
        return LoopResult(query, match, True, "accepted", Z, C, score=score, information=info, **kw)

    first = attempt(guesses)
    more = images.guesses() if images is not None else {}
    # a guess the refinement cannot bring within the limits would only cost an ICP (a periodic texture's
    # landmarks agree on alignments a period apart: most first-lap candidates had one, docs/backend.md)
    more = {k: G for k, G in more.items() if outside_bounds(G, reach=1.0) is None}
    if not more:
        return first
    if first.accepted:
        if first.images_confirm or not images.can_confirm or not c.images_second_opinion:
            return first
        # the points verified one alignment, the images agree on another: refined from theirs, it is the loop
        # where the points cannot tell the two apart (the same place, nearly as good) and the images confirm it
        second = attempt(more)
        if not second.accepted:
            log.debug("loop %d->%d: the images' own alignment does not verify (%s)", query, match, second.reason)
            return first
        distance = apart(second.T_match_query, first.T_match_query)
        ranks = [r.agreement * r.structure_overlap for r in (second, first)]  # as the fits were ranked (both grounded)
        wins = second.images_confirm and distance <= same_place and ranks[0] >= c.ambiguity_ratio * ranks[1]
        log.debug("loop %d->%d: the images' own alignment %s the points' (confirmed: %s, %.2f apart, ranked %.2f "
                  "against %.2f)", query, match, "replaces" if wins else "does not replace", second.images_confirm,
                  distance, *ranks)
        return second if wins else first
    # the images' guesses, only where the point guesses failed: wherever those verify, the result is theirs
    second = attempt({**guesses, **more})
    return second if second.accepted else first
