"""Running the system: :class:`SlamSystem` (front-end, back-end worker, the hand-over between them) and
:func:`run`, which drives it over a frame source and writes the outputs (:mod:`vggt_slam_pp.outputs`:
trajectories, ``report.json``, ``graph.json``, ``map.ply``, ``dem/``, ``map.json``) into a folder.

``predictions/`` holds every submap's raw prediction (safetensors), replayable with ``--backbone
replay`` and read back by ``--resume``; ``submaps/`` each submap's points (the back-end's on-disk store).

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

from vggt_slam_pp.backend.backend import BackendConfig, BackendResult, SubmapMessage
from vggt_slam_pp.backend.worker import BackendWorker, WorkerConfig
from vggt_slam_pp.configs import PRESETS, from_dict, merged
from vggt_slam_pp.dem.raster import DemConfig
from vggt_slam_pp.errors import FrontendError, InputError, VggtSlamError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.frontend import Frontend, FrontendConfig, FrontendResult
from vggt_slam_pp.geometry.lie import sim3_inverse
from vggt_slam_pp.io.frames import FrameSource
from vggt_slam_pp.outputs import (
    OutputConfig,
    RunStats,
    prepare_run_folder,
    write_keyframes_snapshot,
    write_run_outputs,
)
from vggt_slam_pp.plugins import BACKBONES
from vggt_slam_pp.plugins import load as load_plugin
from vggt_slam_pp.resources import reset_peak_rss, rss_mb

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
    colmap_mapper: str = "global"  # colmap: "global" (each submap on its own by COLMAP's global mapper, linked by
    # its shared keyframes) or "incremental" (registered into the previous submap's shared keyframes; docs/frontend.md)
    colmap_link: str = "auto"  # colmap, global mapper: how each submap is linked to the previous one: "shared" (by
    # their shared keyframes), "joint" (by one bundle adjustment of both, each placed by all its cameras: better on
    # real EuRoC and the castle walk, worse on forward motion), "auto" (joint unless the cameras move ahead;
    # docs/frontend.md, "The joint link")
    deterministic: bool = True  # colmap: the mapper on one thread too (bit-identical runs, ~30 % slower; docs/frontend.md)
    image_features: bool = True  # colmap: keep each submap's feature database for loops from images (about 10 MB
    # per submap of 16-20 keyframes in run/submaps/; False: loops are registered from points only)
    seed: int = 0


@dataclass(frozen=True)
class RunConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    calibrated: bool = False
    save_predictions: bool = True
    backend: bool = True  # loop closure; False = odometry only
    backend_config: BackendConfig = field(default_factory=BackendConfig)
    worker: WorkerConfig = field(default_factory=WorkerConfig)  # how the back-end runs beside the front-end
    outputs: OutputConfig = field(default_factory=OutputConfig)  # map.ply and DEM export
    blas_threads: int = 1  # numpy / scipy BLAS threads in the front-end's process (0: the library's default).
    # The front-end's matrices are small: a second OpenBLAS thread spin-waits more than it computes (2 cores:
    # 88 -> 107 fps on the block loop with 1) and takes the core the back-end worker would use

    @classmethod
    def from_dict(cls, data: dict) -> RunConfig:
        """The configuration a run wrote to ``config.json`` (missing keys keep their defaults)."""
        return from_dict(cls, _upgrade(data))

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
        return from_dict(cls, _upgrade(data), where=str(path))

    @classmethod
    def preset(cls, name: str) -> RunConfig:
        """A named configuration from :data:`PRESETS`."""
        if name not in PRESETS:
            raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        return from_dict(cls, merged(dataclasses.asdict(cls()), PRESETS[name][1]), where=f"preset {name}")


# config.json keys of version 0.x runs that moved: BackendConfig's process control went to WorkerConfig
_MOVED_TO_WORKER = {"worker": "mode", "worker_threads": "threads", "worker_priority": "priority",
                    "worker_duty": "duty"}


def _upgrade(data):
    """A ``config.json`` written by an earlier version, in today's form: moved keys follow (the worker's
    settings, fault injection); the removed ``loop_information`` is dropped when it was "icp" (today's
    behaviour) and refused otherwise; a colmap run without ``colmap_mapper`` keeps the incremental mapper
    it was made with."""
    if isinstance(data, dict) and isinstance(data.get("backbone"), dict) and \
            data["backbone"].get("name") == "colmap" and "colmap_mapper" not in data["backbone"]:
        # a colmap run from before the global mapper was its default: it used the incremental one
        data = {**data, "backbone": {**data["backbone"], "colmap_mapper": "incremental"}}
    if not isinstance(data, dict) or not isinstance(data.get("backend_config"), dict):
        return data
    b, data = dict(data["backend_config"]), dict(data)
    if b.get("loop_information", "icp") != "icp":
        raise InputError(f"backend_config.loop_information {b['loop_information']!r} is no longer supported "
                         "(loop edges always carry the registration's information); remove the key")
    moved = {new: b.pop(old) for old, new in _MOVED_TO_WORKER.items() if old in b}
    if moved:
        data["worker"] = {**moved, **data.get("worker", {})}
    if "inject_wrong_candidates" in b:
        b["faults"] = {"wrong_candidates": b.pop("inject_wrong_candidates")}
    b.pop("loop_information", None)
    b.pop("queue_size", None)  # the bounded inbox it sized is gone (WorkerConfig.catch_up_lag)
    data["backend_config"] = b
    return data


def make_backbone(config: RunConfig, source: FrameSource) -> Backbone:
    """Instantiate the configured backbone for ``source`` (:data:`vggt_slam_pp.plugins.BACKBONES`)."""
    return load_plugin(BACKBONES, config.backbone.name, "backbone", FrontendError)(config, source)


def run(source: FrameSource, config: RunConfig, out_dir: str | Path, backbone: Backbone | None = None,
        progress: Callable[[int, int], None] | None = None, resume: bool = False,
        prior_map: str | Path | None = None, localize_only: bool = False, input_record: dict | None = None,
        viewer=None) -> dict:
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
    (docs/backend.md, "Maps").

    ``input_record``: how the input was given (the CLI's flags), written to ``input.json`` for ``--resume``.
    ``viewer``: a :class:`~vggt_slam_pp.viz.live.LiveViewer` fed with every finished submap and pose
    snapshot (``run --viewer``).
    """
    from threadpoolctl import threadpool_limits

    if config.blas_threads < 0:
        raise InputError(f"blas_threads must be >= 0 (0: the library default), got {config.blas_threads}")
    limit = threadpool_limits(config.blas_threads, user_api="blas") if config.blas_threads else nullcontext()
    with limit:
        return _run(source, config, Path(out_dir), backbone, progress, resume, prior_map, localize_only, input_record,
                    viewer)


