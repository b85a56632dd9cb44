"""GPU checks of the models: CUDA output equals the CPU reference; mixed precision stays finite.

Marked ``gpu`` (deselected by default, skipped without CUDA). Run on a GPU machine with
``python -m pytest -m gpu tests/test_models_gpu.py``.
"""

from __future__ import annotations

import pytest
import torch

from test_models_vggt import _check_case, _load, _model, _run
from vggt_slam_pp.models.runtime import autocast_dtype, inference_context

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def _to(t: dict, device: str) -> dict:
    return {k: v.to(device) for k, v in t.items()}


def test_vggt_tiny_cuda_float32_matches_reference(reference):
    meta, t = _load(reference, "vggt_tiny_track")
    model = _model(meta, t).cuda()
    assert _check_case(model, _to(t, "cuda")) >= 22


def test_vggt_tiny_cuda_autocast_finite_and_close(reference):
    meta, t = _load(reference, "vggt_tiny_track")
    model = _model(meta, t).cuda()
    dtype = autocast_dtype("cuda")
    assert dtype in (torch.bfloat16, torch.float16)
    with inference_context("cuda"):
        out = model(t["input.images"].cuda(), query_points=t["input.query_points"].cuda())
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert out[key].dtype == torch.float32, key  # heads run in float32 under autocast
        assert torch.isfinite(out[key]).all(), key
    ref_cpu, _ = _run(_model(meta, t), t)
    rel = ((out["depth"].cpu() - ref_cpu["depth"]).abs() / ref_cpu["depth"]).median()
    assert rel < 0.05, f"median relative depth error under {dtype}: {rel:.3g}"
    assert (out["pose_enc"].cpu() - ref_cpu["pose_enc"]).abs().max() < 0.1


def test_dinov2_tiny_cuda_matches_reference(reference):
    from test_models_dinov2 import _fixture
    from vggt_slam_pp.models import build_dinov2

    meta, t = _fixture(reference, "dinov2_tiny_reg4")
    model = build_dinov2(meta["config"]).eval()
    model.load_state_dict({k.removeprefix("state_dict."): v for k, v in t.items() if k.startswith("state_dict.")})
    with torch.no_grad():
        out = model.cuda().forward_features(t["input.x"].cuda())["x_norm_patchtokens"].cpu()
    assert (out - t["output.forward_features.x_norm_patchtokens"]).abs().max() < 1e-4
