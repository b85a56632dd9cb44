"""Trajectories and their file formats: TUM, KITTI (12 columns) and EuRoC CSV.

A :class:`Trajectory` holds camera (or body) poses ``T_world_cam`` with timestamps in seconds.

Formats
-------
* **TUM**: ``timestamp tx ty tz qx qy qz qw`` per line (quaternion scalar **last**), ``#`` comments.
* **KITTI**: 12 numbers per line, the row-major ``[R | t]`` 3x4 matrix; no timestamps (a separate
  times file with one number per line may give them; otherwise the row index is used).
* **EuRoC CSV**: ``timestamp_ns, px, py, pz, qw, qx, qy, qz[, ...]`` (quaternion scalar **first**),
  header line starting with ``#``; extra columns (velocities, biases) are ignored.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from vggt_slam_pp.errors import GeometryError, TrajectoryError
from vggt_slam_pp.geometry.quaternion import pose_from_tq, pose_to_tq

log = logging.getLogger(__name__)

TrajectoryFormat = Literal["tum", "kitti", "euroc"]
FORMATS: tuple[str, ...] = ("tum", "kitti", "euroc")

__all__ = [
    "FORMATS",
    "Trajectory",
    "TrajectoryFormat",
    "detect_format",
    "read_trajectory",
    "write_trajectory",
    "read_tum",
    "read_kitti",
    "read_euroc_csv",
    "write_tum",
    "write_kitti",
    "write_euroc_csv",
    "atomic_write_text",
    "nearest_time_indices",
]


@dataclass(frozen=True)
class Trajectory:
    """Timestamped poses.

    Attributes:
        timestamps: ``[N]`` float64 seconds, strictly increasing is not required but typical.
        poses: ``[N, 4, 4]`` float64 ``T_world_cam`` (rigid, or similarity for estimates).
        has_timestamps: False when the times are row indices (KITTI without a times file).
        interpolated: ``[N]`` bool, True for poses that were interpolated rather than estimated.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    has_timestamps: bool = True
    interpolated: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        ts = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(ts):
            raise TrajectoryError(f"trajectory needs [N] timestamps and [N, 4, 4] poses; got {ts.shape}, {poses.shape}")
        if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(poses))):
            raise TrajectoryError("trajectory contains NaN or inf")
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "poses", poses)
        if self.interpolated is not None:
            interp = np.asarray(self.interpolated, dtype=bool).reshape(-1)
            if len(interp) != len(ts):
                raise TrajectoryError("interpolated mask length differs from the number of poses")
            object.__setattr__(self, "interpolated", interp)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """``[N, 3]`` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        """Sum of distances between consecutive positions (world units)."""
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def subset(self, idx: np.ndarray) -> Trajectory:
        interp = None if self.interpolated is None else self.interpolated[idx]
        return Trajectory(self.timestamps[idx], self.poses[idx], self.has_timestamps, interp)

    def transformed(self, T_new_world: np.ndarray) -> Trajectory:
        """The same trajectory expressed in another world frame: ``T_new_cam = T_new_world @ T_world_cam``."""
        return Trajectory(self.timestamps, np.asarray(T_new_world) @ self.poses, self.has_timestamps,
                          self.interpolated)

    def interpolate_at(self, query: np.ndarray) -> Trajectory:
        """Poses at ``query`` times [M]: exact where a time matches, otherwise interpolated between the
        neighbouring poses (rotation slerp, linear translation, geometric scale for Sim(3) poses) and
        held constant before the first / after the last pose. ``interpolated`` marks the non-exact ones."""
        from scipy.spatial.transform import Rotation, Slerp

        query = np.asarray(query, dtype=np.float64).reshape(-1)
        order = np.argsort(self.timestamps, kind="stable")
        ts, P = self.timestamps[order], self.poses[order]
        scale = np.cbrt(np.linalg.det(P[:, :3, :3]))
        R = P[:, :3, :3] / scale[:, None, None]
        out = np.zeros((len(query), 4, 4))
        out[:, 3, 3] = 1.0
        exact = np.zeros(len(query), bool)
        pos = np.searchsorted(ts, query)
        for j, (q, i) in enumerate(zip(query, pos, strict=True)):
            if i < len(ts) and ts[i] == q:
                out[j], exact[j] = P[i], True
                continue
            if i == 0 or i == len(ts):
                out[j] = P[0] if i == 0 else P[-1]
                continue
            a = (q - ts[i - 1]) / (ts[i] - ts[i - 1])
            rot = Slerp([0.0, 1.0], Rotation.from_matrix(R[i - 1:i + 1]))([a]).as_matrix()[0]
            s = scale[i - 1] ** (1 - a) * scale[i] ** a
            out[j, :3, :3] = s * rot
            out[j, :3, 3] = (1 - a) * P[i - 1, :3, 3] + a * P[i, :3, 3]
        return Trajectory(query, out, self.has_timestamps, ~exact)

    def right_multiplied(self, T_cam_sensor: np.ndarray) -> Trajectory:
        """Poses of a rigidly attached sensor: ``T_world_sensor = T_world_cam @ T_cam_sensor``."""
        return Trajectory(self.timestamps, self.poses @ np.asarray(T_cam_sensor), self.has_timestamps,
                          self.interpolated)


def nearest_time_indices(query: np.ndarray, reference: np.ndarray, max_diff: float) -> np.ndarray:
    """For each ``query [N]`` time, the index of the nearest ``reference [M]`` time (any order), or -1 when
    the nearest is farther than ``max_diff`` seconds. A tie goes to the later reference time."""
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if len(reference) == 0:
        return np.full(len(query), -1)
    order = np.argsort(reference, kind="stable")
    srt = reference[order]
    pos = np.clip(np.searchsorted(srt, query), 0, len(srt) - 1)
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(srt[pos] - query) <= np.abs(query - srt[left]), pos, left)
    return np.where(np.abs(srt[pick] - query) <= max_diff, order[pick], -1)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _read_rows(path: Path, delimiter: str | None) -> list[tuple[int, list[float]]]:
    if not path.is_file():
        raise TrajectoryError(f"trajectory file not found: {path}")
    rows: list[tuple[int, list[float]]] = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"cannot read trajectory file {path}: {exc}") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("%"):
            continue
        parts = line.split(delimiter) if delimiter else line.replace(",", " ").split()
        try:
            rows.append((lineno, [float(p) for p in parts if p.strip() != ""]))
        except ValueError:
            raise TrajectoryError(f"{path}:{lineno}: not a row of numbers: {line[:60]!r}") from None
    if not rows:
        raise TrajectoryError(f"trajectory file has no poses: {path}")
    return rows


def _columns(path: Path, rows: list[tuple[int, list[float]]], ncols: int, fmt: str, exact: bool) -> np.ndarray:
    for lineno, vals in rows:
        if (len(vals) != ncols) if exact else (len(vals) < ncols):
            raise TrajectoryError(
                f"{path}:{lineno}: {fmt} rows need {'exactly' if exact else 'at least'} {ncols} numbers, "
                f"found {len(vals)}")
    return np.array([vals[:ncols] for _, vals in rows], dtype=np.float64)


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM file (``t tx ty tz qx qy qz qw``)."""
    path = Path(path)
    data = _columns(path, _read_rows(path, None), 8, "TUM", exact=True)
    try:
        poses = pose_from_tq(data[:, 1:4], data[:, 4:8], "xyzw")
    except GeometryError as exc:  # zero or non-finite quaternion
        raise TrajectoryError(f"{path}: invalid pose: {exc}") from None
    return Trajectory(data[:, 0], poses)


