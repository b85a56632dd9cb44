"""VGGT-SLAM++: monocular RGB SLAM with VGGT submaps, DEM-based covisibility and Sim(3) loop closure.

Conventions (see ``docs/conventions.md``):

* ``T_a_b`` maps points from frame ``b`` into frame ``a``; Sim(3) acts as ``x -> s R x + t``.
* Cameras follow OpenCV (x right, y down, z forward).
* Poses are stored as ``[..., 4, 4]`` float64 arrays.
"""

from vggt_slam_pp.errors import VggtSlamError

__version__ = "0.1.0"
__all__ = ["VggtSlamError", "__version__"]
