"""Submap point clouds on disk, loaded on demand (SPEC 3.12: bounded memory).

Every submap's points (submap frame, float32 [N,3]) are written once to ``<folder>/<id>.npy``, and their
image colours (uint8 [N,3], when known) to ``<folder>/<id>.rgb.npy``; a sparse backbone's feature database
and cameras to ``<id>.features.db`` and ``<id>.cameras.npz`` (loops found from images), its appearance
landmarks (keyframe features on its points, :mod:`vggt_slam_pp.frontend.landmarks`) to
``<id>.landmarks.npz``; a small LRU cache holds the active window's points. Both the front-end process
(writer) and the back-end worker process (reader) open the same folder.
"""

from __future__ import annotations

import shutil
from collections import OrderedDict
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import BackendError
from vggt_slam_pp.frontend.types import Landmarks


class SubmapStore:
    def __init__(self, folder: str | Path, cache_size: int = 8) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.cache_size = cache_size
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def path(self, submap_id: int) -> Path:
        return self.folder / f"{submap_id:06d}.npy"

    def colors_path(self, submap_id: int) -> Path:
        return self.folder / f"{submap_id:06d}.rgb.npy"

    def put(self, submap_id: int, points: np.ndarray, colors: np.ndarray | None = None) -> None:
        """Store ``points`` [N,3] and, when given, their ``colors`` [N,3] (uint8 RGB)."""
        pts = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
        for stale in (self.features_path(submap_id), self.cameras_path(submap_id), self.landmarks_path(submap_id)):
            stale.unlink(missing_ok=True)  # an earlier run's, if any
        if colors is not None:
            rgb = np.ascontiguousarray(colors, np.uint8).reshape(-1, 3)
            if len(rgb) != len(pts):
                raise BackendError(f"submap {submap_id}: {len(rgb)} colours for {len(pts)} points")
            tmp = self.folder / f"{submap_id:06d}.rgb.tmp.npy"
            np.save(tmp, rgb)
            tmp.replace(self.colors_path(submap_id))
        tmp = self.folder / f"{submap_id:06d}.tmp.npy"
        np.save(tmp, pts)
        tmp.replace(self.path(submap_id))
        self._remember(submap_id, pts)

    def get_colors(self, submap_id: int) -> np.ndarray | None:
        """The image colours [N,3] uint8 of submap ``submap_id``'s points, or None when not stored."""
        path = self.colors_path(submap_id)
        if not path.is_file():
            return None
        try:
            return np.load(path)
        except (OSError, ValueError) as exc:
            raise BackendError(f"cannot read the colours of submap {submap_id} from {self.folder}: {exc}") from exc

    def landmarks_path(self, submap_id: int) -> Path:
        return self.folder / f"{submap_id:06d}.landmarks.npz"

    def put_landmarks(self, submap_id: int, landmarks: Landmarks) -> None:
        """Keep submap ``submap_id``'s appearance landmarks (after its points: :meth:`put` removes an earlier
        run's)."""
        tmp = self.folder / f"{submap_id:06d}.landmarks.tmp.npz"
        with open(tmp, "wb") as f:
            np.savez(f, xyz=np.asarray(landmarks.xyz, np.float32),
                     descriptors=np.asarray(landmarks.descriptors, np.uint8),
                     keyframe=np.asarray(landmarks.keyframe, np.int16), view=np.asarray(landmarks.view, np.float32))
        tmp.replace(self.landmarks_path(submap_id))

    def get_landmarks(self, submap_id: int) -> Landmarks | None:
        """Submap ``submap_id``'s appearance landmarks (:meth:`put_landmarks`), or None when none were kept."""
        path = self.landmarks_path(submap_id)
        if not path.is_file():
            return None
        try:
            with np.load(path) as z:
                return Landmarks(z["xyz"], z["descriptors"], z["keyframe"], z["view"])
        except (OSError, ValueError, KeyError) as exc:
            raise BackendError(f"cannot read the landmarks of submap {submap_id} from {self.folder}: {exc}") from exc

    def features_path(self, submap_id: int) -> Path:
        return self.folder / f"{submap_id:06d}.features.db"

    def cameras_path(self, submap_id: int) -> Path:
        return self.folder / f"{submap_id:06d}.cameras.npz"

    def put_features(self, submap_id: int, database: str | Path, T_cam_submap: np.ndarray, valid: np.ndarray,
                     frame_indices: np.ndarray) -> None:
        """Keep a sparse backbone's feature ``database`` of the submap (COLMAP: its keyframes' keypoints,
        descriptors and matches; moved here) with its cameras ``T_cam_submap`` [S,4,4], which of them are
        ``valid`` [S] and their source ``frame_indices`` [S]: what loops found from images need
        (:mod:`vggt_slam_pp.backend.image_loops`)."""
        tmp = self.folder / f"{submap_id:06d}.cameras.tmp.npz"
        with open(tmp, "wb") as f:
            np.savez(f, T_cam_submap=np.asarray(T_cam_submap, np.float64), valid=np.asarray(valid, bool),
                     frame_indices=np.asarray(frame_indices, np.int64))
        tmp_db = self.folder / f"{submap_id:06d}.features.tmp.db"
        shutil.move(str(database), tmp_db)  # another file system: copied, so complete only once renamed
        tmp_db.replace(self.features_path(submap_id))
        tmp.replace(self.cameras_path(submap_id))

    def get_features(self, submap_id: int) -> tuple[Path, dict[str, np.ndarray]] | None:
        """(feature database, cameras) of submap ``submap_id`` (:meth:`put_features`), or None when its
        backbone kept none."""
        db, cams = self.features_path(submap_id), self.cameras_path(submap_id)
        if not (db.is_file() and cams.is_file()):
            return None
        try:
            with np.load(cams) as z:
                return db, {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise BackendError(f"cannot read the cameras of submap {submap_id} from {self.folder}: {exc}") from exc

    def get(self, submap_id: int) -> np.ndarray:
        if submap_id in self._cache:
            self._cache.move_to_end(submap_id)
            return self._cache[submap_id]
        try:
            pts = np.load(self.path(submap_id))
        except (OSError, ValueError) as exc:
            raise BackendError(f"cannot read the points of submap {submap_id} from {self.folder}: {exc}") from exc
        self._remember(submap_id, pts)
        return pts

    def _remember(self, submap_id: int, pts: np.ndarray) -> None:
        self._cache[submap_id] = pts
        self._cache.move_to_end(submap_id)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
