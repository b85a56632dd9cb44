"""Three trajectories no bench is tuned on, written as TUM files for ``bench loops --trajectory``.

    python benchmarks/heldout_trajectories.py [--out runs/heldout_trajectories]
    vggt-slam-pp bench loops --noise realistic --trajectory runs/heldout_trajectories/hall_drone.txt --seed S

The kinds of recording the shared ground truth does not cover, each revisiting its start:

- ``office_loop``: a hand-held walk round a 5 x 3.5 m room, 1.4 laps, looking ahead and about 25 deg
  inward, the camera's height wobbling by 7 cm;
- ``hall_drone``: a drone's two laps of a 14 x 8 m hall, climbing from 1.2 to 2.6 m and back, looking ahead
  and about 40 deg outward;
- ``block_walk``: a hand-held walk 1.25 times round a 12 x 6 m block of corridors.

All three are below the 30 m extent that makes a trajectory "outdoor", so the synthetic world is a room and
the 3-D poses are kept (``vggt_slam_pp.synthetic.trajectories.from_trajectory_file``). World z is up; the
camera looks along its z axis with y down (OpenCV). Deterministic: the same files every time. Their figures
are in docs/benchmarks.md ("Whole system").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from vggt_slam_pp.io.trajectory import Trajectory, write_tum
from vggt_slam_pp.synthetic.trajectories import look_along


def _write(path: Path, fps: float, positions: np.ndarray, forward: np.ndarray, pitch_deg: float,
           roll: np.ndarray | None = None) -> None:
    """A TUM file of cameras at ``positions`` [N,3] looking along ``forward`` [N,3] (levelled, then pitched by
    ``pitch_deg`` and rolled by ``roll`` [N] radians about their optical axis)."""
    poses = look_along(positions, forward, pitch_deg)
    if roll is not None:
        poses[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(np.c_[0 * roll, 0 * roll, roll]).as_matrix()
    write_tum(path, Trajectory(np.arange(len(poses)) / fps, poses))


def _ellipse(laps: float, n: int, a: float, b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(s, positions [N,2], tangents [N,2], outward [N,2])`` of ``laps`` laps of an ellipse."""
    s = np.linspace(0.0, laps, n)
    th = 2 * np.pi * s
    xy = np.c_[a * np.cos(th), b * np.sin(th)]
    tangent = np.c_[-a * np.sin(th), b * np.cos(th)]
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    return s, xy, tangent, xy / np.linalg.norm(xy, axis=1)[:, None]


def office_loop(path: Path) -> None:
    s, xy, tangent, outward = _ellipse(1.4, 1500, 2.5, 1.75)
    z = 1.45 + 0.07 * np.sin(2 * np.pi * 3.1 * s) + 0.02 * np.sin(2 * np.pi * 11 * s)
    yaw = np.radians(25 + 8 * np.sin(2 * np.pi * 5 * s))  # toward the room's middle
    forward = np.cos(yaw)[:, None] * tangent - np.sin(yaw)[:, None] * outward
    _write(path, 30.0, np.c_[xy, z], np.c_[forward, 0 * s], -12.0, np.radians(2 * np.sin(2 * np.pi * 7 * s)))


def hall_drone(path: Path) -> None:
    s, xy, tangent, outward = _ellipse(2.0, 2000, 7.0, 4.0)
    z = 1.9 - 0.7 * np.cos(np.pi * s)
    yaw = np.radians(40 + 15 * np.sin(2 * np.pi * 1.5 * s))  # toward the hall's walls
    forward = np.cos(yaw)[:, None] * tangent + np.sin(yaw)[:, None] * outward
    _write(path, 20.0, np.c_[xy, z], np.c_[forward, 0 * s], -15.0)


def block_walk(path: Path) -> None:
    n, laps, (w, h) = 1800, 1.25, (12.0, 6.0)
    s = np.linspace(0.0, laps, n)
    d = (s % 1.0) * 2 * (w + h)  # distance along the block's edge
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h], [0, 0]], float)
    lengths = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(corners, axis=0), axis=1))]
    xy = np.c_[np.interp(d, lengths, corners[:, 0]), np.interp(d, lengths, corners[:, 1])]
    side = np.minimum(np.searchsorted(lengths, d, side="right") - 1, 3)
    forward = np.diff(corners, axis=0)[side]
    xy = gaussian_filter1d(xy, 15, axis=0, mode="nearest")  # rounded corners
    forward = gaussian_filter1d(forward / np.linalg.norm(forward, axis=1)[:, None], 25, axis=0, mode="nearest")
    forward /= np.linalg.norm(forward, axis=1)[:, None]
    _write(path, 30.0, np.c_[xy, 1.5 + 0.05 * np.sin(2 * np.pi * 9 * s)], np.c_[forward, 0 * s], -10.0)


TRAJECTORIES = {"office_loop": office_loop, "hall_drone": hall_drone, "block_walk": block_walk}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/heldout_trajectories"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, make in TRAJECTORIES.items():
        make(args.out / f"{name}.txt")
        print(args.out / f"{name}.txt")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
