"""The command line: JSON outputs and one-line errors with non-zero exit codes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import random_trajectory
from vggt_slam_pp.cli.main import main
from vggt_slam_pp.io.trajectory import Trajectory, write_trajectory


def _run(capsys, *argv):
    code = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    return code, out, err


def test_eval_json(tmp_path, rng, capsys):
    gt = random_trajectory(rng, 100)
    est = Trajectory(gt.timestamps + 0.001, gt.poses.copy())
    est.poses[:, :3, 3] *= 3.0  # a scaled copy: Sim(3) alignment removes it
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.txt", est, "tum")
    code, out, _ = _run(capsys, "eval", "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt", "--json")
    assert code == 0
    res = json.loads(out)
    for key in ("ate_rmse", "ate_mean", "ate_median", "ate_max", "n_matched", "scale", "rpe_trans_rmse"):
        assert key in res
    assert res["ate_rmse"] < 1e-6 and res["n_matched"] == 100
    assert res["scale"] == pytest.approx(1 / 3.0)
    code, out, _ = _run(capsys, "eval", "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt", "--align", "se3",
                        "--json")
    assert json.loads(out)["ate_rmse"] > 1.0


def test_eval_kitti_files(tmp_path, rng, capsys):
    gt = random_trajectory(rng, 30)
    write_trajectory(tmp_path / "gt.kitti", gt, "kitti")
    write_trajectory(tmp_path / "est.kitti", gt, "kitti")
    code, out, _ = _run(capsys, "eval", "--gt", tmp_path / "gt.kitti", "--est", tmp_path / "est.kitti", "--json")
    assert code == 0 and json.loads(out)["n_matched"] == 30


def _one_line_error(code, out, err, *needles):
    assert code != 0
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for n in needles:
        assert n in lines[0]


def test_bad_inputs_are_one_line_errors(tmp_path, rng, capsys):
    gt = random_trajectory(rng, 20, t0=0.0)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "late.txt", random_trajectory(rng, 20, t0=500.0), "tum")
    (tmp_path / "bad.txt").write_text("0.0 1 2 3 0 0 0 1\n0.1 1 2 three 0 0 0 1\n")
    (tmp_path / "empty").mkdir()
    (tmp_path / "corrupt").mkdir()
    (tmp_path / "corrupt" / "000001.png").write_bytes(b"garbage")
    _one_line_error(*_run(capsys, "eval", "--gt", tmp_path / "gt.txt", "--est", tmp_path / "bad.txt"), "bad.txt:2")
    _one_line_error(*_run(capsys, "eval", "--gt", tmp_path / "gt.txt", "--est", tmp_path / "late.txt"),
                    "no timestamps match")
    _one_line_error(*_run(capsys, "eval", "--gt", tmp_path / "nope.txt", "--est", tmp_path / "gt.txt"), "not found")
    _one_line_error(*_run(capsys, "info", tmp_path / "missing"), "input not found")
    _one_line_error(*_run(capsys, "info", tmp_path / "empty"), "empty")
    _one_line_error(*_run(capsys, "info", tmp_path / "corrupt"), "cannot read image", "000001.png")
    _one_line_error(*_run(capsys, "synth", "--trajectory", tmp_path / "bad.txt", "--out", tmp_path / "s"), "bad.txt:2")


def test_info_json_on_euroc(shared_data, capsys):
    code, out, _ = _run(capsys, "info", shared_data / "euroc_mh05_sample", "--json")
    info = json.loads(out)
    assert code == 0
    assert info["layout"] == "euroc" and info["frames"] == 585 and info["ground_truth"] is True
    assert info["frames_with_ground_truth"] == 585 and info["width"] == 752


def test_synth_then_info_and_demo(tmp_path, capsys):
    code, out, _ = _run(capsys, "synth", "--scene", "figure8", "--frames", 5, "--width", 64, "--height", 48,
                        "--out", tmp_path / "seq", "--json")
    assert code == 0 and json.loads(out)["frames"] == 5
    code, out, _ = _run(capsys, "info", tmp_path / "seq", "--json")
    info = json.loads(out)
    assert info["layout"] == "tum" and info["has_depth"] and info["frames_with_ground_truth"] == 5
    code, out, _ = _run(capsys, "info", tmp_path / "seq")
    assert code == 0 and "depth: yes; intrinsics: yes; ground truth: 5 frames matched" in out
    code, out, _ = _run(capsys, "demo", "--out", tmp_path / "demo", "--frames", 20, "--width", 64, "--height", 48)
    assert code == 0 and "ATE" in out
    report = json.loads((tmp_path / "demo" / "run" / "report.json").read_text())
    assert report["frames"] == 20 and np.isfinite(report["ate_rmse_odometry"]) and np.isfinite(report["ate_rmse"])
    assert report["loops_accepted"] >= 0 and (tmp_path / "demo" / "run" / "keyframes.txt").is_file()
    assert report["odometry_scale_measured_by"] in (None, "heights", "loops") and "odometry_scale_sigma" in report


def test_module_entry_point_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "vggt_slam_pp", "info", str(tmp_path / "missing")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("error: input not found")
    r = subprocess.run([sys.executable, "-m", "vggt_slam_pp", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "vggt-slam-pp" in r.stdout


def test_weights_command_offline(tmp_path, monkeypatch, capsys):
    import torch

    from vggt_slam_pp.models import build_dinov2

    monkeypatch.setenv("VGGT_SLAM_PP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    code, out, _ = _run(capsys, "weights", "--json")
    assert code == 0 and json.loads(out)["weights"] == []
    _one_line_error(*_run(capsys, "weights", "fetch", "vggt-1b"), "--weights PATH")
    _one_line_error(*_run(capsys, "weights", "import", tmp_path / "missing.pt"), "not found")
    bad = tmp_path / "tiny.pt"
    torch.save(build_dinov2({"embed_dim": 48, "depth": 1, "num_heads": 3}).state_dict(), bad)
    _one_line_error(*_run(capsys, "weights", "import", bad, "--name", "dinov2_vits14"), "missing keys")
    code, out, _ = _run(capsys, "weights")
    assert code == 0 and "no weights cached" in out


def test_run_command_simulated_and_bad_input(tmp_path, capsys):
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    seq = tmp_path / "seq"
    write_sequence(make_scene("figure8", frames=40, width=160, height=120, seed=1), seq)
    code, out, _ = _run(capsys, "run", "--input", seq, "--backbone", "simulated", "--noise", "zero",
                        "--out", tmp_path / "out", "--tau", "10", "--submap-size", "4", "-q", "--no-backend")
    assert code == 0 and "ATE rmse (Sim(3)-aligned, keyframes): odometry" in out
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frames"] == 40 and report["submaps"] >= 2 and report["ate_rmse_odometry"] < 1e-6
    assert {"keyframes_s", "backbone_s", "odometry_s"} <= set(report["timings"]) and report["peak_memory_mb"] > 0
    assert json.loads((tmp_path / "out" / "config.json").read_text())["frontend"]["submap_size"] == 4
    # replay the recorded predictions
    code, out, _ = _run(capsys, "run", "--input", seq, "--backbone", "replay", "--replay", tmp_path / "out",
                        "--out", tmp_path / "replayed", "--tau", "10", "--submap-size", "4", "-q", "--no-backend")
    assert code == 0
    # bad inputs: one-line errors
    _one_line_error(*_run(capsys, "run", "--input", tmp_path / "missing", "--backbone", "simulated",
                          "--out", tmp_path / "x", "-q"), "missing")
    _one_line_error(*_run(capsys, "run", "--input", seq, "--backbone", "replay", "--out", tmp_path / "y", "-q"),
                    "--replay")


def test_bench_passes_the_seed_to_the_synthetic_suites(capsys, monkeypatch, tmp_path):
    from vggt_slam_pp import benchmarks

    seen = {}

    def fake(name, result):
        def bench(**kw):
            seen[name] = kw
            return result
        return bench

    cov = {"scenes": {}, "covisibility_recall": None, "covisibility_recall_votes": None, "candidate_recall": None,
           "vpr_top1_precision": None}
    monkeypatch.setattr(benchmarks, "bench_covisibility", fake("covisibility", cov))
    loops = {"scenarios": {}, "mean_ate_reduction": None, "false_loops": 0, "min_fps_ratio": 1.0, "loops_off_truth": 2,
             "loops_verified": 9, "verified_off_truth": 4}
    monkeypatch.setattr(benchmarks, "bench_loops", fake("loops", loops))
    code, out, _ = _run(capsys, "bench", "covisibility", "--seed", 3, "--json")
    assert code == 0 and seen["covisibility"]["seed"] == 3 and json.loads(out)["scenes"] == {}
    assert _run(capsys, "bench", "loops", "--json")[0] == 0 and seen["loops"]["seed"] == 0
    code, out, err = _run(capsys, "bench", "loops")
    assert code == 0 and "false loops 0 (target 0)" in out + err and "off the truth 2" in out + err
    assert "verified 9, of which off the truth 4" in out + err
    row = {"submaps": 15, "ate_odometry": 0.2, "drift_pct_path": 0.08, "ate_final": 0.1, "ate_reduction": 0.5,
           "loops_accepted": 3, "false_loops": 0, "footprint_false_loops": 1, "backend_s_per_submap": 9.0, "fps": 4.0}
    images = {"scenarios": {"laps": row}, "backbone": "colmap", "mean_ate_reduction": 0.5, "false_loops": 0,
              "targets": {"mean_ate_reduction": 0.3}}
    monkeypatch.setattr(benchmarks, "bench_loops_colmap", fake("colmap", images))
    code, out, err = _run(capsys, "bench", "loops", "--backbone", "colmap", "--seed", 2)
    assert code == 0 and seen["colmap"]["seed"] == 2 and "loops from images" in out + err
    assert "target >= 30 %" in out + err and "footprint rule of the simulated bench: 1" in out + err
    mem = {"submaps": 1074, "frames": 25000, "rss_mb_at_50": 400.0, "rss_mb_at_300": 440.0, "growth": 0.1,
           "backend_s_per_submap_first100": 0.25, "backend_s_per_submap_last100": 0.7,
           "backend_cpu_s_per_submap_first100": 0.2, "backend_cpu_s_per_submap_last100": 0.68,
           "peak_rss_mb_all": 900.0, "frontend_submit_wait_fraction": 0.036, "backend_max_lag_submaps": 140,
           "backend_queries_deferred": 300, "ate_reduction": 0.88, "false_loops": 0,
           "backend_stage_s_first100": {"covisibility_s": 0.35, "registration_s": 0.23},
           "backend_stage_s_last100": {"covisibility_s": 0.19, "registration_s": 0.88}}
    monkeypatch.setattr(benchmarks, "bench_memory", fake("memory", mem))
    code, out, err = _run(capsys, "bench", "memory", "--submaps", 1000, "--seed", 1)
    assert code == 0 and seen["memory"]["seed"] == 1 and seen["memory"]["submaps"] == 1000
    assert seen["memory"]["laps"] == 0  # the block loop unless asked
    assert "0.250 / 0.700 wall (target: last <= 1.3x first), 0.200 / 0.680 CPU" in out + err
    assert "submit wait 3.6 %" in out + err and "ATE reduction 0.880" in out + err and "false loops 0" in out + err
    assert "covisibility 0.350 / 0.190, registration 0.230 / 0.880" in out + err
    assert _run(capsys, "bench", "memory", "--laps", 8)[0] == 0 and seen["memory"]["laps"] == 8
    monkeypatch.undo()
    code, out, err = _run(capsys, "bench", "memory", "--laps", -1, "--workdir", tmp_path)
    assert code != 0 and "laps must be 0" in err and "Traceback" not in err


def test_bench_frontend_reports_missing_data_as_skipped(tmp_path, capsys):
    code, out, _ = _run(capsys, "bench", "frontend", "--data", tmp_path / "nothing", "--sequence", "castle",
                        "--sequence", "euroc_calibrated", "--runs", 2, "--json", "--workdir", tmp_path / "w")
    result = json.loads(out)
    assert code == 0 and result["runs"] == 2 and result["deterministic"] is True
    assert [r["name"] for r in result["sequences"]] == ["euroc_calibrated", "castle"]
    assert all("no data" in r["skipped"] for r in result["sequences"])


def test_run_summary_says_how_many_edges_degraded(capsys):
    from vggt_slam_pp.cli.main import _print_summary

    report = {"frames_processed": 10, "keyframes": 6, "submaps": 3, "seconds_total": 1.0, "fps": 10.0,
              "edges": [{"prev": 0, "curr": 1, "degraded": False, "cause": ""},
                        {"prev": 1, "curr": 2, "degraded": True, "cause": "overlap frame(s) [5] not registered"}],
              "camera": {"source": "estimated on keyframes 0..4", "params": [400.0, 400, 320, 240, 0, 0, 0, 0]}}
    _print_summary(report, "out")
    out = capsys.readouterr().out
    assert "WARNING: 1 of 2 odometry edges degraded" in out and "1->2 overlap frame(s) [5] not registered" in out
    assert "camera (estimated on keyframes 0..4): OPENCV fx fy cx cy k1 k2 p1 p2 = 400" in out
    report["edges"][1]["degraded"] = False
    report["camera"]["model"] = "OPENCV_FISHEYE"
    _print_summary(report, "out")
    out = capsys.readouterr().out
    assert "odometry: 2 edges, none degraded" in out and "OPENCV_FISHEYE fx fy cx cy k1 k2 k3 k4 = 400" in out


def test_a_saved_configuration_runs_again_and_flags_override_it(tmp_path, capsys):
    from vggt_slam_pp.pipeline import RunConfig
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    seq = tmp_path / "seq"
    write_sequence(make_scene("figure8", frames=30, width=160, height=120, seed=2), seq)
    code, _, _ = _run(capsys, "run", "--input", seq, "--preset", "synthetic", "--noise", "realistic", "--seed", "3",
                      "--tau", "10", "--submap-size", "4", "--out", tmp_path / "a", "-q", "--no-backend")
    assert code == 0
    saved = RunConfig.load(tmp_path / "a" / "config.json")
    assert saved.backbone.name == "simulated" and saved.backbone.seed == 3 and saved.frontend.submap_size == 4
    assert saved.frontend.keyframes.tau_disparity == 10.0 and not saved.backend
    code, _, _ = _run(capsys, "run", "--input", seq, "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "b",
                      "-q")
    assert code == 0 and RunConfig.load(tmp_path / "b" / "config.json") == saved
    first = (tmp_path / "a" / "keyframes_odometry.txt").read_bytes()
    assert (tmp_path / "b" / "keyframes_odometry.txt").read_bytes() == first  # the same run again
    code, _, _ = _run(capsys, "run", "--input", seq, "--config", tmp_path / "a" / "config.json", "--submap-size", "6",
                      "--out", tmp_path / "c", "-q")
    c = RunConfig.load(tmp_path / "c" / "config.json")
    assert code == 0 and c.frontend.submap_size == 6 and c.backbone.seed == 3  # the flag wins, the rest stays


def test_presets_and_bad_configuration_files(tmp_path, capsys):
    from vggt_slam_pp.configs import PRESETS
    from vggt_slam_pp.errors import InputError
    from vggt_slam_pp.pipeline import RunConfig

    assert RunConfig.preset("photos").frontend.submap_size == 8 and RunConfig.preset("vggt").backbone.name == "vggt"
    assert {RunConfig.preset(name).backbone.name for name in PRESETS} == {"vggt", "simulated", "colmap"}
    with pytest.raises(InputError, match="unknown preset"):
        RunConfig.preset("fast")
    bad = tmp_path / "config.json"
    bad.write_text('{"frontend": {"submap_sise": 8}}')
    with pytest.raises(InputError, match=r"config.json.frontend: unknown key\(s\) submap_sise"):
        RunConfig.load(bad)
    bad.write_text('{"frontend": {"submap_size": "8"}}')
    with pytest.raises(InputError, match="submap_size: '8' is not a int"):
        RunConfig.load(bad)
    bad.write_text('{"frontend": 5}')
    with pytest.raises(InputError, match="frontend: 5 is not a section"):
        RunConfig.load(bad)
    older = tmp_path / "older.json"
    older.write_text('{"backbone": {"name": "colmap"}}')  # missing keys keep their defaults
    assert RunConfig.load(older).backbone.name == "colmap" and RunConfig.load(older).frontend.submap_size == 32
    # a colmap run from before the global mapper was the default keeps the incremental one it was made with
    assert RunConfig.load(older).backbone.colmap_mapper == "incremental"
    assert RunConfig().backbone.colmap_mapper == "global"
    # a config.json of version 0.x: the worker's settings and fault injection were in backend_config
    older.write_text('{"backend_config": {"worker": "inline", "worker_duty": 0.25, "queue_size": 4, '
                     '"inject_wrong_candidates": 0.1, "loop_information": "icp", "candidates_per_query": 2}}')
    old = RunConfig.load(older)
    assert (old.worker.mode, old.worker.duty) == ("inline", 0.25)  # queue_size: the bounded inbox is gone
    assert old.backend_config.faults.wrong_candidates == 0.1 and old.backend_config.candidates_per_query == 2
    older.write_text('{"backend_config": {"loop_information": "isotropic"}}')  # gone: refused, not ignored
    with pytest.raises(InputError, match="loop_information 'isotropic' is no longer supported"):
        RunConfig.load(older)
    bad.write_text("{not json")
    _one_line_error(*_run(capsys, "run", "--input", tmp_path, "--config", bad, "--out", tmp_path / "x", "-q"),
                    "not JSON")
    _one_line_error(*_run(capsys, "run", "--input", tmp_path, "--config", tmp_path / "none.json", "--out",
                          tmp_path / "x", "-q"), "cannot read the configuration")
