"""Ray-casting RGB + depth renderer for :class:`World` scenes.

Depth is exact: every pixel's ray is intersected analytically with the ground plane and with each
solid (convex polyhedron clipping), keeping the nearest hit. Only solids within ``max_depth`` whose
projected bounding box overlaps the image are tested, and only over that box, so a frame costs about
one pass over the image per layer of overlapping solids.

Colour is a base albedo per solid modulated by a procedural multi-octave texture (sampled by world
position on each face, mip-mapped by pixel footprint so distant surfaces do not alias) and Lambertian
sun shading. Texture gives optical flow and SIFT plenty of corners. Pixels that see no surface within
``max_depth`` show sky and have depth 0 (unknown).
"""

from __future__ import annotations

import functools
import logging

import cv2
import numpy as np

from vggt_slam_pp.errors import SyntheticError
from vggt_slam_pp.geometry.camera import PinholeCamera
from vggt_slam_pp.synthetic.world import World

log = logging.getLogger(__name__)

__all__ = ["Renderer", "make_texture"]

_NEAR = 0.05


def _dead_leaves(size: int, rng: np.random.Generator, count: int = 30000) -> np.ndarray:
    """Tileable "dead leaves" image in [0, 1]: overlapping disks and squares of random grey with power-law
    radii. Scale-invariant and full of corners at every scale, like natural surfaces."""
    img = np.full((size, size), 0.5, np.float32)
    r_min, r_max = 1.5, size / 16
    u = rng.random(count)
    # radius density ~ r^-3 (inverse-CDF sampling)
    radii = 1.0 / np.sqrt((1 - u) / r_min**2 + u / r_max**2)
    centres = rng.uniform(0, size, (count, 2))
    greys = rng.random(count)
    square = rng.random(count) < 0.5
    for (cx, cy), r, g, sq in zip(centres, radii, greys, square, strict=False):
        for dx in (-size, 0, size) if (cx < r or cx > size - r) else (0,):
            for dy in (-size, 0, size) if (cy < r or cy > size - r) else (0,):
                c = (int(round((cx + dx) * 4)), int(round((cy + dy) * 4)))
                if sq:
                    h = int(round(r * 4 * 0.8))
                    cv2.rectangle(img, (c[0] - h, c[1] - h), (c[0] + h, c[1] + h), float(g), -1, cv2.LINE_AA, 2)
                else:
                    cv2.circle(img, c, int(round(r * 4)), float(g), -1, cv2.LINE_AA, 2)
    return img


