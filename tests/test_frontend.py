"""Front-end: keyframes, submap assembly, odometry, replay, backbones and the `run` pipeline."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vggt_slam_pp.errors import FrontendError, InputError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.backbones.replay import (
    PredictionStore,
    ReplayBackbone,
    load_prediction,
    save_prediction,
)
from vggt_slam_pp.frontend.backbones.simulated import SimulatedBackbone, SimulatedNoise
from vggt_slam_pp.frontend.frontend import Frontend, FrontendConfig, SubmapAssembler
from vggt_slam_pp.frontend.keyframes import KeyframeConfig, KeyframeSelector
from vggt_slam_pp.frontend.odometry import OdometryConfig, chain, estimate_edge
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.geometry import sim3_inverse
from vggt_slam_pp.geometry.lie import transform_points
from vggt_slam_pp.io.frames import Frame
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run

FAST = FrontendConfig(keyframes=KeyframeConfig(tau_disparity=12.0), submap_size=4)


@pytest.fixture(scope="module")
def loop_sequence(tmp_path_factory):
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    out = tmp_path_factory.mktemp("loop")
    write_sequence(make_scene("loop", frames=90, width=160, height=120, seed=3), out)
    return open_source(out)


def _textured(rng, h=120, w=160):
    import cv2

    img = (rng.random((h // 12, w // 12, 3)) * 255).astype(np.uint8)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)


# --------------------------------------------------------------------------------- keyframes
def test_static_frames_give_no_new_keyframe_and_motion_does(rng):
    sel = KeyframeSelector(KeyframeConfig(tau_disparity=20.0))
    img = _textured(rng, 240, 320)
    assert sel.update(img).reason == "first"
    for _ in range(5):
        d = sel.update(img.copy())
        assert not d.is_keyframe and d.disparity < 0.5 and d.tracked >= 10
    assert not sel.update(np.roll(img, 8, axis=1)).is_keyframe  # 8 px < tau
    d = sel.update(np.roll(img, 24, axis=1))
    assert d.is_keyframe and d.reason == "disparity" and d.disparity > 20
    assert not sel.update(np.roll(img, 28, axis=1)).is_keyframe  # the new reference is the shifted one


def test_textureless_frame_forces_a_keyframe(rng):
    sel = KeyframeSelector()
    sel.update(_textured(rng))
    d = sel.update(np.full((120, 160, 3), 128, np.uint8))
    assert d.is_keyframe and d.reason == "tracking-lost" and d.tracked < 10
    d = sel.update(np.full((120, 160, 3), 128, np.uint8))  # still nothing to track: still forced, no crash
    assert d.is_keyframe and d.reason == "tracking-lost"


# --------------------------------------------------------------------------------- submaps
def _frame(i):
    return Frame(i, float(i), np.zeros((4, 4, 3), np.uint8))


def test_submap_assembly_overlap_and_counts():
    asm = SubmapAssembler(3)
    closed = [c for c in (asm.add(_frame(i)) for i in range(8)) if c]
    closed.append(asm.flush())
    ids = [[f.index for f in c] for c in closed]
    assert ids == [[0, 1, 2], [2, 3, 4, 5], [5, 6, 7]]
    assert asm.flush() is None
    with pytest.raises(FrontendError):
        SubmapAssembler(0)


class _Sparse(Backbone):
    name, dense = "sparse", False

    def predict(self, frames):
        raise AssertionError("not called")


def test_the_overlap_grows_with_the_submap_for_sparse_backbones_and_stays_one_for_dense_ones():
    # a long sparse submap shares its last half (its end drifts most), a short one of sparse photos two frames
    assert [Frontend(_Sparse(), FrontendConfig(submap_size=w)).overlap for w in (6, 8, 16, 32, 64)] == [2, 2, 4, 16, 16]
    assert Frontend(_Sparse(), FrontendConfig(submap_size=32, overlap=5)).overlap == 5  # --overlap wins
    dense = SimulatedBackbone({0: np.eye(4)}, SimulatedNoise.zero(0))
    assert Frontend(dense, FrontendConfig(submap_size=32)).overlap == 1
    bridge = Frontend(_Sparse(), FrontendConfig(submap_size=32)).bridge_frames
    assert 4 <= bridge <= 16


# --------------------------------------------------------------------------------- odometry
def _prediction(rng, T_cam_submap, n=400, outliers=0.0, scale=1.0, frame_indices=(0, 1)):
    """Two-frame prediction whose frames see the same world points (keys 0..n-1)."""
    world = rng.uniform([-5, -3, 4], [5, 3, 15], (n, 3))
    pts, conf, pix, keys = [], [], [], []
    for _ in T_cam_submap:
        p = world * scale  # the submap frame is the world frame here
        bad = rng.random(n) < outliers
        p[bad] += rng.normal(0, 3.0, (bad.sum(), 3))
        pts.append(p.astype(np.float64))
        conf.append(np.ones(n, np.float32))
        pix.append(np.zeros((n, 2), np.float32))
        keys.append(np.arange(n, dtype=np.int64))
    T = np.array(T_cam_submap, dtype=np.float64)
    T[:, :3, 3] *= scale
    return SubmapPrediction(np.array(frame_indices), T, np.repeat(np.eye(3)[None], len(T), 0), (4, 4),
                            np.repeat(np.eye(3)[None], len(T), 0), pts, conf, pix, keys,
                            np.ones(len(T), bool)), world


def test_sim3_odometry_recovers_known_transform_with_outliers(rng):

    from vggt_slam_pp.geometry import se3_exp

    T_c1_c0 = se3_exp(np.r_[0.05, -0.1, 0.02, 0.5, 0.1, 1.0])
    prev, world = _prediction(rng, [np.eye(4), T_c1_c0], outliers=0.3)
    # the current submap sees the same points from its own frame (= camera 1), at another scale
    rng2 = np.random.default_rng(1)
    pts1 = transform_points(T_c1_c0, world) * 2.5
    bad = rng2.random(len(world)) < 0.3
    pts1[bad] += rng2.normal(0, 3, (bad.sum(), 3))
    curr = dataclasses.replace(prev, frame_indices=np.array([1, 2]), points=[pts1, pts1],
                               T_cam_submap=np.repeat(np.eye(4)[None], 2, 0))
    edge = estimate_edge(0, prev, 1, curr, OdometryConfig())
    expected = sim3_inverse(T_c1_c0) @ np.diag([1 / 2.5, 1 / 2.5, 1 / 2.5, 1.0])
    assert edge.method == "points" and not edge.degraded
    assert np.allclose(edge.T_prev_curr, expected, atol=1e-6)
    assert 0.35 < edge.inlier_ratio < 0.6 and edge.residual < 1e-6  # ~0.7 x 0.7 clean pairs
    # pose_scale (sparse backbones): the overlap pose plus a point-based scale gives the same answer
    curr_sparse = dataclasses.replace(curr, dense=False, points=[transform_points(T_c1_c0, world) * 2.5] * 2)
    prev_clean, _ = _prediction(np.random.default_rng(5), [np.eye(4), T_c1_c0])
    prev_clean = dataclasses.replace(prev_clean, points=[transform_points(np.eye(4), world)] * 2)
    e2 = estimate_edge(0, prev_clean, 1, curr_sparse)
    assert e2.method == "pose_scale" and np.allclose(e2.T_prev_curr, expected, atol=1e-9)
    assert np.allclose(chain([edge, edge])[2], expected @ expected, atol=1e-6)
    # a joint link from the backbone (colmap --link joint) is used where it agrees with the shared keyframes
    # (here 1 % in scale), and refused where it does not (10 %: the shared keyframes' link is kept)
    from vggt_slam_pp.geometry import make_sim3

    for factor, method in ((1.01, "joint"), (1.10, "pose_scale")):
        T_joint = expected @ make_sim3(factor, np.eye(3), np.zeros(3))
        link = {"prev_frames": [0, 1], "T_prev_curr": T_joint.tolist(), "residual": 0.01, "relative_residual": 0.003}
        e3 = estimate_edge(0, prev_clean, 1, dataclasses.replace(curr_sparse, info={"joint_link": link}))
        assert e3.method == method
        assert np.allclose(e3.T_prev_curr, T_joint if method == "joint" else expected, atol=1e-9)
    assert e3.relative_residual != e3.relative_residual  # NaN: not a joint link


def test_odometry_degrades_without_correspondences(rng):
    prev, _ = _prediction(rng, [np.eye(4), np.eye(4)])
    curr = dataclasses.replace(prev, frame_indices=np.array([1, 2]),
                               keys=[k + 10_000 for k in prev.keys])  # nothing in common
    edge = estimate_edge(0, prev, 1, curr)
    assert edge.degraded and edge.method == "extrapolated" and edge.num_correspondences == 0
    assert "0 correspondences" in edge.cause
    with pytest.raises(Exception, match="overlap frame"):
        estimate_edge(0, prev, 1, dataclasses.replace(prev, frame_indices=np.array([5, 6])))


# --------------------------------------------------------------------------------- replay
def test_replay_round_trip_is_bit_identical(tmp_path, loop_sequence):
    idx, gt = loop_sequence.frame_ground_truth()
    bb = SimulatedBackbone(dict(zip(idx.tolist(), gt.poses, strict=True)), SimulatedNoise(seed=4))
    frames = [loop_sequence[i] for i in (0, 5, 10)]
    pred = bb.predict(frames)
    save_prediction(tmp_path / "p.safetensors", pred)
    back = load_prediction(tmp_path / "p.safetensors")
    for name in ("frame_indices", "T_cam_submap", "intrinsics", "to_original", "valid"):
        a, b = getattr(pred, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    for name in ("points", "conf", "pixels", "keys"):
        for a, b in zip(getattr(pred, name), getattr(back, name), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert back.network_hw == pred.network_hw and back.dense == pred.dense and back.info == pred.info
    store = PredictionStore(tmp_path / "store")
    store.save(0, pred)
    replayed = ReplayBackbone(tmp_path / "store").predict(frames)
    assert np.array_equal(replayed.points[1], pred.points[1])
    with pytest.raises(FrontendError, match="no saved prediction"):
        ReplayBackbone(tmp_path / "store").predict(frames[:2])


# --------------------------------------------------------------------------------- end to end
def _run(source, out, noise="zero", frontend=FAST, backbone=None, **kw):
    config = RunConfig(backbone=BackboneConfig(name="simulated", noise=noise), frontend=frontend, **kw)
    return run(source, config, out, backbone=backbone)


def test_simulated_zero_noise_reproduces_ground_truth(tmp_path, loop_sequence):
    report = _run(loop_sequence, tmp_path / "zero")
    assert report["submaps"] >= 3 and len(report["edges"]) == report["submaps"] - 1
    assert report["ate_rmse_odometry"] < 1e-6 * report["gt_path_length"]
    assert all(e["inlier_ratio"] > 0.99 for e in report["edges"])
    for name in ("keyframes_odometry.txt", "keyframes_odometry.kitti", "frames_odometry.txt",
                 "frames_odometry.kitti", "frames.csv", "config.json", "report.json"):
        assert (tmp_path / "zero" / name).is_file(), name
    rows = (tmp_path / "zero" / "frames.csv").read_text().splitlines()
    assert len(rows) == 1 + len(loop_sequence)
    flags = np.array([[int(v) for v in r.split(",")[2:4]] for r in rows[1:]])
    assert flags[:, 0].sum() == report["keyframes"] and np.all(flags[:, 0] != flags[:, 1])  # kf <-> exact
    kitti = np.loadtxt(tmp_path / "zero" / "frames_odometry.kitti")
    assert kitti.shape == (len(loop_sequence), 12)


def test_simulated_default_noise_drifts_with_distance(tmp_path, loop_sequence):
    from vggt_slam_pp.io.trajectory import read_tum

    report = _run(loop_sequence, tmp_path / "noisy", noise="default")
    est = read_tum(tmp_path / "noisy" / "keyframes_odometry.txt")
    gt = loop_sequence.ground_truth().interpolate_at(est.timestamps)
    assert report["ate_rmse_odometry"] > 1e-3
    # anchored on the first keyframes, the error grows with the distance travelled (on this loop it
    # shrinks again near the end, where the rotated trajectory passes close to its start)
    R0 = gt.poses[0, :3, :3] @ est.poses[0, :3, :3].T  # anchor: first pose, scale of the first steps
    s = gt.subset(np.arange(5)).path_length() / est.subset(np.arange(5)).path_length()
    aligned = (est.positions - est.positions[0]) @ R0.T * s + gt.positions[0]
    err = np.linalg.norm(aligned - gt.positions, axis=1)
    q = len(err) // 4
    assert err[q:2 * q].mean() > 5 * err[:5].mean()
    travelled = np.r_[0, np.cumsum(np.linalg.norm(np.diff(gt.positions, axis=0), axis=1))]
    assert np.corrcoef(travelled[:2 * q], err[:2 * q])[0, 1] > 0.6  # grows with distance (first half)


def test_realistic_noise_drifts_in_scale_as_a_random_walk(loop_sequence):
    """Inside a submap the warp grows from nothing at the first frame to the drawn drift at the last; the
    overlap frame carries it into the next submap, so chained scale is a random walk, unlike the default
    profile's per-submap scale error (which the odometry edge absorbs)."""
    idx, gt = loop_sequence.frame_ground_truth()
    poses = dict(zip(idx.tolist(), gt.poses, strict=True))
    frames = [loop_sequence[i] for i in (0, 6, 12, 18)]
    noise = dataclasses.replace(SimulatedNoise.zero(3), scale_drift=0.05, yaw_drift_deg=2.0)
    pred = SimulatedBackbone(poses, noise).predict(frames)
    true = [np.linalg.inv(poses[f.index]) @ poses[frames[0].index] for f in frames]
    # camera centres in the submap frame: the first exact, the last scaled and turned by the full drift
    c_pred = [np.linalg.inv(T)[:3, 3] for T in pred.T_cam_submap]
    c_true = [np.linalg.inv(T)[:3, 3] for T in true]
    assert np.allclose(c_pred[0], c_true[0]) and np.allclose(pred.T_cam_submap[0], np.eye(4))
    ratio = np.linalg.norm(c_pred[-1]) / np.linalg.norm(c_true[-1])
    assert abs(np.log(ratio)) > 1e-4
    mid = np.linalg.norm(c_pred[1]) / np.linalg.norm(c_true[1])
    assert abs(np.log(mid)) == pytest.approx(abs(np.log(ratio)) / 3, rel=0.05)  # grows linearly along the submap
    assert np.allclose(SimulatedBackbone(poses, noise).predict(frames).points[2], pred.points[2])  # seeded
    # the link error: once the first frame belongs to a committed submap, its points (only) are off
    link = SimulatedBackbone(poses, dataclasses.replace(SimulatedNoise.zero(3), overlap_scale_error=0.1))
    alone = link.predict(frames)
    link.committed([0, 1, 2])
    linked = link.predict(frames)
    ratio = np.linalg.norm(linked.points[0], axis=1) / np.linalg.norm(alone.points[0], axis=1)
    assert np.allclose(ratio, ratio[0]) and abs(np.log(ratio[0])) > 1e-3
    assert np.allclose(linked.points[1], alone.points[1]) and np.allclose(linked.T_cam_submap, alone.T_cam_submap)


