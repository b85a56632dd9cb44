"""ATE / RPE: known answers and a cross-check against evo (test-only dependency)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from conftest import random_sim3, random_trajectory
from vggt_slam_pp.errors import EvaluationError
from vggt_slam_pp.eval import associate, compute_ate, compute_rpe
from vggt_slam_pp.eval.metrics import best_time_offset, submaps_placed_best
from vggt_slam_pp.geometry import decompose_sim3, se3_exp
from vggt_slam_pp.io.trajectory import Trajectory


def _noisy_estimate(rng, gt: Trajectory, T: np.ndarray, noise: float = 0.05, every: int = 1, jitter: float = 0.003):
    """gt moved by the similarity ``T`` (world change), perturbed, on a sub-sampled, jittered clock."""
    idx = np.arange(0, len(gt), every)
    poses = gt.poses[idx] @ se3_exp(rng.normal(scale=noise, size=(len(idx), 6)))
    s, R, t = decompose_sim3(T)
    moved = poses.copy()
    moved[:, :3, :3] = R @ poses[:, :3, :3]
    moved[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    return Trajectory(gt.timestamps[idx] + rng.uniform(-jitter, jitter, len(idx)), moved)


def test_ate_is_zero_for_a_similar_copy(rng):
    gt = random_trajectory(rng)
    T = random_sim3(rng)
    est = _noisy_estimate(rng, gt, T, noise=0.0, jitter=0.0)
    res = compute_ate(gt, est, "sim3")
    assert res.rmse < 1e-9 and res.n_matched == len(gt)
    assert abs(res.scale - 1.0 / decompose_sim3(T)[0]) < 1e-9
    # without scale correction the same estimate is far off
    assert compute_ate(gt, est, "se3").rmse > 0.1
    rpe = compute_rpe(gt, est, 1, "sim3")
    assert rpe.trans_rmse < 1e-9 and rpe.rot_rmse_deg < 1e-6


@pytest.mark.parametrize("align", ["sim3", "se3", "none"])
def test_ate_and_rpe_match_evo(rng, align):
    from evo.core import metrics, sync
    from evo.core import trajectory as evo_traj

    from vggt_slam_pp.geometry import matrix_to_quat

    gt = random_trajectory(rng, 300)
    est = _noisy_estimate(rng, gt, random_sim3(rng, with_scale=(align == "sim3")), every=2)

    def to_evo(tr):
        return evo_traj.PoseTrajectory3D(positions_xyz=tr.positions.copy(),
                                         orientations_quat_wxyz=matrix_to_quat(tr.poses[:, :3, :3], "wxyz"),
                                         timestamps=tr.timestamps.copy())

    ref_e, est_e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.01)
    if align != "none":
        est_e.align(ref_e, correct_scale=(align == "sim3"))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref_e, copy.deepcopy(est_e)))
    stats = ape.get_all_statistics()
    ours = compute_ate(gt, est, align, max_diff=0.01)
    assert ours.n_matched == len(ref_e.timestamps)
    for key in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        assert getattr(ours, key) == pytest.approx(stats[key], rel=1e-6), key
    for delta in (1, 5):
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta, delta_unit=metrics.Unit.frames)
        rpe_t.process_data((ref_e, est_e))
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=delta, delta_unit=metrics.Unit.frames)
        rpe_r.process_data((ref_e, est_e))
        r = compute_rpe(gt, est, delta, align, max_diff=0.01)
        assert r.trans_rmse == pytest.approx(rpe_t.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
        assert r.trans_max == pytest.approx(rpe_t.get_statistic(metrics.StatisticsType.max), rel=1e-6)
        assert r.rot_rmse_deg == pytest.approx(rpe_r.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)


def test_association_matches_evo_with_offset(rng):
    from evo.core import sync

    a = np.sort(rng.uniform(0, 10, 400))
    b = np.sort(rng.uniform(0, 10, 250)) + 0.3
    for offset in (0.0, -0.3):
        i_ref, i_est = associate(Trajectory(a, np.tile(np.eye(4), (400, 1, 1))),
                                 Trajectory(b, np.tile(np.eye(4), (250, 1, 1))), max_diff=0.02, offset=offset)
        # evo matches each stamp of the shorter list (here the estimate) to the nearest of the longer
        ev_short, ev_long = sync.matching_time_indices(b + offset, a, max_diff=0.02)
        np.testing.assert_array_equal(i_est, ev_short)
        np.testing.assert_array_equal(i_ref, ev_long)


def test_no_overlap_in_time_is_an_error(rng):
    gt = random_trajectory(rng, 50, t0=0.0)
    est = random_trajectory(rng, 50, t0=1000.0)
    with pytest.raises(EvaluationError, match="no timestamps match"):
        compute_ate(gt, est)


def test_kitti_rows_match_by_index_only_with_equal_lengths(rng):
    gt = random_trajectory(rng, 20)
    rows = Trajectory(np.arange(20.0), gt.poses, has_timestamps=False)
    assert compute_ate(rows, rows).rmse < 1e-12
    with pytest.raises(EvaluationError, match="no timestamps"):
        compute_ate(gt, rows)
    with pytest.raises(EvaluationError, match="equal lengths"):
        compute_ate(rows, rows.subset(np.arange(10)))


def test_best_time_offset_finds_a_clock_shift_and_only_where_the_reference_is_dense(rng):
    """An estimate whose camera clock runs 40 ms behind a 200 Hz ground truth (its pose at time t is the truth's
    at t + 0.04): the scan finds +40 ms and an ATE near 0 there, where the plain ATE is not; a ground truth
    sampled as sparsely as the estimate (a photo walk) gives no diagnostic, nor one without an ATE at 0."""
    gt = random_trajectory(rng, n=2000, dt=0.005)
    idx = np.arange(20, 1980, 10)  # 20 Hz keyframes
    est = Trajectory(gt.timestamps[idx] - 0.04, gt.poses[idx])
    plain = compute_ate(gt, est, "sim3")
    offset, there = best_time_offset(gt, est)
    assert offset == pytest.approx(0.04, abs=1e-9)
    assert there.rmse < 1e-9 < 1e-3 < plain.rmse and there.n_matched == plain.n_matched == len(idx)
    # a shift that drops a bad pose off the end of the ground truth does not count as a better fit
    last = np.arange(19, 2000, 10)  # the last keyframe is the truth's last sample
    poses = gt.poses[last].copy()
    poses[-1, :3, 3] += 1.0  # a bad last pose: past +50 ms it leaves the truth, and the fit would look better
    offset, there = best_time_offset(gt, Trajectory(gt.timestamps[last] - 0.04, poses))
    assert abs(offset - 0.04) <= 0.01 and there.n_matched == len(last)
    sparse = Trajectory(gt.timestamps[::200], gt.poses[::200])
    assert best_time_offset(sparse, Trajectory(sparse.timestamps, sparse.poses)) is None
    assert best_time_offset(gt, Trajectory(gt.timestamps[:2] + 50.0, gt.poses[:2])) is None  # nothing matches


def test_submaps_placed_best_measures_the_error_inside_the_submaps_not_between_them(rng):
    """Three overlapping submaps, each in its own arbitrary Sim(3) frame with millimetre noise: placed best,
    the error is the noise, however wrong the links between them; a submap bent inside (its scale drifting
    along it) shows; an overlap keyframe counts once; a submap with too few keyframes is left out."""
    from vggt_slam_pp.geometry.lie import transform_points

    gt = random_trajectory(rng, n=60)
    ref = {i: p for i, p in enumerate(gt.positions)}
    spans = [np.arange(0, 25), np.arange(20, 45), np.arange(40, 60)]

    def submap(frames, noise=0.001, bend=0.0):
        local = gt.positions[frames] - gt.positions[frames[0]]
        local = local * (1.0 + bend * np.linspace(0.0, 1.0, len(frames)))[:, None]
        return frames, transform_points(random_sim3(rng), local + rng.normal(0.0, noise, local.shape))

    rmse, fitted = submaps_placed_best([submap(f) for f in spans], ref)
    assert fitted == 3 and rmse < 0.003
    bent, _ = submaps_placed_best([submap(spans[0]), submap(spans[1], bend=0.3), submap(spans[2])], ref)
    assert bent > 10 * rmse
    # counted once: the same submap twice adds nothing; two keyframes cannot be fitted
    twice, fitted = submaps_placed_best([submap(spans[0], noise=0.0)] * 2 + [submap(np.arange(58, 60))], ref)
    assert fitted == 2 and twice < 1e-9
    assert submaps_placed_best([submap(np.arange(3))], {}) is None

