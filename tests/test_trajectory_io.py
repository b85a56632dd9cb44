"""Trajectory files: round trips, format detection, malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import random_trajectory
from vggt_slam_pp.errors import TrajectoryError
from vggt_slam_pp.io.trajectory import (
    Trajectory,
    detect_format,
    read_kitti,
    read_trajectory,
    write_trajectory,
)


@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])
def test_round_trip(tmp_path, rng, fmt):
    traj = random_trajectory(rng, 50, t0=1403638538.5778294 if fmt == "euroc" else 10.0)
    path = tmp_path / f"traj.{fmt}"
    write_trajectory(path, traj, fmt)
    assert detect_format(path) == fmt
    back = read_trajectory(path)
    assert len(back) == len(traj)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-7)
    if fmt == "kitti":
        assert not back.has_timestamps
        np.testing.assert_array_equal(back.timestamps, np.arange(50))
    else:
        np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=2e-9 if fmt == "euroc" else 1e-9)


def test_similarity_estimates_are_written_as_rigid_poses(tmp_path, rng):
    traj = random_trajectory(rng, 10)
    scaled = Trajectory(traj.timestamps, traj.poses.copy())
    scaled.poses[:, :3, :3] *= 2.5
    write_trajectory(tmp_path / "t.txt", scaled, "tum")
    back = read_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(back.poses[:, :3, :3], traj.poses[:, :3, :3], atol=1e-7)
    np.testing.assert_allclose(back.positions, traj.positions, atol=1e-7)


def test_kitti_times_file(tmp_path, rng):
    traj = random_trajectory(rng, 5)
    write_trajectory(tmp_path / "00.txt", traj, "kitti")
    (tmp_path / "00_times.txt").write_text("\n".join(f"{t:.3f}" for t in traj.timestamps))
    back = read_trajectory(tmp_path / "00.txt")  # the sibling times file is found
    assert back.has_timestamps
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-3)
    (tmp_path / "short.txt").write_text("1.0\n2.0\n")
    with pytest.raises(TrajectoryError, match="2 times but"):
        read_kitti(tmp_path / "00.txt", tmp_path / "short.txt")


@pytest.mark.parametrize(
    "content, fmt, message",
    [
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", "tum", r":2: TUM rows need exactly 8"),
        ("1.0 0 0 0 0 0 0 1\nfoo bar\n", "tum", r":2: not a row of numbers"),
        ("# only a comment\n", "tum", "has no poses"),
        ("1 0 0 0 0 1 0 0 0 0 1\n", "kitti", r":1: KITTI rows need exactly 12"),
        ("1.0 0 0 0 0 0 0 0\n", "tum", "invalid pose"),
    ],
)
def test_malformed_files_name_the_problem(tmp_path, content, fmt, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(TrajectoryError, match=message):
        read_trajectory(path, fmt)


def test_missing_file_and_unknown_format(tmp_path):
    with pytest.raises(TrajectoryError, match="not found"):
        read_trajectory(tmp_path / "nope.txt")
    (tmp_path / "five.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(TrajectoryError, match="cannot tell the trajectory format"):
        read_trajectory(tmp_path / "five.txt")


def test_readers_agree_with_evo(tmp_path, rng, shared_data):
    from evo.tools import file_interface

    gt_dir = shared_data / "gt_trajectories_only"
    tum = gt_dir / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz-groundtruth.txt"
    ours, theirs = read_trajectory(tum), file_interface.read_tum_trajectory_file(str(tum))
    np.testing.assert_allclose(ours.poses, np.array(theirs.poses_se3), atol=1e-12)
    np.testing.assert_allclose(ours.timestamps, theirs.timestamps)
    kitti = gt_dir / "kitti_odometry_poses" / "07.txt"
    np.testing.assert_allclose(read_trajectory(kitti).poses,
                               np.array(file_interface.read_kitti_poses_file(str(kitti)).poses_se3), atol=1e-12)
    euroc = gt_dir / "euroc" / "V1_02_medium-state_groundtruth_estimate0-data.csv"
    ours, theirs = read_trajectory(euroc), file_interface.read_euroc_csv_trajectory(str(euroc))
    np.testing.assert_allclose(ours.poses, np.array(theirs.poses_se3), atol=1e-12)
    np.testing.assert_allclose(ours.timestamps, theirs.timestamps, atol=1e-6)
