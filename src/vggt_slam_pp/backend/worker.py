"""The back-end worker: a :class:`~vggt_slam_pp.backend.backend.Backend` in its own process (SPEC 3.10).

GTSAM holds the GIL during a solve, FAISS and OpenCV take CPU, so the back-end cannot share the
front-end's interpreter without stalling it. :class:`BackendWorker` runs it in a separate process
(``spawn``) and talks to it through two queues:

* inbox (unbounded): :class:`SubmapMessage` records; the points travel through the on-disk
  :class:`SubmapStore`, not the queue, so a message is a few hundred bytes and :meth:`BackendWorker.submit`
  never blocks. A back-end that falls more than ``WorkerConfig.catch_up_lag`` submaps behind catches up
  by adding the oldest waiting submaps to the map now and deferring their queries
  (:meth:`Backend.add_submap`, ``query=False``), which run when the worker is idle and at the end
  (:meth:`Backend.query_deferred`). While deferred queries wait, later submaps' queries wait behind them, so
  queries always run in submap order (each with its predecessor's matches and the loops before it): the
  front-end is never stalled, and no loop query is dropped;
* outbox: one :class:`PoseSnapshot` per processed submap, the final :class:`BackendResult`, or an error.

:meth:`BackendWorker.latest` returns the newest snapshot without blocking; an error inside the worker
(an exception, or the process dying) re-raises in the caller as :class:`BackendError` at the next
:meth:`submit`, :meth:`latest` or :meth:`finish`. ``mode="inline"`` runs the same back-end synchronously
in the caller (tests, debugging): identical results, no concurrency.
"""

from __future__ import annotations

import collections
import logging
import os
import queue
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from vggt_slam_pp.backend.backend import Backend, BackendConfig, BackendResult, PoseSnapshot, SubmapMessage
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.errors import BackendError
from vggt_slam_pp.resources import peak_rss_mb

log = logging.getLogger(__name__)

MODES = ("process", "inline")


@dataclass(frozen=True)
class WorkerConfig:
    """How the back-end runs beside the front-end (its algorithm is
    :class:`~vggt_slam_pp.backend.config.BackendConfig`)."""

    mode: str = "process"  # "process" (own process, the front-end never waits on GTSAM) or "inline"
    catch_up_lag: int = 128  # when more submaps than this wait in the worker's inbox (which is unbounded: ids,
    # camera centres and the odometry edge; the points are on disk), the oldest are added to the map with
    # their queries deferred (run in order when the worker is idle, and at the end) until it is back under half
    # this lag; later queries wait behind deferred ones: the front-end never waits, and no query is dropped.
    # <= 0: never defer
    threads: int = 1  # threads for OpenCV / FAISS / torch inside the worker
    priority: str = "idle"  # "idle": CPU time only when the front-end leaves some (Linux SCHED_IDLE,
    # else nice 19); "low": nice 10; "normal"
    duty: float = 0.25  # share of the wall time the worker may work while the front-end is still streaming
    # (and not half its catch-up lag behind, _duty): after each submap it pauses for (1 / duty - 1) x that submap's
    # time. Even at idle priority a busy worker slows a 2-core front-end (every stage 15-20 % at a duty of 0.5,
    # session 28); 1.0: never pause. Once the front-end has finished it runs without pauses
    yield_latency_s: float | None = None  # a latency (how long the oldest waiting submap has waited) up to which
    # the worker yields to the front-end at ``duty``, beyond it its duty rising linearly to 1 at twice this latency
    # (fresher live poses, a slower front-end); None: no such rise. It never pauses while more than half the
    # catch-up lag waits (_duty)


def _limit_threads(n: int, with_torch: bool) -> None:
    """Keep the worker's libraries to ``n`` threads so the front-end keeps its cores. torch is imported
    only for an encoder that needs it (it alone adds ~180 MB to the process)."""
    import cv2
    import faiss

    cv2.setNumThreads(n)
    faiss.omp_set_num_threads(n)
    if with_torch:
        import torch

        torch.set_num_threads(n)


def _lower_priority(priority: str) -> None:
    """Give the front-end precedence on a busy CPU. Linux applies scheduling per thread, so every thread
    already running (library pools started at import) is lowered; later ones inherit it."""
    if priority == "normal":
        return
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        try:
            if priority == "idle" and hasattr(os, "SCHED_IDLE"):
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            else:
                os.setpriority(os.PRIO_PROCESS, tid, 19 if priority == "idle" else 10)
        except OSError as exc:  # not permitted here: run at normal priority
            log.debug("could not lower the priority of thread %d: %s", tid, exc)


def _plain(snapshot: PoseSnapshot) -> tuple:
    return snapshot.version, dict(snapshot.poses), snapshot.loops_accepted, snapshot.last_submap, snapshot.rss_mb


def _snapshot(plain: tuple) -> PoseSnapshot:
    version, poses, loops, last, rss = plain
    for a in poses.values():
        a.flags.writeable = False
    return PoseSnapshot(version, MappingProxyType(poses), loops, last, rss)


