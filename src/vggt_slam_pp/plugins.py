"""Plug-ins by name: every backbone and every DEM encoder a configuration can name, in one place each.

A name maps to ``"module:attribute"``, imported only when used (the command line lists the names
without loading PyTorch or COLMAP). A backbone's attribute is a factory ``(RunConfig, FrameSource) ->
Backbone``; an encoder's is a class with ``from_config(weights)``. Adding one is writing it and adding
its line here (README, "Going further").
"""

from __future__ import annotations

import importlib

BACKBONES: dict[str, str] = {
    "vggt": "vggt_slam_pp.frontend.backbones.vggt:from_run_config",
    "simulated": "vggt_slam_pp.frontend.backbones.simulated:from_run_config",
    "colmap": "vggt_slam_pp.frontend.backbones.colmap:from_run_config",
    "replay": "vggt_slam_pp.frontend.backbones.replay:from_run_config",
}

ENCODERS: dict[str, str] = {
    "hog": "vggt_slam_pp.retrieval.encoders:HogEncoder",
    "dinov2": "vggt_slam_pp.retrieval.encoders:DinoV2Encoder",
}


def load(registry: dict[str, str], name: str, what: str, error: type[Exception]):
    """The object registered as ``name``; ``error`` (one line, with the known names) when there is none."""
    if name not in registry:
        raise error(f"unknown {what} {name!r}; choose one of {', '.join(registry)}")
    module, attribute = registry[name].split(":")
    return getattr(importlib.import_module(module), attribute)
