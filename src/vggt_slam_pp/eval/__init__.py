"""Trajectory evaluation with evo's conventions: timestamp association, ATE and RPE."""

from vggt_slam_pp.eval.metrics import (
    ALIGN_MODES,
    AteResult,
    RpeResult,
    align_trajectory,
    associate,
    compute_ate,
    compute_rpe,
)

__all__ = ["ALIGN_MODES", "AteResult", "RpeResult", "align_trajectory", "associate", "compute_ate", "compute_rpe"]
