"""Front-end: keyframe selection, submap assembly, backbones, point filtering, Sim(3) odometry."""

from vggt_slam_pp.frontend.frontend import Frontend, FrontendConfig, FrontendResult, SubmapAssembler
from vggt_slam_pp.frontend.keyframes import KeyframeConfig, KeyframeSelector
from vggt_slam_pp.frontend.types import OdometryEdge, Submap, SubmapPrediction

__all__ = ["Frontend", "FrontendConfig", "FrontendResult", "KeyframeConfig", "KeyframeSelector",
           "OdometryEdge", "Submap", "SubmapAssembler", "SubmapPrediction"]
