"""The COLMAP front-end on rendered images: repeatable (same seed -> byte-identical trajectories) and
linked by several overlap keyframes."""

from __future__ import annotations

import dataclasses

import pytest

from vggt_slam_pp.frontend.frontend import FrontendConfig
from vggt_slam_pp.frontend.keyframes import KeyframeConfig
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run

pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The first 36 frames (about 24 m, straight: forward motion) of the rendered block loop at 320x240."""
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    scene = make_scene("loop", frames=600, width=320, height=240, seed=0)
    scene = dataclasses.replace(scene, trajectory=scene.trajectory.subset(list(range(36))))
    out = tmp_path_factory.mktemp("straight")
    write_sequence(scene, out, aperiodic=True)
    return open_source(out)


def _config(seed=0):
    return RunConfig(backbone=BackboneConfig(name="colmap", seed=seed),
                     frontend=FrontendConfig(keyframes=KeyframeConfig(tau_disparity=12.0), submap_size=6),
                     calibrated=True, backend=False, save_predictions=False)


def test_same_seed_gives_byte_identical_trajectories(tmp_path, straight):
    a = run(straight, _config(), tmp_path / "a")
    b = run(straight, _config(), tmp_path / "b")
    assert a["submaps"] >= 2 and a["degraded_edges"] == 0 and b["ate_rmse_odometry"] == a["ate_rmse_odometry"]
    assert all(e["shared_frames"] >= 2 for e in a["edges"])  # sparse: several overlap keyframes
    assert a["registered_frames"] == a["keyframes"]
    assert all(e["method"] == "anchored" for e in a["edges"])  # each submap registered into the previous
    for name in ("keyframes_odometry.txt", "frames_odometry.txt"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert a["camera"]["source"] == "given"
