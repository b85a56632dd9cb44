"""Checks of a COLMAP submap reconstruction against its own two-view geometry.

Incremental SfM can settle into a *folded* reconstruction: every observation fits (mean reprojection error
well under a pixel), yet a run of cameras is turned by 5-30 degrees. On a rendered forward drive
(704x214, KITTI-like) the first attempt of one submap bent the cameras of a turn by 5-15 degrees per
keyframe, and the next submap, anchored on them, carried the error on: ATE 12 m on 390 m. Another
initial pair or seed reconstructs the same images correctly.

The check reads the keyframe pairs' verified matches from the submap's feature database and asks, for
each pair of consecutive registered keyframes, whether the reconstruction's relative pose explains them:

* ``agree``: the fraction of the pair's verified matches within ``max_error_px`` (Sampson distance) of
  the epipolar geometry of the reconstruction's relative pose;
* ``best``: the same fraction for the relative pose estimated from those matches alone (LO-RANSAC,
  seeded: deterministic);
* ``rotation_deg``: the angle between the two relative rotations.

* ``shared_points``: the reconstruction's 3-D points observed in both keyframes.

A pair is *inconsistent* when

* *folded*: the reconstruction explains clearly fewer matches than the two-view estimate
  (``best - agree > margin``) and the rotations differ by more than ``min_rotation_deg``. Both are
  needed: a pair with little translation fits any translation direction, and its two-view rotation can
  be poor while the reconstruction still explains its matches; or
* *disconnected*: the reconstruction triangulated almost none of the pair's matches as shared points
  (``shared_points < min_shared_fraction * matches``), or hardly any 3-D point is seen on both sides of
  the pair (``spanning_points < min_spanning_points``; also judged for pairs with too few matches). Two
  blocks of keyframes joined there have no common structure, so the distance between them, hence their
  relative scale, is unconstrained: on the rendered drive the global mapper placed keyframe 499 17 m
  from 497 (1.5 m in truth), while the forward motion's epipolar geometry still fitted. Sound
  consecutive pairs share 30-87 % of their matches as points.

Measured margins are in docs/frontend.md ("Folded submaps").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairCheck:
    """Two consecutive registered keyframes of a reconstruction against their verified matches."""

    first: str  # image names
    second: str
    matches: int  # verified matches of the pair
    agree: float  # fraction explained by the reconstruction's relative pose
    best: float  # fraction explained by the pair's own two-view estimate
    rotation_deg: float  # angle between the two relative rotations (NaN without a two-view estimate)
    shared_points: int = -1  # 3-D points of the reconstruction observed in both keyframes (-1: not counted)
    spanning_points: int = -1  # 3-D points seen on both sides of the pair (before and from its second image on)

    def folded(self, config: FoldCheckConfig) -> bool:
        return self.best - self.agree > config.margin and self.rotation_deg > config.min_rotation_deg

    def disconnected(self, config: FoldCheckConfig) -> bool:
        return (0 <= self.shared_points < config.min_shared_fraction * self.matches
                or 0 <= self.spanning_points < config.min_spanning_points)


@dataclass(frozen=True)
class FoldCheckConfig:
    min_matches: int = 30  # pairs with fewer verified matches are not judged
    max_error_px: float = 2.0  # Sampson distance, pixels at the camera's mean focal length
    margin: float = 0.1  # best - agree above this ...
    min_rotation_deg: float = 2.0  # ... and a rotation difference above this: folded
    min_shared_fraction: float = 0.05  # fewer shared 3-D points than this fraction of the matches: disconnected
    min_spanning_points: int = 10  # fewer 3-D points seen on both sides of a pair (any pair): disconnected


def _cam_from_world(image) -> np.ndarray:
    T = np.eye(4)
    T[:3] = image.cam_from_world().matrix()
    return T


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _essential(T_2_1: np.ndarray) -> np.ndarray:
    """Essential matrix of the relative pose ``T_cam2_cam1 [4, 4]`` (translation normalised)."""
    t = T_2_1[:3, 3]
    n = np.linalg.norm(t)
    return _skew(t / n if n > 1e-12 else t) @ T_2_1[:3, :3]


def sampson(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances [N] of normalised image points ``x1``, ``x2`` [N, 2] to ``x2^T E x1 = 0``."""
    X1 = np.c_[x1, np.ones(len(x1))]
    X2 = np.c_[x2, np.ones(len(x2))]
    Ex1 = X1 @ E.T
    Etx2 = X2 @ E
    num = np.sum(X2 * Ex1, axis=1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def check_pairs(rec, database: str | Path, seed: int = 0, config: FoldCheckConfig | None = None
                ) -> list[PairCheck]:
    """Every pair of consecutive registered images (by name) of ``rec`` with enough verified matches in
    ``database`` (the feature database ``rec`` was built from: same image ids), checked as the module
    docstring says; a pair with fewer matches only when hardly any 3-D point spans it."""
    import pycolmap

    config = config or FoldCheckConfig()
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    out: list[PairCheck] = []
    db = pycolmap.Database.open(Path(database))
    spanning = _spanning(rec, images)
    nan = float("nan")
    try:
        for k, (a, b) in enumerate(zip(images, images[1:], strict=False)):
            m = np.zeros((0, 2), int)
            if db.exists_two_view_geometry(a.image_id, b.image_id):
                m = np.asarray(db.read_two_view_geometry(a.image_id, b.image_id).inlier_matches).reshape(-1, 2)
            if len(m) < config.min_matches:  # too few matches to judge the pair; only whether anything spans it
                if spanning[k] < config.min_spanning_points:
                    out.append(PairCheck(a.name, b.name, len(m), nan, nan, nan, -1, int(spanning[k])))
                continue
            cam_a, cam_b = rec.cameras[a.camera_id], rec.cameras[b.camera_id]
            p1 = np.asarray(db.read_keypoints(a.image_id))[m[:, 0], :2].astype(np.float64)
            p2 = np.asarray(db.read_keypoints(b.image_id))[m[:, 1], :2].astype(np.float64)
            x1, x2 = cam_a.cam_from_img(p1), cam_b.cam_from_img(p2)
            focal = 0.5 * (cam_a.mean_focal_length() + cam_b.mean_focal_length())
            T_rec = _cam_from_world(b) @ np.linalg.inv(_cam_from_world(a))
            agree = float((sampson(_essential(T_rec), x1, x2) * focal < config.max_error_px).mean())
            ransac = pycolmap.RANSACOptions()
            ransac.max_error = config.max_error_px
            ransac.random_seed = int(seed)
            est = pycolmap.estimate_relative_pose(cam_a, p1, cam_b, p2, ransac)
            best, rotation = float("nan"), float("nan")
            if est is not None:
                T_tv = np.eye(4)
                T_tv[:3] = est["cam2_from_cam1"].matrix()
                best = float((sampson(_essential(T_tv), x1, x2) * focal < config.max_error_px).mean())
                rotation = _angle_deg(T_rec[:3, :3].T @ T_tv[:3, :3])
            shared = len(_point_ids(a) & _point_ids(b))
            out.append(PairCheck(a.name, b.name, len(m), agree, best, rotation, shared, int(spanning[k])))
    finally:
        db.close()
    return out


def _spanning(rec, images) -> np.ndarray:
    """[len(images) - 1]: for each pair of consecutive ``images`` (k, k + 1), the 3-D points of ``rec`` whose
    track has images on both sides of it (one at k or before, one at k + 1 or after)."""
    pos = {im.image_id: k for k, im in enumerate(images)}
    diff = np.zeros(len(images) + 1, np.int64)
    for point in rec.points3D.values():
        ks = [pos[e.image_id] for e in point.track.elements if e.image_id in pos]
        if len(ks) > 1 and min(ks) < max(ks):
            diff[min(ks)] += 1
            diff[max(ks)] -= 1
    return np.cumsum(diff)[:max(len(images) - 1, 0)]


def _point_ids(image) -> set[int]:
    return {p.point3D_id for p in image.points2D if p.has_point3D()}


def inconsistent(checks: list[PairCheck], config: FoldCheckConfig | None = None) -> list[PairCheck]:
    """The pairs of ``checks`` that the reconstruction folds or disconnects (module docstring)."""
    config = config or FoldCheckConfig()
    return [c for c in checks if c.folded(config) or c.disconnected(config)]
