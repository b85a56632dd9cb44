"""The HTML report and the 3-D viewer of a run, also loaded in headless Chromium (Debian's ``chromium``,
driven by Playwright; ``.ci/run`` installs it, and the browser tests skip where it is not installed)."""

from __future__ import annotations

import base64
import io
import re
import shutil
import socket

import numpy as np
import pytest

from vggt_slam_pp.cli.main import main
from vggt_slam_pp.viz.report import FIGURES

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A demo-like run with the back-end: a synthetic block loop (300 frames, 240x180), loops closed (at 160x120
    its keyframes hold too few landmarks to judge a lone loop, and no loop there has a partner)."""
    root = tmp_path_factory.mktemp("viz")
    assert main(["demo", "--frames", "300", "--width", "240", "--height", "180", "--out", str(root)]) == 0
    return root / "run"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_run_writes_a_self_contained_report_with_every_figure(finished_run):
    html = (finished_run / "report.html").read_text()
    assert (finished_run / "groundtruth.txt").is_file()  # the run keeps its ground truth for the report
    for fig in FIGURES:
        m = re.search(rf'id="fig-{fig}"[^>]*src="data:image/png;base64,([^"]+)"', html)
        assert m, f"figure {fig} missing"
        from PIL import Image

        w, h = Image.open(io.BytesIO(base64.b64decode(m.group(1)))).size
        assert w > 200 and h > 100, (fig, w, h)
    assert 'id="loop-table"' in html and "accepted" in html and "rejected" in html
    assert "http" not in re.sub(r'src="data:[^"]+"', "", html).split("<pre>")[0]  # nothing fetched from outside


def test_report_command_and_its_errors(finished_run, tmp_path, capsys):
    out = tmp_path / "r.html"
    assert main(["report", str(finished_run), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: not a run folder")


def test_viewer_builds_the_scene_of_a_run(finished_run):
    from vggt_slam_pp.viz.run_folder import load_run
    from vggt_slam_pp.viz.viewer import serve

    serving = serve(finished_run, port=_free_port())
    try:
        names = set(serving.viewer.node_names())
        run = load_run(finished_run)
        for n in run.nodes:
            assert f"/map/submap_{n['id']:06d}" in names
            assert f"/cameras/submap_{n['id']:06d}/kf_000" in names
        for name in ("/trajectory/odometry", "/trajectory/corrected", "/trajectory/ground_truth", "/loops/accepted",
                     "/dem"):
            assert name in names, name
        rejected = [c for c in run.loop_candidates if not c["accepted"]]
        assert rejected and f"/loops/rejected/{rejected[0]['query']:06d}_{rejected[0]['match']:06d}" in names
        v = serving.viewer
        from vggt_slam_pp.dem import GroundPlane
        from vggt_slam_pp.viz.viewer import _wxyz

        rot, R_ground = run.keyframe_rotations(), GroundPlane.from_dict(run.graph["plane"]).R
        for n in run.nodes[:3]:  # every frustum faces as its own keyframe
            for k, f in enumerate(n["frames"]):
                q = np.asarray(v.nodes[f"/cameras/submap_{n['id']:06d}/kf_{k:03d}"].wxyz)
                assert abs(float(q @ _wxyz(R_ground @ rot[f]))) > 1 - 1e-6
        v._show_candidate(rejected[0])  # what a click on the candidate shows
        assert rejected[0]["reason"] in v.gui["candidate_text"].content
        v._set_upto(0)  # the time slider: only the first submap is left
        shown = [sid for sid, sm in v.submaps.items() if sm.handles[0].visible]
        assert shown == [0]
        v._set_upto(max(v.submaps))
        assert "submap_1" in v.gui  # a toggle per submap
        v._set_hidden(1, True)
        assert [sid for sid, sm in v.submaps.items() if not sm.handles[0].visible] == [1]
        v._set_hidden(1, False)
        v._toggle("map", False)
        assert not any(sm.handles[0].visible for sm in v.submaps.values())
    finally:
        serving.stop()


@needs_browser
def test_viewer_renders_in_headless_chromium(finished_run, tmp_path):
    from playwright.sync_api import sync_playwright

    from vggt_slam_pp.viz.viewer import serve

    port = _free_port()
    serving = serve(finished_run, port=port)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1024, "height": 768})
            page.goto(f"http://127.0.0.1:{port}/")
            page.wait_for_selector("canvas", timeout=30_000)
            page.wait_for_timeout(6000)  # the scene streams over the websocket
            shot = tmp_path / "viewer.png"
            page.screenshot(path=str(shot))
            assert page.get_by_text("Layers").count() >= 1  # the GUI came up
            browser.close()
    finally:
        serving.stop()
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB"), float)[:, :700]  # the 3-D canvas, left of the GUI panel
    assert img.std() > 20, img.std()  # not a blank canvas
    assert len(np.unique(img.reshape(-1, 3).astype(np.uint8), axis=0)) > 500  # points, frusta, lines drawn


@needs_browser
def test_report_opens_in_headless_chromium_with_every_figure(finished_run):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page()
        page.goto((finished_run / "report.html").resolve().as_uri())
        sizes = dict(page.evaluate("Array.from(document.images).map(i => [i.id, i.naturalWidth])"))
        rows = page.locator("#loop-table tr").count()
        browser.close()
    for fig in FIGURES:
        assert sizes.get(f"fig-{fig}", 0) > 200, (fig, sizes)
    assert rows > 1


def test_live_viewer_receives_every_submap_and_the_corrected_poses(finished_run, tmp_path):
    """``run(..., viewer=LiveViewer())`` (``run --viewer``): the viewer process draws every submap as it is
    finished and the back-end's pose snapshots, and the run's results are those of a run without it."""
    import json

    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.io.trajectory import read_tum
    from vggt_slam_pp.pipeline import RunConfig, run
    from vggt_slam_pp.viz.live import LiveViewer

    source = open_source(finished_run.parent / "sequence")
    viewer = LiveViewer(port=_free_port())
    report = run(source, RunConfig.preset("synthetic"), tmp_path / "live", viewer=viewer)
    drawn = viewer.close()
    assert drawn is not None and drawn["submaps"] == report["submaps"] and drawn["pose_updates"] >= 1
    assert {"/trajectory/odometry", "/trajectory/corrected", "/map/submap_000000"} <= set(drawn["nodes"])
    assert not viewer.alive()
    # the viewer changes nothing: the same odometry as the demo's run of the same sequence and seed
    config = json.loads((finished_run / "config.json").read_text())
    assert config["backbone"]["seed"] == 0
    a, b = read_tum(tmp_path / "live" / "keyframes_odometry.txt"), read_tum(finished_run / "keyframes_odometry.txt")
    assert np.array_equal(a.poses, b.poses)


def test_height_colours_follow_the_height():
    from vggt_slam_pp.viz.viewer import height_colors

    c = height_colors(np.linspace(0.0, 10.0, 1000)).astype(int)
    assert len(np.unique(c, axis=0)) > 50 and not (c == 255).all(axis=1).any()
    assert np.abs(c[0] - c[-1]).sum() > 100  # ground and tops differ


def test_a_live_viewer_that_died_never_blocks_the_run():
    from vggt_slam_pp.viz.live import LiveViewer

    viewer = LiveViewer(port=_free_port())
    viewer._proc.kill()
    viewer._proc.join(10)
    big = np.zeros((5000, 3), np.float32)  # each message larger than a pipe's buffer
    for i in range(5):
        viewer.submap(i, big, None, np.zeros((2, 3)), [0, 1], np.eye(4))
        viewer.poses({i: np.eye(4)})
    assert viewer.close() is None and not viewer.alive()


def test_the_report_draws_a_long_runs_dem_reduced():
    """A city-scale DEM is drawn as block means at most 1,200 px on its long side (drawing every pixel of a
    1,000-submap run's DEM took the report to about 1 GB); blocks without a height stay empty."""
    from vggt_slam_pp.viz.report import display_dem

    heights = np.full((2500, 5000), np.nan, np.float32)
    heights[:, :2500] = np.arange(2500, dtype=np.float32)[None, :] % 5  # 0 1 2 3 4 along each row
    heights[:100, :5] = 7.0
    small, mpp = display_dem(heights, 0.25)
    assert small.shape == (500, 1000) and mpp == 1.25  # k = 5
    assert np.allclose(small[20:, :500], 2.0) and np.allclose(small[:20, 0], 7.0)  # block means
    assert np.isnan(small[:, 500:]).all()  # nothing seen there
    same, mpp_same = display_dem(heights[:100, :1200], 0.25)
    assert same.shape == (100, 1200) and mpp_same == 0.25  # small enough already: untouched
    odd, _ = display_dem(np.arange(1201 * 3, dtype=np.float32).reshape(1201, 3), 1.0)  # k = 2: a partial last block
    assert odd.shape == (601, 2) and odd[-1, 0] == np.mean([3600, 3601]) and odd[-1, 1] == 3602


def test_a_runs_peak_memory_includes_writing_its_report(tmp_path, monkeypatch):
    """``peak_rss_mb`` in report.json is taken after report.html is written: the report is output writing."""
    import json

    import vggt_slam_pp.viz.report as report_module
    from vggt_slam_pp.resources import rss_mb

    seen = {}
    write = report_module.write_report

    def heavy_report(run_dir, out=None):
        before = json.loads((run_dir / "report.json").read_text())["peak_rss_mb"]  # both processes' peaks so far
        block = np.ones(int((before - rss_mb() + 200) * 2**20) // 8)  # this process alone 200 MiB past it
        seen["rss"], seen["before"] = rss_mb(), before
        del block
        return write(run_dir, out)

    monkeypatch.setattr(report_module, "write_report", heavy_report)
    assert main(["demo", "--frames", "120", "--width", "96", "--height", "72", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert seen["rss"] > seen["before"] + 150 and report["peak_rss_mb"] >= seen["rss"]
