"""The joint link of two COLMAP submaps (frontend/backbones/colmap_joint.py) on synthetic reconstructions
with a known relative pose."""

from __future__ import annotations

import numpy as np
import pytest

from vggt_slam_pp.frontend.backbones.colmap_joint import (
    FORWARD_MOTION_COS,
    forward_motion,
    joint_link,
    placement,
)
from vggt_slam_pp.geometry import make_sim3, sim3_inverse

pycolmap = pytest.importorskip("pycolmap")

W, H, F = 640, 480, 500.0


def _rotation(axis, degrees: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def _scene(n_images: int = 20, seed: int = 0):
    """Cameras (cam_from_world [n,4,4]) moving 0.5 m per image along x and turning slowly, looking at +z,
    and 3-D points in front of them."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(n_images):
        R = _rotation([0, 1, 0], 2.0 * i)
        c = np.array([0.5 * i, 0.05 * np.sin(i), 0.0])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ c
        poses.append(T)
    points = np.column_stack([rng.uniform(-6, 16, 3000), rng.uniform(-3, 3, 3000), rng.uniform(6, 14, 3000)])
    return np.array(poses), points


def _project(T: np.ndarray, points: np.ndarray):
    """Pixels and visibility of every point in a camera [N,2], [N]."""
    p = points @ T[:3, :3].T + T[:3, 3]
    uv = F * p[:, :2] / p[:, 2:3] + [W / 2, H / 2]
    ok = (p[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    return uv, ok


def _reconstruction(poses, points, images: range, T_rec_world: np.ndarray, bent: dict[int, np.ndarray],
                    focal: float = F):
    """A pycolmap reconstruction of ``images`` in the frame ``T_rec_world`` (Sim(3)); every image's keypoints are
    its projections of all points (the same keypoints in any reconstruction holding it); ``bent``: image ->
    a rigid perturbation applied to its pose; ``focal``: the reconstruction's own estimate of the camera."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H,
                                                    params=[focal, focal, W / 2, H / 2], camera_id=1))
    seen = {}
    for i in images:
        uv, ok = _project(poses[i], points)
        T = poses[i] @ sim3_inverse(T_rec_world)
        T[:3, :] /= np.cbrt(np.linalg.det(T[:3, :3]))
        T = bent.get(i, np.eye(4)) @ T
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{i:08d}.png", keypoints=uv, camera_id=1,
                                                        image_id=i + 1),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3]))
        seen[i] = ok
    for j, X in enumerate(points):
        obs = [i for i in images if seen[i][j]]
        if len(obs) >= 2:
            track = pycolmap.Track()
            for i in obs:
                track.add_element(i + 1, j)
            rec.add_point3D(T_rec_world[:3, :3] @ X + T_rec_world[:3, 3], track)
    return rec


def _poses(rec) -> dict[str, np.ndarray]:
    return {im.name: np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]) for im in rec.images.values()}


