"""Resuming an interrupted run: the result equals the uninterrupted run's."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from vggt_slam_pp.cli.main import main
from vggt_slam_pp.errors import InputError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.io import open_source
from vggt_slam_pp.io.trajectory import read_tum
from vggt_slam_pp.pipeline import RunConfig, make_backbone, run


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    folder = tmp_path_factory.mktemp("resume") / "seq"
    write_sequence(make_scene("loop", frames=60, width=96, height=72, seed=4), folder)
    return folder


class _CrashAfter(Backbone):
    """The live backbone until ``calls`` predictions were made, then a Ctrl-C."""

    def __init__(self, live: Backbone, calls: int) -> None:
        self.live, self.calls = live, calls
        self.name, self.dense, self.metric = live.name, live.dense, live.metric

    def predict(self, frames):
        if self.calls == 0:
            raise KeyboardInterrupt
        self.calls -= 1
        return self.live.predict(frames)

    def committed(self, frame_indices) -> None:
        self.live.committed(frame_indices)


def _config(worker: str = "process") -> RunConfig:
    import dataclasses

    from vggt_slam_pp.backend.worker import WorkerConfig

    base = RunConfig.preset("synthetic")
    return dataclasses.replace(base, backbone=dataclasses.replace(base.backbone, noise="realistic", seed=2),
                               frontend=dataclasses.replace(base.frontend, submap_size=4),
                               worker=WorkerConfig(mode=worker))


def _same(a, b) -> None:
    ta, tb = read_tum(a), read_tum(b)
    assert np.array_equal(ta.timestamps, tb.timestamps)
    assert np.abs(ta.poses[:, :3, 3] - tb.poses[:, :3, 3]).max() <= 1e-6


def test_a_resumed_run_equals_the_uninterrupted_one(sequence, tmp_path):
    source = open_source(sequence)
    config = _config(worker="inline")
    whole = run(source, config, tmp_path / "whole")
    other = dataclasses.replace(config, backbone=dataclasses.replace(config.backbone, seed=7))
    run(source, other, tmp_path / "cut")  # an earlier, different run in the same folder: never replayed
    with pytest.raises(KeyboardInterrupt):
        run(source, config, tmp_path / "cut", backbone=_CrashAfter(make_backbone(config, source), 5))
    assert len(list((tmp_path / "cut" / "predictions").glob("*.safetensors"))) == 5
    resumed = run(source, config, tmp_path / "cut", resume=True)
    assert resumed["resumed_backbone_calls"] == 5 and resumed["submaps"] == whole["submaps"] > 5
    for name in ("keyframes_odometry.txt", "keyframes.txt", "frames.txt"):
        _same(tmp_path / "whole" / name, tmp_path / "cut" / name)
    assert resumed["loops_accepted"] == whole["loops_accepted"]
    with pytest.raises(InputError, match="nothing to resume"):
        run(source, config, tmp_path / "empty", resume=True)


def test_run_resume_reads_input_and_configuration_from_the_folder(sequence, tmp_path, capsys, monkeypatch):
    from vggt_slam_pp.frontend.backbones.simulated import SimulatedBackbone

    args = ["run", "--input", str(sequence), "--preset", "synthetic", "--noise", "realistic", "--submap-size", "4",
            "--seed", "2", "--no-backend", "-q"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    original, calls = SimulatedBackbone.predict, []

    def crashing(self, frames):
        calls.append(1)
        if len(calls) > 4:
            raise KeyboardInterrupt
        return original(self, frames)

    monkeypatch.setattr(SimulatedBackbone, "predict", crashing)
    assert main([*args, "--out", str(tmp_path / "cut")]) == 130  # interrupted
    monkeypatch.setattr(SimulatedBackbone, "predict", original)
    assert json.loads((tmp_path / "cut" / "input.json").read_text())["input"] == str(sequence.resolve())
    capsys.readouterr()
    assert main(["run", "--resume", str(tmp_path / "cut"), "-q"]) == 0
    assert "resumed: 4 backbone calls read from predictions/" in capsys.readouterr().out
    _same(tmp_path / "whole" / "keyframes_odometry.txt", tmp_path / "cut" / "keyframes_odometry.txt")
    assert main(["run", "--resume", str(tmp_path / "cut"), "--submap-size", "8"]) == 2  # settings come from DIR
    assert "--resume" in capsys.readouterr().err


def test_a_finished_run_is_a_map_and_damaged_maps_are_refused(sequence, tmp_path):
    import shutil

    from vggt_slam_pp.backend.mapfile import load_map

    source = open_source(sequence)
    config = _config(worker="inline")
    report = run(source, config, tmp_path / "map")
    saved = load_map(tmp_path / "map")
    graph = json.loads((tmp_path / "map" / "graph.json").read_text())
    assert len(saved.submaps) == report["submaps"] and saved.tile_size == graph["tile_size"]
    assert np.allclose(saved.submaps[-1].T_world_submap, graph["nodes"][-1]["T_world_submap"])
    assert saved.submaps[0].camera_centers.shape == (len(saved.submaps[0].frames), 3)
    assert sum(e.kind == "odometry" for e in saved.edges) == report["submaps"] - 1
    assert np.array_equal(saved.store.get(2), np.load(tmp_path / "map" / "submaps" / "000002.npy"))
    colours = saved.store.get_colors(2)  # the image colour of every point, stored beside them
    assert colours.shape == saved.store.get(2).shape and colours.dtype == np.uint8 and np.ptp(colours) > 0

    def damaged(edit, message):
        bad = tmp_path / f"bad_{len(list(tmp_path.iterdir()))}"
        shutil.copytree(tmp_path / "map", bad)
        edit(bad)
        with pytest.raises(InputError, match=message) as info:
            load_map(bad)
        assert "\n" not in str(info.value)

    def truncate(folder):
        p = folder / "submaps" / "000003.npy"
        p.write_bytes(p.read_bytes()[:100])

    def other_version(folder):
        m = json.loads((folder / "map.json").read_text())
        (folder / "map.json").write_text(json.dumps({**m, "version": 99}))

    damaged(truncate, "000003.npy has 100 bytes")
    damaged(lambda f: (f / "submaps" / "000001.npy").unlink(), "000001.npy is missing")
    damaged(lambda f: (f / "submaps" / "000001.rgb.npy").unlink(), "000001.rgb.npy is missing")
    damaged(other_version, "format version 99")
    damaged(lambda f: (f / "map.json").write_text("{}"), "not a vggt-slam-pp map manifest")
    damaged(lambda f: (f / "map.json").unlink(), "not a map: no map.json")
    with pytest.raises(KeyboardInterrupt):  # an interrupted run leaves no manifest: it is not a map
        run(source, config, tmp_path / "map", backbone=_CrashAfter(make_backbone(config, source), 3))
    with pytest.raises(InputError, match="no map.json"):
        load_map(tmp_path / "map")


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A map of a synthetic block loop (300 frames) and the same images again from a quarter of the way,
    as a second recording with other noise."""
    from vggt_slam_pp.io.frames import FrameSubset
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    root = tmp_path_factory.mktemp("relocalise")
    write_sequence(make_scene("loop", frames=300, width=160, height=120, seed=3), root / "seq")
    source = open_source(root / "seq")
    report = run(source, _synthetic(0), root / "map")
    return root, source, FrameSubset(source, np.arange(75, 300)), report


