"""The COLMAP front-end on real images (EuRoC MH_05 excerpt): no degraded odometry edge, the odometry
ATE within what `bench frontend` measured (session 10, 5 seeds: uncalibrated worst 0.085 m, calibrated
worst 0.065 m; issue 17 asks 0.08 / 0.05, not met yet), and the back-end (on by default) leaves the
trajectory no worse than odometry (there is no loop to close).

Slow (about a minute per run on 2 cores): ``python -m pytest -m slow tests/test_frontend_euroc.py``.
"""

from __future__ import annotations

import pytest

from vggt_slam_pp.io import open_source
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run


@pytest.mark.slow
@pytest.mark.parametrize(("calibrated", "target"), [(False, 0.09), (True, 0.07)])
def test_euroc_colmap_odometry_ate(shared_data, tmp_path, calibrated, target):
    source = open_source(shared_data / "euroc_mh05_sample")
    report = run(source, RunConfig(backbone=BackboneConfig(name="colmap"), calibrated=calibrated), tmp_path)
    assert report["error"] is None and report["frames_processed"] == 585
    assert not any(e["degraded"] for e in report["edges"])
    assert report["ate_rmse_odometry"] <= target, report["ate_rmse_odometry"]
    assert report["loops_accepted"] == 0
    assert report["ate_rmse"] <= report["ate_rmse_odometry"] + 1e-3, (report["ate_rmse"], report["ate_rmse_odometry"])
