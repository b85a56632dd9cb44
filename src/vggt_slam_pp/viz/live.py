"""``run ... --viewer``: the 3-D viewer of a run while it runs, in its own process.

The front-end must not slow down for it, so the viewer (viser, its websocket and the scene) lives in a
``spawn``ed process at low priority, fed through one queue with what the run already has: each finished
submap (its points decimated to ``points_per_submap`` with their colours, its keyframes' camera centres,
its odometry pose) and the back-end's pose snapshots, coalesced to at most one every
``pose_interval_s``. A message is a few tens of kB; :meth:`LiveViewer.submap` never blocks. The scene is
drawn in the run's world frame (the first camera's: y down), with the odometry and the corrected paths.
"""

from __future__ import annotations

import logging
import os
import queue
import sys
import time
import traceback

import numpy as np

from vggt_slam_pp.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["LiveViewer"]


def _serve(port: int, host: str, inbox, ready) -> None:
    """The viewer process: a viser server drawing what arrives in ``inbox`` until ``None``."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's; the viewer stops when told (or orphaned)
    try:
        from vggt_slam_pp.backend.worker import _lower_priority

        _lower_priority("idle")  # CPU time only when the front-end (and the back-end) leave some
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - viser prints a banner; this process's output is ours
        _serve_loop(port, host, inbox, ready)
    except BaseException as exc:  # noqa: BLE001 - reported to the run, which goes on without a viewer
        ready.put(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))


def _serve_loop(port: int, host: str, inbox, ready) -> None:
    """Draw what arrives in ``inbox`` until ``None``; report what was drawn in ``ready``."""
    import viser

    from vggt_slam_pp.geometry.lie import transform_points
    from vggt_slam_pp.viz.viewer import RunViewer

    server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction("-y")  # the first camera's frame: y points down
    viewer = RunViewer(server)
    viewer.frustum_scale = 0.3
    viewer.build_gui()
    ready.put(("ready", server.get_port()))
    odometry: dict[int, np.ndarray] = {}
    corrected: dict[int, np.ndarray] = {}
    pose_updates = 0

    def paths() -> None:
        for name, poses in (("odometry", odometry), ("corrected", corrected)):
            ids = [i for i in sorted(poses) if i in viewer.submaps]
            if ids:
                centres = np.concatenate([transform_points(poses[i], viewer.submaps[i].camera_centers)
                                          for i in ids])
                viewer.set_trajectory(name, centres)

    stop = False
    parent = os.getppid()
    while not stop:
        try:
            batch = [inbox.get(timeout=1.0)]
        except queue.Empty:
            if os.getppid() != parent:  # the run is gone (killed): stop serving
                break
            continue
        while True:  # everything waiting: new submaps are all drawn, only the newest poses applied
            try:
                batch.append(inbox.get_nowait())
            except queue.Empty:
                break
        poses = None
        for msg in batch:
            if msg is None:
                stop = True
            elif msg[0] == "submap":
                _, sid, points, colors, centres, frames, T = msg
                odometry[sid] = T
                viewer.add_submap(sid, points, colors, centres, frames, corrected.get(sid, T))
                if len(viewer.submaps) == 1:
                    viewer.look_at_all()
            elif msg[0] == "poses":
                poses = msg[1]
        if poses is not None:
            corrected.update(poses)
            viewer.set_poses(poses)
            pose_updates += 1
        paths()
    ready.put(("stopped", {"submaps": len(viewer.submaps), "pose_updates": pose_updates,
                           "nodes": viewer.node_names()}))
    server.stop()


class LiveViewer:
    """The run's side of the live viewer: :meth:`submap` for each finished submap, :meth:`poses` for the
    back-end's snapshots, :meth:`close` at the end (the server stops with it unless ``keep_serving``)."""

    def __init__(self, port: int = 8080, host: str = "127.0.0.1", points_per_submap: int = 5000,
                 pose_interval_s: float = 0.5, start_timeout_s: float = 60.0, inbox_size: int = 256) -> None:
        import multiprocessing as mp

        try:
            import viser  # noqa: F401 - fail here, in the run's process, with a clear message
        except ImportError:
            raise InputError("--viewer needs viser: pip install 'vggt-slam-pp[viz]'") from None
        from vggt_slam_pp.backend.worker import _start_without_main

        self.points_per_submap, self.pose_interval_s = points_per_submap, pose_interval_s
        ctx = mp.get_context("spawn")
        self._inbox, self._ready = ctx.Queue(maxsize=inbox_size), ctx.Queue()
        self._warned = False
        ready = self._ready
        self._proc = ctx.Process(target=_serve, args=(port, host, self._inbox, ready), name="vggt-slam-pp-viewer",
                                 daemon=True)
        _start_without_main(self._proc, 1)
        try:
            kind, value = ready.get(timeout=start_timeout_s)
        except queue.Empty:
            self._proc.kill()
            raise InputError(f"the viewer did not start within {start_timeout_s:.0f} s") from None
        if kind == "error":
            self._proc.join(5)
            raise InputError(f"the viewer could not start: {value.splitlines()[0]}")
        self.port = int(value)
        self.url = f"http://localhost:{self.port}/"
        self.seconds = 0.0  # time the run spent handing things over
        self._last_poses = -np.inf
        self._pending_poses: dict | None = None

    def submap(self, submap_id: int, points: np.ndarray, colors: np.ndarray | None, camera_centers: np.ndarray,
               frames, T_world_submap: np.ndarray) -> None:
        """A finished submap: ``points`` [N,3] and ``colors`` [N,3] uint8 in its frame, ``camera_centers``
        [S,3], its keyframes' frame indices and its (odometry) pose [4,4]."""
        t = time.perf_counter()
        n = len(points)
        keep = np.linspace(0, n - 1, min(n, self.points_per_submap)).astype(np.int64) if n else np.zeros(0, np.int64)
        self._put(("submap", int(submap_id), np.asarray(points[keep], np.float32),
                   None if colors is None else np.asarray(colors[keep], np.uint8),
                   np.asarray(camera_centers, np.float32), [int(f) for f in frames], np.asarray(T_world_submap)))
        self.seconds += time.perf_counter() - t

    def _put(self, msg) -> None:
        """Hand a message over without ever blocking the run: a viewer that died, or lags so far that its
        (bounded) inbox is full, loses it (said once in the log)."""
        if not self._proc.is_alive():
            self._lost("the live viewer stopped")
            return
        try:
            self._inbox.put_nowait(msg)
        except queue.Full:
            self._lost("the live viewer lags behind")

    def _lost(self, why: str) -> None:
        if not self._warned:
            log.warning("%s: it misses what the run does from now on", why)
            self._warned = True

    def poses(self, poses) -> None:
        """The back-end's newest ``T_world_submap`` per submap; sent at most every ``pose_interval_s``."""
        self._pending_poses = poses
        if time.perf_counter() - self._last_poses >= self.pose_interval_s:
            self._send_poses()

    def _send_poses(self) -> None:
        if self._pending_poses is None:
            return
        t = time.perf_counter()
        self._put(("poses", {int(i): np.asarray(T) for i, T in self._pending_poses.items()}))
        self._pending_poses = None
        self._last_poses = time.perf_counter()
        self.seconds += self._last_poses - t

    def close(self, keep_serving: bool = False) -> dict | None:
        """Send the last poses; stop the viewer unless ``keep_serving`` (then it runs until the process that
        made it exits). Returns what the viewer drew (``submaps``, ``pose_updates``, ``nodes``) once stopped."""
        self._send_poses()
        if keep_serving and self._proc.is_alive():
            return None
        summary = None
        if self._proc.is_alive():
            try:
                self._inbox.put(None, timeout=5)
                kind, value = self._ready.get(timeout=30)
                summary = value if kind == "stopped" else None
                if kind == "error":
                    log.warning("the live viewer failed: %s", value.splitlines()[0])
            except (queue.Full, queue.Empty):
                log.warning("the live viewer did not stop in time")
            self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
        self._inbox.cancel_join_thread()  # nobody reads it any more: never wait for it at exit
        return summary

    def alive(self) -> bool:
        return self._proc.is_alive()
