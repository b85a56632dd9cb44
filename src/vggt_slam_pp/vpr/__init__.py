"""Place recognition inside the covisibility window: AnyLoc-style VLAD, then geometric re-ranking."""

from vggt_slam_pp.vpr.geometry import (
           GeometricMatch,
           GeometryConfig,
           Structure,
           layer_structure,
           match_structure,
           rerank_candidates,
           structure_peaks,
)
from vggt_slam_pp.vpr.vlad import LoopCandidate, Vocabulary, rank_candidates, tile_vlads, vlad

__all__ = ["GeometricMatch", "GeometryConfig", "LoopCandidate", "Structure", "Vocabulary", "layer_structure",
           "match_structure", "rank_candidates", "rerank_candidates", "structure_peaks", "tile_vlads", "vlad"]
