"""Backbones: ``vggt`` (our VGGT-1B), ``simulated`` (synthetic ground truth + noise), ``colmap``
(pycolmap structure-from-motion, weight-free), ``replay`` (saved predictions)."""

from vggt_slam_pp.frontend.backbones.base import Backbone

__all__ = ["Backbone"]
