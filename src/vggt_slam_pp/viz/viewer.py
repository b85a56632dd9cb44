"""``vggt-slam-pp view RUN_DIR``: a 3-D web viewer of a run or a map (viser, the ``viz`` extra).

Everything is drawn in the DEM's ground frame (x, y on the ground plane, z up), read from the run's
folder (:mod:`vggt_slam_pp.viz.run_folder`):

* ``/map/submap_NNNNNN``: each submap's points at their corrected pose, decimated to ``max_points`` in
  all, coloured by image colour or by height (GUI);
* ``/cameras/submap_NNNNNN``: a frustum per keyframe, with a thumbnail of its image when the input is
  still where ``input.json`` says;
* ``/trajectory/{odometry,corrected,ground_truth}``: keyframe paths (the ground truth Sim(3)-aligned to
  the corrected trajectory, as the ATE);
* ``/loops/accepted`` and ``/loops/rejected/QQQ_MMM``: loop edges between submap centres; a rejected
  candidate shows its reason when clicked, and every candidate can be picked in the GUI's list;
* ``/dem``: the fused DEM's hillshade as an image on the ground plane.

GUI: layer toggles, colour mode, a slider over time (submaps up to N) and a range of submaps to show.
:class:`RunViewer` also serves a live run (:meth:`RunViewer.add_submap` / :meth:`RunViewer.set_poses`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import InputError, VggtSlamError
from vggt_slam_pp.geometry.lie import decompose_sim3, transform_points
from vggt_slam_pp.viz.run_folder import RunFolder, load_run

log = logging.getLogger(__name__)

__all__ = ["RunViewer", "serve", "height_colors"]

_COLOURS = {"odometry": (220, 60, 60), "corrected": (40, 110, 220), "ground_truth": (30, 30, 30),
            "accepted": (40, 180, 60), "rejected": (235, 150, 30)}


def height_colors(z: np.ndarray) -> np.ndarray:
    """[N] heights -> [N, 3] uint8, the DEM's ramp over the 1st-99th percentile."""
    from vggt_slam_pp.dem.images import height_ramp

    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(z, [1, 99])
    return np.clip(height_ramp(np.clip((z - lo) / max(hi - lo, 1e-9), 0, 1)), 0, 255).astype(np.uint8)  # 0-255


def _import_viser():
    try:
        import viser
    except ImportError:
        raise InputError("the viewer needs viser: pip install 'vggt-slam-pp[viz]'") from None
    return viser


@dataclass
class _Submap:
    """What the viewer keeps of one submap (ground frame = the DEM plane's canonical frame)."""

    points: np.ndarray  # [N,3] submap frame (decimated)
    image_colors: np.ndarray | None  # [N,3] uint8
    camera_centers: np.ndarray  # [S,3] submap frame
    frames: list[int]
    T_world_submap: np.ndarray
    camera_rotations: np.ndarray | None = None  # [S,3,3] R_world_cam at T_world_submap
    handles: list = field(default_factory=list)


