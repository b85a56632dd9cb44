"""Geometry core: Lie groups on 4x4 matrices, quaternions, point-set alignment, pinhole cameras."""

from vggt_slam_pp.geometry.alignment import RobustSim3, estimate_sim3_robust, umeyama
from vggt_slam_pp.geometry.camera import PinholeCamera
from vggt_slam_pp.geometry.lie import (
    decompose_sim3,
    hat,
    make_sim3,
    rotation_angle,
    se3_exp,
    se3_inverse,
    se3_log,
    sim3_covariance_at_origin,
    sim3_exp,
    sim3_inverse,
    sim3_log,
    so3_exp,
    so3_log,
    transform_points,
)
from vggt_slam_pp.geometry.quaternion import (
    matrix_to_quat,
    pose_from_tq,
    pose_to_tq,
    quat_to_matrix,
    reorder_quat,
)

__all__ = [
    "PinholeCamera", "RobustSim3", "decompose_sim3", "estimate_sim3_robust", "hat", "make_sim3",
    "matrix_to_quat", "pose_from_tq", "pose_to_tq", "quat_to_matrix", "reorder_quat", "rotation_angle",
    "se3_exp", "se3_inverse", "se3_log", "sim3_covariance_at_origin", "sim3_exp", "sim3_inverse", "sim3_log",
    "so3_exp", "so3_log",
    "transform_points", "umeyama",
]