def read_kitti(path: str | os.PathLike, times: str | os.PathLike | None = None) -> Trajectory:
    """Read a KITTI pose file (12 numbers per row); ``times`` is an optional file of seconds per row."""
    path = Path(path)
    data = _columns(path, _read_rows(path, None), 12, "KITTI", exact=True)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    if times is None:
        return Trajectory(np.arange(len(data), dtype=np.float64), poses, has_timestamps=False)
    tpath = Path(times)
    t = _columns(tpath, _read_rows(tpath, None), 1, "times", exact=True)[:, 0]
    if len(t) != len(data):
        raise TrajectoryError(f"{tpath} has {len(t)} times but {path} has {len(data)} poses")
    return Trajectory(t, poses)


def read_euroc_csv(path: str | os.PathLike) -> Trajectory:
    """Read an EuRoC ground-truth CSV (``t[ns], px, py, pz, qw, qx, qy, qz, ...``)."""
    path = Path(path)
    data = _columns(path, _read_rows(path, ","), 8, "EuRoC CSV", exact=False)
    try:
        poses = pose_from_tq(data[:, 1:4], data[:, 4:8], "wxyz")
    except GeometryError as exc:
        raise TrajectoryError(f"{path}: invalid pose: {exc}") from None
    return Trajectory(data[:, 0] * 1e-9, poses)