def test_realistic_profile_fails_some_submaps_into_degraded_edges(loop_sequence):
    idx, gt = loop_sequence.frame_ground_truth()
    poses = dict(zip(idx.tolist(), gt.poses, strict=True))
    noise = dataclasses.replace(SimulatedNoise.realistic(0), failure_rate=1.0)
    fe = Frontend(SimulatedBackbone(poses, noise), FAST)
    for i in range(len(loop_sequence)):
        fe.process(loop_sequence[i])
    res = fe.finish()
    assert len(res.edges) >= 2 and all(e.degraded and e.method == "extrapolated" for e in res.edges)
    assert SimulatedNoise.profile("realistic").scale_drift > 0 and SimulatedNoise.profile("zero").depth_noise == 0
    with pytest.raises(FrontendError, match="unknown noise profile"):
        SimulatedNoise.profile("extreme")


class _Broken(Backbone):
    """Returns NaN poses for frame 1, and no points at all for the second submap (nor for its bridge)."""

    name = "broken"

    def __init__(self, inner):
        self.inner, self.calls = inner, 0

    def predict(self, frames):
        self.calls += 1
        pred = self.inner.predict(frames)
        T = pred.T_cam_submap.copy()
        if len(T) > 1:
            T[1] = np.nan
        if self.calls in (2, 3):
            pred = dataclasses.replace(pred, points=[np.full_like(p, np.inf) for p in pred.points])
        return dataclasses.replace(pred, T_cam_submap=T)


