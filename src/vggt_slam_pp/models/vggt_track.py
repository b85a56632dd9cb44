"""VGGT's track head: a DPT feature extractor and an iterative correlation tracker.

The tracker follows the CoTracker / VGGSfM design as the reference configures it: a correlation
pyramid sampled on a (2r+1)² grid around each track, a motion embedding, an update transformer that
alternates attention over time with virtual-track mediated attention over space, and feature updates.
Parameter names follow the official checkpoint (``track_head.tracker.updateformer.time_blocks.0`` ...).

Shapes: ``B`` scenes, ``S`` frames, ``N`` query points, ``C`` feature channels, feature maps at
half the input resolution (``stride`` 2). Query points are pixels (x, y) of frame 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from vggt_slam_pp.models.layers import Mlp
from vggt_slam_pp.models.vggt_heads import DptConfig, DPTHead


@dataclass(frozen=True)
class TrackerConfig:
    latent_dim: int = 128
    depth: int = 6
    use_spaceatt: bool = True
    max_scale: int = 518
    updateformer_num_heads: int = 8
    num_virtual_tracks: int = 64
    mlp_ratio: float = 4.0


@dataclass(frozen=True)
class TrackHeadConfig:
    dim_in: int | None = None  # None: 2 x the aggregator width
    patch_size: int = 14
    features: int = 128
    iters: int = 4
    predict_conf: bool = True
    stride: int = 2
    corr_levels: int = 7
    corr_radius: int = 4
    hidden_size: int = 384
    feature_extractor: DptConfig = field(default_factory=lambda: DptConfig(
        features=128, feature_only=True, down_ratio=2, pos_embed=False))
    tracker: TrackerConfig = field(default_factory=TrackerConfig)


def bilinear_sample(maps: torch.Tensor, xy: torch.Tensor, padding_mode: str = "border") -> torch.Tensor:
    """Sample ``maps`` [B,C,H,W] at pixel coordinates ``xy`` [B,...,2] (x, y; align_corners=True)
    -> [B,C,...]."""
    H, W = maps.shape[-2:]
    scale = torch.tensor([2 / max(W - 1, 1), 2 / max(H - 1, 1)], device=xy.device, dtype=xy.dtype)
    grid = xy * scale - 1
    shape = grid.shape
    grid = grid.reshape(shape[0], -1, 1, 2) if grid.ndim != 4 else grid
    out = F.grid_sample(maps, grid, align_corners=True, padding_mode=padding_mode)
    return out.reshape(maps.shape[0], maps.shape[1], *shape[1:-1])


def sincos_1d(pos: torch.Tensor, channels: int, base: float) -> torch.Tensor:
    """[sin(p w_k), cos(p w_k)] with w_k = base^(-k/(channels/2)), float64 -> float32: [n, channels]."""
    half = channels // 2
    omega = 1.0 / base ** (torch.arange(half, dtype=torch.float64, device=pos.device) / half)
    a = pos.reshape(-1).double()[:, None] * omega
    return torch.cat([a.sin(), a.cos()], dim=1).float()


def sincos_2d_grid(channels: int, height: int, width: int, device=None) -> torch.Tensor:
    """2-D sin-cos table [1, channels, height, width]: first half encodes the column x, second the row y."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32, device=device),
                            torch.arange(width, dtype=torch.float32, device=device), indexing="ij")
    emb = torch.cat([sincos_1d(xs, channels // 2, 10000.0), sincos_1d(ys, channels // 2, 10000.0)], dim=1)
    return emb.reshape(height, width, channels).permute(2, 0, 1)[None]


def motion_embedding(m: torch.Tensor, channels: int) -> torch.Tensor:
    """[..., 2] motions -> [..., 2*channels]: per axis interleaved (sin, cos) pairs with frequencies
    2k*1000/channels, k = 0..channels/2-1; x block first, then y."""
    freq = torch.arange(0, channels, 2, device=m.device, dtype=torch.float32) * (1000.0 / channels)
    out = []
    for axis in (0, 1):
        a = m[..., axis:axis + 1].float() * freq
        out.append(torch.stack([a.sin(), a.cos()], dim=-1).flatten(-2))
    return torch.cat(out, dim=-1)


class AttnBlock(nn.Module):
    """``x = LN1(x); x += MHA(x, x, x); x += MLP(LN2(x))`` (the residual starts from the normalised x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x)
        x = x + self.attn(x, x, x, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class CrossAttnBlock(nn.Module):
    """``x = LN1(x); c = LNc(c); x += MHA(x, c, c); x += MLP(LN2(x))``."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x)
        context = self.norm_context(context)
        x = x + self.cross_attn(x, context, context, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class UpdateFormer(nn.Module):
    """Time attention per track; space attention through virtual tracks. [B,N,S,Din] -> [B,N,S,Dout]."""

    def __init__(self, depth: int, input_dim: int, hidden: int, heads: int, output_dim: int,
                 mlp_ratio: float, space: bool, num_virtual: int) -> None:
        super().__init__()
        self.num_virtual = num_virtual if space else 0
        self.virual_tracks = nn.Parameter(torch.zeros(1, num_virtual, 1, hidden)) if space else None
        self.input_norm = nn.LayerNorm(input_dim)
        self.input_transform = nn.Linear(input_dim, hidden)
        self.output_norm = nn.LayerNorm(hidden)
        self.flow_head = nn.Linear(hidden, output_dim)
        self.time_blocks = nn.ModuleList(AttnBlock(hidden, heads, mlp_ratio) for _ in range(depth))
        if space:
            self.space_virtual_blocks = nn.ModuleList(AttnBlock(hidden, heads, mlp_ratio) for _ in range(depth))
            self.space_point2virtual_blocks = nn.ModuleList(
                CrossAttnBlock(hidden, heads, mlp_ratio) for _ in range(depth))
            self.space_virtual2point_blocks = nn.ModuleList(
                CrossAttnBlock(hidden, heads, mlp_ratio) for _ in range(depth))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        tokens = self.input_transform(self.input_norm(x))
        init = tokens
        B, _, T, _ = tokens.shape
        if self.virual_tracks is not None:
            tokens = torch.cat([tokens, self.virual_tracks.repeat(B, 1, T, 1)], dim=1)
        N = tokens.shape[1]
        nv = self.num_virtual
        n_space = len(self.space_virtual_blocks) if self.virual_tracks is not None else 0
        j = 0
        for i, blk in enumerate(self.time_blocks):
            tokens = blk(tokens.reshape(B * N, T, -1)).reshape(B, N, T, -1)
            if n_space and i % (len(self.time_blocks) // n_space) == 0:
                space = tokens.permute(0, 2, 1, 3).reshape(B * T, N, -1)
                points, virtual = space[:, :N - nv], space[:, N - nv:]
                virtual = self.space_virtual2point_blocks[j](virtual, points)
                virtual = self.space_virtual_blocks[j](virtual)
                points = self.space_point2virtual_blocks[j](points, virtual)
                tokens = torch.cat([points, virtual], dim=1).reshape(B, T, N, -1).permute(0, 2, 1, 3)
                j += 1
        tokens = tokens[:, :N - nv] + init
        return self.flow_head(self.output_norm(tokens))


class Tracker(nn.Module):
    """Iterative point tracker over feature maps [B,S,C,h,w] (C = latent_dim)."""

    def __init__(self, config: TrackHeadConfig) -> None:
        super().__init__()
        t = config.tracker
        self.config = config
        C = t.latent_dim
        self.transformer_dim = 3 * C + 4
        self.query_ref_token = nn.Parameter(torch.zeros(1, 2, self.transformer_dim))
        self.corr_mlp = Mlp(config.corr_levels * (2 * config.corr_radius + 1) ** 2, config.hidden_size, C)
        self.updateformer = UpdateFormer(t.depth, self.transformer_dim, config.hidden_size,
                                         t.updateformer_num_heads, C + 2, t.mlp_ratio, t.use_spaceatt,
                                         t.num_virtual_tracks)
        self.fmap_norm = nn.LayerNorm(C)
        self.ffeat_norm = nn.GroupNorm(1, C)
        self.ffeat_updater = nn.Sequential(nn.Linear(C, C), nn.GELU())
        self.vis_predictor = nn.Sequential(nn.Linear(C, 1))
        if config.predict_conf:
            self.conf_predictor = nn.Sequential(nn.Linear(C, 1))

    def _correlation(self, pyramid: list[torch.Tensor], feats: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """feats [B,S,N,C], coords [B,S,N,2] -> [B,S,N,levels*(2r+1)^2]."""
        B, S, N, C = feats.shape
        r = self.config.corr_radius
        d = torch.arange(-r, r + 1, device=coords.device, dtype=coords.dtype)
        # first grid axis offsets x, second offsets y (reference layout)
        delta = torch.stack(torch.meshgrid(d, d, indexing="ij"), dim=-1).reshape(1, 2 * r + 1, 2 * r + 1, 2)
        out = []
        for level, fmaps in enumerate(pyramid):
            h, w = fmaps.shape[-2:]
            corr = torch.matmul(feats, fmaps.reshape(B, S, C, h * w)) / C ** 0.5
            corr = corr.reshape(B * S * N, 1, h, w)
            centre = coords.reshape(B * S * N, 1, 1, 2) / 2 ** level
            sampled = bilinear_sample(corr, centre + delta, padding_mode="zeros")
            out.append(sampled.reshape(B, S, N, -1))
        return torch.cat(out, dim=-1)

    def forward(self, query_points: torch.Tensor, fmaps: torch.Tensor, iters: int):
        """query_points [B,N,2] (pixels), fmaps [B,S,C,h,w] -> (list of [B,S,N,2], vis [B,S,N], conf)."""
        cfg = self.config
        B, N, _ = query_points.shape
        _, S, C, h, w = fmaps.shape
        fmaps = self.fmap_norm(fmaps.permute(0, 1, 3, 4, 2)).permute(0, 1, 4, 2, 3)
        q = query_points / float(cfg.stride)
        coords = q.reshape(B, 1, N, 2).repeat(1, S, 1, 1)
        query_feats = bilinear_sample(fmaps[:, 0], q).permute(0, 2, 1)  # [B,N,C]
        feats = query_feats[:, None].repeat(1, S, 1, 1)  # [B,S,N,C]
        pyramid = [fmaps]
        for _ in range(cfg.corr_levels - 1):
            f = pyramid[-1]
            f = F.avg_pool2d(f.reshape(B * S, C, *f.shape[-2:]), kernel_size=2, stride=2)
            pyramid.append(f.reshape(B, S, C, *f.shape[-2:]))
        pos_table = sincos_2d_grid(self.transformer_dim, h, w, device=fmaps.device).expand(B, -1, -1, -1)
        pos = bilinear_sample(pos_table, q).permute(0, 2, 1).reshape(B * N, 1, -1)
        ref = torch.cat([self.query_ref_token[:, :1], self.query_ref_token[:, 1:2].expand(-1, S - 1, -1)], dim=1)
        max_scale = float(cfg.tracker.max_scale)
        preds = []
        for _ in range(iters):
            coords = coords.detach()
            corr = self._correlation(pyramid, feats, coords)
            corr = self.corr_mlp(corr.permute(0, 2, 1, 3).reshape(B * N, S, -1))
            flows = (coords - coords[:, :1]).permute(0, 2, 1, 3).reshape(B * N, S, 2)
            flow_emb = torch.cat([motion_embedding(flows, C // 2), flows / max_scale, flows / max_scale], dim=-1)
            feats_ = feats.permute(0, 2, 1, 3).reshape(B * N, S, C)
            x = torch.cat([flow_emb, corr, feats_], dim=2) + pos
            x = (x + ref.to(x.dtype)).reshape(B, N, S, -1)
            delta = self.updateformer(x).reshape(B * N, S, -1)
            dfeat = delta[:, :, 2:].reshape(B * N * S, C)
            feats_ = self.ffeat_updater(self.ffeat_norm(dfeat)) + feats_.reshape(B * N * S, C)
            feats = feats_.reshape(B, N, S, C).permute(0, 2, 1, 3)
            coords = coords + delta[:, :, :2].reshape(B, N, S, 2).permute(0, 2, 1, 3)
            coords[:, 0] = q
            preds.append(coords * cfg.stride)
        flat = feats.reshape(B * S * N, C)
        vis = torch.sigmoid(self.vis_predictor(flat).reshape(B, S, N))
        conf = torch.sigmoid(self.conf_predictor(flat).reshape(B, S, N)) if cfg.predict_conf else None
        return preds, vis, conf


class TrackHead(nn.Module):
    """Feature extractor (DPT, feature_only, down_ratio 2, no pos-embed) + :class:`Tracker`."""

    def __init__(self, config: TrackHeadConfig, dim_in: int) -> None:
        super().__init__()
        self.config = config
        self.feature_extractor = DPTHead(config.feature_extractor, dim_in)
        self.tracker = Tracker(config)

    def forward(self, tokens, image_hw: tuple[int, int], patch_start_idx: int, query_points: torch.Tensor,
                iters: int | None = None, feature_maps_out: list | None = None):
        fmaps = self.feature_extractor(tokens, image_hw, patch_start_idx)
        if feature_maps_out is not None:
            feature_maps_out.append(fmaps)
        return self.tracker(query_points, fmaps, iters or self.config.iters)
