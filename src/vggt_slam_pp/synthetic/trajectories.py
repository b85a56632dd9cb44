"""Camera trajectories for synthetic sequences (world z up, cameras in the OpenCV convention).

* :func:`figure8`: a figure-eight (lemniscate of Gerono); the crossing is visited twice from
  different directions.
* :func:`block_loop`: once around a city block counter-clockwise, a U-turn, then around it again
  clockwise on the outer lane: every place is revisited from the opposite direction.
* :func:`from_trajectory_file`: any TUM / KITTI / EuRoC trajectory (e.g. the real loops in
  ``shared/data/gt_trajectories_only``), resampled to N frames.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vggt_slam_pp.errors import SyntheticError, TrajectoryError
from vggt_slam_pp.io.trajectory import Trajectory, detect_format, read_trajectory

log = logging.getLogger(__name__)

__all__ = ["look_along", "figure8", "block_loop", "laps", "from_trajectory_file", "resample_path", "SCENES",
           "EUROC_T_BODY_CAM0"]

# Body (IMU) -> cam0 extrinsic of the EuRoC visual-inertial sensor (cam0/sensor.yaml, identical across
# the EuRoC sequences); used to turn EuRoC body trajectories into camera trajectories.
EUROC_T_BODY_CAM0 = np.array([
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
])
# KITTI's world is the first camera (x right, y down, z forward); this maps it to z up.
_KITTI_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])


def look_along(positions: np.ndarray, forward: np.ndarray, pitch_deg: float = -5.0) -> np.ndarray:
    """Camera poses ``T_world_cam [N, 4, 4]`` at ``positions [N, 3]`` looking along the horizontal
    direction of ``forward [N, 3]``, tilted by ``pitch_deg`` (negative looks down), no roll."""
    f = np.asarray(forward, dtype=np.float64).copy()
    f[:, 2] = 0.0
    norm = np.linalg.norm(f, axis=1, keepdims=True)
    if np.any(norm < 1e-12):
        raise SyntheticError("look_along: a forward direction is vertical or zero")
    f /= norm
    p = np.radians(pitch_deg)
    fwd = np.cos(p) * f + np.sin(p) * np.array([0.0, 0.0, 1.0])
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = right, down, fwd
    T[:, :3, 3] = positions
    return T


def resample_path(points: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points equally spaced in arc length along a dense polyline ``points [M, D]``, and the
    polyline's unit tangents there (taken from the dense path, so coarse resampling stays exact)."""
    points = points[np.r_[True, np.linalg.norm(np.diff(points, axis=0), axis=1) > 0]]  # no repeated points
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    q = np.linspace(0.0, s[-1], n)
    dense_tangent = np.gradient(points, s, axis=0)
    out = np.stack([np.interp(q, s, points[:, d]) for d in range(points.shape[1])], axis=1)
    tang = np.stack([np.interp(q, s, dense_tangent[:, d]) for d in range(points.shape[1])], axis=1)
    return out, tang / np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)


def _timestamps(n: int, fps: float) -> np.ndarray:
    return np.arange(n) / fps


def figure8(n_frames: int = 300, size: float = 40.0, height: float = 1.6, fps: float = 10.0,
            pitch_deg: float = -5.0) -> Trajectory:
    """Figure-eight of half-width ``size`` metres at camera ``height``, resampled to constant speed."""
    if n_frames < 2:
        raise SyntheticError("a trajectory needs at least 2 frames")
    t = np.linspace(0.0, 2 * np.pi, 4000)
    xy = np.c_[size * np.sin(t), size * np.sin(t) * np.cos(t)]
    xy, tang = resample_path(xy, n_frames)
    pos = np.c_[xy, np.full(n_frames, height)]
    return Trajectory(_timestamps(n_frames, fps), look_along(pos, np.c_[tang, np.zeros(n_frames)], pitch_deg))