class RunViewer:
    """The scene of one run in a viser server. ``frame``: the DEM plane (``GroundPlane`` dict) whose
    canonical frame the scene is drawn in (None: the run's world frame)."""

    def __init__(self, server, plane: dict | None = None, thumbnails=None, point_size: float = 0.05) -> None:
        self.server = server
        self._plane = None
        if plane is not None:
            from vggt_slam_pp.dem import GroundPlane

            self._plane = GroundPlane.from_dict(plane)
        self.thumbnails = thumbnails  # callable(frame index) -> [h, w, 3] uint8 or None
        self.point_size = point_size
        self.frustum_scale = 0.5  # world units; build_scene sets 1 % of the trajectory's extent
        self.submaps: dict[int, _Submap] = {}
        self._lock = threading.RLock()  # viser's callbacks run on its own thread
        self.colour_mode = "image"
        self.visible_upto = None  # the time slider: submaps with id <= this are shown
        self.visible_range = (0, 10**9)
        self.hidden: set[int] = set()  # submaps switched off one by one
        self._follow = True  # a live run: the time slider follows the newest submap
        # what is shown; rejected candidates (often many) only on request
        self._layers = {"map": True, "cameras": True, "trajectories": True, "loops": True, "rejected": False,
                        "dem": True}
        self.loop_candidates: list[dict] = []
        self.gui: dict = {}
        self.nodes: dict[str, object] = {}  # scene node name -> viser handle, of everything drawn

    def _keep(self, handle):
        with self._lock:
            self.nodes[handle.name] = handle
        return handle

    # -- frames ---------------------------------------------------------------------------------
    def to_ground(self, world: np.ndarray) -> np.ndarray:
        """World points [N,3] -> the scene's frame."""
        return world if self._plane is None else self._plane.to_canonical(world)

    def _ground_rotation(self) -> np.ndarray:
        return np.eye(3) if self._plane is None else self._plane.R

    # -- building -------------------------------------------------------------------------------
    def add_submap(self, submap_id: int, points: np.ndarray, colors: np.ndarray | None, camera_centers: np.ndarray,
                   frames: list[int], T_world_submap: np.ndarray, camera_rotations: np.ndarray | None = None,
                   max_points: int = 20_000) -> None:
        """Add (or replace) a submap: ``points`` [N,3] and ``colors`` [N,3] uint8 in its own frame,
        ``camera_centers`` [S,3] and optionally its keyframes' ``camera_rotations`` [S,3,3] ``R_world_cam``
        (without them every frustum of the submap faces as its first keyframe)."""
        n = len(points)
        keep = np.linspace(0, n - 1, min(n, max_points)).astype(np.int64) if n else np.zeros(0, np.int64)
        sm = _Submap(np.asarray(points[keep], np.float32), None if colors is None else np.asarray(colors[keep], np.uint8),
                     np.asarray(camera_centers, float), list(frames), np.asarray(T_world_submap, float),
                     None if camera_rotations is None else np.asarray(camera_rotations, float))
        with self._lock:
            old = self.submaps.get(submap_id)
            if old is not None:
                self._remove(old)
            self.submaps[submap_id] = sm
            self._draw_submap(submap_id, sm)
        if "submaps" in self.gui:
            self._submap_toggle(submap_id)
        if "time" in self.gui:  # a live run: the sliders grow with it (and follow it unless moved back)
            last, t, r = max(self.submaps), self.gui["time"], self.gui["range"]
            t.max = r.max = max(last, 1)
            if self._follow:
                t.value = last
            if r.value[1] >= last - 1:
                r.value = (r.value[0], last)

    def _draw_submap(self, sid: int, sm: _Submap) -> None:
        scene = self.server.scene
        world = transform_points(sm.T_world_submap, sm.points.astype(np.float64))
        ground = self.to_ground(world)
        colours = sm.image_colors if (self.colour_mode == "image" and sm.image_colors is not None) \
            else height_colors(ground[:, 2])
        visible = self._shown(sid)
        sm.handles = [self._keep(scene.add_point_cloud(f"/map/submap_{sid:06d}", ground.astype(np.float32), colours,
                                                       point_size=self.point_size,
                                                       visible=visible and self._layers["map"]))]
        _, R, _ = decompose_sim3(sm.T_world_submap)
        centres = self.to_ground(transform_points(sm.T_world_submap, sm.camera_centers))
        for k, (c, f) in enumerate(zip(centres, sm.frames, strict=False)):
            R_cam = self._ground_rotation() @ (sm.camera_rotations[k] if sm.camera_rotations is not None else R)
            image = self.thumbnails(f) if self.thumbnails is not None else None
            h = scene.add_camera_frustum(f"/cameras/submap_{sid:06d}/kf_{k:03d}", fov=np.radians(60.0), aspect=4 / 3,
                                         scale=self.frustum_scale, color=(90, 90, 200), image=image,
                                         wxyz=_wxyz(R_cam), position=c, visible=visible and self._layers["cameras"])
            sm.handles.append(self._keep(h))

    def _shown(self, sid: int) -> bool:
        lo, hi = self.visible_range
        return lo <= sid <= hi and (self.visible_upto is None or sid <= self.visible_upto) and sid not in self.hidden

    def set_trajectory(self, name: str, positions_world: np.ndarray, colour=None) -> None:
        """A path [N,3] (world frame) as line segments ``/trajectory/NAME``."""
        p = self.to_ground(np.asarray(positions_world, float))
        if len(p) < 2:
            return
        seg = np.stack([p[:-1], p[1:]], axis=1).astype(np.float32)
        self._keep(self.server.scene.add_line_segments(
            f"/trajectory/{name}", seg, colour or _COLOURS.get(name, (0, 0, 0)), thickness=3.0,
            thickness_units="screen", visible=self._layers["trajectories"]))

    def set_loops(self, candidates: list[dict]) -> None:
        """Loop candidates (``graph.json``'s ``loop_candidates``) between submap centres: accepted ones as
        one node, each rejected one as its own clickable node."""
        self.loop_candidates = sorted(candidates, key=lambda c: (not c.get("accepted"), c["query"], c["match"]))
        scene = self.server.scene
        centre = {i: self.to_ground(transform_points(sm.T_world_submap, sm.camera_centers.mean(0)[None]))[0]
                  for i, sm in self.submaps.items()}
        acc = [c for c in candidates if c.get("accepted") and c["query"] in centre and c["match"] in centre]
        if acc:
            seg = np.array([[centre[c["query"]], centre[c["match"]]] for c in acc], np.float32)
            self._keep(scene.add_line_segments("/loops/accepted", seg, _COLOURS["accepted"], thickness=4.0,
                                               thickness_units="screen", visible=self._layers["loops"]))
        for c in candidates:
            if c.get("accepted") or c["query"] not in centre or c["match"] not in centre:
                continue
            seg = np.array([[centre[c["query"]], centre[c["match"]]]], np.float32)
            name = f"/loops/rejected/{c['query']:06d}_{c['match']:06d}"
            self._keep(scene.add_line_segments(name, seg, _COLOURS["rejected"], thickness=1.5,
                                               thickness_units="screen", visible=self._layers["rejected"]))
            # a line cannot be clicked: a small sphere at its middle can, and shows the reason
            knob = self._keep(scene.add_icosphere(f"{name}_pick", radius=0.3, color=_COLOURS["rejected"],
                                                  position=seg[0].mean(0), visible=self._layers["rejected"]))
            knob.on_click(lambda _e, c=c: self._show_candidate(c))

    def set_dem(self, dem: dict) -> None:
        """The fused DEM (``dem.npz`` as read by :func:`~vggt_slam_pp.viz.run_folder.load_run`) as its
        hillshade on the ground plane (z = 0 of the scene)."""
        from vggt_slam_pp.dem.images import hillshade_rgb

        heights, mpp = dem["heights"], float(dem["mpp"])
        H, W = heights.shape
        step = max(1, int(np.ceil(max(H, W) / 2048)))  # a texture of at most 2048 px a side
        rgb = hillshade_rgb(heights[::step, ::step], mpp=mpp * step)
        u0, v0 = (float(x) * mpp for x in dem["origin_px"])
        centre = (u0 + W * mpp / 2, v0 + H * mpp / 2, -0.01)
        # viser draws an image's row 0 at its -y edge (as OpenCV images), where the DEM's row 0 (smallest v) belongs
        self._keep(self.server.scene.add_image("/dem", np.ascontiguousarray(rgb), render_width=W * mpp,
                                               render_height=H * mpp, position=centre, visible=self._layers["dem"]))

    # -- GUI --------------------------------------------------------------------------------------
    def build_gui(self) -> None:
        gui = self.server.gui
        ids = sorted(self.submaps)
        last = ids[-1] if ids else 0
        with gui.add_folder("Layers"):
            for name in self._layers:
                cb = gui.add_checkbox(name, initial_value=self._layers[name])
                cb.on_update(lambda _e, name=name, cb=cb: self._toggle(name, cb.value))
                self.gui[f"layer_{name}"] = cb
            colour = gui.add_dropdown("colour by", ("image", "height"), initial_value="image")
            colour.on_update(lambda _e: self._recolour(colour.value))
            self.gui["colour"] = colour
        with gui.add_folder("Time and submaps"):
            t = gui.add_slider("submaps up to", min=0, max=max(last, 1), step=1, initial_value=last)
            t.on_update(lambda _e: self._set_upto(int(t.value)))
            r = gui.add_multi_slider("submap range", min=0, max=max(last, 1), step=1, initial_value=(0, max(last, 1)))
            r.on_update(lambda _e: self._set_range(tuple(int(x) for x in r.value)))
            self.gui.update(time=t, range=r)
        self.gui["submaps"] = gui.add_folder("Submaps", expand_by_default=False)
        for sid in ids:
            self._submap_toggle(sid)
        with gui.add_folder("Loop candidates"):
            labels = [f"{c['query']} -> {c['match']}: {'accepted' if c.get('accepted') else 'rejected'}"
                      for c in self.loop_candidates] or ["(none)"]
            pick = gui.add_dropdown("candidate", labels, initial_value=labels[0])
            self.gui["candidate_text"] = gui.add_markdown(self._describe(self.loop_candidates[0])
                                                          if self.loop_candidates else "no loop candidates")
            pick.on_update(lambda _e: self._show_candidate(
                self.loop_candidates[labels.index(pick.value)]) if self.loop_candidates else None)
            self.gui["candidate"] = pick

    def _submap_toggle(self, sid: int) -> None:
        """A checkbox for one submap in the GUI's "Submaps" folder."""
        key = f"submap_{sid}"
        if key in self.gui:
            return
        with self.gui["submaps"]:
            cb = self.server.gui.add_checkbox(f"submap {sid}", initial_value=sid not in self.hidden)
        cb.on_update(lambda _e: self._set_hidden(sid, not cb.value))
        self.gui[key] = cb

    def _set_hidden(self, sid: int, hidden: bool) -> None:
        if hidden:
            self.hidden.add(sid)
        else:
            self.hidden.discard(sid)
        self._refresh_visibility()

    @staticmethod
    def _describe(c: dict) -> str:
        keys = ("reason", "source", "guess", "score", "overlap", "structure_overlap", "agreement", "residual")
        body = "  \n".join(f"**{k}**: {c[k]:.4g}" if isinstance(c.get(k), float) else f"**{k}**: {c.get(k)}"
                           for k in keys if k in c)
        return f"**{c['query']} -> {c['match']}** ({'accepted' if c.get('accepted') else 'rejected'})  \n{body}"

    def _show_candidate(self, c: dict) -> None:
        if "candidate_text" in self.gui:
            self.gui["candidate_text"].content = self._describe(c)

    def _toggle(self, layer: str, on: bool) -> None:
        self._layers[layer] = on
        self._refresh_visibility()

    def _set_upto(self, n: int) -> None:
        self.visible_upto = n
        self._follow = "time" not in self.gui or n >= self.gui["time"].max
        self._refresh_visibility()

    def _set_range(self, lo_hi: tuple[int, int]) -> None:
        self.visible_range = lo_hi
        self._refresh_visibility()

    def _refresh_visibility(self) -> None:
        scene_nodes = {"trajectories": "/trajectory", "loops": "/loops/accepted", "dem": "/dem"}
        with self._lock:
            for sid, sm in self.submaps.items():
                shown = self._shown(sid)
                for h in sm.handles:
                    layer = "map" if h.name.startswith("/map/") else "cameras"
                    h.visible = shown and self._layers[layer]
        for layer, prefix in scene_nodes.items():
            for h in self._handles(prefix):
                h.visible = self._layers[layer]
        for h in self._handles("/loops/rejected/"):
            h.visible = self._layers["rejected"]

    def _handles(self, prefix: str) -> list:
        with self._lock:
            return [h for name, h in self.nodes.items() if name.startswith(prefix)]

    def _recolour(self, mode: str) -> None:
        self.colour_mode = mode
        with self._lock:
            for sm in self.submaps.values():
                world = transform_points(sm.T_world_submap, sm.points.astype(np.float64))
                ground = self.to_ground(world)
                colours = sm.image_colors if (mode == "image" and sm.image_colors is not None) \
                    else height_colors(ground[:, 2])
                sm.handles[0].colors = colours

    def set_poses(self, poses: dict[int, np.ndarray]) -> None:
        """New ``T_world_submap`` for submaps already shown (a live run's pose snapshot)."""
        with self._lock:
            for sid, T in poses.items():
                sm = self.submaps.get(sid)
                if sm is None or np.allclose(sm.T_world_submap, T, atol=1e-4):
                    continue
                if sm.camera_rotations is not None:  # turned with the submap
                    _, R_old, _ = decompose_sim3(sm.T_world_submap)
                    _, R_new, _ = decompose_sim3(np.asarray(T, float))
                    sm.camera_rotations = (R_new @ R_old.T) @ sm.camera_rotations
                sm.T_world_submap = np.asarray(T, float)
                self._remove(sm)
                self._draw_submap(sid, sm)

    def _remove(self, sm: _Submap) -> None:
        with self._lock:
            for h in sm.handles:
                self.nodes.pop(h.name, None)
                h.remove()
            sm.handles = []

    def look_at_all(self) -> None:
        """Start the camera above the middle of everything drawn, looking down at it at 45 deg."""
        centres = [self.to_ground(transform_points(sm.T_world_submap, sm.camera_centers)) for sm in self.submaps.values()
                   if len(sm.camera_centers)]
        if not centres:
            return
        p = np.concatenate(centres)
        mid, size = p.mean(0), float(np.linalg.norm(np.ptp(p, axis=0))) + 1.0
        cam = self.server.initial_camera
        cam.look_at = tuple(mid)
        cam.position = tuple(mid + np.array([0.0, -0.6, 0.8]) * size)
        cam.up = (0.0, 0.0, 1.0)

    def node_names(self) -> list[str]:
        """The names of the scene nodes drawn (what a person sees in the scene tree)."""
        with self._lock:
            return sorted(self.nodes)


