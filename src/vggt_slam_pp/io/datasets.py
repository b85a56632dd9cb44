"""Readers of native dataset layouts, each returning an :class:`ImageSequence`.

Layouts (``detect_layout`` checks them in this order):

============  ======================================================================================
``euroc``     EuRoC ASL: ``mav0/cam0/data.csv``, ``data/``, ``sensor.yaml``; ground truth
              ``mav0/state_groundtruth_estimate0/data.csv`` (body poses; camera = body · T_BS).
``tum``       TUM RGB-D: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``; intrinsics from ``camera.json``
              (our synthetic sequences) or the published freiburg1/2/3 values when the name says which.
``kitti``     KITTI odometry sequence folder: ``image_2/`` (or ``image_0/``), ``times.txt``, ``calib.txt``;
              ground truth ``poses/<seq>.txt`` two levels up (or ``poses.txt`` beside the images).
              A KITTI odometry *root* (``dataset/`` holding ``sequences/NN/``, or ``sequences/`` itself)
              is not a sequence: it is refused with an error that lists its sequences.
``7scenes``   Microsoft 7-Scenes sequence: ``frame-XXXXXX.color.png``, ``.depth.png`` (mm), ``.pose.txt``.
``vkitti2``   Virtual KITTI 2 scene variation: ``frames/rgb/Camera_0/rgb_XXXXX.jpg``,
              ``frames/depth/Camera_0/depth_XXXXX.png`` (cm), ``intrinsic.txt``, ``extrinsic.txt``.
``video``     a video file.
``images``    a folder of images in natural order; timestamps from file names that are times
              (decimal seconds, or integers >= 1e6; nanoseconds when > 1e12), else ``index / fps``.
============  ======================================================================================
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
import yaml
from natsort import natsorted

from vggt_slam_pp.errors import InputError, TrajectoryError
from vggt_slam_pp.geometry.camera import PinholeCamera
from vggt_slam_pp.geometry.lie import se3_inverse
from vggt_slam_pp.io.frames import FrameSource, FrameSubset, ImageSequence
from vggt_slam_pp.io.images import IMAGE_EXTENSIONS, read_rgb
from vggt_slam_pp.io.trajectory import (
    Trajectory,
    nearest_time_indices,
    read_euroc_csv,
    read_kitti,
    read_trajectory,
    read_tum,
)
from vggt_slam_pp.io.video import VIDEO_EXTENSIONS, VideoSource

log = logging.getLogger(__name__)

LAYOUTS = ("euroc", "tum", "kitti", "7scenes", "vkitti2", "video", "images")

__all__ = ["LAYOUTS", "detect_layout", "open_source", "open_image_folder", "open_tum", "open_kitti",
           "open_euroc", "open_7scenes", "open_vkitti2", "list_images"]

# Published TUM RGB-D calibrations (fx, fy, cx, cy, k1, k2, p1, p2, k3) of the colour cameras.
_TUM_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "freiburg3": (535.4, 539.2, 320.1, 247.6, 0.0, 0.0, 0.0, 0.0, 0.0),
}
_SEVEN_SCENES_CAMERA = (585.0, 585.0, 320.0, 240.0)


def list_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` in natural order (``img2`` before ``img10``), hidden files skipped."""
    return natsorted((p for p in folder.iterdir()
                      if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")),
                     key=lambda p: p.name)


def _numeric_timestamps(paths: list[Path]) -> np.ndarray | None:
    """Timestamps from file names such as ``1305031102.175304.png`` (seconds) or
    ``1403638538577829376.png`` (nanoseconds when > 1e12). Small integers (``000123.png``) are frame
    numbers, not times, and give None, as do names that are not increasing numbers."""
    try:
        vals = np.array([float(p.stem) for p in paths])
    except ValueError:
        return None
    if len(vals) > 1 and np.any(np.diff(vals) <= 0):
        return None
    if all("." not in p.stem for p in paths) and vals.max() < 1e6:
        return None
    return vals * 1e-9 if vals.max() > 1e12 else vals


def open_image_folder(root: Path, fps: float = 1.0) -> ImageSequence:
    """A plain folder of images (natural sort). Timestamps from numeric names, else ``index / fps``."""
    if not root.is_dir():
        raise InputError(f"not a folder: {root}")
    paths = list_images(root)
    if not paths:
        raise InputError(f"no images found in {root} (looked for {', '.join(IMAGE_EXTENSIONS)})")
    ts = _numeric_timestamps(paths)
    if ts is None:
        if fps <= 0:
            raise InputError(f"fps must be positive, got {fps}")
        ts = np.arange(len(paths)) / fps
    return ImageSequence(root, "images", paths, ts)


def _read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """TUM list file: ``timestamp filename`` rows, ``#`` comments."""
    times, names = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            times.append(float(parts[0]))
            names.append(parts[1])
        except (ValueError, IndexError):
            raise InputError(f"{path}:{lineno}: expected 'timestamp filename', got {s[:60]!r}") from None
    return np.array(times), names


def open_tum(root: Path, depth_max_diff: float = 0.02) -> ImageSequence:
    """TUM RGB-D sequence folder (also our synthetic sequences). Depth associated within 20 ms."""
    rgb_list = root / "rgb.txt"
    if not rgb_list.is_file():
        raise InputError(f"not a TUM RGB-D folder (no rgb.txt): {root}")
    ts, names = _read_list(rgb_list)
    if len(ts) == 0:
        raise InputError(f"{rgb_list} lists no images")
    paths = [root / n for n in names]
    depth_paths = None
    depth_scale = 5000.0
    camera = None
    cam_json = root / "camera.json"
    if cam_json.is_file():
        try:
            c = json.loads(cam_json.read_text())
            camera = PinholeCamera(c["fx"], c["fy"], c["cx"], c["cy"], int(c["width"]), int(c["height"]),
                                   tuple(c.get("dist", ())))
            depth_scale = float(c.get("depth_scale", depth_scale))
        except (KeyError, ValueError, TypeError, json.JSONDecodeError) as exc:
            raise InputError(f"malformed {cam_json}: {exc}") from None
    else:
        for key, vals in _TUM_CAMERAS.items():
            if key in root.name:
                w, h = 640, 480
                camera = PinholeCamera(*vals[:4], w, h, tuple(vals[4:]) if any(vals[4:]) else ())
    depth_list = root / "depth.txt"
    if depth_list.is_file():
        dts, dnames = _read_list(depth_list)
        match = nearest_time_indices(ts, dts, depth_max_diff)
        depth_paths = [root / dnames[m] if m >= 0 else None for m in match]
    gt = None
    gt_path = root / "groundtruth.txt"
    if gt_path.is_file():
        try:
            gt = read_tum(gt_path)
        except TrajectoryError as exc:
            raise InputError(f"bad ground truth: {exc}") from None
    return ImageSequence(root, "tum", paths, ts, depth_paths=depth_paths, depth_scale=depth_scale,
                         camera=camera, ground_truth=gt)


def _kitti_calib(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in path.read_text().splitlines():
        if ":" not in line:
            continue
        key, vals = line.split(":", 1)
        try:
            out[key.strip()] = np.array([float(v) for v in vals.split()])
        except ValueError:
            raise InputError(f"{path}: malformed calibration line {line[:40]!r}") from None
    return out


_KITTI_IMAGE_DIRS = ("image_2", "image_0")
_KITTI_SEQUENCE_MARKERS = ("times.txt", "calib.txt", "velodyne")


def _is_kitti_sequence(folder: Path) -> bool:
    """Whether ``folder`` looks like a KITTI odometry sequence: it has ``image_2/`` or ``image_0/``."""
    return any((folder / d).is_dir() for d in _KITTI_IMAGE_DIRS)


def _name_ranges(names: list[str]) -> str:
    """``00, 01, 02, 05`` -> ``00-02, 05``: runs of three or more consecutive numbers of equal width
    are shortened; other names are listed as they are."""
    parts: list[str] = []
    i = 0
    while i < len(names):
        j = i
        if names[i].isdigit():
            while (j + 1 < len(names) and names[j + 1].isdigit() and len(names[j + 1]) == len(names[i])
                   and int(names[j + 1]) == int(names[j]) + 1):
                j += 1
        parts.append(f"{names[i]}-{names[j]}" if j - i >= 2 else ", ".join(names[i : j + 1]))
        i = j + 1
    return ", ".join(parts)


def _kitti_root_error(path: Path) -> InputError | None:
    """The error for a KITTI odometry root given where one sequence is expected, or None.

    ``path`` is a root when it holds ``sequences/NN/`` or when it is such a ``sequences`` folder itself:
    a folder whose sub-folders are KITTI sequences (``image_2/`` or ``image_0/``, see
    :func:`_is_kitti_sequence`). Ground truth is ``poses/NN.txt`` beside ``sequences``. A root whose
    sequence folders hold only ``times.txt``, ``calib.txt`` or ``velodyne/`` (the images were not
    downloaded) gets an error saying so.
    """
    if not path.is_dir() or _is_kitti_sequence(path):
        return None
    seq_dir = path / "sequences" if (path / "sequences").is_dir() else path
    try:
        subdirs = natsorted((d for d in seq_dir.iterdir() if d.is_dir() and not d.name.startswith(".")),
                            key=lambda d: d.name)
    except OSError:
        return None
    with_images = [d for d in subdirs if _is_kitti_sequence(d)]
    without_images = [d for d in subdirs if d not in with_images
                      and any((d / m).exists() for m in _KITTI_SEQUENCE_MARKERS)]
    if not with_images and not (without_images and (seq_dir.name == "sequences" or seq_dir != path)):
        return None
    poses_dir = seq_dir.parent / "poses"
    if not with_images:
        names = [d.name for d in without_images]
        log.debug("%s: KITTI sequences without images: %s", path, names)
        return InputError(
            f"{path} is a KITTI odometry root with {len(names)} sequence(s) ({_name_ranges(names)}) "
            "but none has image_2/ or image_0/: download the colour or grayscale images of the odometry "
            "benchmark")
    names = [d.name for d in with_images]
    gt_names = [n for n in names if (poses_dir / f"{n}.txt").is_file()]
    gt = f"; ground truth for {_name_ranges(gt_names)}" if gt_names else "; no ground truth"
    log.debug("%s: KITTI root, sequences %s, ground truth %s", path, names, gt_names)
    return InputError(
        f"{path} is a KITTI odometry root with {len(names)} sequence{'s' if len(names) != 1 else ''} "
        f"({_name_ranges(names)}{gt}): pass one sequence folder instead, e.g. {with_images[0]}")


def _kitti_times(path: Path, n_images: int) -> np.ndarray:
    """Seconds per frame from a KITTI ``times.txt`` (one number a line, scientific notation allowed)."""
    try:
        ts = np.array([float(x) for x in path.read_text().split()])
    except ValueError as exc:
        raise InputError(f"{path}: malformed time ({exc})") from None
    if len(ts) != n_images:
        raise InputError(f"{path} has {len(ts)} times for {n_images} images")
    return ts


def open_kitti(root: Path) -> ImageSequence:
    """KITTI odometry sequence folder (``sequences/XX``). Ground truth is for the chosen camera:
    the cam0 poses of ``poses/XX.txt`` (12 columns, camera-to-world of the left grayscale camera),
    timed by ``times.txt``, moved by the camera's baseline from ``calib.txt``.

    A KITTI odometry root (``dataset/`` or ``dataset/sequences``) raises :class:`InputError` naming
    its sequences."""
    cam_name = next((d for d in _KITTI_IMAGE_DIRS if (root / d).is_dir()), None)
    if cam_name is None:
        root_error = _kitti_root_error(root)
        if root_error is not None:
            raise root_error
        raise InputError(f"not a KITTI sequence folder (no image_2/ or image_0/): {root}")
    img_dir = root / cam_name
    paths = list_images(img_dir)
    if not paths:
        raise InputError(f"no images in {img_dir}")
    times = root / "times.txt"
    if times.is_file():
        ts = _kitti_times(times, len(paths))
    else:
        log.info("%s: no times.txt; assuming 10 Hz", root)
        ts = np.arange(len(paths)) * 0.1
    camera = None
    T_cam0_cam = np.eye(4)
    calib = root / "calib.txt"
    if calib.is_file():
        cal = _kitti_calib(calib)
        key = "P2" if cam_name == "image_2" else "P0"
        if key in cal and cal[key].size == 12:
            P = cal[key].reshape(3, 4)
            h, w = read_rgb(paths[0]).shape[:2]
            camera = PinholeCamera.from_matrix(P[:, :3], w, h)
            # P = K [I | b]: a cam0 point x is at x + b in this camera, so T_cam0_cam = [I | -b].
            T_cam0_cam[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])
    gt = None
    for cand in (root.parent.parent / "poses" / f"{root.name}.txt", root / "poses.txt", root / f"{root.name}.txt"):
        if cand.is_file():
            try:
                g = read_kitti(cand)
            except TrajectoryError as exc:
                raise InputError(f"bad ground truth: {exc}") from None
            if len(g) != len(paths):
                raise InputError(f"{cand} has {len(g)} poses for {len(paths)} images")
            if cam_name != "image_0" and not T_cam0_cam[:3, 3].any():
                log.warning("%s: no P2 baseline in calib.txt; ground truth %s is of cam0 (image_0), "
                            "used unchanged for image_2", root, cand)
            gt = Trajectory(ts, g.poses @ T_cam0_cam)
            break
    return ImageSequence(root, "kitti", paths, ts, camera=camera, ground_truth=gt)


def _euroc_yaml(path: Path) -> dict:
    try:
        text = path.read_text()
        # OpenCV-style headers ("%YAML:1.0") are not valid for PyYAML.
        return yaml.safe_load(re.sub(r"^%YAML:.*$", "", text, flags=re.M)) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"cannot parse {path}: {exc}") from None