def _error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(scale error, translation error) of a Sim(3) link against the truth."""
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    s_true = np.cbrt(np.linalg.det(T_true[:3, :3]))
    return abs(s / s_true - 1.0), float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]))


def test_placement_recovers_a_similarity():
    poses, _ = _scene()
    S = make_sim3(2.5, _rotation([1, 2, 3], 40.0), np.array([1.0, -2.0, 0.5]))  # T_to_from
    frm = {str(i): T for i, T in enumerate(poses)}
    to = {}
    for name, T in frm.items():  # the same cameras in frame "to": cam_from_to = cam_from_from . S^-1, made rigid
        U = T @ sim3_inverse(S)
        U[:3, :] /= np.cbrt(np.linalg.det(U[:3, :3]))
        to[name] = U
    np.testing.assert_allclose(placement(frm, to), S, atol=1e-9)
    assert placement({"a": poses[0]}, {"a": poses[0]}) is None  # one camera does not place a frame


def _noise(rng, images, degrees: float, metres: float) -> dict[int, np.ndarray]:
    out = {}
    for i in images:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _rotation(rng.normal(size=3), degrees), rng.normal(scale=metres, size=3)
        out[i] = T
    return out


def test_the_joint_link_of_exact_reconstructions_is_exact():
    """Two reconstructions in frames 2.5x apart in scale and 30 deg in rotation are joined and linked exactly."""
    poses, points = _scene()
    T_curr_world = make_sim3(0.4, _rotation([0, 0, 1], 30.0), np.array([2.0, 1.0, -1.0]))
    prev = _reconstruction(poses, points, range(0, 12), np.eye(4), {})
    curr = _reconstruction(poses, points, range(8, 20), T_curr_world, {})
    T, residual, relative = joint_link([(prev, None), (curr, None)])
    np.testing.assert_allclose(T, sim3_inverse(T_curr_world), atol=1e-6)
    assert residual < 1e-6 and relative < 1e-6  # each submap's cameras sit exactly on the joint model


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_joint_link_places_each_submap_by_all_its_cameras(seed):
    """The four shared keyframes are the least constrained cameras of both submaps (the previous one's end, the
    current one's start): with their poses off by 1 deg and 0.1 m in each reconstruction, a link through them
    alone inherits the errors of both; the joint link places each submap by all twelve of its cameras."""
    rng = np.random.default_rng(seed)
    poses, points = _scene(seed=seed)
    T_curr_world = make_sim3(0.4, _rotation([0, 0, 1], 30.0), np.array([2.0, 1.0, -1.0]))
    prev = _reconstruction(poses, points, range(0, 12), np.eye(4), _noise(rng, range(8, 12), 1.0, 0.1))
    curr = _reconstruction(poses, points, range(8, 20), T_curr_world, _noise(rng, range(8, 12), 1.0, 0.1))
    T_true = sim3_inverse(T_curr_world)  # T_prevworld_currworld

    own_prev, own_curr = _poses(prev), _poses(curr)
    shared = [n for n in own_curr if n in own_prev]
    through_shared = placement({n: own_curr[n] for n in shared}, {n: own_prev[n] for n in shared})
    joined = joint_link([(prev, None), (curr, None)])
    assert joined is not None
    joint, residual, relative = joined
    assert 0.02 < residual < 0.5  # the noisy cameras (0.1 m per axis) are off the joint model (prev units: metres)
    assert 0.005 < relative < 0.2  # of the cameras' spread (about 1.7 m)
    s_shared, t_shared = _error(through_shared, T_true)
    s_joint, t_joint = _error(joint, T_true)
    assert t_joint < 0.5 * t_shared and s_joint < max(0.5 * s_shared, 0.005), (s_joint, t_joint, s_shared, t_shared)


def test_the_joint_link_is_refused_when_a_shared_image_has_other_features():
    poses, points = _scene()
    prev = _reconstruction(poses, points, range(0, 12), np.eye(4), {})
    curr = _reconstruction(poses, points[::-1].copy(), range(8, 20), np.eye(4), {})  # keypoints in another order
    assert joint_link([(prev, None), (curr, None)]) is None


def test_submaps_with_different_cameras_are_not_joined():
    """A held camera refined on a later submap: a shared image would be seen through two cameras."""
    poses, points = _scene()
    prev = _reconstruction(poses, points, range(0, 12), np.eye(4), {})
    curr = _reconstruction(poses, points, range(8, 20), np.eye(4), {}, focal=1.03 * F)
    assert joint_link([(prev, None), (curr, None)]) is None
    assert joint_link([(prev, None), (_reconstruction(poses, points, range(8, 20), np.eye(4), {}), None)]) is not None


def test_forward_motion_is_told_from_sideways_motion():
    """``auto`` links by the joint adjustment unless the cameras move along their optical axes."""
    poses, points = _scene()  # moving along x, looking along z (turning 2 deg per image)
    sideways = _reconstruction(poses, points, range(0, 12), np.eye(4), {})
    ahead_poses = poses.copy()
    for i, T in enumerate(ahead_poses):  # the same cameras, now stepping along their own optical axis
        c = np.array([0.0, 0.0, 0.5 * i])
        T[:3, :3], T[:3, 3] = np.eye(3), -c
    ahead = _reconstruction(ahead_poses, points + [0.0, 0.0, 8.0], range(0, 12), np.eye(4), {})
    assert forward_motion([sideways]) < 0.2 < FORWARD_MOTION_COS < forward_motion([ahead]) <= 1.0
    # only the images named are used
    assert forward_motion([sideways, ahead], [None, set()]) == forward_motion([sideways])
