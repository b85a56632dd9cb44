"""The facade: run the system on a frame source and write its outputs.

``run(source, config, out_dir)`` runs the front-end and (unless ``backend=False``) the back-end, and
writes, atomically, into ``out_dir``:

* ``keyframes_odometry.txt`` / ``.kitti``: keyframe poses (TUM with timestamps, 12-column KITTI);
* ``frames_odometry.txt`` / ``.kitti``: every input frame, non-keyframes interpolated in time;
* ``frames.csv``: ``index,timestamp,keyframe,interpolated,disparity_px,tracked,reason`` per frame;
* ``config.json``: the resolved configuration; ``report.json``: counts, per-stage timings, throughput,
  peak memory, odometry edges and, with ground truth, ``ate_rmse_odometry`` (Sim(3)-aligned, keyframes);
* ``predictions/``: every submap's raw prediction (safetensors), replayable with ``--backbone replay``;
* with the back-end (:mod:`vggt_slam_pp.outputs`): ``keyframes.txt``/``.kitti`` and ``frames.txt``/``.kitti``
  (corrected), ``graph.json``, ``map.ply``, ``dem/``, ``trajectory.png`` and the loop figures in the report;
  ``submaps/`` holds each submap's points (the back-end's on-disk store).

The back-end runs in its own process (:class:`~vggt_slam_pp.backend.worker.BackendWorker`; ``inline``
mode for tests); ``keyframes.txt`` follows its newest pose snapshot during the run. If the run fails
part-way (a :class:`VggtSlamError`) or is interrupted (Ctrl-C), the outputs of the submaps finished so far
are still written (odometry trajectories, ``keyframes.txt`` at the last snapshot), with the error in
``report.json``, and the error is re-raised.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vggt_slam_pp import __version__
from vggt_slam_pp.backend.backend import BackendConfig, BackendResult, SubmapMessage
from vggt_slam_pp.backend.mapfile import write_manifest
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.backend.worker import BackendWorker
from vggt_slam_pp.configs import PRESETS, from_dict, merged
from vggt_slam_pp.dem.raster import DemConfig
from vggt_slam_pp.errors import EvaluationError, FrontendError, InputError, VggtSlamError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.frontend import Frontend, FrontendConfig, FrontendResult
from vggt_slam_pp.frontend.odometry import chain
from vggt_slam_pp.geometry.lie import sim3_inverse
from vggt_slam_pp.io.frames import FrameSource
from vggt_slam_pp.io.trajectory import Trajectory, atomic_write_text, write_kitti, write_tum
from vggt_slam_pp.outputs import json_default, write_backend_outputs, write_keyframes_snapshot
from vggt_slam_pp.plugins import BACKBONES
from vggt_slam_pp.plugins import load as load_plugin
from vggt_slam_pp.resources import peak_rss_mb, reset_peak_rss, rss_mb

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BackboneConfig:
    name: str = "simulated"
    weights: str = "vggt-1b"  # vggt: name or path
    device: str = "auto"
    stride: int = 2  # dense backbones: pixel stride of the point grid
    replay_dir: str | None = None
    noise: str = "default"  # simulated: "default", "realistic" (monocular drift, 1-3 % of the path) or "zero"
    colmap_matcher: str = "exhaustive"  # colmap: "exhaustive" (all pairs in a submap) or "sequential"
    deterministic: bool = True  # colmap: the mapper on one thread too (bit-identical runs, ~30 % slower; docs/frontend.md)
    seed: int = 0


@dataclass(frozen=True)
class RunConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    calibrated: bool = False
    save_predictions: bool = True
    backend: bool = True  # loop closure; False = odometry only
    backend_config: BackendConfig = field(default_factory=BackendConfig)
    blas_threads: int = 1  # numpy / scipy BLAS threads in the front-end's process (0: the library's default).
    # The front-end's matrices are small: a second OpenBLAS thread spin-waits more than it computes (2 cores:
    # 88 -> 107 fps on the block loop with 1) and takes the core the back-end worker would use

    @classmethod
    def from_dict(cls, data: dict) -> RunConfig:
        """The configuration a run wrote to ``config.json`` (missing keys keep their defaults)."""
        return from_dict(cls, data)

    @classmethod
    def load(cls, path: str | Path) -> RunConfig:
        """Read ``config.json`` of an earlier run (or a file of the same form); one-line errors."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as exc:
            raise InputError(f"cannot read the configuration {path}: {exc.strerror or exc}") from None
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} is not JSON: {exc}") from None
        return from_dict(cls, data, where=str(path))

    @classmethod
    def preset(cls, name: str) -> RunConfig:
        """A named configuration from :data:`PRESETS`."""
        if name not in PRESETS:
            raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        return from_dict(cls, merged(dataclasses.asdict(cls()), PRESETS[name][1]), where=f"preset {name}")


