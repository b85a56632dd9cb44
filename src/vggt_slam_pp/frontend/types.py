"""Typed records at the front-end's seams.

A backbone turns the keyframes of one submap into a :class:`SubmapPrediction`; geometry stays in the
submap's own frame (the frame of its first keyframe, up to the backbone's scale). Odometry links
consecutive submaps with a Sim(3) :class:`OdometryEdge`; the chained world poses live outside the
submap, in a :class:`FrontendResult`.

Point observations are stored per frame as flat arrays so that dense (VGGT, simulated) and sparse
(COLMAP) backbones share one format: ``points[i]`` [Ni,3] in the submap frame, ``conf[i]`` [Ni],
``pixels[i]`` [Ni,2] in *original* image pixels (OpenCV convention), ``keys[i]`` [Ni] int64 — an
identifier of the observation that is the same when the same image is processed in two submaps (the
network-grid pixel index for dense backbones, the SIFT keypoint index for COLMAP). The overlap frame's
keys give the correspondences between consecutive submaps.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from vggt_slam_pp.errors import FrontendError


@dataclass(frozen=True, eq=False)
class SubmapPrediction:
    """What a backbone predicts for the S keyframes of one submap.

    Attributes:
        frame_indices: [S] source frame indices.
        T_cam_submap: [S,4,4] camera-from-submap poses (frame 0 is ~identity).
        intrinsics: [S,3,3] at network resolution.
        network_hw: (H, W) of the network input.
        to_original: [S,3,3] affine map network pixel (x, y, 1) -> original pixel.
        points, conf, pixels, keys: per-frame observations (see the module docstring).
        valid: [S] bool, False for frames the backbone could not reconstruct (their pose is a guess).
        depth, depth_conf: optional dense [S,H,W] maps at network resolution (dense backbones).
        dense: whether observations come from dense per-pixel maps.
    """

    frame_indices: np.ndarray
    T_cam_submap: np.ndarray
    intrinsics: np.ndarray
    network_hw: tuple[int, int]
    to_original: np.ndarray
    points: list[np.ndarray]
    conf: list[np.ndarray]
    pixels: list[np.ndarray]
    keys: list[np.ndarray]
    valid: np.ndarray
    depth: np.ndarray | None = None
    depth_conf: np.ndarray | None = None
    dense: bool = True
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        S = len(self.frame_indices)
        shapes = {"T_cam_submap": (S, 4, 4), "intrinsics": (S, 3, 3), "to_original": (S, 3, 3), "valid": (S,)}
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise FrontendError(f"SubmapPrediction.{name} has shape {np.shape(getattr(self, name))}, "
                                    f"expected {shape}")
        for name in ("points", "conf", "pixels", "keys"):
            if len(getattr(self, name)) != S:
                raise FrontendError(f"SubmapPrediction.{name} has {len(getattr(self, name))} frames, expected {S}")
        for i in range(S):
            n = len(self.points[i])
            if not (len(self.conf[i]) == len(self.pixels[i]) == len(self.keys[i]) == n):
                raise FrontendError(f"SubmapPrediction frame {i}: observation arrays differ in length")

    @property
    def num_frames(self) -> int:
        return len(self.frame_indices)

    def num_points(self) -> int:
        return int(sum(len(p) for p in self.points))

    def select(self, positions: np.ndarray) -> SubmapPrediction:
        """The prediction of the frames at ``positions`` only (poses stay in this submap's frame)."""
        pos = np.asarray(positions, dtype=np.int64)
        pick = [int(i) for i in pos]
        return dataclasses.replace(
            self, frame_indices=self.frame_indices[pos], T_cam_submap=self.T_cam_submap[pos],
            intrinsics=self.intrinsics[pos], to_original=self.to_original[pos], valid=self.valid[pos],
            points=[self.points[i] for i in pick], conf=[self.conf[i] for i in pick],
            pixels=[self.pixels[i] for i in pick], keys=[self.keys[i] for i in pick],
            depth=None if self.depth is None else self.depth[pos],
            depth_conf=None if self.depth_conf is None else self.depth_conf[pos])

    def camera_points(self, i: int) -> np.ndarray:
        """Frame i's points in its own camera frame [Ni,3]."""
        T = self.T_cam_submap[i]
        return self.points[i] @ T[:3, :3].T + T[:3, 3]


@dataclass(frozen=True, eq=False)
class Landmarks:
    """Image features with a 3-D position, in one submap's frame.

    Attributes:
        xyz: [N,3] float32 positions in the submap's frame.
        descriptors: [N,32] uint8 ORB descriptors.
        keyframe: [N] int16 index of the keyframe (in the submap) each was seen in.
        view: [N,3] float32 unit direction from that keyframe's camera to the landmark, submap frame.
    """

    xyz: np.ndarray
    descriptors: np.ndarray
    keyframe: np.ndarray
    view: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def empty() -> Landmarks:
        return Landmarks(np.zeros((0, 3), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.int16),
                         np.zeros((0, 3), np.float32))


@dataclass(frozen=True, eq=False)
class Submap:
    """One submap: its id, keyframes and the backbone's (filtered) prediction."""

    id: int
    frame_indices: np.ndarray  # [S] source indices; the first ``overlap`` are the previous submap's last ones
    timestamps: np.ndarray  # [S]
    prediction: SubmapPrediction
    has_overlap: bool
    overlap: int = 0  # how many leading keyframes the previous submap also holds (0 for the first)
    colors: np.ndarray | None = None  # [N,3] uint8 image colour of every point (prediction.points in order)
    landmarks: Landmarks | None = None  # keyframe image features on the submap's points (frontend/landmarks.py)


@dataclass(frozen=True)
class OdometryEdge:
    """``T_prev_curr``: Sim(3) mapping submap ``curr`` coordinates into submap ``prev``'s."""

    prev: int
    curr: int
    T_prev_curr: np.ndarray
    residual: float  # RMS 3-D residual of the inliers, in prev-submap units
    inlier_ratio: float
    num_correspondences: int
    method: str  # "points", "pose_scale", "joint" or "anchored", or "extrapolated" when it had to degrade
    degraded: bool = False  # no measured link: the back-end gives the edge a large uncertainty
    cause: str = ""  # why it degraded, or how it was recovered ("" for a plain edge)
    shared_frames: int = 1  # keyframes reconstructed in both submaps that the estimate used
    relative_residual: float = float("nan")  # "joint": the cameras' placement residual over their spread (the
    # back-end's rotation and log-scale sigma of the edge); NaN for the other methods
