"""Point filtering (SPEC 3.4): drop the lowest-confidence points of a submap, then keep points whose
camera-frame distance lies in ``[d_min, d_max]`` (submap units; metres only when the backbone is metric).

Points whose confidence equals the percentile are kept, so a backbone with uniform confidences
(the simulated one) keeps everything in range."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.frontend.types import SubmapPrediction

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FilterConfig:
    conf_drop_percent: float = 25.0
    d_min: float = 0.2
    d_max: float = 30.0


def filter_points(pred: SubmapPrediction, config: FilterConfig | None = None) -> SubmapPrediction:
    """A copy of ``pred`` keeping the confident points in range; non-finite points are always dropped."""
    c = config or FilterConfig()
    finite = [np.isfinite(p).all(axis=1) & np.isfinite(w) for p, w in zip(pred.points, pred.conf, strict=True)]
    all_conf = np.concatenate([w[f] for w, f in zip(pred.conf, finite, strict=True)]) if pred.num_points() else []
    threshold = float(np.percentile(all_conf, c.conf_drop_percent)) if len(all_conf) and c.conf_drop_percent > 0 \
        else -np.inf
    keep_lists = []
    for i in range(pred.num_frames):
        with np.errstate(invalid="ignore", over="ignore"):
            dist = np.linalg.norm(pred.camera_points(i), axis=1) if len(pred.points[i]) else np.zeros(0)
            keep = finite[i] & (pred.conf[i] >= threshold) & (dist >= c.d_min) & (dist <= c.d_max)
        keep_lists.append(keep)
    kept = int(sum(k.sum() for k in keep_lists))
    log.debug("filter: kept %d of %d points (conf >= %.3g, %.2f <= d <= %.1f)", kept, pred.num_points(),
              threshold, c.d_min, c.d_max)
    return dataclasses.replace(
        pred,
        points=[p[k] for p, k in zip(pred.points, keep_lists, strict=True)],
        conf=[w[k] for w, k in zip(pred.conf, keep_lists, strict=True)],
        pixels=[x[k] for x, k in zip(pred.pixels, keep_lists, strict=True)],
        keys=[x[k] for x, k in zip(pred.keys, keep_lists, strict=True)],
        info={**pred.info, "points_before_filter": pred.num_points(), "points_after_filter": kept},
    )