def detect_format(path: str | os.PathLike) -> TrajectoryFormat:
    """Guess the format from the first data row: 12 columns -> KITTI, commas -> EuRoC, 8 -> TUM."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"trajectory file not found: {path}")
    with open(path, errors="replace") as fh:
        for line in fh:
            s = line.strip()
            if not s or s.startswith("#") or s.startswith("%"):
                continue
            if "," in s:
                return "euroc"
            n = len(s.split())
            if n == 12:
                return "kitti"
            if n == 8:
                return "tum"
            raise TrajectoryError(f"{path}: cannot tell the trajectory format from a row of {n} values "
                                  "(TUM has 8, KITTI 12, EuRoC CSV is comma-separated)")
    raise TrajectoryError(f"trajectory file has no poses: {path}")


def read_trajectory(path: str | os.PathLike, fmt: str = "auto", times: str | os.PathLike | None = None) -> Trajectory:
    """Read a trajectory in ``fmt`` (``auto``, ``tum``, ``kitti`` or ``euroc``)."""
    if fmt == "auto":
        fmt = detect_format(path)
    if fmt == "tum":
        return read_tum(path)
    if fmt == "kitti":
        if times is None:
            sibling = Path(path).with_name(Path(path).stem + "_times.txt")
            times = sibling if sibling.is_file() else None
        return read_kitti(path, times)
    if fmt == "euroc":
        return read_euroc_csv(path)
    raise TrajectoryError(f"unknown trajectory format {fmt!r}; expected one of auto, {', '.join(FORMATS)}")


def _sim3_to_rigid_rows(poses: np.ndarray) -> np.ndarray:
    """Rotation part with the scale divided out (similarity estimates store s R)."""
    out = poses.copy()
    s = np.cbrt(np.linalg.det(poses[:, :3, :3]))
    out[:, :3, :3] /= s[:, None, None]
    return out


def write_tum(path: str | os.PathLike, traj: Trajectory) -> None:
    t, q = pose_to_tq(_sim3_to_rigid_rows(traj.poses), "xyzw")
    lines = [f"{ts:.9f} {x[0]:.9f} {x[1]:.9f} {x[2]:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}"
             for ts, x, qq in zip(traj.timestamps, t, q, strict=False)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_kitti(path: str | os.PathLike, traj: Trajectory) -> None:
    rows = _sim3_to_rigid_rows(traj.poses)[:, :3, :].reshape(-1, 12)
    atomic_write_text(path, "\n".join(" ".join(f"{v:.9e}" for v in r) for r in rows) + "\n")


def write_euroc_csv(path: str | os.PathLike, traj: Trajectory) -> None:
    t, q = pose_to_tq(_sim3_to_rigid_rows(traj.poses), "wxyz")
    lines = ["#timestamp [ns], p_x [m], p_y [m], p_z [m], q_w [], q_x [], q_y [], q_z []"]
    lines += [f"{int(round(ts * 1e9))},{x[0]:.9f},{x[1]:.9f},{x[2]:.9f},{qq[0]:.9f},{qq[1]:.9f},{qq[2]:.9f},{qq[3]:.9f}"
              for ts, x, qq in zip(traj.timestamps, t, q, strict=False)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_trajectory(path: str | os.PathLike, traj: Trajectory, fmt: TrajectoryFormat) -> None:
    """Write ``traj`` atomically in ``fmt``. A similarity's scale is removed from the rotation part."""
    writers = {"tum": write_tum, "kitti": write_kitti, "euroc": write_euroc_csv}
    if fmt not in writers:
        raise TrajectoryError(f"unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)}")
    writers[fmt](path, traj)