def _build(config: BackendConfig, folder: str | Path, prior_map: tuple[str, bool] | None) -> Backend:
    backend = Backend(config, SubmapStore(folder, config.cache_submaps))
    if prior_map is not None:
        from vggt_slam_pp.backend.mapfile import load_map

        backend.seed_map(load_map(prior_map[0]), localize_only=prior_map[1])
    return backend


def _duty(worker: WorkerConfig, latency_s: float, backlog: int) -> float:
    """The share of the wall time a worker works while the front-end streams: ``worker.duty``, and 1 while more
    than half the catch-up lag waits; with a ``yield_latency_s``, rising linearly from ``duty`` once the oldest
    waiting submap has waited that long (``latency_s``) to 1 at twice that. A short run's back-end work mostly
    waits for the end of the stream (the front-end keeps its speed); a long run's back-end works harder once it
    falls behind (docs/backend.md, "Worker duty")."""
    if worker.catch_up_lag > 0 and backlog > worker.catch_up_lag // 2:
        return 1.0
    if worker.yield_latency_s is None:
        return worker.duty
    late = (latency_s - worker.yield_latency_s) / max(worker.yield_latency_s, 1e-9)
    return worker.duty + (1.0 - worker.duty) * min(max(late, 0.0), 1.0)


def _deferring(was: bool, backlog: int, lag: int) -> bool:
    """Whether a worker with ``backlog`` submaps waiting defers the next one's query: from a backlog over
    ``lag`` until it is back at half of it (``was``: it deferred the last one; ``lag`` <= 0: never). The
    hysteresis makes deferred queries come in runs of consecutive submaps, and the live ones too, so each
    keeps its predecessor's matches for the sequence prior: deferring whenever just over the lag alternated
    (1,000-submap bench: every other query from submap 228 on, and no revisit was followed)."""
    if lag <= 0:
        return False
    if backlog > lag:
        return True
    return was and backlog > lag // 2


