"""Running a suite: every task once (resumable), locally in a process pool or on a Ray cluster.

A task's outputs go to its own folder; ``result.json`` there is written last (atomically), with the
figures the tables need or the error that stopped the run. A task whose ``result.json`` holds no error is
finished and is never run again; a failed one is run again the next time. Ray is imported only with
``ray=...``: GPU runs (the ``vggt`` backbone on a CUDA device) ask Ray for one GPU each, CPU runs for
``cpus_per_run`` cores.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from vggt_slam_pp.errors import InputError
from vggt_slam_pp.io.trajectory import atomic_write_text
from vggt_slam_pp.suite.spec import SuiteSpec, Task, expand

log = logging.getLogger(__name__)

__all__ = ["run_task", "run_suite", "finished_result"]

RESULT = "result.json"


def task_digest(task: Task) -> str:
    """What the run depends on (its input and its whole configuration): a run made with other settings
    under the same names is not finished."""
    import hashlib

    what = {"input": task.input, "layout": task.layout, "gt": task.gt, "stride": task.stride,
            "max_frames": task.max_frames, "config": task.run_config}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:16]


def finished_result(task: Task) -> dict | None:
    """The task's result when it finished without an error with the task's settings, else None."""
    path = Path(task.folder) / RESULT
    try:
        r = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if r.get("error") is not None or r.get("digest") != task_digest(task):
        return None
    # the task names the run (its folder may have been moved or renamed since)
    return {**r, "dataset": task.dataset, "sequence": task.sequence, "config": task.config, "seed": task.seed,
            "folder": task.folder}


def run_task(task: Task) -> dict:
    """Run one task (in whichever process the executor gives it) and write its ``result.json``."""
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.io.frames import FrameSubset
    from vggt_slam_pp.pipeline import RunConfig, run

    folder = Path(task.folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = {"dataset": task.dataset, "sequence": task.sequence, "config": task.config, "seed": task.seed,
           "folder": str(folder), "digest": task_digest(task), "error": None}
    t0 = time.perf_counter()
    try:
        source = open_source(task.input, layout=task.layout, ground_truth=task.gt, stride=task.stride)
        if task.max_frames:
            source = FrameSubset.every(source, 1, task.max_frames)
        config = RunConfig.from_dict(task.run_config)
        report = run(source, config, folder / "run",
                     input_record={"input": task.input, "layout": task.layout, "gt": task.gt, "stride": task.stride,
                                   "max_frames": task.max_frames, "map": None, "localize_only": False})
        keys = ("ate_rmse", "ate_rmse_odometry", "ate_reduction", "gt_path_length", "frontend_fps", "fps",
                "seconds_total", "keyframes", "submaps", "loops_accepted", "degraded_edges", "peak_rss_mb")
        out.update({k: report.get(k) for k in keys})
        # the corrected trajectory's with the back-end, the odometry's without (never one for the other)
        out["ate"] = report.get("ate_rmse") if config.backend else report.get("ate_rmse_odometry")
    except Exception as exc:  # noqa: BLE001 - one failed run is recorded and the suite goes on
        out["error"] = f"{type(exc).__name__}: {exc}".strip()
        out["traceback"] = traceback.format_exc()
    out["seconds"] = time.perf_counter() - t0
    atomic_write_text(folder / RESULT, json.dumps(out, indent=2, default=str))
    return out


def _crashed(task: Task, exc: BaseException) -> dict:
    """The result of a task whose process died before it could write one (written for it)."""
    out = {"dataset": task.dataset, "sequence": task.sequence, "config": task.config, "seed": task.seed,
           "folder": task.folder, "digest": task_digest(task),
           "error": f"the run's process died: {type(exc).__name__}: {exc}".strip()}
    Path(task.folder).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(task.folder) / RESULT, json.dumps(out, indent=2, default=str))
    return out


def _prepare_data(suite: SuiteSpec, out: Path) -> None:
    """Render the suite's synthetic sequences into ``out/data`` (once: a finished one is kept)."""
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    for d in suite.datasets:
        if d.synthetic is None:
            continue
        folder = out / "data" / d.name
        if (folder / "groundtruth.txt").is_file():  # written last
            continue
        s = d.synthetic
        log.info("rendering %s into %s", d.name, folder)
        write_sequence(make_scene(s.get("scene", "loop"), frames=int(s.get("frames", 600)),
                                  width=int(s.get("width", 320)), height=int(s.get("height", 240)),
                                  seed=int(s.get("seed", 0))), folder)


def _uses_gpu(task: Task) -> bool:
    b = task.run_config.get("backbone", {})
    return b.get("name") == "vggt" and str(b.get("device", "auto")) in ("auto", "cuda") and _cuda()


def _cuda() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except ImportError:
        return False


def run_suite(suite: SuiteSpec, out: Path, runs: int | None = None, jobs: int = 1, ray: str | None = None,
              cpus_per_run: float = 1.0, progress: Callable[[dict, int, int], None] | None = None) -> list[dict]:
    """Run every task of ``suite`` not finished yet; returns every task's result (finished earlier or now).

    ``jobs``: local processes at a time (1: in this process); ``ray``: ``"local"`` (``ray.init()`` on this
    machine) or a cluster address; ``progress(result, done, total)`` after each task.
    """
    out = Path(out).resolve()  # the tasks' folders must mean the same in every worker (a Ray cluster's too)
    if jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    if runs is not None and runs < 1:
        raise InputError(f"--runs must be >= 1, got {runs}")
    if ray is not None:
        try:  # before anything runs or renders
            import ray as _  # noqa: F401
        except ImportError:
            raise InputError("--ray needs Ray: pip install 'vggt-slam-pp[ray]'") from None
    tasks = expand(suite, out, runs)
    _prepare_data(suite, out)
    results: dict[str, dict] = {}
    todo = []
    for t in tasks:
        r = finished_result(t)
        if r is not None:
            results[t.key] = r
        else:
            todo.append(t)
    log.info("suite %s: %d runs, %d finished earlier, %d to run", suite.name, len(tasks), len(results), len(todo))
    done = len(results)

    def record(t: Task, r: dict) -> None:
        nonlocal done
        results[t.key] = r
        done += 1
        if progress:
            progress(r, done, len(tasks))

    if ray is not None:
        _run_on_ray(todo, ray, cpus_per_run, record)
    elif jobs == 1:
        for t in todo:
            record(t, run_task(t))
    else:
        import concurrent.futures as cf
        import multiprocessing as mp

        with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(run_task, t): t for t in todo}
            for f in cf.as_completed(futures):
                try:
                    r = f.result()
                except Exception as exc:  # noqa: BLE001 - a worker that died (killed, out of memory, crashed)
                    r = _crashed(futures[f], exc)
                record(futures[f], r)
    return [results[t.key] for t in tasks]


def _run_on_ray(todo: list[Task], address: str, cpus_per_run: float, record) -> None:
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs Ray: pip install 'vggt-slam-pp[ray]'") from None
    started = not ray.is_initialized()
    if started:
        ray.init(address=None if address == "local" else address, include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
    try:
        remote = ray.remote(run_task)
        refs = {}
        for t in todo:
            opts = {"num_gpus": 1, "num_cpus": 1} if _uses_gpu(t) else {"num_cpus": cpus_per_run}
            refs[remote.options(**opts).remote(t)] = t
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            try:
                r = ray.get(ready[0])
            except Exception as exc:  # noqa: BLE001 - a worker that died (killed, out of memory, crashed)
                r = _crashed(refs[ready[0]], exc)
            record(refs[ready[0]], r)
    finally:
        if started:
            ray.shutdown()
