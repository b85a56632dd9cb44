"""The COLMAP front-end on real images (EuRoC MH_05 excerpt): no degraded odometry edge, the odometry
ATE within issue 17's medians (0.06 m uncalibrated, 0.04 m calibrated; `bench frontend`, session 39: 0.033 m
both), the uncalibrated camera in the equidistant model with the focal length within 1.5 % of the dataset's
calibration (458.7 px; the polynomial model came out 2.4 % long), and the back-end (on by default) leaves the
trajectory no worse than odometry (there is no loop to close).

Slow (about five minutes per run on 2 cores): ``python -m pytest -m slow tests/test_frontend_euroc.py``.
"""

from __future__ import annotations

import pytest

from vggt_slam_pp.io import open_source
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run


@pytest.mark.slow
@pytest.mark.parametrize(("calibrated", "target"), [(False, 0.06), (True, 0.04)])
def test_euroc_colmap_odometry_ate(shared_data, tmp_path, calibrated, target):
    source = open_source(shared_data / "euroc_mh05_sample")
    report = run(source, RunConfig(backbone=BackboneConfig(name="colmap"), calibrated=calibrated), tmp_path)
    assert report["error"] is None and report["frames_processed"] == 585
    assert not any(e["degraded"] for e in report["edges"])
    assert report["ate_rmse_odometry"] <= target, report["ate_rmse_odometry"]
    assert report["loops_accepted"] == 0
    if not calibrated:
        camera = report["camera"]
        assert camera["model"] == "OPENCV_FISHEYE" and abs(0.5 * sum(camera["params"][:2]) / 458.0 - 1) < 0.015
    assert report["ate_rmse"] <= report["ate_rmse_odometry"] + 1e-3, (report["ate_rmse"], report["ate_rmse_odometry"])
