"""The map: everything the back-end knows, in one object (SPEC 3.6, 3.10-3.12).

:class:`Map` owns

* the Sim(3) :class:`~vggt_slam_pp.backend.graph.PoseGraph` (optimised ``T_world_submap`` per submap, odometry
  and loop edges) and the odometry-only poses beside it;
* the :class:`~vggt_slam_pp.backend.store.SubmapStore` (each submap's points, submap frame, on disk);
* the :class:`~vggt_slam_pp.backend.places.Gallery` (the DEM plane and grid, the tile index, the VLAD
  vocabulary, the structures) and the pose each submap's DEM layer was rasterised with: when the graph
  moves a submap by more than ``relocate_min_shift_tiles`` its layer is rasterised and indexed again
  (:meth:`Map.refresh_layers`);
* the segments: chains of submaps linked by odometry. A recording added to a saved map starts a new one,
  not placed in the map's frame until a loop places it (:meth:`Map.move_segment`).

It is built empty (a new run) or from a saved map (:meth:`Map.seed`); :mod:`vggt_slam_pp.backend.mapfile`
reads and writes it on disk. The back-end's policies (candidates, verification, when to optimise) live
in :class:`~vggt_slam_pp.backend.backend.Backend`.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from vggt_slam_pp.backend.graph import Edge, PoseGraph
from vggt_slam_pp.backend.places import Described, Gallery
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.errors import BackendError, DemError, GeometryError
from vggt_slam_pp.frontend.types import OdometryEdge
from vggt_slam_pp.geometry.lie import decompose_sim3, so3_exp, transform_points
from vggt_slam_pp.resources import release_free_memory

log = logging.getLogger(__name__)


def subsample_indices(count: int, n: int) -> np.ndarray:
    """The indices [min(count, n)] of at most ``n`` of ``count`` items, evenly spaced in their order."""
    return np.linspace(0, count - 1, min(count, n)).astype(np.int64)


def subsample(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of ``points`` [N,3], evenly spaced in their order."""
    if len(points) <= n:
        return points
    return points[subsample_indices(len(points), n)]


