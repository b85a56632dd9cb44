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
    assert edges[0].score > 0.4 and edges[0].votes == 40
    assert index.vote(6, np.zeros((0, dim), np.float32)) == []


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
