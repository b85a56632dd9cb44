"""Weight loading: both file formats, Hugging Face folders and naming, renamed keys, bad checkpoints."""

from __future__ import annotations

import json
import re

import pytest
import torch

from vggt_slam_pp.errors import WeightsError
from vggt_slam_pp.models import build_dinov2, build_vggt
from vggt_slam_pp.models import weights as W

TINY_DINO = {"embed_dim": 48, "depth": 2, "num_heads": 3, "num_register_tokens": 4,
             "interpolate_antialias": True, "interpolate_offset": 0.0}
TINY_VGGT = {
    "VGGT": {"embed_dim": 32, "enable_track": False},
    "dino": {"embed_dim": 32, "depth": 1, "num_heads": 2},
    "aggregator": {"depth": 2, "num_heads": 2, "cached_layer_indices": [0, 1, 1, 1]},
    "camera_head": {"trunk_depth": 1, "num_heads": 2},
    "dpt": {"features": 8, "out_channels": [4, 8, 8, 8], "intermediate_layer_idx": [0, 1, 1, 1]},
}


@pytest.fixture(autouse=True)
def isolated_caches(tmp_path, monkeypatch):
    """No test touches the user's caches or the network."""
    monkeypatch.setenv("VGGT_SLAM_PP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def _randomise(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.2)
    return model.eval()


def _to_hf(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Official DINOv2 naming -> Hugging Face ``transformers`` naming (the inverse of our converter)."""
    out = {}
    for k, v in sd.items():
        if m := re.match(r"blocks\.(\d+)\.attn\.qkv\.(weight|bias)", k):
            for name, part in zip(("query", "key", "value"), v.chunk(3), strict=True):
                out[f"dinov2.encoder.layer.{m[1]}.attention.attention.{name}.{m[2]}"] = part.clone()
            continue
        k2 = {"cls_token": "embeddings.cls_token", "mask_token": "embeddings.mask_token",
              "pos_embed": "embeddings.position_embeddings",
              "register_tokens": "embeddings.register_tokens"}.get(k, k)
        k2 = re.sub(r"^patch_embed\.proj\.", "embeddings.patch_embeddings.projection.", k2)
        k2 = re.sub(r"^blocks\.(\d+)\.attn\.proj\.", r"encoder.layer.\1.attention.output.dense.", k2)
        k2 = re.sub(r"^blocks\.(\d+)\.ls([12])\.gamma", r"encoder.layer.\1.layer_scale\2.lambda1", k2)
        k2 = re.sub(r"^blocks\.(\d+)\.", r"encoder.layer.\1.", k2)
        k2 = re.sub(r"^norm\.", "layernorm.", k2)
        out["dinov2." + k2] = v
    return out


@pytest.fixture(scope="module")
def dino():
    model = _randomise(build_dinov2(TINY_DINO))
    x = torch.rand(1, 3, 42, 56)
    with torch.no_grad():
        ref = model.forward_features(x)["x_norm_patchtokens"]
    return model, x, ref


def _same(model, x, ref):
    with torch.no_grad():
        assert torch.equal(model.forward_features(x)["x_norm_patchtokens"], ref)


@pytest.mark.parametrize("fmt", ["pth", "safetensors"])
def test_both_file_formats(tmp_path, dino, fmt):
    from safetensors.torch import save_file

    model, x, ref = dino
    path = tmp_path / f"ckpt.{fmt}"
    if fmt == "pth":
        torch.save(model.state_dict(), path)
    else:
        save_file(model.state_dict(), str(path))
    _same(W.load_dinov2(TINY_DINO, weights=path), x, ref)


def test_hugging_face_folder_and_naming(tmp_path, dino):
    from safetensors.torch import save_file

    model, x, ref = dino
    folder = tmp_path / "snapshot"
    folder.mkdir()
    save_file(_to_hf(model.state_dict()), str(folder / "model.safetensors"))
    (folder / "config.json").write_text(json.dumps({"model_type": "dinov2"}))
    _same(W.load_dinov2(TINY_DINO, weights=folder), x, ref)


def test_renamed_and_wrapped_keys(tmp_path, dino):
    model, x, ref = dino
    path = tmp_path / "wrapped.pt"
    torch.save({"state_dict": {f"module.{k}": v for k, v in model.state_dict().items()}, "epoch": 3}, path)
    _same(W.load_dinov2(TINY_DINO, weights=path), x, ref)


def test_truncated_file(tmp_path, dino):
    from safetensors.torch import save_file

    model, _, _ = dino
    for suffix in ("pt", "safetensors"):
        path = tmp_path / f"full.{suffix}"
        if suffix == "pt":
            torch.save(model.state_dict(), path)
        else:
            save_file(model.state_dict(), str(path))
        data = path.read_bytes()
        cut = tmp_path / f"cut.{suffix}"
        cut.write_bytes(data[: len(data) // 2])
        with pytest.raises(WeightsError, match="cannot read weights"):
            W.load_dinov2(TINY_DINO, weights=cut)


def test_partial_or_wrong_checkpoint_names_the_keys(tmp_path, dino):
    model, _, _ = dino
    sd = model.state_dict()
    partial = {k: v for k, v in sd.items() if not k.startswith("blocks.1.")}
    partial["head.weight"] = torch.zeros(3)
    torch.save(partial, tmp_path / "partial.pt")
    with pytest.raises(WeightsError) as err:
        W.load_dinov2(TINY_DINO, weights=tmp_path / "partial.pt")
    msg = str(err.value)
    assert "missing keys" in msg and "blocks.1.attn.proj.bias" in msg
    assert "1 unexpected keys (head.weight)" in msg and "\n" not in msg
    bad = dict(sd)
    bad["pos_embed"] = torch.zeros(1, 10, 48)
    torch.save(bad, tmp_path / "shape.pt")
    with pytest.raises(WeightsError, match=r"wrong shape \(pos_embed \(1, 10, 48\) != \(1, 1370, 48\)\)"):
        W.load_dinov2(TINY_DINO, weights=tmp_path / "shape.pt")
    # a VGGT checkpoint is not a DINOv2 one
    with pytest.raises(WeightsError, match="does not match DinoVisionTransformer"):
        W.load_dinov2(TINY_DINO, weights=_vggt_checkpoint(tmp_path)[0])


def _vggt_checkpoint(tmp_path):
    model = _randomise(build_vggt(TINY_VGGT), seed=1)
    folder = tmp_path / "vggt-snapshot"
    folder.mkdir(exist_ok=True)
    torch.save(model.state_dict(), folder / "model.pt")
    return folder, model


def test_vggt_from_snapshot_folder(tmp_path):
    folder, model = _vggt_checkpoint(tmp_path)
    images = torch.rand(2, 3, 28, 42)
    loaded = W.load_vggt(folder, config=TINY_VGGT)
    with torch.no_grad():
        a, b = model(images), loaded(images)
    assert torch.equal(a["depth"], b["depth"]) and torch.equal(a["pose_enc"], b["pose_enc"])
    assert loaded.aggregator._resnet_mean.device.type == "cpu"


def test_offline_without_local_file_says_how_to_pass_one():
    with pytest.raises(WeightsError) as err:
        W.resolve_weights("vggt-1b")
    msg = str(err.value)
    assert "not cached" in msg and "--weights PATH" in msg and "\n" not in msg
    with pytest.raises(WeightsError, match="weights file not found"):
        W.resolve_weights("/nonexistent/model.pt")
    with pytest.raises(WeightsError, match="unknown weights"):
        W.resolve_weights("vggt-2b")


def test_import_into_cache_then_load_by_name(tmp_path):
    model = _randomise(build_dinov2("dinov2_vits14"), seed=2)
    src = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(model.state_dict(), src)
    target = W.import_weights(src, "dinov2_vits14")
    assert target.parent == W.cache_dir() and target.suffix == ".safetensors"
    listed = W.cached_weights()
    assert [(c.name, c.where) for c in listed] == [("dinov2_vits14", "ours")]
    loaded = W.load_dinov2("dinov2_vits14")
    x = torch.rand(1, 3, 28, 28)
    with torch.no_grad():
        assert torch.equal(loaded(x), model(x))
    with pytest.raises(WeightsError, match="does not match"):
        W.import_weights(src, "dinov2_vitb14")


def test_release_file_names():
    assert W.dinov2_release_file("dinov2_vitb14") == "dinov2_vitb14/dinov2_vitb14_pretrain.pth"
    assert W.dinov2_release_file("dinov2_vitg14_reg") == "dinov2_vitg14/dinov2_vitg14_reg4_pretrain.pth"
    assert W.dinov2_hf_repo("dinov2_vitl14_reg") == "facebook/dinov2-with-registers-large"
