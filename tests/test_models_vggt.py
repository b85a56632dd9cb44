"""VGGT parity with the official reference fixtures (``../shared/reference``), manifests and utilities."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vggt_slam_pp.errors import ModelError
from vggt_slam_pp.models.cameras import (
    extri_intri_to_pose_encoding,
    extrinsic_to_T_cam_world,
    pose_encoding_to_extri_intri,
    unproject_depth_map_to_point_map,
)
from vggt_slam_pp.models.preprocess import preprocess_images
from vggt_slam_pp.models.vggt import VggtConfig, build_vggt

# reference/README.md "Suggested tolerances": (kind, value); "rel" means |diff| <= v * max(1, |ref|)
TOL = {
    "pose_enc": ("abs", 1e-4), "pose_enc_list": ("abs", 1e-4), "extrinsic": ("abs", 1e-4),
    "intrinsic": ("abs", 1e-3), "depth": ("rel", 1e-4), "depth_conf": ("rel", 1e-4),
    "world_points": ("rel", 1e-4), "world_points_conf": ("rel", 1e-4), "images": ("abs", 0.0),
    "world_points_from_depth": ("abs", 1e-3), "feature_maps": ("abs", 1e-3), "track": ("abs", 0.05),
    "track_list": ("abs", 0.05), "vis": ("abs", 1e-2), "conf": ("abs", 1e-2), "tokens": ("abs", 1e-4),
    "pre_activation": ("abs", 1e-4),
}


def _close(ours, ref: torch.Tensor, kind: str) -> None:
    ours = torch.as_tensor(np.asarray(ours) if not isinstance(ours, torch.Tensor) else ours).cpu()
    ref = ref.cpu()
    assert tuple(ours.shape) == tuple(ref.shape), (kind, tuple(ours.shape), tuple(ref.shape))
    mode, tol = TOL[kind]
    diff = (ours.double() - ref.double()).abs()
    bound = tol * torch.clamp(ref.double().abs(), min=1.0) if mode == "rel" else torch.full_like(diff, tol)
    worst = (diff - bound).max().item()
    assert worst <= 0, f"{kind}: exceeds tolerance by {worst:.3g} (max |diff| {diff.max().item():.3g})"


def _load(reference, name):
    from safetensors.torch import load_file

    meta = json.loads((reference / "fixtures" / f"{name}.json").read_text())
    return meta, load_file(str(reference / "fixtures" / f"{name}.safetensors"))


def _model(meta, tensors):
    model = build_vggt(meta["config"]).eval()
    model.load_state_dict({k.removeprefix("state_dict."): v for k, v in tensors.items()
                           if k.startswith("state_dict.")}, strict=True)
    return model


def _run(model, t, prefix=""):
    """Forward with hooks on the dense heads' last conv; returns (outputs, intermediates)."""
    inter: dict = {}
    hooks = []
    for head in ("depth_head", "point_head"):
        module = getattr(model, head).scratch.output_conv2

        def hook(_m, _i, out, head=head):
            inter.setdefault(f"{head}.pre_activation", []).append(out)

        hooks.append(module.register_forward_hook(hook))
    qp = t.get(f"{prefix}input.query_points")
    with torch.no_grad():
        out = model(t[f"{prefix}input.images"], query_points=qp, intermediates=inter)
    for h in hooks:
        h.remove()
    return out, inter


