"""Inputs and outputs: frame sources for images, videos and dataset layouts; trajectory files."""

from vggt_slam_pp.io.datasets import LAYOUTS, detect_layout, open_source
from vggt_slam_pp.io.frames import Frame, FrameSource, ImageSequence
from vggt_slam_pp.io.trajectory import Trajectory, read_trajectory, write_trajectory

__all__ = ["LAYOUTS", "Frame", "FrameSource", "ImageSequence", "Trajectory", "detect_layout", "open_source",
           "read_trajectory", "write_trajectory"]