def test_nan_and_empty_predictions_degrade_and_still_write_outputs(tmp_path, loop_sequence, caplog):
    idx, gt = loop_sequence.frame_ground_truth()
    inner = SimulatedBackbone(dict(zip(idx.tolist(), gt.poses, strict=True)), SimulatedNoise.zero())
    report = _run(loop_sequence, tmp_path / "broken", backbone=_Broken(inner))
    assert report["invalid_frames"] and report["points_per_submap"][1] == 0
    assert report["edges"][0]["degraded"] and report["edges"][1]["degraded"]
    assert all(e["method"] == "extrapolated" and "bridge" in e["cause"] for e in report["edges"][:2])
    assert report["degraded_edges"] == 2 and not any(e["degraded"] for e in report["edges"][2:])
    assert "non-finite poses" in caplog.text and "degraded" in caplog.text
    assert (tmp_path / "broken" / "keyframes_odometry.txt").is_file()


class _BlasProbe(Backbone):
    """Records the numpy BLAS thread count each prediction runs under."""

    name = "probe"

    def __init__(self, inner):
        self.inner, self.threads = inner, []

    def predict(self, frames):
        from threadpoolctl import threadpool_info

        self.threads.append({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
        return self.inner.predict(frames)


def test_frontend_runs_with_the_configured_blas_threads(tmp_path, loop_sequence):
    from threadpoolctl import threadpool_info

    idx, gt = loop_sequence.frame_ground_truth()
    before = {i["prefix"]: i["num_threads"] for i in threadpool_info()}
    blas_default = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
    probe = _BlasProbe(SimulatedBackbone(dict(zip(idx.tolist(), gt.poses, strict=True)), SimulatedNoise.zero()))
    _run(loop_sequence, tmp_path / "one", backbone=probe)  # default: 1
    assert probe.threads and all(t == {1} for t in probe.threads)
    assert {i["prefix"]: i["num_threads"] for i in threadpool_info()} == before  # restored after the run
    probe.threads.clear()
    _run(loop_sequence, tmp_path / "default", backbone=probe, blas_threads=0)  # the library's own
    assert probe.threads and all(t == blas_default for t in probe.threads)
    with pytest.raises(InputError, match="blas_threads"):
        _run(loop_sequence, tmp_path / "bad", blas_threads=-1)


def test_few_and_identical_frames(tmp_path, rng):
    from vggt_slam_pp.io.frames import FrameSource

    class Still(FrameSource):
        def __init__(self, n, image):
            from pathlib import Path

            super().__init__(Path("."))
            self.n, self.image = n, image

        def __len__(self):
            return self.n

        @property
        def timestamps(self):
            return np.arange(self.n, dtype=float)

        def _load(self, i):
            return Frame(i, float(i), self.image, np.full(self.image.shape[:2], 5.0, np.float32),
                         _camera())

        def _native_ground_truth(self):
            from vggt_slam_pp.io.trajectory import Trajectory

            return Trajectory(self.timestamps, np.repeat(np.eye(4)[None], self.n, 0))

    report = _run(Still(12, _textured(rng)), tmp_path / "still")
    assert report["keyframes"] == 1 and report["submaps"] == 1 and report["error"] is None
    assert (tmp_path / "still" / "frames_odometry.txt").read_text().count("\n") == 12


def _camera():
    from vggt_slam_pp.geometry import PinholeCamera

    return PinholeCamera(100.0, 100.0, 79.5, 59.5, 160, 120)


def test_replay_run_equals_recorded_run(tmp_path, loop_sequence):
    first = _run(loop_sequence, tmp_path / "a", noise="default")
    config = RunConfig(backbone=BackboneConfig(name="replay", replay_dir=str(tmp_path / "a")), frontend=FAST)
    second = run(loop_sequence, config, tmp_path / "b")
    assert second["ate_rmse_odometry"] == first["ate_rmse_odometry"]
    assert (tmp_path / "a" / "keyframes_odometry.txt").read_text() == \
        (tmp_path / "b" / "keyframes_odometry.txt").read_text()


def test_vggt_backbone_with_a_tiny_random_model(loop_sequence):
    import torch

    from test_models_weights import TINY_VGGT
    from vggt_slam_pp.frontend.backbones.vggt import VggtBackbone
    from vggt_slam_pp.models import build_vggt

    torch.manual_seed(0)
    model = build_vggt(TINY_VGGT)
    with torch.no_grad():  # random weights: give the FoV outputs a realistic ~1 rad (ReLU would give 0)
        model.camera_head.pose_branch.fc2.bias[7:9] = 1.0
    bb = VggtBackbone(model=model, device="cpu", stride=4, target_size=112)
    frames = [loop_sequence[i] for i in (0, 4, 8)]
    pred = bb.predict(frames)
    assert pred.network_hw == (84, 112) and pred.num_frames == 3 and pred.dense
    assert np.allclose(pred.T_cam_submap[0], np.eye(4), atol=1e-6)
    assert pred.num_points() > 0 and all(np.isfinite(p).all() for p in pred.points)
    # pixels map back into the original 160x120 image
    allpix = np.concatenate(pred.pixels)
    assert allpix[:, 0].min() >= -0.5 and allpix[:, 0].max() <= 159.5 and allpix[:, 1].max() <= 119.5


def test_colmap_failure_is_an_invalid_submap_not_a_crash():
    pytest.importorskip("pycolmap")
    from vggt_slam_pp.frontend.backbones.colmap import ColmapBackbone

    frames = [Frame(i, float(i), np.zeros((48, 64, 3), np.uint8)) for i in range(3)]
    pred = ColmapBackbone().predict(frames)  # black frames: no features, no reconstruction
    assert not pred.valid.any() and pred.num_points() == 0 and pred.num_frames == 3


def test_fewer_frames_than_one_submap(tmp_path, loop_sequence):
    few = FrontendConfig(keyframes=KeyframeConfig(tau_disparity=12.0), submap_size=200)
    report = _run(loop_sequence, tmp_path / "few", frontend=few)
    assert report["submaps"] == 1 and report["edges"] == [] and report["error"] is None
    assert 2 <= report["keyframes"] < 200 and report["ate_rmse_odometry"] < 1e-6 * report["gt_path_length"]


def test_a_keypoint_takes_a_point_seen_at_its_pixel():
    """Landmarks (frontend/landmarks.py) lift a keypoint onto the point observed nearest its pixel, within
    1.5 of the points' pixel spacing, and onto none where no point is near (sky, filtered points)."""
    from vggt_slam_pp.frontend.landmarks import _points_at

    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:240:4, 0:320:4]
    pixels = np.stack([u.ravel(), v.ravel()], -1) + rng.uniform(-0.4, 0.4, (u.size, 2))
    keep = ~((pixels[:, 0] > 200) & (pixels[:, 1] < 100))  # a region without points
    pixels = pixels[keep]
    at = rng.uniform([0, 0], [319, 239], (500, 2))
    j = _points_at(pixels, at, (240, 320), 1.5)
    found = j >= 0
    d = np.linalg.norm(pixels[np.maximum(j, 0)] - at, axis=1)
    nearest = np.min(np.linalg.norm(pixels[None] - at[:, None], axis=2), axis=1)
    assert np.all(d[found] <= 1.5 * 4 + 1e-9)
    assert np.all(found[nearest <= 2.0])  # a point within half the spacing is always found ...
    assert np.median(d[found] - nearest[found]) == 0.0  # ... and it is the nearest one, mostly
    inside_hole = (at[:, 0] > 212) & (at[:, 1] < 88)
    assert inside_hole.any() and not found[inside_hole].any()