def _check_case(model, t, prefix=""):
    out, inter = _run(model, t, prefix)
    checked = 0
    for key, ref in t.items():
        if not key.startswith(prefix):
            continue
        name = key[len(prefix):]
        if name.startswith("output."):
            o = out[name[len("output."):]]
            _close(torch.stack(o) if isinstance(o, list) else o, ref, name[len("output."):])
        elif name.startswith("intermediate.aggregator.layer_"):
            _close(inter["aggregator"][int(name.rsplit("_", 1)[1])], ref, "tokens")
        elif name.endswith("pre_activation"):
            head = name.split(".")[1]
            _close(torch.cat(inter[f"{head}.pre_activation"]), ref, "pre_activation")
        elif name == "intermediate.track_head.feature_maps":
            _close(inter["track_feature_maps"], ref, "feature_maps")
        elif name == "intermediate.track_head.track_list":
            _close(torch.stack(inter["track_list"]), ref, "track_list")
        elif name.startswith("intermediate.patch_embed."):
            imgs = t[f"{prefix}input.images"]
            agg = model.aggregator
            x = ((imgs - agg._resnet_mean) / agg._resnet_std).flatten(0, 1)
            with torch.no_grad():
                _close(agg.patch_embed.forward_features(x)[name.rsplit(".", 1)[1]], ref, "tokens")
        elif name.startswith("derived."):
            H, W = t[f"{prefix}input.images"].shape[-2:]
            ext, K = pose_encoding_to_extri_intri(out["pose_enc"], (H, W))
            if name == "derived.extrinsic":
                _close(ext, ref, "extrinsic")
            elif name == "derived.intrinsic":
                _close(K, ref, "intrinsic")
            else:
                pts = unproject_depth_map_to_point_map(out["depth"][0], ext[0], K[0])
                assert pts.dtype == np.float64
                _close(pts[None], ref, "world_points_from_depth")
        else:
            continue
        checked += 1
    return checked


@pytest.fixture(scope="module")
def track_fixture(reference):
    meta, t = _load(reference, "vggt_tiny_track")
    return _model(meta, t), t


def test_tiny_notrack_every_output(reference):
    meta, t = _load(reference, "vggt_tiny_notrack")
    model = _model(meta, t)
    assert model.track_head is None
    assert _check_case(model, t) >= 18
    out, _ = _run(model, t)
    assert "track" not in out and set(out) >= {"pose_enc", "depth", "world_points", "images"}


def test_tiny_track_every_output(track_fixture):
    model, t = track_fixture
    assert _check_case(model, t) >= 22
    out, _ = _run(model, t)
    assert torch.allclose(out["track"][:, 0], t["input.query_points"])  # frame 0 = the queries


@pytest.mark.parametrize("case", ["odd", "single"])
def test_tiny_extra_cases(reference, track_fixture, case):
    model, _ = track_fixture
    _, t = _load(reference, "vggt_tiny_extra")
    assert _check_case(model, t, prefix=f"{case}.") >= 15


def test_unbatched_input_and_chunked_dpt_equal(track_fixture):
    model, t = track_fixture
    imgs = t["input.images"]
    with torch.no_grad():
        batched = model(imgs)
        unbatched = model(imgs[0])
        depth_chunked = model.depth_head(
            model.aggregator(imgs, keep={0, 2, 3, 5}), tuple(imgs.shape[-2:]), 5, frames_chunk_size=1)[0]
    assert torch.equal(batched["depth"], unbatched["depth"])
    assert torch.allclose(depth_chunked, batched["depth"], rtol=1e-5, atol=1e-5)


def test_vggt_1b_manifest_on_meta(reference):
    rows = [line.split("\t") for line in (reference / "vggt_1b_state_dict_manifest.tsv").read_text().splitlines()
            if line and not line.startswith("#")]
    assert rows[0][:2] == ["key", "shape"]
    expected = [(r[0], r[1]) for r in rows[1:]]
    model = build_vggt({}, device="meta")
    ours = [(k, "x".join(map(str, v.shape))) for k, v in model.state_dict().items()]
    assert len(ours) == 1797
    assert ours == expected
    assert sum(v.numel() for v in model.state_dict().values()) == 1_256_537_516


def test_config_defaults_are_vggt_1b():
    c = VggtConfig.from_dict({})
    assert (c.embed_dim, c.aggregator.depth, c.dpt.features, c.track_head.corr_levels) == (1024, 24, 256, 7)
    assert c.dino.num_register_tokens == 4 and c.dino.interpolate_antialias and c.dino.interpolate_offset == 0
    with pytest.raises(ModelError, match="unknown VGGT config sections"):
        VggtConfig.from_dict({"heads": {}})


