"""Seeded procedural worlds: a ground plane (z = 0, z up) and convex solids placed around a camera path.

Every solid is a convex polyhedron given by six half-spaces ``n . x <= c`` in the world frame: boxes
(buildings, vehicles, curbs, poles, furniture) have a flat top, ramps a sloped one. Solids are placed
beside the path with a clearance corridor so the camera never enters one, and sizes, heights and colours
are drawn from the world's seed, which makes places distinctive (for place recognition) and repeatable.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from vggt_slam_pp.errors import SyntheticError

log = logging.getLogger(__name__)

WorldStyle = Literal["outdoor", "indoor"]

__all__ = ["Solid", "World", "WorldStyle", "generate_world"]


@dataclass(frozen=True)
class Solid:
    """One convex solid standing on the ground.

    Attributes:
        kind: ``building``, ``vehicle``, ``curb``, ``pole``, ``ramp``, ``furniture`` or ``box``.
        center: ``[2]`` ground position (x, y) of the footprint centre, world units.
        size: ``[3]`` full extents (length along the yaw direction, width, height).
        yaw: rotation about z (radians).
        color: ``[3]`` base albedo in [0, 1].
        texture_offset: ``[2]`` texture-space offset so that similar solids look different.
        ramp: if true the top rises linearly from 0 at the back (-length/2) to ``height`` at the front.
    """

    kind: str
    center: np.ndarray
    size: np.ndarray
    yaw: float
    color: np.ndarray
    texture_offset: np.ndarray
    ramp: bool = False

    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Half-spaces ``(normals [6, 3], offsets [6])`` with ``normals @ x <= offsets`` inside."""
        L, W, H = self.size
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        ax = np.array([c, s, 0.0])
        ay = np.array([-s, c, 0.0])
        z = np.array([0.0, 0.0, 1.0])
        p0 = np.array([self.center[0], self.center[1], 0.0])
        normals = [ax, -ax, ay, -ay, -z]
        offsets = [ax @ p0 + L / 2, -ax @ p0 + L / 2, ay @ p0 + W / 2, -ay @ p0 + W / 2, 0.0]
        if self.ramp:
            # top: z <= H (x_local + L/2) / L  ->  (-H/L) ax . x + z <= H/2 - (H/L) ax . p0
            n = np.array([-(H / L) * ax[0], -(H / L) * ax[1], 1.0])
            normals.append(n)
            offsets.append(H / 2 - (H / L) * (ax @ p0))
        else:
            normals.append(z)
            offsets.append(H)
        normals = np.array(normals)
        scale = np.linalg.norm(normals, axis=1)
        return normals / scale[:, None], np.array(offsets) / scale

    def corners(self) -> np.ndarray:
        """``[8, 3]`` corners of the bounding box."""
        L, W, H = self.size
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        local = np.array([[x, y] for x in (-L / 2, L / 2) for y in (-W / 2, W / 2)])
        xy = local @ np.array([[c, s], [-s, c]]) + self.center
        return np.concatenate([np.c_[xy, np.zeros(4)], np.c_[xy, np.full(4, H)]])

    def contains(self, points: np.ndarray) -> np.ndarray:
        """``[N]`` bool: which ``points [N, 3]`` lie inside the solid."""
        n, c = self.planes()
        return np.all(points @ n.T <= c + 1e-9, axis=1)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "center": self.center.tolist(), "size": self.size.tolist(),
                "yaw": float(self.yaw), "color": self.color.tolist(),
                "texture_offset": self.texture_offset.tolist(), "ramp": self.ramp}

    @classmethod
    def from_dict(cls, d: dict) -> Solid:
        return cls(d["kind"], np.asarray(d["center"], float), np.asarray(d["size"], float), float(d["yaw"]),
                   np.asarray(d["color"], float), np.asarray(d["texture_offset"], float), bool(d["ramp"]))


@dataclass(frozen=True)
class World:
    """A ground plane at ``z = 0`` plus solids. ``ground_color`` is the ground's base albedo."""

    solids: tuple[Solid, ...]
    style: str
    seed: int
    ground_color: np.ndarray = field(default_factory=lambda: np.array([0.55, 0.52, 0.48]))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps({"style": self.style, "seed": self.seed,
                                          "ground_color": self.ground_color.tolist(),
                                          "solids": [s.to_dict() for s in self.solids]}))

    @classmethod
    def load(cls, path: str | Path) -> World:
        d = json.loads(Path(path).read_text())
        return cls(tuple(Solid.from_dict(s) for s in d["solids"]), d["style"], int(d["seed"]),
                   np.asarray(d["ground_color"], float))

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Surface height ``[N]`` at ground positions ``xy [N, 2]`` (0 on bare ground)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        h = np.zeros(len(xy))
        for s in self.solids:
            n, c = s.planes()
            # inside the footprint (4 vertical planes), height where the top plane is reached
            side = np.all(np.c_[xy, np.zeros(len(xy))] @ n[:4].T <= c[:4], axis=1)
            if not side.any():
                continue
            top_n, top_c = n[5], c[5]
            top = (top_c - xy[side] @ top_n[:2]) / top_n[2]
            h[side] = np.maximum(h[side], top)
        return h