class Map:
    def __init__(self, graph: PoseGraph, store: SubmapStore, gallery: Gallery, layer_max_points: int = 200_000,
                 relocate_min_shift_tiles: float = 0.25, relocate_budget: int = 64,
                 relocate_per_submap: float = 0.0, altitude_min_pairs: int = 5,
                 altitude_explained: float = 0.5) -> None:
        self.graph = graph
        self.store = store
        self.gallery = gallery
        self.layer_max_points = layer_max_points
        self.relocate_min_shift_tiles = relocate_min_shift_tiles
        self.relocate_budget = relocate_budget  # layers described again per refresh at most (<= 0: all)
        self.relocate_per_submap = relocate_per_submap  # ... and on average per new submap (<= 0: no such limit)
        self._relocate_tokens = float(max(relocate_budget, 0))  # what the average allows now (at most one refresh's)
        self.odometry_poses: dict[int, np.ndarray] = {}
        self.segment: dict[int, int] = {}  # submap id -> segment id (its first submap)
        self.placed: set[int] = set()  # segments in the map's frame
        self.index_new = True  # localisation only: new submaps query the map but do not join its gallery
        self._extent: dict[int, np.ndarray] = {}  # 8 bounding-box corners per submap (submap frame)
        self._centroid: dict[int, np.ndarray] = {}  # point centroid per submap (submap frame)
        self._layer_pose: dict[int, np.ndarray] = {}  # pose each gallery layer was rasterised with
        self._stale: set[int] = set()  # layers that moved enough but wait for a refresh with budget left
        self.degraded_edges: set[int] = set()  # i of the degraded odometry edges i -> i + 1
        self.prior_poses: dict[int, np.ndarray] = {}  # a seeded map's submaps at their saved poses (its frame)
        self.altitude_min_pairs = altitude_min_pairs
        self.altitude_explained = altitude_explained
        # per segment: (last submap with a height, its altitude, its height in odometry units) and the sums
        # sum (dlog H - climb)^2, sum dlog H^2, pairs (set_height)
        self._altitude: dict[int, tuple[tuple[int, float, float] | None, float, float, int]] = {}
        # per segment: sums over its heights of 1, h, h^2, g, g^2 (h = H - H_0, g = (H - altitude) - (H_0 - altitude_0),
        # odometry units, about the first height H_0), then H_0 and H_0 - altitude_0
        self._levels: dict[int, np.ndarray] = {}
        self._levels_held: dict[int, bool] = {}  # per segment: whether its levels followed the altitude at its last height
        self.flying: set[int] = set()  # segments whose cameras' height follows their altitude: no height cue
        self._set_aside: dict[int, dict[int, float]] = {}  # a flying segment's heights, out of the graph meanwhile
        self.graph_only_heights: set[int] = set()  # submaps whose height weighs in the graph but gives no loop cue

    # -- building it --------------------------------------------------------------------------------
    def add_submap(self, submap_id: int, odometry: OdometryEdge | None, points: np.ndarray,
                   camera_centers: np.ndarray | None = None) -> np.ndarray:
        """A new submap (``points`` [N,3], ``camera_centers`` [S,3], submap frame) enters the graph at
        ``T_world_prev T_prev_curr`` (the optimised previous pose) with its odometry edge weighted by the
        alignment residual; the first of a segment at the identity, levelled on the map's ground plane when
        it starts a recording beside a map (:meth:`_levelled_start`). Returns its pose ``T_world_submap``."""
        sid, e = submap_id, odometry
        if e is None:
            T = self._levelled_start(points, camera_centers) if self.graph.poses else np.eye(4)
            T_odo = T.copy()
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
        if self.relocate_per_submap > 0:
            cap = self.relocate_budget if self.relocate_budget > 0 else np.inf  # at most one refresh's budget
            self._relocate_tokens = min(self._relocate_tokens + self.relocate_per_submap, cap)
        if e is not None and e.degraded:
            self.degraded_edges.add(e.prev)
        if e is not None:
            cameras = e.method in ("pose_scale", "joint", "anchored") and not e.degraded
            self.graph.add_edge(Edge(e.prev, sid, e.T_prev_curr,
                                     self.graph.odometry_sigmas(e.T_prev_curr, e.residual, e.degraded, cameras,
                                                               e.relative_residual,
                                                               e.num_correspondences if e.method == "points" else 0),
                                     "odometry",
                                     # its scale sigma the prior walk, which a measured one replaces (not one the
                                     # shared cameras measured: GraphConfig.odometry_scale_sigma_cameras)
                                     {"residual": e.residual, "degraded": e.degraded, "prior_scale": not cameras}))
        if len(points):
            self._remember_extent(sid, points)
        return T

    def height(self, sid: int) -> float | None:
        """Submap ``sid``'s cameras' height above its own ground, its units, for loops' scale cue (None: not
        measured, no cue, or one that weighs only in the graph: :attr:`graph_only_heights`)."""
        h = self.graph.heights.get(sid)
        return h[0] if h is not None and sid not in self.graph_only_heights else None

    def height_near(self, sid: int, reach: int = 2) -> float | None:
        """Submap ``sid``'s cameras' height, its units: its own, or, when it has none (its cameras' heights
        spread too much: a turn, pose noise), the nearest submap's of its recording within ``reach``
        submaps, carried into its units by their relative scale in the graph (a few submaps of odometry
        are accurate in scale; the heights of a steady camera are not lost where one submap fails)."""
        own = self.height(sid)
        if own is not None or sid not in self.graph.poses:
            return own
        s = decompose_sim3(self.graph.poses[sid])[0]
        for d in range(1, reach + 1):
            for k in (sid - d, sid + d):
                h = self.height(k)
                if h is not None and self.same_segment(k, sid) and not any(
                        i in self.degraded_edges for i in range(min(k, sid), max(k, sid))):  # no extrapolated scale
                    return h * decompose_sim3(self.graph.poses[k])[0] / s
        return None

    def height_cue(self, query: int, match: int) -> tuple[float | None, float | None, bool]:
        """``(query height, match height, measured)`` for a loop's scale cue (:meth:`height_near`; None
        without one).

        The cue holds within one recording (one rig; another recording's camera may ride higher). It is a
        full constraint (the guesses rescaled to it, 10 % tolerance) only once the recording's heights have
        been measured to hold steady (``measured``, :meth:`PoseGraph.height_variogram` of its own heights: enough
        along odometry to tell their own noise from odometry's scale drift, about 11 on one chain). Before that the
        heights are a hypothesis and only a loose bound (``RegistrationConfig.height_cue_unmeasured_tolerance``):
        a hand-held camera that moves up and down a few per cent between submaps passes the climbing test
        (:meth:`set_height`) while odometry's scale noise hides its climb, and rescaling its loops to ratios
        of heights that are not its scale turned them by 4-11 deg (docs/experiments.md, session 43)."""
        if not self.same_segment(query, match):
            return None, None, False
        measured = self.graph.height_variogram(self.segment[query]) is not None
        return self.height_near(query), self.height_near(match), measured

    def set_height(self, sid: int, height: float, altitude: float | None = None, cue: bool = True) -> bool:
        """Submap ``sid``'s cameras stand ``height`` (its units) above its ground: a height factor in the
        graph, one world height per recording (segment). Returns whether it is in the graph now.

        ``altitude``: the cameras' median height above the DEM plane where odometry placed them (world units).
        A height gives the submap's scale only if the camera keeps one height above the ground (a car, a
        walker): then, between nearby submaps, its changes are odometry's scale drift and noise, not a climb.
        A drone's or a hand-held camera's height changes as it climbs, and odometry sees the climb: over
        pairs of nearby submaps with heights (at most 3 apart, no degraded edge between), while the climb
        ``(altitude_b - altitude_a) / mean height`` explains more than ``altitude_explained`` of the changes of
        ``log`` height in odometry units (``sum (dlog H - climb)^2 < (1 - altitude_explained) sum dlog H^2``, at
        least ``altitude_min_pairs`` pairs), or the altitude explains that share of the heights' own levels
        (over more than ``altitude_min_pairs`` heights, the variance of the ground's altitude under the cameras,
        ``altitude - H``, below ``1 - altitude_explained`` of the variance of ``H``: a camera that climbs from one
        to three metres above its ground; at two heights in a row, since one height moves those variances a lot
        while they are few: realistic block loop seed 2, a car, read 0.36 at its 6th height and 1.54 at its 7th,
        docs/experiments.md, session 66), the recording's heights are out of the graph (:attr:`flying`; no
        height cue for its loops either, :meth:`height_near`). The changes between neighbours are mostly
        odometry's scale noise where a drone climbs slowly (held-out hall_drone, realistic seed 2: their share
        0.42-0.57 over 26 heights that went from 0.7 to 2.1 with the altitude, the levels' 0.03-0.08 from the
        9th height on; docs/experiments.md, session 65); a car's altitude stays where its heights follow
        odometry's scale, and the tilt odometry drifts in moves it apart from them. The decision is taken again
        at every new height, on all of them: a car whose first few pairs happened to follow its climb gets its
        heights back, those set aside meanwhile included (realistic block loop and KITTI 07-driven worlds, seed
        15: the unexplained share ``sum (dlog H - climb)^2 / sum dlog H^2`` was 0.48 / 0.35 at pairs 5-6, 0.8-13 from pair 7 on; decided once
        and for all, their heights never came back: ATE reduction -33.5 / 0.0 %). ``cue`` False: the height weighs
        in the graph but gives its loops no scale cue (:meth:`height`)."""
        seg = self.segment[sid]
        if not cue:
            self.graph_only_heights.add(sid)
        climbs = self._climbs(sid, height, altitude) if altitude is not None else seg in self.flying
        if climbs:
            if seg not in self.flying:
                self.flying.add(seg)
                aside = self._set_aside.setdefault(seg, {})
                aside.update({i: h for i, (h, g) in self.graph.heights.items() if g == seg})
                dropped = self.graph.drop_heights(seg)
                log.info("recording %d: its cameras' height follows their altitude (a flying or hand-held camera): "
                         "%d heights out of the graph, no scale from heights", seg, dropped)
            self._set_aside[seg][sid] = float(height)
            return False
        if seg in self.flying:
            self.flying.discard(seg)
            back = self._set_aside.pop(seg, {})
            for i, h in sorted(back.items()):
                if i in self.graph.poses:
                    self.graph.add_height(i, h, seg)
            log.info("recording %d: its cameras' height no longer follows their altitude: %d heights back in the "
                     "graph", seg, len(back))
        self.graph.add_height(sid, height, seg)
        return True

    def _climbs(self, sid: int, height: float, altitude: float) -> bool:
        """Add submap ``sid``'s height and altitude to its segment's sums (:meth:`set_height`); whether the
        segment's climb now explains its heights."""
        seg = self.segment[sid]
        last, num, den, pairs = self._altitude.get(seg, (None, 0.0, 0.0, 0))
        H = float(decompose_sim3(self.odometry_poses[sid])[0]) * float(height)  # odometry's units
        if last is not None and 0 < sid - last[0] <= 3 and not any(
                i in self.degraded_edges for i in range(last[0], sid)):
            climb = (altitude - last[1]) / (0.5 * (H + last[2]))
            change = float(np.log(H / last[2]))
            num, den, pairs = num + (change - climb) ** 2, den + change ** 2, pairs + 1
        self._altitude[seg] = ((sid, float(altitude), H), num, den, pairs)
        sums = self._levels.setdefault(seg, np.array([0.0, 0.0, 0.0, 0.0, 0.0, H, H - altitude]))
        h, g = H - sums[5], H - altitude - sums[6]  # about the first height and ground: no cancellation
        sums[:5] += [1.0, h, h * h, g, g * g]
        n = sums[0]
        var_height, var_ground = sums[2] / n - (sums[1] / n) ** 2, sums[4] / n - (sums[3] / n) ** 2
        levels = bool(n > self.altitude_min_pairs and var_height > 0 and
                      var_ground < (1.0 - self.altitude_explained) * var_height)
        held, self._levels_held[seg] = self._levels_held.get(seg, False), levels
        return (levels and held) or (pairs >= self.altitude_min_pairs and num < (1.0 - self.altitude_explained) * den)

    def _levelled_start(self, points: np.ndarray, camera_centers: np.ndarray | None) -> np.ndarray:
        """The pose [4,4] of a recording's first submap beside a map: its own ground plane (fitted to its
        points) turned onto the map's by the smallest rotation and lifted onto it; heading and position
        stay the identity's (unknown until a loop places it). The recording's camera may be mounted at
        another pitch or roll than the map's: without this its "up" would be the map's normal read in
        its own frame, and every height, DEM layer and levelled registration of it would be tilted."""
        from vggt_slam_pp.dem import fit_ground_plane

        grid = self.gallery.grid
        T = np.eye(4)
        if grid is None or len(points) < 100:
            return T
        try:
            own = fit_ground_plane(points, camera_centers)
        except DemError:
            return T
        if own.degraded:
            return T
        n_map, n_own = grid.plane.normal, own.normal
        axis = np.cross(n_own, n_map)
        angle = float(np.arctan2(np.linalg.norm(axis), n_own @ n_map))
        if np.linalg.norm(axis) > 1e-12:
            T[:3, :3] = so3_exp(axis / np.linalg.norm(axis) * angle)
        T[:3, 3] = n_map * float((grid.plane.origin - T[:3, :3] @ own.origin) @ n_map)
        log.info("a recording beside the map: its ground is %.1f deg off the map's; levelled", np.degrees(angle))
        return T

    def seed(self, saved, localize_only: bool = False) -> None:
        """Start from a saved map (:class:`~vggt_slam_pp.backend.mapfile.SavedMap`, its points already in
        this map's store): its submaps enter the graph at their poses with their odometry and loop edges,
        and their layers the gallery, in the saved DEM plane and tiles; nothing is queried.
        ``localize_only``: the saved submaps stay fixed and new ones do not join the gallery."""
        from vggt_slam_pp.dem import DemGrid, GroundPlane

        if self.graph.poses:
            raise BackendError("a map can only seed an empty back-end")
        self.gallery.set_grid(DemGrid.create(GroundPlane.from_dict(saved.plane), dataclasses.replace(
            self.gallery.config.dem, tile_size=saved.tile_size)))
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
                self.gallery.add(sm.id, self.layer_points(sm.id))
                self._layer_pose[sm.id] = sm.T_world_submap.copy()
        for e in saved.edges:
            self.graph.add_edge(e)
            if e.kind == "odometry" and e.info.get("degraded"):
                self.degraded_edges.add(e.i)
        if localize_only:  # the map's submaps are held where they are; new ones do not join the gallery
            self.graph.anchors |= set(self.graph.poses)
            self.index_new = False
        else:
            self.prior_poses = {i: T.copy() for i, T in self.graph.poses.items()}
        log.info("map seeded: %d submaps, %d edges%s", len(saved.submaps), len(saved.edges),
                 " (localisation only)" if localize_only else "")

    def keep_prior_frame(self) -> np.ndarray:
        """After a global solve of a map that a recording extends: the similarity [4,4] that takes the
        seeded submaps back as close as they can come to their saved poses (least squares over their camera
        centres and point centroids), applied to every pose. The solve holds only the first submap, so
        loops from the new recording may shift and turn the saved map as a whole by a few tenths of a
        metre; its frame is the map's frame, in which the new trajectory must come out. Relative poses
        and the solution's shape are unchanged. Returns the similarity (the identity without a seeded map)."""
        from vggt_slam_pp.geometry.alignment import umeyama

        ids = [i for i in self.prior_poses if i in self.graph.poses]
        if len(ids) < 2:
            return np.eye(4)
        local = [np.zeros(3)]
        src, dst = [], []
        for i in ids:
            pts = np.array(local + ([self._centroid[i]] if i in self._centroid else []))
            src.append(transform_points(self.graph.poses[i], pts))
            dst.append(transform_points(self.prior_poses[i], pts))
        try:
            G = umeyama(np.concatenate(src), np.concatenate(dst), with_scale=True)
        except GeometryError:
            return np.eye(4)
        for i, T in self.graph.poses.items():
            self.graph.poses[i] = G @ T
        for g in self.graph.height_refs:  # every world height with the frame's scale
            self.graph.height_refs[g] *= decompose_sim3(G)[0]
        return G

    def index_layer(self, submap_id: int, described: Described) -> None:
        """Add a submap's described layer (at its current pose) to the gallery."""
        self.gallery.add(submap_id, described)
        self._layer_pose[submap_id] = self.graph.poses[submap_id].copy()

    def _remember_extent(self, sid: int, points: np.ndarray) -> None:
        self._centroid[sid] = points.mean(0)
        lo, hi = points.min(0), points.max(0)
        self._extent[sid] = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    # -- reading it ---------------------------------------------------------------------------------
    def layer_points(self, submap_id: int) -> np.ndarray:
        """The submap's points for its DEM layer [<= layer_max_points, 3], world frame at its current pose."""
        return transform_points(self.graph.poses[submap_id],
                                subsample(self.store.get(submap_id), self.layer_max_points))

    def centroid_world(self, submap_id: int) -> np.ndarray:
        """The submap's point centroid [3] at its current pose."""
        return self.centroids_world([submap_id])[0]

    def centroids_world(self, submap_ids: list[int]) -> np.ndarray:
        """The point centroids [len(submap_ids), 3] of those submaps at their current poses (at once: a query
        measures its distance to every earlier submap)."""
        if not submap_ids:
            return np.zeros((0, 3))
        T = np.stack([self.graph.poses[i] for i in submap_ids])
        c = np.stack([self._centroid[i] for i in submap_ids])
        return np.einsum("nij,nj->ni", T[:, :3, :3], c) + T[:, :3, 3]

    def has_points(self, submap_id: int) -> bool:
        return submap_id in self._centroid

    def with_points(self) -> list[int]:
        """Submaps with points, in insertion order."""
        return list(self._centroid)

    def in_gallery(self, submap_id: int) -> bool:
        return submap_id in self._layer_pose

    def is_placed(self, submap_id: int) -> bool:
        """Whether the submap's segment is in the map's frame."""
        return self.segment.get(submap_id) in self.placed

    def same_segment(self, a: int, b: int) -> bool:
        """Whether odometry links submaps ``a`` and ``b``."""
        return self.segment.get(a) == self.segment.get(b)

    def members(self, segment: int) -> list[int]:
        return sorted(i for i, g in self.segment.items() if g == segment)

    def steps(self, a: int, b: int) -> np.ndarray:
        """Lengths [n] of the steps between consecutive submap origins from ``a`` to ``b`` (current estimate)."""
        lo, hi = min(a, b), max(a, b)
        centres = [self.graph.poses[i][:3, 3] for i in range(lo, hi + 1) if i in self.graph.poses]
        return np.linalg.norm(np.diff(centres, axis=0), axis=1) if len(centres) > 1 else np.zeros(0)

    def path(self, a: int, b: int) -> float:
        """Length of the chain of submap origins between submaps ``a`` and ``b`` in the current estimate."""
        return float(self.steps(a, b).sum())

    def placed_submaps(self) -> list[int]:
        """Submaps in the map's frame: those the pose graph connects to the map's first submap (all of them
        for a single recording). A recording whose placing loops the final robust solve dropped is not."""
        if not self.graph.poses:
            return []
        root = self.graph.component_roots()
        first = root[min(self.graph.poses)]
        return sorted(i for i, r in root.items() if r == first and self.segment.get(i) in self.placed)

    # -- changing it --------------------------------------------------------------------------------
    def move_segment(self, segment: int, C: np.ndarray) -> list[int]:
        """Move every submap of ``segment`` by the world-frame Sim(3) ``C`` [4,4] (its odometry poses too),
        describe their layers again, and count the segment as placed. Returns its submaps."""
        members = self.members(segment)
        for i in members:
            self.graph.poses[i] = C @ self.graph.poses[i]
            self.odometry_poses[i] = C @ self.odometry_poses[i]
            if i in self._layer_pose:
                self._relocate(i)
        if segment in self.graph.height_refs:  # the recording's world height moves with its scale
            self.graph.height_refs[segment] *= decompose_sim3(C)[0]
        self.placed.add(segment)  # segments stay the odometry chains: drift bounds and cycles still follow them
        return members

    def refresh_layers(self, moved: set[int] | None = None) -> int:
        """After the graph moved submaps (``moved``: those it may have moved; None: any), rasterise and
        index again the layers that moved by at least ``relocate_min_shift_tiles`` since they were
        rasterised: at most ``relocate_budget`` of them, and at most ``relocate_per_submap`` per submap added
        on average (what a long run's revisits cost stays flat: every loop closure moves hundreds of layers),
        those that moved most first; the others wait for the next refresh (one that finds nothing moved
        catches up on them). Returns how many."""
        grid = self.gallery.grid
        thr = self.relocate_min_shift_tiles * (grid.tile_size if grid else 1.0)
        check = (set(self._layer_pose) if moved is None else moved | self._stale) & set(self._layer_pose)
        shifts = []
        for i in check:
            if i not in self._extent or i not in self.graph.poses:
                continue
            T, ext = self.graph.poses[i], self._extent[i]
            shift = np.linalg.norm(transform_points(T, ext) - transform_points(self._layer_pose[i], ext), axis=1).max()
            if shift >= thr:
                shifts.append((-shift, i))
            else:
                self._stale.discard(i)
        shifts.sort()
        budget = len(shifts) if self.relocate_budget <= 0 else min(len(shifts), self.relocate_budget)
        if self.relocate_per_submap > 0:
            budget = min(budget, int(self._relocate_tokens))
            self._relocate_tokens -= budget
        for i in sorted(i for _, i in shifts[:budget]):  # in id order: the HNSW graph depends on insertion order
            self._relocate(i)
            self._stale.discard(i)
        self._stale.update(i for _, i in shifts[budget:])
        if shifts[:budget]:
            release_free_memory()
        return budget

    @property
    def stale(self) -> bool:
        """Whether layers wait to be described again (the refresh budget ran out)."""
        return bool(self._stale)

    def _relocate(self, i: int) -> None:
        self.gallery.relocate(i, self.layer_points(i))
        self._layer_pose[i] = self.graph.poses[i].copy()
