"""The ``vggt`` backbone path end to end without weights: an oracle VGGT (issue 22).

The oracle (:mod:`vggt_slam_pp.synthetic.oracle`) answers VGGT's forward contract from the synthetic
ground truth, re-deriving the preprocessing geometry from the contract alone. With it in place of the
network, the whole front-end must reproduce the ground truth; deliberately introduced convention errors
in *our* path (decoding, pixel mapping, depth reading, preprocessing) must be caught, either by the
odometry ATE or by a pixel-consistency check of the predictions against the ground truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from vggt_slam_pp.errors import ModelError
from vggt_slam_pp.frontend.backbones.oracle import oracle_backbone
from vggt_slam_pp.frontend.frontend import FrontendConfig
from vggt_slam_pp.frontend.keyframes import KeyframeConfig
from vggt_slam_pp.io.frames import FrameSource
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run
from vggt_slam_pp.synthetic.oracle import OracleNoise, OracleVggt, consistency, placements

CONFIG = RunConfig(backbone=BackboneConfig(name="vggt"),
                   frontend=FrontendConfig(keyframes=KeyframeConfig(tau_disparity=12.0), submap_size=4),
                   backend=False, save_predictions=False)
SIZES = {"landscape": (160, 120), "portrait": (121, 163)}  # (width, height); the portrait one is odd-sized


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    out = {}
    for name, (w, h) in SIZES.items():
        folder = tmp_path_factory.mktemp(name)
        write_sequence(make_scene("loop", frames=90, width=w, height=h, seed=3), folder)
        out[name] = open_source(folder)
    return out


@pytest.fixture(scope="module")
def clean_runs():
    return {}  # (shape, mode) -> (report, consistency of every submap), filled by the zero-noise test


class _Prefix(FrameSource):
    """The first ``n`` frames of a source (short runs for the corrupted paths)."""

    layout = "prefix"

    def __init__(self, source: FrameSource, n: int) -> None:
        super().__init__(source.root)
        self.source, self.n = source, n

    def __len__(self) -> int:
        return self.n

    @property
    def timestamps(self) -> np.ndarray:
        return self.source.timestamps[:self.n]

    def _load(self, i: int):
        return self.source[i]

    def _native_ground_truth(self):
        return self.source.ground_truth()


def _run(source, out, **kw):
    bb = oracle_backbone(source, record=True, **kw)
    report = run(source, CONFIG, out, backbone=bb)
    return report, [consistency(p, v) for p, v in zip(bb.predictions, bb.views, strict=True)]


def _worst(checks) -> dict:
    return {k: max(getattr(c, k) for c in checks) for k in
            ("rotation_deg", "translation_rel", "focal_rel", "principal_px", "reprojection_px", "depth_rel")}


def _half_pixel(source, mode) -> float:
    """The principal-point offset any VGGT has (the encoding has no principal point; decoding puts it at
    W/2, H/2 on the integer pixel grid): half a network pixel, in original pixels."""
    f = source[0]
    p = placements([f.depth.shape], mode)[0]
    return float(np.hypot(0.5 / p.scale_x, 0.5 / p.scale_y))


# ------------------------------------------------------------------------------------ the oracle itself
def test_oracle_follows_the_contract_shapes_and_encoding(sequences):
    src = sequences["portrait"]
    bb = oracle_backbone(src, mode="crop")
    frames = [src[i] for i in (0, 2, 4)]
    from vggt_slam_pp.models.preprocess import preprocess_images

    images, _ = preprocess_images([f.image for f in frames], "crop")
    oracle = OracleVggt("crop").eval()
    oracle.frames = bb.views_for(frames)
    out = oracle(images)
    S, (H, W) = 3, images.shape[-2:]
    assert (H, W) == (518, 518)  # 121x163 -> 518x700, central 518 rows
    assert out["pose_enc"].shape == (1, S, 9) and len(out["pose_enc_list"]) == 4
    assert out["depth"].shape == (1, S, H, W, 1) and out["depth_conf"].shape == (1, S, H, W)
    assert out["world_points"].shape == (1, S, H, W, 3) and out["images"].shape == (1, S, 3, H, W)
    assert all(v.dtype == torch.float32 for k, v in out.items() if k not in ("pose_enc_list", "images"))
    assert (out["depth"] > 0).all() and (out["depth_conf"] > 1).all()
    enc = out["pose_enc"][0].double()
    assert torch.allclose(enc[0, :7], torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64), atol=1e-7)
    assert (enc[:, 6] >= 0).all()  # w >= 0
    # world points of frame 0 are its own depth along its rays; sky pixels get the lowest confidence
    assert torch.allclose(out["world_points"][0, 0, ..., 2], out["depth"][0, 0, ..., 0], rtol=1e-6)
    sky = frames[0].depth == 0
    assert sky.any() and out["depth_conf"].min() < 1.001
    with pytest.raises(ModelError, match="told"):
        oracle(images)  # the frames are consumed by each call


def test_mixed_sizes_geometry_agrees_with_preprocessing(sequences):
    """Two independent derivations of the preprocessing geometry (the oracle's, from the contract, and
    ``preprocess_images``') agree, pad-to-largest included; the oracle accepts the images it gets."""
    from vggt_slam_pp.models.preprocess import preprocess_images

    frames = [sequences["landscape"][0], sequences["portrait"][0]]
    views = [oracle_backbone(sequences[k]).views_for([f])[0] for k, f in zip(SIZES, frames, strict=True)]
    for mode in ("crop", "pad"):
        images, infos = preprocess_images([f.image for f in frames], mode)
        places = placements([f.depth.shape for f in frames], mode)
        for info, p in zip(infos, places, strict=True):
            assert info.network_hw == p.network_hw == tuple(images.shape[-2:])
            assert np.allclose([info.scale_x, info.scale_y, info.offset_x, info.offset_y],
                               [p.scale_x, p.scale_y, p.offset_x, p.offset_y], rtol=0, atol=1e-12)
        oracle = OracleVggt(mode)
        oracle.frames = views
        oracle(images)  # the image check passes for both frames
        assert max(oracle.calls[-1]["image_error"]) < 0.01


# ------------------------------------------------------------------------------ zero noise: exact path
@pytest.mark.parametrize("shape", ["landscape", "portrait"])
@pytest.mark.parametrize("mode", ["crop", "pad"])
def test_zero_noise_oracle_reproduces_ground_truth(tmp_path, sequences, clean_runs, shape, mode):
    src = sequences[shape]
    report, checks = _run(src, tmp_path / "run", mode=mode)
    clean_runs[(shape, mode)] = report, checks
    assert report["error"] is None and report["degraded_edges"] == 0
    assert report["submaps"] >= 10 and len(report["edges"]) == report["submaps"] - 1
    assert report["ate_rmse_odometry"] <= 1e-4 * report["gt_path_length"]
    w = _worst(checks)
    half = _half_pixel(src, mode)
    assert w["rotation_deg"] < 1e-4 and w["translation_rel"] < 1e-5
    assert w["focal_rel"] < 1e-5
    assert w["principal_px"] <= half + 1e-4  # the contract's half network pixel, nothing more
    assert w["reprojection_px"] <= half + 1e-3
    assert w["depth_rel"] < 1e-5


# ------------------------------------------------------------------- convention errors must be caught
def _transposed(ext, K):
    R = ext[..., :3, :3].transpose(-1, -2)
    return torch.cat([R, ext[..., 3:]], dim=-1), K


def _world_from_camera(ext, K):
    R = ext[..., :3, :3].transpose(-1, -2)
    return torch.cat([R, -R @ ext[..., 3:]], dim=-1), K


@pytest.mark.parametrize("error", [_transposed, _world_from_camera], ids=["transposed", "world_from_camera"])
def test_extrinsic_convention_errors_break_the_odometry(tmp_path, sequences, monkeypatch, error):
    import vggt_slam_pp.models.cameras as cameras

    src = _Prefix(sequences["landscape"], 30)
    clean, _ = _run(src, tmp_path / "clean", mode="crop")
    assert clean["ate_rmse_odometry"] <= 1e-4 * clean["gt_path_length"]
    decode = cameras.pose_encoding_to_extri_intri
    monkeypatch.setattr(cameras, "pose_encoding_to_extri_intri", lambda enc, hw: error(*decode(enc, hw)))
    bad, checks = _run(src, tmp_path / "bad", mode="crop")
    assert bad["ate_rmse_odometry"] > 1e-4 * bad["gt_path_length"]
    assert bad["ate_rmse_odometry"] > 100 * clean["ate_rmse_odometry"]
    assert _worst(checks)["rotation_deg"] > 1.0


def _predict_checks(source, mode="crop", frames=(0, 3, 6, 9, 12)):
    bb = oracle_backbone(source, mode=mode)
    fr = [source[i] for i in frames]
    return _worst([consistency(bb.predict(fr), bb.views_for(fr))])


def _no_mapping_back(monkeypatch):
    from vggt_slam_pp.models.preprocess import PreprocessInfo

    monkeypatch.setattr(PreprocessInfo, "to_original_matrix", lambda self: np.eye(3))


def _decoded_at_original_size(monkeypatch):
    import vggt_slam_pp.models.cameras as cameras

    decode = cameras.pose_encoding_to_extri_intri
    monkeypatch.setattr(cameras, "pose_encoding_to_extri_intri", lambda enc, hw: decode(enc, (120, 160)))


def _depth_flipped(monkeypatch):
    import vggt_slam_pp.frontend.backbones.vggt as vggt_backbone

    dense = vggt_backbone.dense_observations
    monkeypatch.setattr(vggt_backbone, "dense_observations",
                        lambda T, depth, conf, K, A, stride: dense(T, depth[::-1], conf[::-1], K, A, stride))


def _depth_at_original_resolution(monkeypatch):
    import cv2

    import vggt_slam_pp.frontend.backbones.vggt as vggt_backbone

    def wrong(T, depth, conf, K, A, stride):  # resized to the photo's size, read on that grid
        size = (round(depth.shape[1] * A[0, 0]), round(depth.shape[0] * A[1, 1]))
        return dense(T, cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST),
                     cv2.resize(conf, size, interpolation=cv2.INTER_NEAREST), K, A, stride)

    dense = vggt_backbone.dense_observations
    monkeypatch.setattr(vggt_backbone, "dense_observations", wrong)


