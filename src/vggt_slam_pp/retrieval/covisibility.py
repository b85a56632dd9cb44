"""Per-submap retrieval stage: DEM layer -> encoder -> tile/chip descriptors -> HNSW voting -> VLAD.

:class:`CovisibilityStage` is what the back-end calls for every new submap (SPEC 3.6-3.9):

1. rasterise the submap's points (world frame) into its DEM layer (the ground plane and grid are
   fixed by the first submap);
2. encode the layer's encoder image once (dense patch features) and compute the gradient weights;
3. chips (window = whole layer) vote in the HNSW gallery -> covisibility edges; the previous query's
   match (its verified loop when the back-end reported one through :meth:`CovisibilityStage.confirm`,
   else its top candidate) and its ``sequence_neighbours`` temporal neighbours on either side join them
   (source "sequence"): a camera that revisits a place keeps revisiting the places along it, so the
   submap that follows a revisit query overlaps the ones next to that query's match;
4. VLAD of the chips against the tiles of the covisible submaps, then every covisible submap re-ranked
   by DEM structure correlation over yaw and shift (:mod:`vggt_slam_pp.vpr.geometry`) -> loop candidates;
5. insert the layer's tiles (descriptors and VLADs) into the gallery; refresh the VLAD vocabulary as
   the gallery grows.

Tiles need at least ``min_occupancy`` non-empty pixels to enter the gallery or act as chips.
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
    vlad_cache_submaps: int = 16  # tile VLADs cached for this many submaps (oldest first out)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    rerank: bool = True  # candidates = the covisible submaps ranked by structure correlation (VLAD breaks ties)
    sequence_neighbours: int = 1  # the previous query's match +- this many submaps join the covisible set; -1: off


@dataclass(frozen=True, eq=False)
class _Described:
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


class CovisibilityStage:
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
        self._previous: tuple[int, list[int]] | None = None  # (query, its matches) for the sequence prior

    def _ensure_grid(self, points_world: np.ndarray, camera_centers: np.ndarray | None,
                     median_depth: float | None) -> None:
        if self.grid is None:
            plane = fit_ground_plane(points_world, camera_centers)
            if median_depth is None and self.config.dem.tile_size == "auto" and camera_centers is not None \
                    and len(camera_centers) and len(points_world):
                from scipy.spatial import cKDTree

                median_depth = float(np.median(cKDTree(camera_centers).query(points_world)[0]))
            self.grid = DemGrid.create(plane, self.config.dem, median_depth)
            cells_per_tile = self.grid.tile_px / self.encoder.patch_px
            if cells_per_tile != int(cells_per_tile):
                log.warning("tile_px %d is not a multiple of the encoder patch %d", self.grid.tile_px,
                            self.encoder.patch_px)

    def _describe(self, submap_id: int, points_world: np.ndarray) -> _Described:
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
        return _Described(layer, vfeats, m, cpt, tiles, chips, usable, chip_ok, _keys(layer, tr, tc),
                          layer_structure(layer, self.grid.tile_size, c.geometry))

    def process(self, submap_id: int, points_world: np.ndarray, camera_centers: np.ndarray | None = None,
                median_depth: float | None = None, insert: bool = True, headings: int = 1) -> StageResult:
        """Query the gallery with a new submap's layer and (``insert``) add its tiles.

        ``headings`` > 1: the chips of copies of the submap turned about the vertical by multiples of
        360 / ``headings`` degrees vote too (a submap whose heading in the map is unknown: DEM
        descriptors are not rotation-invariant); the edges keep each match's best score.
        """
        c = self.config
        t = {}
        t0 = time.perf_counter()
        self._ensure_grid(points_world, camera_centers, median_depth)
        t["raster_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = self._describe(submap_id, points_world)
        t["encode_s"] = time.perf_counter() - t0
        if self.index is None:
            self.index = TileIndex(d.tiles.shape[2], c.index, self.encoder.name)
        t0 = time.perf_counter()
        edges = self.index.vote(submap_id, d.chips[d.chip_ok])
        if headings > 1:
            edges = self._vote_turned(submap_id, points_world, headings, edges)
        edges += self._sequence_edges(submap_id, {e.match for e in edges})
        t["vote_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        candidates: list[LoopCandidate] = []
        if self.vocab is None and self._vlad_count() >= c.vlad_clusters * 4:
            self._train_vocabulary()
        if self.vocab is not None and edges:
            tr, tc = d.usable.shape
            q = tile_vlads(d.vfeats, self.vocab, d.cpt, c.vlad_context_tiles)[:tr, :tc][d.chip_ok]
            gallery = {e.match: self._vlads_of(e.match) for e in edges}
            gallery = {k: v for k, v in gallery.items() if len(v)}
            candidates = rank_candidates(submap_id, q, gallery, c.vlad_min_score)
        t["vlad_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if c.rerank and edges:
            structures = {e.match: self._structure[e.match] for e in edges if e.match in self._structure}
            candidates = rerank_candidates(submap_id, d.structure, structures, candidates, self.grid.tile_size,
                                           c.geometry)
        t["rerank_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if insert:
            self.add(submap_id, d)
        t["index_s"] = time.perf_counter() - t0
        self._previous = (submap_id, [candidates[0].match] if candidates else [])
        return StageResult(submap_id, d.layer, edges, candidates, t, d.keys[d.chip_ok], d.chips[d.chip_ok])

    def add(self, submap_id: int, described: _Described | np.ndarray) -> None:
        """Insert a submap's tiles into the gallery without querying (``described``: its layer's
        descriptors, or its points in the world frame; the grid must exist)."""
        d = described if isinstance(described, _Described) else self._describe(submap_id, described)
        if self.index is None:
            self.index = TileIndex(d.tiles.shape[2], self.config.index, self.encoder.name)
        self._insert(submap_id, d)
        self._vlad_cells.append(d.vfeats[d.m > 0].reshape(-1, d.vfeats.shape[2]).astype(np.float16))
        self._cap_vlad_cells()
        if self.vocab is not None and self.vocab.needs_refresh(self._vlad_seen):
            self._train_vocabulary()

    def _vote_turned(self, submap_id: int, points_world: np.ndarray, headings: int,
                     edges: list[CovisibilityEdge]) -> list[CovisibilityEdge]:
        from vggt_slam_pp.geometry.lie import so3_exp

        best = {e.match: e for e in edges}
        centre = points_world.mean(0)
        for k in range(1, headings):
            R = so3_exp(self.grid.plane.normal * (2 * np.pi * k / headings))
            d = self._describe(submap_id, (points_world - centre) @ R.T + centre)
            for e in self.index.vote(submap_id, d.chips[d.chip_ok]):
                if e.match not in best or e.score > best[e.match].score:
                    best[e.match] = e
        return sorted(best.values(), key=lambda e: -e.score)[: self.config.index.top_k]

    def set_grid(self, grid: DemGrid) -> None:
        """Use ``grid`` (a saved map's plane and tiles) instead of fitting one to the first submap."""
        self.grid = grid

    def confirm(self, query: int, matches: list[int]) -> None:
        """The back-end verified loops ``query`` -> ``matches``: they (not the top candidate) anchor the
        next query's sequence prior. Ignored unless ``query`` is the last processed submap."""
        if self._previous is not None and self._previous[0] == query and matches:
            self._previous = (query, [int(m) for m in matches])

    def _sequence_edges(self, submap_id: int, voted: set[int]) -> list[CovisibilityEdge]:
        """Edges to the previous query's matches and their +-``sequence_neighbours`` neighbours that are
        in the gallery, older than the excluded recent submaps and not voted already (score 0)."""
        n = self.config.sequence_neighbours
        if n < 0 or self._previous is None:
            return []
        newest = submap_id - self.config.index.exclude_recent
        near = sorted({m + k for m in self._previous[1] for k in range(-n, n + 1)})
        return [CovisibilityEdge(submap_id, m, 0.0, 0, "sequence") for m in near
                if m < newest and m in self._structure and m not in voted]

    def relocate(self, submap_id: int, points_world: np.ndarray) -> DemLayer:
        """Re-rasterise and re-index a submap whose pose the back-end changed."""
        if self.index is None or self.grid is None:
            raise RetrievalError("relocate before any submap was processed")
        d = self._describe(submap_id, points_world)
        self.index.remove_submap(submap_id)
        self._insert(submap_id, d)
        return d.layer

    def tiles_of(self, submap_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Live gallery tiles of a submap: keys [T,2] and descriptors [T,D]."""
        return self.index.tiles_of(submap_id) if self.index is not None else (np.zeros((0, 2)), np.zeros((0, 0)))

    def tile_centers_uv(self, keys: np.ndarray) -> np.ndarray:
        """Canonical (u, v) of tile centres [T,2] from their keys (Iu, Iv)."""
        return (np.asarray(keys, float) + 0.5) * self.grid.tile_size

    def _insert(self, submap_id: int, d: _Described) -> None:
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

    def _vlads_of(self, submap_id: int) -> np.ndarray:
        if submap_id not in self._tile_vlads:
            vfeats, usable, cpt = self._tile_cells[submap_id]
            v = tile_vlads(vfeats.astype(np.float32), self.vocab, cpt, self.config.vlad_context_tiles)
            tr, tc = usable.shape
            if len(self._tile_vlads) >= self.config.vlad_cache_submaps:
                self._tile_vlads.pop(next(iter(self._tile_vlads)))
            self._tile_vlads[submap_id] = v[:tr, :tc][usable]
        return self._tile_vlads[submap_id]


def _keys(layer: DemLayer, tr: int, tc: int) -> np.ndarray:
    iv, iu = np.mgrid[0:tr, 0:tc]
    return np.stack([iu + layer.origin_tile[0], iv + layer.origin_tile[1]], axis=-1)
