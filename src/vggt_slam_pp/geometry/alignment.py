"""Point-set alignment: Umeyama (with or without scale) and a robust Sim(3) estimator.

All functions estimate ``T_dst_src``, the transform that maps ``src`` points onto ``dst`` points:
``dst_i ~= s R src_i + t``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.geometry.lie import make_sim3, transform_points

log = logging.getLogger(__name__)

__all__ = ["umeyama", "RobustSim3", "estimate_sim3_robust"]


def _check_pairs(src: np.ndarray, dst: np.ndarray, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise GeometryError(f"src and dst must both be [N, 3]; got {src.shape} and {dst.shape}")
    if src.shape[0] < minimum:
        raise GeometryError(f"need at least {minimum} point pairs, got {src.shape[0]}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise GeometryError("point pairs contain NaN or inf")
    return src, dst


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares similarity (or rigid) transform ``T_dst_src [4, 4]`` (Umeyama 1991).

    Args:
        src: ``[N, 3]`` source points.
        dst: ``[N, 3]`` destination points, paired with ``src``.
        with_scale: estimate the scale (Sim(3)); otherwise the scale is fixed to 1 (SE(3)).
        weights: optional ``[N]`` non-negative weights.

    Raises:
        GeometryError: fewer than 3 pairs, non-finite values, or a degenerate (collinear / coincident)
            source set.
    """
    src, dst = _check_pairs(src, dst, 3)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(src),) or np.any(w < 0) or w.sum() <= 0:
        raise GeometryError("weights must be [N], non-negative, with a positive sum")
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(w @ np.sum(xs**2, axis=1))
    cov = (xd * w[:, None]).T @ xs
    U, D, Vt = np.linalg.svd(cov)
    if var_s < 1e-18 or D[1] < 1e-12 * max(D[0], 1e-300):
        raise GeometryError("degenerate point set: source points are coincident or collinear")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return make_sim3(s, R, t)


@dataclass(frozen=True)
class RobustSim3:
    """Result of :func:`estimate_sim3_robust`.

    Attributes:
        T_dst_src: ``[4, 4]`` estimated transform.
        inliers: ``[N]`` boolean inlier mask of the final refit.
        rmse: root-mean-square residual over the inliers (dst units).
        inlier_ratio: fraction of pairs that are inliers.
        threshold: the inlier threshold that was used (dst units).
        iterations: RANSAC hypotheses evaluated.
    """

    T_dst_src: np.ndarray
    inliers: np.ndarray
    rmse: float
    inlier_ratio: float
    threshold: float
    iterations: int


def estimate_sim3_robust(
    src: np.ndarray,
    dst: np.ndarray,
    threshold: float | None = None,
    *,
    relative_threshold: float = 0.02,
    with_scale: bool = True,
    max_iterations: int = 2000,
    confidence: float = 0.999,
    refit_rounds: int = 3,
    seed: int = 0,
) -> RobustSim3:
    """Robust ``T_dst_src`` by RANSAC over 3-point Umeyama hypotheses, then iterative refit on inliers.

    Args:
        src, dst: ``[N, 3]`` paired points, possibly with gross outliers.
        threshold: inlier distance in dst units. When ``None`` it is ``relative_threshold`` times the
            RMS distance of ``dst`` to its centroid, so it follows the scene's (unknown) scale.
        with_scale: Sim(3) when true, SE(3) otherwise.
        max_iterations: cap on RANSAC hypotheses (adaptively reduced with ``confidence``).
        refit_rounds: Umeyama refits on the growing inlier set after RANSAC.
        seed: seed of the sampler, so results are repeatable.

    Raises:
        GeometryError: too few pairs or no non-degenerate hypothesis with at least 3 inliers.
    """
    src, dst = _check_pairs(src, dst, 3)
    n = len(src)
    if threshold is None:
        spread = float(np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1))))
        threshold = relative_threshold * max(spread, 1e-12)
    if threshold <= 0:
        raise GeometryError(f"inlier threshold must be positive, got {threshold}")
    rng = np.random.default_rng(seed)
    thr2 = threshold**2
    best_inliers: np.ndarray | None = None
    best_cost = np.inf
    needed = max_iterations
    it = 0
    while it < min(needed, max_iterations):
        it += 1
        idx = rng.choice(n, size=3, replace=False)
        try:
            T = umeyama(src[idx], dst[idx], with_scale=with_scale)
        except GeometryError:
            continue
        r2 = np.sum((transform_points(T, src) - dst) ** 2, axis=1)
        inl = r2 < thr2
        cost = float(np.sum(np.minimum(r2, thr2)))  # MSAC: truncated quadratic
        if cost < best_cost and inl.sum() >= 3:
            best_cost, best_inliers = cost, inl
            ratio = inl.mean()
            if ratio >= 1.0:
                needed = it
            else:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1 - ratio**3, 1e-12))))
    if best_inliers is None:
        raise GeometryError(f"robust Sim(3) failed: no hypothesis with 3 inliers among {n} pairs")
    inliers = best_inliers
    T = umeyama(src[inliers], dst[inliers], with_scale=with_scale)
    for _ in range(refit_rounds):
        r2 = np.sum((transform_points(T, src) - dst) ** 2, axis=1)
        new = r2 < thr2
        if new.sum() < 3 or np.array_equal(new, inliers):
            break
        inliers = new
        T = umeyama(src[inliers], dst[inliers], with_scale=with_scale)
    r2 = np.sum((transform_points(T, src) - dst) ** 2, axis=1)
    rmse = float(np.sqrt(np.mean(r2[inliers])))
    log.debug("robust sim3: %d/%d inliers after %d hypotheses, rmse %.3g", inliers.sum(), n, it, rmse)
    return RobustSim3(T, inliers, rmse, float(inliers.mean()), float(threshold), it)
