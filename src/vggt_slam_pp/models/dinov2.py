"""Our DINOv2 vision transformer, checkpoint-compatible with the official release.

Token layout ``[cls, R registers, P patches]``; registers get no positional embedding. The stored
37x37 positional embedding is resized to the input's patch grid in one of two ways, exactly as the
official model does: without registers, bicubic with the "offset 0.1" scale factors (the sampling
positions then follow ``1/s``, not the size ratio); with registers, antialiased bicubic to the target
size. Facets (q, k, v thirds of a block's ``qkv`` output) are exposed for AnyLoc-style descriptors.

Shapes: input ``[B, 3, H, W]`` normalised with ImageNet statistics (:data:`IMAGENET_MEAN`, ``_STD``),
H and W multiples of 14; ``P = (H/14)(W/14)``; ``D`` = embedding width.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from vggt_slam_pp.errors import ModelError
from vggt_slam_pp.models.layers import Block

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class DinoV2Config:
    """Constructor arguments of a DINOv2 ViT (names as in the official class)."""

    img_size: int = 518
    patch_size: int = 14
    embed_dim: int = 768
    depth: int = 12
    num_heads: int = 12
    mlp_ratio: float = 4.0
    init_values: float | None = 1.0
    qkv_bias: bool = True
    proj_bias: bool = True
    ffn_bias: bool = True
    layernorm_eps: float = 1e-6
    num_register_tokens: int = 0
    interpolate_antialias: bool = False
    interpolate_offset: float = 0.1
    ffn_layer: str = "mlp"
    block_chunks: int = 0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DinoV2Config:
        """Build from a dictionary, ignoring descriptive keys that are not constructor arguments."""
        return config_from_dict(cls, d)


_SIZES = {  # arch letter -> (embed_dim, depth, heads, ffn)
    "s": (384, 12, 6, "mlp"),
    "b": (768, 12, 12, "mlp"),
    "l": (1024, 24, 16, "mlp"),
    "g": (1536, 40, 24, "swiglufused"),
}
HUB_NAMES = tuple(f"dinov2_vit{a}14{r}" for a in "sblg" for r in ("", "_reg"))


def hub_config(name: str) -> DinoV2Config:
    """Config of an official torch-hub backbone name such as ``dinov2_vitb14`` or ``dinov2_vitl14_reg``."""
    if name not in HUB_NAMES:
        raise ModelError(f"unknown DINOv2 model {name!r}; expected one of {', '.join(HUB_NAMES)}")
    dim, depth, heads, ffn = _SIZES[name[len("dinov2_vit")]]
    reg = name.endswith("_reg")
    return DinoV2Config(embed_dim=dim, depth=depth, num_heads=heads, ffn_layer=ffn,
                        num_register_tokens=4 if reg else 0, interpolate_antialias=reg,
                        interpolate_offset=0.0 if reg else 0.1)


def config_from_dict(cls, d: Mapping[str, Any]):
    """``cls(**d)`` keeping only ``cls``'s fields (fixture configs carry descriptive extra keys)."""
    names = {f.name for f in dataclasses.fields(cls)}
    ignored = sorted(set(d) - names)
    if ignored:
        log.debug("%s: ignoring non-constructor keys %s", cls.__name__, ignored)
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in names}
    try:
        return cls(**kwargs)
    except TypeError as exc:  # pragma: no cover - dataclass signature mismatch
        raise ModelError(f"bad {cls.__name__}: {exc}") from exc