def test_bad_input_shapes(track_fixture):
    model, _ = track_fixture
    with pytest.raises(ModelError, match="multiple of the patch size"):
        model(torch.zeros(2, 3, 50, 84))
    with pytest.raises(ModelError, match=r"\[S,3,H,W\]"):
        model(torch.zeros(2, 1, 56, 84))


def test_preprocessing_exact(reference):
    _, t = _load(reference, "vggt_preprocess")
    src = {k.split(".")[1][0]: t[k].numpy() for k in t if k.startswith("source.")}
    runs = [k.removeprefix("output_u8.") for k in t if k.startswith("output_u8.")]
    assert len(runs) == 5
    for run in runs:
        mode, names = run.split(".")
        x, infos = preprocess_images([src[n] for n in names], mode)
        assert x.dtype == torch.float32 and len(infos) == len(names)
        assert torch.equal(x, t[f"output_u8.{run}"].float() / 255), run


def test_preprocess_info_maps_back_to_original_pixels():
    img = np.zeros((100, 150, 3), np.uint8)
    _, (crop,) = preprocess_images([img], "crop")
    _, (pad,) = preprocess_images([np.zeros((150, 100, 3), np.uint8)], "pad")
    assert crop.network_hw == (350, 518) and pad.network_hw == (518, 518) and pad.offset_x == 84
    # corners of the original image (OpenCV centres: -0.5 .. W-0.5) map to the resized extent
    assert np.allclose(crop.to_original([[-0.5, -0.5], [517.5, 349.5]]), [[-0.5, -0.5], [149.5, 99.5]])
    assert np.allclose(pad.to_original([[pad.offset_x - 0.5, -0.5]]), [[-0.5, -0.5]])
    K_net = np.array([[400.0, 0, 259], [0, 400.0, 175], [0, 0, 1]])
    K = crop.intrinsics_to_original(K_net)
    assert np.isclose(K[0, 0], 400 / crop.scale_x) and np.isclose(K[0, 2], crop.to_original([[259, 0]])[0, 0])
    with pytest.raises(ModelError, match="unknown preprocessing mode"):
        preprocess_images([img], "resize")
    with pytest.raises(ModelError, match="no images"):
        preprocess_images([], "crop")


def test_pose_encoding_round_trip(rng):
    from vggt_slam_pp.geometry import so3_exp

    R = torch.tensor(np.stack([so3_exp(rng.normal(size=3)) for _ in range(20)]))
    t = torch.tensor(rng.normal(size=(20, 3)))
    ext = torch.cat([R, t[..., None]], dim=-1)
    K = torch.tensor([[300.0, 0, 259], [0, 280.0, 147], [0, 0, 1]], dtype=torch.float64).expand(20, 3, 3)
    enc = extri_intri_to_pose_encoding(ext, K, (294, 518))
    assert enc.dtype == torch.float32 and (enc[:, 6] >= 0).all()
    ext2, K2 = pose_encoding_to_extri_intri(enc.double(), (294, 518))
    assert torch.allclose(ext2, ext, atol=1e-5) and torch.allclose(K2, K, atol=1e-3)
    # a scaled quaternion decodes to the same rotation
    ext3, _ = pose_encoding_to_extri_intri(torch.cat([enc[:, :3], 3 * enc[:, 3:7], enc[:, 7:]], -1), (294, 518))
    assert torch.allclose(ext3[..., :3], ext[..., :3].float(), atol=1e-5)
    T = extrinsic_to_T_cam_world(ext)
    assert T.shape == (20, 4, 4) and np.allclose(T[:, 3], [0, 0, 0, 1])


def test_importing_the_models_sets_no_global_torch_flags():
    import subprocess
    import sys

    code = (
        "import torch\n"
        "def flags():\n"
        "    return (torch.get_default_dtype(), torch.get_num_threads(), torch.backends.cudnn.benchmark,\n"
        "            torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32,\n"
        "            torch.get_float32_matmul_precision(), torch.is_grad_enabled())\n"
        "before = flags()\n"
        "import vggt_slam_pp.models.weights, vggt_slam_pp.models.runtime, vggt_slam_pp.models.preprocess\n"
        "import vggt_slam_pp.models.cameras\n"
        "assert flags() == before, (before, flags())\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
