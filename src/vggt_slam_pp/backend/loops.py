"""Loop candidates and their acceptance (SPEC 3.9-3.11): which submaps a new one is registered against, and
which verified registrations become edges of the pose graph.

:class:`LoopCloser` works on a :class:`~vggt_slam_pp.backend.map.Map`:

1. candidates (:meth:`LoopCloser.candidates`): the best ``candidates_per_query`` by place recognition, plus
   the ``proximity_candidates`` nearest earlier submaps in the current estimate (within a radius, or within
   what the estimate can have drifted between the two); a submap of a recording
   not yet placed in the map gets its ``unplaced_candidates`` best covisible submaps by votes instead;
2. each is registered and verified (:func:`~vggt_slam_pp.backend.registration.register_loop`, with the two
   submaps' image landmarks where both kept them: :mod:`~vggt_slam_pp.backend.appearance`) within the
   bounds odometry allows (:meth:`LoopCloser.bounds`, along the least uncertain path through the pose
   graph); when both submaps come from a sparse backbone that kept its image features, the best
   ``images.max_candidates`` are registered from their images instead
   (:func:`~vggt_slam_pp.backend.image_loops.register_by_images`);
3. a verified loop becomes an edge when it closes a consistent cycle with another verified loop
   (:meth:`LoopCloser.consistent`, pairwise consistency) or when its correction is within one sigma of the
   drift model and no verified loop between the same places disagrees with it
   (:meth:`LoopCloser.odometry_consistent`, :meth:`LoopCloser.contradicted`); a loop that would place a recording in the map
   needs ``placement_votes`` agreeing loops (:meth:`LoopCloser.placement`). Otherwise it waits for a
   partner ("pending"). Rejected candidates are kept with their reason.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from vggt_slam_pp.backend import image_loops
from vggt_slam_pp.backend.appearance import LANDMARKS_GUESS, ImageCheck
from vggt_slam_pp.backend.config import BackendConfig
from vggt_slam_pp.backend.graph import Edge
from vggt_slam_pp.backend.map import Map, subsample
from vggt_slam_pp.backend.places import StageResult, ranked_matches
from vggt_slam_pp.backend.registration import (
    LoopBounds,
    LoopResult,
    correction_size,
    drift_bounds,
    mutual_matches,
    register_loop,
)
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse

log = logging.getLogger(__name__)

PENDING = "verified, but no cycle-consistent second loop (yet)"


class LoopCloser:
    """Candidates, verification and acceptance of loops for the submaps of one :class:`Map`; every
    verified candidate, accepted or not, is in :attr:`loops` with its reason."""

    def __init__(self, config: BackendConfig, map_: Map) -> None:
        self.config = config
        self.map = map_
        self.loops: list[LoopResult] = []
        self._pending: list[int] = []  # indices in loops: verified, waiting for a consistent partner
        self._queries = 0  # queries with earlier submaps to compare with (fault injection counts them)

    @property
    def tile_size(self) -> float:
        return self.map.gallery.grid.tile_size

    def accepted_count(self) -> int:
        return sum(r.accepted for r in self.loops)

    def verified_matches(self, query: int) -> list[int]:
        """Matches of the verified loops of ``query``, pending ones too."""
        return [r.match for r in self.loops if r.query == query and (r.accepted or r.reason == PENDING)]

    # -- candidates ---------------------------------------------------------------------------------
    def candidates(self, sid: int, res: StageResult) -> list[tuple[int, float, float, str]]:
        """(match, score, margin, source): the best ``candidates_per_query`` by place recognition
        (VLAD-ranked, then covisibility order; source "retrieval"), plus the ``proximity_candidates``
        earlier submaps whose point centroid is nearest in the current estimate (within
        ``proximity_radius_tiles``, or within what the estimate can have drifted between the two through the
        pose graph, :meth:`drift_reach`, where that is at most ``proximity_max_reach_tiles``; "proximity"):
        retrieval finds loops the estimate has drifted away from, proximity the ones it has not, or not beyond
        what odometry allows; verification decides for both. With fault injection
        (``faults.wrong_candidates`` > 0), that share of queries also gets a submap from elsewhere
        ("injected"). A submap of a recording not yet placed in the map gets its ``unplaced_candidates``
        best covisible submaps by votes instead, and no proximity candidates (its position means nothing
        yet)."""
        m = self.map
        count = self.config.candidates_per_query
        if m.is_placed(sid):
            ranked = ranked_matches(res)
        else:  # where it lies is unknown: the re-ranking by DEM correlation near the estimate means nothing
            ranked = [(c.match, c.score) for c in res.edges if c.source == "votes"]
            count = self.config.unplaced_candidates
        out = []
        for k, (j, s) in enumerate(ranked[:count]):
            nxt = ranked[k + 1][1] if k + 1 < len(ranked) else 0.0
            out.append((j, s, s - nxt, "retrieval"))
        if self.config.proximity_candidates and m.has_points(sid) and m.is_placed(sid):
            here = m.centroid_world(sid)
            recent = m.gallery.config.index.exclude_recent
            old = [j for j in m.with_points() if j < sid - recent
                   and (m.index_new or m.in_gallery(j))]  # localisation only: the map's submaps
            if old:
                d = np.linalg.norm(m.centroids_world(old) - here, axis=1)
                radius = self.config.proximity_radius_tiles * self.tile_size
                # or as far as the estimate can have drifted between the two through the graph, where that is
                # within a limit (beyond it the radius holds: the nearest in the estimate is no better a guess)
                reach = self.drift_reach(sid, self.config.proximity_max_reach_tiles * self.tile_size)
                gate = np.array([max(radius, reach.get(j, 0.0)) for j in old])
                taken = {j for j, *_ in out}
                near = [k for k in np.argsort(d, kind="stable") if d[k] <= gate[k]][: self.config.proximity_candidates]
                out += [(old[k], 0.0, np.inf, "proximity") for k in near if old[k] not in taken]
                out += self._injected(old, d, gate, {j for j, *_ in out})
        return out

    def _injected(self, old: list[int], dist: np.ndarray, gate: np.ndarray, taken: set[int]) -> list:
        """Fault injection: every ``1 / faults.wrong_candidates``-th query gets the nearest earlier submap
        beyond its proximity gate ``gate`` [len(old)] (a hard negative: close enough to reach registration)."""
        rate = self.config.faults.wrong_candidates
        self._queries += 1
        if rate <= 0 or int(self._queries * rate) == int((self._queries - 1) * rate):
            return []
        far = [(dj, j) for j, dj, gj in zip(old, dist, gate, strict=True) if dj > gj and j not in taken]
        return [(min(far)[1], 0.0, np.inf, "injected")] if far else []

    # -- verification and acceptance ----------------------------------------------------------------
    def verify(self, sid: int, res: StageResult, points: np.ndarray, colors: np.ndarray | None = None
               ) -> list[LoopResult]:
        """Register every candidate of ``sid`` (``points``: its own frame; ``colors``: their image colours,
        when known) and decide on each (see the
        module docstring). Returns the loops that become graph edges now, ``sid``'s and pending ones that
        found their partner; their edges are already in the graph."""
        m, g = self.map, self.map.graph
        accepted: list[LoopResult] = []
        by_images = 0
        for match, score, margin, source in self.candidates(sid, res):
            t0 = time.thread_time()
            if self.config.images.enabled and image_loops.available(m.store, sid, match):
                # a sparse backbone's submaps: their images verify a loop, their few shared points cannot
                if by_images >= self.config.images.max_candidates:  # each costs seconds: kept with its reason
                    self.loops.append(LoopResult(sid, match, False, f"not registered: {by_images} registrations "
                                                 "from images per query", None, None, 0.0, 0.0, np.inf, 0, score,
                                                 "images", source=source))
                    continue
                by_images += 1
                r = image_loops.register_by_images(
                    sid, match, m.store, g.poses[sid], g.poses[match], self.bounds(match, sid), self.config.images,
                    score, slack=self.config.registration.icp_radius_tiles * self.tile_size)
            else:
                r = self._register(sid, match, score, margin, res, points, colors)
            r = dataclasses.replace(r, source=source, seconds=time.thread_time() - t0)
            log.info("loop candidate %d->%d: %s (overlap %.2f, structure %.2f, agreement %.2f, guess %s)",
                     sid, match, r.reason, r.overlap, r.structure_overlap, r.agreement, r.guess)
            if not r.accepted:
                self.loops.append(r)
                continue
            if log.isEnabledFor(logging.DEBUG):
                log.debug("verified %d->%d: correction |log s| %.3f, %.1f deg, moves it %.2f", sid, match,
                          *correction_size(r.correction, m.centroid_world(sid)))
            if not m.is_placed(sid) and m.is_placed(match):
                partners = self.placement(r)  # a loop that would place this recording in the map
                if not partners:
                    self._wait(r)
                    continue
            else:
                partners = self.consistent(r)
            if self.config.loop_consistency and not partners and not self.odometry_consistent(r):
                self._wait(r)
                continue
            for k in partners:  # pending partners join now
                if k in self._pending:
                    self._pending.remove(k)
                    self.loops[k] = dataclasses.replace(self.loops[k], accepted=True, reason="accepted")
                    accepted.append(self._add(self.loops[k]))
            self.loops.append(r)
            accepted.append(self._add(r))
        return accepted

    def _register(self, sid: int, match: int, score: float, margin: float, res: StageResult, points: np.ndarray,
                  colors: np.ndarray | None) -> LoopResult:
        """Register candidate ``sid`` -> ``match`` from the two submaps' points (registration.py)."""
        m, g, grid = self.map, self.map.graph, self.map.gallery.grid
        keys, desc = m.gallery.tiles_of(match)
        ia, ib = mutual_matches(res.chip_descriptors, desc)
        chip_uv = m.gallery.tile_centers_uv(res.chip_keys[ia])
        tile_uv = m.gallery.tile_centers_uv(keys[ib])
        pm = subsample(m.store.get(match), self.config.registration_max_points)
        h_q, h_m, measured = m.height_cue(sid, match)
        cm = m.store.get_colors(match) if colors is not None else None
        cm = subsample(cm, self.config.registration_max_points) if cm is not None else None
        return register_loop(sid, match, points, pm, g.poses[sid], g.poses[match], grid.plane, grid.tile_size,
                             chip_uv, tile_uv, score, margin, self.bounds(match, sid), self.config.registration,
                             colors_query=colors, colors_match=cm, height_query=h_q, height_match=h_m,
                             images=self._images(sid, match), height_measured=measured)

    def _images(self, sid: int, match: int) -> ImageCheck | None:
        """The two submaps' image landmarks for registration (backend/appearance.py), or None (none kept)."""
        a = self.config.appearance
        if not a.enabled:
            return None
        lq, lm = self.map.store.get_landmarks(sid), self.map.store.get_landmarks(match)
        if lq is None or lm is None:
            return None
        s_m, _, _ = decompose_sim3(self.map.graph.poses[match])
        return ImageCheck(lq, lm, a.radius_tiles * self.tile_size / float(s_m), a, seed=sid * 7919 + match)

    def _wait(self, r: LoopResult) -> None:
        self._pending.append(len(self.loops))
        self.loops.append(dataclasses.replace(r, accepted=False, reason=PENDING))

    def _add(self, r: LoopResult) -> LoopResult:
        """``r`` becomes a robust loop edge (placing its query's recording in the map first, if it is not)."""
        m = self.map
        if not m.is_placed(r.query) and m.is_placed(r.match):
            members = m.move_segment(m.segment[r.query], self.move(r))  # at the current poses
            log.info("submaps %d..%d placed in the map by loop %d->%d", members[0], members[-1], r.query, r.match)
        s_m, _, _ = decompose_sim3(m.graph.poses[r.match])
        g = m.graph.config
        trans = max(r.residual, g.loop_trans_sigma_tiles * self.tile_size) / float(s_m)
        sig = np.r_[[g.loop_rot_sigma] * 3, [trans] * 3, g.loop_scale_sigma]
        info = {k: v for k, v in r.to_dict().items() if k not in ("T_match_query", "information")}  # the edge has them
        m.graph.add_edge(Edge(r.match, r.query, r.T_match_query, sig, "loop", info, r.information))
        return r

    def move(self, r: LoopResult) -> np.ndarray:
        """The world-frame move of the query's recording that loop ``r`` asks for, at the current poses."""
        P = self.map.graph.poses
        return P[r.match] @ r.T_match_query @ sim3_inverse(P[r.query])

    def placement(self, r: LoopResult) -> list[int]:
        """Pending loops (indices in :attr:`loops`) from the same unplaced recording to the map that agree
        with ``r`` on where the recording lies, when together with ``r`` they come from at least
        ``placement_votes`` distinct query submaps; else []. A place that merely looks like another (a
        repetitive world) gives one or two loops at a time; the true place keeps giving them as the
        recording moves on, all asking the same move of the recording."""
        c, m = self.config, self.map
        seg = m.segment[r.query]
        C = self.move(r)
        centre = np.mean([m.graph.poses[i][:3, 3] for i in m.members(seg)], axis=0)
        tol = c.placement_trans_tiles * self.tile_size
        agree, queries = [], {r.query}
        for k in self._pending:
            o = self.loops[k]
            if m.segment[o.query] != seg or not m.is_placed(o.match) or o.T_match_query is None:
                continue
            log_s, angle, moved = correction_size(sim3_inverse(C) @ self.move(o), centre)
            if log_s <= c.placement_log_scale and angle <= c.placement_deg and moved <= tol:
                agree.append(k)
                queries.add(o.query)
        return agree if len(queries) >= c.placement_votes else []

    def consistent(self, r: LoopResult) -> list[int]:
        """Indices (in :attr:`loops`) of the verified loops, accepted or pending, that close a consistent
        cycle with ``r`` (pairwise consistency, as in PCM): loops (q, m) and (q', m') from two distinct queries
        (1 <= |q - q'|, and |m - m'|, at most ``consistency_submaps``) predict each other through the short
        odometry chains q -> q' and m -> m' (current estimate): ``E = (O_m Z') ^ -1 Z O_q`` must be the
        identity within what odometry drifts over those chains and what the two loops' own registrations err
        (3 sigma in scale and angle, of the registration's drift model over the chains' submaps together with
        the pose graph's loop sigmas, ``GraphConfig.loop_scale_sigma`` / ``loop_rot_sigma``, twice;
        ``consistency_trans_tiles`` plus ``translation_drift`` of the two chains' length in translation).
        A wrong loop is a random alignment: it rarely agrees with another. Loops of the same query onto
        neighbouring matches do not count: a query placed at a look-alike place registers onto every
        submap that saw that place, consistently (1,000-submap bench, seed 1: one query onto submaps
        1 and 2, 246 m wrong)."""
        return [k for k, agrees, dq in self._cycles(r) if agrees and dq > 0]

    def contradicted(self, r: LoopResult) -> list[int]:
        """Indices (in :attr:`loops`) of the verified loops, accepted or pending, between the same two places
        as ``r`` (queries and matches at most ``consistency_submaps`` apart, the same query onto another
        match included) that do *not* close a consistent cycle with it: one of the two is wrong, and which
        one, neither can tell. A loop so contradicted is not accepted alone (:meth:`odometry_consistent`):
        on a street of look-alikes, consecutive queries verify onto the same place at different turns. A loop
        whose images confirm its pose independently (``images_confirm``, registered from a guess that was not
        the landmarks' own alignment) is contradicted only by an accepted loop or by a pending one whose images
        confirm it too: a pending loop its images could not confirm is weaker evidence than a pose that the
        points and the landmarks found apart (realistic KITTI 07, seed 3: the right end-of-run revisit,
        confirmed by 342 landmarks, was held back by a wrong neighbour that its images could not judge). A loop
        refined from the landmarks' guess is not independently confirmed: one such, on realistic KITTI 00, was
        17 m off along the street."""
        independent = r.images_confirm and r.guess != LANDMARKS_GUESS
        return [k for k, agrees, _ in self._cycles(r) if not agrees
                and (not independent or self.loops[k].accepted or self.loops[k].images_confirm)]

    def _cycles(self, r: LoopResult):
        """``(index, consistent, |q - q'|)`` for every verified loop, accepted or pending, whose query and match
        are within ``consistency_submaps`` of ``r``'s (not ``r``'s own pair), in the same recordings:
        whether it closes a consistent cycle with ``r`` (:meth:`consistent`)."""
        c, reg, g_cfg, m = self.config, self.config.registration, self.config.graph, self.map
        P = m.graph.poses
        for k, o in enumerate(self.loops):
            if not (o.accepted or k in self._pending) or o.T_match_query is None:
                continue
            dq, dm = abs(o.query - r.query), abs(o.match - r.match)
            if dq + dm == 0 or dq > c.consistency_submaps or dm > c.consistency_submaps:
                continue
            if not (m.same_segment(o.query, r.query) and m.same_segment(o.match, r.match)):
                continue  # the cycle needs odometry between the two queries and between the two matches
            O_m = sim3_inverse(P[r.match]) @ P[o.match]
            O_q = sim3_inverse(P[r.query]) @ P[o.query]
            E = sim3_inverse(O_m @ o.T_match_query) @ r.T_match_query @ O_q
            s, R, t = decompose_sim3(E)
            # 3 sigma of what the cycle adds up: the odometry's walk over both chains and the two loops' own errors
            # (the pose graph's loop sigmas: reverse revisits register a few degrees off, and two right loops of
            # one revisit then disagreed by more than the walk alone allows)
            hops = max(dq + dm, 1)
            tol_s = 3.0 * np.hypot(np.sqrt(hops) * reg.scale_sigma_per_submap, np.sqrt(2) * g_cfg.loop_scale_sigma)
            tol_deg = 3.0 * np.hypot(np.sqrt(hops) * reg.yaw_sigma_per_submap_deg,
                                     np.sqrt(2) * np.degrees(g_cfg.loop_rot_sigma))
            s_q2, _, _ = decompose_sim3(P[o.query])  # E maps the other query's frame onto itself: its units
            chains = m.path(r.query, o.query) + m.path(r.match, o.match)
            tol_t = (c.consistency_trans_tiles * self.tile_size + reg.translation_drift * chains) / float(s_q2)
            ang = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
            log.debug("cycle %d->%d / %d->%d: scale %.3f, angle %.2f deg, translation %.2f (tolerance %.2f)",
                      r.query, r.match, o.query, o.match, s, ang, np.linalg.norm(t), tol_t)
            agrees = (abs(np.log(s)) <= tol_s and ang <= tol_deg and np.linalg.norm(t) <= tol_t)
            yield k, bool(agrees), dq

    def odometry_consistent(self, r: LoopResult) -> bool:
        """A loop whose correction is within one sigma of the drift model (a third of :meth:`bounds`; where its
        images confirm it, ``lone_confirmed_sigmas``, below) closes a consistent cycle with the odometry chain
        itself: it needs no partner loop, if its structure overlap is at least ``lone_min_structure_overlap`` (every wrong loop
        accepted alone on the bench worlds, realistic and default profiles, 1,000 submaps, sat at 0.25-0.27
        against the threshold 0.25; a loop registered from images is exempt: its "structure overlap" is the
        share of keyframes registered). Its scale change is not tested when the cameras' heights measured it
        (``r.scale_cue``): it is then what odometry drifted, measured, not a sign of a wrong place (its turn and
        move still are tested). Nor may a verified loop between the same places disagree with it
        (:meth:`contradicted`). With ``lone_needs_images``, a loop registered from points with landmarks must
        also be one its images could judge (they refuse what they judge and disagree with at registration). A
        loop whose images confirm its pose (``r.images_confirm``: the landmarks' own alignment, from enough
        agreeing pairs, is the pose the points verified) may correct up to ``lone_confirmed_sigmas`` sigmas
        (3 by default: as far as the bounds registration searched): under realistic drift a right revisit often
        needs more than one."""
        if not self.map.same_segment(r.match, r.query):
            return False  # a loop that would place a recording needs a cycle-consistent partner
        if r.guess != "images" and r.structure_overlap < self.config.lone_min_structure_overlap:
            return False  # alone, it must clear the structure test with a margin (look-alikes sit at its edge)
        if (self.config.lone_needs_images and r.guess != "images" and 0 <= r.appearance_comparable
                < self.config.appearance.min_comparable):
            return False  # alone, and its images cannot judge it (a street seen the other way, a crossing)
        b = self.bounds(r.match, r.query)
        sigmas = max(1.0, self.config.lone_confirmed_sigmas) if r.images_confirm else 1.0
        share = sigmas / 3.0  # the bounds are 3 sigma
        log_s, angle, moved = correction_size(r.correction, self.map.centroid_world(r.query))
        log.debug("lone loop %d->%d: scale %.3f (one sigma %.3f), turn %.2f deg (%.2f), move %.2f (%.2f), "
                  "confirmed by its images: %s", r.query, r.match, log_s, b.max_log_scale / 3, angle,
                  b.max_yaw_deg / 3, moved, b.max_translation / 3, r.images_confirm)
        if not ((log_s <= share * b.max_log_scale or r.scale_cue > 0) and angle <= share * b.max_yaw_deg
                and moved <= share * b.max_translation):
            return False
        against = self.contradicted(r) if self.config.lone_needs_no_contradiction else []
        if against:  # one of the two is wrong, and this loop alone cannot say which
            log.info("loop %d->%d not accepted alone: verified loop(s) %s between the same places disagree",
                     r.query, r.match, [(self.loops[k].query, self.loops[k].match) for k in against])
        return not against

    def bounds(self, match: int, query: int) -> LoopBounds:
        """What odometry can have drifted between ``match`` and ``query`` (submap ids):
        :func:`~vggt_slam_pp.backend.registration.drift_bounds` along the least uncertain path between
        them in the pose graph (:meth:`drift_path`): accepted loops shorten it, so once a revisit has been
        closed, the next submaps of that revisit are searched only as far as their short path allows, not
        as far as the whole chain of odometry back to the match."""
        m = self.map
        if not m.same_segment(match, query):  # no odometry between them: physical limits
            return LoopBounds(self.config.registration.max_scale_change, np.inf, 180.0)
        hops, path, degraded, loops = self.drift_path(query, match)
        reg = self.config.registration
        b = drift_bounds(reg, hops + loops, path, self.tile_size, degraded)
        if not loops:
            return b
        return LoopBounds(b.max_log_scale, b.max_translation + loops * reg.loop_hop_tiles * self.tile_size, b.max_yaw_deg)

    def drift_path(self, a: int, b: int) -> tuple[int, float, list[float], int]:
        """The path from submap ``a`` to ``b`` through the pose graph (odometry edges between consecutive
        submaps of a recording, and accepted loops) along which the current estimate can have drifted least:
        Dijkstra on the translation each edge can add (``translation_drift`` of an odometry step's length,
        plus ``degraded_steps`` of it for a degraded edge; ``loop_hop_tiles`` for a loop). Returns (odometry
        edges on it, their total length, the lengths of its degraded edges, loops on it); without loops this
        is the chain of odometry between the two."""
        _, state = self._drift_search(a, b)
        if b in state:
            hops, length, degraded, loops = state[b]
            return hops, length, list(degraded), loops
        lo, hi = min(a, b), max(a, b)  # not connected (cannot happen within a segment): the id chain
        steps = self.map.steps(lo, hi)
        return hi - lo, float(steps.sum()), [], 0

    def drift_reach(self, a: int, limit: float) -> dict[int, float]:
        """How far (world units) the estimate can have drifted between submap ``a`` and each submap it reaches
        through the pose graph within ``limit`` (the least along any path, as :meth:`drift_path` measures it)."""
        best, _ = self._drift_search(a, None, limit)
        return best

    def _drift_search(self, a: int, b: int | None, limit: float = np.inf) -> tuple[dict, dict]:
        """Dijkstra from ``a`` (to ``b``, or to every submap within ``limit``): (drift per submap, path state per
        submap: hops, length, degraded lengths, loops)."""
        import heapq

        m, reg = self.map, self.config.registration
        poses = m.graph.poses
        loop_adj: dict[int, list[int]] = {}
        for e in m.graph.edges:
            if e.kind == "loop":
                loop_adj.setdefault(e.i, []).append(e.j)
                loop_adj.setdefault(e.j, []).append(e.i)
        hop_cost = reg.loop_hop_tiles * self.tile_size
        best = {a: 0.0}
        state = {a: (0, 0.0, (), 0)}  # hops, length, degraded lengths, loops
        heap = [(0.0, a)]
        while heap:
            cost, i = heapq.heappop(heap)
            if i == b:
                break
            if cost > best.get(i, np.inf):
                continue
            hops, length, degraded, loops = state[i]
            steps = []
            for j in (i - 1, i + 1):
                if j in poses and m.same_segment(i, j):
                    step = float(np.linalg.norm(poses[j][:3, 3] - poses[i][:3, 3]))
                    bad = min(i, j) in m.degraded_edges
                    add = reg.translation_drift * step + (reg.degraded_steps * step if bad else 0.0)
                    steps.append((j, add, (hops + 1, length + step, degraded + ((step,) if bad else ()), loops)))
            for j in loop_adj.get(i, ()):
                steps.append((j, hop_cost, (hops, length, degraded, loops + 1)))
            for j, add, st in steps:
                if cost + add < best.get(j, np.inf) and cost + add <= limit:
                    best[j] = cost + add
                    state[j] = st
                    heapq.heappush(heap, (cost + add, j))
        return best, state

    def prune(self, min_weight: float, kernel: str | None = None) -> int:
        """Loops the robust pose graph switched off (weight below ``min_weight`` under ``kernel``, default the
        configured one, after a global solve: odometry and the other loops cannot explain them) leave the graph
        and are reported as rejected.
        Returns how many left."""
        g = self.map.graph
        weights = g.loop_weights(kernel)
        loops = [e for e in g.edges if e.kind == "loop"]
        out = {(e.j, e.i): w for e, w in zip(loops, weights, strict=True) if w < min_weight}
        if not out:
            return 0
        g.edges = [e for e in g.edges if e.kind != "loop" or (e.j, e.i) not in out]
        for k, r in enumerate(self.loops):
            if r.accepted and (r.query, r.match) in out:
                self.loops[k] = dataclasses.replace(
                    r, accepted=False, reason=f"rejected by the pose graph: odometry and the other loops do not "
                                              f"explain it (robust weight {out[(r.query, r.match)]:.3f})")
        log.info("%d loop(s) left the graph at the end (robust weight < %g)", len(out), min_weight)
        return len(out)