# Kinds with (length, width, height) ranges, lateral offset from the path (beyond the clearance), and
# spacing along the path, in metres for "outdoor"; "indoor" uses its own table.
_OUTDOOR = {
    "building": dict(L=(6, 16), W=(6, 14), H=(4, 22), offset=(3.5, 7.0), spacing=11.0),
    "vehicle": dict(L=(3.8, 4.8), W=(1.7, 2.0), H=(1.4, 1.9), offset=(0.5, 1.5), spacing=14.0),
    "curb": dict(L=(6, 14), W=(0.3, 0.4), H=(0.12, 0.2), offset=(0.0, 0.3), spacing=16.0),
    "pole": dict(L=(0.15, 0.3), W=(0.15, 0.3), H=(3.0, 7.0), offset=(0.2, 1.0), spacing=13.0),
    "ramp": dict(L=(3.0, 6.0), W=(2.0, 3.5), H=(0.5, 1.5), offset=(0.5, 2.5), spacing=45.0),
    "box": dict(L=(0.8, 2.5), W=(0.8, 2.5), H=(0.6, 2.5), offset=(0.5, 3.0), spacing=9.0),
}
_INDOOR = {
    "furniture": dict(L=(0.6, 1.8), W=(0.5, 1.0), H=(0.4, 1.1), offset=(0.2, 0.9), spacing=1.1),
    "box": dict(L=(0.2, 0.6), W=(0.2, 0.6), H=(0.15, 0.6), offset=(0.1, 0.8), spacing=0.7),
    "pole": dict(L=(0.05, 0.1), W=(0.05, 0.1), H=(0.8, 2.0), offset=(0.2, 1.0), spacing=2.5),
    "ramp": dict(L=(0.5, 1.2), W=(0.4, 0.8), H=(0.1, 0.35), offset=(0.1, 0.8), spacing=3.0),
    "building": dict(L=(1.5, 3.0), W=(0.3, 0.6), H=(1.8, 2.6), offset=(1.0, 2.0), spacing=3.5),  # partitions
}


def _densify(path_xy: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(path_xy, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if s[-1] <= 0:
        return path_xy[:1]
    q = np.arange(0.0, s[-1], step)
    return np.c_[np.interp(q, s, path_xy[:, 0]), np.interp(q, s, path_xy[:, 1])]


def generate_world(
    path_xy: np.ndarray,
    style: WorldStyle = "outdoor",
    seed: int = 0,
    clearance: float | None = None,
    density: float = 1.0,
) -> World:
    """Procedural world around a camera path.

    Args:
        path_xy: ``[M, 2]`` ground-plane positions the camera will visit (world units: metres).
        style: ``outdoor`` (street: buildings, vehicles, curbs, poles, ramps, boxes) or ``indoor``
            (room-scale furniture, boxes, poles, small ramps, partitions).
        seed: random seed; the same path, style and seed give the same world.
        clearance: free corridor half-width around the path (default 3.0 outdoor, 0.45 indoor).
        density: multiplier of the number of solids.
    """
    path_xy = np.asarray(path_xy, dtype=np.float64)
    if path_xy.ndim != 2 or path_xy.shape[1] != 2 or len(path_xy) < 2 or not np.all(np.isfinite(path_xy)):
        raise SyntheticError(f"path_xy must be a finite [M>=2, 2] array, got {path_xy.shape}")
    if style not in ("outdoor", "indoor"):
        raise SyntheticError(f"world style must be 'outdoor' or 'indoor', got {style!r}")
    table = _OUTDOOR if style == "outdoor" else _INDOOR
    clearance = (3.0 if style == "outdoor" else 0.45) if clearance is None else clearance
    rng = np.random.default_rng(seed)
    dense = _densify(path_xy, 0.1 if style == "indoor" else 0.5)
    tree = cKDTree(dense)
    tangents = np.gradient(dense, axis=0)
    tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-12)
    normals = np.c_[-tangents[:, 1], tangents[:, 0]]
    seg_len = 0.1 if style == "indoor" else 0.5
    solids: list[Solid] = []
    occupied: list[tuple[np.ndarray, float]] = []  # footprint circles of placed solids
    for kind, spec in table.items():
        spacing = spec["spacing"] / max(density, 1e-6)
        n_slots = max(1, int(len(dense) * seg_len / spacing))
        for _ in range(n_slots * 2):  # both sides of the path on average
            k = rng.integers(len(dense))
            side = rng.choice((-1.0, 1.0))
            L, W, H = (rng.uniform(*spec[a]) for a in ("L", "W", "H"))
            radius = 0.5 * np.hypot(L, W)
            lateral = clearance + rng.uniform(*spec["offset"]) + (W / 2 if kind in ("curb", "vehicle") else radius)
            center = dense[k] + side * lateral * normals[k]
            along = kind in ("curb", "vehicle", "ramp") or rng.random() < 0.5
            yaw = float(np.arctan2(tangents[k, 1], tangents[k, 0])) if along else float(rng.uniform(-np.pi, np.pi))
            if kind == "ramp" and rng.random() < 0.5:
                yaw += np.pi
            # the camera corridor must stay free of the whole footprint
            if tree.query(center)[0] < clearance + (W / 2 if along else radius) - 1e-9:
                continue
            near = [c for c, r in occupied if np.linalg.norm(c - center) < r + radius * 0.9]
            if near:
                continue
            hue = rng.uniform(0.25, 0.9, size=3)
            solids.append(Solid(kind, center, np.array([L, W, H]), yaw, hue, rng.uniform(0, 1000, 2),
                                ramp=(kind == "ramp")))
            occupied.append((center, radius))
    # exact check of the corridor: drop any solid a path point is inside of (long curbs on bends)
    pts = np.c_[dense, np.full(len(dense), 0.05)]
    kept = []
    for s in solids:
        near = tree.query_ball_point(s.center, 0.5 * np.hypot(*s.size[:2]) + clearance)
        if near:
            local = pts[near]
            grown = Solid(s.kind, s.center, s.size + np.array([2 * clearance, 2 * clearance, 0]), s.yaw,
                          s.color, s.texture_offset)
            if np.any(grown.contains(local)):
                continue
        kept.append(s)
    log.debug("world %s seed %d: %d solids", style, seed, len(kept))
    return World(tuple(kept), style, seed)
