"""The front-end: frames -> keyframes -> submaps -> backbone -> filtered predictions -> Sim(3) odometry.

Submap assembly (SPEC 3.2): a submap closes when it holds ``submap_size`` (w = 32) *new* keyframes,
and at the end of the input (the final partial submap is kept). Every submap after the first starts
with ``overlap`` frames, the previous submap's last registered keyframes, which link the two by
odometry: one for dense backbones (the paper's choice: a dense frame gives thousands of
correspondences), :func:`sparse_overlap` for sparse ones (our decision, docs/frontend.md: a sparse
frame gives a few hundred points, a single frame is a single point of failure, and a long submap drifts
most at its end).

Recovery (never a silent identity edge):

1. the backbone retries internally (other initialisations, seeds) when it registers few frames;
2. *split*: keyframes left unregistered at the end of a submap are handed to the next submap, so the
   submap ends on a registered frame;
3. *bridge*: when the shared frames do not link the new submap to the previous one, the new submap is
   reconstructed again with more of the previous submap's registered keyframes in front (a few, then up to 16);
4. last resort, the edge is *extrapolated* (:func:`~vggt_slam_pp.frontend.odometry.extrapolated_edge`)
   and flagged ``degraded`` with its cause; the back-end gives it a large uncertainty.

Every recovery is logged and written into the edge's ``cause`` (``report.json``).
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
from vggt_slam_pp.frontend.landmarks import LandmarkConfig, keyframe_landmarks
from vggt_slam_pp.frontend.odometry import (
    OdometryConfig,
    chain,
    estimate_edge,
    link_problem,
    overlap_disagreement,
    with_cause,
)
from vggt_slam_pp.frontend.types import OdometryEdge, Submap, SubmapPrediction
from vggt_slam_pp.geometry.lie import sim3_inverse
from vggt_slam_pp.io.frames import Frame
from vggt_slam_pp.io.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrontendConfig:
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    submap_size: int = 32  # w: new keyframes per submap
    overlap: int = 0  # keyframes shared with the previous submap; 0 = auto (1 dense, sparse_overlap(w) sparse)
    bridge_frames: int = 0  # extra keyframes of the previous submap for a bridge; 0 = auto (max(4, min(16, 2 * overlap)))
    bridge_max_frames: int = 16  # a bridge that fails is tried once more with up to this many (all of a short
    # previous submap's registered keyframes: a fast start or turn leaves its last keyframes the poorly tracked ones)
    filter: FilterConfig = field(default_factory=FilterConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)  # image features on the points (loops)


def sparse_overlap(submap_size: int) -> int:
    """Keyframes a sparse backbone's submap shares with the previous one: ``w^2 / 64``, from 2 to 16 (w = 8: 2,
    16: 4, 24: 9, 32: 16). A submap drifts most at its end, and the longer it is the more: the link must reach
    further into it, while a short submap of sparse photos would give up too many of its new views.
    Measured (docs/frontend.md, "The overlap"): at w = 32, 16 shared instead of 8 lowered every sequence's
    odometry ATE (EuRoC calibrated 0.0405 -> 0.0332 m, uncalibrated 0.0658 -> 0.0630 m, the rendered drive
    0.356 -> 0.306 m and 0.456 -> 0.411 m); at w = 16 (rendered block loop) 8 instead of 4 raised it 0.266 ->
    0.298 m, and at w = 8 (castle walk) 4 instead of 2 broke a link (0.033 -> 0.59 m)."""
    return max(2, min(16, submap_size * submap_size // 64))


class SubmapAssembler:
    """Groups keyframes into submaps of ``size`` new keyframes plus ``overlap`` of the previous one's."""

    def __init__(self, size: int, overlap: int = 1) -> None:
        if size < 1:
            raise FrontendError(f"submap size must be >= 1, got {size}")
        if overlap < 1:
            raise FrontendError(f"submap overlap must be >= 1, got {overlap}")
        self.size, self.overlap = size, overlap
        self._overlap: list[Frame] = []
        self._new: list[Frame] = []

    def add(self, keyframe: Frame) -> list[Frame] | None:
        """Add a keyframe; returns the frames of a completed submap (overlap first) or None."""
        self._new.append(keyframe)
        return self._close() if len(self._new) >= self.size else None

    def flush(self) -> list[Frame] | None:
        """The final partial submap, if any new keyframes are pending."""
        return self._close() if self._new else None

    def settle(self, kept: list[Frame], overlap: list[Frame], carry: list[Frame]) -> None:
        """After a submap was built: it kept ``kept``; the next submap starts with ``overlap`` (by default
        its last frames) and the keyframes in ``carry`` (left unregistered) go before the pending ones."""
        self._overlap = list(overlap) if overlap else kept[-self.overlap:]
        self._new = list(carry) + self._new

    def _close(self) -> list[Frame]:
        frames = self._overlap + self._new
        self._overlap, self._new = frames[-self.overlap:], []
        return frames


