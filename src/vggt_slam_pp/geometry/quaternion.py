"""Quaternion <-> rotation matrix conversions with the component order always explicit.

Two orders are in common use and both appear in our inputs:

* ``"xyzw"`` (scalar last): TUM trajectory files, SciPy, ROS.
* ``"wxyz"`` (scalar first): EuRoC CSV files, Eigen's constructor, GTSAM.

Quaternions are Hamilton, unit norm, ``[..., 4]``; returned quaternions have a non-negative scalar part.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from vggt_slam_pp.errors import GeometryError

QuatOrder = Literal["xyzw", "wxyz"]

__all__ = ["QuatOrder", "quat_to_matrix", "matrix_to_quat", "pose_from_tq", "pose_to_tq", "reorder_quat"]


def _check_order(order: str) -> None:
    if order not in ("xyzw", "wxyz"):
        raise GeometryError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")


def reorder_quat(q: np.ndarray, src: QuatOrder, dst: QuatOrder) -> np.ndarray:
    """Convert ``q [..., 4]`` from component order ``src`` to ``dst``."""
    _check_order(src)
    _check_order(dst)
    q = np.asarray(q, dtype=np.float64)
    if src == dst:
        return q.copy()
    return np.roll(q, 1 if src == "xyzw" else -1, axis=-1)


def quat_to_matrix(q: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` from quaternions ``[..., 4]`` in the given order (normalised first)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise GeometryError(f"quaternions must have shape [..., 4], got {q.shape}")
    norms = np.linalg.norm(q, axis=-1)
    if not np.all(np.isfinite(norms)) or np.any(norms < 1e-12):
        raise GeometryError("quaternion with zero or non-finite norm")
    xyzw = reorder_quat(q, order, "xyzw").reshape(-1, 4)
    return Rotation.from_quat(xyzw).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Unit quaternions ``[..., 4]`` in the given order, scalar part >= 0, from rotations ``[..., 3, 3]``."""
    _check_order(order)
    R = np.asarray(R, dtype=np.float64)
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(R.shape[:-2] + (4,))
    xyzw = np.where(xyzw[..., 3:4] < 0, -xyzw, xyzw)
    return reorder_quat(xyzw, "xyzw", order)


def pose_from_tq(t: np.ndarray, q: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Rigid transforms ``[..., 4, 4]`` from translations ``[..., 3]`` and quaternions ``[..., 4]``."""
    R = quat_to_matrix(q, order)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_to_tq(T: np.ndarray, order: QuatOrder) -> tuple[np.ndarray, np.ndarray]:
    """Translations ``[..., 3]`` and quaternions ``[..., 4]`` of rigid transforms ``[..., 4, 4]``."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3], order)
