"""DINOv2 parity with the official reference fixtures (``../shared/reference``) and its manifests."""

from __future__ import annotations

import json
from collections import defaultdict

import pytest
import torch

from vggt_slam_pp.errors import ModelError
from vggt_slam_pp.models.dinov2 import HUB_NAMES, build_dinov2, hub_config

TINY = ["dinov2_tiny_noreg", "dinov2_tiny_reg4", "dinov2_tiny_reg4_swiglu"]
TOL = 1e-4  # reference/README.md: ViT tokens, facets, intermediate layers


def _fixture(reference, name):
    from safetensors.torch import load_file

    meta = json.loads((reference / "fixtures" / f"{name}.json").read_text())
    tensors = load_file(str(reference / "fixtures" / f"{name}.safetensors"))
    return meta, tensors


def _close(ours: torch.Tensor, ref: torch.Tensor, tol: float = TOL) -> None:
    assert tuple(ours.shape) == tuple(ref.shape)
    if ref.numel():
        err = (ours.double() - ref.double()).abs().max().item()
        assert err <= tol, f"max |diff| {err:.3g} > {tol}"


@pytest.fixture(scope="module", params=TINY)
def tiny(request, reference):
    meta, t = _fixture(reference, request.param)
    model = build_dinov2(meta["config"]).eval()
    sd = {k.removeprefix("state_dict."): v for k, v in t.items() if k.startswith("state_dict.")}
    assert list(model.state_dict()) == meta["state_dict_keys_in_order"]
    model.load_state_dict(sd, strict=True)
    return model, t


def test_forward_features_and_default_forward(tiny):
    model, t = tiny
    with torch.no_grad():
        out = model.forward_features(t["input.x"])
        default = model(t["input.x"])
    for key in ("x_norm_clstoken", "x_norm_regtokens", "x_norm_patchtokens", "x_prenorm"):
        _close(out[key], t[f"output.forward_features.{key}"])
    _close(default, t["output.forward.default_output"])
    R = model.num_register_tokens
    assert out["x_prenorm"].shape[1] == 1 + R + out["x_norm_patchtokens"].shape[1]


def test_masked_forward(tiny):
    model, t = tiny
    with torch.no_grad():
        out = model.forward_features(t["input.x"], masks=t["output.masked.mask"])
    _close(out["x_norm_clstoken"], t["output.masked.forward_features.x_norm_clstoken"])
    _close(out["x_norm_patchtokens"], t["output.masked.forward_features.x_norm_patchtokens"])


def test_intermediate_layers_three_call_styles(tiny):
    model, t = tiny
    x = t["input.x"]
    depth = len(model.blocks)
    with torch.no_grad():
        pairs = model.get_intermediate_layers(x, n=depth, return_class_token=True)
        maps = model.get_intermediate_layers(x, n=[0, 2], reshape=True, norm=False)
        (last,) = model.get_intermediate_layers(x)
    assert isinstance(pairs, tuple) and len(pairs) == depth
    for i, (patches, cls) in enumerate(pairs):
        _close(patches, t[f"output.get_intermediate_layers.n_all.norm.layer_{i}.patch_tokens"])
        _close(cls, t[f"output.get_intermediate_layers.n_all.norm.layer_{i}.class_token"])
    _close(maps[0], t["output.get_intermediate_layers.idx_0_2.nonorm.reshape.layer_0"])
    _close(maps[1], t["output.get_intermediate_layers.idx_0_2.nonorm.reshape.layer_2"])
    _close(last, t["output.get_intermediate_layers.n_1.default"])


def test_facets(tiny):
    model, t = tiny
    x = t["input.x"]
    depth = len(model.blocks)
    with torch.no_grad():
        values = model.get_facets(x, range(depth), "value")
        last = depth - 1
        for facet in ("query", "key", "value", "qkv"):
            ref = t[f"output.facet.last_block.{'qkv_output' if facet == 'qkv' else facet}"]
            _close(model.get_facets(x, [last], facet)[last], ref)
        patch_v = model.get_facets(x, [0], "value", patches_only=True)[0]
    for i in range(depth):
        _close(values[i], t[f"output.facet.block_{i}.value"])
    _close(patch_v, t["output.facet.block_0.value"][:, 1 + model.num_register_tokens:])


@pytest.mark.parametrize("variant", ["noreg", "reg4"])
def test_pos_embed_interpolation_both_modes(reference, variant):
    _, t = _fixture(reference, "dinov2_pos_embed_interpolation")
    # the fixture's width is 48: a hub configuration (same interpolation mode) at that width
    cfg = hub_config("dinov2_vits14" if variant == "noreg" else "dinov2_vits14_reg")
    model = build_dinov2({**cfg.__dict__, "embed_dim": 48, "num_heads": 3, "depth": 1})
    with torch.no_grad():
        model.pos_embed.copy_(t[f"{variant}.pos_embed"])
    grids = [k for k in t if k.startswith(f"{variant}.grid_")]
    assert len(grids) == 9
    for key in grids:
        gh, gw = map(int, key.rsplit("_", 1)[1].split("x"))
        out = model.interpolate_pos_encoding(gh * gw, gh * 14, gw * 14, torch.float32)
        _close(out, t[key], 5e-5)
    # the square 37x37 input returns the stored embedding itself
    assert torch.equal(model.interpolate_pos_encoding(37 * 37, 518, 518, torch.float32), model.pos_embed)


def test_plain_size_ratio_would_fail_noreg(reference):
    """The offset-0.1 quirk matters: the size-ratio kernel is O(1) away from the reference."""
    _, t = _fixture(reference, "dinov2_pos_embed_interpolation")
    grid = t["noreg.pos_embed"][:, 1:].reshape(1, 37, 37, 48).permute(0, 3, 1, 2)
    plain = torch.nn.functional.interpolate(grid, size=(4, 5), mode="bicubic")
    ref = t["noreg.grid_4x5"][:, 1:].reshape(1, 4, 5, 48).permute(0, 3, 1, 2)
    assert (plain - ref).abs().max() > 0.05


def test_manifest_every_hub_model_on_meta(reference):
    rows = defaultdict(list)
    for line in (reference / "dinov2_state_dict_manifest.tsv").read_text().splitlines():
        if line.startswith("#") or line.startswith("model\t"):
            continue
        model, key, shape, *_ = line.split("\t")
        rows[model].append((key, shape))
    assert sorted(rows) == sorted(HUB_NAMES)
    for name, expected in rows.items():
        model = build_dinov2(name, device="meta")
        ours = [(k, "x".join(map(str, v.shape))) for k, v in model.state_dict().items()]
        assert ours == expected, name


def test_bad_inputs_are_clear():
    model = build_dinov2({"embed_dim": 48, "depth": 1, "num_heads": 3})
    with pytest.raises(ModelError, match="multiple of the patch size"):
        model(torch.zeros(1, 3, 50, 56))
    with pytest.raises(ModelError, match="unknown DINOv2 model"):
        build_dinov2("dinov2_vitx14")
    with pytest.raises(ModelError, match="unknown facet"):
        model.get_facets(torch.zeros(1, 3, 28, 28), [0], "values")
    with pytest.raises(ModelError, match="out of range"):
        model.get_intermediate_layers(torch.zeros(1, 3, 28, 28), n=[3])