def _wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _thumbnail_reader(folder: Path, width: int = 96):
    """frame index -> small RGB image, from the input named in ``input.json``; None when it is gone."""
    import json

    import cv2

    try:
        given = json.loads((folder / "input.json").read_text())
        from vggt_slam_pp.io import open_source

        source = open_source(given["input"], layout=given.get("layout", "auto"), stride=given.get("stride", 1))
    except (OSError, ValueError, KeyError, VggtSlamError) as exc:
        log.info("no thumbnails (%s)", exc)
        return None

    def read(index: int):
        try:
            image = source[int(index)].image
        except (IndexError, VggtSlamError, OSError):
            return None
        h, w = image.shape[:2]
        return cv2.resize(image, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)

    return read


def build_scene(server, run: RunFolder, max_points: int = 300_000) -> RunViewer:
    """Fill ``server``'s scene and GUI with ``run``."""
    graph = run.graph or {}
    viewer = RunViewer(server, graph.get("plane"), _thumbnail_reader(run.folder))
    extent = float(np.linalg.norm(np.ptp(run.odometry.positions, axis=0))) if len(run.odometry) else 1.0
    viewer.frustum_scale = max(0.01 * extent, 1e-3)
    viewer.point_size = max(0.002 * extent, 1e-3)
    nodes = run.nodes
    per = max(1000, max_points // max(len(nodes), 1))
    rotations = run.keyframe_rotations()
    first_own = int(run.report.get("map_submaps", 0))  # an extended map: earlier submaps are another recording's
    thumbnails = viewer.thumbnails
    for n in nodes:
        got = run.submap_points(n["id"])
        pts, rgb = got if got is not None else (np.zeros((0, 3), np.float32), None)
        frames = n.get("frames", [])
        own = n["id"] >= first_own  # this run's frames: its thumbnails and keyframe rotations apply
        viewer.thumbnails = thumbnails if own else None
        rot = np.array([rotations[f] for f in frames]) if own and frames and all(f in rotations for f in frames) \
            else None
        viewer.add_submap(n["id"], np.asarray(pts), None if rgb is None else np.asarray(rgb),
                          np.asarray(n.get("camera_centers", np.zeros((0, 3)))), frames,
                          np.asarray(n["T_world_submap"]), camera_rotations=rot, max_points=per)
    viewer.thumbnails = thumbnails
    if not nodes:
        log.warning("%s has no graph.json (a run without the back-end): trajectories only", run.folder)
    viewer.set_trajectory("odometry", run.odometry.positions)
    if run.corrected is not None:
        viewer.set_trajectory("corrected", run.corrected.positions)
    if run.ground_truth is not None:
        from vggt_slam_pp.eval.metrics import associate
        from vggt_slam_pp.geometry.alignment import umeyama

        est = run.corrected or run.odometry
        try:  # the ground truth drawn in the estimate's frame (the inverse of the ATE's alignment)
            i_ref, i_est = associate(run.ground_truth, est)
            T = umeyama(run.ground_truth.positions[i_ref], est.positions[i_est], with_scale=True)
            viewer.set_trajectory("ground_truth", transform_points(T, run.ground_truth.positions))
        except VggtSlamError as exc:
            log.warning("ground truth not drawn: %s", exc)
    viewer.set_loops(run.loop_candidates)
    if run.dem is not None:
        viewer.set_dem(run.dem)
    viewer.build_gui()
    viewer.look_at_all()
    return viewer


class _Serving:
    def __init__(self, server, viewer: RunViewer) -> None:
        self.server, self.viewer = server, viewer
        self.port = server.get_port()

    def wait(self) -> None:
        threading.Event().wait()

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints; only the CLI may
            self.server.stop()


def serve(run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080, max_points: int = 300_000) -> _Serving:
    """Start a viser server on ``host:port`` showing the run in ``run_dir``; returns it serving
    (``.port``, ``.viewer``, ``.stop()``).

    Raises:
        InputError: not a run folder, or viser is not installed.
    """
    viser = _import_viser()
    run = load_run(run_dir)
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner; only the CLI may print
        server = viser.ViserServer(host=host, port=port, verbose=False)
    # the DEM's ground frame is z up; without a back-end the scene stays in the first camera's frame (y down)
    server.scene.set_up_direction("+z" if (run.graph or {}).get("plane") else "-y")
    try:
        viewer = build_scene(server, run, max_points)
    except BaseException:
        _Serving(server, None).stop()
        raise
    return _Serving(server, viewer)
