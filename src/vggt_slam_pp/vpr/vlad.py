"""AnyLoc-style VLAD (SPEC 3.9): dense features hard-assigned to a k-means vocabulary (32 clusters),
residuals summed per cluster, intra-normalised per cluster, then L2-normalised.

The vocabulary is built by k-means (FAISS) from gallery features and refreshed as the map grows
(:meth:`Vocabulary.needs_refresh`). Retrieval: a query chip's VLAD against the VLADs of the tiles of
the covisible submaps only; each chip's best tile votes (its cosine) for its submap; submaps ranked by
the summed votes become loop candidates (those above ``min_score``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vggt_slam_pp.errors import RetrievalError


class Vocabulary:
    def __init__(self, centroids: np.ndarray, trained_on: int) -> None:
        self.centroids = np.ascontiguousarray(centroids, dtype=np.float32)
        self.trained_on = trained_on

    @property
    def k(self) -> int:
        return len(self.centroids)

    @property
    def dim(self) -> int:
        return self.centroids.shape[1]

    @classmethod
    def train(cls, features: np.ndarray, k: int = 32, niter: int = 20, seed: int = 0,
              max_points: int = 100_000) -> Vocabulary:
        import faiss

        x = np.ascontiguousarray(features, dtype=np.float32).reshape(-1, np.shape(features)[-1])
        if len(x) < k:
            raise RetrievalError(f"need at least {k} features to build a {k}-word vocabulary, got {len(x)}")
        if len(x) > max_points:
            x = x[np.random.default_rng(seed).choice(len(x), max_points, replace=False)]
        # a young map has few features per word (the vocabulary is refreshed as it grows): FAISS would print a
        # warning to stderr at every training below 39 per word
        km = faiss.Kmeans(x.shape[1], k, niter=niter, seed=seed, verbose=False, min_points_per_centroid=1)
        km.train(x)
        return cls(km.centroids, len(x))

    def needs_refresh(self, gallery_size: int, growth: float = 2.0) -> bool:
        """Refresh once the gallery has grown by ``growth`` x since training."""
        return gallery_size >= growth * max(self.trained_on, 1)

    def assign(self, features: np.ndarray) -> np.ndarray:
        x = np.asarray(features, np.float32)
        d2 = (x * x).sum(1)[:, None] - 2 * x @ self.centroids.T + (self.centroids**2).sum(1)[None]
        return np.argmin(d2, axis=1)


def vlad(features: np.ndarray, vocab: Vocabulary, assignments: np.ndarray | None = None) -> np.ndarray:
    """VLAD of a set of features [N,D] -> [k*D] float32 (intra- then L2-normalised; zeros if N == 0)."""
    x = np.asarray(features, np.float32).reshape(-1, vocab.dim)
    out = np.zeros((vocab.k, vocab.dim), np.float32)
    if len(x):
        a = vocab.assign(x) if assignments is None else assignments
        np.add.at(out, a, x - vocab.centroids[a])
        n = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.where(n > 0, out / np.maximum(n, 1e-12), 0.0)
    flat = out.reshape(-1)
    n = np.linalg.norm(flat)
    return (flat / n if n > 0 else flat).astype(np.float32)


def tile_vlads(cell_features: np.ndarray, vocab: Vocabulary, cells_per_tile: int = 2,
               context_tiles: int = 3) -> np.ndarray:
    """VLAD of every tile of a layer over the cells of its ``context_tiles`` x ``context_tiles``
    neighbourhood: [Tr, Tc, k*D]. (A 2x2-cell tile alone has too few features for a VLAD.)

    The same as :func:`vlad` of each tile's window of ``cell_features`` [rows, cols, D], computed at once: every
    cell's residual to its word summed per block of ``cells_per_tile`` x ``cells_per_tile`` cells (a window is a
    run of whole blocks; the cells beyond the last tile are one more row and column of blocks), then over the
    windows through an integral image of the blocks."""
    rows, cols, D = cell_features.shape
    c, k = cells_per_tile, vocab.k
    tr, tc = rows // c, cols // c
    if tr == 0 or tc == 0:
        return np.zeros((tr, tc, k * D), np.float32)
    x = np.asarray(cell_features, np.float32).reshape(-1, D)
    assign = vocab.assign(x)
    block = ((np.arange(rows) // c)[:, None] * (tc + 1) + (np.arange(cols) // c)[None]).reshape(-1)
    slot = ((block * k + assign) * D)[:, None] + np.arange(D)[None]  # each residual's entry in the block sums
    integral = np.zeros((tr + 2, tc + 2, k, D), np.float64)
    integral[1:, 1:] = np.bincount(slot.reshape(-1), (x - vocab.centroids[assign]).reshape(-1).astype(np.float64),
                                   (tr + 1) * (tc + 1) * k * D).reshape(tr + 1, tc + 1, k, D)
    for i in range(2, tr + 2):  # cumulative sums down, then across (numpy's cumsum over a leading axis is slow)
        integral[i] += integral[i - 1]
    for j in range(2, tc + 2):
        integral[:, j] += integral[:, j - 1]
    h = context_tiles // 2
    i0, i1 = np.maximum(0, np.arange(tr) - h)[:, None], np.minimum(tr + 1, np.arange(tr) + h + 1)[:, None]
    j0, j1 = np.maximum(0, np.arange(tc) - h)[None], np.minimum(tc + 1, np.arange(tc) + h + 1)[None]
    out = integral[i1, j1] - integral[i0, j1] - integral[i1, j0] + integral[i0, j0]  # [tr, tc, k, D]
    n = np.linalg.norm(out, axis=3, keepdims=True)
    out = np.where(n > 1e-9, out / np.maximum(n, 1e-12), 0.0).reshape(tr, tc, k * D)
    n = np.linalg.norm(out, axis=2, keepdims=True)
    return np.where(n > 0, out / np.maximum(n, 1e-300), out).astype(np.float32)


@dataclass(frozen=True)
class LoopCandidate:
    query: int
    match: int
    score: float  # VLAD: summed best-tile cosines / chips
    votes: int
    geometry: float = -1.0  # structure correlation in [0, 1] (vpr.geometry); -1 when not checked


def rank_candidates(query_submap: int, chip_vlads: np.ndarray, gallery: dict[int, np.ndarray],
                    min_score: float = 0.0) -> list[LoopCandidate]:
    """Chips [C, V] vote with their best tile among the covisible submaps' tile VLADs
    (``gallery``: submap -> [T, V]); returns candidates sorted by summed cosine."""
    if not gallery or len(chip_vlads) == 0:
        return []
    ids = np.concatenate([np.full(len(v), s) for s, v in gallery.items()])
    tiles = np.concatenate(list(gallery.values()))
    sims = chip_vlads @ tiles.T
    best = np.argmax(sims, axis=1)
    best_sim = sims[np.arange(len(best)), best]
    out = []
    for s in np.unique(ids[best]):
        sel = ids[best] == s
        score = float(np.maximum(best_sim[sel], 0).sum() / len(chip_vlads))
        if score > min_score:
            out.append(LoopCandidate(query_submap, int(s), score, int(sel.sum())))
    return sorted(out, key=lambda c: -c.score)
