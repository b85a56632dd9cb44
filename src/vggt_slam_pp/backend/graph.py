"""The Sim(3) pose graph over submaps, solved with GTSAM (SPEC 3.11).

Nodes are ``T_world_submap`` (our convention: ``x_world = s R x_submap + t``). Edges measure
``T_i^-1 T_j`` (``T_ij``, submap j in submap i's frame): odometry edges with a Gaussian noise model
from their alignment residual, loop edges with a robust kernel (Cauchy by default: measured to reject a
bad loop a Huber kernel let through). The first submap of each connected part of the graph has a prior.

GTSAM's ``Similarity3(R, t_g, s)`` maps ``p -> s (R p + t_g)``, so ``t_g = t / s``; its tangent vector
is ``[omega (3), u (3), lambda (1)]``, which fixes the order of the sigmas below.

:meth:`PoseGraph.optimize` solves either every node (global) or a window of nodes with the others held
fixed (their factors become priors of negligible sigma): the cheap per-submap update. When the back-end's
last global solve would prune loops, they are weighed again with ``GraphConfig.final_kernel`` (GNC), and the
solution more loops agree with is kept (:meth:`PoseGraph.loop_agreement`): a revisit whose drift is larger than
the odometry sigmas say starts in Cauchy's flat tail, where it neither moves the map nor keeps its weight.

The odometry's scale walks (a monocular front-end's submaps drift above all in scale): its edges carry a prior
walk (``odometry_scale_sigma``, registration's drift model) until the heights or the loops' cycles measure it
(:meth:`PoseGraph.measured_scale_walk`), which then replaces it in every solve.

Height factors (:meth:`PoseGraph.add_height`): a camera carried at one height above its ground (a car,
a walker, a robot) measures each submap's scale on its own: ``s_i h_i = H``, where ``h_i`` is the
cameras' height in submap i's units and ``H`` that height in the world, one unknown per recording
(``group``). Odometry's scale is a random walk; these keep it from wandering. Each ``H`` is a node of
its own (a Sim(3) whose scale is ``H``; its rotation and translation are held at the identity) joined
to each of its submaps by a between-factor that constrains the scale alone; it is free in a global
solve and held in a windowed one.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from vggt_slam_pp.errors import BackendError
from vggt_slam_pp.geometry.lie import decompose_sim3, make_sim3, sim3_inverse, sim3_log

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GraphConfig:
    robust_kernel: str = "cauchy"  # "cauchy", "huber", "none" (loop factors) or "gnc" (graduated non-convexity,
    # truncated least squares: loops are in or out; see PoseGraph._solve_gnc)
    kernel_width: float = 0.5  # in whitened units: our sigmas are ~5x the actual spread (whitened residuals
    # ~0.2-0.5), so 0.5 is about the typical residual; 1.0 left wrong loops almost unweighted (docs/backend.md)
    continuation: bool = False  # cauchy: solve with Huber first, then Cauchy from there
    final_kernel: str | None = "gnc"  # when the end's global solve (robust_kernel) would prune loops, they are
    # weighed again with this one from there, and the solution more loops agree with is kept (Backend._final_kernel):
    # GNC (PoseGraph._solve_gnc) closes a revisit whose drift is larger than the odometry sigmas say, which Cauchy
    # leaves in its flat tail (docs/backend.md, "loop acceptance"); None: robust_kernel alone
    odometry_rot_sigma: float = 0.01  # rad, scaled up by the residual ratio
    odometry_scale_sigma: float = 0.05  # log-scale walk per submap until one is measured (the heights' variogram or
    # the loops' cycles, PoseGraph.measured_scale_walk): registration's drift model (RegistrationConfig.
    # scale_sigma_per_submap), what a monocular front-end's submaps drift in scale (docs/backend.md, "pose graph")
    odometry_scale_sigma_cameras: float = 0.01  # ... an edge from the shared keyframes' cameras measured its scale
    # there: this, a measured walk only widening it (as before session 61)
    min_odometry_scale_sigma: float = 0.01  # a measured walk is taken as at least this (the heights' and loops' own
    # errors, 1-2 %, are as large as what they would measure below it)
    odometry_trans_sigma_rel: float = 0.02  # of the step, plus the residual (PoseGraph.odometry_sigmas)
    odometry_trans_sigma_rel_cameras: float = 0.002  # the same for an edge from the shared keyframes' cameras
    # (a sparse backbone, "pose_scale" / "joint" / "anchored"), measured 0.05-0.45 % of the step on the castle walk and
    # EuRoC
    odometry_relative_sigma_floor: float = 0.002  # an edge that measures its own relative uncertainty (COLMAP's
    # joint link: the cameras' placement residual over their spread) has that as its rotation (rad) and log-scale
    # sigma, at least this much
    degraded_inflation: float = 100.0  # a degraded (extrapolated) odometry edge's scale sigma times this: its scale is
    # a guess (the two submaps' median depths)
    degraded_motion_inflation: float = 3.0  # ... and its rotation and translation sigmas (a linked edge's, without a
    # residual) times this: they are the shared keyframe's camera in both submaps (odometry.extrapolated_edge), not
    # its fit (extrapolated edges of the realistic profile, 94 in 80 runs: 0.39 deg and 1.4 % of the step off the
    # truth, median, as close as linked edges; at 100x, a scale set by heights or loops turned the rest of the run
    # about them, session 54; at 10x over a translation sigma as large as the step, the graph was cut in two there:
    # docs/experiments.md, session 62)
    loop_rot_sigma: float = 0.02
    loop_scale_sigma: float = 0.02
    loop_trans_sigma_tiles: float = 0.02  # floor of a loop's translation sigma, in tiles (ICP along a
    # street of facades is weakly constrained along the street: the RMS residual understates that)
    height_factors: bool = True  # a submap's scale from its cameras' height above its ground (PoseGraph.add_height)
    height_max_spread: float = 0.1  # a submap's cameras' height joins the graph while their own heights spread
    # (search.camera_heights) at most this much; only heights within RegistrationConfig.height_cue_max_spread (0.1)
    # also give loops their scale cue. A car's submap of tens of metres spreads 0.1-0.2 under the realistic profile
    # (pose error grows along it), and most of KITTI 00-driven's lost their heights; at 0.2 realistic KITTI 00-driven
    # seeds 0-7 went from median 78.6 % / worst 0.0 % to 84.7 / 76.8 %, but seed 0 accepted a look-alike 17 m along
    # the street and a hand-held held-out run fell 35.8 -> -23.0 %: not the default (docs/experiments.md, session 64)
    height_kernel_width: float = 2.0  # Cauchy width (whitened) of the height factors: a camera that changes
    # its height between submaps (a drone, a walker climbing stairs) loses its pull
    height_lags: int = 6  # the scale noise is measured over lags 1..6 submaps (PoseGraph.scale_noise)
    height_min_edges: int = 8  # differences per lag needed to measure it; until then no height factor
    min_height_sigma: float = 0.01  # a height is not trusted below 1 % (measured 0.2-5.6 % on the bench worlds)
    min_scale_drift: float = 0.02  # heights join the graph only when the odometry's scale is measured to walk at
    # least this much per submap: below it, the heights' own errors (correlated over neighbouring submaps,
    # 1-4 % on the bench worlds) are as large as what they would correct (default profile: KITTI 00-driven
    # ATE 2.64 -> 6.5 m with heights at 1.7 %; docs/experiments.md, session 21)
    max_odometry_scale_sigma: float = 0.2  # the measured odometry scale noise is capped here
    loop_scale_noise: bool = True  # without heights, the odometry's scale noise is measured from the loops' cycles
    # (PoseGraph.loop_scale_noise) and used where at least min_scale_drift: a hand-held or flying monocular camera's
    # odometry walks 6 % per submap in scale, and a 1 % sigma lets it bend the map against every loop (docs/backend.md,
    # "pose graph"); below it, the loops' own scale errors are as large as what it measures
    loop_scale_min_cycles: int = 5  # ... once the loops of this many queries lie on chains of odometry
    shared_loops: bool = True  # the loops of one query count as one measurement (PoseGraph.loop_shares)
    max_iterations: int = 100
    gnc_inlier_probability: float = 0.99  # gnc: a loop is an inlier within this chi-square quantile


@dataclass(frozen=True)
class Edge:
    """A relative measurement ``T_ij`` between nodes i and j, with 7 sigmas ``[rot 3, trans 3, scale]``
    or, when ``information`` (7x7, same order) is given, that full information matrix instead."""

    i: int
    j: int
    T_ij: np.ndarray
    sigmas: np.ndarray
    kind: str  # "odometry" or "loop"
    info: dict = field(default_factory=dict)
    information: np.ndarray | None = None

    def whitened_norm(self, r: np.ndarray) -> float:
        """Mahalanobis length of a tangent residual ``r`` [7] under this edge's noise."""
        if self.information is not None:
            return float(np.sqrt(max(r @ self.information @ r, 0.0)))
        return float(np.linalg.norm(r / self.sigmas))


