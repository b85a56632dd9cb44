"""DEM: ground plane, rasterisation on analytic surfaces, reducers, images, export, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from vggt_slam_pp.dem import (
    DemConfig,
    DemGrid,
    GroundPlane,
    encoder_image,
    export_dem,
    fit_ground_plane,
    rasterize,
)
from vggt_slam_pp.dem.images import fill_holes, hillshade_rgb
from vggt_slam_pp.dem.raster import reduce_heights
from vggt_slam_pp.errors import DemError
from vggt_slam_pp.geometry import so3_exp

FLAT = GroundPlane(np.zeros(3), np.eye(3))


def _surface(rng, fn, n=200_000, extent=8.0):
    uv = rng.uniform(0, extent, (n, 2))
    return np.c_[uv, fn(uv[:, 0], uv[:, 1])]


def _grid(plane=FLAT, tile=1.0, px=10):
    return DemGrid.create(plane, DemConfig(tile_size=tile, tile_px=px))


def _centres(layer):
    """Canonical (u, v) of every pixel centre of a layer."""
    H, W = layer.heights.shape
    v, u = np.mgrid[0:H, 0:W]
    return (u + layer.origin_px[0] + 0.5) * layer.mpp, (v + layer.origin_px[1] + 0.5) * layer.mpp


def test_plane_fit_recovers_a_tilted_plane_with_clutter(rng):
    R = so3_exp(np.array([0.3, -0.2, 0.5]))
    ground = _surface(rng, lambda u, v: 0.002 * rng.normal(size=u.shape), 20_000, 20.0)
    clutter = rng.uniform([0, 0, 0.5], [20, 20, 3.0], (6000, 3))  # boxes, walls above the ground
    pts = np.r_[ground, clutter] @ R.T + [1.0, 2.0, 3.0]
    cams = np.array([[10.0, 10.0, 1.5]]) @ R.T + [1.0, 2.0, 3.0]
    plane = fit_ground_plane(pts, cams)
    assert not plane.degraded and plane.inlier_ratio > 0.7
    assert np.isclose(abs(plane.normal @ R[:, 2]), 1.0, atol=1e-3) and plane.normal @ R[:, 2] > 0  # towards the camera
    canon = plane.to_canonical(ground @ R.T + [1.0, 2.0, 3.0])
    assert np.abs(canon[:, 2]).max() < 0.02
    assert np.allclose(plane.R @ plane.R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(plane.R), 1.0)
    assert np.allclose(plane.to_world(plane.to_canonical(pts[:10])), pts[:10])


def test_plane_bad_inputs(rng):
    with pytest.raises(DemError, match="too few points"):
        fit_ground_plane(rng.normal(size=(10, 3)))
    blob = rng.normal(size=(5000, 3))  # no dominant plane: degrade to the least-variance plane, logged
    plane = fit_ground_plane(blob)
    assert plane.degraded
    flat = np.c_[rng.uniform(0, 5, (500, 2)), np.full(500, 1.5)]  # all points at one height
    p = fit_ground_plane(flat)
    assert np.isclose(abs(p.normal[2]), 1.0) and np.allclose(p.to_canonical(flat)[:, 2], 0, atol=1e-9)


@pytest.mark.parametrize("reducer", ["softmax", "mean", "max"])
def test_analytic_surfaces(rng, reducer):
    g = _grid()
    cases = {
        "flat": (lambda u, v: np.full_like(u, 0.7), 1e-9),
        "tilted": (lambda u, v: 0.1 * u - 0.05 * v, 0.01),  # within-pixel slope spread: <= 0.015
        "step": (lambda u, v: np.where(u < 4.0, 0.0, 1.0), 1e-9),
        "box": (lambda u, v: np.where((abs(u - 4) < 1.5) & (abs(v - 4) < 1.5), 2.0, 0.0), 1e-9),
    }
    for name, (fn, tol) in cases.items():
        layer = rasterize(_surface(rng, fn), g, reducer=reducer)
        uc, vc = _centres(layer)
        valid = np.isfinite(layer.heights)
        assert valid.mean() > 0.9, name
        expected = fn(uc, vc)
        if name in ("step", "box"):  # pixels straddling an edge mix two heights
            edge = (abs(uc - 4.0) < g.mpp) if name == "step" else \
                (abs(abs(uc - 4) - 1.5) < g.mpp) | (abs(abs(vc - 4) - 1.5) < g.mpp)
            valid &= ~edge
        err = np.abs(layer.heights - expected)[valid]
        assert err.max() < tol + 1e-6, (name, reducer, err.max())


def test_reducers_against_hand_computed_pixels():
    flat = np.array([0, 0, 0, 2, 2, 5])
    h = np.array([1.0, 1.1, 3.0, -1.0, -1.02, 0.4])
    tau = 0.5
    for reducer, expect0 in (("mean", (1.0 + 1.1 + 3.0) / 3), ("max", 3.0)):
        out, counts = reduce_heights(flat, h, 6, reducer, tau)
        assert np.isclose(out[0], expect0) and list(counts) == [3, 0, 2, 0, 0, 1]
        assert np.isnan(out[1]) and np.isnan(out[3]) and np.isclose(out[5], 0.4)
    out, _ = reduce_heights(flat, h, 6, "softmax", tau)
    w = np.exp(np.array([1.0, 1.1, 3.0]) / tau)
    assert np.isclose(out[0], (w @ [1.0, 1.1, 3.0]) / w.sum())
    w2 = np.exp(np.array([-1.0, -1.02]) / tau)
    assert np.isclose(out[2], (w2 @ [-1.0, -1.02]) / w2.sum())
    # numerically stable: 100 m spread in one pixel with tau 0.02 gives the top height, not NaN
    out, _ = reduce_heights(np.zeros(3, int), np.array([0.0, 50.0, 100.0]), 1, "softmax", 0.02)
    assert out[0] == 100.0


def test_translating_a_layer_shifts_it_predictably(rng):
    g = _grid(tile=1.0, px=10)
    pts = _surface(rng, lambda u, v: np.sin(u) + 0.3 * v, 100_000)
    a = rasterize(pts, g)
    shift = np.array([3 * 1.0, 2 * 1.0, 0.25])  # whole tiles in u/v, and up
    b = rasterize(pts + shift, g)
    assert b.origin_px == (a.origin_px[0] + 30, a.origin_px[1] + 20)
    assert np.allclose(b.heights, a.heights + 0.25, atol=1e-5, equal_nan=True)
    assert {tuple(k) for k in b.tile_keys()} == {(k[0] + 3, k[1] + 2) for k in a.tile_keys()}


def test_empty_pixels_and_empty_layer(rng):
    g = _grid()
    pts = np.r_[_surface(rng, lambda u, v: 0 * u, 5000, 2.0), [[5.05, 5.05, 1.0]]]
    layer = rasterize(pts, g)
    assert np.isnan(layer.heights).sum() > 0.5 * layer.heights.size
    assert layer.counts[np.isnan(layer.heights)].max() == 0
    with pytest.raises(DemError, match="empty layer"):
        rasterize(np.full((4, 3), np.nan), g)
    with pytest.raises(DemError, match="unknown reducer"):
        rasterize(pts, g, reducer="median")
    with pytest.raises(DemError, match="auto"):
        DemGrid.create(FLAT, DemConfig(tile_size="auto"))
    auto = DemConfig(tile_size="auto")
    assert np.isclose(DemGrid.create(FLAT, auto, median_depth=8.0).tile_size, 8.0 * auto.auto_tile_fraction)


def test_images_and_export(tmp_path, rng):
    g = _grid()
    layer = rasterize(_surface(rng, lambda u, v: np.where(u < 4, 0.0, 1.0)), g)
    img = encoder_image(layer.heights)
    assert img.dtype == np.float32 and img.min() >= 0 and img.max() <= 1
    H, W = img.shape
    # the step edge is darkened relative to the flat high side
    col = int((4.0 / g.mpp) - layer.origin_px[0])
    assert img[H // 2, col] < img[H // 2, col + 5] - 0.3
    flat = encoder_image(np.full((8, 8), 2.0))
    assert np.allclose(flat, 0.5)
    holes = layer.heights.copy()
    holes[:3] = np.nan
    assert np.all(encoder_image(holes)[:3] == 1.0)  # empty -> white
    rgb = hillshade_rgb(holes, mpp=g.mpp)
    assert rgb.shape == (H, W, 3) and np.all(rgb[:3] == 255)
    paths = export_dem(tmp_path, layer.heights, g.mpp, g.plane, layer.origin_px)
    data = np.load(paths["array"])
    assert np.array_equal(data["heights"], layer.heights, equal_nan=True) and float(data["mpp"]) == g.mpp
    assert paths["color"].stat().st_size > 0 and paths["gray"].stat().st_size > 0


def test_fused_dem_is_the_top_of_all_layers(rng):
    from vggt_slam_pp.dem.raster import fuse_layers
    from vggt_slam_pp.geometry import make_sim3, transform_points

    g = _grid()
    pts = _surface(rng, lambda u, v: 0.5 + 0 * u, 20_000, 3.0)
    a = rasterize(pts, g, 0)
    b = rasterize(transform_points(make_sim3(1.0, np.eye(3), [2.0, 0.0, 0.5]), pts), g, 1)
    fused, origin = fuse_layers([(a.origin_px, a.heights), (b.origin_px, b.heights.astype(np.float16))])
    assert origin == (min(a.origin_px[0], b.origin_px[0]), min(a.origin_px[1], b.origin_px[1]))
    assert fused.dtype == np.float32 and np.nanmax(fused) == pytest.approx(1.0, abs=1e-3)
    u = b.origin_px[0] - origin[0]  # where both layers cover the ground, the higher one wins
    assert np.nanmin(fused[:, u + 2:u + 8]) == pytest.approx(1.0, abs=1e-3)
    assert np.nanmin(fused) == pytest.approx(0.5, abs=1e-3)
    with pytest.raises(DemError, match="no DEM layers"):
        fuse_layers([])


def test_fusing_layers_one_at_a_time_equals_fusing_them_at_once(rng):
    """fuse_layers takes a generator and grows its canvas as layers arrive, in any direction; the result
    is the per-pixel max over the union of the layers' boxes."""
    from vggt_slam_pp.dem.raster import fuse_layers

    layers = []
    for _ in range(30):
        h = rng.normal(size=(int(rng.integers(3, 12)), int(rng.integers(3, 12)))).astype(np.float32)
        h[rng.random(h.shape) < 0.3] = np.nan
        layers.append(((int(rng.integers(-60, 60)), int(rng.integers(-60, 60))), h))
    u0 = min(o[0] for o, _ in layers)
    v0 = min(o[1] for o, _ in layers)
    u1 = max(o[0] + h.shape[1] for o, h in layers)
    v1 = max(o[1] + h.shape[0] for o, h in layers)
    brute = np.full((v1 - v0, u1 - u0), np.nan, np.float32)
    for (u, v), h in layers:
        view = brute[v - v0:v - v0 + h.shape[0], u - u0:u - u0 + h.shape[1]]
        view[:] = np.fmax(view, h)
    fused, origin = fuse_layers(iter(layers))
    assert origin == (u0, v0) and fused.shape == brute.shape
    assert np.array_equal(fused, brute, equal_nan=True)


def test_fill_holes_fills_sampling_gaps_only():
    h = np.full((20, 20), np.nan, np.float32)
    h[::4, :10] = 1.0  # rows of samples every 4 px (sparse far ground)
    h[::4, 10:] = 3.0
    f = fill_holes(h, 2)
    assert np.array_equal(f[np.isfinite(h)], h[np.isfinite(h)])  # data untouched
    assert np.isfinite(f[:17]).all()  # gaps of 3 rows closed
    assert np.allclose(f[2, :8], 1.0) and np.allclose(f[2, 12:], 3.0)
    assert 1.0 < f[2, 10] < 3.0  # mean of the neighbourhood at the boundary
    big = np.full((30, 30), np.nan, np.float32)
    big[:5] = 0.0
    assert np.isnan(fill_holes(big, 3)[10:]).all()  # holes wider than the radius stay empty
    assert fill_holes(h, 0) is h
