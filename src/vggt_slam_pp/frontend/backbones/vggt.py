"""The paper's backbone: our VGGT-1B (``vggt_slam_pp.models``) on the keyframes of a submap.

Preprocessing (crop mode, 518 wide), device and precision are chosen once. The submap frame is frame
0's camera: ``T_cam_submap[i] = E_i · E_0^-1`` with VGGT's camera-from-world extrinsics ``E``; points
are unprojected from the depth head with the predicted cameras (more accurate than the point head),
on a pixel grid with ``stride``. Frames whose outputs are not finite are marked invalid.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone, dense_observations
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.geometry.lie import se3_inverse
from vggt_slam_pp.io.frames import Frame

if TYPE_CHECKING:
    from vggt_slam_pp.io.frames import FrameSource
    from vggt_slam_pp.pipeline import RunConfig

log = logging.getLogger(__name__)


class VggtBackbone(Backbone):
    name = "vggt"
    dense = True

    def __init__(self, weights: str | Path = "vggt-1b", device: str = "auto", stride: int = 2,
                 mode: str = "crop", target_size: int = 518, model: torch.nn.Module | None = None,
                 config: Mapping | None = None, allow_download: bool = True) -> None:
        from vggt_slam_pp.models.runtime import autocast_dtype, pick_device

        self.device = pick_device(device)
        self.dtype = autocast_dtype(self.device)
        if model is None:
            from vggt_slam_pp.models.weights import load_vggt

            model = load_vggt(weights, config=config, device=self.device, allow_download=allow_download)
        self.model = model.to(self.device).eval()
        self.stride, self.mode, self.target_size = stride, mode, target_size
        log.info("vggt backbone on %s (%s)", self.device, self.dtype or torch.float32)

    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        from vggt_slam_pp.models.cameras import pose_encoding_to_extri_intri
        from vggt_slam_pp.models.preprocess import preprocess_images
        from vggt_slam_pp.models.runtime import inference_context

        if not frames:
            raise FrontendError("vggt backbone: no frames")
        images, infos = preprocess_images([f.image for f in frames], self.mode, self.target_size)
        H, W = images.shape[-2:]
        with inference_context(self.device, self.dtype):
            out = self.model(images.to(self.device))
        ext, K = pose_encoding_to_extri_intri(out["pose_enc"][0].float(), (H, W))
        E = np.zeros((len(frames), 4, 4))
        E[:, :3] = ext.cpu().double().numpy()
        E[:, 3, 3] = 1
        K = K.cpu().double().numpy()
        depth = out["depth"][0, ..., 0].float().cpu().numpy()
        dconf = out["depth_conf"][0].float().cpu().numpy()
        valid = np.isfinite(E).all(axis=(1, 2)) & np.isfinite(K).all(axis=(1, 2)) & \
            np.isfinite(depth).all(axis=(1, 2)) & np.isfinite(dconf).all(axis=(1, 2))
        if not valid[0]:
            raise FrontendError("vggt backbone: the reference frame's prediction is not finite (NaN/inf)")
        if not valid.all():
            log.warning("vggt: non-finite outputs for %d of %d frames; marking them invalid",
                        int((~valid).sum()), len(frames))
        E0_inv = se3_inverse(E[0])
        T_cam_submap = E @ E0_inv
        to_orig = []
        pts, conf, pix, keys = [], [], [], []
        for i, info in enumerate(infos):
            A = info.to_original_matrix()
            to_orig.append(A)
            if not valid[i]:
                T_cam_submap[i] = np.eye(4)
                pts.append(np.zeros((0, 3), np.float32))
                conf.append(np.zeros(0, np.float32))
                pix.append(np.zeros((0, 2), np.float32))
                keys.append(np.zeros(0, np.int64))
                continue
            p, w, x, k = dense_observations(se3_inverse(T_cam_submap[i]), depth[i], dconf[i], K[i], A, self.stride)
            pts.append(p)
            conf.append(w)
            pix.append(x)
            keys.append(k)
        return SubmapPrediction(np.array([f.index for f in frames]), T_cam_submap, K, (H, W), np.array(to_orig),
                                pts, conf, pix, keys, valid, depth, dconf, dense=True)

    def close(self) -> None:
        self.model = None


def from_run_config(config: RunConfig, source: FrameSource) -> Backbone:
    """The ``vggt`` backbone of a run (:data:`vggt_slam_pp.plugins.BACKBONES`)."""
    b = config.backbone
    return VggtBackbone(b.weights, device=b.device, stride=b.stride)