def to_gtsam(T: np.ndarray):
    import gtsam

    s, R, t = decompose_sim3(T)
    return gtsam.Similarity3(gtsam.Rot3(R), np.asarray(t, float) / float(s), float(s))


def from_gtsam(S) -> np.ndarray:
    return make_sim3(S.scale(), S.rotation().matrix(), S.scale() * np.asarray(S.translation()))


def _key(i: int) -> int:
    import gtsam

    return gtsam.symbol("s", i)


def _height_key(group: int) -> int:
    import gtsam

    return gtsam.symbol("h", group)


class PoseGraph:
    """Owns the poses and edges; not thread-safe (the back-end worker alone touches it)."""

    def __init__(self, config: GraphConfig | None = None) -> None:
        import gtsam  # noqa: F401  - loaded now, not at the first loop (~40 MB: a step in the memory trace)

        self.config = config or GraphConfig()
        self.poses: dict[int, np.ndarray] = {}
        self.edges: list[Edge] = []
        self.last_solve: dict = {}
        # held at their pose in every solve, besides the first node of each connected part of the graph
        # (its gauge: a recording that no loop has linked to the map yet is a part of its own): the nodes
        # of a map used for localisation only
        self.anchors: set[int] = set()
        self.heights: dict[int, tuple[float, int]] = {}  # node -> (its cameras' height in its units, group)
        self.height_refs: dict[int, float] = {}  # group -> H, its cameras' height in the world's units
        self.heights_weighed = False  # a solve has weighed height factors (Backend.finish then solves globally)
        # group (None: all) -> (its heights when measured, height_variogram())
        self._variogram_at: dict[int | None, tuple[int, tuple[float, float] | None]] = {}
        self._loop_noise_at: tuple[tuple | None, float | None] = (None, None)  # (loops when measured, the result)

    # -- building -------------------------------------------------------------------------------
    def add_node(self, i: int, T_world_submap: np.ndarray) -> None:
        if i in self.poses:
            raise BackendError(f"submap {i} is already in the pose graph")
        if not np.isfinite(T_world_submap).all():
            raise BackendError(f"submap {i}: non-finite initial pose")
        self.poses[i] = np.asarray(T_world_submap, float).copy()

    def odometry_sigmas(self, T_ij: np.ndarray, residual: float, degraded: bool = False,
                        from_cameras: bool = False, relative: float = float("nan"), fitted: int = 0) -> np.ndarray:
        """Sigmas [7] of an odometry edge ``T_ij`` with its ``residual`` (the shared points' RMS misfit under it,
        i's units): translation ``odometry_trans_sigma_rel`` of the step (the errors the points share: their
        depth's) plus the residual; ``fitted`` > 0: ``T_ij`` was fitted to that many of those points, so their
        misfit is the noise the fit averaged, and counts as ``residual / sqrt(fitted)`` (a camera-measured edge's
        points were not fitted: their misfit is its error at their distance, and counts whole).
        ``from_cameras``: an edge measured from the shared keyframes' cameras (a sparse backbone's),
        ``odometry_trans_sigma_rel_cameras`` of it, and ``odometry_scale_sigma_cameras`` in scale.
        ``relative``: the edge's own relative uncertainty, when it measures one (rotation and log-scale sigma,
        at least ``odometry_relative_sigma_floor``; otherwise ``odometry_rot_sigma`` / ``odometry_scale_sigma``).
        ``degraded``: the rotation and translation sigmas times ``degraded_motion_inflation`` (with no residual
        term when it is unknown: an extrapolated edge's motion is a camera's), the scale's ``degraded_inflation``."""
        c = self.config
        s, _, t = decompose_sim3(T_ij)
        step = float(np.linalg.norm(t))
        if not np.isfinite(residual):
            residual = 0.0 if degraded else max(step, 1.0)  # unknown: as large as the step
        elif fitted > 0:
            residual = float(residual) / np.sqrt(fitted)
        rel = c.odometry_trans_sigma_rel_cameras if from_cameras else c.odometry_trans_sigma_rel
        trans = rel * step + max(float(residual), 1e-4 * max(step, 1e-3), 1e-9)
        rot, scale = c.odometry_rot_sigma, c.odometry_scale_sigma_cameras if from_cameras else c.odometry_scale_sigma
        if np.isfinite(relative):
            rot = scale = max(float(relative), c.odometry_relative_sigma_floor)
        sig = np.r_[[rot] * 3, [trans / max(float(s), 1e-9)] * 3, scale]
        if degraded:
            sig = sig * np.r_[[c.degraded_motion_inflation] * 6, c.degraded_inflation]
        return sig

    def add_height(self, i: int, height: float, group: int) -> None:
        """Node ``i``'s cameras stand ``height`` (its own units) above its ground; ``group``: the recording
        (one rig, one height). The group's world height starts at this node's current ``s_i height``."""
        if i not in self.poses:
            raise BackendError(f"height of submap {i}: not in the pose graph")
        if not (np.isfinite(height) and height > 0):
            raise BackendError(f"height of submap {i} must be positive and finite, got {height}")
        self.heights[i] = (float(height), int(group))
        self.height_refs.setdefault(int(group), float(decompose_sim3(self.poses[i])[0]) * float(height))

    def drop_heights(self, group: int) -> int:
        """Remove the heights of recording ``group`` and its world height (they give no scale); how many."""
        kept = {i: h for i, h in self.heights.items() if h[1] != group}
        dropped, self.heights = len(self.heights) - len(kept), kept
        self.height_refs.pop(int(group), None)
        self._variogram_at = {}
        return dropped

    def add_edge(self, edge: Edge) -> None:
        for n in (edge.i, edge.j):
            if n not in self.poses:
                raise BackendError(f"edge {edge.i}->{edge.j}: submap {n} is not in the pose graph")
        if edge.sigmas.shape != (7,) or not np.all(edge.sigmas > 0):
            raise BackendError(f"edge {edge.i}->{edge.j}: sigmas must be 7 positive numbers")
        if edge.information is not None and (edge.information.shape != (7, 7) or
                                             np.linalg.eigvalsh(edge.information).min() <= 0):
            raise BackendError(f"edge {edge.i}->{edge.j}: information must be a 7x7 positive-definite matrix")
        self.edges.append(edge)

    # -- solving --------------------------------------------------------------------------------
    def height_variogram(self, group: int | None = None) -> tuple[float, float] | None:
        """``(sigma_o, sigma_h)`` measured from the heights (of recording ``group``; None: every recording's):
        the odometry's scale random walk per submap and the heights' own noise (log-scale), or None while too few
        heights lie on chains of odometry to measure them (fewer than ``height_min_edges`` differences at 3 lags
        or more).

        Along a chain of non-degraded odometry edges, at the submaps with heights, ``y_k = log(S_k h_k)``
        (``S_k`` the chained odometry scale) is ``log H`` plus the odometry's scale random walk plus the heights'
        own noise, so the robust variance of ``y_k - y_{k-L}`` is ``L sigma_o^2 + 2 sigma_h^2`` (a variogram): a
        line fitted over lags 1..``height_lags`` gives both. Cached: measured again when the number of heights
        has grown by 5 %."""
        c = self.config
        heights = {k: h for k, h in self.heights.items() if group is None or h[1] == group}
        n = len(heights)
        cached = self._variogram_at.get(group)
        if cached and n < cached[0] * 1.05 + 1:
            return cached[1]
        cum, chain = self._odometry_chains()
        y = {k: cum[k] + float(np.log(h)) for k, (h, _) in heights.items()}
        lags, var = [], []
        for L in range(1, c.height_lags + 1):
            d = np.array([y[k] - y[k - L] for k in y if (k - L) in y and chain[k - L] == chain[k]
                          and heights[k - L][1] == heights[k][1]])
            if len(d) >= c.height_min_edges:
                lags.append(L)
                var.append((1.4826 * float(np.median(np.abs(d - np.median(d))))) ** 2)
        out = None
        if len(lags) >= 3:
            (a, b), *_ = np.linalg.lstsq(np.c_[np.ones(len(lags)), lags], np.asarray(var), rcond=None)
            out = (float(np.sqrt(max(b, 0.0))), max(float(np.sqrt(max(a / 2, 0.0))), c.min_height_sigma))
            log.debug("scale noise from %d heights: odometry %.4f, heights %.4f", n, *out)
        self._variogram_at[group] = (n, out)
        return out

    def _odometry_chains(self) -> tuple[dict[int, float], dict[int, int]]:
        """Per node: the chained log odometry scale along its run of non-degraded odometry edges, and the run's
        first node."""
        odo = {e.j: e for e in self.edges if e.kind == "odometry" and e.j == e.i + 1}
        cum: dict[int, float] = {}
        chain: dict[int, int] = {}
        for k in sorted(self.poses):
            e = odo.get(k)
            if e is not None and (k - 1) in cum and not e.info.get("degraded"):
                cum[k], chain[k] = cum[k - 1] + float(np.log(decompose_sim3(e.T_ij)[0])), chain[k - 1]
            else:
                cum[k], chain[k] = 0.0, k
        return cum, chain

    def loop_scale_noise(self) -> float | None:
        """The odometry's scale random walk per submap (log-scale sigma) measured from the loops, or None while
        the loops of fewer than ``loop_scale_min_cycles`` queries lie on one chain of non-degraded odometry with
        their match.

        A loop ``m -> q`` and the odometry from ``m`` to ``q`` close a cycle whose log-scale residual ``r`` is the
        odometry's walk over ``n = q - m`` submaps plus the loop's own error: ``E[r^2] = n sigma_o^2 + sigma_l^2``.
        ``sigma_o^2`` is taken as the median of ``r^2 / n`` over the queries (each query's loops share its errors:
        their median counts once) divided by 0.455 (about the median of a chi-square with one degree of freedom); the
        loops' own error and a few wrong loops inflate it little. Cached until the loop edges change."""
        loops = [e for e in self.edges if e.kind == "loop"]
        key = tuple((e.i, e.j) for e in loops)  # (a new submap's odometry edge closes no cycle)
        if self._loop_noise_at[0] == key:
            return self._loop_noise_at[1]
        out = None
        if len({e.j for e in loops}) >= self.config.loop_scale_min_cycles:
            cum, chain = self._odometry_chains()
            per_query: dict[int, list[float]] = {}
            for e in loops:
                m, q = min(e.i, e.j), max(e.i, e.j)
                if m == q or chain.get(m) != chain.get(q):
                    continue
                r = float(np.log(decompose_sim3(e.T_ij)[0])) * (1 if e.i == m else -1) - (cum[q] - cum[m])
                per_query.setdefault(q, []).append(r * r / (q - m))
            if len(per_query) >= self.config.loop_scale_min_cycles:
                out = float(np.sqrt(np.median([np.median(v) for v in per_query.values()]) / 0.455))
                log.debug("odometry scale noise from %d loops: %.4f", sum(map(len, per_query.values())), out)
        self._loop_noise_at = (key, out)
        return out

    def scale_noise(self) -> tuple[float, float] | None:
        """``(odometry scale sigma, height sigma)`` for the solve, from :meth:`height_variogram`, or None (not
        measured yet, or odometry's scale walks less than ``min_scale_drift``: the heights then stay out of the
        graph). Heights are used only when ``sigma_o`` is at least ``min_scale_drift`` (a monocular front-end
        that drifts 6 % per submap, the realistic profile: yes; the default profile's, under 1 %: no), weighted
        by the measured ratio: the odometry sigma is ``odometry_scale_sigma`` or the measured one if larger (up to
        ``max_odometry_scale_sigma``), the height sigma keeps the measured ratio to it."""
        c = self.config
        measured = self.height_variogram()
        if measured is None or measured[0] < c.min_scale_drift or measured[0] <= 0.0:
            return None  # (no walk measured at all: the heights' weight relative to it is undefined)
        sigma_o, sigma_h = measured
        used = float(np.clip(sigma_o, c.min_odometry_scale_sigma, c.max_odometry_scale_sigma))
        return used, max(sigma_h * used / sigma_o, c.min_height_sigma)

    def measured_scale_walk(self) -> tuple[float, str] | None:
        """The odometry's log-scale walk per submap as measured, and by what: the heights' variogram
        (:meth:`height_variogram`) or else the loops' cycles (:meth:`loop_scale_noise`); a walk under
        ``min_scale_drift`` (the loops' and heights' own errors weigh as much) is taken as ``min_odometry_scale_sigma``,
        one over it is capped at ``max_odometry_scale_sigma``. None: nothing measures it yet (the odometry edges keep
        the prior ``odometry_scale_sigma``)."""
        c = self.config
        walk, by = None, None
        if c.height_factors and self.heights:
            measured = self.height_variogram()
            walk, by = (measured[0], "heights") if measured is not None else (None, None)
        if walk is None and c.loop_scale_noise:
            walk, by = self.loop_scale_noise(), "loops"
        if walk is None:
            return None
        return (c.min_odometry_scale_sigma if walk < c.min_scale_drift else min(walk, c.max_odometry_scale_sigma)), by

    def loop_shares(self) -> dict[int, int]:
        """Query node -> how many loop edges it has. The loops of one query are registrations of the same points,
        so they share its errors (its scale, its ground, its own up): in the solve they count as one
        measurement together, each with its information divided by that number (``GraphConfig.shared_loops``)."""
        out: dict[int, int] = {}
        if self.config.shared_loops:
            for e in self.edges:
                if e.kind == "loop":
                    out[e.j] = out.get(e.j, 0) + 1
        return out

    def _noise(self, edge: Edge, kernel: str, scale_sigma: float | None = None, share: int = 1):
        """``scale_sigma``: the odometry's measured scale walk (:meth:`scale_noise`, :meth:`measured_scale_walk`): it
        replaces the prior in the scale sigma of an edge built with it (``info["prior_scale"]``), and is a floor
        for one that measured its own where it is over ``min_odometry_scale_sigma`` (a walk measured under the
        gate leaves such an edge as it is);
        ``share``: a loop's information divided by this (:meth:`loop_shares`), its robust kernel narrowed to match."""
        import gtsam

        if edge.information is not None:
            base = gtsam.noiseModel.Gaussian.Information(np.asarray(edge.information, float) / share)
        else:
            sig = np.asarray(edge.sigmas, float) * np.sqrt(share)
            if scale_sigma is not None and edge.kind == "odometry":
                sig = sig.copy()
                if edge.info.get("prior_scale"):  # the prior walk replaced by the measured one (a degraded edge's
                    # inflation kept)
                    sig[6] = scale_sigma * (self.config.degraded_inflation if edge.info.get("degraded") else 1.0)
                elif scale_sigma > self.config.min_odometry_scale_sigma:  # the edge measured its own scale
                    sig[6] = max(sig[6], scale_sigma)  # uncertainty: at least a walk measured over the floor
            base = gtsam.noiseModel.Diagonal.Sigmas(sig)
        if edge.kind != "loop" or kernel == "none":
            return base
        k = self.config.kernel_width / np.sqrt(share)  # the same robust weight at the same residual, 1 / share of
        # the cost: the kernel still judges each loop by its own sigmas
        est = {"cauchy": gtsam.noiseModel.mEstimator.Cauchy, "huber": gtsam.noiseModel.mEstimator.Huber}
        return gtsam.noiseModel.Robust.Create(est[kernel].Create(k), base)

    def optimize(self, window: set[int] | None = None, kernel: str | None = None) -> dict[int, np.ndarray]:
        """Optimise the nodes in ``window`` (all when None), holding the others fixed, with the loops'
        ``kernel`` (default: ``GraphConfig.robust_kernel``).

        Returns the new poses of the optimised nodes (also stored in :attr:`poses`).
        """
        import gtsam

        t0 = time.perf_counter()
        if not self.poses:
            return {}
        kernel = kernel or self.config.robust_kernel
        if kernel not in ("cauchy", "huber", "none", "gnc"):
            raise BackendError(f"unknown robust kernel {kernel!r}; use gnc, cauchy, huber or none")
        # Cauchy is not convex: a true loop closing a large drift starts far out in its tail and is
        # ignored. Continuation (optional) solves with Huber (convex) first, then with Cauchy from there;
        # a wrong loop keeps a large residual and loses its weight in the second solve. On the demo it
        # made the result worse (see docs/backend.md), so it is off by default.
        stages = ["huber", "cauchy"] if kernel == "cauchy" and self.config.continuation else [kernel]
        free = set(self.poses) if window is None else {i for i in window if i in self.poses}
        free -= self.anchors
        touching = [e for e in self.edges if e.i in free or e.j in free]
        used: set[int] = set(free)
        for e in touching:
            used.update((e.i, e.j))
        fixed = used - free
        fixed.update(used & (set(self.component_roots().values()) | self.anchors))
        if not fixed:  # a window disconnected from the anchor: pin its oldest node
            fixed.add(min(used))
        tight = gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)
        values = gtsam.Values()
        for i in sorted(used):
            values.insert(_key(i), to_gtsam(self.poses[i]))
        scale_model = self.scale_noise() if self.config.height_factors and self.heights else None
        heights = {i: self.heights[i] for i in sorted(free & set(self.heights))} if scale_model is not None else {}
        self.heights_weighed = self.heights_weighed or bool(heights)
        groups = sorted({g for _, g in heights.values()})
        for g in groups:
            values.insert(_height_key(g), gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), self.height_refs[g]))
        err0 = None
        iterations = 0
        scale_sigma, height_sigma = scale_model if heights else (None, None)
        measured_by = "heights" if heights else None
        if scale_sigma is None:
            scale_sigma, measured_by = self.measured_scale_walk() or (None, None)
        shares = self.loop_shares()
        for stage in stages:
            graph = gtsam.NonlinearFactorGraph()
            for e in touching:  # (GNC's one inlier bound is in each loop's own sigmas: not shared there)
                noise = self._noise(e, "none" if stage == "gnc" else stage, scale_sigma,
                                    shares.get(e.j, 1) if e.kind == "loop" and stage != "gnc" else 1)
                graph.add(gtsam.BetweenFactorSimilarity3(_key(e.i), _key(e.j), to_gtsam(e.T_ij), noise))
            for i in sorted(fixed):
                graph.add(gtsam.PriorFactorSimilarity3(_key(i), to_gtsam(self.poses[i]), tight))
            self._add_heights(graph, heights, groups, window is None, "none" if stage == "gnc" else stage, height_sigma)
            if err0 is None:
                err0 = graph.error(values)
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(self.config.max_iterations)
            if stage == "gnc":
                values = self._solve_gnc(graph, values, params, [e.kind == "loop" for e in touching])
                continue
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            values = opt.optimize()
            iterations += int(opt.iterations())
        result = values
        out = {}
        for i in free:
            if i in used:
                T = from_gtsam(result.atSimilarity3(_key(i)))
                if not np.isfinite(T).all():
                    raise BackendError(f"pose-graph optimisation produced a non-finite pose for submap {i}")
                out[i] = T
        self.poses.update(out)
        if window is None:
            for g in groups:
                self.height_refs[g] = float(result.atSimilarity3(_height_key(g)).scale())
        self.last_solve = {"nodes": len(used), "free": len(out), "factors": graph.size(),
                           "error_before": float(err0), "error_after": float(graph.error(result)),
                           "iterations": iterations, "seconds": time.perf_counter() - t0,
                           "global": window is None, "height_factors": len(heights),
                           "odometry_scale_sigma": scale_sigma, "odometry_scale_measured_by": measured_by,
                           "height_sigma": height_sigma}
        return out

    def _add_heights(self, graph, heights: dict[int, tuple[float, int]], groups: list[int], free_refs: bool,
                     kernel: str, sigma: float) -> None:
        """The height factors of ``heights`` (log-scale ``sigma``) and a prior on each group's world height
        (free in scale when ``free_refs``, else held); the factors robust (Cauchy) unless ``kernel`` is
        ``none``: under GNC (which passes ``none``) they are plain Gaussian known inliers, its truncated loss
        switching loops only."""
        import gtsam

        c = self.config
        for g in groups:
            sig = np.r_[[1e-6] * 6, 1e3 if free_refs else 1e-6]
            graph.add(gtsam.PriorFactorSimilarity3(_height_key(g), gtsam.Similarity3(
                gtsam.Rot3(), np.zeros(3), self.height_refs[g]), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        base = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[1e6] * 6, sigma])
        noise = base if kernel == "none" else gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(c.height_kernel_width), base)
        for i, (h, g) in heights.items():
            graph.add(gtsam.BetweenFactorSimilarity3(_height_key(g), _key(i),
                                                     gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), 1.0 / h), noise))

    def component_roots(self) -> dict[int, int]:
        """Each node's connected part of the graph (odometry and loop edges), named by its first node; the
        first node of each part is its gauge in a solve."""
        parent = {i: i for i in self.poses}

        def root(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for e in self.edges:
            a, b = root(e.i), root(e.j)
            if a != b:
                parent[max(a, b)] = min(a, b)
        return {i: root(i) for i in self.poses}

    def _solve_gnc(self, graph, values, lm_params, is_loop: list[bool]):
        """Graduated non-convexity (GTSAM ``GncLMOptimizer``, truncated least squares) over plain Gaussian
        factors: odometry and priors are known inliers; each loop ends with weight 1 (inlier) or 0. GNC
        starts from the convex problem, so a true loop that moves the map by tens of metres is not lost in
        a kernel's flat tail, and a loop that the odometry and the other loops cannot explain within its
        chi-square bound (``gnc_inlier_probability``) is switched off."""
        import gtsam

        params = gtsam.GncLMParams(lm_params)
        params.setLossType(gtsam.GncLossType.TLS)
        params.setKnownInliers([k for k in range(graph.size()) if k >= len(is_loop) or not is_loop[k]])
        opt = gtsam.GncLMOptimizer(graph, values, params)
        opt.setInlierCostThresholdsAtProbability(self.config.gnc_inlier_probability)
        return opt.optimize()

    def loop_agreement(self) -> int:
        """How many loops the current poses agree with: each loop's residual within its chi-square bound
        (``gnc_inlier_probability``, 7 degrees of freedom, the loop's own sigmas)."""
        return int(sum(self.loop_weights("gnc")))

    def loop_weights(self, kernel: str | None = None) -> list[float]:
        """Robust weight (0..1) of every loop edge at the current poses under ``kernel`` (default:
        ``GraphConfig.robust_kernel``), in edge order (for reports)."""
        out = []
        k, kernel = self.config.kernel_width, kernel or self.config.robust_kernel
        for e in self.edges:
            if e.kind != "loop":
                continue
            r = sim3_log(sim3_inverse(e.T_ij) @ sim3_inverse(self.poses[e.i]) @ self.poses[e.j])
            d = e.whitened_norm(r)  # same [omega, u, lambda] order as the sigmas
            if kernel == "gnc":  # truncated least squares: in or out by the chi-square bound
                out.append(float(d**2 <= chi2.ppf(self.config.gnc_inlier_probability, 7)))
            else:
                out.append(1.0 / (1.0 + (d / k) ** 2) if kernel == "cauchy" else (1.0 if d <= k or kernel == "none"
                                                                                  else k / d))
        return out
