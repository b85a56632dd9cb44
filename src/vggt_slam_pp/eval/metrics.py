"""Absolute and relative trajectory error, following evo's conventions.

* Association: for every timestamp of the *shorter* trajectory, the nearest timestamp of the other
  within ``max_diff`` seconds (evo's ``associate_trajectories``; matches need not be unique).
* Alignment (``sim3`` | ``se3`` | ``none``): Umeyama of the estimated positions onto the reference
  positions; with ``sim3`` the estimate is scaled, then rigidly moved (evo's ``align(correct_scale=True)``).
* ATE: statistics of ``||p_ref_i - p_est_i||`` over associated, aligned pairs (evo APE, translation part).
* RPE: for index pairs ``(i, i + delta)`` stepping by ``delta`` (evo's default, ``all_pairs=False``),
  ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; translation error ``||t(E)||`` and rotation angle of ``E`` in degrees.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from vggt_slam_pp.errors import EvaluationError, GeometryError
from vggt_slam_pp.geometry.alignment import umeyama
from vggt_slam_pp.geometry.lie import decompose_sim3, rotation_angle, se3_inverse
from vggt_slam_pp.io.trajectory import Trajectory, nearest_time_indices

AlignMode = Literal["sim3", "se3", "none"]
ALIGN_MODES: tuple[str, ...] = ("sim3", "se3", "none")

__all__ = ["ALIGN_MODES", "AlignMode", "AteResult", "RpeResult", "associate", "align_trajectory",
           "best_time_offset", "compute_ate", "compute_rpe", "submaps_placed_best"]


def associate(ref: Trajectory, est: Trajectory, max_diff: float = 0.01, offset: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i_ref [M], i_est [M])`` of matching timestamps (``est`` times shifted by ``offset``).

    Trajectories without real timestamps (KITTI rows) are matched by row index when both lack them.

    Raises:
        EvaluationError: only one of them has timestamps, or no pair matches within ``max_diff``.
    """
    if ref.has_timestamps != est.has_timestamps:
        which = "reference" if not ref.has_timestamps else "estimate"
        raise EvaluationError(f"the {which} has no timestamps (KITTI rows) but the other has; "
                              "give a times file for it")
    if not ref.has_timestamps:
        n = min(len(ref), len(est))
        if len(ref) != len(est):
            raise EvaluationError(f"KITTI trajectories without timestamps must have equal lengths "
                                  f"({len(ref)} vs {len(est)})")
        return np.arange(n), np.arange(n)
    t_ref = ref.timestamps
    t_est = est.timestamps + offset
    est_shorter = len(t_est) < len(t_ref)
    short, long_ = (t_est, t_ref) if est_shorter else (t_ref, t_est)
    match = nearest_time_indices(short, long_, max_diff)
    i_short = np.nonzero(match >= 0)[0]
    i_long = match[i_short]
    if len(i_short) == 0:
        raise EvaluationError(
            f"no timestamps match within {max_diff} s: reference spans [{t_ref.min():.3f}, {t_ref.max():.3f}] s, "
            f"estimate [{t_est.min():.3f}, {t_est.max():.3f}] s")
    return (i_long, i_short) if est_shorter else (i_short, i_long)


def _rigid(poses: np.ndarray) -> np.ndarray:
    """Poses with any similarity scale divided out of the rotation block."""
    _, R, t = decompose_sim3(poses)
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = t
    return out


