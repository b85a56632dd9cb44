"""A backbone for synthetic sequences: ground-truth geometry plus a documented, seeded noise model.

Per submap ``k`` (frames 0..S-1, frame 0 defines the submap frame):

* **intra-submap pose noise**: frame i >= 1 gets ``T_cam_submap = exp(xi) · T_cam_submap_true`` with
  rotation noise N(0, ``rot_noise_deg``) per axis and translation noise N(0, ``trans_noise`` x the
  frame's distance from frame 0) per axis (errors grow within a submap, like a feed-forward model's);
* **depth noise**: multiplicative, ``d' = d (1 + N(0, depth_noise))`` per pixel;
* **scale error**: the whole submap (poses and points) is scaled by ``exp(N(0, scale_error))``,
  monocular scale ambiguity (on its own it does not accumulate: the odometry edge absorbs it);
* **drift inside the submap** (``scale_drift``, ``yaw_drift_deg``, ``tilt_drift_deg``): frame i and its
  points are warped by a similarity about the submap origin that grows linearly from nothing at the
  first frame to ``exp(N(0, scale_drift))`` and a rotation of N(0, ``yaw_drift_deg``) about the world's
  up axis plus N(0, ``tilt_drift_deg``) about the horizontal ones at the last. The overlap frame carries
  that drift into the next submap, so chaining makes scale and heading a random walk, as monocular
  submaps drift (each frame stays consistent with its own points: the warp moves both);
* **link error** (``overlap_scale_error``, ``overlap_rot_deg``): in every submap but the first, the
  first frame's points (the overlap frame, which links it to the previous submap) are scaled by
  exp(N(0, ``overlap_scale_error``)) and turned about the camera by N(0, ``overlap_rot_deg``) about the
  world's up axis: the odometry edge inherits the error while the rest of the submap stays consistent,
  the way two predictions of the same frame by a feed-forward model disagree;
* **outliers**: a share ``outlier_ratio`` of the depths is off by a factor exp(U(-0.7, 0.7)) with an
  ordinary confidence (the filter cannot tell them);
* **failures**: with probability ``failure_rate`` a submap (chosen by its last frame, so a bridge with
  more frames fails too) does not register the keyframes it shares with the previous submap: the
  front-end then extrapolates a *degraded* edge.

Points are the noisy depths unprojected with the noisy poses, so each submap is self-consistent, as a
real reconstruction is. Confidence is ``exp(-d / 100 - |e| / depth_noise)`` with ``e`` the relative depth
error the point was given: the filter's lowest-25 % cut then removes the worst points, as a learned
confidence aims to, not simply the far ones (which hold most of the structure). With all noise at
zero the predictions are exact and odometry reproduces the ground truth. Random numbers come from
``default_rng([seed, first frame index])``, so a submap's noise does not depend on the run's history.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone, dense_observations
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.geometry.lie import se3_exp, se3_inverse, so3_exp
from vggt_slam_pp.io.frames import Frame

if TYPE_CHECKING:
    from vggt_slam_pp.io.frames import FrameSource
    from vggt_slam_pp.pipeline import RunConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimulatedNoise:
    depth_noise: float = 0.01
    scale_error: float = 0.01
    rot_noise_deg: float = 0.1
    trans_noise: float = 0.005
    seed: int = 0
    scale_drift: float = 0.0
    yaw_drift_deg: float = 0.0
    tilt_drift_deg: float = 0.0
    outlier_ratio: float = 0.0
    failure_rate: float = 0.0
    overlap_scale_error: float = 0.0
    overlap_rot_deg: float = 0.0

    @classmethod
    def zero(cls, seed: int = 0) -> SimulatedNoise:
        return cls(0.0, 0.0, 0.0, 0.0, seed)

    @classmethod
    def realistic(cls, seed: int = 0) -> SimulatedNoise:
        """Drift of published monocular feed-forward submaps (docs/frontend.md, "Simulated noise
        profiles"): mostly scale, about 1-3 % of the path in ATE on the KITTI-driven scenarios."""
        return cls(depth_noise=0.02, scale_error=0.05, rot_noise_deg=0.2, trans_noise=0.01, seed=seed,
                   scale_drift=0.01, yaw_drift_deg=0.2, tilt_drift_deg=0.05, outlier_ratio=0.02,
                   failure_rate=0.03, overlap_scale_error=0.06, overlap_rot_deg=1.2)

    @classmethod
    def profile(cls, name: str, seed: int = 0) -> SimulatedNoise:
        """``default``, ``realistic`` or ``zero``."""
        profiles = {"default": lambda: cls(seed=seed), "realistic": lambda: cls.realistic(seed),
                    "zero": lambda: cls.zero(seed)}
        if name not in profiles:
            raise FrontendError(f"unknown noise profile {name!r}; use one of {', '.join(profiles)}")
        return profiles[name]()


class SimulatedBackbone(Backbone):
    """Needs per-frame depth (``Frame.depth``), intrinsics and ground-truth poses ``T_world_cam``."""

    name = "simulated"
    dense = True
    metric = True  # ground truth in metres (up to the per-submap scale error)

    def __init__(self, gt_poses: Mapping[int, np.ndarray], noise: SimulatedNoise | None = None,
                 stride: int = 4) -> None:
        self.gt = gt_poses
        self.noise = noise or SimulatedNoise()
        self.stride = stride
        self._committed: set[int] = set()

    def committed(self, frame_indices: Sequence[int]) -> None:
        self._committed = {int(i) for i in frame_indices}

    def _drift(self, rng: np.random.Generator, R_submap_world: np.ndarray) -> tuple[float, np.ndarray]:
        """(log-scale, rotation vector in the submap frame) of the warp at a submap's last frame."""
        n = self.noise
        g = float(rng.normal(0.0, n.scale_drift)) if n.scale_drift else 0.0
        w = np.zeros(3)
        if n.yaw_drift_deg or n.tilt_drift_deg:
            w = np.radians(np.r_[rng.normal(0, n.tilt_drift_deg, 2), rng.normal(0, n.yaw_drift_deg)])
        return g, R_submap_world @ w  # world axes (z up) -> submap frame

    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        n = self.noise
        missing = [f.index for f in frames if f.index not in self.gt]
        if missing:
            raise FrontendError(f"simulated backbone: no ground-truth pose for frames {missing[:5]} "
                                "(it needs a synthetic sequence with ground truth)")
        if any(f.depth is None or f.intrinsics is None for f in frames):
            raise FrontendError("simulated backbone: frames need depth and intrinsics (use `synth` sequences)")
        rng = np.random.default_rng([n.seed, int(frames[0].index)])
        T_world_cam0 = self.gt[frames[0].index]
        scale = float(np.exp(rng.normal(0.0, n.scale_error))) if n.scale_error else 1.0
        g_drift, w_drift = self._drift(rng, T_world_cam0[:3, :3].T)
        link = np.eye(3)  # applied to the first frame's points (camera frame = submap frame) when linked
        if frames[0].index in self._committed and (n.overlap_scale_error or n.overlap_rot_deg):
            g = float(rng.normal(0.0, n.overlap_scale_error)) if n.overlap_scale_error else 0.0
            w = np.radians(rng.normal(0.0, n.overlap_rot_deg)) if n.overlap_rot_deg else 0.0
            link = float(np.exp(g)) * so3_exp(T_world_cam0[:3, :3].T @ np.array([0.0, 0.0, w]))
        S = len(frames)
        valid = np.ones(S, bool)
        if n.failure_rate and self._committed:
            fail = np.random.default_rng([n.seed, int(frames[-1].index), 7]).random() < n.failure_rate
            if fail:
                valid = np.array([f.index not in self._committed for f in frames])
        T_cam_submap = np.zeros((S, 4, 4))
        Ks = np.zeros((S, 3, 3))
        pts, conf, pix, keys = [], [], [], []
        for i, f in enumerate(frames):
            T = se3_inverse(self.gt[f.index]) @ T_world_cam0  # true camera-from-submap (metric)
            if i > 0 and (n.rot_noise_deg or n.trans_noise):
                dist = float(np.linalg.norm(se3_inverse(T)[:3, 3]))
                xi = np.r_[rng.normal(0, np.radians(n.rot_noise_deg), 3), rng.normal(0, n.trans_noise * dist, 3)]
                T = se3_exp(xi) @ T
            depth = f.depth.astype(np.float64)
            c = np.exp(-depth / 100.0)
            if n.depth_noise:
                rel = rng.normal(0.0, n.depth_noise, depth.shape)
                depth = depth * (1.0 + rel)
                c = c * np.exp(-np.abs(rel) / n.depth_noise)  # confidence tracks the error actually made
            if n.outlier_ratio:
                out = rng.random(depth.shape) < n.outlier_ratio
                depth = np.where(out, depth * np.exp(rng.uniform(-0.7, 0.7, depth.shape)), depth)
            K = f.intrinsics.K
            T_submap_cam = se3_inverse(T)
            if S > 1 and (g_drift or w_drift.any()):  # drift: a similarity growing along the submap
                a = i / (S - 1)
                R_d, s_d = so3_exp(a * w_drift), float(np.exp(a * g_drift))
                T_submap_cam = T_submap_cam.copy()
                T_submap_cam[:3, :3] = R_d @ T_submap_cam[:3, :3]
                T_submap_cam[:3, 3] = s_d * R_d @ T_submap_cam[:3, 3]
                depth = depth * s_d
                T = se3_inverse(T_submap_cam)
            p, w, x, k = dense_observations(T_submap_cam, depth, c, K, np.eye(3), self.stride)
            if i == 0:
                p = (p @ link.T).astype(np.float32)
            T_scaled = T.copy()
            T_scaled[:3, 3] *= scale
            T_cam_submap[i] = T_scaled
            Ks[i] = K
            pts.append((p * scale).astype(np.float32))
            conf.append(w)
            pix.append(x)
            keys.append(k)
        h, w_ = frames[0].depth.shape
        return SubmapPrediction(np.array([f.index for f in frames]), T_cam_submap, Ks, (h, w_),
                                np.repeat(np.eye(3)[None], S, 0), pts, conf, pix, keys, valid,
                                dense=True, info={"scale_error": scale, "metric": True})


def from_run_config(config: RunConfig, source: FrameSource) -> Backbone:
    """The ``simulated`` backbone of a run (:data:`vggt_slam_pp.plugins.BACKBONES`): ground truth of ``source``."""
    matched = source.frame_ground_truth()
    if matched is None:
        raise FrontendError("the simulated backbone needs ground truth (a synthetic sequence from `synth`)")
    idx, gt = matched
    b = config.backbone
    return SimulatedBackbone(dict(zip((int(i) for i in idx), gt.poses, strict=True)),
                             SimulatedNoise.profile(b.noise, b.seed), stride=max(b.stride, 1) * 2)
