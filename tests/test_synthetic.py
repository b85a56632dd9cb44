"""Synthetic worlds, trajectories and the renderer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vggt_slam_pp.errors import SyntheticError
from vggt_slam_pp.geometry import PinholeCamera, se3_inverse, transform_points
from vggt_slam_pp.io import open_source
from vggt_slam_pp.synthetic import (
    Renderer,
    Solid,
    World,
    block_loop,
    default_camera,
    figure8,
    from_trajectory_file,
    generate_world,
    make_scene,
    write_sequence,
)
from vggt_slam_pp.synthetic.trajectories import look_along


def _single_pose(pos, forward, pitch=0.0):
    return look_along(np.array([pos], float), np.array([forward], float), pitch)[0]


def test_ground_plane_renders_analytic_depth():
    cam = default_camera(80, 60)
    world = World((), "outdoor", 0)
    T = _single_pose([3.0, -2.0, 1.7], [1.0, 0.5, 0.0], pitch=-20.0)
    rgb, depth = Renderer(world, cam, max_depth=200.0).render(T)
    v, u = np.mgrid[0:60, 0:80]
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1) @ T[:3, :3].T
    expected = np.where(rays[..., 2] < 0, -1.7 / np.minimum(rays[..., 2], -1e-12), 0.0)
    expected[expected > 200.0] = 0.0
    np.testing.assert_allclose(depth, expected, rtol=1e-5, atol=1e-5)
    assert (depth == 0).any() and (depth > 0).any()  # horizon in view: sky above it
    assert rgb.shape == (60, 80, 3) and rgb.dtype == np.uint8


def test_box_face_and_ramp_depth():
    cam = default_camera(81, 61)
    box = Solid("building", np.array([12.0, 0.0]), np.array([4.0, 4.0, 3.0]), 0.0, np.ones(3) * 0.5, np.zeros(2))
    T = _single_pose([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    _, depth = Renderer(World((box,), "outdoor", 0), cam).render(T)
    assert depth[30, 40] == pytest.approx(10.0, abs=1e-4)  # front face at x = 10
    # a ramp rising towards +x: height 2 m over 4 m length; a ray straight down onto its middle
    ramp = Solid("ramp", np.array([0.0, 0.0]), np.array([4.0, 2.0, 2.0]), 0.0, np.ones(3), np.zeros(2), ramp=True)
    down = np.eye(4)
    down[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # camera z pointing to -z (world)
    down[:3, 3] = [0.0, 0.0, 5.0]
    _, d2 = Renderer(World((ramp,), "outdoor", 0), cam).render(down)
    assert d2[30, 40] == pytest.approx(5.0 - 1.0, abs=1e-4)  # top is 1 m high at the middle
    assert World((ramp,), "outdoor", 0).height_at(np.array([[1.0, 0.0], [5.0, 0.0]])) == pytest.approx([1.5, 0.0])


def test_depth_reprojects_between_frames():
    scene = make_scene("loop", frames=600, width=160, height=120, seed=3)  # 0.7 m between frames
    r = Renderer(scene.world, scene.camera)
    cam = scene.camera
    checked = 0
    for i in (5, 200, 431):
        j = i + 3
        Ti, Tj = scene.trajectory.poses[i], scene.trajectory.poses[j]
        _, di = r.render(Ti)
        _, dj = r.render(Tj)
        valid = di > 0
        pts_i = cam.unproject_depth(di)[valid]
        pts_j = transform_points(se3_inverse(Tj) @ Ti, pts_i)
        uv = cam.project(pts_j)
        u0, v0 = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (pts_j[:, 2] > 0) & (u0 >= 0) & (u0 < cam.width - 1) & (v0 >= 0) & (v0 < cam.height - 1)
        u0, v0 = u0[inside].astype(int), v0[inside].astype(int)
        z = pts_j[inside, 2]
        # the exact depth at a sub-pixel position lies within its 2x2 neighbourhood of frame j's depths
        quad = np.stack([dj[v0, u0], dj[v0, u0 + 1], dj[v0 + 1, u0], dj[v0 + 1, u0 + 1]], axis=1)
        ok = np.all(quad > 0, axis=1)
        lo, hi = quad[ok].min(axis=1), quad[ok].max(axis=1)
        within = (z[ok] >= lo * (1 - 1e-3)) & (z[ok] <= hi * (1 + 1e-3))
        assert within.mean() > 0.92  # the rest straddle occlusion edges (a larger share at 160x120)
        fx, fy = uv[inside][ok, 0] - u0[ok], uv[inside][ok, 1] - v0[ok]
        bilinear = (quad[ok] @ np.array([1.0, 0, 0, 0]) * (1 - fx) * (1 - fy) + quad[ok][:, 1] * fx * (1 - fy)
                    + quad[ok][:, 2] * (1 - fx) * fy + quad[ok][:, 3] * fx * fy)
        assert np.median(np.abs(bilinear - z[ok]) / z[ok]) < 2e-3
        checked += ok.sum()
    assert checked > 10000


def test_worlds_are_seeded_and_keep_the_path_clear():
    traj = block_loop(200)
    a = generate_world(traj.positions[:, :2], seed=1)
    b = generate_world(traj.positions[:, :2], seed=1)
    c = generate_world(traj.positions[:, :2], seed=2)
    assert len(a.solids) > 30
    assert [s.to_dict() for s in a.solids] == [s.to_dict() for s in b.solids]
    assert [s.to_dict() for s in a.solids] != [s.to_dict() for s in c.solids]
    kinds = {s.kind for s in a.solids}
    assert {"building", "vehicle", "curb", "pole"} <= kinds
    cam_pts = traj.positions
    for s in a.solids:
        assert not s.contains(cam_pts).any()
        assert not s.contains(np.c_[cam_pts[:, :2], np.full(len(cam_pts), 0.1)]).any()


def test_renders_are_deterministic_and_textured():
    scene = make_scene("figure8", frames=50, width=320, height=240, seed=0)
    r = Renderer(scene.world, scene.camera)
    a, da = r.render(scene.trajectory.poses[10])
    b, db = r.render(scene.trajectory.poses[10])
    assert np.array_equal(a, b) and np.array_equal(da, db)
    gray = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=1000, qualityLevel=0.01, minDistance=8)
    assert corners is not None and len(corners) > 150  # enough for Lucas-Kanade keyframing
    assert len(cv2.SIFT_create().detect(gray)) > 100


def test_block_loop_revisits_from_the_opposite_direction():
    traj = block_loop(400)
    P = traj.positions
    fwd = traj.poses[:, :3, 2]
    first, second = np.arange(0, 180), np.arange(220, 400)
    d = np.linalg.norm(P[first, None, :2] - P[None, second, :2], axis=2)
    close = d < 6.0
    assert close.any(axis=1).mean() > 0.8  # most of the first lap is passed again
    i, j = np.nonzero(close)
    heading_dot = np.sum(fwd[first[i]] * fwd[second[j]], axis=1)
    assert np.median(heading_dot) < -0.8  # ... in the opposite direction
    np.testing.assert_allclose(P[:, 2], 1.6)


def test_laps_revisit_the_start_in_the_same_direction():
    from vggt_slam_pp.synthetic import laps

    traj = laps(700, laps=1.4, lane_change=1.0)
    P, fwd = traj.positions, traj.poses[:, :3, 2]
    n_lap = int(700 / 1.4)
    start, again = np.arange(0, n_lap), np.arange(n_lap + 20, 700)
    d = np.linalg.norm(P[again, None, :2] - P[None, start, :2], axis=2)
    j = d.argmin(axis=1)
    assert np.all(d[np.arange(len(again)), j] < 1.6)  # the second lap passes the start again, a lane further out
    assert np.all(d[np.arange(len(again)), j] > 0.5)
    assert np.all(np.sum(fwd[again] * fwd[start[j]], axis=1) > 0.95)  # ... in the same direction
    with pytest.raises(SyntheticError):
        laps(10, laps=0.0)


def test_figure8_crosses_itself():
    traj = figure8(400, size=40.0)
    near = np.nonzero(np.linalg.norm(traj.positions[:, :2], axis=1) < 1.0)[0]
    assert len(near) >= 2 and near.max() - near.min() > 150  # visited twice, far apart in time
    mid = near[np.argmin(np.abs(near - 200))]  # the crossing half-way round (start and end coincide)
    f0, f1 = traj.poses[near[0], :3, 2], traj.poses[mid, :3, 2]
    assert np.sum(f0 * f1) < 0.2  # from a clearly different direction
    steps = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert steps.std() / steps.mean() < 0.02  # constant speed


def test_trajectory_files_drive_the_camera(shared_data):
    kitti = shared_data / "gt_trajectories_only" / "kitti_odometry_poses" / "07.txt"
    traj, style = from_trajectory_file(kitti, 300)
    assert style == "outdoor" and len(traj) == 300
    np.testing.assert_allclose(traj.positions[:, 2], 1.65)  # flattened onto the flat world
    assert traj.path_length() > 600  # KITTI 07 is 695 m
    # the loop closes: the end comes back near the start
    assert np.linalg.norm(traj.positions[-1] - traj.positions[0]) < 15
    tum = shared_data / "gt_trajectories_only" / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz-groundtruth.txt"
    t2, style2 = from_trajectory_file(tum, 50)
    assert style2 == "indoor" and np.ptp(t2.positions[:, 2]) > 0.05  # 3-D motion kept
    with pytest.raises(SyntheticError):
        from_trajectory_file(shared_data / "README.md")


def test_written_sequence_reads_back_through_the_tum_reader(tmp_path):
    scene = make_scene("loop", frames=6, width=96, height=72, seed=5)
    summary = write_sequence(scene, tmp_path / "seq")
    assert summary["frames"] == 6
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.json", "world.json"):
        assert (tmp_path / "seq" / name).is_file()
    src = open_source(tmp_path / "seq")
    assert src.layout == "tum" and len(src) == 6
    assert src.camera == PinholeCamera(scene.camera.fx, scene.camera.fy, scene.camera.cx, scene.camera.cy, 96, 72)
    idx, gt = src.frame_ground_truth()
    assert len(idx) == 6
    np.testing.assert_allclose(gt.poses, scene.trajectory.poses, atol=1e-6)
    rgb, depth = Renderer(scene.world, scene.camera).render(scene.trajectory.poses[2])
    f = src[2]
    assert np.array_equal(f.image, rgb)
    keep = (depth > 0) & (depth < 65535 / 5000)
    np.testing.assert_allclose(f.depth[keep], depth[keep], atol=1.0 / 5000)
    assert np.all(f.depth[depth >= 65535 / 5000] == 0)  # beyond the 16-bit range: unknown
    assert World.load(tmp_path / "seq" / "world.json").solids[0].to_dict() == scene.world.solids[0].to_dict()


def test_trajectory_file_with_repeated_stamps_is_resampled(tmp_path):
    from vggt_slam_pp.io.trajectory import Trajectory, write_trajectory

    base = block_loop(40, length=20, width=14, corner_radius=3, lane_offset=1.0)
    ts = base.timestamps.copy()
    ts[10] = ts[9]  # a repeated stamp, as in TUM fr2/desk's ground truth
    write_trajectory(tmp_path / "t.txt", Trajectory(ts, base.poses), "tum")
    traj, style = from_trajectory_file(tmp_path / "t.txt", 25)
    assert len(traj) == 25 and style == "indoor"
    assert np.all(np.isfinite(traj.poses))


def test_an_interrupted_render_resumes_and_another_scene_starts_over(tmp_path, monkeypatch):
    scene = make_scene("loop", frames=6, width=64, height=48, seed=5)
    write_sequence(scene, tmp_path / "seq")
    files = sorted((tmp_path / "seq" / "rgb").glob("*.png"))
    for p in files[4:]:  # interrupted after 4 frames
        p.unlink()
    (tmp_path / "seq" / "groundtruth.txt").unlink()
    (tmp_path / "seq" / "depth" / files[0].name).write_bytes(b"kept, not rendered again")
    rendered = []
    original = Renderer.render

    def counting(self, T):
        rendered.append(T)
        return original(self, T)

    monkeypatch.setattr(Renderer, "render", counting)
    write_sequence(scene, tmp_path / "seq")
    assert len(rendered) == 3  # the 4th frame (maybe half-written) and the two missing ones
    assert (tmp_path / "seq" / "depth" / files[0].name).read_bytes() == b"kept, not rendered again"
    assert len(open_source(tmp_path / "seq")) == 6 and all((tmp_path / "seq" / "rgb" / p.name).is_file() for p in files)
    rendered.clear()
    other = make_scene("loop", frames=6, width=64, height=48, seed=6)  # another world: nothing is kept
    write_sequence(other, tmp_path / "seq")
    assert len(rendered) == 6
    assert (tmp_path / "seq" / "depth" / files[0].name).read_bytes().startswith(b"\x89PNG")