def _turtle(commands: list[tuple], start: np.ndarray, heading: float, step: float) -> np.ndarray:
    """Dense 2-D path from ``("S", length)`` straights and ``("A", radius, angle)`` arcs (left > 0)."""
    pts = [np.asarray(start, dtype=np.float64)]
    pos, h = pts[0].copy(), heading
    for cmd in commands:
        if cmd[0] == "S":
            k = max(1, int(np.ceil(cmd[1] / step)))
            for _ in range(k):
                pos = pos + (cmd[1] / k) * np.array([np.cos(h), np.sin(h)])
                pts.append(pos)
        else:
            r, ang = cmd[1], cmd[2]
            k = max(2, int(np.ceil(abs(ang) * r / step)))
            centre = pos + r * np.sign(ang) * np.array([-np.sin(h), np.cos(h)])
            a0 = h - np.sign(ang) * np.pi / 2
            for j in range(1, k + 1):
                a = a0 + ang * j / k
                pts.append(centre + r * np.array([np.cos(a), np.sin(a)]))
            h += ang
            pos = pts[-1]
    return np.array(pts)


def block_loop(n_frames: int = 300, length: float = 60.0, width: float = 40.0, corner_radius: float = 6.0,
               lane_offset: float = 4.0, height: float = 1.6, fps: float = 10.0, pitch_deg: float = -5.0
               ) -> Trajectory:
    """Around a ``length x width`` block counter-clockwise, a U-turn to the outer lane, then clockwise."""
    if n_frames < 2:
        raise SyntheticError("a trajectory needs at least 2 frames")
    Ls, Ws = length - 2 * corner_radius, width - 2 * corner_radius
    if Ls <= 0 or Ws <= 0:
        raise SyntheticError("block is smaller than twice its corner radius")
    r_out = corner_radius + lane_offset
    q = np.pi / 2
    ccw = [("S", Ls / 2), ("A", corner_radius, q), ("S", Ws), ("A", corner_radius, q), ("S", Ls),
           ("A", corner_radius, q), ("S", Ws), ("A", corner_radius, q), ("S", Ls / 2)]
    uturn = [("A", lane_offset / 2, -np.pi)]
    cw = [("S", Ls / 2), ("A", r_out, -q), ("S", Ws), ("A", r_out, -q), ("S", Ls), ("A", r_out, -q),
          ("S", Ws), ("A", r_out, -q), ("S", Ls / 2)]
    xy = _turtle(ccw + uturn + cw, np.array([0.0, -width / 2]), 0.0, 0.05)
    xy, tang = resample_path(xy, n_frames)
    pos = np.c_[xy, np.full(n_frames, height)]
    return Trajectory(_timestamps(n_frames, fps), look_along(pos, np.c_[tang, np.zeros(n_frames)], pitch_deg))


def laps(n_frames: int = 300, length: float = 60.0, width: float = 40.0, corner_radius: float = 6.0,
         laps: float = 1.4, lane_change: float = 1.0, height: float = 1.6, fps: float = 10.0,
         pitch_deg: float = -5.0) -> Trajectory:
    """Round a ``length x width`` block counter-clockwise ``laps`` times (the same direction every time,
    ``lane_change`` metres further out on each new lap, reached gradually): revisits that see the same
    facades from nearly the same viewpoints, as a camera driven round a block twice does."""
    if n_frames < 2:
        raise SyntheticError("a trajectory needs at least 2 frames")
    Ls, Ws = length - 2 * corner_radius, width - 2 * corner_radius
    if Ls <= 0 or Ws <= 0:
        raise SyntheticError("block is smaller than twice its corner radius")
    if laps <= 0:
        raise SyntheticError("laps must be positive")
    q = np.pi / 2
    lap = [("S", Ls / 2), ("A", corner_radius, q), ("S", Ws), ("A", corner_radius, q), ("S", Ls),
           ("A", corner_radius, q), ("S", Ws), ("A", corner_radius, q), ("S", Ls / 2)]
    xy = _turtle(lap, np.array([0.0, -width / 2]), 0.0, 0.05)
    xy = xy[:-1] if np.allclose(xy[-1], xy[0], atol=1e-6) else xy
    n_lap = len(xy)
    k = np.arange(int(np.ceil(laps * n_lap)))
    # each new lap lies lane_change further out, reached gradually: away from the block's centre (the origin)
    d = xy[k % n_lap]
    out = d + d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9) * (lane_change * k / n_lap)[:, None]
    xy, tang = resample_path(out, n_frames)
    pos = np.c_[xy, np.full(n_frames, height)]
    return Trajectory(_timestamps(n_frames, fps), look_along(pos, np.c_[tang, np.zeros(n_frames)], pitch_deg))


