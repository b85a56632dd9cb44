"""Transformer building blocks shared by our DINOv2 and VGGT implementations.

Module and parameter names follow the official checkpoints (``norm1``, ``attn.qkv``, ``ls1.gamma``,
``mlp.fc1`` ...), so the published state dicts load without renaming. Attention uses PyTorch's fused
``scaled_dot_product_attention``. Shapes: ``B`` batch, ``N`` tokens, ``C`` channels, ``h`` heads.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class Mlp(nn.Module):
    """``fc1 -> GELU (exact erf) -> fc2``."""

    def __init__(self, in_features: int, hidden_features: int, out_features: int | None = None,
                 bias: bool = True) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features, bias=bias)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_features, out_features or in_features, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


def swiglu_hidden(dim: int, mlp_ratio: float) -> int:
    """Hidden width of DINOv2's fused SwiGLU FFN: ``((int(4D * 2/3) + 7) // 8) * 8`` for ratio 4."""
    return (int(int(dim * mlp_ratio) * 2 / 3) + 7) // 8 * 8


class SwiGLUFFN(nn.Module):
    """``w12`` (D -> 2H), split into a, b, ``SiLU(a) * b``, ``w3`` (H -> D)."""

    def __init__(self, dim: int, hidden: int, bias: bool = True) -> None:
        super().__init__()
        self.w12 = nn.Linear(dim, 2 * hidden, bias=bias)
        self.w3 = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, b = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(a) * b)


class LayerScale(nn.Module):
    """Elementwise learned scale ``gamma`` [C]."""

    def __init__(self, dim: int, init_values: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_values)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Rope2D:
    """2-D rotary position embedding (VGGT's aggregator), base frequency ``base``.

    The head channels are split in two halves: the first is rotated by the token's row coordinate,
    the second by its column coordinate. Within a half of ``d`` channels the frequencies are
    ``base^(-2k/d)``, the angle table is ``[theta, theta]`` and rotation is "rotate-half"
    (non-interleaved). Tables are computed in float32 and cast to the activation dtype.
    """

    def __init__(self, base: float = 100.0) -> None:
        self.base = float(base)

    def tables(self, positions: torch.Tensor, head_dim: int, dtype: torch.dtype
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """cos/sin tables for ``positions`` [B, N, 2] (row, col) int -> four tensors [B, 1, N, head_dim/2]."""
        d = head_dim // 2
        exponents = torch.arange(0, d, 2, device=positions.device).float() / d
        inv_freq = 1.0 / (self.base ** exponents)
        out = []
        for axis in (0, 1):
            angles = positions[..., axis].to(inv_freq.dtype)[..., None] * inv_freq  # [B, N, d/2]
            angles = torch.cat((angles, angles), dim=-1).to(dtype)
            out.extend((angles.cos()[:, None], angles.sin()[:, None]))
        return out[0], out[1], out[2], out[3]

    @staticmethod
    def apply(x: torch.Tensor, tables: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """Rotate ``x`` [B, h, N, head_dim] with tables from :meth:`tables`."""
        cos_y, sin_y, cos_x, sin_x = tables
        y, x_ = x.chunk(2, dim=-1)
        return torch.cat((_rotate(y, cos_y, sin_y), _rotate(x_, cos_x, sin_x)), dim=-1)


def _rotate(v: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    a, b = v.chunk(2, dim=-1)
    return v * cos + torch.cat((-b, a), dim=-1) * sin


class Attention(nn.Module):
    """Multi-head self-attention with a packed ``qkv`` Linear, optional QK LayerNorm and 2-D RoPE."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True, proj_bias: bool = True,
                 qk_norm: bool = False, norm_eps: float = 1e-5) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.q_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim, bias=proj_bias)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, ...] | None = None,
                qkv_out: list[torch.Tensor] | None = None) -> torch.Tensor:
        """x [B, N, C] -> [B, N, C]; ``qkv_out`` (if given) receives the raw qkv output [B, N, 3C]."""
        B, N, C = x.shape
        qkv = self.qkv(x)
        if qkv_out is not None:
            qkv_out.append(qkv)
        q, k, v = qkv.reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4).unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q, k = Rope2D.apply(q, rope), Rope2D.apply(k, rope)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(B, N, C))


class Block(nn.Module):
    """Pre-norm transformer block: ``x + ls1(attn(norm1 x))``, then ``x + ls2(mlp(norm2 x))``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, qkv_bias: bool = True,
                 proj_bias: bool = True, ffn_bias: bool = True, init_values: float | None = None,
                 norm_eps: float = 1e-5, qk_norm: bool = False, ffn_layer: str = "mlp") -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias, proj_bias=proj_bias, qk_norm=qk_norm)
        self.ls1 = LayerScale(dim, init_values) if init_values else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        if ffn_layer == "mlp":
            self.mlp: nn.Module = Mlp(dim, int(dim * mlp_ratio), bias=ffn_bias)
        elif ffn_layer in ("swiglu", "swiglufused"):
            self.mlp = SwiGLUFFN(dim, swiglu_hidden(dim, mlp_ratio), bias=ffn_bias)
        else:
            raise ValueError(f"unknown ffn_layer {ffn_layer!r} (expected 'mlp' or 'swiglufused')")
        self.ls2 = LayerScale(dim, init_values) if init_values else nn.Identity()

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, ...] | None = None,
                qkv_out: list[torch.Tensor] | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), rope=rope, qkv_out=qkv_out))
        return x + self.ls2(self.mlp(self.norm2(x)))
