"""The back-end's synchronous core: covisibility -> loop registration -> Sim(3) pose graph (SPEC 3.8-3.12).

:class:`Backend` owns the pose graph, the covisibility stage and the submap store. For every new submap
(:class:`SubmapMessage`, points read from the :class:`SubmapStore`):

1. its node enters the graph at ``T_world_prev T_prev_curr`` (the optimised previous pose), with the
   odometry edge weighted by its alignment residual;
2. its points (world frame, subsampled) go through the covisibility stage: DEM layer, descriptors,
   HNSW voting, VLAD candidates;
3. the best ``candidates_per_query`` candidates are registered and verified
   (:func:`~vggt_slam_pp.backend.registration.register_loop`) within the bounds odometry allows
   (:meth:`Backend._bounds`); a verified loop becomes a robust edge when it closes a consistent cycle
   with another verified loop (:meth:`Backend._consistent`, pairwise consistency) or when its
   correction is within one sigma of the drift model (:meth:`Backend._odometry_consistent`); otherwise
   it waits for such a partner ("pending"). Rejected candidates are kept with their reason;
4. with a new loop the graph is optimised: globally when the loop closes further back than
   ``far_loop_submaps``, otherwise over the window (the new submap, its loop partners and their
   neighbours) with the rest fixed; at :meth:`finish`, globally, after which loops the robust graph
   switched off (weight < ``min_loop_weight``) leave it and are reported as rejected;
5. layers of submaps that moved by more than ``relocate_min_shift_tiles`` are re-rasterised and
   re-indexed; a :class:`PoseSnapshot` is published.

A recording added to a saved map (:meth:`Backend.seed_map`) is a separate part of the graph until loops
from several of its submaps agree on where it lies (:meth:`Backend._placement`); docs/backend.md, "Maps".

The same object runs inline (synchronous mode, tests) or inside the worker process
(:mod:`vggt_slam_pp.backend.worker`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from vggt_slam_pp.backend.graph import Edge, GraphConfig, PoseGraph
from vggt_slam_pp.backend.registration import (
    LoopBounds,
    LoopResult,
    RegistrationConfig,
    correction_size,
    drift_bounds,
    mutual_matches,
    register_loop,
)
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.errors import BackendError
from vggt_slam_pp.frontend.types import OdometryEdge
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse, transform_points
from vggt_slam_pp.resources import release_free_memory, rss_mb
from vggt_slam_pp.retrieval.covisibility import CovisibilityConfig, CovisibilityStage

log = logging.getLogger(__name__)

PENDING = "verified, but no cycle-consistent second loop (yet)"


@dataclass(frozen=True)
class BackendConfig:
    encoder: str = "hog"  # "hog" (weight-free) or "dinov2"
    encoder_weights: str | None = None  # dinov2: a path or hub name; None = the default resolution
    covisibility: CovisibilityConfig = field(default_factory=CovisibilityConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    candidates_per_query: int = 3
    proximity_candidates: int = 2  # also verify the nearest earlier submaps in the current estimate
    proximity_radius_tiles: float = 10.0
    far_loop_submaps: int = 10
    window_neighbours: int = 1
    dem_max_points: int = 200_000
    registration_max_points: int = 10_000
    relocate_min_shift_tiles: float = 0.25
    cache_submaps: int = 8
    loop_information: str = "icp"  # "icp": full 7x7 from the registration (weak directions stay weak);
    # "isotropic": the configured loop sigmas
    worker: str = "process"  # "process" (own process, the front-end never waits on GTSAM) or "inline"
    queue_size: int = 128  # bounded inbox of the worker (ids, camera centres, odometry edge; the points are
    # on disk): the front-end blocks only when the back-end is this many submaps behind
    worker_threads: int = 1  # threads for OpenCV / FAISS / torch inside the worker
    worker_priority: str = "idle"  # "idle": CPU time only when the front-end leaves some (Linux SCHED_IDLE,
    # else nice 19); "low": nice 10; "normal"
    worker_duty: float = 0.5  # share of the wall time the worker may work while the front-end is still
    # streaming: after each submap it pauses for (1 / duty - 1) x that submap's time, unless its inbox is
    # over half full; once the front-end has finished it runs without pauses. Even at idle priority a busy
    # worker costs a 2-core front-end ~10 % (cache and wake-up contention); 1.0: never pause
    loop_consistency: bool = True  # a verified loop enters the graph only with a cycle-consistent second one
    consistency_submaps: int = 3  # partners: queries and matches at most this many submaps apart
    consistency_trans_tiles: float = 1.0  # translation tolerance of the cycle, in tiles
    min_loop_weight: float = 0.05  # at the end, loops the robust graph weighs less leave it (reported rejected)
    unplaced_headings: int = 8  # a submap not yet placed in the map also queries turned by 360 / this
    unplaced_candidates: int = 6  # its best covisible submaps by votes are all registered
    placement_votes: int = 3  # a recording is placed in a map by loops from this many of its submaps that agree
    placement_log_scale: float = 0.15  # on its move within these (|log scale|, degrees, tiles at its centre)
    placement_deg: float = 10.0
    placement_trans_tiles: float = 3.0
    inject_wrong_candidates: float = 0.0  # fault injection: share of queries given a random candidate from
    # beyond the proximity radius (it goes through verification like any other)


@dataclass(frozen=True)
class SubmapMessage:
    """A new submap for the back-end; its points (submap frame) are already in the store."""

    submap_id: int
    camera_centers: np.ndarray  # [S,3] submap frame
    odometry: OdometryEdge | None  # from the previous submap (None for the first)


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
    poses: dict[int, np.ndarray]
    odometry_poses: dict[int, np.ndarray]
    edges: list[dict]
    covisibility: list[dict]
    loops: list[dict]  # every verified candidate, accepted or not, with its reason
    seconds_per_submap: list[float]
    timings: dict[str, float]
    plane: dict | None
    tile_size: float | None
    mpp: float | None
    peak_rss_mb: float = 0.0  # of the back-end's process
    memory_trace: list = field(default_factory=list)  # (submaps done, RSS MiB of the back-end's process)
    placed: list[int] = field(default_factory=list)  # submaps whose poses are in the map's frame


def _subsample(points: np.ndarray, n: int) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(np.int64)]


class Backend:
    def __init__(self, config: BackendConfig, store: SubmapStore, encoder=None) -> None:
        from vggt_slam_pp.errors import RetrievalError
        from vggt_slam_pp.plugins import ENCODERS, load

        self.config = config
        self.store = store
        if encoder is None:
            encoder = load(ENCODERS, config.encoder, "encoder", RetrievalError).from_config(config.encoder_weights)
        self.stage = CovisibilityStage(encoder, config.covisibility)
        self.graph = PoseGraph(config.graph)
        self.odometry_poses: dict[int, np.ndarray] = {}
        self.covisibility: list[dict] = []
        self.loops: list[LoopResult] = []
        self.seconds: list[float] = []
        self.timings = {"covisibility_s": 0.0, "registration_s": 0.0, "optimization_s": 0.0, "relocate_s": 0.0}
        self._extent: dict[int, np.ndarray] = {}  # 8 bounding-box corners per submap (submap frame)
        self._layer_pose: dict[int, np.ndarray] = {}  # pose each layer was rasterised with
        self._centroid: dict[int, np.ndarray] = {}  # point centroid per submap (submap frame)
        self._version = 0
        self.memory_trace: list[tuple[int, float]] = []
        self._queries = 0  # queries with earlier submaps to compare with (fault injection counts them)
        self._pending: list[int] = []  # indices in loops: verified, waiting for a consistent partner
        # segments: chains of submaps linked by odometry. A recording added to a prior map starts a new one,
        # unplaced (a part of the graph of its own) until a loop links it to a placed one
        self.segment: dict[int, int] = {}  # submap id -> segment id (its first submap)
        self.placed: set[int] = set()
        self.index_new = True  # localisation only: new submaps query the map but do not join its gallery

    def seed_map(self, saved, localize_only: bool = False) -> None:
        """Start from a saved map (:class:`~vggt_slam_pp.backend.mapfile.SavedMap`, its points already in
        this back-end's store): its submaps enter the graph at their poses with their odometry and loop
        edges, and their layers the gallery, in the map's DEM plane and tiles; nothing is queried.
        ``localize_only``: the map's submaps stay fixed and the new ones are not added to the gallery."""
        from vggt_slam_pp.dem import DemGrid, GroundPlane

        if self.graph.poses:
            raise BackendError("a map can only seed an empty back-end")
        grid = DemGrid.create(GroundPlane.from_dict(saved.plane), dataclasses.replace(
            self.config.covisibility.dem, tile_size=saved.tile_size))
        self.stage.set_grid(grid)
        for sm in saved.submaps:
            self.graph.add_node(sm.id, sm.T_world_submap)
            self.odometry_poses[sm.id] = sm.T_world_submap.copy()
            first = sm.id if sm.id == 0 or not any(e.kind == "odometry" and e.j == sm.id for e in saved.edges) \
                else self.segment[sm.id - 1]
            self.segment[sm.id] = first
            if sm.placed:
                self.placed.add(first)
            points = self.store.get(sm.id)
            if len(points) >= 3:
                self._remember_extent(sm.id, points)
                self.stage.add(sm.id, transform_points(sm.T_world_submap, _subsample(points, self.config.dem_max_points)))
                self._layer_pose[sm.id] = sm.T_world_submap.copy()
        for e in saved.edges:
            self.graph.add_edge(e)
        if localize_only:  # the map's submaps are held where they are; new ones do not join the gallery
            self.graph.anchors |= set(self.graph.poses)
            self.index_new = False
        log.info("map seeded: %d submaps, %d edges%s", len(saved.submaps), len(saved.edges),
                 " (localisation only)" if localize_only else "")

    def _remember_extent(self, sid: int, points: np.ndarray) -> None:
        self._centroid[sid] = points.mean(0)
        lo, hi = points.min(0), points.max(0)
        self._extent[sid] = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    # -- the per-submap step --------------------------------------------------------------------
    def add_submap(self, msg: SubmapMessage) -> PoseSnapshot:
        t_start = time.perf_counter()
        sid = msg.submap_id
        points = self.store.get(sid)
        e = msg.odometry
        if e is None:
            T = np.eye(4)
            T_odo = np.eye(4)
            self.segment[sid] = sid
            if not self.graph.poses:  # the first recording defines the map's frame; a later one (a recording
                self.placed.add(sid)  # beside a map) is its own part of the graph until a loop places it
        else:
            if e.prev not in self.graph.poses:
                raise BackendError(f"odometry edge {e.prev}->{e.curr} refers to an unknown submap")
            T = self.graph.poses[e.prev] @ e.T_prev_curr
            T_odo = self.odometry_poses[e.prev] @ e.T_prev_curr
            self.segment[sid] = self.segment[e.prev]
        self.graph.add_node(sid, T)
        self.odometry_poses[sid] = T_odo
        if e is not None:
            self.graph.add_edge(Edge(e.prev, sid, e.T_prev_curr,
                                     self.graph.odometry_sigmas(e.T_prev_curr, e.residual, e.degraded), "odometry",
                                     {"residual": e.residual, "degraded": e.degraded}))
        if len(points):
            self._remember_extent(sid, points)
        accepted: list[LoopResult] = []
        if len(points) >= 3:
            t0 = time.perf_counter()
            pw = transform_points(T, _subsample(points, self.config.dem_max_points))
            unplaced = self.segment[sid] not in self.placed
            res = self.stage.process(sid, pw, transform_points(T, msg.camera_centers), insert=self.index_new,
                                     headings=self.config.unplaced_headings if unplaced else 1)
            if self.index_new:
                self._layer_pose[sid] = T
            self.covisibility += [{"query": c.query, "match": c.match, "score": c.score, "votes": c.votes,
                                   "source": c.source} for c in res.edges]
            self.timings["covisibility_s"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            accepted = self._verify(sid, res, _subsample(points, self.config.registration_max_points))
            self.timings["registration_s"] += time.perf_counter() - t0
        if accepted:
            far = sid - min(r.match for r in accepted) > self.config.far_loop_submaps
            window = None if far else self._window(sid, [n for r in accepted for n in (r.query, r.match)])
            self._optimize(window)
        self.seconds.append(time.perf_counter() - t_start)
        snap = self.snapshot()
        if len(self.seconds) % 10 == 0:
            self.memory_trace.append((len(self.seconds), snap.rss_mb))
        return snap

    def _candidates(self, sid: int, res) -> list[tuple[int, float, float, str]]:
        """(match, score, margin, source): the best ``candidates_per_query`` by place recognition
        (VLAD-ranked, then covisibility order; source "retrieval"), plus the ``proximity_candidates``
        earlier submaps whose point centroid is nearest in the current estimate (within
        ``proximity_radius_tiles``; "proximity"): retrieval finds loops the estimate has drifted away
        from, proximity the ones it has not; verification decides for both. With
        ``inject_wrong_candidates`` > 0, that share of queries also gets a random submap from elsewhere
        ("injected", fault testing). A submap of a recording not yet placed in the map gets its
        ``unplaced_candidates`` best covisible submaps by votes instead, and no proximity candidates
        (its position means nothing yet)."""
        count = self.config.candidates_per_query
        if self.segment[sid] in self.placed:
            ranked = [(c.match, c.score) for c in res.candidates]
            seen = {m for m, _ in ranked}
            ranked += [(c.match, c.score) for c in res.edges if c.match not in seen]
        else:  # where it lies is unknown: the re-ranking by DEM correlation near the estimate means nothing
            ranked = [(c.match, c.score) for c in res.edges if c.source == "votes"]
            count = self.config.unplaced_candidates
        out = []
        for k, (m, s) in enumerate(ranked[:count]):
            nxt = ranked[k + 1][1] if k + 1 < len(ranked) else 0.0
            out.append((m, s, s - nxt, "retrieval"))
        if self.config.proximity_candidates and sid in self._centroid and self.segment[sid] in self.placed:
            here = transform_points(self.graph.poses[sid], self._centroid[sid][None])[0]
            old = [j for j in self._centroid if j < sid - self.stage.config.index.exclude_recent
                   and (self.index_new or j in self._layer_pose)]  # localisation only: the map's submaps
            if old:
                d = np.array([np.linalg.norm(transform_points(self.graph.poses[j], self._centroid[j][None])[0] - here)
                              for j in old])
                radius = self.config.proximity_radius_tiles * self.stage.grid.tile_size
                taken = {m for m, *_ in out}
                for k in np.argsort(d)[: self.config.proximity_candidates]:
                    if d[k] <= radius and old[k] not in taken:
                        out.append((old[k], 0.0, np.inf, "proximity"))
                out += self._injected(old, d, radius, {m for m, *_ in out})
        return out

    def _injected(self, old: list[int], dist: np.ndarray, radius: float, taken: set[int]) -> list:
        """Fault injection: every ``1 / inject_wrong_candidates``-th query gets the nearest earlier submap
        beyond the proximity radius (a hard negative: close enough to reach registration)."""
        rate = self.config.inject_wrong_candidates
        self._queries += 1
        if rate <= 0 or int(self._queries * rate) == int((self._queries - 1) * rate):
            return []
        far = [(dj, j) for j, dj in zip(old, dist, strict=True) if dj > radius and j not in taken]
        return [(min(far)[1], 0.0, np.inf, "injected")] if far else []

    def _verify(self, sid: int, res, points: np.ndarray) -> list[LoopResult]:
        """Register every candidate of ``sid`` (``points``: its own frame); a geometrically verified loop
        enters the graph once it is cycle-consistent with another verified loop (:meth:`_consistent`).
        Returns the loops added now (a pending loop joins when its partner arrives)."""
        accepted: list[LoopResult] = []
        for match, score, margin, source in self._candidates(sid, res):
            keys, desc = self.stage.tiles_of(match)
            ia, ib = mutual_matches(res.chip_descriptors, desc)
            chip_uv = self.stage.tile_centers_uv(res.chip_keys[ia])
            tile_uv = self.stage.tile_centers_uv(keys[ib])
            T_m = self.graph.poses[match]
            pm = _subsample(self.store.get(match), self.config.registration_max_points)
            r = register_loop(sid, match, points, pm, self.graph.poses[sid], T_m, self.stage.grid.plane,
                              self.stage.grid.tile_size, chip_uv, tile_uv, score, margin, self._bounds(match, sid),
                              self.config.registration)
            r = dataclasses.replace(r, source=source)
            log.info("loop candidate %d->%d: %s (overlap %.2f, structure %.2f, agreement %.2f, guess %s)",
                     sid, match, r.reason, r.overlap, r.structure_overlap, r.agreement, r.guess)
            if not r.accepted:
                self.loops.append(r)
                continue
            log.debug("verified %d->%d: correction |log s| %.3f, %.1f deg, moves it %.2f", sid, match,
                      *correction_size(r.correction, transform_points(self.graph.poses[sid], points.mean(0)[None])[0]))
            if self.segment[sid] not in self.placed and self.segment[match] in self.placed:
                partners = self._placement(r)  # a loop that would place this recording in the map
                if not partners:
                    self._pending.append(len(self.loops))
                    self.loops.append(dataclasses.replace(r, accepted=False, reason=PENDING))
                    continue
            else:
                partners = self._consistent(r)
            if self.config.loop_consistency and not partners and not self._odometry_consistent(r):
                self._pending.append(len(self.loops))
                self.loops.append(dataclasses.replace(r, accepted=False, reason=PENDING))
                continue
            for k in partners:  # pending partners join now
                if k in self._pending:
                    self._pending.remove(k)
                    self.loops[k] = dataclasses.replace(self.loops[k], accepted=True, reason="accepted")
                    accepted.append(self._add_loop(self.loops[k]))
            self.loops.append(r)
            accepted.append(self._add_loop(r))
        # the sequence prior follows every verified loop, pending ones too: their partner is likely next door
        self.stage.confirm(sid, [r.match for r in self.loops if r.query == sid and (r.accepted or r.reason == PENDING)])
        return accepted

    def _add_loop(self, r: LoopResult) -> LoopResult:
        self._place(r)
        grid = self.stage.grid
        s_m, _, _ = decompose_sim3(self.graph.poses[r.match])
        g = self.config.graph
        trans = max(r.residual, g.loop_trans_sigma_tiles * grid.tile_size) / float(s_m)
        sig = np.r_[[g.loop_rot_sigma] * 3, [trans] * 3, g.loop_scale_sigma]
        info = r.information if self.config.loop_information == "icp" else None
        self.graph.add_edge(Edge(r.match, r.query, r.T_match_query, sig, "loop", r.to_dict(), info))
        return r

    def _placement(self, r: LoopResult) -> list[int]:
        """Pending loops (indices in :attr:`loops`) from the same unplaced recording to the map that agree
        with ``r`` on where the recording lies, when together with ``r`` they come from at least
        ``placement_votes`` distinct query submaps; else []. A place that merely looks like another (a
        repetitive world) gives one or two loops at a time; the true place keeps giving them as the
        recording moves on, all asking the same move of the recording."""
        c = self.config
        P = self.graph.poses
        seg = self.segment[r.query]
        move = self._move
        C = move(r)
        centre = np.mean([P[i][:3, 3] for i, g in self.segment.items() if g == seg], axis=0)
        tol = c.placement_trans_tiles * self.stage.grid.tile_size
        agree, queries = [], {r.query}
        for k in self._pending:
            o = self.loops[k]
            if self.segment[o.query] != seg or self.segment[o.match] not in self.placed or o.T_match_query is None:
                continue
            log_s, angle, moved = correction_size(sim3_inverse(C) @ move(o), centre)
            if log_s <= c.placement_log_scale and angle <= c.placement_deg and moved <= tol:
                agree.append(k)
                queries.add(o.query)
        return agree if len(queries) >= c.placement_votes else []

    def _move(self, r: LoopResult) -> np.ndarray:
        """The world-frame move of the query's recording that loop ``r`` asks for, at the current poses."""
        P = self.graph.poses
        return P[r.match] @ r.T_match_query @ sim3_inverse(P[r.query])

    def _place(self, r: LoopResult) -> None:
        """The first loop that links an unplaced recording (the query's segment) to a placed one moves the
        whole recording by that loop's correction, so the pose graph starts from the merged estimate."""
        seg, target = self.segment[r.query], self.segment[r.match]
        if seg in self.placed or target not in self.placed:
            return
        C = self._move(r)  # at the current poses, not the verification's
        members = sorted(i for i, g in self.segment.items() if g == seg)
        for i in members:
            self.graph.poses[i] = C @ self.graph.poses[i]
            self.odometry_poses[i] = C @ self.odometry_poses[i]
            if i in self._layer_pose:
                self.stage.relocate(i, transform_points(self.graph.poses[i],
                                                        _subsample(self.store.get(i), self.config.dem_max_points)))
                self._layer_pose[i] = self.graph.poses[i].copy()
        self.placed.add(seg)  # segments stay the odometry chains: drift bounds and cycles still follow them
        log.info("submaps %d..%d placed in the map by loop %d->%d", members[0], members[-1], r.query, r.match)

    def placed_submaps(self) -> list[int]:
        """Submaps in the map's frame: those the pose graph connects to the map's first submap (all of them
        for a single recording). A recording whose placing loops the final robust solve dropped is not."""
        if not self.graph.poses:
            return []
        root = self.graph.component_roots()
        first = root[min(self.graph.poses)]
        return sorted(i for i, r in root.items() if r == first and self.segment.get(i) in self.placed)

    def _consistent(self, r: LoopResult) -> list[int]:
        """Indices (in :attr:`loops`) of the verified loops, accepted or pending, that close a consistent
        cycle with ``r`` (pairwise consistency, as in PCM): loops (q, m) and (q', m') with |q - q'| and
        |m - m'| at most ``consistency_submaps`` (not both zero) predict each other through the short
        odometry chains q -> q' and m -> m' (current estimate): ``E = (O_m Z') ^ -1 Z O_q`` must be the
        identity within what odometry drifts over those chains (3 sigma of the registration's drift model in
        scale and angle; ``consistency_trans_tiles`` plus ``translation_drift`` of the two chains' length).
        A wrong loop is a random alignment: it rarely agrees with another."""
        c, reg = self.config, self.config.registration
        P = self.graph.poses
        out = []
        for k, o in enumerate(self.loops):
            if not (o.accepted or k in self._pending) or o.T_match_query is None:
                continue
            dq, dm = abs(o.query - r.query), abs(o.match - r.match)
            if dq > c.consistency_submaps or dm > c.consistency_submaps or (dq == 0 and dm == 0):
                continue
            seg = self.segment.get
            if seg(o.query) != seg(r.query) or seg(o.match) != seg(r.match):
                continue  # the cycle needs odometry between the two queries and between the two matches
            O_m = sim3_inverse(P[r.match]) @ P[o.match]
            O_q = sim3_inverse(P[r.query]) @ P[o.query]
            E = sim3_inverse(O_m @ o.T_match_query) @ r.T_match_query @ O_q
            s, R, t = decompose_sim3(E)
            walk = 3.0 * np.sqrt(max(dq + dm, 1))
            s_q2, _, _ = decompose_sim3(P[o.query])  # E maps the other query's frame onto itself: its units
            chains = self._path(r.query, o.query) + self._path(r.match, o.match)
            tol_t = (c.consistency_trans_tiles * self.stage.grid.tile_size + reg.translation_drift * chains) / float(s_q2)
            ang = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
            log.debug("cycle %d->%d / %d->%d: scale %.3f, angle %.2f deg, translation %.2f (tolerance %.2f)",
                      r.query, r.match, o.query, o.match, s, ang, np.linalg.norm(t), tol_t)
            if (abs(np.log(s)) <= walk * reg.scale_sigma_per_submap and ang <= walk * reg.yaw_sigma_per_submap_deg
                    and np.linalg.norm(t) <= tol_t):
                out.append(k)
        return out

    def _odometry_consistent(self, r: LoopResult) -> bool:
        """A loop whose correction is within one sigma of the drift model (a third of :meth:`_bounds`) closes
        a consistent cycle with the odometry chain itself: it needs no partner loop."""
        if self.segment.get(r.match) != self.segment.get(r.query):
            return False  # a loop that would place a recording needs a cycle-consistent partner
        b = self._bounds(r.match, r.query)
        centroid = transform_points(self.graph.poses[r.query], self._centroid[r.query][None])[0]
        log_s, angle, moved = correction_size(r.correction, centroid)
        return log_s <= b.max_log_scale / 3 and angle <= b.max_yaw_deg / 3 and moved <= b.max_translation / 3

    def _steps(self, a: int, b: int) -> np.ndarray:
        """Lengths [n] of the steps between consecutive submap origins from ``a`` to ``b`` (current estimate)."""
        lo, hi = min(a, b), max(a, b)
        centres = [self.graph.poses[i][:3, 3] for i in range(lo, hi + 1) if i in self.graph.poses]
        return np.linalg.norm(np.diff(centres, axis=0), axis=1) if len(centres) > 1 else np.zeros(0)

    def _path(self, a: int, b: int) -> float:
        """Length of the chain of submap origins between submaps ``a`` and ``b`` in the current estimate."""
        return float(self._steps(a, b).sum())

    def _bounds(self, match: int, query: int) -> LoopBounds:
        """What odometry can have drifted between ``match`` and ``query`` (submap ids):
        :func:`~vggt_slam_pp.backend.registration.drift_bounds` over the chain between them in the
        current estimate, with its degraded edges."""
        if self.segment.get(match) != self.segment.get(query):  # no odometry between them: physical limits
            return LoopBounds(self.config.registration.max_scale_change, np.inf, 180.0)
        lo, hi = min(match, query), max(match, query)
        steps = self._steps(lo, hi)
        degraded = [float(steps[e.i - lo]) for e in self.graph.edges if e.kind == "odometry" and lo <= e.i < hi
                    and e.info.get("degraded") and e.i - lo < len(steps)]
        return drift_bounds(self.config.registration, hi - lo, float(steps.sum()), self.stage.grid.tile_size,
                            degraded)

    def _window(self, sid: int, matches: list[int]) -> set[int]:
        k = self.config.window_neighbours
        window = set()
        for n in [sid, *matches]:
            window.update(range(n - k, n + k + 1))
        return {n for n in window if n in self.graph.poses}

    def _optimize(self, window: set[int] | None) -> None:
        t0 = time.perf_counter()
        before = {i: T.copy() for i, T in self.graph.poses.items()}
        self.graph.optimize(window)
        self.timings["optimization_s"] += time.perf_counter() - t0
        self._version += 1
        t0 = time.perf_counter()
        thr = self.config.relocate_min_shift_tiles * (self.stage.grid.tile_size if self.stage.grid else 1.0)
        moved = 0
        for i, T in self.graph.poses.items():
            if i not in self._layer_pose or i not in self._extent:
                continue
            now = transform_points(T, self._extent[i])
            if np.abs(now - transform_points(before[i], self._extent[i])).max() < 1e-12:
                continue
            shift = np.linalg.norm(now - transform_points(self._layer_pose[i], self._extent[i]), axis=1).max()
            if shift >= thr:
                self.stage.relocate(i, transform_points(T, _subsample(self.store.get(i), self.config.dem_max_points)))
                self._layer_pose[i] = T.copy()
                moved += 1
        if moved:
            release_free_memory()
        self.timings["relocate_s"] += time.perf_counter() - t0

    def _prune_loops(self) -> None:
        """Loops the robust pose graph switched off (weight below ``min_loop_weight`` after the global
        solve: odometry and the other loops cannot explain them) leave the graph and are reported as
        rejected; the graph is solved once more without them."""
        weights = self.graph.loop_weights()
        loops = [e for e in self.graph.edges if e.kind == "loop"]
        out = {(e.j, e.i): w for e, w in zip(loops, weights, strict=True) if w < self.config.min_loop_weight}
        if not out:
            return
        self.graph.edges = [e for e in self.graph.edges if e.kind != "loop" or (e.j, e.i) not in out]
        for k, r in enumerate(self.loops):
            if r.accepted and (r.query, r.match) in out:
                self.loops[k] = dataclasses.replace(
                    r, accepted=False, reason=f"rejected by the pose graph: odometry and the other loops do not "
                                              f"explain it (robust weight {out[(r.query, r.match)]:.3f})")
        log.info("%d loop(s) left the graph at the end (robust weight < %g)", len(out), self.config.min_loop_weight)
        self._optimize(None)  # without any loop left this returns the odometry chain

    # -- outputs --------------------------------------------------------------------------------
    def snapshot(self) -> PoseSnapshot:
        poses = {}
        for i, T in self.graph.poses.items():
            a = T.copy()
            a.flags.writeable = False
            poses[i] = a
        return PoseSnapshot(self._version, MappingProxyType(poses), sum(r.accepted for r in self.loops),
                            max(self.graph.poses) if self.graph.poses else -1, rss_mb())

    def finish(self) -> BackendResult:
        """Final global optimisation (when there is any loop) and the result."""
        if any(e.kind == "loop" for e in self.graph.edges):
            self._optimize(None)
            self._prune_loops()
        weights = iter(self.graph.loop_weights())
        edges = []
        for e in self.graph.edges:
            d = {"from": e.i, "to": e.j, "kind": e.kind, "T": e.T_ij.tolist(), "sigmas": e.sigmas.tolist(), **e.info}
            if e.information is not None:
                d["information"] = e.information.tolist()
            if e.kind == "loop":
                d["robust_weight"] = next(weights)
            edges.append(d)
        grid = self.stage.grid
        return BackendResult(
            poses={i: T.copy() for i, T in self.graph.poses.items()},
            odometry_poses=dict(self.odometry_poses), edges=edges, covisibility=list(self.covisibility),
            loops=[r.to_dict() for r in self.loops], seconds_per_submap=list(self.seconds),
            timings=dict(self.timings), plane=grid.plane.to_dict() if grid else None,
            tile_size=grid.tile_size if grid else None, mpp=grid.mpp if grid else None,
            memory_trace=list(self.memory_trace), placed=self.placed_submaps())
