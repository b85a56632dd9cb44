"""Geometry core, tested by properties."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import random_sim3
from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.geometry import (
    PinholeCamera,
    decompose_sim3,
    estimate_sim3_robust,
    hat,
    make_sim3,
    matrix_to_quat,
    pose_from_tq,
    pose_to_tq,
    quat_to_matrix,
    reorder_quat,
    rotation_angle,
    se3_exp,
    se3_inverse,
    se3_log,
    sim3_covariance_at_origin,
    sim3_exp,
    sim3_inverse,
    sim3_log,
    so3_exp,
    so3_log,
    transform_points,
    umeyama,
)


def _random_xi(rng, n, scale=True):
    xi = rng.normal(size=(n, 7))
    w = xi[:, :3]
    ang = rng.uniform(0, np.pi * 0.98, n)
    xi[:, :3] = w / np.linalg.norm(w, axis=1, keepdims=True) * ang[:, None]
    xi[:, 6] = rng.uniform(-1.5, 1.5, n) if scale else 0.0
    return xi


def test_hat_is_cross_product(rng):
    a, b = rng.normal(size=(2, 10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", hat(a), b), np.cross(a, b), atol=1e-12)


def test_sim3_exp_log_round_trip(rng):
    xi = _random_xi(rng, 200)
    np.testing.assert_allclose(sim3_log(sim3_exp(xi)), xi, atol=1e-9)


def test_sim3_exp_log_near_identity_and_pure_scale(rng):
    tiny = rng.normal(scale=1e-9, size=(20, 7))
    np.testing.assert_allclose(sim3_log(sim3_exp(tiny)), tiny, atol=1e-15)
    pure_scale = np.zeros((3, 7))
    pure_scale[:, 6] = [-2.0, 0.5, 3.0]
    pure_scale[:, 3:6] = [[1, 2, 3], [0, 0, 1], [-1, 0, 0]]
    T = sim3_exp(pure_scale)
    np.testing.assert_allclose(decompose_sim3(T)[0], np.exp(pure_scale[:, 6]))
    np.testing.assert_allclose(sim3_log(T), pure_scale, atol=1e-12)


def test_a_perturbation_about_a_point_is_moved_to_the_origin_exactly(rng):
    # T_c exp(eta) T_c^-1 (a rotation, scale and shift about the point c) equals exp(A eta) about the origin, and
    # the covariance moves with the same A
    c = rng.normal(scale=5.0, size=3)
    T_c = make_sim3(1.0, np.eye(3), c)
    A = sim3_covariance_at_origin(np.eye(7), c)  # A A^T for the identity covariance
    B = np.eye(7)
    B[3:6, 0:3], B[3:6, 6] = hat(c), -c
    for eta in _random_xi(rng, 20) * 0.3:
        xi = sim3_log(T_c @ sim3_exp(eta) @ sim3_inverse(T_c))
        np.testing.assert_allclose(xi, B @ eta, atol=1e-9)
    np.testing.assert_allclose(A, B @ B.T, atol=1e-12)
    # a rotation about c leaves c where it was: its perturbation at the origin moves the origin by the lever arm
    eta = np.r_[0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.0]
    xi = B @ eta
    assert np.linalg.norm(xi[3:6]) == pytest.approx(0.01 * np.linalg.norm(np.cross([0, 0, 1.0], c)), rel=1e-12)
    np.testing.assert_allclose(transform_points(sim3_exp(xi), c[None])[0], c, atol=1e-3 * np.linalg.norm(c))


def test_se3_exp_log_round_trip_and_rigidity(rng):
    xi = _random_xi(rng, 100, scale=False)[:, :6]
    T = se3_exp(xi)
    np.testing.assert_allclose(np.linalg.det(T[:, :3, :3]), 1.0, atol=1e-12)
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-9)


def test_exp_matches_closed_form_rotation(rng):
    w = _random_xi(rng, 50)[:, :3]
    T = sim3_exp(np.c_[w, np.zeros((50, 4))])
    np.testing.assert_allclose(T[:, :3, :3], so3_exp(w), atol=1e-12)
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-9)


def test_inverse_and_composition(rng):
    A = sim3_exp(_random_xi(rng, 50))
    B = sim3_exp(_random_xi(rng, 50))
    eye = np.broadcast_to(np.eye(4), A.shape)
    np.testing.assert_allclose(A @ sim3_inverse(A), eye, atol=1e-9)
    np.testing.assert_allclose(sim3_inverse(A @ B), sim3_inverse(B) @ sim3_inverse(A), atol=1e-9)
    np.testing.assert_allclose(sim3_inverse(A), np.linalg.inv(A), atol=1e-9)
    R = se3_exp(_random_xi(rng, 50, scale=False)[:, :6])
    np.testing.assert_allclose(se3_inverse(R), np.linalg.inv(R), atol=1e-9)
    # composition acts on points like applying one after the other
    p = rng.normal(size=(50, 7, 3))
    np.testing.assert_allclose(transform_points(A @ B, p), transform_points(A, transform_points(B, p)), atol=1e-9)


def test_make_decompose_round_trip(rng):
    T = random_sim3(rng)
    s, R, t = decompose_sim3(T)
    np.testing.assert_allclose(make_sim3(s, R, t), T, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    with pytest.raises(GeometryError):
        decompose_sim3(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_quaternion_orders(rng):
    # 90 degrees about z: xyzw = (0, 0, sin45, cos45), wxyz = (cos45, 0, 0, sin45)
    c = np.sqrt(0.5)
    Rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(quat_to_matrix(np.array([0, 0, c, c]), "xyzw"), Rz, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(np.array([c, 0, 0, c]), "wxyz"), Rz, atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat(Rz, "wxyz"), [c, 0, 0, c], atol=1e-12)
    R = so3_exp(_random_xi(rng, 30)[:, :3])
    for order in ("xyzw", "wxyz"):
        q = matrix_to_quat(R, order)
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(q, order), R, atol=1e-12)
    np.testing.assert_allclose(reorder_quat(matrix_to_quat(R, "xyzw"), "xyzw", "wxyz"), matrix_to_quat(R, "wxyz"))
    T = se3_exp(_random_xi(rng, 5, scale=False)[:, :6])
    t, q = pose_to_tq(T, "wxyz")
    np.testing.assert_allclose(pose_from_tq(t, q, "wxyz"), T, atol=1e-12)
    with pytest.raises(GeometryError):
        quat_to_matrix(np.zeros(4), "xyzw")


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_recovers_random_sim3_exactly(seed):
    rng = np.random.default_rng(seed)
    T = random_sim3(rng)
    src = rng.normal(scale=5.0, size=(50, 3))
    dst = transform_points(T, src)
    np.testing.assert_allclose(umeyama(src, dst), T, atol=1e-9)


def test_umeyama_without_scale_and_weights(rng):
    T = random_sim3(rng, with_scale=False)
    src = rng.normal(size=(30, 3))
    dst = transform_points(T, src)
    np.testing.assert_allclose(umeyama(src, dst, with_scale=False), T, atol=1e-9)
    # zero weight on a corrupted pair ignores it
    dst_bad = dst.copy()
    dst_bad[0] += 100.0
    w = np.ones(30)
    w[0] = 0.0
    np.testing.assert_allclose(umeyama(src, dst_bad, with_scale=False, weights=w), T, atol=1e-9)


def test_umeyama_degenerate_inputs():
    line = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    with pytest.raises(GeometryError, match="collinear"):
        umeyama(line, line)
    with pytest.raises(GeometryError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    bad = np.ones((5, 3))
    bad[0, 0] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        umeyama(bad, bad)


@pytest.mark.parametrize("seed", range(3))
def test_robust_sim3_with_30_percent_outliers(seed):
    rng = np.random.default_rng(seed)
    T = random_sim3(rng)
    n = 400
    src = rng.uniform(-5, 5, size=(n, 3))
    dst = transform_points(T, src) + rng.normal(scale=1e-3, size=(n, 3))
    out = rng.choice(n, size=int(0.3 * n), replace=False)
    dst[out] = rng.uniform(-30, 30, size=(len(out), 3))
    res = estimate_sim3_robust(src, dst, threshold=0.05, seed=seed)
    s_true = decompose_sim3(T)[0]
    s_est, R_est, _t_est = decompose_sim3(res.T_dst_src)
    assert abs(s_est / s_true - 1) < 1e-3
    assert rotation_angle(R_est.T @ decompose_sim3(T)[1]) < 1e-3
    truth = np.ones(n, bool)
    truth[out] = False
    assert np.mean(res.inliers == truth) > 0.99
    assert abs(res.inlier_ratio - 0.7) < 0.02
    assert res.rmse < 5e-3
    # plain Umeyama is ruined by the same outliers: its error on the clean pairs is far larger
    clean_err = lambda T_: np.linalg.norm(transform_points(T_, src[truth]) - dst[truth], axis=1).mean()  # noqa: E731
    assert clean_err(umeyama(src, dst)) > 100 * clean_err(res.T_dst_src)


def test_robust_sim3_relative_threshold_is_scale_free(rng):
    T = random_sim3(rng)
    src = rng.uniform(-1, 1, size=(200, 3))
    dst = transform_points(T, src)
    dst[:40] += rng.normal(scale=5.0, size=(40, 3))
    a = estimate_sim3_robust(src, dst)
    b = estimate_sim3_robust(src, dst * 1000.0)
    assert np.array_equal(a.inliers, b.inliers)
    np.testing.assert_allclose(decompose_sim3(b.T_dst_src)[0], 1000.0 * decompose_sim3(a.T_dst_src)[0], rtol=1e-9)


def test_pinhole_project_unproject_round_trip(rng):
    cam = PinholeCamera(458.654, 457.296, 367.215, 248.375, 752, 480)
    pts = np.c_[rng.uniform(-2, 2, (100, 2)), rng.uniform(1, 10, 100)]
    uv = cam.project(pts)
    np.testing.assert_allclose(cam.unproject(uv, pts[:, 2]), pts, atol=1e-9)
    behind = cam.project(np.array([[0.0, 0.0, -1.0]]))
    assert np.all(np.isnan(behind))


def test_distorted_camera_round_trip_matches_opencv(rng):
    import cv2

    dist = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)  # EuRoC cam0
    cam = PinholeCamera(458.654, 457.296, 367.215, 248.375, 752, 480, dist)
    uv = np.c_[rng.uniform(0, 751, 200), rng.uniform(0, 479, 200)]
    depth = rng.uniform(0.5, 20, 200)
    pts = cam.unproject(uv, depth)
    np.testing.assert_allclose(pts[:, 2], depth)
    np.testing.assert_allclose(cam.project(pts), uv, atol=1e-6)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, np.array(dist))
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-9)
    # distortion really moves corner pixels
    assert np.abs(cam.without_distortion().project(pts) - uv).max() > 10


def test_camera_scaling_and_depth_unprojection():
    cam = PinholeCamera(100.0, 100.0, 31.5, 23.5, 64, 48)
    half = cam.scaled(32, 24)
    assert (half.fx, half.cx, half.cy) == (50.0, 15.5, 11.5)
    depth = np.full((48, 64), 2.0)
    pm = cam.unproject_depth(depth)
    assert pm.shape == (48, 64, 3)
    np.testing.assert_allclose(cam.project(pm.reshape(-1, 3)).reshape(48, 64, 2)[5, 7], [7, 5], atol=1e-9)
    with pytest.raises(GeometryError):
        PinholeCamera(-1, 1, 0, 0, 10, 10)
