"""``evaluate SUITE.yaml``: resumable runs, equal results in every executor, tables, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vggt_slam_pp.cli.main import main
from vggt_slam_pp.suite import load_suite, run_suite, write_tables

TINY = """
name: tiny
runs: 2
datasets:
  - name: loop
    synthetic: {scene: loop, frames: 60, width: 96, height: 72, seed: 4}
configurations:
  - name: odometry
    preset: synthetic
    overrides: {backend: false}
  - name: small_submaps
    preset: synthetic
    overrides: {backend: false, frontend.submap_size: 4, backbone.noise: realistic}
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("suite")
    (folder / "tiny.yaml").write_text(TINY)
    return folder / "tiny.yaml"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _ates(results: list[dict]) -> dict:
    return {(r["config"], r["sequence"], r["seed"]): r["ate"] for r in results}


def test_a_suite_runs_once_then_repeats_nothing(tiny, tmp_path, monkeypatch):
    out = tmp_path / "out"
    suite = load_suite(tiny)
    first = run_suite(suite, out)
    assert len(first) == 4 and all(r["error"] is None and r["ate"] > 0 for r in first)
    assert {r["seed"] for r in first} == {0, 1}
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("result.json")}

    def no_run(task):
        raise AssertionError(f"{task.key} ran again")

    monkeypatch.setattr("vggt_slam_pp.suite.runner.run_task", no_run)
    again = run_suite(suite, out)
    assert _ates(again) == _ates(first)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("result.json")} == stamps
    changed = load_suite(_write(tiny.parent / "changed.yaml", TINY.replace("submap_size: 4", "submap_size: 5")))
    from vggt_slam_pp.suite import expand
    from vggt_slam_pp.suite.runner import finished_result

    done = {t.config: finished_result(t) is not None for t in expand(changed, out)}
    assert done == {"odometry": True, "small_submaps": False}  # other settings under the same name run again
    paths = write_tables(again, out)
    md = paths["md"].read_text()
    assert "| odometry |" in md and "| small_submaps |" in md and "average" in md and "±" in md
    assert paths["csv"].read_text().count("\n") == 3 and r"\begin{tabular}" in paths["tex"].read_text()


def test_results_are_equal_with_one_or_two_jobs_and_on_a_local_ray_instance(tiny, tmp_path):
    pytest.importorskip("ray")  # in the test extra; skipped only where Ray has no wheel
    suite = load_suite(tiny)
    one = _ates(run_suite(suite, tmp_path / "one", runs=1, jobs=1))
    two = _ates(run_suite(suite, tmp_path / "two", runs=1, jobs=2))
    ray = _ates(run_suite(suite, tmp_path / "ray", runs=1, ray="local"))
    assert one == two == ray and len(one) == 2