def make_backbone(config: RunConfig, source: FrameSource) -> Backbone:
    """Instantiate the configured backbone for ``source`` (:data:`vggt_slam_pp.plugins.BACKBONES`)."""
    return load_plugin(BACKBONES, config.backbone.name, "backbone", FrontendError)(config, source)


def run(source: FrameSource, config: RunConfig, out_dir: str | Path, backbone: Backbone | None = None,
        progress: Callable[[int, int], None] | None = None, resume: bool = False,
        prior_map: str | Path | None = None, localize_only: bool = False) -> dict:
    """Run on ``source`` and write the outputs into ``out_dir``; returns the report dictionary.

    ``resume``: ``out_dir`` holds an interrupted run of the same input and configuration; the backbone
    calls it finished are read from its ``predictions/`` instead of being computed again, and everything
    else (keyframe selection, odometry, the back-end) runs again, deterministically, so the result is
    the uninterrupted run's (docs/frontend.md, "Resume").

    ``prior_map``: a finished run's folder (a map, :mod:`vggt_slam_pp.backend.mapfile`). The recording
    is added to it: its submaps are matched against the map by the same covisibility, place recognition
    and registration, come out in the map's frame once a loop places them, and the extended map is
    written to ``out_dir`` (never into the map's folder). ``localize_only``: the map is held fixed and
    not extended; ``out_dir`` then holds the recording's trajectory in the map's frame, not a map
    (docs/backend.md, "Maps")."""
    from threadpoolctl import threadpool_limits

    if config.blas_threads < 0:
        raise InputError(f"blas_threads must be >= 0 (0: the library default), got {config.blas_threads}")
    limit = threadpool_limits(config.blas_threads, user_api="blas") if config.blas_threads else nullcontext()
    with limit:
        return _run(source, config, out_dir, backbone, progress, resume, prior_map, localize_only)


