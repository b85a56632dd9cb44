"""The front-end: frames -> keyframes -> submaps -> backbone -> filtered predictions -> Sim(3) odometry.

Submap assembly (SPEC 3.2): a submap closes when it holds ``submap_size`` (w = 32) *new* keyframes,
and at the end of the input (the final partial submap is kept). Every submap after the first starts
with one overlap frame, the previous submap's last keyframe, which links the two by odometry.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.filtering import FilterConfig, filter_points
from vggt_slam_pp.frontend.keyframes import KeyframeConfig, KeyframeDecision, KeyframeSelector
from vggt_slam_pp.frontend.odometry import OdometryConfig, chain, estimate_edge
from vggt_slam_pp.frontend.types import OdometryEdge, Submap, SubmapPrediction
from vggt_slam_pp.geometry.lie import sim3_inverse
from vggt_slam_pp.io.frames import Frame
from vggt_slam_pp.io.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrontendConfig:
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    submap_size: int = 32  # w: new keyframes per submap
    filter: FilterConfig = field(default_factory=FilterConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)


class SubmapAssembler:
    """Groups keyframes into submaps of ``size`` new keyframes plus the previous submap's last one."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise FrontendError(f"submap size must be >= 1, got {size}")
        self.size = size
        self._overlap: Frame | None = None
        self._new: list[Frame] = []

    def add(self, keyframe: Frame) -> list[Frame] | None:
        """Add a keyframe; returns the frames of a completed submap (overlap first) or None."""
        self._new.append(keyframe)
        return self._close() if len(self._new) >= self.size else None

    def flush(self) -> list[Frame] | None:
        """The final partial submap, if any new keyframes are pending."""
        return self._close() if self._new else None

    def _close(self) -> list[Frame]:
        frames = ([self._overlap] if self._overlap is not None else []) + self._new
        self._overlap, self._new = self._new[-1], []
        return frames


@dataclass
class FrontendResult:
    submaps: list[Submap]
    edges: list[OdometryEdge]
    T_world_submap: list[np.ndarray]
    decisions: list[tuple[int, float, KeyframeDecision]]  # (frame index, timestamp, decision)
    timings: dict[str, float]

    def keyframe_trajectory(self) -> Trajectory:
        """``T_world_cam`` of every keyframe (Sim(3) in the odometry's scale), first occurrence kept."""
        seen: set[int] = set()
        ts, poses = [], []
        for sm, T_ws in zip(self.submaps, self.T_world_submap, strict=True):
            pred = sm.prediction
            for i, idx in enumerate(sm.frame_indices):
                if int(idx) in seen:
                    continue
                seen.add(int(idx))
                ts.append(sm.timestamps[i])
                poses.append(T_ws @ sim3_inverse(pred.T_cam_submap[i]))
        return Trajectory(np.array(ts), np.array(poses).reshape(-1, 4, 4))

    def all_frame_trajectory(self) -> Trajectory:
        """Every input frame: keyframes exact, the others interpolated in time (``interpolated`` mask)."""
        kf = self.keyframe_trajectory()
        return kf.interpolate_at(np.array([t for _, t, _ in self.decisions]))


class Frontend:
    """Feed frames with :meth:`process`; :meth:`finish` closes the last submap and returns the result."""

    def __init__(self, backbone: Backbone, config: FrontendConfig | None = None, store=None) -> None:
        self.backbone = backbone
        self.config = config or FrontendConfig()
        self.selector = KeyframeSelector(self.config.keyframes)
        self.assembler = SubmapAssembler(self.config.submap_size)
        self.store = store  # optional PredictionStore recording every raw prediction
        self.submaps: list[Submap] = []
        self.edges: list[OdometryEdge] = []
        self.decisions: list[tuple[int, float, KeyframeDecision]] = []
        self.timings = {"keyframes_s": 0.0, "backbone_s": 0.0, "filter_s": 0.0, "odometry_s": 0.0}

    def process(self, frame: Frame) -> Submap | None:
        t = time.perf_counter()
        decision = self.selector.update(frame.image)
        self.timings["keyframes_s"] += time.perf_counter() - t
        self.decisions.append((frame.index, frame.timestamp, decision))
        if not decision.is_keyframe:
            return None
        frames = self.assembler.add(frame)
        return self._build(frames) if frames else None

    def release_points(self, keep_last: int = 1) -> None:
        """Drop the point observations of all but the last ``keep_last`` submaps (the next odometry edge
        needs only the last one); poses and frame indices stay. Bounds the front-end's memory."""
        for k in range(max(0, len(self.submaps) - keep_last)):
            sm = self.submaps[k]
            pred = sm.prediction
            if pred.num_points() == 0 and pred.depth is None:
                continue
            empty = [np.zeros((0, 3), np.float32)] * pred.num_frames
            light = dataclasses.replace(pred, points=empty, conf=[np.zeros(0, np.float32)] * pred.num_frames,
                                        pixels=[np.zeros((0, 2), np.float32)] * pred.num_frames,
                                        keys=[np.zeros(0, np.int64)] * pred.num_frames, depth=None, depth_conf=None)
            self.submaps[k] = dataclasses.replace(sm, prediction=light)

    def finish(self) -> FrontendResult:
        frames = self.assembler.flush()
        if frames:
            self._build(frames)
        if not self.submaps:
            raise FrontendError("no frames were processed")
        return FrontendResult(self.submaps, self.edges, chain(self.edges), self.decisions, dict(self.timings))

    def _build(self, frames: list[Frame]) -> Submap:
        sid = len(self.submaps)
        t = time.perf_counter()
        raw = self.backbone.predict(frames)
        self.timings["backbone_s"] += time.perf_counter() - t
        raw = _sanitize(raw, frames)
        if self.store is not None:
            self.store.save(sid, raw)
        t = time.perf_counter()
        pred = filter_points(raw, self.config.filter)
        self.timings["filter_s"] += time.perf_counter() - t
        if pred.num_points() == 0:
            log.warning("submap %d: no points left after filtering", sid)
        submap = Submap(sid, np.array([f.index for f in frames]), np.array([f.timestamp for f in frames]),
                        pred, has_overlap=sid > 0)
        if self.submaps:
            t = time.perf_counter()
            self.edges.append(estimate_edge(sid - 1, self.submaps[-1].prediction, sid, pred, self.config.odometry))
            self.timings["odometry_s"] += time.perf_counter() - t
        self.submaps.append(submap)
        log.info("submap %d: %d keyframes, %d points", sid, len(frames), pred.num_points())
        return submap


def _sanitize(pred: SubmapPrediction, frames: list[Frame]) -> SubmapPrediction:
    """Reject predictions for other frames; degrade (logged) frames with non-finite poses to invalid,
    holding the previous frame's pose. Non-finite points are removed later by the filter."""
    if [int(i) for i in pred.frame_indices] != [f.index for f in frames]:
        raise FrontendError("backbone returned a prediction for other frames than requested")
    bad = ~np.isfinite(pred.T_cam_submap).all(axis=(1, 2))
    if not bad.any():
        return pred
    log.warning("backbone returned non-finite poses for %d of %d frames (frames %s): marked invalid",
                int(bad.sum()), len(bad), [frames[i].index for i in np.nonzero(bad)[0][:5]])
    T = pred.T_cam_submap.copy()
    for i in np.nonzero(bad)[0]:
        T[i] = T[i - 1] if i > 0 else np.eye(4)
    return dataclasses.replace(pred, T_cam_submap=T, valid=pred.valid & ~bad)