def test_a_failed_run_is_recorded_and_the_suite_goes_on(tmp_path, capsys):
    suite = tmp_path / "s.yaml"
    suite.write_text(TINY.replace("runs: 2", "runs: 1") + """
  - name: broken
    preset: synthetic
    overrides: {backend: false, backbone.name: replay}
""")
    assert main(["evaluate", str(suite), "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert "| broken | fail |" in captured.out and "FAILED" in captured.err
    result = json.loads(next((tmp_path / "out" / "runs" / "broken").rglob("result.json")).read_text())
    assert result["error"] and "replay" in result["error"]
    assert (tmp_path / "out" / "table.tex").is_file() and (tmp_path / "out" / "plots" / "summary.png").is_file()
    assert (tmp_path / "out" / "plots" / "loop.png").is_file()


@pytest.mark.parametrize("text, message", [
    ("datasets: [\n  - name: x", "not valid YAML"),
    ("datasets:\n  - {name: gone, root: /no/such/folder}\nconfigurations:\n  - {name: a, preset: synthetic}",
     "root not found"),
    ("datasets:\n  - {name: l, synthetic: {scene: loop}}\nconfigurations:\n  - {name: a, preset: nosuch}",
     "unknown preset 'nosuch'"),
    ("datasets:\n  - {name: l, synthetic: {scene: loop}}\nconfigurations:\n  - {name: a, preset: synthetic, "
     "overrides: {frontend.nosuch: 1}}", "unknown key(s) nosuch"),
])
def test_a_bad_suite_fails_at_once_in_one_line(tmp_path, capsys, text, message):
    suite = tmp_path / "bad.yaml"
    suite.write_text(text)
    out = tmp_path / "out"
    assert main(["evaluate", str(suite), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()  # nothing ran


def test_the_example_suites_are_valid(tmp_path):
    """The paper suites name datasets that are not here (their structure is checked); the offline suite
    loads completely where ../shared/data is present."""
    import yaml

    from vggt_slam_pp.suite import expand

    root = Path(__file__).resolve().parents[1] / "benchmarks" / "suites"
    files = {f.name: f for f in root.glob("*.yaml")}
    assert set(files) >= {"offline.yaml", "paper_kitti.yaml", "paper_tum.yaml", "paper_euroc.yaml"}
    for f in files.values():
        data = yaml.safe_load(f.read_text())
        assert data["datasets"] and data["configurations"], f
    if not (root.parents[1].parent / "shared" / "data").is_dir():
        pytest.skip("../shared/data is not present")
    tasks = expand(load_suite(files["offline.yaml"]), tmp_path)
    assert len({(t.dataset, t.sequence) for t in tasks}) >= 3


def test_sequences_are_found_in_dataset_roots(tmp_path):
    """A folder of sequences (TUM-like sub-folders, Virtual KITTI 2-like nesting, a KITTI odometry root)
    gives each of them; an unknown name fails and lists those present."""
    from vggt_slam_pp.errors import InputError
    from vggt_slam_pp.suite.spec import DatasetSpec, SuiteSpec, sequences_of

    root = tmp_path / "root"
    for name in ("fr1_desk", "fr2_xyz"):
        (root / name).mkdir(parents=True)
        (root / name / "rgb.txt").write_text("# timestamp filename\n")
    (root / "Scene01" / "clone").mkdir(parents=True)
    (root / "Scene01" / "clone" / "rgb.txt").write_text("")
    (root / "notes").mkdir()
    kitti = tmp_path / "dataset" / "sequences"
    for name in ("00", "07"):
        (kitti / name / "image_2").mkdir(parents=True)
    suite = SuiteSpec("s", tmp_path / "s.yaml", 1, (), ())
    assert [n for n, _ in sequences_of(DatasetSpec("tum", root, None), suite)] == ["Scene01/clone", "fr1_desk", "fr2_xyz"]
    assert [n for n, _ in sequences_of(DatasetSpec("kitti", tmp_path / "dataset", ("07",)), suite)] == ["07"]
    with pytest.raises(InputError, match="no sequence 05 .* has 00, 07"):
        sequences_of(DatasetSpec("kitti", tmp_path / "dataset", ("05",)), suite)


def test_ray_is_not_imported_without_ray(tiny, tmp_path):
    import subprocess
    import sys

    code = (f"import sys\nfrom vggt_slam_pp.suite import load_suite, run_suite\n"
            f"run_suite(load_suite({str(tiny)!r}), {str(tmp_path / 'out')!r}, runs=1, jobs=1)\n"
            "assert 'ray' not in sys.modules, 'ray was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_plots_survive_a_suite_without_any_ate(tmp_path):
    from vggt_slam_pp.suite import write_plots

    results = [{"dataset": "d", "sequence": "d", "config": c, "seed": 0, "folder": str(tmp_path / c), "ate": None,
                "error": "RuntimeError: boom"} for c in ("a", "b")]
    assert [p.name for p in write_plots(results, tmp_path)] == ["d.png", "summary.png"]
    assert "fail" in write_tables(results, tmp_path)["md"].read_text()
