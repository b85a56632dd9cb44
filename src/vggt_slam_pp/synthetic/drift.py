"""Trajectory-level odometry drift: a seeded random walk on the relative motions of a trajectory.

Used by the demo and by tests that need a plausible drifting estimate without running a front-end.
"""

from __future__ import annotations

import numpy as np

from vggt_slam_pp.geometry.lie import se3_inverse, sim3_exp
from vggt_slam_pp.io.trajectory import Trajectory

__all__ = ["simulate_drift"]


def simulate_drift(traj: Trajectory, rot_noise_deg: float = 0.3, trans_noise: float = 0.02,
                   scale_noise: float = 0.003, seed: int = 0) -> Trajectory:
    """Chain the ground truth's relative motions, each perturbed by a random Sim(3) increment.

    Args:
        traj: ground-truth ``T_world_cam`` poses.
        rot_noise_deg: std of the per-step rotation error (degrees, per axis).
        trans_noise: std of the per-step translation error as a fraction of the step length.
        scale_noise: std of the per-step log-scale change (scale drift, as in monocular odometry).
        seed: random seed.

    Returns:
        a trajectory with the same timestamps, starting at the first ground-truth pose, whose error grows
        with the distance travelled.
    """
    rng = np.random.default_rng(seed)
    P = traj.poses
    rel = se3_inverse(P[:-1]) @ P[1:]
    step = np.linalg.norm(rel[:, :3, 3], axis=1)
    xi = np.zeros((len(rel), 7))
    xi[:, :3] = rng.normal(0.0, np.radians(rot_noise_deg), (len(rel), 3))
    xi[:, 3:6] = rng.normal(0.0, 1.0, (len(rel), 3)) * (trans_noise * step)[:, None]
    xi[:, 6] = rng.normal(0.0, scale_noise, len(rel))
    noisy = rel @ sim3_exp(xi)
    out = [P[0]]
    scale = 1.0
    for k in range(len(noisy)):
        s = np.cbrt(np.linalg.det(noisy[k][:3, :3]))
        scale *= s
        step_T = noisy[k].copy()
        step_T[:3, :3] /= s  # keep the poses rigid; the scale drift acts on later translations
        step_T[:3, 3] *= scale
        out.append(out[-1] @ step_T)
    return Trajectory(traj.timestamps.copy(), np.array(out))
