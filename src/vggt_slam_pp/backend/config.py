"""The back-end's algorithm configuration (how the worker process runs is
:class:`~vggt_slam_pp.backend.worker.WorkerConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from vggt_slam_pp.backend.appearance import AppearanceConfig
from vggt_slam_pp.backend.graph import GraphConfig
from vggt_slam_pp.backend.image_loops import ImageLoopConfig
from vggt_slam_pp.backend.places import CovisibilityConfig
from vggt_slam_pp.backend.registration import RegistrationConfig


@dataclass(frozen=True)
class FaultConfig:
    """Fault injection, for tests of the verification's robustness; off by default."""

    wrong_candidates: float = 0.0  # share of queries given a wrong candidate from beyond the proximity gate
    # (it goes through verification like any other)
    slow_submap_s: float = 0.0  # the back-end sleeps this long for every submap (a back-end that cannot keep up)


@dataclass(frozen=True)
class BackendConfig:
    encoder: str = "hog"  # "hog" (weight-free) or "dinov2" (vggt_slam_pp.plugins.ENCODERS)
    encoder_weights: str | None = None  # dinov2: a path or hub name; None = the default resolution
    covisibility: CovisibilityConfig = field(default_factory=CovisibilityConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    images: ImageLoopConfig = field(default_factory=ImageLoopConfig)  # loops from images (sparse backbones)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)  # loops' support by keyframe features
    graph: GraphConfig = field(default_factory=GraphConfig)
    candidates_per_query: int = 3
    proximity_candidates: int = 2  # also verify the nearest earlier submaps in the current estimate
    proximity_radius_tiles: float = 10.0
    proximity_max_reach_tiles: float = 50.0  # ... or farther, as far as the estimate can have drifted between the
    # two through the pose graph (LoopCloser.drift_reach) where that is at most this (beyond it, the radius): the
    # first query of a revisit that odometry brought back within its own drift, farther than the radius
    far_loop_submaps: int = 10
    window_neighbours: int = 1
    dem_max_points: int = 200_000
    registration_max_points: int = 10_000
    relocate_min_shift_tiles: float = 0.25
    relocate_budget: int = 64  # layers described again after one solve at most (most moved first; the rest
    # later): a long run's global solve must not stall the back-end; <= 0: all at once
    relocate_per_submap: float = 4.0  # ... and at most this many per new submap on average (a revisit's loops
    # move hundreds of layers again and again: its cost per submap stays flat); <= 0: no such limit
    cache_submaps: int = 8
    grid_submaps: int = 3  # an "auto" DEM tile (a backbone without metric scale): the DEM plane and tile are fit to
    # the first this many submaps with points together, their queries held until then (a take-off or a start at a
    # wall sees the ground close up: EuRoC's first submap 30x closer than the flight; the tile is the median of
    # their own camera depths x DemConfig.auto_tile_fraction)
    altitude_min_pairs: int = 5  # a recording's heights give no scale once, over at least this many pairs of
    altitude_explained: float = 0.5  # nearby submaps with heights, the cameras' climb above the ground plane (in
    # odometry) explains more than this share of the heights' changes: a flying or hand-held camera
    # (Map.set_height; the unexplained share measured on car worlds 0.86-820, on a drone trajectory 0.00-0.26,
    # on hand-held ones 0.00-0.06, or 0.65-0.96 where the realistic profile's scale drift outweighs their climb)
    loop_consistency: bool = True  # a verified loop enters the graph only with a cycle-consistent second one
    consistency_submaps: int = 3  # partners: queries and matches at most this many submaps apart
    consistency_trans_tiles: float = 1.0  # translation tolerance of the cycle, in tiles
    lone_min_structure_overlap: float = 0.3  # a loop accepted without a partner needs this structure overlap
    # (verification asks 0.25 of every loop; wrong ones accepted alone sat at 0.25-0.27: docs/backend.md)
    lone_needs_no_contradiction: bool = True  # ... and no verified loop between the same places (queries and
    # matches within consistency_submaps) that disagrees with it (LoopCloser.contradicted)
    lone_needs_images: bool = True  # ... and its images could judge it (appearance.min_comparable comparable
    # landmarks; loops without landmarks or registered from images are exempt): every wrong loop accepted alone in
    # session 41's runs was one they could not judge, every judged one was right (docs/backend.md, loop acceptance)
    lone_confirmed_sigmas: float = 3.0  # a lone loop whose images confirm its pose (LoopResult.images_confirm) may
    # correct up to this many sigmas of the drift model, not one (3: as far as registration's drift bounds allow;
    # right revisits under the realistic profile needed up to 2.2, and every images-confirmed loop left pending in
    # session 48's runs but one, which a disagreeing loop holds back, was right: docs/experiments.md, session 50)
    min_loop_weight: float = 0.05  # at the end, loops the robust graph weighs less leave it (reported rejected)
    unplaced_headings: int = 8  # a submap not yet placed in the map also queries turned by 360 / this
    unplaced_candidates: int = 10  # its best covisible submaps by votes are all registered
    placement_votes: int = 3  # a recording is placed in a map by loops from this many of its submaps that agree
    placement_log_scale: float = 0.15  # on its move within these (|log scale|, degrees, tiles at its centre)
    placement_deg: float = 10.0
    placement_trans_tiles: float = 3.0
    faults: FaultConfig = field(default_factory=FaultConfig)
