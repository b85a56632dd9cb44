"""Our implementations of the networks: VGGT (front-end backbone) and DINOv2 (DEM tile encoder).

``build_vggt`` / ``build_dinov2`` construct them (random weights, any device incl. ``meta``);
``weights.load_vggt`` / ``weights.load_dinov2`` load the official checkpoints strictly;
``preprocess`` and ``cameras`` hold the reference pre- and post-processing.
"""

from vggt_slam_pp.models.dinov2 import DinoV2Config, DinoVisionTransformer, build_dinov2
from vggt_slam_pp.models.vggt import VGGT, VggtConfig, build_vggt

__all__ = ["VGGT", "DinoV2Config", "DinoVisionTransformer", "VggtConfig", "build_dinov2", "build_vggt"]
