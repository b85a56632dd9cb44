"""The ``Frame`` record and the ``FrameSource`` interface shared by every input reader."""

from __future__ import annotations

import dataclasses
import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import InputError
from vggt_slam_pp.geometry.camera import PinholeCamera
from vggt_slam_pp.io.images import read_depth, read_rgb
from vggt_slam_pp.io.trajectory import Trajectory, nearest_time_indices

log = logging.getLogger(__name__)

__all__ = ["Frame", "FrameSource", "ImageSequence", "GT_MAX_DIFF"]

GT_MAX_DIFF = 0.01
"""Default maximum time difference (s) when matching frames to ground-truth poses (evo's default)."""


@dataclass(frozen=True, eq=False)
class Frame:
    """One input frame.

    Attributes:
        index: position in the source (0-based, after any stride).
        timestamp: seconds.
        image: RGB uint8 ``[H, W, 3]``.
        depth: optional z-depth in metres ``[H, W]`` float32, 0 where unknown.
        intrinsics: optional camera (with its distortion) when the source knows it.
        name: file name or other label of the frame.
    """

    index: int
    timestamp: float
    image: np.ndarray
    depth: np.ndarray | None = None
    intrinsics: PinholeCamera | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[2] != 3 or self.image.dtype != np.uint8:
            raise InputError(f"frame {self.index}: image must be uint8 [H, W, 3], got {self.image.dtype} "
                             f"{self.image.shape}")
        if self.depth is not None and self.depth.shape != self.image.shape[:2]:
            raise InputError(f"frame {self.index}: depth {self.depth.shape} does not match image "
                             f"{self.image.shape[:2]}")

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])