@dataclass
class FrontendResult:
    submaps: list[Submap]
    edges: list[OdometryEdge]
    T_world_submap: list[np.ndarray]
    decisions: list[tuple[int, float, KeyframeDecision]]  # (frame index, timestamp, decision)
    timings: dict[str, float]

    def keyframe_trajectory(self) -> Trajectory:
        """``T_world_cam`` of every keyframe (Sim(3) in the odometry's scale): its first registered
        occurrence (a keyframe held by two submaps), else its first occurrence (a guessed pose)."""
        chosen: dict[int, tuple[float, np.ndarray, bool]] = {}
        for sm, T_ws in zip(self.submaps, self.T_world_submap, strict=True):
            pred = sm.prediction
            for i, idx in enumerate(sm.frame_indices):
                have = chosen.get(int(idx))
                if have is None or (not have[2] and pred.valid[i]):
                    chosen[int(idx)] = (sm.timestamps[i], T_ws @ sim3_inverse(pred.T_cam_submap[i]), bool(pred.valid[i]))
        order = sorted(chosen)
        return Trajectory(np.array([chosen[k][0] for k in order]),
                          np.array([chosen[k][1] for k in order]).reshape(-1, 4, 4))

    def all_frame_trajectory(self) -> Trajectory:
        """Every input frame: keyframes exact, the others interpolated in time (``interpolated`` mask)."""
        kf = self.keyframe_trajectory()
        return kf.interpolate_at(np.array([t for _, t, _ in self.decisions]))


class Frontend:
    """Feed frames with :meth:`process`; :meth:`finish` closes the last submap and returns the result."""

    def __init__(self, backbone: Backbone, config: FrontendConfig | None = None, store=None, first_id: int = 0) -> None:
        self.backbone = backbone
        self.first_id = first_id  # id of the first submap (a recording added to a map of first_id submaps)
        self.config = config or FrontendConfig()
        c = self.config
        self.overlap = c.overlap or (1 if backbone.dense else sparse_overlap(c.submap_size))
        self.bridge_frames = c.bridge_frames or max(4, min(16, 2 * self.overlap))
        self.selector = KeyframeSelector(c.keyframes)
        self.assembler = SubmapAssembler(c.submap_size, self.overlap)
        self.store = store  # optional PredictionStore recording every raw prediction
        self.submaps: list[Submap] = []
        self.edges: list[OdometryEdge] = []
        self.decisions: list[tuple[int, float, KeyframeDecision]] = []
        self.timings = {"keyframes_s": 0.0, "backbone_s": 0.0, "filter_s": 0.0, "odometry_s": 0.0, "landmarks_s": 0.0}
        self._last_frames: list[Frame] = []  # keyframes (images) of the last submap, for a bridge
        self._calls = 0  # backbone calls for the current submap (prediction file names)

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
            self.submaps[k] = dataclasses.replace(sm, prediction=light, colors=None, landmarks=None)

    def finish(self) -> FrontendResult:
        while (frames := self.assembler.flush()) is not None:  # a split may hand keyframes back
            self._build(frames)
        if not self.submaps:
            raise FrontendError("no frames were processed")
        return self.partial_result()

    def partial_result(self) -> FrontendResult | None:
        """The submaps finished so far (keyframes still being assembled are not in it); None before the
        first. After an error or an interruption this is what the run's outputs are written from."""
        if not self.submaps:
            return None
        return FrontendResult(self.submaps, self.edges, chain(self.edges), self.decisions, dict(self.timings))

    # -- one submap ---------------------------------------------------------------------------------
    def _predict(self, sid: int, frames: list[Frame]) -> SubmapPrediction:
        t = time.perf_counter()
        raw = self.backbone.predict(frames)
        self.timings["backbone_s"] += time.perf_counter() - t
        raw = _sanitize(raw, frames)
        if self.store is not None:
            self.store.save(sid, raw, attempt=self._calls)
        self._calls += 1
        return raw

    def _filtered(self, raw: SubmapPrediction) -> SubmapPrediction:
        t = time.perf_counter()
        pred = filter_points(raw, self.config.filter)
        self.timings["filter_s"] += time.perf_counter() - t
        return pred

    def _build(self, frames: list[Frame]) -> Submap:
        sid = self.first_id + len(self.submaps)
        self._calls = 0
        prev = self.submaps[-1] if self.submaps else None
        in_prev = set(prev.frame_indices.tolist()) if prev is not None else set()
        n_shared = sum(1 for f in frames if f.index in in_prev)
        raw = self._predict(sid, frames)
        raw, frames, carry = _split_unregistered_tail(raw, frames, n_shared)
        if carry:
            log.warning("submap %d: keyframes %d..%d were not registered; they start the next submap",
                        sid, carry[0].index, carry[-1].index)
        pred = self._filtered(raw)
        note = ""
        problem = link_problem(prev.prediction, pred, self.config.odometry) if prev is not None else ""
        if problem:
            pred, frames, note = self._bridge(sid, prev, pred, frames, problem)
        if pred.num_points() == 0:
            log.warning("submap %d: no points left after filtering", sid)
        t = time.perf_counter()
        landmarks = keyframe_landmarks(pred, [f.image for f in frames], self.config.landmarks)
        self.timings["landmarks_s"] += time.perf_counter() - t
        submap = Submap(sid, np.array([f.index for f in frames]), np.array([f.timestamp for f in frames]),
                        pred, has_overlap=bool(self.submaps), overlap=sum(1 for f in frames if f.index in in_prev),
                        colors=point_colors(pred, frames), landmarks=landmarks)
        if prev is not None:
            t = time.perf_counter()
            edge = estimate_edge(sid - 1, prev.prediction, sid, pred, self.config.odometry)
            self.edges.append(with_cause(edge, note) if note else edge)
            self.timings["odometry_s"] += time.perf_counter() - t
        self.submaps.append(submap)
        self.backbone.committed(submap.frame_indices)
        self._last_frames = frames
        registered = [f for f, v in zip(frames, pred.valid, strict=True) if v]
        self.assembler.settle(frames, registered[-self.overlap:], carry)
        log.info("submap %d: %d keyframes (%d registered), %d points", sid, len(frames), len(registered),
                 pred.num_points())
        return submap

    def _bridge(self, sid: int, prev: Submap, pred: SubmapPrediction, frames: list[Frame], problem: str
                ) -> tuple[SubmapPrediction, list[Frame], str]:
        """Reconstruct the submap again with up to ``bridge_frames`` more registered keyframes of the
        previous submap in front, and if that does not link it either, with up to ``bridge_max_frames`` (all of a
        short submap's: after a fast start or turn its last keyframes may be the poorly tracked ones); returns
        the best linked result and a note for the edge's cause."""
        have = {f.index for f in frames}
        valid = {int(i) for i, v in zip(prev.frame_indices, prev.prediction.valid, strict=True) if v}
        usable = [f for f in self._last_frames if f.index in valid and f.index not in have]
        if not usable:
            return pred, frames, ""
        best, best_frames, best_gap = pred, frames, overlap_disagreement(prev.prediction, pred)
        sizes = sorted({min(self.bridge_frames, len(usable)),
                        min(max(self.bridge_frames, self.config.bridge_max_frames), len(usable))})
        for n in sizes:
            extra = usable[-n:]
            log.warning("submap %d is not soundly linked to submap %d (%s); reconstructing it again with %d "
                        "more keyframes of submap %d", sid, sid - 1, problem, len(extra), sid - 1)
            bridged = extra + frames
            candidate = self._filtered(self._predict(sid, bridged))
            if not link_problem(prev.prediction, candidate, self.config.odometry):
                return candidate, bridged, (f"bridged: reconstructed again with {len(extra)} more keyframes of "
                                            f"submap {sid - 1} ({problem})")
            gap = overlap_disagreement(prev.prediction, candidate)
            if gap < best_gap:  # NaN compares False: keep the earlier
                best, best_frames, best_gap = candidate, bridged, gap
        return best, best_frames, (f"bridge with {' and '.join(str(n) for n in sizes)} more keyframes of submap "
                                   f"{sid - 1} failed")


