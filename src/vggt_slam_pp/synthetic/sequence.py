"""Write synthetic sequences in the TUM RGB-D layout, readable by the ordinary TUM reader.

Layout written into ``out``::

    rgb/<timestamp>.png        colour, 8-bit RGB
    depth/<timestamp>.png      16-bit depth, raw = metres * depth_scale (0 = unknown or out of range)
    rgb.txt, depth.txt         "timestamp filename" lists
    groundtruth.txt            TUM trajectory of T_world_cam (world z up, OpenCV camera)
    camera.json                fx fy cx cy width height depth_scale (+ dist = [])
    world.json                 the generated world (solids), for ground-truth footprints
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vggt_slam_pp.errors import SyntheticError
from vggt_slam_pp.geometry.camera import PinholeCamera
from vggt_slam_pp.io.images import write_depth_png
from vggt_slam_pp.io.trajectory import Trajectory, atomic_write_text, write_tum
from vggt_slam_pp.synthetic.renderer import Renderer
from vggt_slam_pp.synthetic.trajectories import SCENES, from_trajectory_file
from vggt_slam_pp.synthetic.world import World, generate_world

log = logging.getLogger(__name__)

__all__ = ["SyntheticScene", "default_camera", "make_scene", "write_sequence"]


@dataclass(frozen=True)
class SyntheticScene:
    """A world, a camera trajectory through it and the camera."""

    world: World
    trajectory: Trajectory
    camera: PinholeCamera
    name: str


def default_camera(width: int = 640, height: int = 480, hfov_deg: float = 70.0) -> PinholeCamera:
    """A centred pinhole camera with the given horizontal field of view."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return PinholeCamera(f, f, (width - 1) / 2, (height - 1) / 2, width, height)


def make_scene(
    scene: str | None = "loop",
    *,
    trajectory_file: str | Path | None = None,
    frames: int | None = 300,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    style: str | None = None,
    scene_options: dict | None = None,
) -> SyntheticScene:
    """Build a scene: a built-in trajectory (``figure8``, ``loop``; ``scene_options`` are passed to its
    function, e.g. ``{"length": 600.0}`` for a larger block) or one read from a file, plus a world
    generated around it with ``seed``."""
    if trajectory_file is not None:
        traj, auto_style = from_trajectory_file(trajectory_file, frames)
        name = Path(trajectory_file).stem
    else:
        if scene not in SCENES:
            raise SyntheticError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)} or give a trajectory file")
        traj = SCENES[scene](n_frames=300 if frames is None else frames, **(scene_options or {}))
        auto_style, name = "outdoor", scene
    style = style or auto_style
    world = generate_world(traj.positions[:, :2], style=style, seed=seed)
    return SyntheticScene(world, traj, default_camera(width, height), name)


def write_sequence(
    scene: SyntheticScene,
    out: str | Path,
    *,
    depth_scale: float = 5000.0,
    max_depth: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    aperiodic: bool = False,
) -> dict:
    """Render every pose of ``scene`` and write the TUM RGB-D layout into ``out``.

    ``aperiodic``: a texture that does not repeat (see :class:`Renderer`); the periodic default keeps the
    images that the loop-closure benchmarks were measured on.

    An interrupted render resumes: ``render.json`` (written first) names what is rendered, and when it
    matches, the leading frames whose colour and depth images are both on disk are kept (the last of them
    is rendered again: it may be the one that was being written); the images of a render of anything else
    are removed first.

    Returns:
        a summary: frames, seconds spent rendering and writing, seconds per frame.
    """
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    max_depth = max_depth or (80.0 if scene.world.style == "outdoor" else 15.0)
    renderer = Renderer(scene.world, scene.camera, max_depth=max_depth, aperiodic=aperiodic)
    traj = scene.trajectory
    done = _resumable(out, _fingerprint(scene, depth_scale, max_depth, aperiodic),
                      [f"{ts:.6f}.png" for ts in traj.timestamps])
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    t0 = time.perf_counter()
    t_render = 0.0
    for i, (ts, T) in enumerate(zip(traj.timestamps, traj.poses, strict=False)):
        name = f"{ts:.6f}.png"
        rgb_lines.append(f"{ts:.6f} rgb/{name}")
        depth_lines.append(f"{ts:.6f} depth/{name}")
        if i + 1 < done:
            continue
        tr = time.perf_counter()
        rgb, depth = renderer.render(T)
        t_render += time.perf_counter() - tr
        if not cv2.imwrite(str(out / "rgb" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise SyntheticError(f"cannot write {out / 'rgb' / name}")
        write_depth_png(out / "depth" / name, depth, depth_scale)
        if progress is not None:
            progress(i + 1, len(traj))
    atomic_write_text(out / "rgb.txt", "\n".join(rgb_lines) + "\n")
    atomic_write_text(out / "depth.txt", "\n".join(depth_lines) + "\n")
    write_tum(out / "groundtruth.txt", traj)
    cam = scene.camera
    atomic_write_text(out / "camera.json", json.dumps(
        {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height,
         "depth_scale": depth_scale, "dist": []}, indent=1))
    scene.world.save(out / "world.json")
    total = time.perf_counter() - t0
    n = len(traj)
    summary = {"frames": n, "width": cam.width, "height": cam.height, "solids": len(scene.world.solids),
               "style": scene.world.style, "seconds_total": total, "seconds_render": t_render,
               "seconds_per_frame": total / n, "path_length": traj.path_length(), "out": str(out)}
    log.info("wrote %d frames to %s in %.1f s (%.3f s/frame)", n, out, total, total / n)
    return summary


def _fingerprint(scene: SyntheticScene, depth_scale: float, max_depth: float, aperiodic: bool) -> dict:
    """What a rendered frame depends on (the world, the camera, the poses and the rendering options)."""
    import hashlib

    poses = (np.ascontiguousarray(scene.trajectory.poses, np.float64).tobytes()
             + np.ascontiguousarray(scene.trajectory.timestamps, np.float64).tobytes())
    w = scene.world
    world = json.dumps({"style": w.style, "seed": w.seed, "ground_color": np.asarray(w.ground_color).tolist(),
                        "solids": [s.to_dict() for s in w.solids]}, sort_keys=True).encode()
    cam = scene.camera
    return {"name": scene.name, "frames": len(scene.trajectory), "depth_scale": depth_scale, "max_depth": max_depth,
            "aperiodic": aperiodic, "style": scene.world.style,
            "camera": [cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height],
            "poses_sha1": hashlib.sha1(poses).hexdigest(), "world_sha1": hashlib.sha1(world).hexdigest()}


def _resumable(out: Path, fingerprint: dict, names: list[str]) -> int:
    """How many leading frames (file ``names``, in order) of an earlier render of the same ``fingerprint``
    into ``out`` have both images on disk; an earlier render of something else is cleared (0). Writes the
    fingerprint for this render."""
    path = out / "render.json"
    try:
        same = json.loads(path.read_text()) == fingerprint
    except (OSError, ValueError):
        same = False
    if not same:
        for folder in ("rgb", "depth"):
            for old in (out / folder).glob("*.png"):
                old.unlink()
    atomic_write_text(path, json.dumps(fingerprint, indent=1))
    done = 0
    while done < len(names) and all((out / folder / names[done]).is_file() for folder in ("rgb", "depth")):
        done += 1
    return done
