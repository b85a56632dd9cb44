"""Per-submap retrieval stage: DEM layer -> encoder -> tile/chip descriptors -> HNSW voting -> VLAD.

:class:`CovisibilityStage` is what the back-end calls for every new submap (SPEC 3.6-3.9):

1. rasterise the submap's points (world frame) into its DEM layer (the ground plane and grid are
   fixed by the first submap);
2. encode the layer's encoder image once (dense patch features) and compute the gradient weights;
3. chips (window = whole layer) vote in the HNSW gallery -> covisibility edges;
4. VLAD of the chips against the tiles of the covisible submaps -> ranked loop candidates;
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
from vggt_slam_pp.retrieval.descriptors import aggregate, cell_weights
from vggt_slam_pp.retrieval.encoders import Encoder
from vggt_slam_pp.retrieval.index import CovisibilityEdge, IndexConfig, TileIndex
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


@dataclass
class StageResult:
    submap_id: int
    layer: DemLayer
    edges: list[CovisibilityEdge]
    candidates: list[LoopCandidate]
    timings: dict[str, float]


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

    def _ensure_grid(self, points_world: np.ndarray, camera_centers: np.ndarray | None,
                     median_depth: float | None) -> None:
        if self.grid is None:
            plane = fit_ground_plane(points_world, camera_centers)
            self.grid = DemGrid.create(plane, self.config.dem, median_depth)
            cells_per_tile = self.grid.tile_px / self.encoder.patch_px
            if cells_per_tile != int(cells_per_tile):
                log.warning("tile_px %d is not a multiple of the encoder patch %d", self.grid.tile_px,
                            self.encoder.patch_px)

    def process(self, submap_id: int, points_world: np.ndarray, camera_centers: np.ndarray | None = None,
                median_depth: float | None = None) -> StageResult:
        c = self.config
        t = {}
        t0 = time.perf_counter()
        self._ensure_grid(points_world, camera_centers, median_depth)
        layer = rasterize(points_world, self.grid, submap_id, c.dem.reducer, c.dem.tau)
        t["raster_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
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
        t["encode_s"] = time.perf_counter() - t0
        if self.index is None:
            self.index = TileIndex(tiles.shape[2], c.index, self.encoder.name)
        t0 = time.perf_counter()
        chip_ok = usable & (np.linalg.norm(chips, axis=2) > 0)
        edges = self.index.vote(submap_id, chips[chip_ok])
        t["vote_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        candidates: list[LoopCandidate] = []
        if self.vocab is None and sum(len(x) for x in self._vlad_cells) >= c.vlad_clusters * 4:
            self.vocab = Vocabulary.train(np.concatenate(self._vlad_cells), c.vlad_clusters)
            self._tile_vlads = {}
        if self.vocab is not None and edges:
            q = tile_vlads(vfeats, self.vocab, cpt, c.vlad_context_tiles)[:tr, :tc][chip_ok]
            gallery = {e.match: self._vlads_of(e.match) for e in edges}
            gallery = {k: v for k, v in gallery.items() if len(v)}
            candidates = rank_candidates(submap_id, q, gallery, c.vlad_min_score)
        t["vlad_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.index.add(submap_id, _keys(layer, tr, tc)[usable], tiles[usable])
        self._tile_cells[submap_id] = (vfeats, usable, cpt)
        self._vlad_cells.append(vfeats[m > 0].reshape(-1, vfeats.shape[2]))
        if self.vocab is not None and self.vocab.needs_refresh(sum(len(x) for x in self._vlad_cells)):
            self.vocab = Vocabulary.train(np.concatenate(self._vlad_cells), c.vlad_clusters)
            self._tile_vlads = {}
        t["index_s"] = time.perf_counter() - t0
        return StageResult(submap_id, layer, edges, candidates, t)

    def _vlads_of(self, submap_id: int) -> np.ndarray:
        if submap_id not in self._tile_vlads:
            vfeats, usable, cpt = self._tile_cells[submap_id]
            v = tile_vlads(vfeats, self.vocab, cpt, self.config.vlad_context_tiles)
            tr, tc = usable.shape
            self._tile_vlads[submap_id] = v[:tr, :tc][usable]
        return self._tile_vlads[submap_id]


def _keys(layer: DemLayer, tr: int, tc: int) -> np.ndarray:
    iv, iu = np.mgrid[0:tr, 0:tc]
    return np.stack([iu + layer.origin_tile[0], iv + layer.origin_tile[1]], axis=-1)
