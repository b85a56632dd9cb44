"""Benchmarks behind ``vggt-slam-pp bench``: each returns a JSON-friendly dict of figures.

* ``dem``: rasterise 6.5 M points (about one 32-frame VGGT submap at 518x392) with the softmax
  reducer; ``points_per_s`` and ``ratio_to_count_baseline`` = our time / the time of computing the same
  pixel indices plus an ``np.bincount`` count (medians of repeated runs after a warm-up). Target <= 3.
* ``retrieval``: clustered 768-D unit descriptors; ``recall_at_10`` of the HNSW gallery at 100k tiles
  against exact search and ``latency_ratio_100k_10k`` (per-query search latency at 100k over 10k).
  Targets: recall >= 0.95, ratio <= 3.
"""

from __future__ import annotations

import time

import numpy as np


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up: first-touch page faults of the large temporaries
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench_dem(n_points: int = 6_500_000, repeats: int = 5, seed: int = 0) -> dict:
    from vggt_slam_pp.dem import DemConfig, DemGrid, GroundPlane, rasterize
    from vggt_slam_pp.dem.raster import pixel_indices
    from vggt_slam_pp.geometry import so3_exp

    rng = np.random.default_rng(seed)
    R = so3_exp(np.array([0.05, -0.08, 0.6]))
    plane = GroundPlane(np.array([1.0, -2.0, 0.5]), R)
    uv = rng.uniform([0, 0], [40, 30], (n_points, 2))
    h = 0.5 * np.sin(uv[:, 0] / 3) + 0.3 * np.cos(uv[:, 1] / 2) + 0.02 * rng.normal(size=n_points)
    boxes = rng.random(n_points) < 0.1
    h[boxes] += rng.uniform(0.5, 3.0, boxes.sum())
    points = plane.to_world(np.c_[uv, h])
    grid = DemGrid.create(plane, DemConfig())

    def ours():
        return rasterize(points, grid, reducer="softmax", tau=0.02)

    def baseline():
        c = plane.to_canonical(points)
        iu, iv = pixel_indices(c, grid.mpp)
        u0, v0 = iu.min(), iv.min()
        return np.bincount((iv - v0) * (iu.max() - u0 + 1) + (iu - u0))

    t_ours = _median_time(ours, repeats)
    t_base = _median_time(baseline, repeats)
    layer = ours()
    return {"points": n_points, "reducer": "softmax", "seconds": t_ours, "baseline_seconds": t_base,
            "points_per_s": n_points / t_ours, "ratio_to_count_baseline": t_ours / t_base,
            "layer_shape": list(layer.heights.shape), "mpp": grid.mpp, "target_ratio": 3.0}


def bench_retrieval(n_large: int = 100_000, n_small: int = 10_000, dim: int = 768, queries: int = 1000,
                    seed: int = 0) -> dict:
    import faiss

    from vggt_slam_pp.retrieval import IndexConfig, TileIndex

    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(1000, dim)).astype(np.float32)

    def clustered(r, n):
        x = centres[r.integers(0, len(centres), n)] + 0.5 * r.normal(size=(n, dim)).astype(np.float32)
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    X = clustered(rng, n_large)
    Q = clustered(np.random.default_rng(seed + 1), queries)
    out: dict = {"dim": dim, "queries": queries, "config": IndexConfig().__dict__}
    for n, name in ((n_small, "10k"), (n_large, "100k")):
        index = TileIndex(dim)
        t = time.perf_counter()
        index.add(0, np.zeros((n, 2), np.int64), X[:n])
        out[f"build_seconds_{name}"] = time.perf_counter() - t
        index.search(Q[:10])
        t = time.perf_counter()
        _, found = index.search(Q)
        out[f"latency_ms_{name}"] = 1000 * (time.perf_counter() - t) / queries
        exact = faiss.IndexFlatIP(dim)
        exact.add(X[:n])
        _, truth = exact.search(Q, 10)
        out[f"recall_at_10_{name}"] = float(np.mean([len(set(a) & set(b)) / 10 for a, b in zip(truth, found,
                                                                                                 strict=True)]))
    out["recall_at_10"] = out["recall_at_10_100k"]
    out["latency_ratio_100k_10k"] = out["latency_ms_100k"] / out["latency_ms_10k"]
    out["targets"] = {"recall_at_10": 0.95, "latency_ratio_100k_10k": 3.0}
    return out
