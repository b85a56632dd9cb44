"""A submap's appearance landmarks: image features of a few keyframes, lifted to 3-D by the submap's own
points (issue 18: loops that look alike in their geometry but not in their images).

On streets of facades a submap's points register as well onto a look-alike place tens of metres along the
street as onto the true one (docs/backend.md, "Open"), and nothing the point registration measures tells the
two apart. The images do: the same facade seen again gives the same corners at the same 3-D places, and a
look-alike gives other corners, or the same texture at other places. So every submap keeps, for up to
``LandmarkConfig.keyframes`` of its keyframes (spread evenly over the valid ones), ORB features (binary,
32 bytes: small enough to keep for every submap of a long run, on disk) whose keypoint falls on one of the
submap's own points (within ``max_pixel_gap`` grid spacings): each such feature is a landmark with a
position in the submap's frame and the direction its keyframe saw it from.
:mod:`vggt_slam_pp.backend.appearance` counts the landmarks of two submaps that a loop's alignment brings
together and whose descriptors match, and aligns two submaps by their landmarks alone.

Any backbone whose points carry their pixels (dense VGGT / simulated, sparse COLMAP) gives landmarks; a
sparse backbone's few points give fewer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vggt_slam_pp.frontend.types import Landmarks, SubmapPrediction


@dataclass(frozen=True)
class LandmarkConfig:
    keyframes: int = 12  # keyframes per submap whose features are kept (evenly spread); 0: no landmarks
    features: int = 400  # ORB features detected per keyframe (at most)
    max_pixel_gap: float = 1.5  # a keypoint takes the nearest point of its keyframe within this many of the
    # points' own pixel spacings (the side of the image area they cover, shared among them)


def keyframe_landmarks(pred: SubmapPrediction, images: list[np.ndarray], config: LandmarkConfig) -> Landmarks:
    """The landmarks of one submap: ORB features of up to ``config.keyframes`` of its valid keyframes
    whose keypoints fall on the submap's points (``pred.points[i]`` at ``pred.pixels[i]``, original image
    pixels).

    Args:
        pred: the submap's (filtered) prediction.
        images: [S] the keyframes' RGB uint8 images [H,W,3], in the prediction's order.
    """
    valid = [i for i in range(len(images)) if pred.valid[i] and len(pred.pixels[i]) >= 2]
    if config.keyframes <= 0 or not valid:
        return Landmarks.empty()
    pick = sorted({valid[int(round(k))] for k in np.linspace(0, len(valid) - 1, min(config.keyframes, len(valid)))})
    orb = cv2.ORB_create(nfeatures=config.features)
    xyz, desc, kf, view = [], [], [], []
    for i in pick:
        image = np.ascontiguousarray(images[i], np.uint8)
        kps, d = orb.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
        if d is None or not kps:
            continue
        j = _points_at(np.asarray(pred.pixels[i], float), np.array([kp.pt for kp in kps], float), image.shape[:2],
                       config.max_pixel_gap)
        on = j >= 0
        p = np.asarray(pred.points[i], np.float32)[j[on]]
        ray = p - np.linalg.inv(pred.T_cam_submap[i])[:3, 3]
        xyz.append(p)
        desc.append(d[on])
        kf.append(np.full(len(p), i, np.int16))
        view.append((ray / np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)).astype(np.float32))
    if not xyz:
        return Landmarks.empty()
    return Landmarks(np.concatenate(xyz), np.concatenate(desc), np.concatenate(kf), np.concatenate(view))


def _points_at(pixels: np.ndarray, at: np.ndarray, hw: tuple[int, int], max_gap: float) -> np.ndarray:
    """[K] index of a point whose pixel (``pixels`` [N,2]) is nearest each of ``at`` [K,2] within ``max_gap``
    of the points' pixel spacing, -1 where none is. The spacing is the side of the image area the points
    cover (4-pixel blocks that hold one) shared among them; the points are bucketed in cells of that side,
    one point a cell, and each query looks at its cell and the 8 around it (dense backbones give thousands
    of points a keyframe: a tree or a distance transform per keyframe cost more than the features)."""
    H, W = hw
    if len(pixels) == 0 or len(at) == 0:
        return np.full(len(at), -1)
    px = np.clip(np.rint(pixels).astype(np.int64), 0, [W - 1, H - 1])
    blocks = np.zeros(((H + 3) // 4, (W + 3) // 4), bool)
    blocks[px[:, 1] // 4, px[:, 0] // 4] = True
    spacing = max(1.0, float(np.sqrt(16.0 * blocks.sum() / len(pixels))))
    radius, c = max_gap * spacing, max(1, int(np.ceil(spacing)))
    rows, cols = H // c + 3, W // c + 3  # one empty cell of margin all round
    cell = np.full(rows * cols, -1)
    cell[(px[:, 1] // c + 1) * cols + px[:, 0] // c + 1] = np.arange(len(pixels))
    k = np.clip(np.rint(at).astype(np.int64), 0, [W - 1, H - 1])
    best, best_d = np.full(len(at), -1), np.full(len(at), np.inf)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            j = cell[(k[:, 1] // c + 1 + dy) * cols + k[:, 0] // c + 1 + dx]
            d = np.where(j >= 0, np.linalg.norm(pixels[np.maximum(j, 0)] - at, axis=1), np.inf)
            better = (d < best_d) & (d <= radius)
            best[better], best_d[better] = j[better], d[better]
    return best