def _serve(config: BackendConfig, worker: WorkerConfig, folder: str, inbox, outbox, streaming_done,
           prior_map: tuple[str, bool] | None = None) -> None:
    """The worker process: build the back-end (seeded with ``prior_map``: folder, localisation only), then
    one snapshot per message until ``None``; while the front-end streams (``streaming_done`` not set) it
    works ``worker.duty`` of the time."""
    parent = os.getppid()
    try:
        _lower_priority(worker.priority)
        _limit_threads(worker.threads, config.encoder != "hog")
        backend = _build(config, folder, prior_map)
        outbox.put(("ready", None))
        waiting: collections.deque = collections.deque()  # (arrival time, message) received, not yet processed
        deferring = False  # catching up: from a backlog over the lag down to half of it, every query deferred
        while True:
            if not waiting:
                try:
                    waiting.append((time.perf_counter(), inbox.get(timeout=0.05 if backend.deferred else 1.0)))
                except queue.Empty:
                    if os.getppid() != parent:  # the caller is gone (killed): stop quietly
                        return
                    if backend.deferred:  # idle: a query deferred while catching up
                        outbox.put(("snapshot", _plain(backend.query_deferred())))
                    continue
            while True:  # everything sent so far: the backlog decides how to process the oldest
                try:
                    waiting.append((time.perf_counter(), inbox.get_nowait()))
                except queue.Empty:
                    break
            _, msg = waiting.popleft()
            if msg is None:
                result = backend.finish()
                result.peak_rss_mb = peak_rss_mb()
                outbox.put(("result", result))
                return
            t0 = time.perf_counter()
            backlog = sum(m is not None for _, m in waiting)
            deferring = _deferring(deferring, backlog, worker.catch_up_lag)
            outbox.put(("snapshot", _plain(backend.add_submap(msg, query=not deferring))))
            now = time.perf_counter()
            duty = _duty(worker, now - waiting[0][0] if waiting else 0.0, backlog)
            if duty < 1 and not streaming_done.is_set():
                streaming_done.wait((now - t0) * (1.0 / duty - 1.0))
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the caller, which re-raises it
        outbox.put(("error", f"{type(exc).__name__}: {exc}", traceback.format_exc()))


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _start_without_main(proc, threads: int) -> None:
    """Start a ``spawn`` process without re-running the caller's ``__main__`` in it, with its BLAS and
    OpenMP pools sized to ``threads`` (read once, at the child's imports).

    ``spawn`` normally re-imports the main script in the child, which fails (or re-runs the work) when a
    user's script calls :func:`vggt_slam_pp.pipeline.run` without an ``if __name__ == "__main__"`` guard.
    The worker's target lives in this importable module, so the main module is hidden while the child's
    start-up data is prepared (inside ``start()``) and restored right after.
    """
    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if main is not None and k in main.__dict__}
    env = {k: os.environ.get(k) for k in _THREAD_VARIABLES}
    try:
        for k in saved:
            setattr(main, k, None) if k == "__spec__" else delattr(main, k)
        os.environ.update(dict.fromkeys(_THREAD_VARIABLES, str(threads)))  # BLAS / OpenMP pools of the child
        proc.start()
    finally:
        for k, v in saved.items():
            setattr(main, k, v)
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class BackendWorker:
    """Front-end side of the back-end. ``submit`` each finished submap (points already in ``store``),
    read :meth:`latest` for optimised poses, and :meth:`finish` for the final result."""

    def __init__(self, config: BackendConfig, folder: str | Path, *, worker: WorkerConfig | None = None,
                 start_timeout_s: float = 300.0, prior_map: tuple[str, bool] | None = None) -> None:
        """``prior_map``: (a saved map's folder, localisation only); the worker rasterises and indexes every
        submap of it before it is ready, so give a ``start_timeout_s`` that grows with the map."""
        worker = worker or WorkerConfig()
        mode = worker.mode
        if mode not in MODES:
            raise BackendError(f"unknown back-end mode {mode!r}; choose one of {', '.join(MODES)}")
        if not 0 < worker.duty <= 1:
            raise BackendError(f"the worker's duty must be in (0, 1], got {worker.duty}")
        if worker.yield_latency_s is not None and not worker.yield_latency_s >= 0:
            raise BackendError(f"the worker's yield latency must be >= 0 s, got {worker.yield_latency_s}")
        self.config, self.worker_config, self.mode = config, worker, mode
        self.folder = Path(folder)
        self.store = SubmapStore(self.folder, cache_size=0)  # the writer keeps nothing in memory
        self._latest: PoseSnapshot | None = None
        self._result: BackendResult | None = None
        self.submitted = 0
        self.wait_s = 0.0  # time the caller spent handing submaps over (the inbox never blocks)
        if mode == "inline":
            self._backend: Backend | None = _build(config, self.folder, prior_map)
            return
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self._inbox = ctx.Queue()
        self._outbox = ctx.Queue()
        self._streaming_done = ctx.Event()
        self._proc = ctx.Process(target=_serve, args=(config, worker, str(self.folder), self._inbox, self._outbox,
                                                      self._streaming_done, prior_map),
                                 name="vggt-slam-pp-backend", daemon=True)
        _start_without_main(self._proc, worker.threads)
        self._backend = None
        self._await(lambda kind: kind == "ready", start_timeout_s, "start")

    # -- messages ---------------------------------------------------------------------------------
    def submit(self, msg: SubmapMessage) -> None:
        """Hand one submap to the back-end; never blocks (the inbox is unbounded, see the module docstring)."""
        self.submitted += 1
        if self._backend is not None:
            self._latest = self._backend.add_submap(msg)
            return
        t0 = time.perf_counter()
        self._drain()
        self._check_alive()
        self._inbox.put(msg)
        self.wait_s += time.perf_counter() - t0

    def latest(self) -> PoseSnapshot | None:
        """The newest pose snapshot (non-blocking); raises if the worker has failed."""
        if self._backend is None:
            self._drain()
        return self._latest

    def finish(self, timeout_s: float | None = None) -> BackendResult:
        """Process everything submitted, optimise globally, return the result and stop the worker."""
        if self._backend is not None:
            self._result = self._backend.finish()
            self._result.peak_rss_mb = peak_rss_mb()
            return self._result
        self._streaming_done.set()  # no more pauses: catch up at full speed
        self._inbox.put(None)
        self._await(lambda kind: kind == "result", timeout_s, "finish")
        self._proc.join(timeout=30)
        return self._result

    def close(self) -> None:
        """Stop the worker now (after an error or an interruption)."""
        if self._backend is None and self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=10)

    # -- internals --------------------------------------------------------------------------------
    def _handle(self, item: tuple) -> str:
        kind = item[0]
        if kind == "snapshot":
            self._latest = _snapshot(item[1])
        elif kind == "result":
            self._result = item[1]
        elif kind == "error":
            log.debug("back-end worker traceback:\n%s", item[2])
            self.close()
            raise BackendError(f"back-end failed: {item[1]}")
        return kind

    def _drain(self) -> None:
        while True:
            try:
                item = self._outbox.get_nowait()
            except queue.Empty:
                return
            self._handle(item)

    def _check_alive(self) -> None:
        if not self._proc.is_alive():
            self._drain()  # an error message may still be in flight
            raise BackendError(f"the back-end worker exited unexpectedly (exit code {self._proc.exitcode})")

    def _await(self, done, timeout_s: float | None, what: str) -> None:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            try:
                item = self._outbox.get(timeout=0.5)
            except queue.Empty:
                self._check_alive()
                if deadline is not None and time.monotonic() > deadline:
                    self.close()
                    raise BackendError(f"the back-end worker did not {what} within {timeout_s:.0f} s") from None
                continue
            if done(self._handle(item)):
                return
