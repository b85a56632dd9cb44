"""Pinhole camera with optional OpenCV distortion (OpenCV convention: x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from vggt_slam_pp.errors import GeometryError

__all__ = ["PinholeCamera"]


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one camera at one image resolution.

    Attributes:
        fx, fy, cx, cy: focal lengths and principal point in pixels (pixel centres at integers).
        width, height: image size in pixels.
        dist: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; empty = none.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy, *self.dist)
        if not all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise GeometryError(f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if self.width <= 0 or self.height <= 0:
            raise GeometryError(f"invalid image size {self.width}x{self.height}")
        if len(self.dist) not in (0, 4, 5, 8):
            raise GeometryError(f"distortion must have 0, 4, 5 or 8 coefficients, got {len(self.dist)}")

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int, height: int, dist=()) -> PinholeCamera:
        """From a ``[3, 3]`` intrinsic matrix."""
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height),
                   tuple(float(d) for d in dist))

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same camera for an image resized to ``width x height`` (pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, width=int(width), height=int(height))

    def without_distortion(self) -> PinholeCamera:
        return replace(self, dist=())

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points ``[N, 3]`` to pixels ``[N, 2]``; points with ``z <= 0`` give NaN."""
        p = np.asarray(points_cam, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise GeometryError(f"points_cam must be [N, 3], got {p.shape}")
        out = np.full((len(p), 2), np.nan)
        front = p[:, 2] > 0
        if not front.any():
            return out
        if self.distorted:
            uv, _ = cv2.projectPoints(p[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K,
                                      np.asarray(self.dist, dtype=np.float64))
            out[front] = uv.reshape(-1, 2)
        else:
            q = p[front]
            out[front, 0] = self.fx * q[:, 0] / q[:, 2] + self.cx
            out[front, 1] = self.fy * q[:, 1] / q[:, 2] + self.cy
        return out

    def normalized_rays(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates ``[N, 3]`` (``z = 1``) of pixels ``uv [N, 2]``."""
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise GeometryError(f"uv must be [N, 2], got {uv.shape}")
        if self.distorted and len(uv):
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, np.asarray(self.dist, np.float64),
                                     None, None, criteria=criteria).reshape(-1, 2)
        else:
            xy = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        return np.concatenate([xy, np.ones((len(uv), 1))], axis=1)

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points ``[N, 3]`` of pixels ``uv [N, 2]`` at z-depths ``depth [N]``."""
        depth = np.asarray(depth, dtype=np.float64)
        return self.normalized_rays(uv) * depth.reshape(-1, 1)

    def unproject_depth(self, depth: np.ndarray) -> np.ndarray:
        """Point map ``[H, W, 3]`` in the camera frame from a z-depth image ``[H, W]``."""
        depth = np.asarray(depth)
        if depth.shape != (self.height, self.width):
            raise GeometryError(f"depth must be [{self.height}, {self.width}], got {depth.shape}")
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        return self.unproject(uv, depth.ravel()).reshape(self.height, self.width, 3)

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables ``(map_x, map_y)`` ``[H, W]`` that undistort an image onto :meth:`without_distortion`."""
        return cv2.initUndistortRectifyMap(self.K, np.asarray(self.dist, np.float64), None, self.K,
                                           (self.width, self.height), cv2.CV_32FC1)

    def undistort_image(self, image: np.ndarray) -> np.ndarray:
        """Undistorted copy of ``image [H, W(, C)]`` for the camera :meth:`without_distortion`."""
        if not self.distorted:
            return image
        mx, my = self.undistort_maps()
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width,
                "height": self.height, "dist": list(self.dist)}