class FrameSource(ABC):
    """A finite, indexable sequence of frames with optional ground truth.

    Subclasses load frames lazily; iterating yields :class:`Frame` objects in order.
    """

    layout: str = "unknown"

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._gt_override: Trajectory | None = None

    @abstractmethod
    def __len__(self) -> int: ...

    @property
    @abstractmethod
    def timestamps(self) -> np.ndarray:
        """``[N]`` seconds of every frame."""

    @abstractmethod
    def _load(self, i: int) -> Frame: ...

    @property
    def camera(self) -> PinholeCamera | None:
        """Calibration of the source's camera at its native resolution, when the layout provides it."""
        return None

    def _native_ground_truth(self) -> Trajectory | None:
        return None

    def ground_truth(self) -> Trajectory | None:
        """Ground-truth camera poses ``T_world_cam`` (the dataset's world frame), or None."""
        return self._gt_override if self._gt_override is not None else self._native_ground_truth()

    def set_ground_truth(self, gt: Trajectory) -> None:
        """Pair the source with an external ground truth (e.g. images + a TUM or KITTI file).

        A trajectory without timestamps (KITTI rows) is matched to frames by index and must have one pose
        per frame.
        """
        if not gt.has_timestamps:
            if len(gt) != len(self):
                raise InputError(f"ground truth without timestamps has {len(gt)} poses but the source has "
                                 f"{len(self)} frames; give a times file or a TUM trajectory")
            gt = Trajectory(self.timestamps.copy(), gt.poses)
        self._gt_override = gt

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for a source of {n} frames")
        return self._load(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._load(i)

    def frame_ground_truth(self, max_diff: float = GT_MAX_DIFF) -> tuple[np.ndarray, Trajectory] | None:
        """Ground truth at the frames: ``(frame_indices [M], Trajectory of M poses)`` for frames whose
        nearest ground-truth pose lies within ``max_diff`` seconds; None without ground truth."""
        gt = self.ground_truth()
        if gt is None or len(gt) == 0:
            return None
        match = nearest_time_indices(self.timestamps, gt.timestamps, max_diff)
        idx = np.nonzero(match >= 0)[0]
        return idx, Trajectory(self.timestamps[idx], gt.poses[match[idx]])

    def info(self) -> dict:
        """What the source contains, as a JSON-friendly dictionary."""
        n = len(self)
        if n == 0:
            raise InputError(f"source has no frames: {self.root}")
        first = self[0]
        ts = self.timestamps
        gt = self.ground_truth()
        matched = self.frame_ground_truth()
        cam = self.camera
        duration = float(ts[-1] - ts[0]) if n > 1 else 0.0
        return {
            "layout": self.layout,
            "path": str(self.root),
            "frames": n,
            "width": first.width,
            "height": first.height,
            "time_start": float(ts[0]),
            "time_end": float(ts[-1]),
            "duration_s": duration,
            "fps": (n - 1) / duration if duration > 0 else None,
            "has_depth": first.depth is not None,
            "intrinsics": cam.to_dict() if cam is not None else None,
            "ground_truth": gt is not None,
            "ground_truth_poses": len(gt) if gt is not None else 0,
            "frames_with_ground_truth": int(len(matched[0])) if matched is not None else 0,
        }


class ImageSequence(FrameSource):
    """Frames stored as image files, with optional depth images, calibration and ground truth.

    Every dataset layout that stores images as files is read into this one class.
    """

    def __init__(
        self,
        root: Path,
        layout: str,
        image_paths: Sequence[Path],
        timestamps: np.ndarray,
        *,
        depth_paths: Sequence[Path | None] | None = None,
        depth_scale: float = 1.0,
        depth_invalid: int | None = None,
        camera: PinholeCamera | None = None,
        ground_truth: Trajectory | None = None,
    ) -> None:
        super().__init__(root)
        self.layout = layout
        self.image_paths = [Path(p) for p in image_paths]
        ts = np.asarray(timestamps, dtype=np.float64)
        if len(ts) != len(self.image_paths):
            raise InputError(f"{root}: {len(self.image_paths)} images but {len(ts)} timestamps")
        if depth_paths is not None and len(depth_paths) != len(self.image_paths):
            raise InputError(f"{root}: {len(self.image_paths)} images but {len(depth_paths)} depth entries")
        self._timestamps = ts
        self.depth_paths = list(depth_paths) if depth_paths is not None else None
        self.depth_scale = float(depth_scale)
        self.depth_invalid = depth_invalid
        self._camera = camera
        self._gt = ground_truth

    def __len__(self) -> int:
        return len(self.image_paths)

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    @property
    def camera(self) -> PinholeCamera | None:
        return self._camera

    def _native_ground_truth(self) -> Trajectory | None:
        return self._gt

    def _load(self, i: int) -> Frame:
        path = self.image_paths[i]
        image = read_rgb(path)
        depth = None
        if self.depth_paths is not None and self.depth_paths[i] is not None:
            depth = read_depth(self.depth_paths[i], self.depth_scale, self.depth_invalid)
            if depth.shape != image.shape[:2]:
                raise InputError(f"depth {self.depth_paths[i]} is {depth.shape}, image {path} is "
                                 f"{image.shape[:2]}")
        return Frame(i, float(self._timestamps[i]), image, depth, self._camera, path.name)


class FrameSubset(FrameSource):
    """Some frames of another source, renumbered 0..n-1 (``--stride``, ``--max-frames``).

    Timestamps, calibration and ground truth are the source's: ground truth is matched by time.
    """

    def __init__(self, source: FrameSource, indices: np.ndarray) -> None:
        super().__init__(source.root)
        self.source = source
        self.indices = np.asarray(indices, dtype=np.int64)
        if len(self.indices) and (self.indices.min() < 0 or self.indices.max() >= len(source)):
            raise InputError(f"frame subset out of range for a source of {len(source)} frames")
        self.layout = source.layout

    @classmethod
    def every(cls, source: FrameSource, stride: int = 1, limit: int | None = None) -> FrameSource:
        """Every ``stride``-th frame, at most ``limit`` of them (the source itself when that is all)."""
        if stride < 1:
            raise InputError(f"stride must be >= 1, got {stride}")
        if limit is not None and limit < 1:
            raise InputError(f"the number of frames must be >= 1, got {limit}")
        idx = np.arange(0, len(source), stride)[:limit]
        return source if len(idx) == len(source) else cls(source, idx)

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def timestamps(self) -> np.ndarray:
        return self.source.timestamps[self.indices]

    @property
    def camera(self) -> PinholeCamera | None:
        return self.source.camera

    def _native_ground_truth(self) -> Trajectory | None:
        return self.source.ground_truth()

    def _load(self, i: int) -> Frame:
        return dataclasses.replace(self.source[int(self.indices[i])], index=i)
