"""The outputs of a run with the back-end (SPEC 4), all written atomically into the run folder.

* ``keyframes.txt`` / ``.kitti``, ``frames.txt`` / ``.kitti``: the corrected trajectory (the odometry-only
  files are written by the pipeline beside them);
* ``graph.json``: nodes (corrected and odometry ``T_world_submap``, frames, keyframe camera centres), edges (odometry and loop, with
  sigmas and robust weights), covisibility edges with scores, every loop candidate with its verdict;
* ``map.ply``: the fused point cloud (each submap subsampled to ``ply_points_per_submap`` points, in its
  final pose), coloured by height above the ground plane (yellow ground to dark green, as the DEM);
* ``dem/``: the fused DEM (colour and grayscale PNG, ``.npz`` with heights, mpp, plane, origin);
* ``trajectory.png``: odometry, corrected and (when known) ground truth, seen from above.

Returns the report fields: ``ate_rmse`` (with ground truth), ``loops_accepted``, ``loops_rejected`` (of which
``loops_pending`` and ``loops_dropped_by_graph``),
``backend_s_per_submap``, ``backend_timings``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from vggt_slam_pp.backend.backend import BackendResult
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.dem import DemGrid, GroundPlane, export_dem, rasterize
from vggt_slam_pp.dem.images import height_ramp
from vggt_slam_pp.dem.map import fuse_layers
from vggt_slam_pp.errors import EvaluationError, VggtSlamError
from vggt_slam_pp.frontend.frontend import FrontendResult
from vggt_slam_pp.geometry.lie import sim3_inverse, transform_points
from vggt_slam_pp.io.trajectory import Trajectory, atomic_write_text, write_kitti, write_tum

log = logging.getLogger(__name__)


def write_backend_outputs(out: Path, source, result: FrontendResult, backend: BackendResult, store: SubmapStore,
                          ply_points_per_submap: int = 20_000, prior=None) -> dict:
    """``prior``: the :class:`~vggt_slam_pp.backend.mapfile.SavedMap` this recording was added to (its
    submaps join ``graph.json``, ``map.ply`` and the DEM)."""
    out = Path(out)
    corrected = dataclasses.replace(result, T_world_submap=[backend.poses[sm.id] for sm in result.submaps])
    kf, kf_odo = corrected.keyframe_trajectory(), result.keyframe_trajectory()
    write_tum(out / "keyframes.txt", kf)
    write_kitti(out / "keyframes.kitti", kf)
    allf = corrected.all_frame_trajectory()
    write_tum(out / "frames.txt", allf)
    write_kitti(out / "frames.kitti", allf)
    _write_graph(out / "graph.json", result, backend, prior)
    accepted = [c for c in backend.loops if c["accepted"]]
    fields: dict = {
        "loops_accepted": len(accepted), "loops_rejected": len(backend.loops) - len(accepted),
        # of the rejected: verified geometrically but left without a cycle-consistent partner, or switched
        # off by the final robust solve (docs/backend.md, "loop acceptance")
        "loops_pending": sum(c["reason"].startswith("verified, but") for c in backend.loops),
        "loops_dropped_by_graph": sum(c["reason"].startswith("rejected by the pose graph") for c in backend.loops),
        "backend_s_per_submap": float(np.mean(backend.seconds_per_submap)) if backend.seconds_per_submap else 0.0,
        "backend_s_per_submap_max": float(np.max(backend.seconds_per_submap)) if backend.seconds_per_submap else 0.0,
        "backend_timings": backend.timings,
    }
    gt_pair = source.frame_ground_truth()
    gt = None
    if gt_pair is not None:
        from vggt_slam_pp.eval import compute_ate

        gt = gt_pair[1]
        try:
            fields["ate_rmse"] = compute_ate(gt, kf, "sim3").rmse
            fields["ate_rmse_all_frames"] = compute_ate(gt, allf, "sim3").rmse
        except (EvaluationError, VggtSlamError) as exc:
            log.warning("ATE not computed: %s", exc)
    try:
        _write_map(out, result, backend, store, ply_points_per_submap)
    except VggtSlamError as exc:  # a map that cannot be drawn must not lose the trajectory
        log.warning("map outputs skipped: %s", exc)
    _plot(out / "trajectory.png", kf_odo, kf, gt)
    return fields


def write_keyframes_snapshot(out: Path, submaps: list, poses) -> None:
    """``keyframes.txt`` (TUM) at a pose snapshot taken mid-run: the keyframes of every submap the
    snapshot has a pose for. Written atomically, so an interrupted run leaves a consistent trajectory."""
    have = [sm for sm in submaps if sm.id in poses]
    if not have:
        return
    partial = FrontendResult(have, [], [np.asarray(poses[sm.id]) for sm in have], [], {})
    write_tum(Path(out) / "keyframes.txt", partial.keyframe_trajectory())


def _write_graph(path: Path, result: FrontendResult, backend: BackendResult, prior=None) -> None:
    known = [(sm.id, sm.frames, sm.camera_centers) for sm in prior.submaps] if prior is not None else []
    known += [(sm.id, sm.frame_indices, [sim3_inverse(T)[:3, 3] for T in sm.prediction.T_cam_submap])
              for sm in result.submaps]
    nodes = [{"id": i, "frames": [int(f) for f in frames], "T_world_submap": backend.poses[i].tolist(),
              "T_world_submap_odometry": backend.odometry_poses[i].tolist(),
              "camera_centers": [np.asarray(c, float).tolist() for c in centres],
              "placed": i in backend.placed} for i, frames, centres in known]
    graph = {"nodes": nodes, "edges": backend.edges, "covisibility": backend.covisibility,
             "loop_candidates": backend.loops,
             "rejected": [c for c in backend.loops if not c["accepted"]],
             "plane": backend.plane, "tile_size": backend.tile_size, "mpp": backend.mpp}
    atomic_write_text(path, json.dumps(graph, indent=1, default=json_default))


def json_default(o):
    """``json.dumps(default=...)`` for numpy values (arrays, numpy scalars); anything else as text."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def _height_colors(h: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(h, [1, 99]) if len(h) else (0.0, 1.0)
    return height_ramp(np.clip((h - lo) / max(hi - lo, 1e-9), 0, 1)).astype(np.uint8)