@pytest.mark.parametrize("error, measure, limit", [
    (_no_mapping_back, "reprojection_px", 10.0),
    (_no_mapping_back, "focal_rel", 1.0),
    (_decoded_at_original_size, "reprojection_px", 10.0),
    (_depth_flipped, "depth_rel", 0.05),
    (_depth_at_original_resolution, "depth_rel", 0.05),
], ids=["to_original_identity_pixels", "to_original_identity_K", "intrinsics_at_original_size", "depth_flipped",
        "depth_at_original_resolution"])
def test_pixel_and_depth_convention_errors_are_caught(sequences, monkeypatch, error, measure, limit):
    src = sequences["landscape"]
    clean = _predict_checks(src)
    assert clean[measure] < 0.3 * min(limit, 1.0)
    error(monkeypatch)
    assert _predict_checks(src)[measure] > limit


def test_preprocessing_errors_are_caught_by_the_oracle(sequences, monkeypatch):
    import vggt_slam_pp.models.preprocess as preprocess

    src = sequences["landscape"]
    original = preprocess.preprocess_images
    monkeypatch.setattr(preprocess, "preprocess_images",
                        lambda images, mode="crop", target_size=518: _bgr(*original(images, mode, target_size)))
    with pytest.raises(ModelError, match="does not show the original image"):
        _predict_checks(src)
    monkeypatch.setattr(preprocess, "preprocess_images", original)
    monkeypatch.setattr(preprocess, "_network_size",
                        lambda w0, h0, mode, target: (target, h0 * target // w0 // 14 * 14))
    with pytest.raises(ModelError, match="contract's crop preprocessing"):  # floor instead of round: 378 rows
        _predict_checks(src)


def _bgr(images, infos):
    return images[:, [2, 1, 0]], infos


# ------------------------------------------------------------------------------------------ noise
def test_noisy_oracle_drifts(tmp_path, sequences, clean_runs):
    src = sequences["landscape"]
    clean = clean_runs.get(("landscape", "crop"))
    if clean is None:
        clean = _run(src, tmp_path / "clean", mode="crop")
    noise = OracleNoise(depth_noise=0.01, scale_error=0.01, rot_noise_deg=0.1, trans_noise=0.005)
    report, checks = _run(src, tmp_path / "noisy", mode="crop", noise=noise, seed=1)
    ate = report["ate_rmse_odometry"]
    assert np.isfinite(ate) and report["error"] is None
    assert ate > 100 * clean[0]["ate_rmse_odometry"] and ate > 1e-4 * report["gt_path_length"]
    assert ate < 0.2 * report["gt_path_length"]  # drift, not a broken chain
    w = _worst(checks)
    assert 0.05 < w["rotation_deg"] < 2.0 and 1e-3 < w["depth_rel"] < 0.05
    assert dataclasses.asdict(noise) == report["oracle"]["noise"]