@functools.lru_cache(maxsize=4)
def make_texture(size: int = 1024, seed: int = 0, levels: int = 6) -> tuple[np.ndarray, ...]:
    """Tileable procedural texture in [0, 1] and its mip pyramid (``levels`` images, float32).

    A dead-leaves pattern (sharp edges and corners at all scales) mixed with multi-octave value noise
    (gradual shading). Cached per arguments: treat the arrays as read-only."""
    rng = np.random.default_rng(seed)
    noise = np.zeros((size, size), np.float32)
    for octave in range(2, 7):  # cells of size/4 ... size/64 pixels
        cells = 2**octave
        grid = np.tile(rng.random((cells, cells)).astype(np.float32), (3, 3))  # periodic neighbours
        noise += cv2.resize(grid, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[size : 2 * size, size : 2 * size]
    noise = (noise - noise.min()) / max(float(np.ptp(noise)), 1e-6)
    tex = np.clip(0.7 * _dead_leaves(size, rng) + 0.3 * noise, 0.0, 1.0)
    pyramid = [tex]
    for _ in range(levels - 1):
        prev = pyramid[-1]
        padded = np.pad(prev, 4, mode="wrap")  # periodic blur keeps the texture tileable
        blurred = cv2.GaussianBlur(padded, (5, 5), 1.0)[4:-4, 4:-4]
        pyramid.append(cv2.resize(blurred, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return tuple(pyramid)


class Renderer:
    """Renders a world through one pinhole camera (distortion is ignored).

    Args:
        world: the scene.
        camera: intrinsics and image size.
        max_depth: surfaces beyond this distance (world units) are not drawn.
        texels_per_unit: texture resolution on surfaces (texels per world unit).
        texture_seed: seed of the procedural texture.
        aperiodic: break the texture's repetition (one 1024-texel tile every 16 m outdoors): each
            tile-sized cell of a surface gets a pseudo-random offset and a second texture layer at an
            incommensurate scale and angle is blended in. A repeating ground seen at several distances
            gives scale-invariant features (SIFT) false matches; with it, COLMAP folded a rendered corner
            (docs/experiments.md). Default off: the loop-closure benchmarks were measured without it.
    """

    def __init__(self, world: World, camera: PinholeCamera, max_depth: float = 80.0,
                 texels_per_unit: float | None = None, texture_seed: int = 7, aperiodic: bool = False) -> None:
        if max_depth <= _NEAR:
            raise SyntheticError(f"max_depth must exceed {_NEAR}")
        self.world = world
        self.camera = camera.without_distortion()
        self.max_depth = float(max_depth)
        self.tpu = float(texels_per_unit or (64.0 if world.style == "outdoor" else 256.0))
        self.pyramid = make_texture(seed=texture_seed)
        self.aperiodic = aperiodic
        self._texture_seed = texture_seed
        H, W = camera.height, camera.width
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        self._rays_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
        solids = world.solids
        planes = [s.planes() for s in solids]
        self._planes_n = np.array([n for n, _ in planes]).reshape(-1, 6, 3)
        self._planes_c = np.array([c for _, c in planes]).reshape(-1, 6)
        self._corners = np.array([s.corners() for s in solids]).reshape(-1, 8, 3)
        self._centres = self._corners.mean(axis=1) if len(solids) else np.zeros((0, 3))
        self._radii = (np.linalg.norm(self._corners - self._centres[:, None], axis=2).max(axis=1)
                       if len(solids) else np.zeros(0))
        self._colors = np.array([s.color for s in solids]).reshape(-1, 3)
        self._tex_off = np.array([s.texture_offset for s in solids]).reshape(-1, 2)
        sun = np.array([0.4, -0.3, 0.85])
        self._sun = sun / np.linalg.norm(sun)

    def _sample(self, tu: np.ndarray, tv: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Trilinear texture lookup at surface coordinates (tu, tv) (world units) and mip ``level``."""
        level = np.clip(level, 0, len(self.pyramid) - 1)
        tex = np.zeros(tu.shape, np.float32)
        lo = np.floor(level).astype(int)
        frac = (level - lo).astype(np.float32)
        mu = (tu * self.tpu).astype(np.float32)
        mv = (tv * self.tpu).astype(np.float32)
        for lev in range(len(self.pyramid)):
            use = (lo == lev) | (lo + 1 == lev)
            if not use.any():
                continue
            scale = np.float32(2.0**-lev)
            img = self.pyramid[lev]
            # wrap texture coordinates into range so remap's float maps stay precise
            size = np.float32(img.shape[0])
            su = np.mod(mu * scale, size)
            sv = np.mod(mv * scale, size)
            sample = cv2.remap(img, su, sv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            wgt = np.where(lo == lev, 1.0 - frac, np.where(lo + 1 == lev, frac, 0.0)).astype(np.float32)
            tex += wgt * sample
        return tex

    def _scatter_tiles(self, tu: np.ndarray, tv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shift the texture by a pseudo-random offset per texture-sized cell of the surface, so that the
        pattern does not repeat every tile (a repeating ground seen at several distances gives
        scale-invariant features false matches)."""
        period = self.pyramid[0].shape[0] / self.tpu
        cu = np.floor(tu / period).astype(np.int64)
        cv = np.floor(tv / period).astype(np.int64)
        h = (cu * 73856093) ^ (cv * 19349663) ^ (self._texture_seed * 83492791)
        h = (h * 2654435761) % (1 << 32)
        ou = (h & 0xFFFF) / 65536.0 * period
        ov = ((h >> 16) & 0xFFFF) / 65536.0 * period
        return tu + ou, tv + ov

    def _visible_solids(self, T_world_cam: np.ndarray) -> list[tuple[int, slice, slice]]:
        """Solids that may be visible and the pixel window their bounding box covers."""
        out = []
        if len(self._centres) == 0:
            return out
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        cam = self.camera
        dist = np.linalg.norm(self._centres - t, axis=1)
        cand = np.nonzero(dist - self._radii < self.max_depth)[0]
        if len(cand) == 0:
            return out
        corners_cam = (self._corners[cand] - t) @ R  # [K, 8, 3] = R^T (p - t)
        z = corners_cam[..., 2]
        for k, idx in enumerate(cand):
            zk = z[k]
            if zk.max() <= _NEAR:
                continue
            if zk.min() <= _NEAR:
                rows, cols = slice(0, cam.height), slice(0, cam.width)
            else:
                u = cam.fx * corners_cam[k, :, 0] / zk + cam.cx
                v = cam.fy * corners_cam[k, :, 1] / zk + cam.cy
                u0, u1 = int(np.floor(u.min())), int(np.ceil(u.max())) + 1
                v0, v1 = int(np.floor(v.min())), int(np.ceil(v.max())) + 1
                u0, v0 = max(u0, 0), max(v0, 0)
                u1, v1 = min(u1, cam.width), min(v1, cam.height)
                if u0 >= u1 or v0 >= v1:
                    continue
                rows, cols = slice(v0, v1), slice(u0, u1)
            out.append((int(idx), rows, cols))
        return out

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Render one view.

        Args:
            T_world_cam: ``[4, 4]`` camera pose (OpenCV camera, world z up).

        Returns:
            ``rgb`` uint8 ``[H, W, 3]`` and ``depth`` float32 ``[H, W]`` (z-depth, 0 = no surface).
        """
        T = np.asarray(T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise SyntheticError("camera pose must be a finite [4, 4] matrix")
        R, o = T[:3, :3], T[:3, 3]
        d = self._rays_cam @ R.T  # [H, W, 3] world directions with unit z-depth
        H, W = d.shape[:2]
        depth = np.full((H, W), np.inf)
        owner = np.full((H, W), -1, np.int32)  # -1 ground, >= 0 solid index
        face = np.full((H, W), -1, np.int8)
        # ground plane z = 0 (the camera is above it)
        if o[2] > 0:
            with np.errstate(divide="ignore", invalid="ignore"):
                tg = -o[2] / d[..., 2]
            ok = (d[..., 2] < 0) & (tg > _NEAR) & (tg <= self.max_depth)
            depth[ok] = tg[ok]
        for idx, rows, cols in self._visible_solids(T):
            n, c = self._planes_n[idx], self._planes_c[idx]
            dd = d[rows, cols]  # [h, w, 3]
            den = dd @ n.T  # [h, w, 6]
            num = c - n @ o  # [6]
            with np.errstate(divide="ignore", invalid="ignore"):
                tt = num / den
            entering = den < 0
            t_in = np.where(entering, tt, -np.inf)
            t_out = np.where(den > 0, tt, np.inf)
            parallel_out = (den == 0) & (num < 0)
            t_enter = t_in.max(axis=-1)
            t_exit = t_out.min(axis=-1)
            hit = (t_enter <= t_exit) & (t_enter > _NEAR) & ~parallel_out.any(axis=-1) & (t_enter <= self.max_depth)
            sub = depth[rows, cols]
            closer = hit & (t_enter < sub)
            if not closer.any():
                continue
            sub[closer] = t_enter[closer]
            owner[rows, cols][closer] = idx
            face[rows, cols][closer] = np.argmax(t_in, axis=-1)[closer]
        return self._shade(o, d, depth, owner, face)

    def _shade(self, o, d, depth, owner, face) -> tuple[np.ndarray, np.ndarray]:
        H, W = depth.shape
        hitmask = np.isfinite(depth)
        dep = np.where(hitmask, depth, 0.0)
        p = o + d * dep[..., None]  # world points
        # per-pixel normals and texture axes
        normal = np.zeros((H, W, 3))
        normal[..., 2] = 1.0
        tu = p[..., 0].copy()
        tv = p[..., 1].copy()
        albedo = np.broadcast_to(self.world.ground_color, (H, W, 3)).copy()
        solid = owner >= 0
        if solid.any():
            sid, fid = owner[solid], face[solid]
            n = self._planes_n[sid, fid]  # [M, 3]
            normal[solid] = n
            ps = p[solid]
            vertical = np.abs(n[:, 2]) < 0.7
            horiz = np.stack([-n[:, 1], n[:, 0]], axis=1)
            horiz /= np.maximum(np.linalg.norm(horiz, axis=1, keepdims=True), 1e-12)
            u_face = np.where(vertical, ps[:, 0] * horiz[:, 0] + ps[:, 1] * horiz[:, 1], ps[:, 0])
            v_face = np.where(vertical, ps[:, 2], ps[:, 1])
            tu[solid] = u_face + self._tex_off[sid, 0]
            tv[solid] = v_face + self._tex_off[sid, 1]
            albedo[solid] = self._colors[sid]
        # mip level from the pixel footprint on the surface; grazing angles stretch it along one axis
        # only, so the isotropic level uses the geometric mean of the two axes (1 / sqrt(cos))
        dnorm = np.linalg.norm(d, axis=-1)
        cosang = np.abs(np.sum(normal * d, axis=-1)) / dnorm
        footprint = self.tpu * dep * dnorm / self.camera.fx / np.sqrt(np.clip(cosang, 0.05, 1.0))
        level = np.clip(np.log2(np.maximum(footprint, 1e-6)), 0, len(self.pyramid) - 1)
        if self.aperiodic:
            tu, tv = self._scatter_tiles(tu, tv)
            # a second layer at an incommensurate scale and angle: the local pattern no longer repeats
            # (one texture, however shifted per cell, shows every patch once per cell)
            c, s_ = np.cos(1.1), np.sin(1.1)
            tex = 0.6 * self._sample(tu, tv, level) + 0.4 * self._sample(
                (c * tu - s_ * tv) * 0.618 + 3.7, (s_ * tu + c * tv) * 0.618 + 1.3, level - np.log2(1 / 0.618))
            tex = (tex - 0.5) * 1.25 + 0.5  # the blend's contrast back to one layer's
        else:
            tex = self._sample(tu, tv, level)
        shade = 0.45 + 0.55 * np.clip(normal @ self._sun, 0.0, 1.0)
        rgb = albedo * (0.12 + 0.88 * tex[..., None]) * shade[..., None]
        # sky: vertical gradient by the ray's elevation
        elev = np.clip(d[..., 2] / dnorm, -1.0, 1.0)
        sky = np.stack([0.55 + 0.2 * elev, 0.7 + 0.15 * elev, 0.95 + 0.0 * elev], axis=-1)
        rgb = np.where(hitmask[..., None], rgb, sky)
        rgb8 = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return rgb8, dep.astype(np.float32)