def _synthetic(seed: int) -> RunConfig:
    import dataclasses

    from vggt_slam_pp.backend.worker import WorkerConfig

    base = RunConfig.preset("synthetic")
    return dataclasses.replace(base, backbone=dataclasses.replace(base.backbone, seed=seed),
                               worker=WorkerConfig(mode="inline"))


def test_a_second_recording_is_placed_in_the_map_and_extends_it(mapped, tmp_path):
    from vggt_slam_pp.backend.mapfile import load_map
    from vggt_slam_pp.eval import compute_ate

    root, source, second, first = mapped
    def contents():
        return {str(p): p.read_bytes() for p in sorted((root / "map").rglob("*")) if p.is_file()}

    before = contents()
    report = run(second, _synthetic(1), tmp_path / "more", prior_map=root / "map")
    assert report["map_submaps"] == first["submaps"] and report["placed_fraction"] == 1.0
    assert main(["run", "--input", str(root / "seq"), "--preset", "synthetic", "--map", str(root / "map"),
                 "--out", str(root / "map"), "-q"]) == 2  # refused before anything is written
    assert contents() == before  # the map is untouched, its points and DEM included
    extended = load_map(tmp_path / "more")
    assert len(extended.submaps) == first["submaps"] + report["submaps"]
    assert extended.store.get_colors(0) is not None  # the map's colours came along
    # re-solved with the new loops, the map keeps its frame: on average its submaps stay where they were
    saved = load_map(root / "map").submaps
    shift = np.mean([e.T_world_submap[:3, 3] - s.T_world_submap[:3, 3] for e, s in zip(extended.submaps[:len(saved)], saved, strict=True)], 0)
    assert np.linalg.norm(shift) < 0.02, shift
    # the second recording comes out in the map's frame: the map's own alignment to the ground truth fits it
    gt = source.frame_ground_truth()[1]
    T = compute_ate(gt, read_tum(root / "map" / "keyframes.txt"), "sim3").T_ref_est
    est = read_tum(tmp_path / "more" / "keyframes.txt")
    truth = np.array([gt.poses[np.argmin(np.abs(gt.timestamps - t))][:3, 3] for t in est.timestamps])
    err = np.linalg.norm(est.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3] - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) <= 3 * first["ate_rmse"] + 0.05, (np.sqrt(np.mean(err**2)), first["ate_rmse"])


def test_localize_only_keeps_the_map_fixed_and_refuses_to_write_into_it(mapped, tmp_path):
    root, _, second, first = mapped
    report = run(second, _synthetic(1), tmp_path / "loc", prior_map=root / "map", localize_only=True)
    assert report["placed_fraction"] == 1.0 and not (tmp_path / "loc" / "map.json").exists()  # not a map
    nodes = json.loads((tmp_path / "loc" / "graph.json").read_text())["nodes"]
    saved = json.loads((root / "map" / "graph.json").read_text())["nodes"]
    for a, b in zip(nodes[: first["submaps"]], saved, strict=True):
        assert np.allclose(a["T_world_submap"], b["T_world_submap"], atol=1e-9)
    with pytest.raises(InputError, match="never modified in place"):
        run(second, _synthetic(1), root / "map", prior_map=root / "map", input_record={"input": "new"})
    assert not (root / "map" / "input.json").exists()  # refused before anything is written
    with pytest.raises(InputError, match="not a map"):
        run(second, _synthetic(1), tmp_path / "x", prior_map=tmp_path / "loc")
