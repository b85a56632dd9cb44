"""A finished (or interrupted) run's folder, read back for people: the report and the viewer.

:func:`load_run` reads what :mod:`vggt_slam_pp.outputs` wrote (``report.json``, ``config.json``, the
trajectories, ``groundtruth.txt``, ``graph.json``, ``dem/dem.npz``) into a :class:`RunFolder`. Only
``report.json`` and ``keyframes_odometry.txt`` are required; everything else is optional (a run
without the back-end has no graph, no corrected trajectory and no DEM).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import InputError, VggtSlamError
from vggt_slam_pp.io.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

__all__ = ["RunFolder", "load_run", "aligned_positions", "motion_axes"]


@dataclass(frozen=True, eq=False)
class RunFolder:
    """What a run wrote, as read back. Trajectories are keyframes ``T_world_cam`` (TUM files)."""

    folder: Path
    report: dict
    config: dict
    odometry: Trajectory
    corrected: Trajectory | None  # keyframes.txt (with the back-end)
    ground_truth: Trajectory | None  # groundtruth.txt (when the input had one)
    graph: dict | None  # graph.json: nodes, edges, covisibility, loop_candidates, plane, tile_size
    dem: dict | None  # dem/dem.npz: heights [H, W] float32 (NaN: unknown), mpp, origin_px, plane

    @property
    def name(self) -> str:
        return self.folder.resolve().name

    @property
    def nodes(self) -> list[dict]:
        return list(self.graph.get("nodes", [])) if self.graph else []

    @property
    def loop_candidates(self) -> list[dict]:
        return list(self.graph.get("loop_candidates", [])) if self.graph else []

    def loop_edges(self) -> list[dict]:
        return [e for e in (self.graph or {}).get("edges", []) if e.get("kind") == "loop"]

    def keyframe_rotations(self) -> dict[int, np.ndarray]:
        """Frame index -> ``R_world_cam`` [3,3] of every keyframe (corrected when there is a corrected
        trajectory), matched through ``frames.csv``'s timestamps; {} without ``frames.csv``."""
        import csv

        path = self.folder / "frames.csv"
        if not path.is_file():
            return {}
        traj = self.corrected or self.odometry
        by_time = {round(float(t), 6): T[:3, :3] for t, T in zip(traj.timestamps, traj.poses, strict=True)}
        out = {}
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                R = by_time.get(round(float(row["timestamp"]), 6))
                if R is not None:
                    out[int(row["index"])] = R / np.cbrt(np.linalg.det(R))  # a similarity's scale divided out
        return out

    def submap_points(self, submap_id: int) -> tuple[np.ndarray, np.ndarray | None] | None:
        """A submap's points ``[N, 3]`` (its own frame) and colours ``[N, 3]`` uint8 (or None), from the
        run's submap store; None when the run kept none."""
        pts = self.folder / "submaps" / f"{submap_id:06d}.npy"
        if not pts.is_file():
            return None
        points = np.load(pts, mmap_mode="r")
        rgb = pts.with_name(f"{submap_id:06d}.rgb.npy")
        colors = np.load(rgb, mmap_mode="r") if rgb.is_file() else None
        if colors is not None and len(colors) != len(points):
            colors = None
        return points, colors


def _read_json(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path} is not readable JSON: {exc}") from None


def _read_trajectory(path: Path) -> Trajectory | None:
    if not path.is_file():
        return None
    try:
        return read_tum(path)
    except VggtSlamError as exc:
        raise InputError(f"{path}: {exc}") from None


def load_run(folder: str | Path) -> RunFolder:
    """Read a run folder.

    Raises:
        InputError: not a run folder (no ``report.json`` or no ``keyframes_odometry.txt``), or a file in
            it that cannot be read.
    """
    folder = Path(folder)
    report = _read_json(folder / "report.json")
    odometry = _read_trajectory(folder / "keyframes_odometry.txt")
    if report is None or odometry is None:
        raise InputError(f"not a run folder (no report.json or keyframes_odometry.txt): {folder}")
    dem = None
    npz = folder / "dem" / "dem.npz"
    if npz.is_file():
        try:
            with np.load(npz) as d:
                dem = {"heights": d["heights"], "mpp": float(d["mpp"]), "origin_px": d["origin_px"],
                       "plane": json.loads(str(d["plane"]))}
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"{npz} is not a readable DEM: {exc}") from None
    return RunFolder(folder, report, _read_json(folder / "config.json") or {}, odometry,
                     _read_trajectory(folder / "keyframes.txt"), _read_trajectory(folder / "groundtruth.txt"),
                     _read_json(folder / "graph.json"), dem)


def aligned_positions(trajectory: Trajectory, ground_truth: Trajectory | None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Camera centres ready to draw: ``(timestamps [M], positions [M, 3], truth [M, 3] or None,
    errors [M] or None)``. With ground truth the trajectory is Sim(3)-aligned to it (as the ATE), and
    only its poses that have a ground-truth pose are kept; without, it is returned as it is."""
    from vggt_slam_pp.eval.metrics import align_trajectory, associate

    if ground_truth is not None:
        try:
            i_ref, i_est = associate(ground_truth, trajectory)
            aligned, _, _ = align_trajectory(ground_truth.poses[i_ref], trajectory.poses[i_est], "sim3")
        except VggtSlamError as exc:
            log.warning("not aligned to the ground truth: %s", exc)
        else:
            p, truth = aligned[:, :3, 3], ground_truth.poses[i_ref][:, :3, 3]
            return trajectory.timestamps[i_est], p, truth, np.linalg.norm(p - truth, axis=1)
    return trajectory.timestamps, trajectory.positions, None, None


def motion_axes(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mean [3], axes [3,3])`` of a path [N,3]: rows are the directions of most motion first, the
    least last (a top view projects on the first two, a side view on the first and the last)."""
    mean = positions.mean(0)
    return mean, np.linalg.svd(positions - mean, full_matrices=False)[2]
