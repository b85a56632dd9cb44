"""Frame sources: every layout on small files written here, and the real EuRoC excerpt."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import random_trajectory
from vggt_slam_pp.errors import InputError
from vggt_slam_pp.geometry import se3_inverse
from vggt_slam_pp.io import detect_layout, open_source
from vggt_slam_pp.io.frames import FrameSubset
from vggt_slam_pp.io.trajectory import write_trajectory

H, W = 24, 32


def _img(seed: int, gray: bool = False) -> np.ndarray:
    r = np.random.default_rng(seed)
    return r.integers(0, 255, (H, W) if gray else (H, W, 3), dtype=np.uint8)


def _write(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)


def test_image_folder_natural_order_grayscale_and_times(tmp_path):
    for i in (10, 2, 1):
        _write(tmp_path / f"img{i}.png", _img(i, gray=(i == 2)))
    (tmp_path / "notes.txt").write_text("ignored")
    src = open_source(tmp_path)
    assert src.layout == "images" and len(src) == 3
    assert [p.name for p in src.image_paths] == ["img1.png", "img2.png", "img10.png"]
    frames = list(src)
    assert frames[1].image.shape == (H, W, 3)
    assert np.array_equal(frames[1].image[..., 0], frames[1].image[..., 2])  # gray replicated
    bgr = _img(1)
    assert np.array_equal(frames[0].image, bgr[..., ::-1])  # RGB order
    np.testing.assert_allclose(src.timestamps, [0, 1, 2])
    np.testing.assert_allclose(open_source(tmp_path, fps=10.0).timestamps, [0, 0.1, 0.2])


def test_image_folder_numeric_names_are_timestamps(tmp_path):
    for ns in (1403638538577829376, 1403638538627829504):
        _write(tmp_path / f"{ns}.png", _img(0))
    np.testing.assert_allclose(open_source(tmp_path).timestamps, [1403638538.5778294, 1403638538.6278295])


def test_bad_inputs_give_clear_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        open_source(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty"):
        open_source(tmp_path / "empty")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "a.txt").write_text("x")
    with pytest.raises(InputError, match="no images and no known dataset layout"):
        open_source(tmp_path / "other")
    bad = tmp_path / "bad"
    _write(bad / "0.png", _img(0))
    (bad / "1.png").write_bytes(b"not a png at all")
    src = open_source(bad)
    assert src[0].image.shape == (H, W, 3)
    with pytest.raises(InputError, match="cannot read image"):
        src[1]
    with pytest.raises(InputError, match="unknown layout"):
        open_source(bad, layout="nope")
    (tmp_path / "clip.txt").write_text("x")
    with pytest.raises(InputError, match="not a video"):
        open_source(tmp_path / "clip.txt")


def _make_tum(root: Path, n: int = 6) -> np.ndarray:
    ts = 1305031102.175304 + 0.033 * np.arange(n)
    rgb, dep = ["# rgb"], ["# depth"]
    for i, t in enumerate(ts):
        _write(root / "rgb" / f"{t:.6f}.png", _img(i))
        d = np.full((H, W), 5000 * (1 + i), np.uint16)
        _write(root / "depth" / f"{t + 0.004:.6f}.png", d)
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(dep) + "\n")
    return ts


def test_tum_layout(tmp_path, rng):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    ts = _make_tum(root)
    gt = random_trajectory(rng, 40, t0=ts[0] - 0.3, dt=0.02)
    write_trajectory(root / "groundtruth.txt", gt, "tum")
    assert detect_layout(root) == "tum"
    src = open_source(root)
    f = src[2]
    assert f.depth is not None and f.depth.dtype == np.float32
    np.testing.assert_allclose(f.depth, 3.0)
    assert src.camera.fx == 517.3 and src.camera.distorted  # published freiburg1 calibration
    idx, _traj = src.frame_ground_truth()
    assert len(idx) == len(src)
    info = src.info()
    assert info["layout"] == "tum" and info["frames"] == 6 and info["has_depth"] and info["ground_truth"]
    assert info["width"] == W and info["height"] == H


def test_kitti_layout_with_camera_offset(tmp_path, rng):
    root = tmp_path / "sequences" / "05"
    n = 4
    for i in range(n):
        _write(root / "image_2" / f"{i:06d}.png", _img(i))
    (root / "times.txt").write_text("\n".join(f"{0.1 * i:.6e}" for i in range(n)))
    fx, b = 700.0, -0.54 * 700.0  # P2 = K [I | (b/fx, 0, 0)]
    p0 = f"{fx} 0 16 0 0 {fx} 12 0 0 0 1 0"
    p2 = f"{fx} 0 16 {b} 0 {fx} 12 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\nP2: {p2}\nP3: {p2}\n")
    gt = random_trajectory(rng, n)
    (tmp_path / "poses").mkdir()
    write_trajectory(tmp_path / "poses" / "05.txt", gt, "kitti")
    src = open_source(root)
    assert src.layout == "kitti" and src.camera.fx == fx
    g = src.ground_truth()
    # the colour camera sits 0.54 m to the right of cam0 (x axis of cam0)
    np.testing.assert_allclose(g.positions, gt.poses[:, :3, 3] + 0.54 * gt.poses[:, :3, 0], atol=1e-6)
    np.testing.assert_allclose(g.timestamps, 0.1 * np.arange(n))


def _make_euroc(root: Path, n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    cam = root / "mav0" / "cam0"
    stamps = 1403638538577829376 + 50_000_000 * np.arange(n, dtype=np.int64)
    lines = ["#timestamp [ns],filename"]
    for i, s in enumerate(stamps):
        _write(cam / "data" / f"{s}.png", _img(i, gray=True))
        lines.append(f"{s},{s}.png")
    (cam / "data.csv").write_text("\r\n".join(lines) + "\r\n")
    T_BS = np.eye(4)
    T_BS[:3, 3] = [0.1, -0.2, 0.3]
    T_BS[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [" + ", ".join(map(str, T_BS.ravel())) + "]\n"
        f"resolution: [{W}, {H}]\nintrinsics: [30.0, 31.0, 15.5, 11.5]\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [-0.1, 0.01, 0.0, 0.0]\n")
    return stamps, T_BS


def test_euroc_layout_applies_body_to_camera(tmp_path, rng):
    stamps, T_BS = _make_euroc(tmp_path)
    body = random_trajectory(rng, 100, t0=stamps[0] * 1e-9 - 0.5, dt=0.005)
    gt_dir = tmp_path / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    write_trajectory(gt_dir / "data.csv", body, "euroc")
    src = open_source(tmp_path)
    assert src.layout == "euroc" and len(src) == 5
    assert src[0].image.shape == (H, W, 3)
    assert src.camera.dist == (-0.1, 0.01, 0.0, 0.0)
    np.testing.assert_allclose(src.ground_truth().poses, body.poses @ T_BS, atol=1e-7)
    assert open_source(tmp_path / "mav0").layout == "euroc"


def test_euroc_real_excerpt(shared_data):
    src = open_source(shared_data / "euroc_mh05_sample")
    info = src.info()
    assert info["layout"] == "euroc" and info["frames"] == 585
    assert (info["width"], info["height"]) == (752, 480)
    assert info["frames_with_ground_truth"] == 585  # every frame has ground truth within 10 ms
    assert abs(info["duration_s"] - 29.2) < 1e-3
    idx, gt = src.frame_ground_truth(max_diff=0.0026)
    assert len(idx) == 585
    # camera = body * T_BS: the lever arm between body and camera is about 7 cm
    from vggt_slam_pp.io.trajectory import read_euroc_csv

    raw = read_euroc_csv(shared_data / "euroc_mh05_sample" / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    j = np.argmin(np.abs(raw.timestamps - gt.timestamps[0]))
    lever = np.linalg.norm(gt.positions[0] - raw.positions[j])
    assert 0.06 < lever < 0.08
    f = src[100]
    assert f.image.shape == (480, 752, 3) and f.intrinsics.distorted


def test_7scenes_layout(tmp_path, rng):
    gt = random_trajectory(rng, 3)
    for i in range(3):
        _write(tmp_path / f"frame-{i:06d}.color.png", _img(i))
        d = np.full((H, W), 1500, np.uint16)
        d[0, 0] = 65535
        _write(tmp_path / f"frame-{i:06d}.depth.png", d)
        np.savetxt(tmp_path / f"frame-{i:06d}.pose.txt", gt.poses[i])
    src = open_source(tmp_path)
    assert src.layout == "7scenes"
    f = src[1]
    assert f.depth[0, 0] == 0.0 and f.depth[1, 1] == pytest.approx(1.5)
    np.testing.assert_allclose(src.ground_truth().poses, gt.poses)
    assert src.camera.fx == pytest.approx(585.0 * W / 640)


def test_vkitti2_layout(tmp_path, rng):
    gt = random_trajectory(rng, 3)
    base = tmp_path / "Scene01" / "clone"
    intr, extr = ["frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"], ["frame cameraID r1,1 ..."]
    for i in range(3):
        _write(base / "frames" / "rgb" / "Camera_0" / f"rgb_{i:05d}.jpg", _img(i))
        _write(base / "frames" / "depth" / "Camera_0" / f"depth_{i:05d}.png", np.full((H, W), 250, np.uint16))
        for cam in (0, 1):
            intr.append(f"{i} {cam} 725.0087 725.0087 620.5 187")
            extr.append(f"{i} {cam} " + " ".join(f"{v:.12f}" for v in se3_inverse(gt.poses[i]).ravel()))
    (base / "intrinsic.txt").write_text("\n".join(intr) + "\n")
    (base / "extrinsic.txt").write_text("\n".join(extr) + "\n")
    src = open_source(base)
    assert src.layout == "vkitti2" and len(src) == 3
    np.testing.assert_allclose(src[0].depth, 2.5)
    np.testing.assert_allclose(src.ground_truth().poses, gt.poses, atol=1e-9)
    assert src.camera.fx == pytest.approx(725.0087)


def test_video_source_stride_and_fps(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (64, 48))
    assert writer.isOpened()
    for i in range(20):
        img = np.zeros((48, 64, 3), np.uint8)
        img[:, :, 1] = 12 * i  # frame number encoded in green
        writer.write(img)
    writer.release()
    src = open_source(path)
    assert src.layout == "video" and len(src) == 20
    g = [int(round(f.image[..., 1].mean() / 12)) for f in src]
    assert g == list(range(20))
    s5 = open_source(path, stride=5)
    assert len(s5) == 4
    np.testing.assert_allclose(s5.timestamps, [0, 0.25, 0.5, 0.75])
    assert int(round(s5[2].image[..., 1].mean() / 12)) == 10  # random access
    assert len(open_source(path, target_fps=5.0)) == 5
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 100)
    with pytest.raises(InputError):
        open_source(tmp_path / "broken.mp4")


def test_images_paired_with_external_ground_truth(tmp_path, rng):
    for i in range(5):
        _write(tmp_path / "imgs" / f"{i}.png", _img(i))
    gt = random_trajectory(rng, 5)
    write_trajectory(tmp_path / "gt.kitti", gt, "kitti")
    src = open_source(tmp_path / "imgs", ground_truth=tmp_path / "gt.kitti", fps=10.0)
    np.testing.assert_allclose(src.ground_truth().timestamps, np.arange(5) / 10.0)
    assert len(src.frame_ground_truth()[0]) == 5
    write_trajectory(tmp_path / "short.kitti", gt.subset(np.arange(3)), "kitti")
    with pytest.raises(InputError, match="3 poses but the source has 5 frames"):
        open_source(tmp_path / "imgs", ground_truth=tmp_path / "short.kitti")


def test_synthetic_camera_json_is_read(tmp_path):
    _make_tum(tmp_path)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 20, "fy": 20, "cx": 15.5, "cy": 11.5, "width": W,
                                                      "height": H, "depth_scale": 1000.0}))
    src = open_source(tmp_path)
    assert src.camera.fx == 20 and not src.camera.distorted
    np.testing.assert_allclose(src[0].depth, 5.0)  # raw 5000 / 1000


def _make_kitti_root(root: Path, rng, seqs=("00", "05", "07"), gt_for=("00", "05"), n: int = 2) -> dict:
    """A tiny KITTI odometry root: ``root/sequences/NN/image_0/*.png`` + ``times.txt``, and
    ``root/poses/NN.txt`` (12-column camera-to-world of cam0) for the sequences in ``gt_for``."""
    gts = {}
    for k, name in enumerate(seqs):
        seq = root / "sequences" / name
        for i in range(n):
            _write(seq / "image_0" / f"{i:06d}.png", _img(10 * k + i, gray=True))
        (seq / "times.txt").write_text("".join(f"{0.1 * i + 0.05:.6e}\n" for i in range(n)))
        if name in gt_for:
            (root / "poses").mkdir(parents=True, exist_ok=True)
            gts[name] = random_trajectory(rng, n)
            write_trajectory(root / "poses" / f"{name}.txt", gts[name], "kitti")
    return gts


def test_kitti_root_is_refused_with_its_sequences(tmp_path, rng):
    root = tmp_path / "dataset"
    _make_kitti_root(root, rng)
    for path in (root, root / "sequences"):
        for call in (lambda p=path: open_source(p), lambda p=path: detect_layout(p),
                     lambda p=path: open_source(p, layout="kitti")):
            with pytest.raises(InputError) as info:
                call()
            msg = str(info.value)
            assert "\n" not in msg
            assert "KITTI odometry root with 3 sequences (00, 05, 07; ground truth for 00, 05)" in msg
            assert str(root / "sequences" / "00") in msg and msg.startswith(str(path))
            assert "no images" not in msg


def test_kitti_root_message_shortens_runs_and_notes_missing_images(tmp_path, rng):
    root = tmp_path / "dataset"
    _make_kitti_root(root, rng, seqs=("00", "01", "02", "03", "09", "10"), gt_for=(), n=1)
    with pytest.raises(InputError, match=r"6 sequences \(00-03, 09, 10; no ground truth\)"):
        open_source(root)
    bare = tmp_path / "calib_only" / "sequences"
    for name in ("00", "01"):
        (bare / name).mkdir(parents=True)
        (bare / name / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"2 sequence\(s\) \(00, 01\) but none has image_2/ or image_0/"):
        open_source(bare.parent)


def test_kitti_sequence_of_a_root_opens_with_its_ground_truth(tmp_path, rng):
    root = tmp_path / "dataset"
    gts = _make_kitti_root(root, rng)
    src = open_source(root / "sequences" / "05")
    assert src.layout == "kitti" and len(src) == 2
    assert src[1].image.shape == (H, W, 3)
    np.testing.assert_allclose(src.timestamps, [0.05, 0.15])
    g = src.ground_truth()
    np.testing.assert_allclose(g.poses, gts["05"].poses, atol=1e-6)  # image_0 is cam0: no offset
    np.testing.assert_allclose(g.timestamps, [0.05, 0.15])
    assert open_source(root / "sequences" / "07").ground_truth() is None
    (root / "sequences" / "07" / "times.txt").write_text("0.0\nabc\n")
    with pytest.raises(InputError, match="malformed time"):
        open_source(root / "sequences" / "07")


def test_stride_applies_to_every_layout_and_keeps_ground_truth(tmp_path, rng):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    ts = _make_tum(root)
    gt = random_trajectory(rng, 40, t0=ts[0] - 0.3, dt=0.02)
    write_trajectory(root / "groundtruth.txt", gt, "tum")
    full = open_source(root)
    src = open_source(root, stride=2)
    assert len(src) == 3 and src.layout == "tum" and src.camera.fx == full.camera.fx
    np.testing.assert_array_equal(src.timestamps, full.timestamps[::2])
    f = src[1]
    assert f.index == 1 and f.timestamp == full[2].timestamp and np.array_equal(f.image, full[2].image)
    idx, traj = src.frame_ground_truth()
    np.testing.assert_array_equal(idx, [0, 1, 2])
    np.testing.assert_allclose(traj.poses, full.frame_ground_truth()[1].poses[::2])
    with pytest.raises(InputError, match="stride"):
        open_source(root, stride=0)
    first = FrameSubset.every(full, 1, limit=4)  # --max-frames
    assert len(first) == 4 and [f.index for f in first] == [0, 1, 2, 3]
