"""Batched SO(3), SE(3) and Sim(3) helpers on 4x4 homogeneous matrices.

Conventions
-----------
* A transform named ``T_a_b`` maps points expressed in frame ``b`` into frame ``a``.
* Sim(3) acts as ``x -> s * R @ x + t``; its matrix is ``[[s R, t], [0, 1]]``. SE(3) is the case ``s = 1``.
* Composition is matrix multiplication: ``T_a_c = T_a_b @ T_b_c``.
* Tangent vectors follow GTSAM's order so that they can be passed straight to the pose graph:
  SE(3) ``xi = [omega (3), u (3)]``, Sim(3) ``xi = [omega (3), u (3), sigma]`` with ``s = exp(sigma)``.
  The exponential is the matrix exponential of the algebra element ``[[sigma I + [omega]_x, u], [0, 0]]``.

Every function accepts arbitrary leading batch dimensions (``[..., 4, 4]``) and works in float64.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from vggt_slam_pp.errors import GeometryError

__all__ = [
    "hat",
    "so3_exp",
    "so3_log",
    "make_sim3",
    "decompose_sim3",
    "sim3_inverse",
    "se3_inverse",
    "sim3_exp",
    "sim3_log",
    "sim3_covariance_at_origin",
    "se3_exp",
    "se3_log",
    "transform_points",
    "rotation_angle",
]


def _as_batch(a: np.ndarray, tail: tuple[int, ...], name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.shape[a.ndim - len(tail):] != tail:
        raise GeometryError(f"{name} must have shape [..., {', '.join(map(str, tail))}], got {a.shape}")
    return a


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices of vectors. ``w [..., 3] -> [..., 3, 3]`` with ``hat(w) @ v == cross(w, v)``."""
    w = _as_batch(w, (3,), "w")
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices from rotation vectors (axis * angle). ``[..., 3] -> [..., 3, 3]``."""
    w = _as_batch(w, (3,), "w")
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape[:-1] + (3, 3))


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices (angle in [0, pi]). ``[..., 3, 3] -> [..., 3]``."""
    R = _as_batch(R, (3, 3), "R")
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def make_sim3(s: np.ndarray | float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build ``[[s R, t], [0, 1]]``. ``s [...]``, ``R [..., 3, 3]``, ``t [..., 3]`` -> ``[..., 4, 4]``."""
    R = _as_batch(R, (3, 3), "R")
    t = _as_batch(t, (3,), "t")
    s = np.asarray(s, dtype=np.float64)
    batch = np.broadcast_shapes(s.shape, R.shape[:-2], t.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def decompose_sim3(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split ``T [..., 4, 4]`` into scale ``[...]``, rotation ``[..., 3, 3]`` and translation ``[..., 3]``.

    The scale is the cube root of ``det(s R)``; a non-positive determinant (a reflection or a singular
    matrix) is rejected.
    """
    T = _as_batch(T, (4, 4), "T")
    det = np.linalg.det(T[..., :3, :3])
    if not np.all(np.isfinite(det)) or np.any(det <= 0):
        raise GeometryError("transform is not a similarity: det(sR) must be positive and finite")
    s = np.cbrt(det)
    R = T[..., :3, :3] / s[..., None, None]
    return s, R, T[..., :3, 3].copy()


def sim3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of Sim(3) (or SE(3)) transforms, in closed form. ``[..., 4, 4] -> [..., 4, 4]``."""
    s, R, t = decompose_sim3(T)
    Rt = np.swapaxes(R, -1, -2)
    return make_sim3(1.0 / s, Rt, -np.einsum("...ij,...j->...i", Rt, t) / s[..., None])


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms. ``[..., 4, 4] -> [..., 4, 4]``."""
    T = _as_batch(T, (4, 4), "T")
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _algebra(w: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """``sigma I + [w]_x`` for ``w [..., 3]`` and ``sigma [...]``."""
    return hat(w) + sigma[..., None, None] * np.eye(3)


def _left_jacobian(A: np.ndarray) -> np.ndarray:
    """``W = integral_0^1 expm(A tau) d tau`` for ``A [..., 3, 3]``, via the block exponential."""
    batch = A.shape[:-2]
    M = np.zeros(batch + (6, 6))
    M[..., :3, :3] = A
    M[..., :3, 3:] = np.eye(3)
    return expm(M)[..., :3, 3:]


def sim3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map ``[omega, u, sigma] [..., 7] -> [..., 4, 4]``."""
    xi = _as_batch(xi, (7,), "xi")
    M = np.zeros(xi.shape[:-1] + (4, 4))
    M[..., :3, :3] = _algebra(xi[..., :3], xi[..., 6])
    M[..., :3, 3] = xi[..., 3:6]
    T = expm(M)
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T


def sim3_log(T: np.ndarray) -> np.ndarray:
    """Logarithm map ``[..., 4, 4] -> [omega, u, sigma] [..., 7]`` (rotation angle in [0, pi])."""
    s, R, t = decompose_sim3(T)
    w = so3_log(R)
    sigma = np.log(s)
    W = _left_jacobian(_algebra(w, sigma))
    u = np.linalg.solve(W, t[..., None])[..., 0]
    return np.concatenate([w, u, sigma[..., None]], axis=-1)


def sim3_covariance_at_origin(cov: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The covariance [7,7] of a Sim(3) tangent perturbation ``[omega, u, sigma]`` of a frame (``T exp(xi)``: on
    the right, in the frame's own coordinates) taken about the frame's origin, from ``cov`` [7,7], the same
    perturbation taken about the point ``c`` [3] of that frame. A registration is known best where its data
    lie; its rotation and scale errors move the origin by the lever arm: ``u = v + [c]x omega - sigma c``
    (the adjoint of the translation to ``c``, exact)."""
    A = np.eye(7)
    A[3:6, 0:3] = hat(np.asarray(c, np.float64))
    A[3:6, 6] = -np.asarray(c, np.float64)
    return A @ np.asarray(cov, np.float64) @ A.T


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map ``[omega, u] [..., 6] -> [..., 4, 4]``."""
    xi = _as_batch(xi, (6,), "xi")
    return sim3_exp(np.concatenate([xi, np.zeros(xi.shape[:-1] + (1,))], axis=-1))


def se3_log(T: np.ndarray) -> np.ndarray:
    """Logarithm map ``[..., 4, 4] -> [omega, u] [..., 6]``; the scale of ``T`` must be 1."""
    return sim3_log(T)[..., :6]


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T [..., 4, 4]`` to ``points [..., N, 3]`` (batch dims broadcast) -> ``[..., N, 3]``."""
    T = _as_batch(T, (4, 4), "T")
    points = _as_batch(points, (3,), "points")
    return np.einsum("...ij,...nj->...ni", T[..., :3, :3], points) + T[..., None, :3, 3]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle in radians of rotation matrices ``[..., 3, 3] -> [...]`` (robust near 0 and pi)."""
    return np.linalg.norm(so3_log(R), axis=-1)