def _euroc_matrix(d: dict, path: Path) -> np.ndarray:
    try:
        return np.array(d["data"], dtype=np.float64).reshape(int(d["rows"]), int(d["cols"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: malformed matrix entry: {exc}") from None


def open_euroc(root: Path, camera: str = "cam0") -> ImageSequence:
    """EuRoC ASL sequence (the folder holding ``mav0`` or ``mav0`` itself). Timestamps in seconds."""
    mav = root / "mav0" if (root / "mav0").is_dir() else root
    cam_dir = mav / camera
    data_csv = cam_dir / "data.csv"
    if not data_csv.is_file():
        raise InputError(f"not an EuRoC ASL folder (no {camera}/data.csv): {root}")
    stamps, paths = [], []
    for lineno, line in enumerate(data_csv.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        try:
            stamps.append(int(parts[0]))
            paths.append(cam_dir / "data" / parts[1])
        except (ValueError, IndexError):
            raise InputError(f"{data_csv}:{lineno}: expected 'timestamp_ns,filename'") from None
    if not paths:
        raise InputError(f"{data_csv} lists no images")
    ts = np.array(stamps, dtype=np.float64) * 1e-9
    cam = None
    T_BS = np.eye(4)
    sensor = cam_dir / "sensor.yaml"
    if sensor.is_file():
        y = _euroc_yaml(sensor)
        if "T_BS" in y:
            T_BS = _euroc_matrix(y["T_BS"], sensor)
        try:
            fx, fy, cx, cy = (float(v) for v in y["intrinsics"])
            w, h = (int(v) for v in y["resolution"])
            dist = tuple(float(v) for v in y.get("distortion_coefficients", ()))
            if y.get("distortion_model", "radial-tangential") != "radial-tangential":
                log.warning("%s: distortion model %s is not supported; ignoring distortion", sensor,
                            y.get("distortion_model"))
                dist = ()
            cam = PinholeCamera(fx, fy, cx, cy, w, h, dist)
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("%s: no usable intrinsics (%s)", sensor, exc)
    gt = None
    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        try:
            body = read_euroc_csv(gt_csv)
        except TrajectoryError as exc:
            raise InputError(f"bad ground truth: {exc}") from None
        gt = body.right_multiplied(T_BS)  # T_R_C = T_R_S @ T_BS (S = body/IMU frame)
    return ImageSequence(root, "euroc", paths, ts, camera=cam, ground_truth=gt)


def open_7scenes(root: Path, fps: float = 30.0) -> ImageSequence:
    """7-Scenes sequence folder (``seq-XX``). Depth in millimetres (65535 = unknown), poses camera-to-world.

    Note: 7-Scenes depth is not registered to the colour image; it is provided as recorded.
    """
    paths = natsorted(root.glob("frame-*.color.png"), key=lambda p: p.name)
    if not paths:
        raise InputError(f"not a 7-Scenes sequence folder (no frame-*.color.png): {root}")
    depth_paths = [p.with_name(p.name.replace(".color.png", ".depth.png")) for p in paths]
    depth_paths = [d if d.is_file() else None for d in depth_paths]
    pose_paths = [p.with_name(p.name.replace(".color.png", ".pose.txt")) for p in paths]
    ts = np.arange(len(paths)) / fps
    gt = None
    if all(p.is_file() for p in pose_paths):
        try:
            poses = np.stack([np.loadtxt(p).reshape(4, 4) for p in pose_paths])
        except ValueError as exc:
            raise InputError(f"malformed 7-Scenes pose file in {root}: {exc}") from None
        gt = Trajectory(ts, poses)
    h, w = read_rgb(paths[0]).shape[:2]
    fx, fy, cx, cy = _SEVEN_SCENES_CAMERA
    cam = PinholeCamera(fx, fy, cx, cy, 640, 480).scaled(w, h)
    return ImageSequence(root, "7scenes", paths, ts, depth_paths=depth_paths if any(depth_paths) else None,
                         depth_scale=1000.0, depth_invalid=65535, camera=cam, ground_truth=gt)


def _vkitti_table(path: Path, camera_id: int, ncols: int) -> dict[int, np.ndarray]:
    rows = {}
    for line in path.read_text().splitlines()[1:]:
        parts = line.split()
        if len(parts) < 2 + ncols:
            continue
        try:
            frame, cam = int(parts[0]), int(parts[1])
            if cam == camera_id:
                rows[frame] = np.array([float(v) for v in parts[2 : 2 + ncols]])
        except ValueError:
            raise InputError(f"{path}: malformed row {line[:50]!r}") from None
    return rows


def open_vkitti2(root: Path, camera_id: int = 0, fps: float = 10.0) -> ImageSequence:
    """Virtual KITTI 2 scene variation (e.g. ``Scene01/clone``). Depth in centimetres; ``extrinsic.txt``
    holds world-to-camera matrices, inverted here into ``T_world_cam``."""
    base = root / "frames" if (root / "frames").is_dir() else root
    rgb_dir = base / "rgb" / f"Camera_{camera_id}"
    paths = list_images(rgb_dir) if rgb_dir.is_dir() else []
    if not paths:
        raise InputError(f"not a Virtual KITTI 2 folder (no frames/rgb/Camera_{camera_id}/): {root}")
    idx = [int(re.findall(r"\d+", p.stem)[-1]) for p in paths]
    depth_dir = base / "depth" / f"Camera_{camera_id}"
    depth_paths = None
    if depth_dir.is_dir():
        depth_paths = [depth_dir / f"depth_{i:05d}.png" for i in idx]
        depth_paths = [d if d.is_file() else None for d in depth_paths]
    ts = np.array(idx, dtype=np.float64) / fps
    cam = None
    intr = root / "intrinsic.txt"
    if intr.is_file():
        k = _vkitti_table(intr, camera_id, 4)
        if idx[0] in k:
            h, w = read_rgb(paths[0]).shape[:2]
            cam = PinholeCamera(*k[idx[0]], w, h)
    gt = None
    extr = root / "extrinsic.txt"
    if extr.is_file():
        e = _vkitti_table(extr, camera_id, 16)
        if all(i in e for i in idx):
            T_cam_world = np.stack([e[i].reshape(4, 4) for i in idx])
            gt = Trajectory(ts, se3_inverse(T_cam_world))
    return ImageSequence(root, "vkitti2", paths, ts, depth_paths=depth_paths, depth_scale=100.0,
                         depth_invalid=65535, camera=cam, ground_truth=gt)


def detect_layout(path: Path) -> str:
    """Name of the layout found at ``path`` (see the module docstring), or raise :class:`InputError`."""
    if not path.exists():
        raise InputError(f"input not found: {path}")
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        raise InputError(f"input file is not a video ({', '.join(VIDEO_EXTENSIONS)}): {path}")
    if (path / "mav0" / "cam0" / "data.csv").is_file() or (path / "cam0" / "data.csv").is_file():
        return "euroc"
    if (path / "rgb.txt").is_file():
        return "tum"
    if (path / "image_2").is_dir() or (path / "image_0").is_dir():
        return "kitti"
    if next(path.glob("frame-*.color.png"), None) is not None:
        return "7scenes"
    if (path / "frames" / "rgb").is_dir() or ((path / "rgb").is_dir() and (path / "extrinsic.txt").is_file()):
        return "vkitti2"
    root_error = _kitti_root_error(path)
    if root_error is not None:
        raise root_error
    if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in path.iterdir() if p.is_file()):
        return "images"
    if not any(path.iterdir()):
        raise InputError(f"input folder is empty: {path}")
    raise InputError(f"no images and no known dataset layout in {path} (layouts: {', '.join(LAYOUTS)})")


def open_source(
    path: str | Path,
    layout: str = "auto",
    *,
    ground_truth: str | Path | None = None,
    gt_format: str = "auto",
    stride: int = 1,
    target_fps: float | None = None,
    fps: float = 1.0,
) -> FrameSource:
    """Open any supported input.

    Args:
        path: a folder (image folder or dataset layout) or a video file.
        layout: ``auto`` or one of :data:`LAYOUTS` to override detection.
        ground_truth: optional trajectory file paired with the frames (replaces the layout's own).
        gt_format: format of ``ground_truth`` (``auto``, ``tum``, ``kitti``, ``euroc``).
        stride: keep every ``stride``-th frame (videos skip decoding the others); frames are renumbered.
        target_fps: videos only: the stride that gives about this frame rate.
        fps: frame rate assumed for image folders whose file names are not timestamps.
    """
    path = Path(path)
    if layout == "auto":
        layout = detect_layout(path)
    elif layout not in LAYOUTS:
        raise InputError(f"unknown layout {layout!r}; expected auto or one of {', '.join(LAYOUTS)}")
    elif not path.exists():
        raise InputError(f"input not found: {path}")
    openers = {
        "euroc": lambda: open_euroc(path),
        "tum": lambda: open_tum(path),
        "kitti": lambda: open_kitti(path),
        "7scenes": lambda: open_7scenes(path),
        "vkitti2": lambda: open_vkitti2(path),
        "video": lambda: VideoSource(path, stride=stride, target_fps=target_fps),
        "images": lambda: open_image_folder(path, fps=fps),
    }
    source = openers[layout]()
    if len(source) == 0:
        raise InputError(f"no frames in {path}")
    if ground_truth is not None:
        try:
            source.set_ground_truth(read_trajectory(ground_truth, gt_format))
        except TrajectoryError as exc:
            raise InputError(f"bad ground truth: {exc}") from None
    return source if layout == "video" else FrameSubset.every(source, stride)
