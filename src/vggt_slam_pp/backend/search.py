"""Estimate-free alignment of two submaps: the first step of loop registration (our decision; the paper
registers loops from the current estimate).

Under realistic drift the current estimate of a revisit can be tens of metres, tens of degrees and tens of
percent in scale off, so the candidate alignments come from the two submaps' own data, in their own
frames:

1. Each cloud is *levelled* by its up direction (the ground plane's normal in that submap's frame); its
   ground level is a low percentile of its heights.
2. Its points are binned into ``cell``-sized ground cells (:class:`CellMap`): a cell is *structure*
   when its highest point stands ``height`` above the ground, *clear* when it was observed and neither it
   nor a neighbour is structure.
3. For every yaw (the full circle) and scale (within what odometry allows), the query's cells are
   rotated and scaled about their centroid and slid over the match's, at every shift where the two
   overlap (OpenCV ``matchTemplate``, unnormalised correlations of binary images):
   ``score = agreements - conflicts``; agreements = query structure on match structure (one cell of
   tolerance), conflicts = query structure on the match's clear ground plus match structure on the
   query's clear ground. Free space is evidence: a wrong place or a shrunken query puts buildings where
   the other submap saw open ground, so the score does not favour small scales as an occupancy
   correlation does. With the points' image colours, a structure agreement counts as far as the two
   cells' hues agree (:func:`hue_vectors`, :func:`colour_match`): every face of an object has its hue.
4. The best alignments are refined at half the cell (yaw and scale steps halved: by default the yaw at the
   peak's scale, then the scale at the best yaw) and ranked again by :func:`free_space_agreement`
   in 3-D (heights scale with the query: a shrunken query's buildings fall under the structure height),
   and ICP refines the survivors (:mod:`vggt_slam_pp.backend.registration`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vggt_slam_pp.errors import BackendError
from vggt_slam_pp.geometry.lie import transform_points


@dataclass(frozen=True)
class SearchConfig:
    cell_tiles: float = 0.5  # fine cell; the exhaustive pass runs at twice this
    yaw_step_deg: float = 6.0  # exhaustive pass (the refinement uses half)
    scale_step: float = 0.08  # log-scale step of the exhaustive pass (the refinement uses half)
    ground_percentile: float = 20.0
    structure_height_tiles: float = 0.15
    min_structure_cells: int = 8
    candidates_per_scale: int = 3  # the best distinct alignments kept per scale of the exhaustive pass
    refine: int = 8  # of all those, the best (by score) refined at the fine cell
    refine_descent: bool = True  # refine yaw at the peak's scale, then scale at the best yaw (9 of the 5 x 5
    # yaw-scale grid's 25 scorings); False: the whole grid
    min_agreement_cells: int = 10  # free-space agreement on fewer cells counts as none


def up_frame(up: np.ndarray) -> np.ndarray:
    """A rotation [3,3] taking the unit vector ``up`` to +z (the rest of the frame is arbitrary)."""
    z = np.asarray(up, float) / np.linalg.norm(up)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[0]) > 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def own_ground(points: np.ndarray, up_guess: np.ndarray, inlier: float, max_tilt_deg: float = 15.0,
               low_percentile: float = 60.0, min_support: float = 0.3, iterations: int = 200, seed: int = 0
               ) -> tuple[np.ndarray, float] | None:
    """A submap's own ground plane ``(normal [3], offset)``, ``normal . x = offset`` on it, the normal
    within ``max_tilt_deg`` of ``up_guess`` and on its side: the plane that holds most of the points below
    their ``low_percentile`` height along the guess within ``inlier`` (RANSAC over point triples), refined
    by least squares on its inliers. None when no such plane holds ``min_support`` of those points (no
    visible ground)."""
    g = np.asarray(up_guess, float)
    g = g / np.linalg.norm(g)
    P = np.asarray(points, float).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1)]
    if len(P) < 10 or not inlier > 0:
        return None
    h = P @ g
    low = P[h <= np.percentile(h, low_percentile)]
    rng = np.random.default_rng(seed)
    if len(low) > 4000:
        low = low[rng.choice(len(low), 4000, replace=False)]
    cos_max = float(np.cos(np.radians(max_tilt_deg)))
    triples = rng.integers(0, len(low), size=(iterations, 3))
    a, b, c = low[triples[:, 0]], low[triples[:, 1]], low[triples[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n, a = n[ok] / norm[ok, None], a[ok]
    n *= np.sign(n @ g)[:, None]
    ok = n @ g >= cos_max
    n, a = n[ok], a[ok]
    if not len(n):
        return None
    dist = n @ low.T  # [iterations, len(low)]: each point's distance to each plane, in place (a hot loop)
    dist -= np.einsum("ij,ij->i", a, n)[:, None]
    counts = np.count_nonzero(np.abs(dist, out=dist) < inlier, axis=1)
    k = int(np.argmax(counts))
    inliers = low[np.abs((low - a[k]) @ n[k]) < inlier]
    if len(inliers) < max(3, min_support * len(low)):
        return None
    centre = inliers.mean(0)
    _, _, Vt = np.linalg.svd(inliers - centre, full_matrices=False)
    up = Vt[2] * np.sign(Vt[2] @ g)
    return (up, float(up @ centre)) if up @ g >= cos_max else None


def own_up(points: np.ndarray, up_guess: np.ndarray, unit: float, max_tilt_deg: float = 15.0,
           inlier_tiles: float = 0.1, seed: int = 0) -> np.ndarray:
    """The up direction [3] of a submap read from its own ground (:func:`own_ground`, inliers within
    ``inlier_tiles`` of ``unit``: one tile in this cloud's frame); ``up_guess`` (normalised) without one.

    The estimate's up drifts with odometry (3-4 deg of tilt after a few hundred submaps of the default
    profile): levelled by it, a submap's far ground stands above the structure height and counts as
    structure, and two such grounds "agree" at wrong alignments (docs/backend.md)."""
    g = np.asarray(up_guess, float)
    ground = own_ground(points, g, inlier_tiles * float(unit), max_tilt_deg, seed=seed)
    return ground[0] if ground is not None else g / np.linalg.norm(g)


def camera_height(points: np.ndarray, camera_centers: np.ndarray | None, up_guess: np.ndarray,
                  max_tilt_deg: float = 15.0, max_spread: float = 0.1, inlier: float = 0.1, seed: int = 0
                  ) -> float | None:
    """The height of :func:`camera_heights`, None where the cameras do not keep one height (a spread over
    ``max_spread``)."""
    measured = camera_heights(points, camera_centers, up_guess, max_tilt_deg, inlier, seed)
    return measured[0] if measured is not None and measured[1] <= max_spread else None


def camera_heights(points: np.ndarray, camera_centers: np.ndarray | None, up_guess: np.ndarray,
                   max_tilt_deg: float = 15.0, inlier: float = 0.1, seed: int = 0,
                   point_camera: np.ndarray | None = None, min_camera_points: int = 50
                   ) -> tuple[float, float] | None:
    """``(height, spread)``: the height of a submap's cameras above its own ground (its frame's units), the
    median distance of the camera centres [S,3] to the submap's ground plane (:func:`own_ground` of
    ``points`` [N,3] near ``up_guess``, inliers within ``inlier`` x a first guess of the height: the cameras
    over the 20th percentile of the points), and how far the cameras' own heights spread about it (robust,
    1.48 MAD / median: 0 for cameras at one height). None when there is no ground plane or with fewer than
    two cameras.

    ``point_camera`` [N] (the keyframe each point was reconstructed from, its index in ``camera_centers``),
    when known: each camera's height is measured above the ground its own points hold (at least
    ``min_camera_points`` of them, a plane within ``max_tilt_deg`` of the submap's), wherever two or more
    cameras have one. A backbone predicts each keyframe's pose and depth together, and the pose error that
    grows along a submap moves a keyframe's points with it: above the submap's common plane the cameras of
    a long car submap spread 10-25 % and the median is 3 % off (p90 8 %), above their own grounds they
    spread 0.5 % and the median is 1.2 % off (p90 2.6 %; docs/experiments.md, session 65). A camera that
    really changes height still spreads.

    A camera carried at a steady height (a car, a walker, a robot) gives each submap's scale directly: the
    ratio of two submaps' heights is their relative scale, however far odometry's scale has drifted
    between them. A flying camera changes height within a submap and gives no cue. The plane, not a
    percentile of the points, is the ground: a percentile moves with the terrain a submap happens to see
    and with its tilt (measured on the realistic profile's submaps: 11-17 % spread of the heights in world
    units against 1.6-3 %, docs/experiments.md)."""
    C = np.asarray(camera_centers, float).reshape(-1, 3) if camera_centers is not None else np.zeros((0, 3))
    P = np.asarray(points, float).reshape(-1, 3)
    finite = np.isfinite(P).all(axis=1)
    P = P[finite]
    if point_camera is not None:
        point_camera = np.asarray(point_camera).reshape(-1)
        if len(point_camera) != len(finite):
            raise BackendError(f"{len(point_camera)} camera labels for {len(finite)} points")
        point_camera = point_camera[finite]
    if len(C) < 2 or len(P) < 10 or not np.isfinite(C).all():
        return None
    g = np.asarray(up_guess, float) / np.linalg.norm(up_guess)
    rough = float(np.median(C @ g) - np.percentile(P @ g, 20.0))
    if not rough > 0:
        return None
    ground = own_ground(P, g, inlier * rough, max_tilt_deg, seed=seed)
    if ground is None:
        return None
    h = C @ ground[0] - ground[1]
    if point_camera is not None:
        own = _own_camera_heights(P, point_camera, C, ground[0], inlier * rough,
                                  max_tilt_deg, min_camera_points, seed)
        if len(own) >= 2:
            h = own
    mid = float(np.median(h))
    if not mid > 0:
        return None
    return mid, 1.4826 * float(np.median(np.abs(h - mid))) / mid


def point_cameras(points_per_camera: np.ndarray) -> np.ndarray:
    """Each point's keyframe [sum of points_per_camera]: its index among the cameras, from how many of the
    points (in order) each keyframe gave [S] (:func:`camera_heights`' ``point_camera``)."""
    counts = np.asarray(points_per_camera, np.int64).reshape(-1)
    return np.repeat(np.arange(len(counts)), counts)


def _own_camera_heights(P: np.ndarray, point_camera: np.ndarray, C: np.ndarray, up: np.ndarray, inlier: float,
                        max_tilt_deg: float, min_points: int, seed: int) -> np.ndarray:
    """The heights [K<=S] of the cameras ``C`` [S,3] that have a ground of their own: :func:`own_ground` (normal
    near ``up``) of the ``min_points`` or more points of ``P`` [N,3] they reconstructed (``point_camera`` [N],
    an index into ``C``)."""
    out = []
    for i, c in enumerate(C):
        mine = P[point_camera == i]
        if len(mine) < min_points:
            continue
        ground = own_ground(mine, up, inlier, max_tilt_deg, seed=seed + i)
        height = c @ ground[0] - ground[1] if ground is not None else 0.0
        if height > 0:
            out.append(height)
    return np.array(out)


def hue_vectors(colors: np.ndarray | None, n: int, full_saturation: float = 0.08, min_value: int = 24
                ) -> np.ndarray:
    """Each point's hue as a 2-D vector [n,2]: the direction of its chromaticity ``rgb / (r + g + b)``
    away from grey, of length ``min(1, saturation / full_saturation)`` (saturation: the chromaticity's
    distance from grey). Shading and texture scale the three channels alike, so the hue of a surface
    is the same on every face and from every direction; grey, dark or unknown (``colors`` None)
    points get 0 (no colour evidence)."""
    if colors is None:
        return np.zeros((n, 2))
    rgb = np.asarray(colors, float).reshape(-1, 3)
    total = rgb.sum(1)
    chroma = rgb / np.maximum(total, 1e-9)[:, None] - 1.0 / 3.0
    v = chroma @ np.array([[1.0, 1.0], [-1.0, 1.0], [0.0, -2.0]]) / np.array([np.sqrt(2.0), np.sqrt(6.0)])
    sat = np.linalg.norm(v, axis=1)
    u = v / np.maximum(sat, 1e-12)[:, None] * np.minimum(1.0, sat / full_saturation)[:, None]
    u[rgb.max(1) < min_value] = 0.0
    return u


def colour_match(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """How far two hue vectors [...,2] (:func:`hue_vectors`) agree, in [0, 1]: 1 when either has no
    colour, the cosine of the hue difference (clipped at 0) when both are saturated."""
    v = 1.0 - np.linalg.norm(u, axis=-1) * np.linalg.norm(w, axis=-1) + np.sum(u * w, axis=-1)
    return np.clip(v, 0.0, 1.0)


def cell_heights(levelled: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Highest point per ``cell``-sized ground cell of a levelled cloud [N,3] (height = last coordinate):
    (sorted cell keys [K] int64, tops [K], index of the top point [K])."""
    if len(levelled) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
    ij = np.floor(levelled[:, :2] / cell).astype(np.int64)
    keys = (ij[:, 0] << 32) + (ij[:, 1] & 0xFFFFFFFF)
    order = np.lexsort((levelled[:, 2], keys))  # by key, highest last
    keys, h = keys[order], levelled[order, 2]
    last = np.r_[keys[1:] != keys[:-1], True]
    return keys[last], h[last], order[last]


def footprint_overlap(a_levelled: np.ndarray, b_levelled: np.ndarray, cell: float, min_points: int = 3) -> float:
    """The share of ground the two aligned, levelled clouds [N,3], [M,3] (height last, one frame) both cover,
    of the smaller one's: ``cell``-sized cells holding at least ``min_points`` points of a cloud are its
    footprint (a stray point does not widen it). What ``bench loops`` calls a revisit, measured on the
    submaps themselves (docs/backend.md, "registration")."""
    def cells(P: np.ndarray) -> set:
        if not len(P):
            return set()
        keys, counts = np.unique(np.floor(np.asarray(P)[:, :2] / cell).astype(np.int64), axis=0, return_counts=True)
        return set(map(tuple, keys[counts >= min_points]))

    a, b = cells(a_levelled), cells(b_levelled)
    return len(a & b) / max(1, min(len(a), len(b)))


def free_space_agreement(src_levelled: np.ndarray, dst_levelled: np.ndarray, cell: float, above: float,
                         max_pixels: int = 4_000_000, src_hue: np.ndarray | None = None,
                         dst_hue: np.ndarray | None = None, src_structure: np.ndarray | None = None
                         ) -> tuple[float, int]:
    """Consistency of two aligned, levelled clouds [N,3], [M,3] (height last, same frame) in
    ``cell``-sized ground cells: a cell is structure where its top is higher than ``above``. Returns
    (agreements / (agreements + conflicts), agreements + conflicts): agreements = structure cells of
    either side with structure of the other within one cell; conflicts = structure cells of either side
    that the other observed as clear ground (no structure within one cell). Different tops of the same
    building are no conflict (a near camera does not see the roof); a building where the other submap saw
    open ground is.

    With hue vectors [N,2], [M,2] (:func:`hue_vectors`), a structure cell agrees by how well its colour
    matches the other side's structure near it (:func:`colour_match`), and the rest of it is a conflict:
    a building in the other submap's place but of another colour is not the same building.
    ``src_structure`` [N] marks the source's structure as its own ground saw it (default: above ``above``)."""
    both = np.concatenate([src_levelled[:, :2], dst_levelled[:, :2]])
    lo = both.min(0) - 2 * cell
    shape = tuple(int(x) for x in np.ceil((both.max(0) - lo) / cell) + 2)
    if shape[0] * shape[1] > max_pixels:
        return 0.0, 0
    imgs = []
    for cloud, hue, up in ((src_levelled, src_hue, src_structure), (dst_levelled, dst_hue, None)):
        up = cloud[:, 2] > above if up is None else up
        struct = _raster(cloud[up, :2], lo, cell, shape)
        colour = _hue_raster(cloud[up, :2], hue[up] if hue is not None else None, lo, cell, shape)
        imgs.append((struct, cv2.dilate(struct, _KERNEL), _clear(_raster(cloud[:, :2], lo, cell, shape), struct),
                     colour, _near_hue(colour)))
    (s_s, s_near, s_clear, s_hue, s_hue_near), (d_s, d_near, d_clear, d_hue, d_hue_near) = imgs
    s_on = s_s * d_near * colour_match(s_hue, d_hue_near)
    d_on = d_s * s_near * colour_match(d_hue, s_hue_near)
    agree = float(s_on.sum() + d_on.sum())
    conflict = float((s_s * d_clear).sum() + (d_s * s_clear).sum()
                     + (s_s * d_near).sum() + (d_s * s_near).sum()) - agree
    total = agree + conflict
    return (agree / total if total else 0.0), int(total)


@dataclass(frozen=True)
class CellMap:
    """A levelled cloud's observed cells: centres [K,2], whether each is structure [K], and the hue
    vector of its top point [K,2] (:func:`hue_vectors`; zeros without colour)."""

    uv: np.ndarray
    structure: np.ndarray
    hue: np.ndarray

    @classmethod
    def of(cls, levelled: np.ndarray, cell: float, above: float, hue: np.ndarray | None = None) -> CellMap:
        keys, top, index = cell_heights(levelled, cell)
        ij = np.c_[keys >> 32, (keys & 0xFFFFFFFF).astype(np.int32)]  # the low word back to signed
        return cls((ij + 0.5) * cell, top > above, hue[index] if hue is not None else np.zeros((len(keys), 2)))

    @property
    def coloured(self) -> bool:
        return bool(np.any(self.hue[self.structure] != 0))


def _raster(uv: np.ndarray, lo: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    return _raster_cells(ij[np.all((ij >= 0) & (ij < np.asarray(shape)), axis=1)], shape)


def _raster_cells(ij: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[H,W] float32: 1 at the cells ``ij`` [N,2] (all inside ``shape``), 0 elsewhere."""
    img = np.zeros(shape, np.float32)
    img[ij[:, 0], ij[:, 1]] = 1.0
    return img


_KERNEL = np.ones((3, 3), np.uint8)


def _hue_raster(uv: np.ndarray, hue: np.ndarray | None, lo: np.ndarray, cell: float, shape: tuple[int, int]
                ) -> np.ndarray:
    """Mean hue vector per cell [H,W,2] (zeros without colour)."""
    if hue is None or len(uv) == 0:
        return np.zeros((*shape, 2), np.float32)
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    keep = np.all((ij >= 0) & (ij < np.asarray(shape)), axis=1)
    return _hue_raster_cells(ij[keep], hue[keep], shape)


def _hue_raster_cells(ij: np.ndarray, hue: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Mean hue vector [H,W,2] of the points at cells ``ij`` [N,2] (all inside ``shape``), hues [N,2]."""
    out = np.zeros((*shape, 2), np.float32)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    count = np.bincount(flat, minlength=shape[0] * shape[1]).astype(np.float32)
    for k in range(2):
        total = np.bincount(flat, weights=hue[:, k], minlength=shape[0] * shape[1]).astype(np.float32)
        out[..., k] = (total / np.maximum(count, 1.0)).reshape(shape)
    return out


def _near_hue(hue: np.ndarray) -> np.ndarray:
    """The mean hue vector of the coloured cells within one cell [H,W,2] (what a structure cell is
    compared with: the other side's structure within one cell, as in the agreements)."""
    has = (np.linalg.norm(hue, axis=-1) > 0).astype(np.float32)
    count = cv2.boxFilter(has, -1, (3, 3), normalize=False)
    out = np.zeros_like(hue)
    for k in range(2):
        out[..., k] = cv2.boxFilter(np.ascontiguousarray(hue[..., k]), -1, (3, 3), normalize=False) / np.maximum(count, 1)
    return out


def _clear(observed: np.ndarray, structure: np.ndarray) -> np.ndarray:
    return observed * (1.0 - cv2.dilate(structure, _KERNEL))


@dataclass(frozen=True)
class Alignment:
    """A 2-D similarity ``uv_match = A[:, :2] @ uv_query + A[:, 2]`` of levelled cells, with its score."""

    score: float
    A: np.ndarray  # [2,3]
    yaw_deg: float
    scale: float


def free_space_peaks(query: CellMap, match: CellMap, cell: float, yaws_deg: np.ndarray, scales: np.ndarray,
                     count: int = 3, near: tuple[np.ndarray, float] | None = None,
                     max_pixels: int = 4_000_000) -> list[Alignment]:
    """The ``count`` best distinct alignments of ``query``'s cells onto ``match``'s over every yaw in
    ``yaws_deg``, scale in ``scales`` (about the query's structure centroid) and every overlapping shift,
    by ``agreements - conflicts`` (module docstring), best first. ``near`` = (point [2], radius) keeps
    only shifts that put the query's centroid within ``radius`` of ``point``. Alternatives closer than
    three cells (at a yaw within 20 deg) to a better one are dropped."""
    if not query.structure.any() or not match.structure.any():
        return []
    centre = query.uv[query.structure].mean(0)
    reach = float(np.max(np.linalg.norm(query.uv - centre, axis=1))) * float(np.max(scales)) + cell
    pad = int(np.ceil(2 * reach / cell)) + 1
    m_lo = match.uv.min(0) - pad * cell
    m_shape = tuple(int(x) for x in np.ceil((match.uv.max(0) - m_lo) / cell) + pad + 1)
    if m_shape[0] * m_shape[1] > max_pixels:  # footprints this large are not one place
        return []
    plans = []  # per yaw and scale: the query's cells there and the window positions to score
    for s in scales:
        for yaw in yaws_deg:
            a = np.radians(yaw)
            sR = float(s) * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            rs = (query.uv - centre) @ sR.T
            lo = rs.min(0)
            shape = tuple(int(x) for x in np.ceil((rs.max(0) - lo) / cell) + 1)
            # window positions (i, j): the query's centroid lands at m_lo - lo + (i, j) cell
            i0, i1 = np.zeros(2, int), np.array(m_shape) - np.array(shape)
            if near is not None:
                i0 = np.maximum(i0, np.floor((near[0] - near[1] - m_lo + lo) / cell).astype(int))
                i1 = np.minimum(i1, np.ceil((near[0] + near[1] - m_lo + lo) / cell).astype(int))
            if not np.any(i1 < i0):
                plans.append((float(yaw), float(s), sR, rs, lo, shape, i0, i1))
    if not plans:
        return []
    # the match's rasters only where some window reads them, one cell beyond for the 3 x 3 filters (the same
    # values there as over the whole padded map)
    r0 = np.maximum(np.min([i0 for *_, i0, _ in plans], axis=0) - 1, 0)
    r1 = np.minimum(np.max([i1 + shape for *_, shape, _, i1 in plans], axis=0) + 1, m_shape)
    crop = (int(r1[0] - r0[0]), int(r1[1] - r0[1]))
    ij_m = np.floor((match.uv - m_lo) / cell).astype(np.int64) - r0
    inside = np.all((ij_m >= 0) & (ij_m < np.asarray(crop)), axis=1)
    on = inside & match.structure
    b_struct = _raster_cells(ij_m[on], crop)
    b_near = cv2.dilate(b_struct, _KERNEL)
    b_clear = _clear(_raster_cells(ij_m[inside], crop), b_struct)
    coloured = query.coloured and match.coloured
    if coloured:  # agreements weighted by 1 - |a||b| + a.b (colour_match before its clipping)
        b_hue = _near_hue(_hue_raster_cells(ij_m[on], match.hue[on], crop))
        b_colour = [np.ascontiguousarray(b_hue[..., 0]), np.ascontiguousarray(b_hue[..., 1]),
                    np.linalg.norm(b_hue, axis=-1).astype(np.float32)]
    found: list[Alignment] = []
    for yaw, s, sR, rs, lo, shape, i0, i1 in plans:
        ij = np.floor((rs - lo) / cell).astype(np.int64)  # inside the template by construction
        a_struct = _raster_cells(ij[query.structure], shape)
        a_clear = _clear(_raster_cells(ij, shape), a_struct)
        w0 = i0 - r0
        win = (slice(w0[0], i1[0] - r0[0] + shape[0]), slice(w0[1], i1[1] - r0[1] + shape[1]))
        score = (cv2.matchTemplate(b_near[win], a_struct, cv2.TM_CCORR)
                 - cv2.matchTemplate(b_clear[win], a_struct, cv2.TM_CCORR)
                 - cv2.matchTemplate(b_struct[win], a_clear, cv2.TM_CCORR))
        if coloured:
            hue = _hue_raster_cells(ij[query.structure], query.hue[query.structure], shape)
            a_colour = [np.ascontiguousarray(hue[..., 0]), np.ascontiguousarray(hue[..., 1]),
                        np.linalg.norm(hue, axis=-1).astype(np.float32)]
            for sign, b_img, a_img in zip((1.0, 1.0, -1.0), b_colour, a_colour, strict=True):
                score += sign * cv2.matchTemplate(b_img[win], a_img, cv2.TM_CCORR)
        is_max = (score >= cv2.dilate(score, _KERNEL)) & (score > 0)
        ii, jj = np.nonzero(is_max)
        offset = m_lo + i0 * cell - lo - sR @ centre
        for k in np.argsort(-score[ii, jj])[: 2 * count]:
            A = np.empty((2, 3))
            A[:, :2], A[:, 2] = sR, offset + np.array([ii[k], jj[k]]) * cell
            found.append(Alignment(float(score[ii[k], jj[k]]), A, yaw, s))
    found.sort(key=lambda g: -g.score)
    out: list[Alignment] = []
    for g in found:
        at = g.A[:, :2] @ centre + g.A[:, 2]
        if all(np.linalg.norm(at - (o.A[:, :2] @ centre + o.A[:, 2])) >= 3 * cell
               or abs((g.yaw_deg - o.yaw_deg + 180) % 360 - 180) > 20 for o in out):
            out.append(g)
            if len(out) == count:
                break
    return out


def _lift(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def search_alignments(src: np.ndarray, dst: np.ndarray, up_src: np.ndarray, up_dst: np.ndarray, unit: float,
                      prior: np.ndarray, max_log_scale: float, max_yaw_deg: float, max_shift: float, count: int,
                      config: SearchConfig | None = None, hue_src: np.ndarray | None = None,
                      hue_dst: np.ndarray | None = None, scale_cue: tuple[float, float] | None = None
                      ) -> list[tuple[np.ndarray, float]]:
    """Up to ``count`` candidate similarities ``T`` [4,4] with ``T src ~ dst`` from the two clouds (each in
    its own frame; ``unit``: one tile in ``dst``'s frame), best first, each with its free-space
    agreement (module docstring).

    The search covers what odometry can have drifted away from ``prior`` (the current estimate's
    ``T``): yaws within ``max_yaw_deg`` (180: the full circle), scales within ``exp(+-max_log_scale)``
    and shifts that move the query's centroid by at most ``max_shift`` (``dst`` units; inf: anywhere the
    two overlap). The result depends on ``prior`` only through these bounds. With the points' hue
    vectors (:func:`hue_vectors`), structure agrees by its colour too. ``scale_cue`` = (scale, tolerance):
    an independent measurement of ``T``'s scale (:func:`camera_height`): only scales within
    ``exp(+-tolerance)`` of it (and within the bounds) are searched; [] when the two ranges do not meet.
    """
    c = config or SearchConfig()
    Rs, Rd = up_frame(up_src), up_frame(up_dst)
    P = _lift(Rd) @ prior @ _lift(Rs.T)  # the prior between the levelled frames
    s_p = float(np.cbrt(np.linalg.det(P[:3, :3])))
    yaw_p = float(np.degrees(np.arctan2(P[1, 0], P[0, 0])))
    cs = (s_p * src) @ Rs.T  # the query in the match's unit
    cd = dst @ Rd.T
    gs, gd = (float(np.percentile(x[:, 2], c.ground_percentile)) for x in (cs, cd))
    h = c.structure_height_tiles * unit
    cell = c.cell_tiles * unit
    maps = {k: (CellMap.of(cs, k, gs + h, hue_src), CellMap.of(cd, k, gd + h, hue_dst)) for k in (cell, 2 * cell)}
    if min(m.structure.sum() for m in maps[2 * cell]) < c.min_structure_cells:
        return []
    lo_s, hi_s = -max_log_scale, max_log_scale  # log-scales about the prior's
    if scale_cue is not None:
        centre = float(np.log(scale_cue[0] / s_p))
        lo_s, hi_s = max(lo_s, centre - scale_cue[1]), min(hi_s, centre + scale_cue[1])
        if lo_s > hi_s:
            return []
    n = max(1, int(np.ceil((hi_s - lo_s) / (2 * c.scale_step))))
    scales = np.exp(np.linspace(lo_s, hi_s, 2 * n + 1))
    step = (hi_s - lo_s) / (2 * n)
    half = min(float(max_yaw_deg), 180.0)
    yaws = yaw_p + (np.arange(-180.0, 180.0, c.yaw_step_deg) if half >= 180.0 else
                    np.linspace(-half, half, 2 * max(1, int(np.ceil(half / c.yaw_step_deg))) + 1))

    def near(m: CellMap) -> tuple[np.ndarray, float] | None:
        if not np.isfinite(max_shift):
            return None
        centre = m.uv[m.structure].mean(0)
        at = P[:2, :2] @ (centre / s_p) + P[:2, 3]  # where the prior puts the query's structure centroid
        return at, float(max_shift)

    coarse = [g for sc in scales
              for g in free_space_peaks(*maps[2 * cell], 2 * cell, yaws, np.array([sc]), c.candidates_per_scale,
                                        near=near(maps[2 * cell][0]))]
    coarse = sorted(coarse, key=lambda g: -g.score)[: c.refine]
    q_fine = maps[cell][0]
    centre = q_fine.uv[q_fine.structure].mean(0)
    ranked = []
    agreements: dict[bytes, tuple[float, int]] = {}  # peaks that refine to one alignment are measured once
    offsets = np.arange(-1.0, 1.01, 0.5)
    for g in coarse:
        yaws_g, scales_g = g.yaw_deg + offsets * c.yaw_step_deg / 2, g.scale * np.exp(offsets * step / 2)
        near_g = (g.A[:, :2] @ centre + g.A[:, 2], 3 * cell)
        if c.refine_descent:
            fine = free_space_peaks(*maps[cell], cell, yaws_g, np.array([g.scale]), count=1, near=near_g)
            yaw = fine[0].yaw_deg if fine else g.yaw_deg
            fine += free_space_peaks(*maps[cell], cell, np.array([yaw]), np.delete(scales_g, 2), count=1,
                                     near=near_g)
            fine.sort(key=lambda a: -a.score)
        else:
            fine = free_space_peaks(*maps[cell], cell, yaws_g, scales_g, count=1, near=near_g)
        best = fine[0] if fine else g
        G = np.eye(4)
        G[:2, :2], G[:2, 3] = best.A[:, :2], best.A[:, 2]
        G[2, 2], G[2, 3] = best.scale, gd - best.scale * gs
        key = G.tobytes()
        if key not in agreements:
            agreements[key] = free_space_agreement(transform_points(G, cs), cd, cell, gd + h, src_hue=hue_src,
                                                   dst_hue=hue_dst)
        agree, cells = agreements[key]
        T = _lift(Rd.T) @ G @ _lift(Rs) @ np.diag([s_p, s_p, s_p, 1.0])
        ranked.append((agree if cells >= c.min_agreement_cells else 0.0, best.score, T))
    ranked.sort(key=lambda r: (-r[0], -r[1]))
    return [(T, agree) for agree, _, T in ranked[:count]]