def _run(source: FrameSource, config: RunConfig, out_dir: str | Path, backbone: Backbone | None,
         progress: Callable[[int, int], None] | None, resume: bool = False, prior_map: str | Path | None = None,
         localize_only: bool = False) -> dict:
    from vggt_slam_pp.frontend.backbones.replay import PredictionStore, ResumeBackbone

    out = Path(out_dir)
    prior = _open_prior_map(prior_map, out, config) if prior_map is not None else None
    if resume and not PredictionStore(out / "predictions").all():
        raise InputError(f"nothing to resume in {out}: no saved predictions (predictions/submap_*.safetensors)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "map.json").unlink(missing_ok=True)  # the folder is a map again only when this run finishes
    reset_peak_rss()  # peak_rss_mb: this run's, not whatever the calling process did before
    atomic_write_text(out / "config.json", json.dumps(dataclasses.asdict(config), indent=2, default=str))
    t0 = time.perf_counter()
    backbone = backbone or make_backbone(config, source)
    if resume:
        backbone = ResumeBackbone(backbone, out / "predictions")
    store = None
    if not resume:  # an earlier run's predictions in this folder must never be replayed into this one
        for old in PredictionStore(out / "predictions").all():
            old.unlink()
    if (config.save_predictions or resume) and config.backbone.name != "replay":
        store = PredictionStore(out / "predictions", keep_existing=resume)
    first_id = len(prior.submaps) if prior is not None else 0
    frontend = Frontend(backbone, config.frontend, store=store, first_id=first_id)
    backend_config = _scale_aware(config.backend_config, backbone)
    worker = None
    if config.backend:
        worker = BackendWorker(backend_config, out / "submaps", start_timeout_s=300.0 + 5.0 * first_id,
                               prior_map=(str(prior.folder), localize_only) if prior is not None else None)
    feeder = _BackendFeeder(frontend, worker, out)
    n = len(source)
    error: BaseException | None = None
    t_read = 0.0
    backend_result: BackendResult | None = None
    t_loop = time.perf_counter()
    frontend_s = None
    t_finish = 0.0
    try:
        for i in range(n):
            t = time.perf_counter()
            frame = source[i]
            if config.calibrated and frame.intrinsics is not None and frame.intrinsics.dist is not None \
                    and backbone.name != "colmap":
                frame = _undistorted(frame)
            t_read += time.perf_counter() - t
            if frontend.process(frame) is not None:
                feeder.feed()
            if progress:
                progress(i + 1, n)
        result = frontend.finish()
        feeder.feed()
        frontend_s = time.perf_counter() - t_loop
        if worker is not None:
            t = time.perf_counter()
            backend_result = worker.finish()
            t_finish = time.perf_counter() - t
    except (VggtSlamError, KeyboardInterrupt) as exc:
        error = exc
        log.error("run %s: %s; writing the outputs of %d finished submaps",
                  "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed", exc or "interrupted",
                  len(frontend.submaps))
        result = FrontendResult(frontend.submaps, frontend.edges, chain(frontend.edges), frontend.decisions,
                                dict(frontend.timings)) if frontend.submaps else None
        feeder.flush()
        if worker is not None:
            worker.close()
    finally:
        backbone.close()
    total = time.perf_counter() - t0
    report = _report(source, config, result, total, t_read, error)
    report.update(backbone.describe())
    report["timings"] = {**report.get("timings", {}), "backend_submit_s": feeder.seconds,
                         "backend_finish_wait_s": t_finish}
    if result is not None:
        _write_trajectories(out, result)
    if result is not None and backend_result is not None:
        report.update(write_backend_outputs(out, source, result, backend_result, SubmapStore(out / "submaps", 0),
                                            prior=prior))
        if prior is not None:
            placed = set(backend_result.placed)
            report["map_submaps"] = first_id
            report["placed_submaps"] = sum(sm.id in placed for sm in result.submaps)
            report["placed_fraction"] = report["placed_submaps"] / max(len(result.submaps), 1)
        if "ate_rmse" in report and "ate_rmse_odometry" in report and report["ate_rmse_odometry"] > 0:
            report["ate_reduction"] = 1.0 - report["ate_rmse"] / report["ate_rmse_odometry"]
    if worker is not None:
        report["backend_mode"] = worker.mode
        report["backend_queue_wait_s"] = worker.wait_s
        report["memory_trace"] = {"frontend": feeder.memory_trace,
                                  "backend": backend_result.memory_trace if backend_result is not None else []}
        report["backend_max_lag_submaps"] = feeder.max_lag
    # the front-end's own rate: frames over the wall time of the frame loop (any wait on a full back-end
    # queue or, inline, the back-end's own work included); the final back-end solve is not part of it
    report["frontend_fps"] = len(result.decisions) / max(frontend_s, 1e-9) if result and frontend_s else None
    backend_peak = backend_result.peak_rss_mb if backend_result is not None and worker.mode == "process" else 0.0
    report["peak_rss_mb"] = peak_rss_mb() + backend_peak
    report["peak_rss_mb_backend"] = backend_peak
    atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=json_default))
    if error is not None:
        raise error
    if backend_result is not None and not localize_only:
        write_manifest(out, first_id + len(result.submaps))  # last: the folder is now a complete map
    return report