def _run(source: FrameSource, config: RunConfig, out: Path, backbone: Backbone | None,
         progress: Callable[[int, int], None] | None, resume: bool, prior_map: str | Path | None,
         localize_only: bool, input_record: dict | None, viewer=None) -> dict:
    from vggt_slam_pp.frontend.backbones.replay import PredictionStore

    prior = _open_prior_map(prior_map, out, config) if prior_map is not None else None
    if resume and not PredictionStore(out / "predictions").all():
        raise InputError(f"nothing to resume in {out}: no saved predictions (predictions/submap_*.safetensors)")
    reset_peak_rss()  # peak_rss_mb: this run's, not whatever the calling process did before
    t0 = time.perf_counter()
    backbone = backbone or make_backbone(config, source)
    prepare_run_folder(out, config, input_record, keep_predictions=resume)
    system = SlamSystem(config, out, backbone, resume=resume, prior=prior, localize_only=localize_only, viewer=viewer)
    n = len(source)
    error: BaseException | None = None
    t_read = 0.0
    try:
        for i in range(n):
            t = time.perf_counter()
            frame = source[i]
            t_read += time.perf_counter() - t
            system.process(frame)
            if progress:
                progress(i + 1, n)
        result = system.finish()
    except (VggtSlamError, KeyboardInterrupt) as exc:
        error = exc
        result = system.partial_result()
        log.error("run %s: %s; writing the outputs of %d finished submaps",
                  "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed", exc or "interrupted",
                  len(result.frontend.submaps) if result.frontend is not None else 0)
    finally:
        system.backbone.close()
    stats = system.stats(time.perf_counter() - t0, t_read, error)
    report = write_run_outputs(out, source, config, result.frontend, result.backend, stats, prior=prior,
                               write_map=not localize_only)
    if error is not None:
        raise error
    return report


@dataclass
class SlamResult:
    """What a run produced: the front-end's submaps and odometry, and (with the back-end) its result."""

    frontend: FrontendResult | None  # None when no submap was finished
    backend: BackendResult | None


