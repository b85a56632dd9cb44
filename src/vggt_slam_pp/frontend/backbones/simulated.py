"""A backbone for synthetic sequences: ground-truth geometry plus a documented, seeded noise model.

Per submap ``k`` (frames 0..S-1, frame 0 defines the submap frame):

* **intra-submap pose noise**: frame i >= 1 gets ``T_cam_submap = exp(xi) · T_cam_submap_true`` with
  rotation noise N(0, ``rot_noise_deg``) per axis and translation noise N(0, ``trans_noise`` x the
  frame's distance from frame 0) per axis (errors grow within a submap, like a feed-forward model's);
* **depth noise**: multiplicative, ``d' = d (1 + N(0, depth_noise))`` per pixel;
* **scale error**: the whole submap (poses and points) is scaled by ``exp(N(0, scale_error))``,
  monocular scale ambiguity that chaining turns into scale drift.

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

import numpy as np

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone, dense_observations
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.geometry.lie import se3_exp, se3_inverse
from vggt_slam_pp.io.frames import Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimulatedNoise:
    depth_noise: float = 0.01
    scale_error: float = 0.01
    rot_noise_deg: float = 0.1
    trans_noise: float = 0.005
    seed: int = 0

    @classmethod
    def zero(cls, seed: int = 0) -> SimulatedNoise:
        return cls(0.0, 0.0, 0.0, 0.0, seed)


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
        S = len(frames)
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
            K = f.intrinsics.K
            p, w, x, k = dense_observations(se3_inverse(T), depth, c, K, np.eye(3), self.stride)
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
                                np.repeat(np.eye(3)[None], S, 0), pts, conf, pix, keys, np.ones(S, bool),
                                dense=True, info={"scale_error": scale, "metric": True})
