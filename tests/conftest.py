"""Shared test fixtures. Tests that need ``../shared`` skip cleanly when it is absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data"
REFERENCE = SHARED / "reference"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def shared_data() -> Path:
    if not DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return DATA


@pytest.fixture(scope="session")
def reference() -> Path:
    """``../shared/reference`` (model parity fixtures and manifests); skips when absent."""
    if not (REFERENCE / "fixtures").is_dir():
        pytest.skip("../shared/reference is not present")
    return REFERENCE


def random_sim3(rng: np.random.Generator, with_scale: bool = True) -> np.ndarray:
    from vggt_slam_pp.geometry import make_sim3, so3_exp

    axis = rng.normal(size=3)
    angle = rng.uniform(0.0, np.pi * 0.95)
    R = so3_exp(axis / np.linalg.norm(axis) * angle)
    s = float(np.exp(rng.uniform(-1.0, 1.0))) if with_scale else 1.0
    return make_sim3(s, R, rng.normal(scale=3.0, size=3))


def random_trajectory(rng: np.random.Generator, n: int = 200, t0: float = 100.0, dt: float = 0.1):
    """A smooth random rigid trajectory (random-walk velocity and angular velocity)."""
    from vggt_slam_pp.geometry import se3_exp
    from vggt_slam_pp.io.trajectory import Trajectory

    poses = [np.eye(4)]
    v = np.array([1.0, 0.0, 0.0])
    w = np.zeros(3)
    for _ in range(n - 1):
        v = v + rng.normal(scale=0.05, size=3)
        w = 0.9 * w + rng.normal(scale=0.02, size=3)
        poses.append(poses[-1] @ se3_exp(np.r_[w, v * dt]))
    return Trajectory(t0 + dt * np.arange(n), np.array(poses))