def align_trajectory(ref_poses: np.ndarray, est_poses: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Align estimated poses to reference poses (both ``[M, 4, 4]``, already associated).

    Returns:
        aligned: ``[M, 4, 4]`` rigid poses: rotation ``R_a R_i``, translation ``s R_a t_i + t_a``.
        T_ref_est: ``[4, 4]`` the similarity ``[[s R_a, t_a], [0, 1]]`` that was applied.
        scale: ``s`` (1 unless ``mode == "sim3"``).
    """
    if mode not in ALIGN_MODES:
        raise EvaluationError(f"unknown alignment {mode!r}; expected one of {', '.join(ALIGN_MODES)}")
    est = _rigid(est_poses)
    if mode == "none":
        return est, np.eye(4), 1.0
    if len(est) < 3:
        raise EvaluationError(f"alignment needs at least 3 matched poses, got {len(est)}")
    try:
        T = umeyama(est[:, :3, 3], ref_poses[:, :3, 3], with_scale=(mode == "sim3"))
    except GeometryError as exc:
        raise EvaluationError(f"cannot align trajectories: {exc}") from None
    s, R, t = decompose_sim3(T)
    aligned = est.copy()
    aligned[:, :3, :3] = R @ est[:, :3, :3]
    aligned[:, :3, 3] = est[:, :3, 3] @ (s * R).T + t
    return aligned, T, float(s)


def _stats(err: np.ndarray) -> dict[str, float]:
    return {"rmse": float(np.sqrt(np.mean(err**2))), "mean": float(np.mean(err)),
            "median": float(np.median(err)), "std": float(np.std(err)), "min": float(np.min(err)),
            "max": float(np.max(err)), "sse": float(np.sum(err**2))}


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error (translation, world units of the reference)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    n_matched: int
    scale: float
    align: str
    T_ref_est: np.ndarray
    errors: np.ndarray
    index_ref: np.ndarray
    index_est: np.ndarray

    def summary(self) -> dict:
        """JSON-friendly dictionary with ``ate_*`` keys."""
        d = {f"ate_{k}": v for k, v in asdict(self).items()
             if k in ("rmse", "mean", "median", "std", "min", "max", "sse")}
        d.update(n_matched=self.n_matched, scale=self.scale, align=self.align,
                 T_ref_est=self.T_ref_est.tolist())
        return d


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over index pairs ``(i, i + delta)``."""

    trans_rmse: float
    trans_mean: float
    trans_median: float
    trans_max: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_max_deg: float
    delta: int
    n_pairs: int

    def summary(self) -> dict:
        return {f"rpe_{k}": v for k, v in asdict(self).items()}


def compute_ate(ref: Trajectory, est: Trajectory, align: str = "sim3", max_diff: float = 0.01,
                offset: float = 0.0) -> AteResult:
    """ATE of ``est`` against ``ref`` after association and alignment (see module docstring)."""
    i_ref, i_est = associate(ref, est, max_diff, offset)
    ref_p = ref.poses[i_ref]
    aligned, T, s = align_trajectory(ref_p, est.poses[i_est], align)
    err = np.linalg.norm(ref_p[:, :3, 3] - aligned[:, :3, 3], axis=1)
    return AteResult(**_stats(err), n_matched=len(err), scale=s, align=align, T_ref_est=T, errors=err,
                     index_ref=i_ref, index_est=i_est)


def best_time_offset(ref: Trajectory, est: Trajectory, span: float = 0.1, step: float = 0.005,
                     align: str = "sim3", max_diff: float = 0.01) -> tuple[float, AteResult] | None:
    """The time offset in ``[-span, span]`` s (steps of ``step``) added to ``est``'s times that minimises its
    ATE, with that ATE: a diagnostic, never part of a reported ATE. Both a camera clock that lags the ground
    truth's and an along-track error of the estimate (a scale error, say) show as an offset, so the offset
    alone does not tell which (docs/experiments.md, session 23). None when either trajectory lacks
    timestamps, when the reference is too sparse to be matched at shifted times (median spacing over
    ``2 * max_diff``: photo walks, frame-index times), or when there is no ATE at offset 0 (too few matches,
    no finite error). Offsets at which fewer poses match than at 0 are skipped (a shift must not drop the
    hard ends)."""
    if not (ref.has_timestamps and est.has_timestamps) or len(ref) < 2 or len(est) == 0:
        return None
    if float(np.median(np.diff(np.sort(ref.timestamps)))) > 2 * max_diff:
        return None
    try:
        base = compute_ate(ref, est, align, max_diff)
    except (EvaluationError, GeometryError):
        return None
    if not np.isfinite(base.rmse):
        return None
    best = (0.0, base)
    for offset in np.arange(-span, span + step / 2, step):
        try:
            r = compute_ate(ref, est, align, max_diff, float(offset))
        except (EvaluationError, GeometryError):
            continue
        if r.n_matched >= base.n_matched and r.rmse < best[1].rmse:
            best = (round(float(offset), 6), r)
    return best


def submaps_placed_best(submaps: list[tuple[np.ndarray, np.ndarray]], ref_positions: dict[int, np.ndarray]
                        ) -> tuple[float, int] | None:
    """The keyframe ATE (RMSE, reference units) with every submap placed where it fits the reference best: a
    diagnostic that splits a chained trajectory's error into what lies inside the submaps (this figure) and
    what the links between them add (the chained ATE above it).

    Args:
        submaps: per submap, ``(frame indices [S], camera centres [S,3] in the submap's frame)`` of its
            registered keyframes.
        ref_positions: reference camera position [3] per frame index.

    Each submap is fitted on its own (Umeyama Sim(3) of its centres onto the reference's); a keyframe counts
    once, in the first submap that holds it. Submaps with fewer than 3 referenced keyframes, or whose centres
    are degenerate (collinear), are left out. Returns (RMSE, submaps fitted), or None when none could be."""
    seen: set[int] = set()
    residuals, fitted = [], 0
    for frames, centres in submaps:
        keep = np.array([int(f) in ref_positions for f in frames], bool)
        if keep.sum() < 3:
            continue
        f_kept, c_kept = np.asarray(frames)[keep], np.asarray(centres, float)[keep]
        ref = np.array([ref_positions[int(f)] for f in f_kept])
        try:
            T = umeyama(c_kept, ref)
        except GeometryError:
            continue
        fitted += 1
        new = np.array([int(f) not in seen for f in f_kept], bool)
        seen.update(int(f) for f in f_kept)
        placed = c_kept[new] @ T[:3, :3].T + T[:3, 3]
        residuals.append(np.linalg.norm(placed - ref[new], axis=1))
    if not fitted:
        return None
    r = np.concatenate(residuals)
    return float(np.sqrt(np.mean(r ** 2))), fitted


def compute_rpe(ref: Trajectory, est: Trajectory, delta: int = 1, align: str = "sim3", max_diff: float = 0.01,
                offset: float = 0.0) -> RpeResult:
    """RPE with a frame step ``delta`` (evo's ``delta_unit=frames``, ``all_pairs=False``)."""
    if delta < 1:
        raise EvaluationError(f"RPE delta must be >= 1, got {delta}")
    i_ref, i_est = associate(ref, est, max_diff, offset)
    ref_p = _rigid(ref.poses[i_ref])
    aligned, _, _ = align_trajectory(ref_p, est.poses[i_est], align)
    ids = np.arange(0, len(ref_p), delta)
    if len(ids) < 2:
        raise EvaluationError(f"RPE needs at least two poses {delta} apart; {len(ref_p)} matched")
    a, b = ids[:-1], ids[1:]
    rel_ref = se3_inverse(ref_p[a]) @ ref_p[b]
    rel_est = se3_inverse(aligned[a]) @ aligned[b]
    E = se3_inverse(rel_ref) @ rel_est
    te = np.linalg.norm(E[:, :3, 3], axis=1)
    re = np.degrees(rotation_angle(E[:, :3, :3]))
    return RpeResult(float(np.sqrt(np.mean(te**2))), float(te.mean()), float(np.median(te)), float(te.max()),
                     float(np.sqrt(np.mean(re**2))), float(re.mean()), float(re.max()), delta, len(a))
