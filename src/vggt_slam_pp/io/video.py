"""Video files as a frame source (OpenCV decoding), with a frame stride or a target frame rate."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vggt_slam_pp.errors import InputError
from vggt_slam_pp.io.frames import Frame, FrameSource
from vggt_slam_pp.io.images import to_rgb_uint8

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")

__all__ = ["VIDEO_EXTENSIONS", "VideoSource"]


class VideoSource(FrameSource):
    """Frames of a video file.

    Args:
        path: the video file.
        stride: keep every ``stride``-th decoded frame.
        target_fps: if given, overrides ``stride`` with ``round(native_fps / target_fps)`` (at least 1).

    Timestamps are ``decoded_index / native_fps`` seconds. Sequential iteration decodes each frame once;
    random access seeks.
    """

    layout = "video"
    _cap: cv2.VideoCapture | None = None

    def __init__(self, path: Path, stride: int = 1, target_fps: float | None = None) -> None:
        super().__init__(path)
        if not self.root.is_file():
            raise InputError(f"video not found: {path}")
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise InputError(f"cannot open video (corrupt or unsupported codec): {path}")
        self.native_fps = float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        if count <= 0:
            raise InputError(f"video has no frames: {path}")
        if target_fps is not None:
            if target_fps <= 0:
                raise InputError(f"target fps must be positive, got {target_fps}")
            stride = max(1, int(round(self.native_fps / target_fps)))
        if stride < 1:
            raise InputError(f"stride must be >= 1, got {stride}")
        self.stride = stride
        self._decoded = np.arange(0, count, stride)
        self._next = -1  # decoded index the open capture will return next

    def __len__(self) -> int:
        return len(self._decoded)

    @property
    def timestamps(self) -> np.ndarray:
        return self._decoded / self.native_fps

    def _read_decoded(self, k: int) -> np.ndarray:
        if self._cap is None:
            self._cap = cv2.VideoCapture(str(self.root))
            self._next = 0
        if k < self._next or k - self._next > 4 * self.stride + 30:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, k)
            self._next = k
        while self._next < k:
            if not self._cap.grab():
                break
            self._next += 1
        ok, img = self._cap.read()
        if not ok or img is None:
            raise InputError(f"cannot decode frame {k} of {self.root}")
        self._next = k + 1
        return img

    def _load(self, i: int) -> Frame:
        k = int(self._decoded[i])
        img = to_rgb_uint8(self._read_decoded(k), str(self.root))
        return Frame(i, float(k / self.native_fps), img, None, None, f"{self.root.name}#{k}")

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __del__(self) -> None:
        self.close()