def _open_prior_map(folder: str | Path, out: Path, config: RunConfig):
    """Check the map in ``folder`` and copy its submaps' points into ``out``'s store (the map's folder is
    never written to)."""
    import os
    import shutil

    from vggt_slam_pp.backend.mapfile import load_map

    if not config.backend:
        raise InputError("adding a recording to a map needs the back-end (drop --no-backend)")
    saved = load_map(folder)
    if out.resolve() == saved.folder.resolve():
        raise InputError(f"--out must not be the map's folder {saved.folder}: a map is never modified in place")
    store = out / "submaps"
    store.mkdir(parents=True, exist_ok=True)
    for sm in saved.submaps:
        src, dst = saved.store.path(sm.id), store / saved.store.path(sm.id).name
        dst.unlink(missing_ok=True)
        try:
            os.link(src, dst)  # the points never change: a hard link costs no space
        except OSError:
            shutil.copy2(src, dst)
    return saved


def _scale_aware(config: BackendConfig, backbone: Backbone) -> BackendConfig:
    """A backbone without metric scale (VGGT normalises each submap, COLMAP's scale is arbitrary) gets the
    DEM tile size "auto" (a fraction of the first submap's median depth) instead of the metric 2 m: with
    2 "units" of a normalised VGGT scene (about 20 m) the oracle VGGT closed 6-9 loops of the block loop
    where the simulated backbone closes 18-21 (docs/backend.md)."""
    dem = config.covisibility.dem
    if backbone.metric or isinstance(dem.tile_size, str) or dem.tile_size != DemConfig().tile_size:
        return config
    log.info("backbone %s has no metric scale: DEM tile size 'auto' (%.2f x the first submap's median depth)",
             backbone.name, dem.auto_tile_fraction)
    covis = dataclasses.replace(config.covisibility, dem=dataclasses.replace(dem, tile_size="auto"))
    return dataclasses.replace(config, covisibility=covis)


class _BackendFeeder:
    """Sends every finished submap to the back-end worker (points to the on-disk store first), releases
    the front-end's copy of the points it no longer needs (bounded memory), and keeps ``keyframes.txt``
    at the newest pose snapshot, so an interrupted run leaves its latest consistent trajectory."""

    def __init__(self, frontend: Frontend, worker: BackendWorker | None, out: Path) -> None:
        self.frontend, self.worker, self.out = frontend, worker, out
        self.sent = 0
        self.seconds = 0.0
        self._written = (-1, -1)
        # every ``trace_every`` submaps sent: (submaps sent, front-end RSS MiB)
        self.memory_trace: list[tuple[int, float]] = []
        self.trace_every = 10
        self.max_lag = 0  # most submaps the back-end was behind the front-end at a hand-over
        # keyframes.txt is rewritten (all keyframes) at most this often: every snapshot made long runs
        # quadratic (316 submaps: 30 s of the front-end's time); flush() writes the newest at the end
        self.write_interval_s = 2.0
        self._latest = None
        self._last_write = -np.inf

    def feed(self) -> None:
        if self.worker is None:
            return
        t = time.perf_counter()
        while self.sent < len(self.frontend.submaps):
            sm = self.frontend.submaps[self.sent]
            pred = sm.prediction
            pts = np.concatenate([p for p in pred.points if len(p)]) if pred.num_points() else np.zeros((0, 3))
            self.worker.store.put(sm.id, pts)
            centres = np.array([sim3_inverse(T)[:3, 3] for T in pred.T_cam_submap])
            edge = self.frontend.edges[self.sent - 1] if self.sent > 0 else None
            self.worker.submit(SubmapMessage(sm.id, centres, edge))
            self.sent += 1
        self.frontend.release_points(keep_last=1)
        snap = self.worker.latest()
        self._latest = snap or self._latest
        done = snap.last_submap + 1 - self.frontend.first_id if snap is not None else 0
        self.max_lag = max(self.max_lag, self.sent - max(done, 0))
        if time.perf_counter() - self._last_write >= self.write_interval_s:
            self._write_latest()
        if self.sent // self.trace_every > len(self.memory_trace):
            self.memory_trace.append((self.sent, rss_mb()))
        self.seconds += time.perf_counter() - t

    def _write_latest(self) -> None:
        snap = self._latest
        if snap is not None and (snap.version, snap.last_submap) != self._written:
            write_keyframes_snapshot(self.out, self.frontend.submaps, snap.poses)
            self._written = (snap.version, snap.last_submap)
            self._last_write = time.perf_counter()

    def flush(self) -> None:
        """``keyframes.txt`` at the newest snapshot now (a failed or interrupted run)."""
        if self.worker is None:
            return
        try:
            self._latest = self.worker.latest() or self._latest
        except VggtSlamError:  # the worker failed: keep the last snapshot it published
            pass
        self._write_latest()


