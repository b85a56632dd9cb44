"""Whether two submaps' images agree with a loop's alignment (issue 18: look-alike places).

A loop verified from points (:mod:`~vggt_slam_pp.backend.registration`) says that the query's geometry fits
the match's at some alignment. On streets of facades a look-alike place tens of metres along the street fits
as well, and no figure of the point registration separates the two (docs/backend.md, "Open"). The submaps'
keyframe images can: each submap keeps ORB features lifted onto its own points (its *landmarks*,
:mod:`vggt_slam_pp.frontend.landmarks`). At the loop's alignment, a landmark of the query should lie where
the match saw the same corner, within ``radius_tiles``, with a similar descriptor (Hamming distance at most
``max_hamming`` of 256 bits), much more often than at a wrong alignment.

Images can only agree where both submaps saw the same surface from similar directions: where two passes
cross at right angles, or drive a street the other way round, the same facade shows other corners or its
other side, and a right loop finds no agreeing feature. So only the query's landmarks that land near a match
landmark seen from within ``max_view_angle_deg`` of the same direction are *comparable*;
:func:`appearance_support` counts those and, of them, the ones whose descriptors agree. Where few are
comparable the images cannot say (the loop is then judged by its points alone).

The same landmarks also *find* an alignment (:func:`landmark_alignment`): mutual nearest descriptors across
the two submaps, and the similarity most of them agree on (RANSAC). Under drift of a few per cent the
estimate-free search can miss a revisit that the images see plainly (``bench loops --noise realistic``,
KITTI 07-driven: 44 -> 0, 184 of 196 matches within a tile, 0.4 m from the truth); registration refines it
from there (``landmarks`` guess) and verifies it like any other.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vggt_slam_pp.errors import GeometryError
from vggt_slam_pp.frontend.types import Landmarks
from vggt_slam_pp.geometry.alignment import umeyama
from vggt_slam_pp.geometry.lie import decompose_sim3, sim3_inverse, transform_points

LANDMARKS_GUESS = "landmarks"  # the name of the initial guess taken from the landmarks' own alignment


@dataclass(frozen=True)
class AppearanceConfig:
    enabled: bool = True  # check loops against the two submaps' landmarks where both kept them
    radius_tiles: float = 1.0  # a query landmark agrees when a match landmark lies this close after the alignment
    max_hamming: int = 50  # ... with an ORB descriptor at most this many bits away (of 256)
    max_view_angle_deg: float = 30.0  # ... seen from within this angle of the same direction (else not comparable)
    min_comparable: int = 50  # fewer comparable landmarks: the images cannot judge the loop
    min_agreeing: int = 5  # where they can, fewer agreeing ones: the images disagree, the loop is refused
    # (verified look-alikes 7.7-98.6 m off scored 0-1 on the bench worlds, right loops 5-331: docs/backend.md);
    # <= 0: never refused
    guess: bool = True  # registration also starts from the alignment of the two submaps' landmarks
    guess_min_inliers: int = 12  # ... when at least this many mutual descriptor matches agree on it
    # the landmarks *confirm* a verified loop when their own alignment (needs guess on), from at least
    # confirm_min_inliers agreeing matches, is the loop's within these (a lone loop may then correct up to
    # BackendConfig.lone_confirmed_sigmas):
    confirm_min_inliers: int = 30
    confirm_deg: float = 3.0  # rotation between the two alignments
    confirm_log_scale: float = 0.05  # |log| of their scale ratio
    confirm_radius_share: float = 0.5  # median distance between the two alignments' placements of the agreeing
    # query landmarks, as a share of radius_tiles


@dataclass(frozen=True)
class ImageCheck:
    """The two submaps' landmarks, for one loop candidate
    (:func:`~vggt_slam_pp.backend.registration.register_loop`): an alignment they agree on, and whether they
    agree with any alignment. ``radius`` in match frame units."""

    query: Landmarks
    match: Landmarks
    radius: float
    config: AppearanceConfig
    seed: int = 0

    def guesses(self) -> dict[str, np.ndarray]:
        """``{"landmarks": T_match_query}`` (:func:`landmark_alignment`), or {} when too few agree."""
        found = self.alignment
        return {LANDMARKS_GUESS: found.T_match_query} if found is not None else {}

    @cached_property
    def alignment(self) -> LandmarkAlignment | None:
        """The alignment the two submaps' landmarks agree on (:func:`landmark_alignment`), or None (too few
        agree, or ``config.guess`` off)."""
        if not self.config.guess:
            return None
        return landmark_alignment(self.query, self.match, self.radius, self.config.max_hamming,
                                  self.config.guess_min_inliers, self.seed)

    @property
    def can_confirm(self) -> bool:
        """Whether the landmarks' own alignment rests on enough agreeing matches (``confirm_min_inliers``) to
        confirm a loop (:meth:`confirms`)."""
        found = self.alignment
        return found is not None and found.inliers >= self.config.confirm_min_inliers

    def confirms(self, T_match_query: np.ndarray) -> bool:
        """Whether the landmarks' own alignment (:attr:`alignment`, from at least ``confirm_min_inliers``
        agreeing matches) is ``T_match_query`` [4,4] within ``confirm_deg``, ``confirm_log_scale`` and, at
        the agreeing query landmarks, ``confirm_radius_share`` of the radius: the pose the points verified
        (structure, free space) is the one the images' matches agree on. For a loop refined from the
        landmarks' guess, whose ICP holds those pairs (``register_loop``), the two are not independent in
        pose; the points' verification and the landmarks' consensus still are. False without an alignment
        (``config.guess`` off, or too few agree)."""
        c, found = self.config, self.alignment
        if not self.can_confirm:
            return False
        s, R, _ = decompose_sim3(sim3_inverse(found.T_match_query) @ np.asarray(T_match_query, float))
        angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
        apart = np.linalg.norm(transform_points(T_match_query, found.query_xyz)
                               - transform_points(found.T_match_query, found.query_xyz), axis=1)
        return bool(angle <= c.confirm_deg and abs(np.log(s)) <= c.confirm_log_scale
                    and np.median(apart) <= c.confirm_radius_share * self.radius)

    def support(self, T_match_query: np.ndarray) -> AppearanceSupport:
        return appearance_support(self.query, self.match, T_match_query, self.radius, self.config.max_hamming,
                                  self.config.max_view_angle_deg)

    def disagrees(self, support: AppearanceSupport) -> bool:
        """Whether the images can judge an alignment (enough comparable landmarks) and reject it."""
        return support.comparable >= self.config.min_comparable and support.agreeing < self.config.min_agreeing


@dataclass(frozen=True)
class LandmarkAlignment:
    """What :func:`landmark_alignment` found: the alignment and the landmark pairs that agree with it."""

    T_match_query: np.ndarray  # [4,4] Sim(3)
    query_xyz: np.ndarray  # [K,3] the agreeing query landmarks, query frame
    match_xyz: np.ndarray  # [K,3] their matches, match frame

    @property
    def inliers(self) -> int:
        return len(self.query_xyz)


@dataclass(frozen=True)
class AppearanceSupport:
    agreeing: int  # comparable query landmarks with a similar match landmark (descriptor within the limit)
    comparable: int  # query landmarks that the alignment brings within the radius of a match landmark seen from
    # a similar direction

    @property
    def share(self) -> float:
        return self.agreeing / self.comparable if self.comparable else 0.0


def _popcount(x: np.ndarray) -> np.ndarray:
    """[K] number of set bits of each row of ``x`` [K,B] uint8."""
    return np.unpackbits(x, axis=1).sum(1)


def appearance_support(query: Landmarks, match: Landmarks, T_match_query: np.ndarray, radius: float,
                       max_hamming: int, max_view_angle_deg: float = 30.0) -> AppearanceSupport:
    """Of ``query``'s landmarks moved into the match's frame by ``T_match_query`` [4,4] (Sim(3)): how many
    have a landmark of ``match`` within ``radius`` (match frame units) seen from within
    ``max_view_angle_deg`` of the same direction (comparable), and how many of those have one whose ORB
    descriptor is at most ``max_hamming`` bits away (agreeing)."""
    if len(query) == 0 or len(match) == 0:
        return AppearanceSupport(0, 0)
    moved = transform_points(T_match_query, np.asarray(query.xyz, float))
    near = cKDTree(np.asarray(match.xyz, float)).query_ball_point(moved, radius)
    counts = np.fromiter((len(n) for n in near), int, len(near))
    if not counts.any():
        return AppearanceSupport(0, 0)
    qi = np.repeat(np.arange(len(near)), counts)
    mj = np.fromiter((j for n in near for j in n), int, int(counts.sum()))
    R = np.asarray(T_match_query, float)[:3, :3]
    R = R / np.cbrt(np.linalg.det(R))  # the rotation of the similarity
    q_view = np.asarray(query.view, float) @ R.T
    cos = np.einsum("ij,ij->i", q_view[qi], np.asarray(match.view, float)[mj])
    similar = cos >= np.cos(np.radians(max_view_angle_deg))
    qi, mj = qi[similar], mj[similar]
    dist = _popcount(np.bitwise_xor(query.descriptors[qi], match.descriptors[mj]))
    return AppearanceSupport(len(np.unique(qi[dist <= max_hamming])), len(np.unique(qi)))


def landmark_alignment(query: Landmarks, match: Landmarks, radius: float, max_hamming: int, min_inliers: int,
                       seed: int = 0, hypotheses: int = 256) -> LandmarkAlignment | None:
    """The alignment of ``query``'s landmarks onto ``match``'s from the landmarks alone: mutual nearest ORB
    descriptors at most ``max_hamming`` bits apart, and the similarity that takes the most query landmarks within ``radius``
    (match frame units) of their match's: the best of ``hypotheses`` 3-point Umeyama similarities (seeded
    draws, solved all at once), refitted on its inliers; None when fewer than ``min_inliers`` agree."""
    if len(query) < 3 or len(match) < 3:
        return None
    pairs = [m for m in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(query.descriptors, match.descriptors)
             if m.distance <= max_hamming]
    if len(pairs) < max(min_inliers, 3):
        return None
    src = np.asarray(query.xyz, float)[[m.queryIdx for m in pairs]]
    dst = np.asarray(match.xyz, float)[[m.trainIdx for m in pairs]]
    rng = np.random.default_rng(seed)
    pick = np.argsort(rng.random((hypotheses, len(src))), axis=1)[:, :3]  # 3 distinct pairs a hypothesis
    T = _similarities(src[pick], dst[pick])
    moved = np.einsum("kij,nj->kni", T[:, :3, :3], src) + T[:, None, :3, 3]
    inliers = np.linalg.norm(moved - dst, axis=2) <= radius
    best = inliers[np.argmax(inliers.sum(1))]
    for _ in range(2):  # refit on the inliers, which may then grow
        if best.sum() < 3:
            return None
        try:
            fit = umeyama(src[best], dst[best])
        except GeometryError:
            return None
        best = np.linalg.norm(transform_points(fit, src) - dst, axis=1) <= radius
    if int(best.sum()) < min_inliers:
        return None
    return LandmarkAlignment(fit, src[best], dst[best])


def _similarities(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[K,4,4] Umeyama similarities ``T_dst_src`` of K point sets ``src``, ``dst`` [K,M,3] at once (degenerate
    sets give some similarity; they gather no inliers)."""
    mu_s, mu_d = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    xs, xd = src - mu_s, dst - mu_d
    var_s = np.maximum((xs**2).sum((1, 2)) / src.shape[1], 1e-18)
    U, D, Vt = np.linalg.svd(np.einsum("kmi,kmj->kij", xd, xs) / src.shape[1])
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    S = np.ones((len(src), 3))
    S[:, 2] = np.where(sign < 0, -1.0, 1.0)
    R = np.einsum("kij,kj,kjl->kil", U, S, Vt)
    scale = (D * S).sum(1) / var_s
    T = np.zeros((len(src), 4, 4))
    T[:, :3, :3] = scale[:, None, None] * R
    T[:, :3, 3] = mu_d[:, 0] - np.einsum("kij,kj->ki", T[:, :3, :3], mu_s[:, 0])
    T[:, 3, 3] = 1.0
    return T
