"""Loops found from images (sparse backbones): a revisit that shares few 3-D points is registered by
matching the two submaps' keyframes and registering the query's into the match's own cameras."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vggt_slam_pp.backend.image_loops import (
    ImageLoopConfig,
    available,
    fit_similarity,
    image_loop_information,
    register_by_images,
)
from vggt_slam_pp.backend.registration import LoopBounds
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.geometry.lie import decompose_sim3, make_sim3, sim3_exp, sim3_inverse, sim3_log, so3_exp


def test_fit_similarity_recovers_a_similarity_from_cameras(rng):
    S = make_sim3(1.7, so3_exp(np.array([0.1, -0.3, 0.8])), np.array([3.0, -1.0, 2.0]))
    cams = np.array([make_sim3(1.0, so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3)) for _ in range(6)])
    T, rel = fit_similarity(cams, np.array([S @ C for C in cams]))
    assert np.allclose(T, S, atol=1e-9) and rel < 1e-9
    line = cams.copy()  # cameras along a line: the rotation about it comes from their orientations
    line[:, :3, 3] = np.outer(np.arange(6.0), [1.0, 0.2, 0.0])
    T, rel = fit_similarity(line, np.array([S @ C for C in line]))
    assert np.allclose(T, S, atol=1e-9) and rel < 1e-9


@pytest.fixture(scope="module")
def passes(tmp_path_factory):
    """Two passes along the start of the rendered block loop (0.4 m apart sideways), and a stretch further
    on: three short submaps reconstructed by the COLMAP backbone, their features in a submap store."""
    pytest.importorskip("pycolmap")
    from vggt_slam_pp.frontend.backbones.colmap import ColmapBackbone
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    scene = make_scene("loop", frames=600, width=320, height=240, seed=0)
    traj = scene.trajectory
    first = traj.subset(np.arange(0, 14, 2))
    shifted = first.poses.copy()
    shifted[:, :3, 3] += shifted[:, :3, 0] * 0.4  # 0.4 m to the camera's right
    second = dataclasses.replace(first, poses=shifted)
    elsewhere = traj.subset(np.arange(40, 54, 2))
    store = SubmapStore(tmp_path_factory.mktemp("store"))
    truth = {}
    for sid, part in enumerate((first, second, elsewhere)):
        out = tmp_path_factory.mktemp(f"pass{sid}")
        write_sequence(dataclasses.replace(scene, trajectory=part), out, aperiodic=True)
        src = open_source(out)
        frames = [dataclasses.replace(src[i], index=100 * sid + i) for i in range(len(src))]
        backbone = ColmapBackbone(calibrated=True)  # its feature files live as long as it does
        pred = backbone.predict(frames)
        assert pred.valid.all()
        store.put_features(sid, pred.info["features"], pred.T_cam_submap, pred.valid, pred.frame_indices)
        centres = np.array([sim3_inverse(T)[:3, 3] for T in pred.T_cam_submap])
        scale = np.linalg.norm(np.diff(part.poses[[0, -1], :3, 3], axis=0)) / np.linalg.norm(centres[-1] - centres[0])
        truth[sid] = make_sim3(scale, part.poses[0, :3, :3], part.poses[0, :3, 3])  # submap frame (camera 0) -> world
    return store, truth


def test_an_image_loop_is_certain_where_the_two_submaps_see_each_other():
    # the query's cameras along a line from its origin; only the last two see the match submap
    centres = np.c_[np.arange(8.0), np.zeros(8), np.zeros(8)]
    linked = np.array([0, 0, 0, 0, 0, 0, 200, 900], float)
    rel = 0.01
    info = image_loop_information(rel, centres, linked)

    def whitened(T):  # Mahalanobis length of the query's frame moved by T (right perturbation)
        xi = sim3_log(T)
        return float(np.sqrt(xi @ info @ xi))

    c = (linked[:, None] * centres).sum(0) / linked.sum()
    turn = make_sim3(1.0, so3_exp(np.array([0.0, 0.0, 2 * rel])), np.zeros(3))
    about_c = make_sim3(1.0, np.eye(3), c) @ turn @ make_sim3(1.0, np.eye(3), -c)
    # turning the query about the cameras that see the match costs its rotation alone (2 sigma) ...
    assert whitened(about_c) == pytest.approx(2.0, rel=1e-6)
    # ... and the same turn about its origin, which swings those cameras by 2 % of their 7-unit lever, more
    assert whitened(turn) > 3.0
    # a scale change about them likewise; a shift is in units of the cameras' spread
    grow = make_sim3(np.exp(rel), np.eye(3), (1 - np.exp(rel)) * c)
    assert whitened(grow) == pytest.approx(1.0, rel=1e-6)
    spread = float(np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, axis=1))))
    assert whitened(sim3_exp(np.r_[0, 0, 0, rel * spread, 0, 0, 0])) == pytest.approx(1.0, rel=1e-6)
    # with no matches across known, every camera counts alike
    even = image_loop_information(rel, centres, np.zeros(8))
    np.testing.assert_allclose(even, image_loop_information(rel, centres, np.ones(8)))


def test_a_revisit_is_registered_from_images_and_another_place_is_not(passes):
    store, truth = passes
    assert available(store, 1, 0) and not available(store, 1, 7)
    bounds = LoopBounds(0.7, np.inf, 180.0)
    r = register_by_images(1, 0, store, truth[1], truth[0], bounds, ImageLoopConfig())
    assert r.accepted, r.reason
    assert r.guess == "images" and r.overlap >= 0.5 and r.information is not None
    E = sim3_inverse(sim3_inverse(truth[0]) @ truth[1]) @ r.T_match_query  # error against the truth
    s, R, t = decompose_sim3(E)
    assert abs(np.log(s)) < 0.03 and np.degrees(np.arccos((np.trace(R) - 1) / 2)) < 1.0
    assert np.linalg.norm(truth[0][:3, :3] @ t) < 0.2  # metres, at the match's origin
    far = register_by_images(2, 0, store, truth[2], truth[0], bounds, ImageLoopConfig())
    assert not far.accepted and far.reason.startswith("images:")
    tight = register_by_images(1, 0, store, truth[1] @ make_sim3(1.0, np.eye(3), np.array([5.0, 0, 0])), truth[0],
                               LoopBounds(0.7, 1.0, 180.0), ImageLoopConfig())
    assert not tight.accepted and "odometry allows" in tight.reason  # the drift bounds still apply


def test_image_loops_can_be_switched_off_from_the_command_line():
    from vggt_slam_pp.cli.main import build_parser, run_config_from_args
    from vggt_slam_pp.frontend.backbones.colmap import from_run_config

    parser = build_parser()
    on = run_config_from_args(parser.parse_args(["run", "--input", "x", "--preset", "photos"]))
    off = run_config_from_args(parser.parse_args(["run", "--input", "x", "--preset", "photos", "--no-image-loops"]))
    assert on.backbone.image_features and not off.backbone.image_features
    pytest.importorskip("pycolmap")
    assert from_run_config(on, None)._features is not None and from_run_config(off, None)._features is None


def test_the_colmap_bench_calls_a_loop_false_by_where_it_puts_the_query_cameras(tmp_path):
    """``bench loops --backbone colmap`` judges a loop by the query's cameras it places, each submap's frame
    fitted to the ground truth by its own cameras (any scale): the true relative pose is 0 m off, one
    shifted by 2 m is 2 m off."""
    from vggt_slam_pp.benchmarks import _loop_camera_errors
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    write_sequence(make_scene("figure8", frames=12, width=48, height=36, seed=1), tmp_path / "seq")
    source = open_source(tmp_path / "seq")
    idx, gt = source.frame_ground_truth()
    assert idx.tolist() == list(range(12))  # ground-truth row = frame index
    nodes, frames = [], {0: [0, 1, 2, 3], 1: [7, 8, 9, 10]}
    scale_of = {0: 0.5, 1: 2.0}  # each submap in its own scale (as SfM submaps are)
    for sid, fr in frames.items():
        T_sub_world = sim3_inverse(make_sim3(scale_of[sid], gt.poses[fr[0], :3, :3], gt.poses[fr[0], :3, 3]))
        centres = [(T_sub_world @ np.r_[gt.poses[f, :3, 3], 1.0])[:3].tolist() for f in fr]
        nodes.append({"id": sid, "frames": fr, "camera_centers": centres})
    truth = sim3_inverse(make_sim3(0.5, gt.poses[0, :3, :3], gt.poses[0, :3, 3])) @ make_sim3(
        2.0, gt.poses[7, :3, :3], gt.poses[7, :3, 3])  # T_0_1
    off = make_sim3(1.0, np.eye(3), np.array([2.0 / 0.5, 0.0, 0.0])) @ truth  # 2 m along x in submap 0's units
    for T, expect in ((truth, 0.0), (off, 2.0)):
        graph = {"nodes": nodes, "edges": [{"from": 0, "to": 1, "kind": "loop", "T": T.tolist()}]}
        assert _loop_camera_errors(source, graph)[(1, 0)] == pytest.approx(expect, abs=1e-6)


def test_a_submap_stored_again_drops_the_features_of_an_earlier_run(tmp_path):
    store = SubmapStore(tmp_path / "s")
    store.put(3, np.zeros((5, 3)))
    db = tmp_path / "f.db"
    db.write_bytes(b"features")
    store.put_features(3, db, np.repeat(np.eye(4)[None], 2, 0), np.array([True, False]), np.array([7, 8]))
    got = store.get_features(3)
    assert got is not None and got[0].read_bytes() == b"features" and not db.exists()
    assert got[1]["frame_indices"].tolist() == [7, 8] and got[1]["valid"].tolist() == [True, False]
    assert not list((tmp_path / "s").glob("*.tmp*"))
    store.put(3, np.zeros((5, 3)))  # a new run into the same folder: its own submap 3 has no features
    assert store.get_features(3) is None and not available(store, 3, 3)