def point_colors(pred: SubmapPrediction, frames: list[Frame]) -> np.ndarray:
    """The image colour [N,3] uint8 under every point of ``pred`` (its ``points`` concatenated in order),
    read at the point's pixel (nearest) in its keyframe's image."""
    out = []
    for pix, frame in zip(pred.pixels, frames, strict=True):
        img = frame.image
        if len(pix) == 0:
            out.append(np.zeros((0, 3), np.uint8))
            continue
        xy = np.rint(np.asarray(pix, float)).astype(np.int64)
        x = np.clip(xy[:, 0], 0, img.shape[1] - 1)
        y = np.clip(xy[:, 1], 0, img.shape[0] - 1)
        out.append(np.asarray(img[y, x], np.uint8).reshape(-1, 3))
    return np.concatenate(out) if out else np.zeros((0, 3), np.uint8)


def _split_unregistered_tail(raw: SubmapPrediction, frames: list[Frame], n_shared: int
                             ) -> tuple[SubmapPrediction, list[Frame], list[Frame]]:
    """Cut the keyframes after the last registered new keyframe off the submap: (kept prediction, kept
    frames, carried frames). Nothing is cut when no new keyframe (beyond the ``n_shared`` overlap
    frames) is registered: bridging and extrapolation handle that."""
    valid = np.asarray(raw.valid, bool)
    if valid[-1] or not valid[n_shared:].any():
        return raw, frames, []
    r = int(np.nonzero(valid)[0][-1]) + 1
    if r <= max(n_shared, 1):
        return raw, frames, []
    return raw.select(np.arange(r)), frames[:r], frames[r:]


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
