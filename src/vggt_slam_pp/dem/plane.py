"""The ground plane and the planar-canonical frame of the DEM (SPEC 3.6).

RANSAC on point triples, refined by SVD on the inliers; the normal points towards the cameras; the
in-plane axes are the dominant eigenvectors of the projected inliers; the origin is the inlier mean.
Canonical coordinates of a world point: ``(u, v, h)`` = (in-plane axis 1, axis 2, height along the
normal). The plane is fitted once (first submap(s)) and then kept fixed so tiles stay comparable.

Degradations (logged): without a dominant plane (inlier ratio below ``min_inlier_ratio``) the plane
of least variance of all points (PCA) is used; fewer than ``min_points`` points raise :class:`DemError`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.errors import DemError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlaneConfig:
    iterations: int = 500
    relative_threshold: float = 0.01  # inlier distance as a fraction of the points' spread
    min_inlier_ratio: float = 0.15
    min_points: int = 30
    max_points: int = 200_000  # random subset for the fit (seeded)
    seed: int = 0


@dataclass(frozen=True)
class GroundPlane:
    """``T_canon_world``: rows = (axis_u, axis_v, normal); canonical = R (p - origin)."""

    origin: np.ndarray  # [3]
    R: np.ndarray  # [3,3] rows axis_u, axis_v, normal (right-handed)
    inlier_ratio: float = 1.0
    degraded: bool = False

    @property
    def normal(self) -> np.ndarray:
        return self.R[2]

    def to_canonical(self, points: np.ndarray) -> np.ndarray:
        """World points [N,3] -> canonical (u, v, h) [N,3]."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.R.T

    def to_world(self, canonical: np.ndarray) -> np.ndarray:
        return np.asarray(canonical, dtype=np.float64) @ self.R + self.origin

    def to_dict(self) -> dict:
        return {"origin": self.origin.tolist(), "R": self.R.tolist(), "inlier_ratio": self.inlier_ratio,
                "degraded": self.degraded}

    @classmethod
    def from_dict(cls, d: dict) -> GroundPlane:
        return cls(np.asarray(d["origin"], float), np.asarray(d["R"], float), float(d["inlier_ratio"]),
                   bool(d["degraded"]))


def _frame_from(normal: np.ndarray, inliers: np.ndarray, origin: np.ndarray) -> np.ndarray:
    n = normal / np.linalg.norm(normal)
    proj = inliers - origin
    proj = proj - np.outer(proj @ n, n)
    # dominant in-plane direction of the projected inliers
    cov = proj.T @ proj
    w, V = np.linalg.eigh(cov)
    a = V[:, np.argmax(w)]
    a = a - (a @ n) * n
    if np.linalg.norm(a) < 1e-9:  # degenerate spread: any in-plane direction
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    return np.stack([a, b, n])


def fit_ground_plane(points: np.ndarray, camera_centers: np.ndarray | None = None,
                     config: PlaneConfig | None = None) -> GroundPlane:
    """Fit the ground plane to world points [N,3]; ``camera_centers`` [M,3] orient the normal."""
    c = config or PlaneConfig()
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1)]
    if len(P) < c.min_points:
        raise DemError(f"too few points for a ground plane: {len(P)} (need at least {c.min_points})")
    rng = np.random.default_rng(c.seed)
    if len(P) > c.max_points:
        P = P[rng.choice(len(P), c.max_points, replace=False)]
    spread = float(np.sqrt(np.mean(np.sum((P - P.mean(0)) ** 2, axis=1))))
    thr = max(c.relative_threshold * spread, 1e-9)
    best, best_count = None, -1
    for _ in range(c.iterations):
        a, b, d = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, d - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int(np.count_nonzero(np.abs((P - a) @ n) < thr))
        if count > best_count:
            best, best_count = (a, n), count
    ratio = best_count / len(P) if best is not None else 0.0
    degraded = best is None or ratio < c.min_inlier_ratio
    if degraded:
        log.warning("no dominant ground plane (best inlier ratio %.2f < %.2f): using the least-variance "
                    "plane of all points", ratio, c.min_inlier_ratio)
        inl = P
    else:
        a, n = best
        inl = P[np.abs((P - a) @ n) < thr]
    origin = inl.mean(axis=0)
    _, _, Vt = np.linalg.svd(inl - origin, full_matrices=False)
    normal = Vt[2]
    if camera_centers is not None and len(camera_centers):
        if (np.mean(camera_centers, axis=0) - origin) @ normal < 0:
            normal = -normal
    return GroundPlane(origin, _frame_from(normal, inl, origin), float(ratio), degraded)
