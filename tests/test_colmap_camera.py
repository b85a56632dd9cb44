"""The shared camera of uncalibrated COLMAP submaps (frontend/backbones/colmap_camera.py): the full model is
chosen by how well it explains the images, and every model's bounds hold."""

from __future__ import annotations

import numpy as np
import pytest

from vggt_slam_pp.frontend.backbones.colmap_camera import constrained_start, intrinsics_sane

pycolmap = pytest.importorskip("pycolmap")

W, H = 752, 480
# EuRoC's 752 x 480 lens as the equidistant model fits it (about 79 deg across); its OPENCV calibration is
# fx 458.7, k1 -0.283, k2 0.074
WIDE_LENS = ("OPENCV_FISHEYE", [462.0, 461.5, 366.6, 251.4, -0.0035, 0.0352, -0.0654, 0.0426])
# a pinhole with mild barrel distortion, in the OPENCV model
NARROW_LENS = ("OPENCV", [460.0, 459.0, 370.0, 245.0, -0.08, 0.01, 0.0, 0.0])
TURN_DEG = 8.0  # per camera: 88 deg over the twelve (EuRoC's first submap turns 87 deg)


def _reconstruction(lens, seed=0, noise_px=0.3):
    """Twelve cameras on an arc (1 m apart, turning ``TURN_DEG`` each, pitching up to 4 deg) looking into a box of points, seen through
    ``lens`` (keypoints = the lens's projections plus Gaussian noise); the reconstruction holds the true poses and
    points and, as its camera, a first RADIAL guess (f 3 % long, no distortion), as structure from motion starts."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    true_cam = pycolmap.Camera(model=lens[0], width=W, height=H, params=lens[1], camera_id=1)
    points = np.column_stack([rng.uniform(-10, 22, 6000), rng.uniform(-6, 6, 6000), rng.uniform(4, 16, 6000)])
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="RADIAL", width=W, height=H,
                                                    params=[1.03 * lens[1][0], W / 2, H / 2, 0.0, 0.0], camera_id=1))
    seen = {}
    for i in range(12):
        R = Rotation.from_euler("yx", [-TURN_DEG * i, 4.0 * np.sin(i)], degrees=True).as_matrix()
        t = -R @ np.array([1.0 * i, 0.0, 0.0])
        p = points @ R.T + t
        front = p[:, 2] > 0.5
        uv = np.full((len(points), 2), -1.0)
        uv[front] = true_cam.img_from_cam(p[front]) + rng.normal(0, noise_px, (front.sum(), 2))
        ok = front & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{i:08d}.png", keypoints=uv, camera_id=1,
                                                        image_id=i + 1),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        seen[i] = ok
    for j, X in enumerate(points):
        obs = [i for i in range(12) if seen[i][j]]
        if len(obs) >= 2:
            track = pycolmap.Track()
            for i in obs:
                track.add_element(i + 1, j)
            rec.add_point3D(X, track)
    return rec


@pytest.mark.parametrize(("lens", "model"), [(WIDE_LENS, "OPENCV_FISHEYE"), (NARROW_LENS, "OPENCV")])
def test_the_full_camera_model_is_the_one_that_explains_the_images(lens, model, caplog):
    """Stage 1 (RADIAL) and stage 2 as the backbone runs them. Seen through a wide lens that the polynomial in the
    undistorted radius does not fit at its edges, the equidistant model is chosen, and its focal length is right
    where OPENCV's comes out long (on EuRoC: 2.6 % against 0.7 %); through a pinhole with mild distortion, which
    both models fit, OPENCV stays."""
    from vggt_slam_pp.frontend.backbones.colmap import ColmapBackbone

    caplog.set_level("INFO", logger="vggt_slam_pp.frontend.backbones.colmap")
    backbone = ColmapBackbone(calibrated=False, keep_features=False)
    rec = _reconstruction(lens)
    backbone._refine_camera(rec, refine_principal_point=False)  # stage 1
    assert next(iter(rec.cameras.values())).model.name == "RADIAL"
    f_stage1 = float(next(iter(rec.cameras.values())).params[0])
    full = backbone._full_model(rec)
    assert next(iter(rec.cameras.values())).model.name == "RADIAL"  # the input is left as it was
    assert "OPENCV 0." in caplog.text  # both families were tried; through the pinhole, the equidistant one fits
    # its constrained model worse than RADIAL does, and goes no further
    assert ("OPENCV_FISHEYE 0." if model == "OPENCV_FISHEYE" else "RADIAL_FISHEYE refinement of the camera is not kept"
            ) in caplog.text
    cam = next(iter(full.cameras.values()))
    assert cam.model.name == model
    f_true = 0.5 * (lens[1][0] + lens[1][1])
    assert abs(0.5 * (cam.params[0] + cam.params[1]) / f_true - 1) < 0.005, (cam.params, f_true)
    assert intrinsics_sane(cam.params, W, H, model) == ""
    if model == "OPENCV_FISHEYE":
        assert f_stage1 > 1.04 * f_true  # what the polynomial in r made of this lens


def test_a_simple_radial_estimate_is_refined_too():
    """The constrained estimate may also come with one radial term (``estimate_model="SIMPLE_RADIAL"``)."""
    from vggt_slam_pp.frontend.backbones.colmap import ColmapBackbone

    backbone = ColmapBackbone(calibrated=False, keep_features=False, estimate_model="SIMPLE_RADIAL")
    rec = _reconstruction(NARROW_LENS)
    cam = next(iter(rec.cameras.values()))
    cam.model, cam.params = "SIMPLE_RADIAL", [cam.params[0], W / 2, H / 2, 0.0]
    backbone._refine_camera(rec, refine_principal_point=False)
    full = backbone._full_model(rec)
    params = next(iter(full.cameras.values())).params
    assert next(iter(full.cameras.values())).model.name == "OPENCV" and abs(params[0] / NARROW_LENS[1][0] - 1) < 0.01


def test_the_equidistant_start_has_the_radial_estimates_projection():
    """The two equidistant terms fitted to a RADIAL camera project the image's rays near where it does; a
    pinhole gives tan's series (1/3, 2/15, ...)."""
    f, cx, cy, k1, k2 = 466.3, 376.0, 240.0, -0.274, 0.0667
    params = constrained_start("RADIAL_FISHEYE", f, cx, cy, k1, k2, W, H)
    radial = pycolmap.Camera(model="RADIAL", width=W, height=H, params=[f, cx, cy, k1, k2])
    fisheye = pycolmap.Camera(model="RADIAL_FISHEYE", width=W, height=H, params=params)
    grid = np.stack(np.meshgrid(np.linspace(0, W - 1, 20), np.linspace(0, H - 1, 14)), -1).reshape(-1, 2)
    rays = radial.cam_from_img(grid)
    back = fisheye.img_from_cam(np.column_stack([rays, np.ones(len(rays))]))
    miss = np.linalg.norm(back - grid, axis=1)
    assert np.median(miss) < 2.0 and miss.max() < 6.0, miss  # a start for the bundle adjustment (corners 446 px out)
    pinhole = constrained_start("RADIAL_FISHEYE", 400.0, 160.0, 120.0, 0.0, 0.0, 320, 240)
    np.testing.assert_allclose(pinhole[3:5], [1 / 3, 2 / 15], atol=0.03)


def test_intrinsics_of_every_model_have_bounds():
    assert intrinsics_sane(WIDE_LENS[1], W, H, "OPENCV_FISHEYE") == ""
    assert "out of bounds" in intrinsics_sane([462, 462, 376, 240, 0.0, 0.0, 1.5, 0.0], W, H, "OPENCV_FISHEYE")
    # a radial mapping that turns back before the image's corners: no real lens does that
    assert "folds back" in intrinsics_sane([460, 460, 376, 240, -0.6, 0.0, 0.0, 0.0], W, H)
    assert "folds back" in intrinsics_sane([460, 460, 376, 240, -0.4, 0.0, 0.0, 0.0], W, H, "OPENCV_FISHEYE")
    assert intrinsics_sane([460, 460, 160, 100, -0.6, 0.0, 0.0, 0.0], 320, 200) == ""  # a narrow image's corners
