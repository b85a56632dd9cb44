"""The ``vggt`` backbone path with an oracle network (:class:`~vggt_slam_pp.synthetic.oracle.OracleVggt`)
in place of VGGT-1B, on synthetic sequences: proves preprocessing, pose decoding, pixel mapping, depth
unprojection and Sim(3) chaining end to end without weights (docs/models.md, "Oracle VGGT")."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.backbones.vggt import VggtBackbone
from vggt_slam_pp.synthetic.oracle import OracleNoise, OracleVggt, OracleView


class OracleBackbone(Backbone):
    """A ``vggt`` backbone whose network is an :class:`OracleVggt`: before each ``predict`` it tells the
    oracle the ground truth of the frames. Records every raw prediction in ``predictions`` (with the
    frames' views in ``views``) when ``record`` is set. Built by :func:`oracle_backbone`."""

    name = "vggt"
    dense = True

    def __init__(self, inner, oracle: OracleVggt, gt_poses: Mapping[int, np.ndarray],
                 record: bool = False) -> None:
        self.inner, self.oracle, self.gt = inner, oracle, gt_poses
        self.record = record
        self.predictions: list = []
        self.views: list[list[OracleView]] = []

    def views_for(self, frames) -> list[OracleView]:
        missing = [f.index for f in frames if f.index not in self.gt]
        if missing:
            raise FrontendError(f"oracle backbone: no ground-truth pose for frames {missing[:5]}")
        if any(f.depth is None or f.intrinsics is None for f in frames):
            raise FrontendError("oracle backbone: frames need depth and intrinsics (use `synth` sequences)")
        return [OracleView(np.asarray(self.gt[f.index], dtype=np.float64), f.depth, f.intrinsics.K, f.image,
                           f.index) for f in frames]

    def predict(self, frames):
        views = self.views_for(frames)
        self.oracle.frames = views
        pred = self.inner.predict(frames)
        if self.record:
            self.predictions.append(pred)
            self.views.append(views)
        return pred

    def committed(self, frame_indices) -> None:
        self.inner.committed(frame_indices)

    def describe(self) -> dict:
        o = self.oracle
        return {**self.inner.describe(),
                "oracle": {"mode": o.mode, "calls": len(o.calls), "normalize": o.normalize, "seed": o.seed,
                           "noise": dataclasses.asdict(o.noise)}}

    def close(self) -> None:
        self.inner.close()


def oracle_backbone(source, mode: str = "crop", noise: OracleNoise | None = None, seed: int = 0, *,
                    stride: int = 2, target_size: int = 518, normalize: bool = True, record: bool = False,
                    image_tolerance: float | None = 0.02, device: str = "cpu"):
    """The ``vggt`` backbone path with an :class:`OracleVggt` in place of the network, for a synthetic
    ``source`` (depth, intrinsics and ground truth; ``synth`` output read with ``open_source``).

    Pass it to ``pipeline.run(source, RunConfig(backbone=BackboneConfig(name="vggt"), ...), out,
    backbone=oracle_backbone(source, mode="pad"))``. ``record``: keep every raw prediction and the
    ground truth it was made for (``.predictions``, ``.views``; see :func:`consistency`). ``device``:
    where the backbone runs (``"auto"`` picks CUDA, with VggtBackbone's autocast)."""
    matched = source.frame_ground_truth()
    if matched is None:
        raise FrontendError("the oracle backbone needs ground truth (a synthetic sequence from `synth`)")
    idx, gt = matched
    oracle = OracleVggt(mode, target_size, noise, seed, normalize, image_tolerance=image_tolerance)
    inner = VggtBackbone(model=oracle, device=device, stride=stride, mode=mode, target_size=target_size)
    return OracleBackbone(inner, oracle, dict(zip((int(i) for i in idx), gt.poses, strict=True)), record)
