"""The back-end's synchronous core: covisibility -> loop registration -> Sim(3) pose graph (SPEC 3.8-3.12).

:class:`Backend` orchestrates, for every new submap (:class:`SubmapMessage`, points read from the map's
store), over one :class:`~vggt_slam_pp.backend.map.Map`:

1. its node enters the map's graph at ``T_world_prev T_prev_curr`` (:meth:`Map.add_submap`);
2. its points (world frame, subsampled) go through the covisibility stage
   (:class:`~vggt_slam_pp.backend.places.CovisibilityStage`): DEM layer, descriptors, HNSW voting, VLAD
   candidates; its layer joins the map's gallery;
3. the candidates are registered, verified and accepted or kept pending by the
   :class:`~vggt_slam_pp.backend.loops.LoopCloser`;
4. with a new loop the graph is optimised: globally when the loop closes further back than
   ``far_loop_submaps``, otherwise over the window (the new submap, its loop partners and their
   neighbours) with the rest fixed; at :meth:`finish`, globally, after which loops the robust graph
   switched off (weight < ``min_loop_weight``) leave it and are reported as rejected;
5. layers of submaps that moved by more than ``relocate_min_shift_tiles`` are re-rasterised and
   re-indexed (:meth:`Map.refresh_layers`); a :class:`PoseSnapshot` is published.

A recording added to a saved map (:meth:`Backend.seed_map`) is a separate part of the graph until loops
from several of its submaps agree on where it lies (:meth:`LoopCloser.placement`); docs/backend.md, "Maps".

The same object runs inline (synchronous mode, tests) or inside the worker process
(:mod:`vggt_slam_pp.backend.worker`).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from vggt_slam_pp.backend.config import BackendConfig, FaultConfig
from vggt_slam_pp.backend.graph import Edge, PoseGraph
from vggt_slam_pp.backend.loops import PENDING, LoopCloser
from vggt_slam_pp.backend.map import Map, subsample, subsample_indices
from vggt_slam_pp.backend.places import CovisibilityStage, Gallery, camera_depth
from vggt_slam_pp.backend.registration import LoopResult
from vggt_slam_pp.backend.search import camera_heights, point_cameras
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.dem import PlaneConfig
from vggt_slam_pp.errors import DemError
from vggt_slam_pp.frontend.types import OdometryEdge
from vggt_slam_pp.geometry.lie import decompose_sim3, transform_points
from vggt_slam_pp.resources import rss_mb
from vggt_slam_pp.retrieval.index import CovisibilityEdge

log = logging.getLogger(__name__)

STAGES = ("covisibility_s", "registration_s", "optimization_s", "relocate_s")  # the per-submap timings by stage

__all__ = ["PENDING", "Backend", "BackendConfig", "BackendResult", "FaultConfig", "PoseSnapshot", "SubmapMessage"]


@dataclass(frozen=True)
class SubmapMessage:
    """A new submap for the back-end; its points (submap frame) are already in the store."""

    submap_id: int
    camera_centers: np.ndarray  # [S,3] submap frame
    odometry: OdometryEdge | None  # from the previous submap (None for the first)
    points_per_camera: np.ndarray | None = None  # [S] how many of the stored points (in order) each keyframe gave


@dataclass(frozen=True)
class PoseSnapshot:
    """Immutable view of the optimised poses after one back-end step."""

    version: int
    poses: MappingProxyType  # submap id -> T_world_submap [4,4] (read-only arrays)
    loops_accepted: int
    last_submap: int
    rss_mb: float = 0.0  # resident memory of the back-end's process when the snapshot was taken


@dataclass
class BackendResult:
    """What the back-end hands to the outputs (:mod:`vggt_slam_pp.outputs` serialises it)."""

    poses: dict[int, np.ndarray]  # submap id -> optimised T_world_submap [4,4]
    odometry_poses: dict[int, np.ndarray]  # submap id -> T_world_submap of odometry alone
    edges: list[Edge]  # the pose graph's odometry and loop edges
    loop_weights: list[float]  # robust weight of each loop edge, in the order of ``edges``
    covisibility: list[CovisibilityEdge]
    loops: list[LoopResult]  # every verified candidate, accepted or not, with its reason
    seconds_per_submap: list[float]  # each submap's back-end time, its query included wherever it ran
    timings: dict[str, float]
    plane: dict | None
    tile_size: float | None
    mpp: float | None
    peak_rss_mb: float = 0.0  # of the back-end's process
    memory_trace: list = field(default_factory=list)  # (submaps done, RSS MiB of the back-end's process)
    placed: list[int] = field(default_factory=list)  # submaps whose poses are in the map's frame
    skipped: list[int] = field(default_factory=list)  # submaps whose query was deferred (back-end behind)
    heights: dict[int, float] = field(default_factory=dict)  # submap id -> its cameras' height (its units)
    height_refs: dict[int, float] = field(default_factory=dict)  # recording (segment) -> that height in the world
    cpu_seconds_per_submap: list[float] = field(default_factory=list)  # the same, in the back-end thread's CPU time:
    # its work, without the time it waited for a CPU the front-end held (the worker runs at idle priority)
    stage_seconds_per_submap: dict[str, list[float]] = field(default_factory=dict)  # stage (STAGES) -> each
    # submap's wall time in it, its deferred query included (where a long run's time goes, window by window)
    odometry_scale_sigma: float | None = None  # the odometry's log-scale sigma per submap in the last solve where it
    # was measured (GraphConfig: from the heights or the loops), None: the configured one
    odometry_scale_measured_by: str | None = None  # "heights" or "loops"


class Backend:
    def __init__(self, config: BackendConfig, store: SubmapStore, encoder=None) -> None:
        from vggt_slam_pp.errors import RetrievalError
        from vggt_slam_pp.plugins import ENCODERS, load

        self.config = config
        if encoder is None:
            encoder = load(ENCODERS, config.encoder, "encoder", RetrievalError).from_config(config.encoder_weights)
        gallery = Gallery(encoder, config.covisibility)
        self.map = Map(PoseGraph(config.graph), store, gallery, config.dem_max_points,
                       config.relocate_min_shift_tiles, config.relocate_budget, config.relocate_per_submap,
                       config.altitude_min_pairs, config.altitude_explained)
        self.stage = CovisibilityStage(gallery)
        self.closer = LoopCloser(config, self.map)
        self.covisibility: list[CovisibilityEdge] = []
        self.seconds: list[float] = []
        self.cpu_seconds: list[float] = []  # the same, CPU time of the back-end's thread
        self.stage_seconds: dict[str, list[float]] = {k: [] for k in STAGES}  # the same, by stage
        self.timings = {**dict.fromkeys(STAGES, 0.0), "deferred_s": 0.0}
        self.memory_trace: list[tuple[int, float]] = []
        self.skipped: list[int] = []  # submaps whose query was deferred (a worker catching up)
        self._deferred: deque[tuple[int, np.ndarray, int]] = deque()  # (submap, camera centres, its entry in
        # ``seconds``: a deferred query's time counts for its submap) still to query
        # (submap, camera centres, points per camera): submaps waiting for the DEM grid (BackendConfig.grid_submaps),
        # in order
        self._held: list[tuple[int, np.ndarray | None, np.ndarray | None]] = []
        self._version = 0

    def seed_map(self, saved, localize_only: bool = False) -> None:
        """Start from a saved map (:meth:`Map.seed`)."""
        self.map.seed(saved, localize_only)

    # -- the per-submap step --------------------------------------------------------------------
    def add_submap(self, msg: SubmapMessage, query: bool = True) -> PoseSnapshot:
        """One new submap. ``query=False`` (a worker catching up): it joins the graph and its layer the
        gallery now, and its query of the map for loops is deferred (:meth:`query_deferred`, run when the
        worker is idle and at :meth:`finish`; listed in :attr:`BackendResult.skipped`). While deferred queries
        wait, a new one waits behind them: queries run in submap order, so each has its predecessor's matches
        (the sequence prior) and the corrections of the loops before it (proximity)."""
        t_start, c_start = time.perf_counter(), time.thread_time()
        stages = self._stage_totals()
        query = query and not self._deferred
        if self.config.faults.slow_submap_s > 0:
            time.sleep(self.config.faults.slow_submap_s)
        m, sid = self.map, msg.submap_id
        points = m.store.get(sid)
        m.add_submap(sid, msg.odometry, points, msg.camera_centers)
        self._measure_height(sid, points, msg.camera_centers, msg.points_per_camera)
        accepted: list[LoopResult] = []
        first = m.gallery.grid is None
        if len(points) >= 3 and not query and not first:
            t0 = time.perf_counter()
            if m.index_new:
                m.index_layer(sid, m.gallery.describe(sid, m.layer_points(sid)))
            self.skipped.append(sid)
            self._deferred.append((sid, msg.camera_centers, len(self.seconds)))
            self.timings["covisibility_s"] += time.perf_counter() - t0
        elif len(points) >= 3 and first:
            need = PlaneConfig().min_points
            if len(points) < need:  # nor may it vote on the tile (a start without parallax)
                log.warning("submap %d: no DEM plane from its %d points (a plane needs %d); it joins the map without "
                            "a DEM layer, and the next submap is tried", sid, len(points), need)
            else:
                self._held.append((sid, msg.camera_centers, msg.points_per_camera))
                if len(self._held) >= self._grid_submaps():
                    self._fit_grid()
        elif len(points) >= 3:
            accepted = self._query(sid, msg.camera_centers, points, index=m.index_new)
        if accepted:
            self._solve_for(sid, accepted)
        elif m.stale:  # layers a solve moved beyond the refresh budget: the next ones now
            t0 = time.perf_counter()
            m.refresh_layers(set())
            self.timings["relocate_s"] += time.perf_counter() - t0
        self.seconds.append(time.perf_counter() - t_start)
        self.cpu_seconds.append(time.thread_time() - c_start)
        for k, v in self._stage_totals(stages).items():
            self.stage_seconds[k].append(v)
        snap = self.snapshot()
        if len(self.seconds) % 10 == 0:
            self.memory_trace.append((len(self.seconds), snap.rss_mb))
        return snap

    def _grid_submaps(self) -> int:
        """How many submaps the DEM plane and grid are fit to: ``BackendConfig.grid_submaps`` for an "auto" tile
        (a depth that one submap may not represent), else the first one's plane alone."""
        return max(1, self.config.grid_submaps) if self.map.gallery.config.dem.tile_size == "auto" else 1

    def _fit_grid(self) -> None:
        """Fit the DEM plane and grid to the held submaps together (:attr:`_held`, their points and cameras at
        their current poses), then run their queries in order (each one's loops solved before the next) and
        measure their heights. Where their points hold no ground plane (a few points: a camera without
        parallax, a start the backbone could not reconstruct) the oldest joins the graph without a layer, with
        a warning, and the rest wait for the next submap."""
        m, t0 = self.map, time.perf_counter()
        held = self._held
        points = [m.layer_points(sid) for sid, _, _ in held]
        cams = [transform_points(m.graph.poses[sid], c) if c is not None else np.zeros((0, 3)) for sid, c, _ in held]
        # each submap's points against its own cameras (another's may stand nearer: a walk round a courtyard)
        depths = [d for d in map(camera_depth, points, cams) if d is not None]
        ids = ", ".join(str(sid) for sid, _, _ in held)
        try:
            m.gallery.ensure_grid(np.concatenate(points), np.concatenate(cams),
                                  float(np.median(depths)) if depths else None)
        except DemError as e:
            log.warning("submap %s: no DEM plane from the points (%s); submap %d joins the map without a DEM layer, "
                        "and the next submap is tried", ids, e, held[0][0])
            held.pop(0)
            return
        finally:
            self.timings["covisibility_s"] += time.perf_counter() - t0
        log.info("DEM plane and tile %.3g fit to submap(s) %s", m.gallery.grid.tile_size, ids)
        self._held = []
        for sid, centres, per_camera in held:
            pts = m.store.get(sid)
            self._measure_height(sid, pts, centres, per_camera)  # the DEM plane exists only now
            accepted = self._query(sid, centres, pts, index=m.index_new)
            if accepted:
                self._solve_for(sid, accepted)

    def _measure_height(self, sid: int, points: np.ndarray, camera_centers: np.ndarray | None,
                        points_per_camera: np.ndarray | None = None) -> None:
        """Submap ``sid``'s cameras' height above its own ground (:func:`~vggt_slam_pp.backend.search.camera_heights`,
        up guessed from the DEM plane at its pose; each camera above its own points' ground where
        ``points_per_camera`` [S] says which of the stored ``points`` each keyframe gave) as a height factor,
        and, while the graph uses heights (:meth:`~vggt_slam_pp.backend.graph.PoseGraph.scale_noise`), its
        scale corrected by it at once (a solve of it alone, its predecessor held). Needs the DEM plane; nothing
        for a camera that does not keep one height, or when neither the graph (``GraphConfig.height_factors``)
        nor loops (``RegistrationConfig.height_cue``) use heights."""
        m, c = self.map, self.config.registration
        grid = m.gallery.grid
        if grid is None or camera_centers is None or len(points) < 10 or sid in m.graph.heights or not (
                self.config.graph.height_factors or c.height_cue):
            return
        s, R, _ = decompose_sim3(m.graph.poses[sid])
        keep = subsample_indices(len(points), c.height_max_points)
        labels = None  # each point's keyframe: each camera above its own ground (search.camera_heights)
        if points_per_camera is not None:
            counts = np.asarray(points_per_camera, np.int64).reshape(-1)
            if len(counts) == len(camera_centers) and counts.sum() == len(points):
                labels = point_cameras(counts)[keep]
            else:
                log.warning("submap %d: %d points per camera for %d cameras and %d points; its height is measured "
                            "above its common ground", sid, counts.sum(), len(camera_centers), len(points))
        measured = camera_heights(points[keep], camera_centers, R.T @ grid.plane.normal, c.max_up_tilt_deg,
                                  seed=sid, point_camera=labels)
        if measured is None:
            return
        h, spread = measured
        # heights whose cameras spread more than the loops' cue allows weigh only in the graph (within
        # GraphConfig.height_max_spread), where the variogram measures their noise; a ratio of tiny heights is noise
        g = self.config.graph
        cue = spread <= c.height_cue_max_spread
        if spread > max(c.height_cue_max_spread, g.height_max_spread if g.height_factors else 0.0) \
                or h * s < c.height_cue_min_tiles * grid.tile_size:
            return
        # the cameras' altitude above the DEM plane as odometry placed them (not the graph: heights move it)
        T = m.odometry_poses[sid]
        altitude = float(np.median((transform_points(T, camera_centers) - grid.plane.origin) @ grid.plane.normal))
        if not m.set_height(sid, h, altitude, cue=cue):
            return
        if self.config.graph.height_factors and m.segment[sid] != sid and m.graph.scale_noise() is not None:
            t0 = time.perf_counter()
            m.graph.optimize({sid})
            self.timings["optimization_s"] += time.perf_counter() - t0

    def _query(self, sid: int, camera_centers: np.ndarray, points: np.ndarray, index: bool) -> list[LoopResult]:
        """Covisibility, then loop candidates verified and accepted, for submap ``sid`` at its current pose
        (``index``: its layer joins the gallery too). Returns the loops accepted now."""
        m = self.map
        t0 = time.perf_counter()
        headings = 1 if m.is_placed(sid) else self.config.unplaced_headings
        res = self.stage.process(sid, m.layer_points(sid), transform_points(m.graph.poses[sid], camera_centers),
                                 insert=False, headings=headings)
        if index:
            m.index_layer(sid, res.described)
        res.described = None  # its dense features are not needed past this point
        self.covisibility += res.edges
        self.timings["covisibility_s"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        n = self.config.registration_max_points
        colors = m.store.get_colors(sid) if self.config.registration.use_colour else None
        accepted = self.closer.verify(sid, res, subsample(points, n), subsample(colors, n) if colors is not None else None)
        # the sequence prior follows every verified loop, pending ones too: their partner is likely next door
        self.stage.confirm(sid, self.closer.verified_matches(sid))
        self.timings["registration_s"] += time.perf_counter() - t0
        return accepted

    def _stage_totals(self, since: dict[str, float] | None = None) -> dict[str, float]:
        """The stages' time so far (:data:`STAGES`), or since ``since`` (an earlier call's result)."""
        return {k: self.timings[k] - (since[k] if since else 0.0) for k in STAGES}

    @property
    def deferred(self) -> int:
        """Submaps whose query waits (added while the worker caught up)."""
        return len(self._deferred)

    def query_deferred(self) -> PoseSnapshot:
        """Run the oldest deferred query: the submap (already in the graph and the gallery) queries the map
        at its current pose, as if it had just arrived; only older submaps can be its candidates."""
        t0, c0 = time.perf_counter(), time.thread_time()
        stages = self._stage_totals()
        sid, centres, entry = self._deferred.popleft()
        accepted = self._query(sid, centres, self.map.store.get(sid), index=False)
        if accepted:
            self._solve_for(sid, accepted)
        spent = time.perf_counter() - t0
        self.seconds[entry] += spent  # the submap's cost, wherever its query ran
        self.cpu_seconds[entry] += time.thread_time() - c0
        for k, v in self._stage_totals(stages).items():
            self.stage_seconds[k][entry] += v
        self.timings["deferred_s"] += spent  # a subtotal: its parts are in the other timings
        return self.snapshot()

    def _solve_for(self, sid: int, accepted: list[LoopResult]) -> None:
        """Optimise after new loops of ``sid``: globally when one reaches further back than
        ``far_loop_submaps``, else over the window around ``sid`` and the loops' submaps."""
        far = sid - min(r.match for r in accepted) > self.config.far_loop_submaps
        self._optimize(None if far else self._window(sid, [n for r in accepted for n in (r.query, r.match)]))

    def _window(self, sid: int, matches: list[int]) -> set[int]:
        k = self.config.window_neighbours
        window = set()
        for n in [sid, *matches]:
            window.update(range(n - k, n + k + 1))
        return {n for n in window if n in self.map.graph.poses}

    def _optimize(self, window: set[int] | None, refresh: bool = True, kernel: str | None = None) -> None:
        """Solve the graph (over ``window``, or globally; ``kernel``: the loops', default the configured one) and
        (``refresh``) describe moved layers again."""
        t0 = time.perf_counter()
        moved = set(self.map.graph.optimize(window, kernel))
        if window is None and self.map.prior_poses:  # a map extended by a recording stays in its frame
            if not np.allclose(self.map.keep_prior_frame(), np.eye(4)):
                moved = set(self.map.graph.poses)  # the held nodes moved with the frame too
        self.timings["optimization_s"] += time.perf_counter() - t0
        self._version += 1
        if refresh:
            t0 = time.perf_counter()
            self.map.refresh_layers(moved)
            self.timings["relocate_s"] += time.perf_counter() - t0

    def _final_kernel(self, kernel: str, final: str, out: int, total: int) -> str:
        """The end's robust decision, after a global solve with ``kernel`` that would prune ``out`` of ``total``
        loops: solve again with ``final`` from there (GraphConfig.final_kernel) and keep whichever solution more
        loops agree with, each within its chi-square bound (``gnc_inlier_probability``, :meth:`PoseGraph.loop_agreement`;
        a tie keeps ``kernel``). Pruned loops may sit in Cauchy's flat tail, a drift larger than the odometry
        sigmas say that the solve never went to (GNC closes them), or be wrong, which GNC would then bend the
        map to: the count of loops the map agrees with tells which (docs/backend.md, "loop acceptance").
        Returns the kernel whose solution the graph now holds."""
        graph = self.map.graph
        before = (dict(graph.poses), dict(graph.height_refs), dict(graph.last_solve), self._version)
        agree = graph.loop_agreement()
        self._optimize(None, refresh=False, kernel=final)
        agree_final = graph.loop_agreement()
        log.info("the final solve would prune %d of %d loops; %d of them agree with it, %d weighed with %s",
                 out, total, agree, agree_final, final)
        if agree_final > agree:
            return final
        graph.poses, graph.height_refs, graph.last_solve, self._version = before
        return kernel

    # -- outputs --------------------------------------------------------------------------------
    def snapshot(self) -> PoseSnapshot:
        poses = {}
        for i, T in self.map.graph.poses.items():
            a = T.copy()
            a.flags.writeable = False
            poses[i] = a
        return PoseSnapshot(self._version, MappingProxyType(poses), self.closer.accepted_count(),
                            max(poses) if poses else -1, rss_mb())

    def finish(self) -> BackendResult:
        """The deferred queries, then the final global optimisation (when there is any loop, or heights weigh or
        have weighed in a solve), pruning of the loops it switched off, and the result."""
        while self._held:  # a run shorter than BackendConfig.grid_submaps: the grid from what there is
            self._fit_grid()
        while self._deferred:
            self.query_deferred()
        graph = self.map.graph
        kernel = graph.config.robust_kernel
        loops = any(e.kind == "loop" for e in graph.edges)
        # also when heights moved submaps earlier but no longer weigh (their gate closed again, or the recording was
        # taken for a climbing camera): those windowed solves left each new submap at its height and the earlier ones
        # where they were, a step in scale that only a global solve under today's decision removes (realistic KITTI
        # 00-driven seed 18: -55 % without one)
        if (graph.config.height_factors and graph.heights and graph.scale_noise() is not None) or loops or (
                graph.heights_weighed):
            # no query follows: the layers are not described again
            self._optimize(None, refresh=False)
            final = graph.config.final_kernel
            weights = graph.loop_weights() if loops else []
            out = sum(w < self.config.min_loop_weight for w in weights)
            if final and final != kernel and out:
                kernel = self._final_kernel(kernel, final, out, len(weights))
            if self.closer.prune(self.config.min_loop_weight, kernel):
                if not any(e.kind == "loop" for e in graph.edges):
                    kernel = graph.config.robust_kernel  # odometry and heights alone, as without loops
                self._optimize(None, refresh=False, kernel=kernel)  # without those loops
        grid = self.map.gallery.grid
        return BackendResult(
            poses={i: T.copy() for i, T in graph.poses.items()},
            odometry_poses=dict(self.map.odometry_poses), edges=list(graph.edges),
            loop_weights=[float(w) for w in graph.loop_weights(kernel)], covisibility=list(self.covisibility),
            loops=list(self.closer.loops), seconds_per_submap=list(self.seconds),
            timings=dict(self.timings), plane=grid.plane.to_dict() if grid else None,
            tile_size=grid.tile_size if grid else None, mpp=grid.mpp if grid else None,
            memory_trace=list(self.memory_trace), placed=self.map.placed_submaps(), skipped=list(self.skipped),
            heights={i: h for i, (h, _) in graph.heights.items()}, height_refs=dict(graph.height_refs),
            cpu_seconds_per_submap=list(self.cpu_seconds),
            stage_seconds_per_submap={k: list(v) for k, v in self.stage_seconds.items()},
            odometry_scale_sigma=graph.last_solve.get("odometry_scale_sigma"),
            odometry_scale_measured_by=graph.last_solve.get("odometry_scale_measured_by"))
