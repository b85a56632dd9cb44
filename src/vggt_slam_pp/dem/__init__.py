"""Planar-canonical Digital Elevation Maps: ground plane, global grid, per-submap layers, images."""

from vggt_slam_pp.dem.images import encoder_image, export_dem, hillshade_rgb
from vggt_slam_pp.dem.plane import GroundPlane, PlaneConfig, fit_ground_plane
from vggt_slam_pp.dem.raster import DemConfig, DemGrid, DemLayer, rasterize

__all__ = ["DemConfig", "DemGrid", "DemLayer", "GroundPlane", "PlaneConfig", "encoder_image", "export_dem",
           "fit_ground_plane", "hillshade_rgb", "rasterize"]