def _undistorted(frame):
    cam = frame.intrinsics
    image = cam.undistort_image(frame.image)
    return dataclasses.replace(frame, image=image, intrinsics=cam.without_distortion(),
                               depth=None if frame.depth is None else cam.undistort_image(frame.depth))


def _write_trajectories(out: Path, result: FrontendResult) -> None:
    kf = result.keyframe_trajectory()
    write_tum(out / "keyframes_odometry.txt", kf)
    write_kitti(out / "keyframes_odometry.kitti", kf)
    allf = result.all_frame_trajectory()
    write_tum(out / "frames_odometry.txt", allf)
    write_kitti(out / "frames_odometry.kitti", allf)
    lines = ["index,timestamp,keyframe,interpolated,disparity_px,tracked,reason"]
    for (idx, ts, d), interp in zip(result.decisions, allf.interpolated, strict=True):
        lines.append(f"{idx},{ts:.9f},{int(d.is_keyframe)},{int(interp)},{d.disparity:.3f},{d.tracked},{d.reason}")
    atomic_write_text(out / "frames.csv", "\n".join(lines) + "\n")


def _ate(gt_pair, est: Trajectory) -> dict:
    from vggt_slam_pp.eval import compute_ate

    _, gt = gt_pair
    try:
        ate = compute_ate(gt, est, "sim3")
    except (EvaluationError, VggtSlamError) as exc:
        log.warning("ATE not computed: %s", exc)
        return {}
    return {"rmse": ate.rmse, "n": ate.n_matched, "scale": ate.scale}


def _report(source: FrameSource, config: RunConfig, result: FrontendResult | None, total: float,
            t_read: float, error: BaseException | None) -> dict:
    report: dict = {"version": __version__, "backbone": config.backbone.name, "calibrated": config.calibrated,
                    "frames": len(source), "seconds_total": total, "peak_memory_mb": peak_rss_mb(),
                    "error": (str(error) or type(error).__name__) if error else None}
    if result is None:
        return report
    kf = result.keyframe_trajectory()
    timings = {"read_s": t_read, **result.timings}
    report.update({
        "frames_processed": len(result.decisions), "keyframes": len(kf), "submaps": len(result.submaps),
        "fps": len(result.decisions) / total if total > 0 else None,
        "timings": timings,
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
    })
    gt_pair = source.frame_ground_truth()
    if gt_pair is not None:
        ate = _ate(gt_pair, kf)
        if ate:
            report["ate_rmse_odometry"] = ate["rmse"]
            report["ate_odometry"] = ate
            report["gt_path_length"] = gt_pair[1].path_length()
        ate_all = _ate(gt_pair, result.all_frame_trajectory())
        if ate_all:
            report["ate_rmse_odometry_all_frames"] = ate_all["rmse"]
    return report
