"""Synthetic worlds, camera trajectories and an RGB + depth renderer for offline tests and demos."""

from vggt_slam_pp.synthetic.renderer import Renderer
from vggt_slam_pp.synthetic.sequence import SyntheticScene, default_camera, make_scene, write_sequence
from vggt_slam_pp.synthetic.trajectories import SCENES, block_loop, figure8, from_trajectory_file, laps
from vggt_slam_pp.synthetic.world import Solid, World, generate_world

__all__ = ["SCENES", "Renderer", "Solid", "SyntheticScene", "World", "block_loop", "default_camera", "figure8",
           "from_trajectory_file", "generate_world", "laps", "make_scene", "write_sequence"]