class PatchEmbed(nn.Module):
    """Conv ``3 -> D`` with kernel = stride = patch size; ``[B,3,H,W] -> [B, P, D]`` row-major."""

    def __init__(self, patch_size: int, embed_dim: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        H, W = x.shape[-2:]
        p = self.patch_size
        if H % p or W % p:
            raise ModelError(f"image size {H}x{W} is not a multiple of the patch size {p}")
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT. Parameter names equal the official ``DinoVisionTransformer`` with ``block_chunks=0``."""

    def __init__(self, config: DinoV2Config) -> None:
        super().__init__()
        if config.block_chunks:
            raise ModelError("block_chunks > 0 is not supported (the hub models use 0)")
        c = self.config = config
        D = c.embed_dim
        grid = c.img_size // c.patch_size
        # Direct parameters first, in the official state-dict order.
        self.cls_token = nn.Parameter(torch.zeros(1, 1, D))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, D))
        self.register_tokens = (nn.Parameter(torch.zeros(1, c.num_register_tokens, D))
                                if c.num_register_tokens else None)
        self.mask_token = nn.Parameter(torch.zeros(1, D))
        self.patch_embed = PatchEmbed(c.patch_size, D)
        self.blocks = nn.ModuleList(
            Block(D, c.num_heads, c.mlp_ratio, qkv_bias=c.qkv_bias, proj_bias=c.proj_bias,
                  ffn_bias=c.ffn_bias, init_values=c.init_values, norm_eps=c.layernorm_eps,
                  ffn_layer=c.ffn_layer)
            for _ in range(c.depth))
        self.norm = nn.LayerNorm(D, eps=c.layernorm_eps)
        self.head = nn.Identity()
        self.num_register_tokens = c.num_register_tokens
        self.patch_size = c.patch_size
        self.embed_dim = D
        self._init_weights()

    def _init_weights(self) -> None:
        if self.cls_token.is_meta:
            return
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        if self.register_tokens is not None:
            nn.init.normal_(self.register_tokens, std=1e-6)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    # -- tokens ---------------------------------------------------------------------------------
    def interpolate_pos_encoding(self, num_patches: int, height: int, width: int,
                                 dtype: torch.dtype) -> torch.Tensor:
        """Positional embedding [1, 1 + gh*gw, D] for an ``height`` x ``width`` pixel input."""
        N = self.pos_embed.shape[1] - 1
        if num_patches == N and height == width:
            return self.pos_embed.to(dtype)
        pos = self.pos_embed.float()
        M = int(math.sqrt(N))
        gh, gw = height // self.patch_size, width // self.patch_size
        grid = pos[:, 1:].reshape(1, M, M, -1).permute(0, 3, 1, 2)
        if self.config.interpolate_offset:
            off = self.config.interpolate_offset
            grid = F.interpolate(grid, scale_factor=((gh + off) / M, (gw + off) / M), mode="bicubic",
                                 antialias=self.config.interpolate_antialias)
        else:
            grid = F.interpolate(grid, size=(gh, gw), mode="bicubic",
                                 antialias=self.config.interpolate_antialias)
        if grid.shape[-2:] != (gh, gw):  # pragma: no cover - guarded by the official size rule
            raise ModelError(f"positional embedding resized to {tuple(grid.shape[-2:])}, expected {(gh, gw)}")
        grid = grid.permute(0, 2, 3, 1).reshape(1, gh * gw, -1)
        return torch.cat((pos[:, :1], grid), dim=1).to(dtype)

    def prepare_tokens(self, x: torch.Tensor, masks: torch.Tensor | None = None) -> torch.Tensor:
        """[B,3,H,W] -> tokens [B, 1+R+P, D] (cls + pos, registers, patches + pos)."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise ModelError(f"expected images [B,3,H,W], got {tuple(x.shape)}")
        H, W = x.shape[-2:]
        t = self.patch_embed(x)
        if masks is not None:
            t = torch.where(masks.unsqueeze(-1), self.mask_token.to(t.dtype).unsqueeze(0), t)
        t = torch.cat((self.cls_token.expand(t.shape[0], -1, -1), t), dim=1)
        t = t + self.interpolate_pos_encoding(t.shape[1] - 1, H, W, t.dtype)
        if self.register_tokens is not None:
            t = torch.cat((t[:, :1], self.register_tokens.expand(t.shape[0], -1, -1), t[:, 1:]), dim=1)
        return t

    # -- outputs --------------------------------------------------------------------------------
    def forward_features(self, x: torch.Tensor, masks: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Official dictionary: ``x_norm_clstoken`` [B,D], ``x_norm_regtokens`` [B,R,D],
        ``x_norm_patchtokens`` [B,P,D], ``x_prenorm`` [B,1+R+P,D], ``masks``."""
        t = self.prepare_tokens(x, masks)
        for blk in self.blocks:
            t = blk(t)
        n = self.norm(t)
        R = self.num_register_tokens
        return {"x_norm_clstoken": n[:, 0], "x_norm_regtokens": n[:, 1:R + 1],
                "x_norm_patchtokens": n[:, R + 1:], "x_prenorm": t, "masks": masks}

    def forward(self, x: torch.Tensor, is_training: bool = False):
        """Normalised cls token [B, D] (the official default), or the feature dict when ``is_training``."""
        out = self.forward_features(x)
        return out if is_training else self.head(out["x_norm_clstoken"])

    def _block_outputs(self, x: torch.Tensor, wanted: Sequence[int]) -> list[torch.Tensor]:
        t = self.prepare_tokens(x)
        outputs = []
        last = max(wanted) if wanted else -1
        for i, blk in enumerate(self.blocks[:last + 1]):
            t = blk(t)
            if i in wanted:
                outputs.append(t)
        return outputs

    def _block_indices(self, n: int | Sequence[int]) -> list[int]:
        depth = len(self.blocks)
        idx = list(range(depth - n, depth)) if isinstance(n, int) else [int(i) for i in n]
        bad = [i for i in idx if not 0 <= i < depth]
        if bad:
            raise ModelError(f"block indices {bad} out of range for a {depth}-block ViT")
        return idx

    def get_intermediate_layers(self, x: torch.Tensor, n: int | Sequence[int] = 1, reshape: bool = False,
                                return_class_token: bool = False, norm: bool = True) -> tuple:
        """Patch tokens of the last ``n`` blocks (int) or of the given block indices, in block order.

        Each is [B, P, D] (``reshape``: [B, D, H/14, W/14]); with ``norm`` the final LayerNorm is
        applied; ``return_class_token`` pairs each with its cls token [B, D].
        """
        outputs = self._block_outputs(x, self._block_indices(n))
        if norm:
            outputs = [self.norm(o) for o in outputs]
        cls_tokens = [o[:, 0] for o in outputs]
        patches = [o[:, 1 + self.num_register_tokens:] for o in outputs]
        if reshape:
            B, _, H, W = x.shape
            p = self.patch_size
            patches = [o.reshape(B, H // p, W // p, -1).permute(0, 3, 1, 2).contiguous() for o in patches]
        if return_class_token:
            return tuple(zip(patches, cls_tokens, strict=True))
        return tuple(patches)

    def get_facets(self, x: torch.Tensor, layers: Sequence[int], facet: str = "value",
                   patches_only: bool = False) -> dict[int, torch.Tensor]:
        """The ``query``/``key``/``value`` facet (or ``qkv``) of each block in ``layers``: [B, N, D].

        A facet is a channel third of ``blocks[i].attn.qkv`` applied to ``norm1`` of the block input;
        tokens in the order [cls, registers, patches] (``patches_only`` drops the first 1+R). Head h
        occupies channels [h*64, h*64+64). The forward stops after the last requested block.
        """
        thirds = {"query": 0, "key": 1, "value": 2}
        if facet not in (*thirds, "qkv"):
            raise ModelError(f"unknown facet {facet!r}; expected query, key, value or qkv")
        wanted = self._block_indices(layers)
        t = self.prepare_tokens(x)
        D = self.embed_dim
        out: dict[int, torch.Tensor] = {}
        for i, blk in enumerate(self.blocks[:max(wanted) + 1]):
            captured: list[torch.Tensor] | None = [] if i in wanted else None
            t = blk(t, qkv_out=captured)
            if captured:
                qkv = captured[0]
                f = qkv if facet == "qkv" else qkv[..., thirds[facet] * D:(thirds[facet] + 1) * D]
                out[i] = f[:, 1 + self.num_register_tokens:] if patches_only else f
        return out


def build_dinov2(spec: str | Mapping[str, Any] | DinoV2Config, device: str | torch.device | None = None
                 ) -> DinoVisionTransformer:
    """Build a DINOv2 ViT from a hub name (``"dinov2_vitb14"``, ``"dinov2_vitl14_reg"``...), a config
    dictionary (e.g. a fixture JSON's ``config``) or a :class:`DinoV2Config`. Random weights; load a
    checkpoint with :func:`vggt_slam_pp.models.weights.load_dinov2`. ``device="meta"`` allocates nothing.
    """
    if isinstance(spec, str):
        config = hub_config(spec)
    elif isinstance(spec, DinoV2Config):
        config = spec
    elif isinstance(spec, Mapping):
        config = DinoV2Config.from_dict(spec)
    else:
        raise ModelError(f"cannot build DINOv2 from {type(spec).__name__}")
    with torch.device(device) if device is not None else contextlib.nullcontext():
        return DinoVisionTransformer(config)

