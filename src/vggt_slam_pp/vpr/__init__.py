"""Place recognition inside the covisibility window: AnyLoc-style VLAD."""

from vggt_slam_pp.vpr.vlad import LoopCandidate, Vocabulary, rank_candidates, tile_vlads, vlad

__all__ = ["LoopCandidate", "Vocabulary", "rank_candidates", "tile_vlads", "vlad"]
