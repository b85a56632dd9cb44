"""Device and precision choices for running the networks (no global torch flags are touched).

GPU: bf16 autocast on compute capability >= 8 (Ampere and newer), fp16 below; CPU: float32. The VGGT
camera / depth / point heads always compute in float32 (see :class:`~vggt_slam_pp.models.vggt.VGGT`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from vggt_slam_pp.errors import ModelError


def pick_device(preference: str = "auto") -> torch.device:
    """``auto`` -> CUDA if available else CPU; ``cpu`` / ``cuda`` / ``cuda:N`` are checked."""
    if preference == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(preference)
    except RuntimeError as exc:
        raise ModelError(f"unknown device {preference!r}") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ModelError(f"device {preference!r} requested but CUDA is not available")
    return device


def autocast_dtype(device: torch.device | str) -> torch.dtype | None:
    """Mixed-precision dtype for ``device``: bf16 (CC >= 8), fp16 (older GPUs) or None (CPU: float32)."""
    device = torch.device(device)
    if device.type != "cuda":
        return None
    major, _ = torch.cuda.get_device_capability(device)
    return torch.bfloat16 if major >= 8 else torch.float16


@contextlib.contextmanager
def inference_context(device: torch.device | str, dtype: torch.dtype | None | str = "auto") -> Iterator[None]:
    """``torch.inference_mode`` plus autocast at :func:`autocast_dtype` (or the given dtype; None = off)."""
    device = torch.device(device)
    if dtype == "auto":
        dtype = autocast_dtype(device)
    with torch.inference_mode():
        if dtype is None or dtype == torch.float32:
            yield
        else:
            with torch.autocast(device_type=device.type, dtype=dtype):
                yield
