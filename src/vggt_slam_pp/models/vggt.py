"""Our VGGT (VGGT-1B by default), checkpoint-compatible with ``facebook/VGGT-1B``.

Aggregator: a DINOv2 ViT-L/14-reg patch embedding, per-frame camera + 4 register tokens (one set for
the first frame of a scene, another for the others), then alternating frame / global attention blocks
with QK LayerNorm and 2-D RoPE. Heads: camera (iterative AdaLN trunk), DPT depth and point heads, and
the track head. Reference behaviour: ``reference/vggt_contract.md``.

Shapes: images ``[S,3,H,W]`` or ``[B,S,3,H,W]`` in [0, 1] (H, W multiples of 14); ``P`` patches
per frame; outputs as in :meth:`VGGT.forward`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from vggt_slam_pp.errors import ModelError
from vggt_slam_pp.models.dinov2 import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    DinoV2Config,
    DinoVisionTransformer,
    config_from_dict,
    hub_config,
)
from vggt_slam_pp.models.layers import Block, Rope2D
from vggt_slam_pp.models.vggt_heads import CameraHead, CameraHeadConfig, DenseOutputConfig, DptConfig, DPTHead
from vggt_slam_pp.models.vggt_track import TrackerConfig, TrackHead, TrackHeadConfig


@dataclass(frozen=True)
class AggregatorConfig:
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    qkv_bias: bool = True
    proj_bias: bool = True
    ffn_bias: bool = True
    aa_order: tuple[str, ...] = ("frame", "global")
    aa_block_size: int = 1
    qk_norm: bool = True
    rope_freq: float = 100.0
    init_values: float = 0.01
    cached_layer_indices: tuple[int, ...] = (4, 11, 17, 23)


def _vitl14_reg() -> DinoV2Config:
    """VGGT's patch embedding: the ``dinov2_vitl14_reg`` layout (antialiased pos-embed resize, offset 0)."""
    return hub_config("dinov2_vitl14_reg")


@dataclass(frozen=True)
class VggtConfig:
    """Every size of the network. The defaults are VGGT-1B."""

    img_size: int = 518
    patch_size: int = 14
    embed_dim: int = 1024
    enable_camera: bool = True
    enable_point: bool = True
    enable_depth: bool = True
    enable_track: bool = True
    dino: DinoV2Config = field(default_factory=_vitl14_reg)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    camera_head: CameraHeadConfig = field(default_factory=CameraHeadConfig)
    dpt: DptConfig = field(default_factory=DptConfig)
    depth_head: DenseOutputConfig = field(default_factory=lambda: DenseOutputConfig(2, "exp", "expp1"))
    point_head: DenseOutputConfig = field(default_factory=lambda: DenseOutputConfig(4, "inv_log", "expp1"))
    track_head: TrackHeadConfig = field(default_factory=TrackHeadConfig)

    @property
    def head_dim_in(self) -> int:
        return 2 * self.embed_dim

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VggtConfig:
        """Nested dictionary as in the fixtures' ``config`` (keys ``VGGT``, ``dino``, ``aggregator``,
        ``camera_head``, ``dpt``, ``depth_head``, ``point_head``, ``track_head``); missing parts keep
        the VGGT-1B values. ``{}`` is VGGT-1B."""
        known = {"VGGT", "dino", "aggregator", "camera_head", "dpt", "depth_head", "point_head", "track_head"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ModelError(f"unknown VGGT config sections {unknown}; expected some of {sorted(known)}")
        base = cls()
        nested = {"dino", "aggregator", "camera_head", "dpt", "depth_head", "point_head", "track_head"}
        top = {k: v for k, v in d.get("VGGT", {}).items() if k not in nested}
        kw: dict[str, Any] = {f.name: getattr(config_from_dict(cls, top), f.name)
                              for f in dataclasses.fields(cls) if f.name not in nested}
        kw["dino"] = _merge(base.dino, d.get("dino", {}))
        kw["aggregator"] = _merge(base.aggregator, d.get("aggregator", {}))
        kw["camera_head"] = _merge(base.camera_head, d.get("camera_head", {}))
        kw["dpt"] = _merge(base.dpt, d.get("dpt", {}))
        kw["depth_head"] = _merge(base.depth_head, d.get("depth_head", {}))
        kw["point_head"] = _merge(base.point_head, d.get("point_head", {}))
        th = dict(d.get("track_head") or {})
        fe = _merge(base.track_head.feature_extractor, th.pop("feature_extractor", {}))
        tr = _merge(base.track_head.tracker, th.pop("tracker", {}))
        kw["track_head"] = dataclasses.replace(_merge(base.track_head, th), feature_extractor=fe, tracker=tr)
        return cls(**kw)


def _merge(base, d: Mapping[str, Any]):
    """``base`` with the fields given in ``d`` replaced (descriptive extra keys ignored)."""
    return config_from_dict(type(base), {**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)},
                                         **dict(d)})