def from_trajectory_file(
    path: str | Path,
    n_frames: int | None = None,
    *,
    fmt: str = "auto",
    flatten: bool | None = None,
    height: float | None = None,
    fps: float = 10.0,
    pitch_deg: float = -5.0,
) -> tuple[Trajectory, str]:
    """Camera trajectory (z up) from a trajectory file, resampled to ``n_frames`` equally spaced in time.

    KITTI files are rotated from their camera-0 world (y down) to z up; EuRoC body poses are turned into
    cam0 poses with :data:`EUROC_T_BODY_CAM0`. Large paths (extent > 30 m) are ``outdoor`` and are
    flattened by default: the world is flat, so heights become ``height`` (default 1.65 m) and orientations
    keep the file's heading with a fixed ``pitch_deg``. Small paths are ``indoor`` and keep their 3-D
    poses, with the floor placed ``height`` (default 1.4 m) below the median camera height.

    Returns:
        the trajectory and the suggested world style (``outdoor`` or ``indoor``).
    """
    try:
        fmt = detect_format(path) if fmt == "auto" else fmt
        traj = read_trajectory(path, fmt)
    except TrajectoryError as exc:
        raise SyntheticError(str(exc)) from None
    if len(traj) < 2:
        raise SyntheticError(f"{path}: a trajectory needs at least 2 poses")
    poses = traj.poses
    if fmt == "kitti":
        poses = _KITTI_TO_Z_UP @ poses
    elif fmt == "euroc":
        poses = poses @ EUROC_T_BODY_CAM0
    order = np.argsort(traj.timestamps, kind="stable")
    keep = order[np.r_[True, np.diff(traj.timestamps[order]) > 0]]  # sorted, repeated stamps dropped
    poses, ts = poses[keep], traj.timestamps[keep]
    if len(keep) < len(traj):
        log.warning("%s: %d poses with unsorted or repeated timestamps dropped", path, len(traj) - len(keep))
    n = len(ts) if n_frames is None else int(n_frames)
    if n < 2:
        raise SyntheticError("a trajectory needs at least 2 frames")
    if n != len(ts):
        q = np.linspace(ts[0], ts[-1], n)
        rots = Slerp(ts, Rotation.from_matrix(poses[:, :3, :3]))(q).as_matrix()
        pos = np.stack([np.interp(q, ts, poses[:, d, 3]) for d in range(3)], axis=1)
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :3], poses[:, :3, 3] = rots, pos
    extent = float(np.linalg.norm(np.ptp(poses[:, :2, 3], axis=0)))
    style = "outdoor" if extent > 30.0 else "indoor"
    flatten = (style == "outdoor") if flatten is None else flatten
    if flatten:
        h = 1.65 if height is None else height
        fwd = poses[:, :3, 2]
        pos = np.c_[poses[:, :2, 3], np.full(n, h)]
        poses = look_along(pos, fwd, pitch_deg)
    else:
        h = 1.4 if height is None else height
        poses = poses.copy()
        poses[:, 2, 3] -= np.median(poses[:, 2, 3]) - h
        low = poses[:, 2, 3] < 0.2
        if low.any():
            log.warning("%s: %d poses are within 0.2 m of the floor; raised to 0.2 m", path, int(low.sum()))
            poses[low, 2, 3] = 0.2
    return Trajectory(_timestamps(n, fps), poses), style


SCENES = {"figure8": figure8, "loop": block_loop, "laps": laps}
"""Built-in scenes for ``vggt-slam-pp synth --scene``."""
