"""Keyframe selection by Lucas-Kanade mean disparity (SPEC 3.2).

A frame becomes a keyframe when the mean displacement of corners tracked from the last keyframe
exceeds ``tau_disparity`` pixels (original resolution), or when fewer than ``min_tracked`` corners
survive tracking (textureless or blurred frames, cuts), or when fewer than ``min_track_ratio`` (25 %)
of the reference's corners still track: forward motion (driving, walking down a street) zooms the view
while the mean flow stays small, and without this rule keyframes there were 7-10 m apart on a rendered
street, too far for structure-from-motion (docs/frontend.md). The first frame is always a keyframe.
Corners: Shi-Tomasi, up to 1000, quality 0.01, min distance 8; pyramidal LK 21x21, 3 levels.
The disparity is the mean over the corners LK reports found (as in the paper). Whether tracking is
lost is decided on corners that also pass a forward-backward check (tracked back to within
``max_fb_error`` px of where they started), because LK alone reports "found" on textureless frames.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeyframeConfig:
    tau_disparity: float = 40.0
    max_corners: int = 1000
    quality_level: float = 0.01
    min_distance: float = 8.0
    lk_window: int = 21
    lk_levels: int = 3
    min_tracked: int = 10
    max_fb_error: float = 1.0
    min_track_ratio: float = 0.25  # keyframe when fewer than this fraction of the reference's corners track
    # (0 = off; forward motion zooms the view while the mean flow stays small, see docs/frontend.md)


@dataclass(frozen=True)
class KeyframeDecision:
    is_keyframe: bool
    disparity: float  # mean LK displacement from the last keyframe, px (nan when not tracked)
    tracked: int  # corners tracked from the last keyframe
    reason: str  # "first", "disparity", "tracking-lost", "" (not a keyframe)


class KeyframeSelector:
    """Stateful selector: feed frames in order with :meth:`update`."""

    def __init__(self, config: KeyframeConfig | None = None) -> None:
        self.config = config or KeyframeConfig()
        self._ref_gray: np.ndarray | None = None
        self._ref_pts: np.ndarray | None = None

    def _corners(self, gray: np.ndarray) -> np.ndarray | None:
        c = self.config
        pts = cv2.goodFeaturesToTrack(gray, maxCorners=c.max_corners, qualityLevel=c.quality_level,
                                      minDistance=c.min_distance)
        return pts if pts is not None and len(pts) else None

    def _set_reference(self, gray: np.ndarray) -> None:
        self._ref_gray = gray
        self._ref_pts = self._corners(gray)

    def update(self, image: np.ndarray) -> KeyframeDecision:
        """``image`` RGB uint8 [H,W,3] (or gray [H,W]) -> decision; a keyframe becomes the new reference."""
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        if self._ref_gray is None:
            self._set_reference(gray)
            return KeyframeDecision(True, float("nan"), 0, "first")
        if self._ref_gray.shape != gray.shape:
            log.warning("frame size changed from %s to %s: forcing a keyframe", self._ref_gray.shape, gray.shape)
            self._set_reference(gray)
            return KeyframeDecision(True, float("nan"), 0, "tracking-lost")
        c = self.config
        tracked, disparity = 0, float("nan")
        if self._ref_pts is not None:
            lk = dict(winSize=(c.lk_window, c.lk_window), maxLevel=c.lk_levels - 1)
            nxt, status, _ = cv2.calcOpticalFlowPyrLK(self._ref_gray, gray, self._ref_pts, None, **lk)
            back, status_b, _ = cv2.calcOpticalFlowPyrLK(gray, self._ref_gray, nxt, None, **lk)
            fb = np.linalg.norm((back - self._ref_pts).reshape(-1, 2), axis=1)
            found = status.reshape(-1).astype(bool)
            tracked = int((found & status_b.reshape(-1).astype(bool) & (fb < c.max_fb_error)).sum())
            if found.any():
                d = np.linalg.norm((nxt - self._ref_pts).reshape(-1, 2)[found], axis=1)
                disparity = float(d.mean())
        if tracked < c.min_tracked:
            self._set_reference(gray)
            return KeyframeDecision(True, disparity, tracked, "tracking-lost")
        if disparity > c.tau_disparity:
            self._set_reference(gray)
            return KeyframeDecision(True, disparity, tracked, "disparity")
        if c.min_track_ratio > 0 and tracked < c.min_track_ratio * len(self._ref_pts):
            self._set_reference(gray)
            return KeyframeDecision(True, disparity, tracked, "tracks-fading")
        return KeyframeDecision(False, disparity, tracked, "")