class Aggregator(nn.Module):
    """Patch embedding + special tokens + alternating frame/global attention."""

    def __init__(self, config: VggtConfig) -> None:
        super().__init__()
        a = config.aggregator
        C = config.embed_dim
        self.config = a
        self.patch_size = config.patch_size
        # direct parameters first: state-dict order of the official module
        self.camera_token = nn.Parameter(torch.zeros(1, 2, 1, C))
        self.register_token = nn.Parameter(torch.zeros(1, 2, a.num_register_tokens, C))
        dino = dataclasses.replace(config.dino, img_size=config.img_size, patch_size=config.patch_size)
        if dino.embed_dim != C:
            raise ModelError(f"patch-embed width {dino.embed_dim} differs from embed_dim {C}")
        self.patch_embed = DinoVisionTransformer(dino)
        self.rope = Rope2D(a.rope_freq) if a.rope_freq > 0 else None
        block = dict(num_heads=a.num_heads, mlp_ratio=a.mlp_ratio, qkv_bias=a.qkv_bias, proj_bias=a.proj_bias,
                     ffn_bias=a.ffn_bias, init_values=a.init_values, qk_norm=a.qk_norm)
        self.frame_blocks = nn.ModuleList(Block(C, **block) for _ in range(a.depth))
        self.global_blocks = nn.ModuleList(Block(C, **block) for _ in range(a.depth))
        self.patch_start_idx = 1 + a.num_register_tokens
        self.reset_buffers()
        if not self.camera_token.is_meta:
            nn.init.normal_(self.camera_token, std=1e-6)
            nn.init.normal_(self.register_token, std=1e-6)

    def reset_buffers(self) -> None:
        """(Re)create the ImageNet normalisation buffers (not in the checkpoint; needed after a meta build)."""
        device = self.camera_token.device
        for name, value in (("_resnet_mean", IMAGENET_MEAN), ("_resnet_std", IMAGENET_STD)):
            self.register_buffer(name, torch.tensor(value, device=device).view(1, 1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor, keep: set[int] | None = None) -> list[torch.Tensor | None]:
        """images [B,S,3,H,W] in [0,1] -> list of ``depth`` entries [B,S,P',2C] (None unless in ``keep``;
        the last entry is always kept)."""
        a = self.config
        B, S, _, H, W = images.shape
        x = ((images - self._resnet_mean) / self._resnet_std).reshape(B * S, 3, H, W)
        patches = self.patch_embed.forward_features(x)["x_norm_patchtokens"]
        C = patches.shape[-1]
        first = torch.cat([self.camera_token[:, :1], self.register_token[:, :1]], dim=2)  # [1,1,5,C]
        others = torch.cat([self.camera_token[:, 1:], self.register_token[:, 1:]], dim=2)
        special = torch.cat([first.expand(B, 1, -1, -1), others.expand(B, S - 1, -1, -1)], dim=1)
        tokens = torch.cat([special.reshape(B * S, -1, C).to(patches.dtype), patches], dim=1)
        Pt = tokens.shape[1]
        rope_frame = rope_global = None
        if self.rope is not None:
            gh, gw = H // self.patch_size, W // self.patch_size
            yy, xx = torch.meshgrid(torch.arange(gh, device=images.device), torch.arange(gw, device=images.device),
                                    indexing="ij")
            pos = torch.stack([yy.reshape(-1), xx.reshape(-1)], dim=-1) + 1
            pos = torch.cat([torch.zeros(self.patch_start_idx, 2, dtype=pos.dtype, device=pos.device), pos])
            head_dim = C // a.num_heads
            rope_frame = self.rope.tables(pos[None], head_dim, torch.float32)
            rope_global = self.rope.tables(pos.repeat(S, 1)[None], head_dim, torch.float32)
        keep = set(keep or ()) | {a.depth - 1}
        outputs: list[torch.Tensor | None] = [None] * a.depth
        fi = gi = 0
        for _ in range(a.depth // a.aa_block_size):
            frame_out: list[torch.Tensor] = []
            global_out: list[torch.Tensor] = []
            for kind in a.aa_order:
                if kind == "frame":
                    tokens = tokens.reshape(B * S, Pt, C)
                    for _ in range(a.aa_block_size):
                        tokens = self.frame_blocks[fi](tokens, rope=rope_frame)
                        fi += 1
                        frame_out.append(tokens.reshape(B, S, Pt, C))
                elif kind == "global":
                    tokens = tokens.reshape(B, S * Pt, C)
                    for _ in range(a.aa_block_size):
                        tokens = self.global_blocks[gi](tokens, rope=rope_global)
                        gi += 1
                        global_out.append(tokens.reshape(B, S, Pt, C))
                else:
                    raise ModelError(f"unknown attention type {kind!r} in aa_order")
            base = fi - a.aa_block_size
            for i, (f, g) in enumerate(zip(frame_out, global_out, strict=True)):
                if base + i in keep:
                    outputs[base + i] = torch.cat([f, g], dim=-1)
        return outputs


class VGGT(nn.Module):
    """Visual Geometry Grounded Transformer. Parameter names equal the official ``VGGT``."""

    def __init__(self, config: VggtConfig | None = None) -> None:
        super().__init__()
        c = self.config = config or VggtConfig()
        dim_in = c.head_dim_in
        for name, sub in (("camera_head", c.camera_head), ("dpt", c.dpt), ("track_head", c.track_head),
                          ("track feature extractor", c.track_head.feature_extractor)):
            if sub.dim_in not in (None, dim_in):
                raise ModelError(f"{name} dim_in {sub.dim_in} must be 2 x embed_dim = {dim_in}")
        self.aggregator = Aggregator(c)
        self.camera_head = CameraHead(c.camera_head, dim_in) if c.enable_camera else None
        self.point_head = DPTHead(c.dpt, dim_in, c.point_head) if c.enable_point else None
        self.depth_head = DPTHead(c.dpt, dim_in, c.depth_head) if c.enable_depth else None
        self.track_head = TrackHead(c.track_head, dim_in) if c.enable_track else None

    def _needed_layers(self, with_track: bool) -> set[int]:
        need = set(self.config.aggregator.cached_layer_indices)
        if self.depth_head is not None or self.point_head is not None:
            need |= set(self.config.dpt.intermediate_layer_idx)
        if with_track:
            need |= set(self.config.track_head.feature_extractor.intermediate_layer_idx)
        return need

    def forward(self, images: torch.Tensor, query_points: torch.Tensor | None = None,
                intermediates: dict[str, Any] | None = None) -> dict[str, Any]:
        """Run the network.

        Args:
            images: [S,3,H,W] or [B,S,3,H,W] float in [0,1]; H, W multiples of 14; frame 0 is the reference.
            query_points: optional [N,2] or [B,N,2] pixel (x, y) in frame 0 (track head only).
            intermediates: optional dict that receives ``aggregator`` (the token list) and, with tracks,
                ``track_feature_maps`` and ``track_list``.

        Returns:
            ``pose_enc`` [B,S,9], ``pose_enc_list`` (4 x [B,S,9]), ``depth`` [B,S,H,W,1], ``depth_conf``
            [B,S,H,W], ``world_points`` [B,S,H,W,3], ``world_points_conf`` [B,S,H,W], ``images`` (eval
            mode), and with query points and a track head ``track`` [B,S,N,2], ``vis`` / ``conf`` [B,S,N].
        """
        if images.ndim == 4:
            images = images.unsqueeze(0)
        if images.ndim != 5 or images.shape[2] != 3:
            raise ModelError(f"expected images [S,3,H,W] or [B,S,3,H,W], got {tuple(images.shape)}")
        H, W = images.shape[-2:]
        p = self.config.patch_size
        if H % p or W % p:
            raise ModelError(f"image size {H}x{W} is not a multiple of the patch size {p}")
        if query_points is not None and query_points.ndim == 2:
            query_points = query_points.unsqueeze(0)
        with_track = self.track_head is not None and query_points is not None
        tokens = self.aggregator(images, keep=self._needed_layers(with_track))
        if intermediates is not None:
            intermediates["aggregator"] = tokens
        psi = self.aggregator.patch_start_idx
        out: dict[str, Any] = {}
        # The camera / depth / point heads run in float32 even inside a mixed-precision autocast region.
        autocast_off = (torch.autocast(images.device.type, enabled=False)
                        if images.device.type in ("cuda", "cpu") else contextlib.nullcontext())
        with autocast_off:
            t32 = [t.float() if t is not None else None for t in tokens]
            if self.camera_head is not None:
                encs = self.camera_head(t32[-1])
                out["pose_enc"] = encs[-1]
                out["pose_enc_list"] = encs
            if self.depth_head is not None:
                out["depth"], out["depth_conf"] = self.depth_head(t32, (H, W), psi)
            if self.point_head is not None:
                out["world_points"], out["world_points_conf"] = self.point_head(t32, (H, W), psi)
        if with_track:
            fmaps: list[torch.Tensor] = []
            tracks, vis, conf = self.track_head(tokens, (H, W), psi, query_points, feature_maps_out=fmaps)
            out["track"], out["vis"], out["conf"] = tracks[-1], vis, conf
            if intermediates is not None:
                intermediates["track_feature_maps"] = fmaps[0]
                intermediates["track_list"] = tracks
        if not self.training:
            out["images"] = images
        return out


def build_vggt(config: Mapping[str, Any] | VggtConfig | None = None,
               device: str | torch.device | None = None) -> VGGT:
    """Build VGGT from the fixtures' nested ``config`` dictionary (``{}`` or None: VGGT-1B) or a
    :class:`VggtConfig`. Random weights; load a checkpoint with
    :func:`vggt_slam_pp.models.weights.load_vggt`. ``device="meta"`` allocates nothing."""
    if config is None or isinstance(config, Mapping):
        cfg = VggtConfig.from_dict(config or {})
    elif isinstance(config, VggtConfig):
        cfg = config
    else:
        raise ModelError(f"cannot build VGGT from {type(config).__name__}")
    with torch.device(device) if device is not None else contextlib.nullcontext():
        return VGGT(cfg)


__all__ = ["VGGT", "AggregatorConfig", "TrackerConfig", "VggtConfig", "build_vggt"]
