"""Saving every submap prediction during a run, and replaying them later without the network.

One safetensors file per submap, ``submap_XXXXX.safetensors``: per-frame observation arrays are
concatenated with an ``offsets`` array; scalars and the ``info`` dict go into the file's metadata. The
round trip is bit-identical.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vggt_slam_pp.errors import FrontendError
from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.io.frames import Frame

if TYPE_CHECKING:
    from vggt_slam_pp.io.frames import FrameSource
    from vggt_slam_pp.pipeline import RunConfig

log = logging.getLogger(__name__)

_ARRAYS = ("frame_indices", "T_cam_submap", "intrinsics", "to_original", "valid", "depth", "depth_conf")
_LISTS = ("points", "conf", "pixels", "keys")


def save_prediction(path: str | Path, pred: SubmapPrediction) -> None:
    """Write ``pred`` to a safetensors file (atomically)."""
    from safetensors.numpy import save_file

    tensors: dict[str, np.ndarray] = {}
    for name in _ARRAYS:
        value = getattr(pred, name)
        if value is not None:
            arr = np.ascontiguousarray(value)
            tensors[name] = arr.astype(np.uint8) if arr.dtype == bool else arr
    counts = np.array([len(p) for p in pred.points], dtype=np.int64)
    tensors["offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    for name in _LISTS:
        parts = getattr(pred, name)
        tensors[name] = np.ascontiguousarray(np.concatenate(parts) if len(parts) else np.zeros(0))
    meta = {"network_hw": json.dumps(list(pred.network_hw)), "dense": json.dumps(pred.dense),
            "info": json.dumps(pred.info, default=float), "valid_dtype": "bool"}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(path)


def load_prediction(path: str | Path) -> SubmapPrediction:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = f.metadata()
            t = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no iterator
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error type
        raise FrontendError(f"cannot read saved prediction {path}: {exc}") from exc
    off = t["offsets"]
    split = {name: [t[name][off[i]:off[i + 1]] for i in range(len(off) - 1)] for name in _LISTS}
    return SubmapPrediction(
        t["frame_indices"], t["T_cam_submap"], t["intrinsics"], tuple(json.loads(meta["network_hw"])),
        t["to_original"], split["points"], split["conf"], split["pixels"], split["keys"],
        t["valid"].astype(bool), t.get("depth"), t.get("depth_conf"), json.loads(meta["dense"]),
        json.loads(meta["info"]))


class PredictionStore:
    """A folder of saved predictions, one file per backbone call (submap id and attempt).

    ``keep_existing``: a file that is already there is not written again (a resumed run replays it).
    """

    def __init__(self, folder: str | Path, keep_existing: bool = False) -> None:
        self.folder = Path(folder)
        self.keep_existing = keep_existing

    def path(self, submap_id: int, attempt: int = 0) -> Path:
        suffix = f"_{attempt}" if attempt else ""
        return self.folder / f"submap_{submap_id:05d}{suffix}.safetensors"

    def save(self, submap_id: int, pred: SubmapPrediction, attempt: int = 0) -> None:
        """Save the ``attempt``-th backbone call for this submap (later ones: a bridge)."""
        path = self.path(submap_id, attempt)
        if not (self.keep_existing and path.is_file()):
            save_prediction(path, pred)

    def all(self) -> list[Path]:
        return sorted(self.folder.glob("submap_*.safetensors"))


def saved_by_frames(folder: str | Path) -> dict[tuple[int, ...], Path]:
    """The saved predictions in ``folder``, keyed by their keyframes' frame indices."""
    from safetensors import safe_open

    out: dict[tuple[int, ...], Path] = {}
    for p in PredictionStore(folder).all():
        try:
            with safe_open(str(p), framework="numpy") as f:
                out[tuple(int(i) for i in f.get_tensor("frame_indices"))] = p
        except Exception as exc:  # noqa: BLE001 - safetensors raises its own error type
            raise FrontendError(f"cannot read saved prediction {p}: {exc}") from exc
    return out


class ReplayBackbone(Backbone):
    """Returns the saved prediction whose frame indices equal the requested keyframes."""

    name = "replay"

    def __init__(self, folder: str | Path) -> None:
        self._by_frames = saved_by_frames(folder)
        if not self._by_frames:
            raise FrontendError(f"no saved predictions (submap_*.safetensors) in {folder}")
        first = load_prediction(next(iter(self._by_frames.values())))
        self.dense = first.dense
        self.metric = bool(first.info.get("metric", False))

    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        key = tuple(int(f.index) for f in frames)
        path = self._by_frames.get(key)
        if path is None:
            raise FrontendError(f"replay: no saved prediction for keyframes {key[0]}..{key[-1]} ({len(key)} "
                                "frames); replay needs the same input, stride and keyframe settings as the "
                                "recorded run")
        return load_prediction(path)


class ResumeBackbone(Backbone):
    """A resumed run: the saved prediction for keyframes an interrupted run had already reconstructed,
    ``live`` for the others. Every call reaches ``live``'s :meth:`committed` hook as before, so a
    backbone whose outputs depend only on its inputs and commits gives what an uninterrupted run gave."""

    def __init__(self, live: Backbone, folder: str | Path) -> None:
        self.live = live
        self.name, self.dense, self.metric = live.name, live.dense, live.metric
        self._by_frames = saved_by_frames(folder)
        self.replayed = 0

    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        path = self._by_frames.get(tuple(int(f.index) for f in frames))
        if path is None:
            return self.live.predict(frames)
        self.replayed += 1
        return load_prediction(path)

    def committed(self, frame_indices: Sequence[int]) -> None:
        self.live.committed(frame_indices)

    def describe(self) -> dict:
        return {**self.live.describe(), "resumed_backbone_calls": self.replayed}

    def close(self) -> None:
        self.live.close()


def from_run_config(config: RunConfig, source: FrameSource) -> Backbone:
    """The ``replay`` backbone of a run (:data:`vggt_slam_pp.plugins.BACKBONES`): an earlier run's predictions."""
    b = config.backbone
    if not b.replay_dir:
        raise FrontendError("the replay backbone needs the folder of a previous run (--replay DIR)")
    folder = Path(b.replay_dir)
    return ReplayBackbone(folder / "predictions" if (folder / "predictions").is_dir() else folder)
