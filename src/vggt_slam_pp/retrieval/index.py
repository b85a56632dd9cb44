"""The gallery of tile descriptors: FAISS ``IndexHNSWFlat`` (inner product = cosine on normalised
vectors) with an id map to (submap, Iu, Iv), incremental insertion, save/load, and submap voting
(SPEC 3.8).

Voting: for each query chip the ``k`` nearest tiles add their cosine to their parent submap's score, one
vote per submap and chip (its best tile there); the query's own submap and its ``exclude_recent`` most recent predecessors are excluded;
scores are divided by the number of chips (so they are comparable across queries); the submaps with
a score >= ``tau_s``, at most the top ``top_k`` = 10, become covisibility edges.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import RetrievalError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IndexConfig:
    hnsw_m: int = 32
    ef_construction: int = 80
    ef_search: int = 128
    k: int = 20  # nearest tiles per chip
    one_vote_per_submap: bool = True  # a chip votes once per submap (its best tile there): a layer with many
    # look-alike tiles (open ground, a long wall) no longer collects all of a chip's votes
    top_k: int = 10  # covisible submaps per query (K)
    tau_s: float = 0.0  # minimum normalised vote score
    exclude_recent: int = 2
    compact_min_dead: int = 1000  # rebuild once retired tiles exceed this and the live ones


@dataclass(frozen=True)
class CovisibilityEdge:
    query: int
    match: int
    score: float
    votes: int
    source: str = "votes"  # "votes": HNSW voting; "sequence": the previous query's match (backend.places)


class TileIndex:
    """HNSW gallery of L2-normalised tile descriptors of dimension ``dim``."""

    def __init__(self, dim: int, config: IndexConfig | None = None, encoder: str = "") -> None:
        self.dim, self.config, self.encoder = int(dim), config or IndexConfig(), encoder
        self.index = self._new_index()
        self.keys = np.zeros((0, 3), np.int64)  # id -> (submap, Iu, Iv)
        self.alive = np.zeros(0, bool)  # False for tiles of a re-rasterised layer (HNSW cannot delete)
        self.compactions = 0

    def _new_index(self):
        import faiss

        hnsw = faiss.IndexHNSWFlat(self.dim, self.config.hnsw_m, faiss.METRIC_INNER_PRODUCT)
        hnsw.hnsw.efConstruction = self.config.ef_construction
        hnsw.hnsw.efSearch = self.config.ef_search
        return faiss.IndexIDMap2(hnsw)

    def __len__(self) -> int:
        return int(self.index.ntotal)

    def _check(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise RetrievalError(f"descriptors must be [N,{self.dim}], got {x.shape}")
        return x

    def add(self, submap_id: int, tile_keys: np.ndarray, descriptors: np.ndarray) -> None:
        """Insert a submap's tiles: keys [T,2] (Iu, Iv), descriptors [T,dim]."""
        d = self._check(descriptors)
        if len(d) == 0:
            return
        ids = np.arange(len(self.keys), len(self.keys) + len(d), dtype=np.int64)
        self.index.add_with_ids(d, ids)
        keys = np.c_[np.full(len(d), submap_id, np.int64), np.asarray(tile_keys, np.int64).reshape(-1, 2)]
        self.keys = np.r_[self.keys, keys]
        self.alive = np.r_[self.alive, np.ones(len(d), bool)]

    def remove_submap(self, submap_id: int) -> int:
        """Retire a submap's tiles (before re-inserting its re-rasterised layer); returns how many.
        HNSW cannot delete: retired tiles stay in the graph, skipped by searches, until they outnumber
        the live ones; then the index is rebuilt from the live tiles (:meth:`compact`), so memory and
        search time follow the map, not the number of relocations."""
        dead = (self.keys[:, 0] == submap_id) & self.alive
        self.alive[dead] = False
        n_dead = len(self.alive) - int(self.alive.sum())
        if n_dead > max(int(self.alive.sum()), self.config.compact_min_dead):
            self.compact()
        return int(dead.sum())

    def compact(self) -> None:
        """Rebuild the HNSW graph from the live tiles only (ids renumbered, keys kept)."""
        import faiss

        live = np.nonzero(self.alive)[0]
        vectors = np.zeros((0, self.dim), np.float32)
        if len(live):
            internal = faiss.vector_to_array(self.index.id_map)  # internal position -> id
            everything = self.index.index.reconstruct_n(0, self.index.ntotal)
            pos = np.empty(len(internal), np.int64)
            pos[internal] = np.arange(len(internal))
            vectors = everything[pos[live]]
        self.index = self._new_index()
        if len(live):
            self.index.add_with_ids(np.ascontiguousarray(vectors), np.arange(len(live), dtype=np.int64))
        log.debug("tile index compacted: %d dead tiles dropped, %d kept", len(self.alive) - len(live), len(live))
        self.keys, self.alive = self.keys[live], np.ones(len(live), bool)
        self.compactions += 1

    def tiles_of(self, submap_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The live tiles of a submap: keys [T,2] (Iu, Iv) and descriptors [T,dim]."""
        ids = np.nonzero((self.keys[:, 0] == submap_id) & self.alive)[0]
        if len(ids) == 0:
            return np.zeros((0, 2), np.int64), np.zeros((0, self.dim), np.float32)
        return self.keys[ids, 1:], np.stack([self.index.reconstruct(int(i)) for i in ids])

    def search(self, queries: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(similarities [Q,k], ids [Q,k]; -1 where fewer than k tiles)."""
        q = self._check(queries)
        return self.index.search(q, k or self.config.k)

    def vote(self, query_submap: int, chips: np.ndarray, top_k: int | None = None) -> list[CovisibilityEdge]:
        """Covisibility edges of ``query_submap`` from its chip descriptors [C,dim], best first (at most
        ``top_k``, default ``IndexConfig.top_k``)."""
        c = self.config
        if len(self) == 0 or len(chips) == 0:
            return []
        dead = int((~self.alive).sum())
        sims, ids = self.search(chips, c.k + min(dead, 4 * c.k))
        ok = ids >= 0
        ok[ok] = self.alive[ids[ok]]
        ok &= np.cumsum(ok, axis=1) <= c.k  # the k best live tiles per chip
        submaps = np.where(ok, self.keys[np.maximum(ids, 0), 0], -1)
        excluded = (submaps < 0) | (submaps >= query_submap - c.exclude_recent)
        if c.one_vote_per_submap:  # a chip's later hits in a submap it already voted for do not count
            for col in range(1, submaps.shape[1]):
                excluded[:, col] |= (submaps[:, :col] == submaps[:, col:col + 1]).any(axis=1)
        sims = np.where(excluded, 0.0, np.maximum(sims, 0.0))
        if not (~excluded).any():
            return []
        cand = np.unique(submaps[~excluded])
        score = np.array([sims[submaps == s].sum() for s in cand]) / len(chips)
        votes = np.array([int(((submaps == s) & ~excluded).sum()) for s in cand])
        order = np.argsort(-score, kind="stable")[: top_k or c.top_k]
        return [CovisibilityEdge(query_submap, int(cand[i]), float(score[i]), int(votes[i]))
                for i in order if score[i] >= c.tau_s and score[i] > 0]

    # -- persistence ------------------------------------------------------------------------------
    def save(self, folder: str | Path) -> None:
        import faiss

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        faiss.write_index(self.index, str(folder / "tiles.faiss.tmp"))
        (folder / "tiles.faiss.tmp").replace(folder / "tiles.faiss")
        np.save(folder / "tile_keys.npy", self.keys)
        np.save(folder / "tile_alive.npy", self.alive)
        meta = {"dim": self.dim, "encoder": self.encoder, "config": asdict(self.config), "ntotal": len(self)}
        (folder / "tiles.json").write_text(json.dumps(meta, indent=2))

    @classmethod
    def load(cls, folder: str | Path, dim: int | None = None, encoder: str | None = None) -> TileIndex:
        """Load an index; ``dim`` / ``encoder`` (if given) must match what it was built with."""
        import faiss

        folder = Path(folder)
        try:
            meta = json.loads((folder / "tiles.json").read_text())
            index = faiss.read_index(str(folder / "tiles.faiss"))
            keys = np.load(folder / "tile_keys.npy")
            alive_file = folder / "tile_alive.npy"
            alive = np.load(alive_file) if alive_file.is_file() else np.ones(len(keys), bool)
        except (OSError, ValueError, RuntimeError) as exc:
            raise RetrievalError(f"cannot read the tile index in {folder}: {exc}") from exc
        if dim is not None and meta["dim"] != dim:
            raise RetrievalError(f"the tile index in {folder} holds {meta['dim']}-D descriptors, this "
                                 f"configuration makes {dim}-D ones (another encoder?); rebuild it")
        if encoder is not None and meta["encoder"] != encoder:
            raise RetrievalError(f"the tile index in {folder} was built with encoder {meta['encoder']!r}, "
                                 f"not {encoder!r}; rebuild it")
        if index.ntotal != len(keys) or index.d != meta["dim"]:
            raise RetrievalError(f"the tile index in {folder} is inconsistent (ids vs keys); rebuild it")
        obj = cls(meta["dim"], IndexConfig(**meta["config"]), meta["encoder"])
        obj.index, obj.keys, obj.alive = index, keys, alive
        faiss.downcast_index(index.index).hnsw.efSearch = obj.config.ef_search
        return obj