def _write_map(out: Path, result: FrontendResult, backend: BackendResult, store: SubmapStore, per_submap: int,
               max_side_px: int = 4096) -> None:
    """``map.ply`` and the fused DEM. The DEM keeps the back-end's resolution unless the map is larger than
    ``max_side_px`` pixels on a side; then it is exported at an integer multiple of it (a city-scale run
    would otherwise need gigabytes for one image)."""
    if backend.plane is None or backend.mpp is None:
        return
    plane = GroundPlane.from_dict(backend.plane)
    clouds, lo, hi = [], np.full(2, np.inf), np.full(2, -np.inf)
    for sid in sorted(backend.poses):
        pts = store.get(sid)
        if len(pts) == 0:
            continue
        world = transform_points(backend.poses[sid], pts)
        sel = world if len(world) <= per_submap else world[np.linspace(0, len(world) - 1, per_submap).astype(int)]
        clouds.append(sel.astype(np.float32))
        uv = plane.to_canonical(sel)[:, :2]
        lo, hi = np.minimum(lo, uv.min(0)), np.maximum(hi, uv.max(0))
    if not clouds:
        return
    factor = max(1, int(np.ceil(float(np.max(hi - lo)) / backend.mpp / max_side_px)))
    tile_px = int(round(backend.tile_size / backend.mpp))
    grid = DemGrid(plane, backend.mpp * factor, max(1, tile_px // factor))
    if factor > 1:
        log.info("DEM export at %.3f m/px (%dx the back-end's) to stay within %d px", grid.mpp, factor, max_side_px)
    layers = []
    for sid in sorted(backend.poses):
        pts = store.get(sid)
        if len(pts):
            layer = rasterize(transform_points(backend.poses[sid], pts), grid, sid)
            layers.append((layer.origin_px, layer.heights.astype(np.float16)))
    cloud = np.concatenate(clouds)
    colors = _height_colors(plane.to_canonical(cloud)[:, 2])
    _write_ply(out / "map.ply", cloud, colors)
    fused, origin = fuse_layers(layers)
    export_dem(out / "dem", fused, grid.mpp, plane, origin)


def _write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    rec = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        f.write(header)
        f.write(rec.tobytes())
    tmp.replace(path)


def _plot(path: Path, odometry: Trajectory, corrected: Trajectory, gt: Trajectory | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vggt_slam_pp.eval.metrics import align_trajectory, associate

    series = {"odometry": odometry, "corrected": corrected}
    xyz = {}
    ref = None
    if gt is not None:
        ref = gt.positions
        for name, tr in series.items():
            try:
                i_ref, i_est = associate(gt, tr)
                aligned, _, _ = align_trajectory(gt.poses[i_ref], tr.poses[i_est], "sim3")
                xyz[name] = aligned[:, :3, 3]
            except VggtSlamError:
                xyz[name] = tr.positions
    else:
        xyz = {name: tr.positions for name, tr in series.items()}
    base = ref if ref is not None else xyz["corrected"]
    centred = base - base.mean(0)
    axes = np.linalg.svd(centred, full_matrices=False)[2][:2]  # the plane of most motion
    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    if ref is not None:
        p = (ref - base.mean(0)) @ axes.T
        ax.plot(p[:, 0], p[:, 1], "k-", lw=1.5, label="ground truth")
    for name, style in (("odometry", "r--"), ("corrected", "b-")):
        p = (xyz[name] - base.mean(0)) @ axes.T
        ax.plot(p[:, 0], p[:, 1], style, lw=1, label=name)
    ax.set_aspect("equal")
    ax.legend()
    ax.set_title("trajectory (top view" + (", Sim(3)-aligned to ground truth)" if ref is not None else ")"))
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)
