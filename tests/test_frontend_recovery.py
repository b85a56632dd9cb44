"""The front-end never chains submaps through a silent identity: a submap that fails, an overlap frame
left unregistered, or unregistered keyframes at a submap's end are recovered (split, bridge) or
flagged (extrapolated, ``degraded`` with its cause in ``report.json``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.backbones.simulated import SimulatedBackbone, SimulatedNoise
from vggt_slam_pp.frontend.frontend import FrontendConfig
from vggt_slam_pp.frontend.keyframes import KeyframeConfig
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run


@pytest.fixture(scope="module")
def loop_sequence(tmp_path_factory):
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    out = tmp_path_factory.mktemp("loop")
    write_sequence(make_scene("loop", frames=90, width=160, height=120, seed=3), out)
    return open_source(out)


class _Faulty(Backbone):
    """A zero-noise simulated backbone whose ``fault(call, frames, pred)`` may break a prediction.
    Broken frames get a wrong (identity) pose as well as ``valid=False``, so that using them shows."""

    def __init__(self, source, fault, dense=True):
        idx, gt = source.frame_ground_truth()
        self.inner = SimulatedBackbone(dict(zip(idx.tolist(), gt.poses, strict=True)), SimulatedNoise.zero())
        self.fault, self.dense, self.calls = fault, dense, 0
        self.name = "faulty"

    def predict(self, frames):
        self.calls += 1
        pred = self.inner.predict(frames)
        bad = np.asarray(self.fault(self.calls, [f.index for f in frames]), bool)
        if not bad.any():
            return dataclasses.replace(pred, dense=self.dense)
        T = pred.T_cam_submap.copy()
        T[bad] = np.eye(4)
        empty = np.zeros((0, 3), np.float32)
        return dataclasses.replace(
            pred, T_cam_submap=T, valid=pred.valid & ~bad, dense=self.dense,
            points=[empty if b else p for p, b in zip(pred.points, bad, strict=True)],
            conf=[np.zeros(0, np.float32) if b else c for c, b in zip(pred.conf, bad, strict=True)],
            pixels=[np.zeros((0, 2), np.float32) if b else x for x, b in zip(pred.pixels, bad, strict=True)],
            keys=[np.zeros(0, np.int64) if b else k for k, b in zip(pred.keys, bad, strict=True)])


def _run(source, out, backbone, overlap=0, submap_size=4):
    config = RunConfig(backbone=BackboneConfig(name="simulated", noise="zero"), backend=False,
                       frontend=FrontendConfig(keyframes=KeyframeConfig(tau_disparity=12.0),
                                               submap_size=submap_size, overlap=overlap))
    return run(source, config, out, backbone=backbone)


def _exact(report):
    return report["ate_rmse_odometry"] < 1e-6 * report["gt_path_length"]


def test_a_failed_submap_is_bridged_and_the_chain_stays_exact(tmp_path, loop_sequence):
    # the third backbone call (submap 2) reconstructs nothing; its bridge (call 4) works
    report = _run(loop_sequence, tmp_path / "r", _Faulty(loop_sequence, lambda call, idx: [call == 3] * len(idx)))
    assert report["degraded_edges"] == 0 and report["recovered_edges"] == 1
    edge = report["edges"][1]
    assert edge["method"] == "points" and edge["cause"].startswith("bridged") and edge["shared_frames"] > 1
    assert _exact(report) and report["invalid_frames"] == []


def test_a_submap_that_always_fails_is_flagged_not_identity(tmp_path, loop_sequence):
    # submap 2 and its bridge (calls 3 and 4) reconstruct nothing
    report = _run(loop_sequence, tmp_path / "f", _Faulty(loop_sequence, lambda call, idx: [call in (3, 4)] * len(idx)))
    edge = report["edges"][1]
    assert edge["degraded"] and edge["method"] == "extrapolated" and "bridge" in edge["cause"]
    assert "not registered" in edge["cause"]
    assert report["degraded_edges"] >= 1 and all(e["cause"] for e in report["edges"] if e["degraded"])


def test_a_bridge_that_fails_with_the_last_keyframes_is_tried_with_all_of_them(tmp_path, loop_sequence):
    # submap 2 (call 3) and its bridge with the previous submap's last 4 keyframes (call 4) reconstruct nothing;
    # with all 8 (call 5: a fast start or turn whose last keyframes are the poorly tracked ones) it links
    backbone = _Faulty(loop_sequence, lambda call, idx: [call in (3, 4)] * len(idx))
    report = _run(loop_sequence, tmp_path / "all", backbone, submap_size=8)
    assert report["degraded_edges"] == 0 and report["recovered_edges"] == 1
    edge = report["edges"][1]
    assert edge["cause"].startswith("bridged: reconstructed again with 8 more keyframes"), edge["cause"]
    assert _exact(report) and report["invalid_frames"] == []


@pytest.mark.parametrize(("overlap", "recovered"), [(1, 1), (2, 0)])
def test_an_unregistered_overlap_frame_is_bridged_or_covered_by_the_other_shared_frame(
        tmp_path, loop_sequence, overlap, recovered):
    state = {}

    def fault(call, idx):  # the overlap frame of the second submap's first reconstruction is not registered
        if call == 2:
            state["frame"] = idx[0]
            return [i == idx[0] for i in idx]
        return [False] * len(idx)

    report = _run(loop_sequence, tmp_path / f"o{overlap}", _Faulty(loop_sequence, fault), overlap=overlap)
    assert report["degraded_edges"] == 0 and report["recovered_edges"] == recovered
    assert report["edges"][0]["shared_frames"] >= 1 and _exact(report)
    if recovered:
        assert report["edges"][0]["cause"].startswith("bridged")


def test_unregistered_keyframes_at_a_submaps_end_start_the_next_submap(tmp_path, loop_sequence, caplog):
    def fault(call, idx):  # the first submap's last two keyframes are not registered
        return [call == 1 and k >= len(idx) - 2 for k in range(len(idx))]

    report = _run(loop_sequence, tmp_path / "s", _Faulty(loop_sequence, fault, dense=False), overlap=2)
    assert "start the next submap" in caplog.text
    assert report["degraded_edges"] == 0 and _exact(report)
    assert report["registered_frames"] == report["keyframes"]  # every keyframe registered once, somewhere


def test_implausible_estimated_intrinsics_are_refused():
    pytest.importorskip("pycolmap")
    from vggt_slam_pp.frontend.backbones.colmap import intrinsics_sane

    euroc = [458.7, 457.3, 367.2, 248.4, -0.283, 0.074, 0.0002, 0.00002]
    assert intrinsics_sane(euroc, 752, 480) == ""
    assert "differ" in intrinsics_sane([425, 355, 376, 240, -0.2, 0.05, 0, 0], 752, 480)  # seen on EuRoC
    assert "focal" in intrinsics_sane([100, 100, 376, 240, 0, 0, 0, 0], 752, 480)
    assert "principal point" in intrinsics_sane([460, 460, 30, 240, 0, 0, 0, 0], 752, 480)
    assert "distortion" in intrinsics_sane([460, 460, 376, 240, -1.5, 0, 0, 0], 752, 480)


def _pair(rng, n_frames=4, shared=2, T_prev_curr=None):
    """prev holds frames 0..n-1, curr frames n-shared..; curr's frame is prev's mapped by T_prev_curr."""
    from vggt_slam_pp.frontend.types import SubmapPrediction
    from vggt_slam_pp.geometry import se3_exp, sim3_inverse
    from vggt_slam_pp.geometry.lie import transform_points

    world = rng.uniform([-5, -3, 4], [5, 3, 15], (300, 3))
    T_cam_prev = np.array([se3_exp(np.r_[0.02 * k, -0.01 * k, 0.03 * k, 0.3 * k, 0.05 * k, 0.2 * k])
                           for k in range(n_frames)])
    T_pc = np.eye(4) if T_prev_curr is None else T_prev_curr

    def pred(frames, T_cam_sub, pts):
        S = len(frames)
        return SubmapPrediction(np.array(frames), T_cam_sub, np.repeat(np.eye(3)[None], S, 0), (4, 4),
                                np.repeat(np.eye(3)[None], S, 0), [pts] * S, [np.ones(len(pts), np.float32)] * S,
                                [np.zeros((len(pts), 2), np.float32)] * S, [np.arange(len(pts))] * S,
                                np.ones(S, bool), dense=False)

    prev = pred(list(range(n_frames)), T_cam_prev, world)
    first = n_frames - shared
    frames = list(range(first, first + n_frames))
    # curr's poses: the same cameras seen from the curr frame (T_cam_curr = T_cam_prev . T_prev_curr)
    T_cam_curr = np.array([T_cam_prev[min(k, n_frames - 1)] @ T_pc for k in frames])
    curr = pred(frames, T_cam_curr, transform_points(sim3_inverse(T_pc), world))
    return prev, curr


def test_anchored_edge_is_exact_and_disagreeing_overlaps_are_flagged(rng):
    from vggt_slam_pp.frontend.odometry import estimate_edge, overlap_disagreement
    from vggt_slam_pp.geometry import make_sim3, so3_exp

    T = make_sim3(1.7, so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, -2.0, 0.5]))
    prev, curr = _pair(rng, T_prev_curr=T)
    assert overlap_disagreement(prev, curr) < 1e-6
    anchored = dataclasses.replace(curr, info={"anchor_frames": [2, 3]})
    edge = estimate_edge(0, prev, 1, anchored)
    assert edge.method == "anchored" and edge.shared_frames == 2 and not edge.degraded
    assert np.allclose(edge.T_prev_curr, T, atol=1e-9)
    assert estimate_edge(0, prev, 1, curr).method == "pose_scale"
    # one shared keyframe's orientation 5 deg off in the current submap: flagged, with the reason
    bent = curr.T_cam_submap.copy()
    bent[1, :3, :3] = so3_exp(np.array([0.0, np.radians(5.0), 0.0])) @ bent[1, :3, :3]
    broken = dataclasses.replace(curr, T_cam_submap=bent)
    assert 4.9 < overlap_disagreement(prev, broken) < 5.1
    edge = estimate_edge(0, prev, 1, broken)
    assert edge.degraded and "disagree by 5.0 deg" in edge.cause
