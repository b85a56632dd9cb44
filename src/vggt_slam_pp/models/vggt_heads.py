"""VGGT's camera head and DPT dense heads (depth, point map, track features).

Parameter names follow the official checkpoint (``camera_head.poseLN_modulation.1``,
``depth_head.scratch.refinenet1.resConfUnit1.conv1`` ...). Shapes: ``B`` scenes, ``S`` frames,
``P'`` = 5 special + P patch tokens, ``2C`` = channel width of the aggregator outputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from vggt_slam_pp.models.layers import Block, Mlp


@dataclass(frozen=True)
class CameraHeadConfig:
    dim_in: int | None = None  # None: 2 x the aggregator width
    trunk_depth: int = 4
    num_heads: int = 16
    mlp_ratio: float = 4.0
    init_values: float = 0.01
    pose_encoding_type: str = "absT_quaR_FoV"
    trans_act: str = "linear"
    quat_act: str = "linear"
    fl_act: str = "relu"
    num_iterations: int = 4


@dataclass(frozen=True)
class DptConfig:
    dim_in: int | None = None  # None: 2 x the aggregator width
    patch_size: int = 14
    features: int = 256
    out_channels: tuple[int, ...] = (256, 512, 1024, 1024)
    intermediate_layer_idx: tuple[int, ...] = (4, 11, 17, 23)
    pos_embed: bool = True
    down_ratio: int = 1
    head_features_2: int = 32
    frames_chunk_size: int = 8
    feature_only: bool = False


@dataclass(frozen=True)
class DenseOutputConfig:
    output_dim: int
    activation: str
    conf_activation: str = "expp1"


def _activate(x: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "linear":
        return x
    if kind == "relu":
        return F.relu(x)
    if kind == "exp":
        return torch.exp(x)
    if kind == "inv_log":
        return torch.sign(x) * torch.expm1(x.abs())
    if kind == "expp1":
        return 1 + torch.exp(x)
    if kind == "expp0":
        return torch.exp(x)
    if kind == "sigmoid":
        return torch.sigmoid(x)
    raise ValueError(f"unknown activation {kind!r}")


# ------------------------------------------------------------------------------------------------
# Camera head
# ------------------------------------------------------------------------------------------------
class CameraHead(nn.Module):
    """Iterative AdaLN-modulated trunk over the camera tokens -> list of pose encodings [B,S,9]."""

    def __init__(self, config: CameraHeadConfig, dim_in: int) -> None:
        super().__init__()
        if config.pose_encoding_type != "absT_quaR_FoV":
            raise ValueError(f"unsupported pose encoding {config.pose_encoding_type!r}")
        self.config = config
        target = 9
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, target))
        self.trunk = nn.Sequential(*[
            Block(dim_in, config.num_heads, config.mlp_ratio, init_values=config.init_values)
            for _ in range(config.trunk_depth)])
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.embed_pose = nn.Linear(target, dim_in)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, target)

    def forward(self, last_tokens: torch.Tensor, num_iterations: int | None = None) -> list[torch.Tensor]:
        """``last_tokens`` [B,S,P',2C] (last aggregator output) -> ``num_iterations`` x [B,S,9]."""
        c = self.config
        tokens = self.token_norm(last_tokens[:, :, 0])
        B, S, _ = tokens.shape
        normed = self.adaln_norm(tokens)
        enc: torch.Tensor | None = None
        out = []
        for _ in range(num_iterations or c.num_iterations):
            cond = self.embed_pose(self.empty_pose_tokens.expand(B, S, -1) if enc is None else enc.detach())
            shift, scale, gate = self.poseLN_modulation(cond).chunk(3, dim=-1)
            m = gate * (normed * (1 + scale) + shift) + tokens
            delta = self.pose_branch(self.trunk_norm(self.trunk(m)))
            enc = delta if enc is None else enc + delta
            out.append(torch.cat([_activate(enc[..., :3], c.trans_act), _activate(enc[..., 3:7], c.quat_act),
                                  _activate(enc[..., 7:], c.fl_act)], dim=-1))
        return out


# ------------------------------------------------------------------------------------------------
# DPT
# ------------------------------------------------------------------------------------------------
class ResidualConvUnit(nn.Module):
    """``ReLU(x) + conv2(ReLU(conv1(ReLU(x))))``: the reference's in-place ReLU makes the skip ReLU(x)."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(x)
        return x + self.conv2(F.relu(self.conv1(x)))


class FusionBlock(nn.Module):
    """``out_conv(resize(RCU2(x_main + RCU1(x_skip))))`` with bilinear align_corners=True resizing."""

    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.has_residual = has_residual
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None,
                size: Sequence[int] | None = None) -> torch.Tensor:
        if self.has_residual and skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=True)
        return self.out_conv(x)


class _Scratch(nn.Module):
    def __init__(self, in_channels: Sequence[int], features: int, feature_only: bool, out2: int,
                 output_dim: int) -> None:
        super().__init__()
        for i, ch in enumerate(in_channels, start=1):
            setattr(self, f"layer{i}_rn", nn.Conv2d(ch, features, 3, padding=1, bias=False))
        self.refinenet1 = FusionBlock(features)
        self.refinenet2 = FusionBlock(features)
        self.refinenet3 = FusionBlock(features)
        self.refinenet4 = FusionBlock(features, has_residual=False)
        if feature_only:
            self.output_conv1 = nn.Conv2d(features, features, 3, padding=1)
        else:
            self.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
            self.output_conv2 = nn.Sequential(nn.Conv2d(features // 2, out2, 3, padding=1), nn.ReLU(),
                                              nn.Conv2d(out2, output_dim, 1))


def uv_position_embedding(height: int, width: int, aspect: float, channels: int,
                          device: torch.device | None = None) -> torch.Tensor:
    """Sinusoidal UV embedding [channels, height, width] of a map for an image of aspect W/H.

    u spans ±(a/d)(w-1)/w, v spans ±(1/d)(h-1)/h with d = sqrt(a²+1); first half of the channels
    encodes u, second half v, each as [sin(p w_k), cos(p w_k)], w_k = 100^(-k/(channels/4)).
    """
    d = (aspect ** 2 + 1.0) ** 0.5
    sx, sy = aspect / d, 1.0 / d
    u = torch.linspace(-sx * (width - 1) / width, sx * (width - 1) / width, width, device=device)
    v = torch.linspace(-sy * (height - 1) / height, sy * (height - 1) / height, height, device=device)
    quarter = channels // 4
    omega = 1.0 / 100.0 ** (torch.arange(quarter, dtype=torch.float64, device=device) / quarter)

    def enc(p: torch.Tensor) -> torch.Tensor:
        a = p.double()[:, None] * omega
        return torch.cat([a.sin(), a.cos()], dim=1).float()  # [n, channels/2]

    eu = enc(u)[None, :, :].expand(height, width, -1)
    ev = enc(v)[:, None, :].expand(height, width, -1)
    return torch.cat([eu, ev], dim=-1).permute(2, 0, 1)


class DPTHead(nn.Module):
    """Dense prediction head over 4 aggregator outputs -> (values [B,S,H,W,D-1], conf [B,S,H,W]),
    or a feature map [B,S,F,H/r,W/r] when ``feature_only``. Frames are processed in chunks."""

    def __init__(self, config: DptConfig, dim_in: int, output: DenseOutputConfig | None = None) -> None:
        super().__init__()
        if not config.feature_only and output is None:
            raise ValueError("a DPT head that is not feature_only needs an output config")
        self.config = config
        self.output = output
        oc = config.out_channels
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, c, 1) for c in oc)
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(oc[0], oc[0], kernel_size=4, stride=4),
            nn.ConvTranspose2d(oc[1], oc[1], kernel_size=2, stride=2),
            nn.Identity(),
            nn.Conv2d(oc[3], oc[3], kernel_size=3, stride=2, padding=1)])
        self.scratch = _Scratch(oc, config.features, config.feature_only, config.head_features_2,
                                output.output_dim if output else 0)

    def _pos(self, x: torch.Tensor, aspect: float) -> torch.Tensor:
        emb = uv_position_embedding(x.shape[-2], x.shape[-1], aspect, x.shape[1], device=x.device)
        return x + 0.1 * emb.to(x.dtype)[None]

    def forward(self, tokens: Sequence[torch.Tensor | None], image_hw: tuple[int, int], patch_start_idx: int,
                frames_chunk_size: int | None = None):
        first = tokens[self.config.intermediate_layer_idx[0]]
        S = first.shape[1]
        chunk = frames_chunk_size if frames_chunk_size is not None else self.config.frames_chunk_size
        if not chunk or chunk >= S:
            return self._forward_frames(tokens, image_hw, patch_start_idx, 0, S)
        parts = [self._forward_frames(tokens, image_hw, patch_start_idx, s, min(s + chunk, S))
                 for s in range(0, S, chunk)]
        if self.config.feature_only:
            return torch.cat(parts, dim=1)
        return torch.cat([p[0] for p in parts], dim=1), torch.cat([p[1] for p in parts], dim=1)

    def _forward_frames(self, tokens, image_hw, patch_start_idx, s0, s1):
        c = self.config
        H, W = image_hw
        ph, pw = H // c.patch_size, W // c.patch_size
        aspect = W / H
        feats = []
        for j, layer in enumerate(c.intermediate_layer_idx):
            x = tokens[layer][:, s0:s1, patch_start_idx:]
            B, S = x.shape[:2]
            x = self.norm(x.reshape(B * S, -1, x.shape[-1]))
            x = x.permute(0, 2, 1).reshape(B * S, -1, ph, pw)
            x = self.projects[j](x)
            if c.pos_embed:
                x = self._pos(x, aspect)
            feats.append(self.resize_layers[j](x))
        sc = self.scratch
        l1, l2, l3, l4 = (getattr(sc, f"layer{i}_rn")(f) for i, f in enumerate(feats, start=1))
        out = sc.refinenet4(l4, size=l3.shape[2:])
        out = sc.refinenet3(out, l3, size=l2.shape[2:])
        out = sc.refinenet2(out, l2, size=l1.shape[2:])
        out = sc.refinenet1(out, l1)
        out = sc.output_conv1(out)
        size = (int(ph * c.patch_size / c.down_ratio), int(pw * c.patch_size / c.down_ratio))
        out = F.interpolate(out, size=size, mode="bilinear", align_corners=True)
        if c.pos_embed:
            out = self._pos(out, aspect)
        if c.feature_only:
            return out.reshape(B, S, *out.shape[1:])
        out = sc.output_conv2(out).permute(0, 2, 3, 1)
        values = _activate(out[..., :-1], self.output.activation)
        conf = _activate(out[..., -1], self.output.conf_activation)
        return values.reshape(B, S, *values.shape[1:]), conf.reshape(B, S, *conf.shape[1:])