class SlamSystem:
    """The running system for one output folder: front-end, back-end worker and the hand-over between them.

    ::

        system = SlamSystem(config, out, backbone)
        for frame in frames:
            system.process(frame)
        result = system.finish()  # or, after an error or Ctrl-C: system.partial_result()

    ``resume``: backbone calls finished by an interrupted run in ``out`` are read back from its
    ``predictions/``; ``prior``: a :class:`~vggt_slam_pp.backend.mapfile.SavedMap` the recording is added
    to (its points already linked into ``out/submaps``); ``localize_only``: that map is held fixed.
    """

    def __init__(self, config: RunConfig, out: Path, backbone: Backbone, resume: bool = False, prior=None,
                 localize_only: bool = False, viewer=None) -> None:
        from vggt_slam_pp.frontend.backbones.replay import PredictionStore, ResumeBackbone

        self.config, self.out = config, Path(out)
        self.backbone = ResumeBackbone(backbone, self.out / "predictions") if resume else backbone
        store = None
        if (config.save_predictions or resume) and config.backbone.name != "replay":
            store = PredictionStore(self.out / "predictions", keep_existing=resume)
        first_id = len(prior.submaps) if prior is not None else 0
        self.frontend = Frontend(self.backbone, config.frontend, store=store, first_id=first_id)
        self.worker: BackendWorker | None = None
        if config.backend:
            self.worker = BackendWorker(_scale_aware(config.backend_config, backbone), self.out / "submaps",
                                        worker=config.worker, start_timeout_s=300.0 + 5.0 * first_id,
                                        prior_map=(str(prior.folder), localize_only) if prior is not None else None)
        self.feeder = _BackendFeeder(self.frontend, self.worker, self.out, viewer)
        self.viewer = viewer  # a LiveViewer (run --viewer): finished submaps and pose snapshots go to it
        self._shown = 0
        self._odometry_pose = np.eye(4)
        self._undistort = config.calibrated and self.backbone.name != "colmap"  # colmap models distortion itself
        self.frontend_s: float | None = None  # wall time of the frame loop (set by finish)
        self.finish_wait_s = 0.0  # time finish() waited for the back-end's last submaps and global solve
        self.undistort_s = 0.0  # counted with reading the input in the report
        self._t_start = time.perf_counter()

    def process(self, frame) -> None:
        """One input frame; a finished submap goes to the back-end at once."""
        if self._undistort and frame.intrinsics is not None and frame.intrinsics.dist is not None:
            t = time.perf_counter()
            frame = _undistorted(frame)
            self.undistort_s += time.perf_counter() - t
        if self.frontend.process(frame) is not None:
            self._show()
            self.feeder.feed()

    def _show(self) -> None:
        """Hand the submaps finished since the last call to the live viewer (before the feeder releases
        their points), at their odometry poses."""
        if self.viewer is None:
            return
        subs = self.frontend.submaps
        while self._shown < len(subs):
            sm = subs[self._shown]
            if self._shown > 0:
                self._odometry_pose = self._odometry_pose @ self.frontend.edges[self._shown - 1].T_prev_curr
            pts, colors, centres, _ = _points_and_cameras(sm)
            self.viewer.submap(sm.id, pts, colors, centres, sm.frame_indices, self._odometry_pose)
            self._shown += 1

    def finish(self) -> SlamResult:
        """The last submap, then the back-end's final global optimisation."""
        result = self.frontend.finish()
        self._show()
        self.feeder.feed()
        self.frontend_s = time.perf_counter() - self._t_start
        backend_result = None
        if self.worker is not None:
            t = time.perf_counter()
            backend_result = self.worker.finish()
            self.finish_wait_s = time.perf_counter() - t
            if self.viewer is not None:
                self.viewer.poses(backend_result.poses)
        return SlamResult(result, backend_result)

    def partial_result(self) -> SlamResult:
        """After an error or an interruption: the submaps finished so far, ``keyframes.txt`` at the newest
        pose snapshot, and the back-end stopped."""
        self.feeder.flush()
        if self.worker is not None:
            self.worker.close()
        return SlamResult(self.frontend.partial_result(), None)

    def stats(self, seconds_total: float, read_s: float, error: BaseException | None) -> RunStats:
        """How the run went, for its report (``read_s``: reading the input; undistorting it is added)."""
        w, f = self.worker, self.feeder
        return RunStats(seconds_total, read_s + self.undistort_s, error, self.backbone.describe(), self.frontend_s, f.seconds,
                        self.finish_wait_s, w.mode if w else None, w.wait_s if w else 0.0, f.memory_trace, f.max_lag)


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
        for src in (saved.store.path(sm.id), saved.store.colors_path(sm.id)):
            if not src.is_file():  # colours are optional (older maps have none)
                continue
            dst = store / src.name
            dst.unlink(missing_ok=True)
            try:
                os.link(src, dst)  # the points never change: a hard link costs no space
            except OSError:
                shutil.copy2(src, dst)
    return saved


