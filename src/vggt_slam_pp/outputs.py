"""Everything a run writes (SPEC 4), atomically, into its folder; the only module that serialises results.

:func:`prepare_run_folder` (before the run): ``config.json``, ``input.json``, old predictions cleared.
:func:`write_run_outputs` (after it, also after an error or Ctrl-C, from the submaps finished so far):

* ``keyframes_odometry.txt`` / ``.kitti``, ``frames_odometry.txt`` / ``.kitti``: the odometry trajectory
  (TUM with timestamps, 12-column KITTI; every input frame, non-keyframes interpolated in time);
* ``frames.csv``: ``index,timestamp,keyframe,interpolated,disparity_px,tracked,reason`` per frame;
* ``groundtruth.txt``: the input's ground truth at its frames (TUM), when it has one;
* ``report.json``: counts, per-stage timings, throughput, peak memory, odometry edges and, with ground
  truth, ``ate_rmse_odometry`` (Sim(3)-aligned, keyframes);
* ``report.html``: the same for people, figures embedded (:mod:`vggt_slam_pp.viz.report`);
* ``map.json`` last, when the run finished with the back-end (:mod:`vggt_slam_pp.backend.mapfile`).

With the back-end (:func:`write_backend_outputs`):

* ``keyframes.txt`` / ``.kitti``, ``frames.txt`` / ``.kitti``: the corrected trajectory (beside the
  odometry-only files);
* ``graph.json``: nodes (corrected and odometry ``T_world_submap``, frames, keyframe camera centres), edges (odometry and loop, with
  sigmas and robust weights), covisibility edges with scores, every loop candidate with its verdict;
* ``map.ply``: the fused point cloud (each submap in its final pose, optionally one point per
  ``map_voxel`` cube, at most ``ply_points_per_submap`` points), coloured by height above the ground
  plane (yellow ground to dark green, as the DEM), written one submap at a time;
* ``dem/``: the fused DEM (colour and grayscale PNG, ``.npz`` with heights, mpp, plane, origin), coarser
  past ``dem_max_side_px``, and then also ``dem/tiles/`` at the back-end's full resolution;
* ``trajectory.png``: odometry, corrected and (when known) ground truth, seen from above.

:func:`write_backend_outputs` returns the report fields: ``ate_rmse`` (with ground truth), ``loops_accepted``, ``loops_rejected`` (of which
``loops_pending`` and ``loops_dropped_by_graph``),
``backend_s_per_submap``, ``backend_timings``, ``odometry_scale_sigma`` (and ``odometry_scale_measured_by``).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vggt_slam_pp import __version__
from vggt_slam_pp.backend.backend import BackendResult
from vggt_slam_pp.backend.mapfile import write_manifest
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.dem import DemGrid, GroundPlane, export_dem, rasterize
from vggt_slam_pp.dem.images import height_ramp
from vggt_slam_pp.dem.raster import fuse_layers
from vggt_slam_pp.errors import EvaluationError, VggtSlamError
from vggt_slam_pp.frontend.frontend import FrontendResult
from vggt_slam_pp.geometry.lie import sim3_inverse, transform_points
from vggt_slam_pp.io.trajectory import Trajectory, atomic_write_text, write_kitti, write_tum
from vggt_slam_pp.resources import peak_rss_mb

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OutputConfig:
    ply_points_per_submap: int = 20_000  # map.ply: at most this many points of each submap
    map_voxel: float = 0.0  # map.ply: one point per cube of this size (world units) in each submap; 0: all
    dem_max_side_px: int = 4096  # exported DEM: coarser (an integer multiple of the back-end's mpp) beyond this
    html_report: bool = True  # report.html (figures, loops, timings, configuration) at the end of the run
    dem_tiles: bool = True  # a map beyond dem_max_side_px: also dem/tiles/ at the back-end's full resolution
    dem_tile_px: int = 2048  # side of those tiles (rounded to whole DEM tiles)


@dataclass
class RunStats:
    """How a run went, besides its results (the report's timings and resources)."""

    seconds_total: float
    read_s: float  # reading input frames
    error: BaseException | None  # what stopped the run (an error or KeyboardInterrupt); None: it finished
    backbone: dict  # the backbone's own description (Backbone.describe)
    frontend_s: float | None  # wall time of the frame loop; None when it did not finish
    backend_submit_s: float  # the front-end's time handing submaps over (a full inbox included)
    backend_finish_wait_s: float  # waiting for the back-end's last submaps and final solve
    backend_mode: str | None = None  # "process" or "inline"; None without the back-end
    backend_queue_wait_s: float = 0.0
    frontend_memory_trace: list = field(default_factory=list)  # (submaps sent, RSS MiB)
    backend_max_lag_submaps: int = 0


def prepare_run_folder(out: Path, config, input_record: dict | None, keep_predictions: bool) -> None:
    """Before a run: the folder exists, is no longer a map (``map.json`` comes back when the run finishes),
    holds the run's ``config.json`` (and ``input.json``); an earlier run's predictions are removed unless
    they are resumed (they must never be replayed into another run)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "map.json").unlink(missing_ok=True)
    atomic_write_text(out / "config.json", json.dumps(dataclasses.asdict(config), indent=2, default=str))
    if input_record is not None:
        atomic_write_text(out / "input.json", json.dumps(input_record, indent=2))
    if not keep_predictions:
        for old in (out / "predictions").glob("submap_*.safetensors"):
            old.unlink()


def write_run_outputs(out: Path, source, config, result: FrontendResult | None, backend: BackendResult | None,
                      stats: RunStats, prior=None, write_map: bool = True) -> dict:
    """Write a run's trajectories, back-end outputs, ``report.json`` and (finished, ``write_map``) its
    ``map.json``; returns the report. ``prior``: the saved map the recording was added to."""
    report = _report(source, config, result, stats)
    report.update(stats.backbone)
    report["timings"] = {**report.get("timings", {}), "backend_submit_s": stats.backend_submit_s,
                         "backend_finish_wait_s": stats.backend_finish_wait_s}
    if result is not None:
        _write_odometry(out, result)
    gt_pair = source.frame_ground_truth()
    if gt_pair is not None:  # the input's ground truth at its frames: the report and the viewer draw it
        write_tum(out / "groundtruth.txt", gt_pair[1])
    if result is not None and backend is not None:
        report.update(write_backend_outputs(out, source, result, backend, SubmapStore(out / "submaps", 0),
                                            config.outputs, prior=prior))
        if prior is not None:
            placed = set(backend.placed)
            report["map_submaps"] = len(prior.submaps)
            report["placed_submaps"] = sum(sm.id in placed for sm in result.submaps)
            report["placed_fraction"] = report["placed_submaps"] / max(len(result.submaps), 1)
        if "ate_rmse" in report and "ate_rmse_odometry" in report and report["ate_rmse_odometry"] > 0:
            report["ate_reduction"] = 1.0 - report["ate_rmse"] / report["ate_rmse_odometry"]
    if stats.backend_mode is not None:
        report["backend_mode"] = stats.backend_mode
        report["backend_queue_wait_s"] = stats.backend_queue_wait_s
        report["memory_trace"] = {"frontend": stats.frontend_memory_trace,
                                  "backend": backend.memory_trace if backend is not None else []}
        report["backend_max_lag_submaps"] = stats.backend_max_lag_submaps
    # the front-end's own rate: frames over the wall time of the frame loop (handing submaps to the back-end
    # or, inline, the back-end's own work included); the final back-end solve is not part of it
    report["frontend_fps"] = len(result.decisions) / max(stats.frontend_s, 1e-9) \
        if result and stats.frontend_s else None
    backend_peak = backend.peak_rss_mb if backend is not None and stats.backend_mode == "process" else 0.0
    report["peak_rss_mb"] = peak_rss_mb() + backend_peak
    report["peak_rss_mb_backend"] = backend_peak
    atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=json_default))
    if config.outputs.html_report:
        from vggt_slam_pp.viz.report import write_report

        try:
            write_report(out)
        except Exception as exc:  # noqa: BLE001 - the report is for people: it must never lose a run's outputs
            log.warning("report.html not written: %s", exc)
        peak = peak_rss_mb() + backend_peak  # the run's peak includes writing the report (report.html shows the
        if peak > report["peak_rss_mb"]:  # figure before it)
            report["peak_rss_mb"] = peak
            atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=json_default))
    if stats.error is None and backend is not None and write_map:
        first = len(prior.submaps) if prior is not None else 0
        write_manifest(out, first + len(result.submaps))  # last: the folder is now a complete map
    return report


def _write_trajectory(out: Path, stem: str, trajectory: Trajectory) -> None:
    """``stem.txt`` (TUM) and ``stem.kitti``."""
    write_tum(out / f"{stem}.txt", trajectory)
    write_kitti(out / f"{stem}.kitti", trajectory)


def _write_odometry(out: Path, result: FrontendResult) -> None:
    _write_trajectory(out, "keyframes_odometry", result.keyframe_trajectory())
    allf = result.all_frame_trajectory()
    _write_trajectory(out, "frames_odometry", allf)
    lines = ["index,timestamp,keyframe,interpolated,disparity_px,tracked,reason"]
    for (idx, ts, d), interp in zip(result.decisions, allf.interpolated, strict=True):
        lines.append(f"{idx},{ts:.9f},{int(d.is_keyframe)},{int(interp)},{d.disparity:.3f},{d.tracked},{d.reason}")
    atomic_write_text(out / "frames.csv", "\n".join(lines) + "\n")


def _ate(gt: Trajectory, est: Trajectory) -> dict:
    from vggt_slam_pp.eval import compute_ate

    try:
        ate = compute_ate(gt, est, "sim3")
    except (EvaluationError, VggtSlamError) as exc:
        log.warning("ATE not computed: %s", exc)
        return {}
    return {"rmse": ate.rmse, "n": ate.n_matched, "scale": ate.scale}


def _report(source, config, result: FrontendResult | None, stats: RunStats) -> dict:
    error = stats.error
    report: dict = {"version": __version__, "backbone": config.backbone.name, "calibrated": config.calibrated,
                    "frames": len(source), "seconds_total": stats.seconds_total, "peak_memory_mb": peak_rss_mb(),
                    "error": (str(error) or type(error).__name__) if error else None}
    if result is None:
        return report
    kf = result.keyframe_trajectory()
    total = stats.seconds_total
    report.update({
        "frames_processed": len(result.decisions), "keyframes": len(kf), "submaps": len(result.submaps),
        "fps": len(result.decisions) / total if total > 0 else None,
        "timings": {"read_s": stats.read_s, **result.timings},
        "path_length_odometry": kf.path_length(),
        "edges": [{"prev": e.prev, "curr": e.curr, "method": e.method, "residual": e.residual,
                   "inlier_ratio": e.inlier_ratio, "correspondences": e.num_correspondences,
                   "shared_frames": e.shared_frames, "degraded": e.degraded, "cause": e.cause}
                  for e in result.edges],
        "degraded_edges": sum(e.degraded for e in result.edges),
        "recovered_edges": sum(bool(e.cause) and not e.degraded for e in result.edges),
        "registered_frames": int(sum(sm.prediction.valid[sm.overlap:].sum() for sm in result.submaps)),
        "invalid_frames": [int(i) for sm in result.submaps for i, v in
                           zip(sm.frame_indices, sm.prediction.valid, strict=True) if not v],
        "points_per_submap": [sm.prediction.info.get("points_after_filter", sm.prediction.num_points())
                              for sm in result.submaps],
        # colmap: submaps whose mapping attempts contradicted their own matches (folded; retried), and the
        # keyframe pairs [first, second, agree, best, degrees] still contradicted in the kept reconstruction
        "folded_attempts": {str(sm.id): sm.prediction.info["folded_attempts"] for sm in result.submaps
                            if sm.prediction.info.get("folded_attempts")},
        "folded_pairs": {str(sm.id): sm.prediction.info["folded_pairs"] for sm in result.submaps
                         if sm.prediction.info.get("folded_pairs")},
    })
    gt_pair = source.frame_ground_truth()
    if gt_pair is not None:
        ate = _ate(gt_pair[1], kf)
        if ate:
            report["ate_rmse_odometry"] = ate["rmse"]
            report["ate_odometry"] = ate
            report["gt_path_length"] = gt_pair[1].path_length()
        ate_all = _ate(gt_pair[1], result.all_frame_trajectory())
        if ate_all:
            report["ate_rmse_odometry_all_frames"] = ate_all["rmse"]
    return report


def write_backend_outputs(out: Path, source, result: FrontendResult, backend: BackendResult, store: SubmapStore,
                          config: OutputConfig | None = None, prior=None) -> dict:
    """``prior``: the :class:`~vggt_slam_pp.backend.mapfile.SavedMap` this recording was added to (its
    submaps join ``graph.json``, ``map.ply`` and the DEM)."""
    out = Path(out)
    corrected = dataclasses.replace(result, T_world_submap=[backend.poses[sm.id] for sm in result.submaps])
    kf, kf_odo = corrected.keyframe_trajectory(), result.keyframe_trajectory()
    _write_trajectory(out, "keyframes", kf)
    allf = corrected.all_frame_trajectory()
    _write_trajectory(out, "frames", allf)
    _write_graph(out / "graph.json", result, backend, prior)
    accepted = [r for r in backend.loops if r.accepted]
    fields: dict = {
        "loops_accepted": len(accepted), "loops_rejected": len(backend.loops) - len(accepted),
        # of the rejected: verified geometrically but left without a cycle-consistent partner, or switched
        # off by the final robust solve (docs/backend.md, "loop acceptance")
        "loops_pending": sum(r.reason.startswith("verified, but") for r in backend.loops),
        "loops_dropped_by_graph": sum(r.reason.startswith("rejected by the pose graph") for r in backend.loops),
        "backend_s_per_submap": float(np.mean(backend.seconds_per_submap)) if backend.seconds_per_submap else 0.0,
        "backend_s_per_submap_max": float(np.max(backend.seconds_per_submap)) if backend.seconds_per_submap else 0.0,
        "backend_seconds_per_submap": [round(float(x), 4) for x in backend.seconds_per_submap],
        # the same in the back-end thread's CPU time: its work, without waiting for a CPU the front-end held
        "backend_cpu_s_per_submap": float(np.mean(backend.cpu_seconds_per_submap)) if backend.cpu_seconds_per_submap
        else 0.0,
        "backend_cpu_seconds_per_submap": [round(float(x), 4) for x in backend.cpu_seconds_per_submap],
        # the wall time per submap by stage (covisibility, registration, optimisation, re-description of moved layers)
        "backend_stage_seconds_per_submap": {k: [round(float(x), 4) for x in v]
                                             for k, v in backend.stage_seconds_per_submap.items()},
        "backend_timings": backend.timings,
        # submaps whose query was deferred while the back-end caught up (WorkerConfig.catch_up_lag)
        "backend_queries_deferred": len(backend.skipped),
        # the odometry's log-scale drift per submap the final solve used, where measured (from the cameras' heights
        # or the loops' cycles; docs/backend.md, "pose graph"); null: the configured sigma
        "odometry_scale_sigma": backend.odometry_scale_sigma,
        "odometry_scale_measured_by": backend.odometry_scale_measured_by,
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
        _write_map(out, backend, store, config or OutputConfig())
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


def _edge_dict(e, weight: float | None) -> dict:
    d = {"from": e.i, "to": e.j, "kind": e.kind, "T": e.T_ij.tolist(), "sigmas": e.sigmas.tolist(), **e.info}
    if e.information is not None:
        d["information"] = e.information.tolist()
    if weight is not None:
        d["robust_weight"] = weight
    return d


def _write_graph(path: Path, result: FrontendResult, backend: BackendResult, prior=None) -> None:
    """``graph.json``, one record per line as it is produced (no whole-graph copy in memory)."""
    placed = set(backend.placed)

    def nodes():
        known = ((sm.id, sm.frames, sm.camera_centers) for sm in prior.submaps) if prior is not None else ()
        mine = ((sm.id, sm.frame_indices, [sim3_inverse(T)[:3, 3] for T in sm.prediction.T_cam_submap])
                for sm in result.submaps)
        for i, frames, centres in itertools.chain(known, mine):
            yield {"id": i, "frames": [int(f) for f in frames], "T_world_submap": backend.poses[i].tolist(),
                   "T_world_submap_odometry": backend.odometry_poses[i].tolist(),
                   "camera_centers": [np.asarray(c, float).tolist() for c in centres], "placed": i in placed,
                   **({"camera_height": backend.heights[i]} if i in backend.heights else {})}

    def edges():
        weights = iter(backend.loop_weights)
        for e in backend.edges:
            yield _edge_dict(e, next(weights) if e.kind == "loop" else None)

    sections = {"nodes": nodes(), "edges": edges(),
                "covisibility": (dataclasses.asdict(c) for c in backend.covisibility),
                "loop_candidates": (r.to_dict() for r in backend.loops),
                "rejected": (r.to_dict() for r in backend.loops if not r.accepted),
                "deferred_queries": iter(backend.skipped)}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write("{")
        for k, (name, records) in enumerate(sections.items()):
            f.write(f'{"," if k else ""}\n "{name}": [')
            for j, rec in enumerate(records):
                f.write(("," if j else "") + "\n  " + json.dumps(rec, default=json_default))
            f.write("\n ]")
        for name, value in (("plane", backend.plane), ("tile_size", backend.tile_size), ("mpp", backend.mpp),
                            ("camera_height_world", {str(k): v for k, v in backend.height_refs.items()})):
            f.write(f',\n "{name}": {json.dumps(value, default=json_default)}')
        f.write("\n}\n")
    tmp.replace(path)


def json_default(o):
    """``json.dumps(default=...)`` for numpy values (arrays, numpy scalars); anything else as text."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def _height_colors(h: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return height_ramp(np.clip((h - lo) / max(hi - lo, 1e-9), 0, 1)).astype(np.uint8)


def submap_cloud(points: np.ndarray, T_world_submap: np.ndarray, per_submap: int, voxel: float = 0.0) -> np.ndarray:
    """A submap's share of ``map.ply`` [n,3] float32, world frame: its points (submap frame) at its pose, one
    per ``voxel``-sized cube when ``voxel`` > 0 (the first in the submap's order), then at most
    ``per_submap`` of them, evenly spaced in that order."""
    world = transform_points(T_world_submap, points)
    if voxel > 0 and len(world):
        keys = np.floor(world / voxel).astype(np.int64)
        keys -= keys.min(0)
        dims = keys.max(0) + 1
        flat = np.ravel_multi_index(keys.T, dims) if float(np.prod(dims.astype(float))) < 2**62 else None
        first = np.unique(flat, return_index=True)[1] if flat is not None else \
            np.unique(keys, axis=0, return_index=True)[1]
        world = world[np.sort(first)]
    if len(world) > per_submap:
        world = world[np.linspace(0, len(world) - 1, per_submap).astype(int)]
    return world.astype(np.float32)


_HEIGHT_SAMPLE = 500  # heights per submap that set map.ply's colour range (its 1st and 99th percentiles)
_PLY_CHUNK = 1 << 20  # points per write when map.ply is assembled


def _write_map(out: Path, backend: BackendResult, store: SubmapStore, config: OutputConfig) -> None:
    """``map.ply`` and the fused DEM, one submap at a time (never the whole map in memory).

    The points go to a temporary file as they are transformed (and voxel-filtered); ``map.ply`` is then
    assembled from it in chunks, coloured by height over a sample's 1st-99th percentile. The DEM keeps
    the back-end's resolution unless the map is larger than ``dem_max_side_px`` pixels on a side; then it
    is exported at an integer multiple of it (a city-scale run would otherwise need gigabytes for one
    image); each submap's layer is fused into it as it is rasterised."""
    if backend.plane is None or backend.mpp is None:
        return
    plane = GroundPlane.from_dict(backend.plane)
    ids = [sid for sid in sorted(backend.poses) if len(store.get(sid))]
    if not ids:
        return
    body = out / "map.ply.points.tmp"
    n, lo, hi, sample = 0, np.full(2, np.inf), np.full(2, -np.inf), []
    with open(body, "wb") as f:
        for sid in ids:
            sel = submap_cloud(store.get(sid), backend.poses[sid], config.ply_points_per_submap, config.map_voxel)
            if not len(sel):
                continue
            f.write(sel.tobytes())
            n += len(sel)
            can = plane.to_canonical(sel)
            lo, hi = np.minimum(lo, can[:, :2].min(0)), np.maximum(hi, can[:, :2].max(0))
            sample.append(can[:: max(1, len(can) // _HEIGHT_SAMPLE), 2].copy())  # a view would keep `can`
    try:
        h_lo, h_hi = np.percentile(np.concatenate(sample), [1, 99])
        _write_ply(out / "map.ply", body, n, plane, float(h_lo), float(h_hi))
    finally:
        body.unlink(missing_ok=True)
    factor = max(1, int(np.ceil(float(np.max(hi - lo)) / backend.mpp / config.dem_max_side_px)))
    tile_px = int(round(backend.tile_size / backend.mpp))
    grid = DemGrid(plane, backend.mpp * factor, max(1, tile_px // factor))
    if factor > 1:
        log.info("DEM export at %.3f m/px (%dx the back-end's) to stay within %d px", grid.mpp, factor,
                 config.dem_max_side_px)

    def layers():
        for sid in ids:
            layer = rasterize(transform_points(backend.poses[sid], store.get(sid)), grid, sid)
            yield layer.origin_px, layer.heights

    fused, origin = fuse_layers(layers())
    export_dem(out / "dem", fused, grid.mpp, plane, origin)
    del fused
    if factor > 1 and config.dem_tiles:
        _write_dem_tiles(out / "dem" / "tiles", backend, store, ids, plane, config)


def _write_dem_tiles(folder: Path, backend: BackendResult, store: SubmapStore, ids: list[int], plane: GroundPlane,
                     config: OutputConfig) -> None:
    """The fused DEM at the back-end's resolution, cut into square tiles of about ``dem_tile_px`` pixels
    (``tile_IV_IU.npz`` with ``_color.png`` beside it, as ``export_dem`` writes; ``index.json`` lists
    them with their origin pixels). One tile is in memory at a time, fused from the submaps whose extent
    touches it (each rasterised again for every tile it touches: one or a few)."""
    tile_px = int(round(backend.tile_size / backend.mpp))
    grid = DemGrid(plane, backend.mpp, tile_px)
    side = max(1, round(config.dem_tile_px / tile_px)) * tile_px
    boxes = {}  # each submap's canonical (u, v) extent: min, max [2, 2] (all its points, one at a time)
    for sid in ids:
        uv = plane.to_canonical(transform_points(backend.poses[sid], store.get(sid)))[:, :2]
        boxes[sid] = np.stack([uv.min(0), uv.max(0)])
    # a layer's pixel box, as rasterize pads it: whole DEM tiles from the one holding its lowest pixel
    px = {sid: np.floor(b / grid.mpp).astype(np.int64) for sid, b in boxes.items()}
    lo_px = {sid: (p[0] // tile_px) * tile_px for sid, p in px.items()}
    hi_px = {sid: p[1] + 1 for sid, p in px.items()}
    start = np.min([lo_px[s] for s in ids], axis=0)
    end = np.max([hi_px[s] for s in ids], axis=0)
    folder.mkdir(parents=True, exist_ok=True)
    index = []
    for v0 in range(int(start[1]), int(end[1]), side):
        for u0 in range(int(start[0]), int(end[0]), side):
            touching = [s for s in ids if lo_px[s][0] < u0 + side and hi_px[s][0] > u0
                        and lo_px[s][1] < v0 + side and hi_px[s][1] > v0]
            if not touching:
                continue
            canvas = np.full((side, side), -np.inf, np.float32)
            for sid in touching:
                layer = rasterize(transform_points(backend.poses[sid], store.get(sid)), grid, sid)
                (lu, lv), (rows, cols) = layer.origin_px, layer.heights.shape
                a_u, a_v = max(lu, u0), max(lv, v0)
                b_u, b_v = min(lu + cols, u0 + side), min(lv + rows, v0 + side)
                if a_u >= b_u or a_v >= b_v:
                    continue
                view = canvas[a_v - v0:b_v - v0, a_u - u0:b_u - u0]
                np.fmax(view, layer.heights[a_v - lv:b_v - lv, a_u - lu:b_u - lu], out=view)
            if not np.isfinite(canvas).any():
                continue
            canvas[~np.isfinite(canvas)] = np.nan
            name = f"tile_{(v0 - int(start[1])) // side:03d}_{(u0 - int(start[0])) // side:03d}"
            export_dem(folder, canvas, grid.mpp, plane, (u0, v0), name=name)
            index.append({"name": name, "origin_px": [u0, v0], "shape": [side, side]})
    atomic_write_text(folder / "index.json", json.dumps({"mpp": grid.mpp, "tile_px": side,
                                                         "plane": plane.to_dict(), "tiles": index}, indent=1))
    log.info("DEM tiles at %.3f m/px: %d of %d px a side in %s", grid.mpp, len(index), side, folder)


def _write_ply(path: Path, points_file: Path, n: int, plane: GroundPlane, h_lo: float, h_hi: float) -> None:
    """Binary little-endian PLY of the ``n`` float32 xyz points in ``points_file``, coloured by height."""
    rec_type = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f, open(points_file, "rb") as src:
        f.write(header)
        while chunk := src.read(_PLY_CHUNK * 12):
            xyz = np.frombuffer(chunk, "<f4").reshape(-1, 3)
            rgb = _height_colors(plane.to_canonical(xyz)[:, 2], h_lo, h_hi)
            rec = np.empty(len(xyz), rec_type)
            rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
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
