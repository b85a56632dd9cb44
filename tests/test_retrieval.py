"""Encoders, structure-aware descriptors, the FAISS-HNSW tile index and VLAD."""

from __future__ import annotations

import numpy as np
import pytest

from vggt_slam_pp.errors import RetrievalError
from vggt_slam_pp.retrieval import HogEncoder, IndexConfig, TileIndex, aggregate, cell_weights, make_encoder
from vggt_slam_pp.vpr import Vocabulary, rank_candidates, tile_vlads, vlad


def _clustered(rng, n, dim=64, centres=200, spread=0.5, seed=0):
    c = np.random.default_rng(seed).normal(size=(centres, dim))  # the same cluster centres for any rng
    x = c[rng.integers(0, centres, n)] + spread * rng.normal(size=(n, dim))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_hog_encoder_shapes_and_orientation(rng):
    enc = make_encoder("hog")
    assert isinstance(enc, HogEncoder) and enc.dim == 36 and enc.patch_px == 14
    stripes = np.tile((np.arange(56) // 4 % 2).astype(np.float32), (42, 1))  # vertical stripes: x gradients
    f = enc.encode(stripes)
    assert f.shape == (3, 4, 36)
    assert np.allclose(np.linalg.norm(f, axis=2), 1.0, atol=1e-5)
    assert np.all(f.reshape(-1, 4, 9).argmax(axis=2) == 0)  # orientation bin 0 (horizontal gradient)
    assert enc.encode(np.zeros((30, 30))).shape == (3, 3, 36)  # padded to a multiple of 14
    with pytest.raises(RetrievalError, match="unknown encoder"):
        make_encoder("sift")


def test_descriptor_aggregation_matches_brute_force(rng):
    rows, cols, D, c = 12, 10, 4, 2
    f = rng.normal(size=(rows, cols, D)).astype(np.float32)
    m = rng.uniform(0, 1, (rows, cols)).astype(np.float32)
    for window in (9, None):
        desc, support = aggregate(f, m, c, window)
        for ti, tj in ((0, 0), (3, 2), (5, 4)):
            cy, cx = c * ti + c / 2, c * tj + c / 2
            num, den = np.zeros(D), 0.0
            for y in range(rows):
                for x in range(cols):
                    dy, dx = y - c * ti, x - c * tj
                    if window is not None and not (-8 <= dy <= 9 and -8 <= dx <= 9):
                        continue
                    w = np.exp(-((y + 0.5 - cy) ** 2 + (x + 0.5 - cx) ** 2) / (2 * 4.0**2))
                    num += w * m[y, x] * f[y, x]
                    den += w * m[y, x]
            assert np.allclose(desc[ti, tj], num / np.linalg.norm(num), atol=1e-5)
            assert np.isclose(support[ti, tj], den, rtol=1e-5)


def test_gradient_weights_ignore_flat_and_empty_cells():
    h = np.zeros((56, 56))
    h[:, 28:] = 1.0  # a step in the middle
    h[:14] = np.nan  # an empty band
    m = cell_weights(h, 14)
    assert m.shape == (4, 4) and np.all(m[0] == 0)  # empty cells weigh nothing
    assert m[2, 1] > 0.5 and m[2, 2] > 0.5 and m[2, 0] < 0.01  # edge cells dominate flat ones


def test_hnsw_recall_against_exact_search(rng):
    import faiss

    x = _clustered(rng, 20_000)
    q = _clustered(np.random.default_rng(7), 200)
    index = TileIndex(64, IndexConfig())
    keys = np.c_[np.arange(len(x)) % 100, np.arange(len(x)) // 100]
    for s in range(10):  # incremental insertion, one "submap" at a time
        sel = slice(s * 2000, (s + 1) * 2000)
        index.add(s, keys[sel], x[sel])
    assert len(index) == 20_000
    exact = faiss.IndexFlatIP(64)
    exact.add(x)
    _, truth = exact.search(q, 10)
    _, found = index.search(q, 10)
    recall = np.mean([len(set(a) & set(b)) / 10 for a, b in zip(truth, found, strict=True)])
    assert recall >= 0.95


def test_index_save_load_identical_and_config_mismatch(tmp_path, rng):
    x = _clustered(rng, 3000)
    index = TileIndex(64, encoder="hog")
    index.add(0, np.zeros((3000, 2), int), x)
    q = x[:50] + 0.01
    before = index.search(q)
    index.save(tmp_path / "idx")
    loaded = TileIndex.load(tmp_path / "idx", dim=64, encoder="hog")
    after = loaded.search(q)
    assert np.array_equal(before[1], after[1]) and np.allclose(before[0], after[0])
    assert np.array_equal(loaded.keys, index.keys)
    with pytest.raises(RetrievalError, match="768-D"):
        TileIndex.load(tmp_path / "idx", dim=768)
    with pytest.raises(RetrievalError, match="encoder"):
        TileIndex.load(tmp_path / "idx", encoder="dinov2")
    with pytest.raises(RetrievalError, match="cannot read"):
        TileIndex.load(tmp_path / "nothing")
    with pytest.raises(RetrievalError, match=r"\[N,64\]"):
        index.add(1, np.zeros((2, 2)), np.zeros((2, 8)))


def test_voting_excludes_recent_neighbours(rng):
    dim = 32
    centres = rng.normal(size=(6, dim)).astype(np.float32)
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    index = TileIndex(dim, IndexConfig(k=5, exclude_recent=2, top_k=3))
    for s in range(6):  # submap s's tiles all look like centre s
        t = centres[s] + 0.01 * rng.normal(size=(20, dim)).astype(np.float32)
        index.add(s, np.zeros((20, 2), int), t / np.linalg.norm(t, axis=1, keepdims=True))
    chips = np.r_[np.repeat(centres[1:2], 8, 0), np.repeat(centres[5:6], 8, 0)]  # revisits 1, and looks like 5
    edges = index.vote(6, chips)
    assert [e.match for e in edges] == [1]  # 5 (and 4, 6) are recent neighbours of query 6
    assert edges[0].votes == 8 and 0.45 < edges[0].score <= 0.5  # one vote per chip: ~cos 1 x 8 / 16 chips
    assert index.vote(6, np.zeros((0, dim), np.float32)) == []
    every_tile = TileIndex(dim, IndexConfig(k=5, exclude_recent=2, top_k=3, one_vote_per_submap=False))
    every_tile.index, every_tile.keys, every_tile.alive = index.index, index.keys, index.alive
    assert every_tile.vote(6, chips)[0].votes == 40  # all 5 nearest tiles of each chip lie in submap 1


def test_one_vote_per_submap_stops_a_hub_layer(rng):
    """A layer with many near-identical tiles takes every neighbour of a chip; counted once per chip, it
    no longer outscores the submap that matches every chip."""
    dim = 32
    a, b = rng.normal(size=(2, dim)).astype(np.float32)
    hub = a + 0.6 * b
    hub /= np.linalg.norm(hub)
    index = TileIndex(dim, IndexConfig(k=10, exclude_recent=0))
    index.add(0, np.zeros((1, 2), int), (a / np.linalg.norm(a))[None])  # the true place: one tile
    noisy = hub + 0.01 * rng.normal(size=(30, dim)).astype(np.float32)
    index.add(1, np.zeros((30, 2), int), noisy / np.linalg.norm(noisy, axis=1, keepdims=True))
    chips = np.repeat((a / np.linalg.norm(a))[None], 4, 0)
    assert index.vote(5, chips)[0].match == 0
    index.config = IndexConfig(k=10, exclude_recent=0, one_vote_per_submap=False)
    assert index.vote(5, chips)[0].match == 1  # the old rule: 9 hub tiles x cos 0.86 beat one exact tile


def test_relocations_compact_the_index(rng):
    """Re-inserting re-rasterised layers retires old tiles; once they outnumber the live ones the graph
    is rebuilt: the index size follows the map and searches see exactly the live tiles."""
    dim = 16
    index = TileIndex(dim, IndexConfig(compact_min_dead=50))
    tiles = {}
    for s in range(5):
        tiles[s] = _clustered(rng, 40, dim, seed=s)
        index.add(s, np.c_[np.arange(40), np.full(40, s)], tiles[s])
    for rnd in range(6):  # every layer relocated six times: new descriptors, same keys
        for s in range(5):
            tiles[s] = _clustered(np.random.default_rng(100 * rnd + s), 40, dim, seed=s)
            index.remove_submap(s)
            index.add(s, np.c_[np.arange(40), np.full(40, s)], tiles[s])
    assert index.compactions >= 2
    assert len(index) <= 2 * 200 + 50  # never more than live + max(live, min dead) + one layer
    keys, desc = index.tiles_of(3)
    assert np.array_equal(keys, np.c_[np.arange(40), np.full(40, 3)])
    assert np.allclose(desc, tiles[3], atol=1e-6)
    sims, ids = index.search(tiles[2][:5], 1)  # a live tile finds itself
    assert np.allclose(sims[:, 0], 1.0, atol=1e-5)
    assert np.array_equal(index.keys[ids[:, 0]], np.c_[np.full(5, 2), np.arange(5), np.full(5, 2)])
    edges = index.vote(9, tiles[1])
    assert edges[0].match == 1 and edges[0].votes > 0

def test_vlad_on_hand_made_descriptors():
    vocab = Vocabulary(np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]), trained_on=3)
    feats = np.array([[1.2, 0.1], [0.9, -0.1], [0.1, 1.5]])  # two in cluster 0, one in cluster 1
    assert list(vocab.assign(feats)) == [0, 0, 1]
    v = vlad(feats, vocab).reshape(3, 2)
    r0 = np.array([0.2 - 0.1, 0.1 - 0.1])  # residual sum of cluster 0 = (0.1, 0.0)
    r1 = np.array([0.1, 0.5])
    expected = np.r_[r0 / np.linalg.norm(r0), r1 / np.linalg.norm(r1), [0, 0]] / np.sqrt(2)
    assert np.allclose(v.reshape(-1), expected, atol=1e-6)
    assert np.isclose(np.linalg.norm(v), 1.0)
    assert not np.any(vlad(np.zeros((0, 2)), vocab))


def test_vocabulary_tile_vlads_and_candidates(rng):
    feats = np.r_[rng.normal([0, 0, 3], 0.2, (300, 3)), rng.normal([3, 0, 0], 0.2, (300, 3)),
                  rng.normal([0, 3, 0], 0.2, (300, 3))]
    vocab = Vocabulary.train(feats, k=3, seed=0)
    assert vocab.k == 3 and not vocab.needs_refresh(900) and vocab.needs_refresh(1800)
    with pytest.raises(RetrievalError, match="at least 32"):
        Vocabulary.train(feats[:10], k=32)
    cells_a = rng.normal([0, 0, 3], 0.2, (8, 8, 3)).astype(np.float32)
    cells_b = rng.normal([3, 0, 0], 0.2, (8, 8, 3)).astype(np.float32)
    va, vb = tile_vlads(cells_a, vocab), tile_vlads(cells_b, vocab)
    assert va.shape == (4, 4, 9)
    cands = rank_candidates(9, va.reshape(-1, 9)[:5], {1: va.reshape(-1, 9), 2: vb.reshape(-1, 9)})
    assert cands[0].match == 1 and cands[0].votes == 5


def test_tile_vlads_equal_each_tiles_own_vlad(rng):
    """tile_vlads computes every tile's window at once (block sums, integral image): the same as vlad() of each
    window's cells, including the cells beyond the last whole tile and windows clipped at the border."""
    vocab = Vocabulary(rng.normal(size=(6, 4)), 1)
    for (rows, cols), c, context in (((9, 7), 2, 3), ((17, 9), 4, 5), ((8, 8), 2, 1)):
        cells = rng.normal(size=(rows, cols, 4)).astype(np.float32)
        cells[0] = 0.0  # empty cells
        cells[:, 1] = vocab.centroids[2]  # cells on a word: no residual
        r = (context // 2) * c
        out = tile_vlads(cells, vocab, c, context)
        assert out.shape == (rows // c, cols // c, 24)
        for i in range(rows // c):
            for j in range(cols // c):
                window = cells[max(0, i * c - r):min(rows, i * c + c + r), max(0, j * c - r):min(cols, j * c + c + r)]
                assert np.allclose(out[i, j], vlad(window.reshape(-1, 4), vocab), atol=1e-5), (rows, c, i, j)


def test_dinov2_encoder_with_a_tiny_model(rng):
    from vggt_slam_pp.models import build_dinov2
    from vggt_slam_pp.retrieval import DinoV2Encoder

    model = build_dinov2({"embed_dim": 48, "depth": 3, "num_heads": 3})
    enc = DinoV2Encoder(model=model)
    img = rng.random((56, 70)).astype(np.float32)
    f = enc.encode(img)
    v = enc.vlad_features(img)
    assert f.shape == (4, 5, 48) and v.shape == (4, 5, 48) and enc.value_layer == 1
    assert np.isfinite(f).all() and not np.allclose(f, v)


def test_benchmarks_run_small():
    from vggt_slam_pp.benchmarks import bench_dem, bench_retrieval

    d = bench_dem(n_points=100_000, repeats=1)
    assert d["points_per_s"] > 0 and d["ratio_to_count_baseline"] > 0 and d["layer_shape"][0] > 0
    r = bench_retrieval(n_large=3000, n_small=1000, dim=32, queries=50)
    assert 0.9 <= r["recall_at_10"] <= 1.0 and r["latency_ratio_100k_10k"] > 0


def _walls(rng, n_walls=6, extent=30.0):
    """A random asymmetric structure layout: wall segments as dense (u, v) samples [N,2] (metres)."""
    pts = []
    for _ in range(n_walls):
        a, ang, length = rng.uniform(0, extent, 2), rng.uniform(0, np.pi), rng.uniform(3, 10)
        t = np.linspace(0, length, int(length / 0.1))
        pts.append(a + t[:, None] * np.array([np.cos(ang), np.sin(ang)]))
    return np.concatenate(pts)


def _structure_of(uv, cell=0.5):
    from vggt_slam_pp.vpr import Structure

    keys, counts = np.unique(np.floor(uv / cell).astype(int), axis=0, return_counts=True)
    return Structure(((keys + 0.5) * cell).astype(np.float32), counts.astype(np.float32))


def test_layer_structure_finds_the_box_not_the_ground():
    from vggt_slam_pp.dem import DemLayer
    from vggt_slam_pp.vpr import layer_structure

    h = np.random.default_rng(0).normal(0, 0.02, (280, 280)).astype(np.float32)  # 20 m x 20 m, ground noise
    h[:20] = np.nan  # an empty strip
    h[140:168, 56:84] = 3.0  # a 2 m x 2 m box, 3 m high
    layer = DemLayer(0, h, np.ones(h.shape, np.int32), (28, 56), 2.0 / 28, 28)
    s = layer_structure(layer, 2.0)
    assert len(s) == 16  # 2 m x 2 m at 0.5 m cells
    origin = np.array([28, 56]) * 2.0 / 28
    assert np.allclose(s.uv.min(0), origin + [4.25, 10.25]) and np.allclose(s.uv.max(0), origin + [5.75, 11.75])
    flat = DemLayer(1, np.zeros((56, 56), np.float32), np.ones((56, 56), np.int32), (0, 0), 2.0 / 28, 28)
    assert len(layer_structure(flat, 2.0)) == 0


def test_structure_match_recovers_yaw_and_shift_and_reranks(rng):
    from vggt_slam_pp.vpr import LoopCandidate, match_structure, rerank_candidates

    place = _walls(rng)
    yaw = np.radians(8.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    c = place.mean(0)
    seen_again = (place - c) @ R.T + c + np.array([2.5, -1.5])  # the revisit, drifted by 8 deg and 2.9 m
    q, m = _structure_of(seen_again), _structure_of(place)
    g = match_structure(q, m, 2.0)
    assert g.score > 0.8 and abs(g.yaw_deg + 8.0) <= 2.0
    a = np.radians(g.yaw_deg)
    Rg = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    centre = np.average(q.uv, axis=0, weights=q.weight)
    back = (seen_again - centre) @ Rg.T + centre + g.shift
    assert np.median(np.linalg.norm(back - place, axis=1)) < 0.7  # within ~a correlation cell
    elsewhere = _structure_of(_walls(np.random.default_rng(99)))
    assert match_structure(q, elsewhere, 2.0).score < g.score - 0.2
    # VLAD liked the look-alike better; the layout check puts the true place first
    ranked = rerank_candidates(7, q, {1: m, 2: elsewhere}, [LoopCandidate(7, 2, 0.9, 30), LoopCandidate(7, 1, 0.5, 10)],
                               2.0)
    assert [r.match for r in ranked] == [1, 2] and ranked[0].score == 0.5 and ranked[0].geometry == g.score
    assert match_structure(_structure_of(place[:5]), m, 2.0).score == 0.0  # too little structure


def test_structure_peaks_lists_distinct_alternatives_on_a_repetitive_street(rng):
    from vggt_slam_pp.vpr import match_structure, structure_peaks

    # four identical L-shaped buildings every 8 m: the query saw two of them
    t = np.linspace(0, 4, 40)
    ell = np.concatenate([np.c_[t, np.zeros_like(t)], np.c_[np.zeros_like(t[:25]), t[:25] * 0.6]])
    street = np.concatenate([ell + [8.0 * k, 0.0] for k in range(4)])
    seen = np.concatenate([ell + [8.0 * k, 0.0] for k in (1, 2)]) + [1.0, 0.0]  # drifted 1 m along the street
    q, m = _structure_of(seen), _structure_of(street)
    peaks = structure_peaks(q, m, 2.0, count=3)
    assert len(peaks) == 3 and [p.score for p in peaks] == sorted((p.score for p in peaks), reverse=True)
    best = match_structure(q, m, 2.0)
    assert (peaks[0].score, peaks[0].yaw_deg) == (best.score, best.yaw_deg) and np.allclose(peaks[0].shift, best.shift)
    shifts = np.array([p.shift for p in peaks])
    gaps = np.linalg.norm(shifts[:, None] - shifts[None], axis=2)[np.triu_indices(3, 1)]
    assert gaps.min() >= 2.0  # alternatives, not neighbours of the best (1 tile apart at least)
    # the true correction (-1 m) and a look-alike one building (8 m) away are both among them
    assert np.min(np.linalg.norm(shifts - [-1.0, 0.0], axis=1)) <= 0.5
    assert np.min(np.linalg.norm(shifts - [7.0, 0.0], axis=1)) <= 0.5 or np.min(
        np.linalg.norm(shifts - [-9.0, 0.0], axis=1)) <= 0.5
    few = structure_peaks(_structure_of(street[:5]), m, 2.0)  # too little structure: one empty match
    assert len(few) == 1 and few[0].score == 0.0


def _region(rng, x0: float, n_boxes: int = 6) -> np.ndarray:
    """World points [N,3] of a 16 m x 16 m patch of ground starting at x = ``x0``, with random boxes."""
    g = rng.uniform([x0, 0.0], [x0 + 16.0, 16.0], (6000, 2))
    z = np.zeros(len(g))
    for _ in range(n_boxes):
        lo = rng.uniform([x0, 0.0], [x0 + 13.0, 13.0])
        size, h = rng.uniform(1.0, 3.0, 2), rng.uniform(0.8, 3.0)
        inside = np.all((g >= lo) & (g <= lo + size), axis=1)
        z[inside] = h
    return np.c_[g, z]


def test_sequence_prior_adds_the_previous_match_and_its_neighbours(rng):
    from vggt_slam_pp.backend.places import CovisibilityConfig, CovisibilityStage

    regions = [_region(rng, 16.0 * k) for k in range(8)]
    cams = lambda p: p.mean(0, keepdims=True) + [0.0, 0.0, 5.0]  # noqa: E731
    cfg = lambda n: CovisibilityConfig(index=IndexConfig(top_k=2), sequence_neighbours=n)  # noqa: E731
    stages = {n: CovisibilityStage.create(HogEncoder(), cfg(n)) for n in (1, -1)}  # 2 voted edges at most
    for stage in stages.values():
        for k, pts in enumerate(regions[:7]):
            stage.process(k, pts, cams(pts))
    stage = stages[1]
    stage.confirm(6, [2])  # the back-end verified 6 -> 2
    out = stage.process(7, regions[7], cams(regions[7]))
    by_match = {e.match: e for e in out.edges}
    assert {1, 2, 3} <= set(by_match) and len(out.edges) <= 2 + 3
    prior = [e for e in out.edges if e.source == "sequence"]
    assert prior and all(e.match in (1, 2, 3) and e.score == 0.0 and e.votes == 0 for e in prior)
    assert all(e.source == "votes" for e in out.edges[: len(out.edges) - len(prior)])  # votes first
    off = stages[-1].process(7, regions[7], cams(regions[7]))
    assert all(e.source == "votes" for e in off.edges)
    assert {e.match for e in off.edges} == {e.match for e in out.edges if e.source == "votes"}
    # anchored at 5, its neighbour 6 is one of query 8's excluded recent submaps and stays out
    stage.confirm(7, [5])
    stage.confirm(6, [0])  # query 6's matches anchor query 7's prior, not query 8's
    nxt = stage.process(8, regions[0], cams(regions[0]))
    assert {e.match for e in nxt.edges if e.source == "sequence"} <= {4, 5} <= {e.match for e in nxt.edges}
    assert all(e.match < 8 - stage.config.index.exclude_recent for e in nxt.edges)


def test_loop_candidates_are_ranked_from_a_pool_wider_than_the_covisibility_edges(rng):
    """Under drift a revisit's true match is often voted below the top K (the covisibility edges): places that
    look alike elsewhere out-vote it. The loop candidates are ranked from the ``candidate_pool`` best-voted
    submaps, so the structure re-ranking still finds it where it lies; the covisibility edges stay the top K."""
    from vggt_slam_pp.backend.places import CovisibilityConfig, CovisibilityStage

    place = _region(rng, 0.0)
    cams = lambda p: p.mean(0, keepdims=True) + [0.0, 0.0, 5.0]  # noqa: E731
    # the true match saw part of the place; exact copies of it lie far away
    layers = [place[place[:, 0] < 9.0]] + [place + [48.0 * k, 0.0, 0.0] for k in (2, 3, 4, 5)]

    def query(pool: int):
        stage = CovisibilityStage.create(HogEncoder(), CovisibilityConfig(index=IndexConfig(top_k=2),
                                                                          candidate_pool=pool))
        for k, pts in enumerate(layers):
            stage.process(k, pts, cams(pts))
        return stage.process(len(layers) + 2, place, cams(place))

    narrow, wide = query(2), query(6)
    assert 0 not in {e.match for e in narrow.edges} | {c.match for c in narrow.candidates}  # out-voted
    assert wide.candidates[0].match == 0
    assert [(e.match, e.source) for e in wide.edges] == [(e.match, e.source) for e in narrow.edges]


def test_sequence_prior_follows_the_submaps_not_the_order_of_the_queries(rng):
    """A worker catching up defers the oldest queries and runs them later: a deferred query still follows
    its predecessor's matches, and a live query whose predecessor was deferred follows nothing."""
    from vggt_slam_pp.backend.places import CovisibilityConfig, CovisibilityStage

    regions = [_region(rng, 16.0 * k) for k in range(7)]
    cams = lambda p: p.mean(0, keepdims=True) + [0.0, 0.0, 5.0]  # noqa: E731
    stage = CovisibilityStage.create(HogEncoder(), CovisibilityConfig(index=IndexConfig(top_k=2)))
    for k in range(5):
        stage.process(k, regions[k], cams(regions[k]))
    stage.confirm(4, [1])  # the back-end verified 4 -> 1
    live = stage.process(6, regions[6], cams(regions[6]))  # 5's query was deferred
    assert not [e for e in live.edges if e.source == "sequence"]
    late = stage.process(5, regions[5], cams(regions[5]), insert=False)  # 5's deferred query, after 6's
    prior = {e.match for e in late.edges if e.source == "sequence"}
    assert prior and prior <= {0, 1, 2} <= {e.match for e in late.edges}