def _scale_aware(config: BackendConfig, backbone: Backbone) -> BackendConfig:
    """A backbone without metric scale (VGGT normalises each submap, COLMAP's scale is arbitrary) gets the
    DEM tile size "auto" (a fraction of the first submaps' median camera depth) instead of the metric 2 m: with
    2 "units" of a normalised VGGT scene (about 20 m) the oracle VGGT closed 6-9 loops of the block loop
    where the simulated backbone closes 18-21 (docs/backend.md)."""
    dem = config.covisibility.dem
    if backbone.metric or isinstance(dem.tile_size, str) or dem.tile_size != DemConfig().tile_size:
        return config
    log.info("backbone %s has no metric scale: DEM tile size 'auto' (%.2f x the median camera depth of the first "
             "%d submaps)", backbone.name, dem.auto_tile_fraction, config.grid_submaps)
    covis = dataclasses.replace(config.covisibility, dem=dataclasses.replace(dem, tile_size="auto"))
    return dataclasses.replace(config, covisibility=covis)


def _points_and_cameras(sm) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """A finished submap's points [N,3], their colours [N,3] uint8 (None when unknown), its keyframes'
    camera centres [S,3], all in the submap's frame, and how many of the points (in order) each keyframe
    gave [S] (they sum to N)."""
    pred = sm.prediction
    counts = np.array([len(p) for p in pred.points], np.int64)
    pts = np.concatenate([p for p in pred.points if len(p)]) if counts.sum() else np.zeros((0, 3))
    colors = sm.colors if sm.colors is not None and len(sm.colors) == len(pts) else None
    return pts, colors, np.array([sim3_inverse(T)[:3, 3] for T in pred.T_cam_submap]), counts


class _BackendFeeder:
    """Sends every finished submap to the back-end worker (points to the on-disk store first), releases
    the front-end's copy of the points it no longer needs (bounded memory), and keeps ``keyframes.txt``
    at the newest pose snapshot, so an interrupted run leaves its latest consistent trajectory."""

    def __init__(self, frontend: Frontend, worker: BackendWorker | None, out: Path, viewer=None) -> None:
        self.frontend, self.worker, self.out, self.viewer = frontend, worker, out, viewer
        self.sent = 0
        self.seconds = 0.0
        self._written = (-1, -1)
        # every ``trace_every`` submaps sent: (submaps sent, front-end RSS MiB)
        self.memory_trace: list[tuple[int, float]] = []
        self.trace_every = 10
        self.max_lag = 0  # most submaps the back-end was behind the front-end at a hand-over
        # keyframes.txt is rewritten (all keyframes) at most this often, and never more than 2 % of the
        # time: every snapshot made long runs quadratic (316 submaps: 30 s of the front-end's time), and
        # at 1,000 submaps one rewrite takes a tenth of a second; flush() writes the newest at the end
        self.write_interval_s = 2.0
        self.write_share = 0.02
        self._latest = None
        self._last_write = -np.inf
        self._write_s = 0.0  # how long the last rewrite took

    def feed(self) -> None:
        if self.worker is None:
            return
        t = time.perf_counter()
        while self.sent < len(self.frontend.submaps):
            sm = self.frontend.submaps[self.sent]
            pts, colors, centres, counts = _points_and_cameras(sm)
            self.worker.store.put(sm.id, pts, colors)
            if sm.landmarks is not None and len(sm.landmarks):
                self.worker.store.put_landmarks(sm.id, sm.landmarks)
            features = sm.prediction.info.get("features")
            if features and Path(features).is_file():  # a sparse backbone's features: loops from images
                p = sm.prediction
                self.worker.store.put_features(sm.id, features, p.T_cam_submap, p.valid, p.frame_indices)
            edge = self.frontend.edges[self.sent - 1] if self.sent > 0 else None
            self.worker.submit(SubmapMessage(sm.id, centres, edge, counts))
            self.sent += 1
        self.frontend.release_points(keep_last=1)
        snap = self.worker.latest()
        self._latest = snap or self._latest
        if snap is not None and self.viewer is not None:
            self.viewer.poses(snap.poses)
        done = snap.last_submap + 1 - self.frontend.first_id if snap is not None else 0
        self.max_lag = max(self.max_lag, self.sent - max(done, 0))
        if time.perf_counter() - self._last_write >= max(self.write_interval_s, self._write_s / self.write_share):
            self._write_latest()
        if self.sent // self.trace_every > len(self.memory_trace):
            self.memory_trace.append((self.sent, rss_mb()))
        self.seconds += time.perf_counter() - t

    def _write_latest(self) -> None:
        snap = self._latest
        if snap is not None and (snap.version, snap.last_submap) != self._written:
            t = time.perf_counter()
            write_keyframes_snapshot(self.out, self.frontend.submaps, snap.poses)
            self._written = (snap.version, snap.last_submap)
            self._last_write = time.perf_counter()
            self._write_s = self._last_write - t

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
