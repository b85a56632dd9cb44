"""The map's place layer (:class:`Gallery`) and the covisibility stage that queries it (SPEC 3.6-3.9).

:class:`Gallery` holds, for every submap in the map, what place recognition needs of its DEM layer: the
tile descriptors in the FAISS-HNSW :class:`~vggt_slam_pp.retrieval.index.TileIndex`, its VLAD features
(float16) and the VLAD :class:`~vggt_slam_pp.vpr.vlad.Vocabulary` trained on a bounded sample of them, and
its DEM structure for geometric re-ranking, all in the map's ground-plane grid (fixed by the first
submap, or by a saved map). It knows no poses: layers come in the world frame, and the back-end's
:class:`~vggt_slam_pp.backend.map.Map` decides when a moved submap is described again.

:class:`CovisibilityStage` is what the back-end runs for every new submap:

1. rasterise the submap's points (world frame) into its DEM layer;
2. encode the layer's encoder image once (dense patch features) and compute the gradient weights;
3. chips (window = whole layer) vote in the HNSW gallery -> covisibility edges; the previous query's
   match (its verified loop when the back-end reported one through :meth:`CovisibilityStage.confirm`,
   else its top candidate) and its ``sequence_neighbours`` temporal neighbours on either side join them
   (source "sequence"): a camera that revisits a place keeps revisiting the places along it, so the
   submap that follows a revisit query overlaps the ones next to that query's match;
4. VLAD of the chips against the tiles of the candidate pool (the ``candidate_pool`` best-voted submaps, of
   which the top K are the covisibility edges, and the sequence edges), then every submap of the pool re-ranked
   by DEM structure correlation over yaw and shift (:mod:`vggt_slam_pp.vpr.geometry`) -> loop candidates;
5. (``insert``) add the layer's tiles (descriptors and VLAD features) to the gallery; the VLAD vocabulary
   is refreshed as the gallery grows.

Tiles need at least ``min_occupancy`` non-empty pixels to enter the gallery or act as chips.
``retrieval/`` (encoders, descriptors, the index) and ``vpr/`` (VLAD, structure) are the leaf libraries
this module puts together.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from vggt_slam_pp.dem import DemConfig, DemGrid, DemLayer, encoder_image, fit_ground_plane, rasterize
from vggt_slam_pp.dem.images import fill_holes
from vggt_slam_pp.errors import RetrievalError
from vggt_slam_pp.retrieval.descriptors import aggregate, cell_weights
from vggt_slam_pp.retrieval.encoders import Encoder
from vggt_slam_pp.retrieval.index import CovisibilityEdge, IndexConfig, TileIndex
from vggt_slam_pp.vpr.geometry import GeometryConfig, Structure, layer_structure, rerank_candidates
from vggt_slam_pp.vpr.vlad import LoopCandidate, Vocabulary, rank_candidates, tile_vlads

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CovisibilityConfig:
    dem: DemConfig = field(default_factory=DemConfig)
    index: IndexConfig = field(default_factory=IndexConfig)
    min_occupancy: float = 0.1
    vlad_clusters: int = 32
    vlad_context_tiles: int = 3
    vlad_min_score: float = 0.0
    vlad_sample: int = 50_000  # features kept (float16) for (re)training the vocabulary
    vlad_cache_submaps: int = 16  # tile VLADs cached for this many submaps (oldest first out), or a query's
    # candidate pool and its sequence edges if more
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    rerank: bool = True  # candidates = the candidate pool ranked by structure correlation (VLAD breaks ties)
    sequence_neighbours: int = 1  # the previous query's match +- this many submaps join the covisible set; -1: off
    candidate_pool: int = 10  # loop candidates are ranked (VLAD, then structure) from this many best-voted submaps
    # (at least the top K = 10 that become covisibility edges). 20 raises the loop candidates' recall under the
    # realistic profile's drift (0.751 / 0.783 -> 0.834 / 0.802, seeds 0 / 1), but in the whole system it was neutral
    # and let one look-alike in as a loop: kept at K (docs/retrieval.md, "candidate pool")


@dataclass(frozen=True, eq=False)
class Described:
    """One DEM layer, described: what the gallery stores of it and what its queries use."""

    layer: DemLayer
    vfeats: np.ndarray  # [rows, cols, D] VLAD features
    m: np.ndarray  # [rows, cols] cell weights
    cpt: int  # cells per tile
    tiles: np.ndarray  # [Tr, Tc, D]
    chips: np.ndarray  # [Tr, Tc, D]
    usable: np.ndarray  # [Tr, Tc] tiles entering the gallery
    chip_ok: np.ndarray  # [Tr, Tc] chips that query
    keys: np.ndarray  # [Tr, Tc, 2] global tile keys
    structure: Structure  # for geometric re-ranking


@dataclass
class StageResult:
    submap_id: int
    layer: DemLayer
    edges: list[CovisibilityEdge]
    candidates: list[LoopCandidate]
    timings: dict[str, float]
    chip_keys: np.ndarray  # [C,2] (Iu, Iv) of the chips that voted
    chip_descriptors: np.ndarray  # [C,D]
    described: Described | None  # the query's layer, for :meth:`Gallery.add` (None once inserted)


def ranked_matches(result: StageResult) -> list[tuple[int, float]]:
    """(match, score) of a query's loop candidates in their order, then of its other edges in theirs: the order
    in which place recognition proposes matches to the back-end."""
    out = [(c.match, c.score) for c in result.candidates]
    seen = {j for j, _ in out}
    return out + [(e.match, e.score) for e in result.edges if e.match not in seen]


def camera_depth(points: np.ndarray, camera_centers: np.ndarray) -> float | None:
    """The median distance of points [N,3] to the nearest of their cameras [S,3] (None without either)."""
    if not len(points) or not len(camera_centers):
        return None
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(camera_centers).query(points)[0]))


class Gallery:
    """The place layer of the map: one described DEM layer per submap (see the module docstring)."""

    def __init__(self, encoder: Encoder, config: CovisibilityConfig | None = None) -> None:
        self.encoder = encoder
        self.config = config or CovisibilityConfig()
        self.grid: DemGrid | None = None
        self.index: TileIndex | None = None
        self.vocab: Vocabulary | None = None
        self._vlad_cells: list[np.ndarray] = []
        self._tile_vlads: dict[int, np.ndarray] = {}
        self._tile_cells: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}  # features, usable tiles, cells/tile
        self._structure: dict[int, Structure] = {}
        self._vlad_seen = 0

    def __contains__(self, submap_id: int) -> bool:
        return submap_id in self._structure

    def ensure_grid(self, points_world: np.ndarray, camera_centers: np.ndarray | None,
                    median_depth: float | None) -> None:
        """Fit the ground plane and grid to the first submaps' points [N,3] and cameras [S,3] (world frame), unless
        a grid is set; ``median_depth``: the "auto" tile's depth (None: the points' to the nearest camera)."""
        if self.grid is None:
            plane = fit_ground_plane(points_world, camera_centers)
            if median_depth is None and self.config.dem.tile_size == "auto" and camera_centers is not None:
                median_depth = camera_depth(points_world, camera_centers)
            self.grid = DemGrid.create(plane, self.config.dem, median_depth)
            cells_per_tile = self.grid.tile_px / self.encoder.patch_px
            if cells_per_tile != int(cells_per_tile):
                log.warning("tile_px %d is not a multiple of the encoder patch %d", self.grid.tile_px,
                            self.encoder.patch_px)

    def set_grid(self, grid: DemGrid) -> None:
        """Use ``grid`` (a saved map's plane and tiles) instead of fitting one to the first submap."""
        self.grid = grid

    def describe(self, submap_id: int, points_world: np.ndarray) -> Described:
        """Rasterise and encode a submap's points [N,3] (world frame) in the gallery's grid."""
        c = self.config
        layer = rasterize(points_world, self.grid, submap_id, c.dem.reducer, c.dem.tau)
        heights = fill_holes(layer.heights, c.dem.fill_radius_px)
        img = encoder_image(heights, c.dem.alpha_edge, c.dem.percentiles)
        feats = self.encoder.encode(img)
        vfeats = self.encoder.vlad_features(img) if self.encoder.name != "hog" else feats
        m = cell_weights(heights, self.encoder.patch_px)[: feats.shape[0], : feats.shape[1]]
        cpt = max(1, self.grid.tile_px // self.encoder.patch_px)
        tiles, _ = aggregate(feats, m, cpt, window_tiles=9)
        chips, _ = aggregate(feats, m, cpt, window_tiles=None)
        occ = layer.tile_occupancy()
        tr, tc = tiles.shape[:2]
        usable = (occ[:tr, :tc] >= c.min_occupancy) & (np.linalg.norm(tiles, axis=2) > 0)
        chip_ok = usable & (np.linalg.norm(chips, axis=2) > 0)
        return Described(layer, vfeats, m, cpt, tiles, chips, usable, chip_ok, _keys(layer, tr, tc),
                         layer_structure(layer, self.grid.tile_size, c.geometry))

    def vote(self, submap_id: int, chips: np.ndarray, top_k: int | None = None) -> list[CovisibilityEdge]:
        """HNSW voting of a query's chip descriptors [C,D] (:meth:`TileIndex.vote`)."""
        self._ensure_index(chips.shape[-1])
        return self.index.vote(submap_id, chips, top_k)

    def add(self, submap_id: int, described: Described | np.ndarray) -> None:
        """Insert a submap's tiles into the gallery (``described``: its layer's descriptors, or its points in
        the world frame; the grid must exist)."""
        d = described if isinstance(described, Described) else self.describe(submap_id, described)
        self._ensure_index(d.tiles.shape[2])
        self._insert(submap_id, d)
        self._vlad_cells.append(d.vfeats[d.m > 0].reshape(-1, d.vfeats.shape[2]).astype(np.float16))
        self._cap_vlad_cells()
        if self.vocab is not None and self.vocab.needs_refresh(self._vlad_seen):
            self._train_vocabulary()

    def relocate(self, submap_id: int, points_world: np.ndarray) -> DemLayer:
        """Describe again a submap whose pose the back-end changed (``points_world``: at the new pose)."""
        if self.index is None or self.grid is None:
            raise RetrievalError("relocate before any submap was processed")
        d = self.describe(submap_id, points_world)
        self.index.remove_submap(submap_id)
        self._insert(submap_id, d)
        return d.layer

    def vocabulary(self) -> Vocabulary | None:
        """The VLAD vocabulary; trained the first time the gallery holds ``4 x vlad_clusters`` features."""
        if self.vocab is None and self._vlad_count() >= self.config.vlad_clusters * 4:
            self._train_vocabulary()
        return self.vocab

    def structures(self, submap_ids) -> dict[int, Structure]:
        return {i: self._structure[i] for i in submap_ids if i in self._structure}

    def tiles_of(self, submap_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Live gallery tiles of a submap: keys [T,2] and descriptors [T,D]."""
        return self.index.tiles_of(submap_id) if self.index is not None else (np.zeros((0, 2)), np.zeros((0, 0)))

    def tile_centers_uv(self, keys: np.ndarray) -> np.ndarray:
        """Canonical (u, v) of tile centres [T,2] from their keys (Iu, Iv)."""
        return (np.asarray(keys, float) + 0.5) * self.grid.tile_size

    def vlads_of(self, submap_id: int) -> np.ndarray:
        """VLADs [T,D'] of a submap's usable tiles under the current vocabulary (an LRU of
        ``vlad_cache_submaps`` submaps)."""
        if submap_id not in self._tile_vlads:
            vfeats, usable, cpt = self._tile_cells[submap_id]
            v = tile_vlads(vfeats.astype(np.float32), self.vocab, cpt, self.config.vlad_context_tiles)
            tr, tc = usable.shape
            c = self.config
            if len(self._tile_vlads) >= max(c.vlad_cache_submaps, c.candidate_pool + 2 * c.sequence_neighbours + 1):
                self._tile_vlads.pop(next(iter(self._tile_vlads)))
            self._tile_vlads[submap_id] = v[:tr, :tc][usable]
        return self._tile_vlads[submap_id]

    def _ensure_index(self, dim: int) -> None:
        if self.index is None:
            self.index = TileIndex(dim, self.config.index, self.encoder.name)

    def _insert(self, submap_id: int, d: Described) -> None:
        self.index.add(submap_id, d.keys[d.usable], d.tiles[d.usable])
        self._tile_cells[submap_id] = (d.vfeats.astype(np.float16), d.usable, d.cpt)  # compact: RAM stays low
        self._structure[submap_id] = d.structure
        self._tile_vlads.pop(submap_id, None)

    def _vlad_count(self) -> int:
        return sum(len(x) for x in self._vlad_cells)

    def _cap_vlad_cells(self) -> None:
        """Keep at most ``vlad_sample`` features for vocabulary training (RAM stays flat)."""
        self._vlad_seen += len(self._vlad_cells[-1])
        total = self._vlad_count()
        if total > self.config.vlad_sample:
            x = np.concatenate(self._vlad_cells)
            keep = np.random.default_rng(len(self._tile_cells)).choice(total, self.config.vlad_sample, replace=False)
            self._vlad_cells = [x[np.sort(keep)]]

    def _train_vocabulary(self) -> None:
        self.vocab = Vocabulary.train(np.concatenate(self._vlad_cells).astype(np.float32), self.config.vlad_clusters)
        self.vocab.trained_on = max(self._vlad_seen, 1)
        self._tile_vlads = {}


class CovisibilityStage:
    """Queries of the :class:`Gallery` by new submaps, with the sequence prior between consecutive ones."""

    def __init__(self, gallery: Gallery) -> None:
        self.gallery = gallery
        self.config = gallery.config
        # query -> its matches, for the sequence prior of the next submap's query, which may run much later
        # (deferred by a worker catching up): a few integers per submap
        self._matches: dict[int, tuple[int, ...]] = {}

    @classmethod
    def create(cls, encoder: Encoder, config: CovisibilityConfig | None = None) -> CovisibilityStage:
        """A stage over a new, empty gallery."""
        return cls(Gallery(encoder, config))

    @property
    def grid(self) -> DemGrid | None:
        return self.gallery.grid

    def process(self, submap_id: int, points_world: np.ndarray, camera_centers: np.ndarray | None = None,
                median_depth: float | None = None, insert: bool = True, headings: int = 1) -> StageResult:
        """Query the gallery with a new submap's layer and (``insert``) add its tiles.

        ``headings`` > 1: the chips of copies of the submap turned about the vertical by multiples of
        360 / ``headings`` degrees vote too (a submap whose heading in the map is unknown: DEM
        descriptors are not rotation-invariant); the edges keep each match's best score.
        """
        c, g = self.config, self.gallery
        t = {}
        t0 = time.perf_counter()
        g.ensure_grid(points_world, camera_centers, median_depth)
        t["raster_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = g.describe(submap_id, points_world)
        t["encode_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pool_k = max(c.index.top_k, c.candidate_pool)
        voted = g.vote(submap_id, d.chips[d.chip_ok], pool_k)
        if headings > 1:
            voted = self._vote_turned(submap_id, points_world, headings, voted, pool_k)
        covisible = voted[: c.index.top_k]  # the covisibility edges (SPEC: the top K = 10 by votes)
        sequence = self._sequence_edges(submap_id, {e.match for e in covisible})
        edges = covisible + sequence
        in_pool = {e.match for e in voted}
        pool = voted + [e for e in sequence if e.match not in in_pool]  # what the loop candidates are ranked from
        t["vote_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        candidates: list[LoopCandidate] = []
        vocab = g.vocabulary()
        if vocab is not None and pool:
            tr, tc = d.usable.shape
            q = tile_vlads(d.vfeats, vocab, d.cpt, c.vlad_context_tiles)[:tr, :tc][d.chip_ok]
            gallery = {e.match: g.vlads_of(e.match) for e in pool}
            gallery = {k: v for k, v in gallery.items() if len(v)}
            candidates = rank_candidates(submap_id, q, gallery, c.vlad_min_score)
        t["vlad_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if c.rerank and pool:
            candidates = rerank_candidates(submap_id, d.structure, g.structures(e.match for e in pool), candidates,
                                           g.grid.tile_size, c.geometry)
        t["rerank_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if insert:
            g.add(submap_id, d)
        t["index_s"] = time.perf_counter() - t0
        self._matches[submap_id] = (candidates[0].match,) if candidates else ()
        return StageResult(submap_id, d.layer, edges, candidates, t, d.keys[d.chip_ok], d.chips[d.chip_ok],
                           None if insert else d)

    def _vote_turned(self, submap_id: int, points_world: np.ndarray, headings: int,
                     edges: list[CovisibilityEdge], top_k: int) -> list[CovisibilityEdge]:
        from vggt_slam_pp.geometry.lie import so3_exp

        best = {e.match: e for e in edges}
        centre = points_world.mean(0)
        for k in range(1, headings):
            R = so3_exp(self.grid.plane.normal * (2 * np.pi * k / headings))
            d = self.gallery.describe(submap_id, (points_world - centre) @ R.T + centre)
            for e in self.gallery.vote(submap_id, d.chips[d.chip_ok], top_k):
                if e.match not in best or e.score > best[e.match].score:
                    best[e.match] = e
        return sorted(best.values(), key=lambda e: -e.score)[:top_k]

    def confirm(self, query: int, matches: list[int]) -> None:
        """The back-end verified loops ``query`` -> ``matches``: they (not the top candidate) anchor the
        sequence prior of the query of submap ``query + 1``. Ignored unless ``query`` has been queried."""
        if query in self._matches and matches:
            self._matches[query] = tuple(int(m) for m in matches)

    def _sequence_edges(self, submap_id: int, voted: set[int]) -> list[CovisibilityEdge]:
        """Edges to the matches of the query of submap ``submap_id - 1`` and their +-``sequence_neighbours``
        neighbours that are in the gallery, older than the excluded recent submaps and not voted already
        (score 0). The prior follows the submaps, not the order of the queries: a worker catching up runs
        the queries it deferred later, and there a deferred query still follows its predecessor's."""
        n = self.config.sequence_neighbours
        previous = self._matches.get(submap_id - 1)
        if n < 0 or previous is None:
            return []
        newest = submap_id - self.config.index.exclude_recent
        near = sorted({m + k for m in previous for k in range(-n, n + 1)})
        return [CovisibilityEdge(submap_id, m, 0.0, 0, "sequence") for m in near
                if m < newest and m in self.gallery and m not in voted]


def _keys(layer: DemLayer, tr: int, tc: int) -> np.ndarray:
    iv, iu = np.mgrid[0:tr, 0:tc]
    return np.stack([iu + layer.origin_tile[0], iv + layer.origin_tile[1]], axis=-1)
