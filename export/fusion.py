"""Fusion network (paper 3.1.1-3.1.2): RGB and depth ResNet18+PSP branches, concatenation (eq. 1) and
multi-head self-attention over spatial locations (eqs. 2-3).

Attention runs on the fused map average-pooled to stride `attention_stride` (with a learned position
embedding, since attention alone is blind to where a location is), its output is upsampled bilinearly
and added back to the fused map (residual). Full-resolution attention over a 120x120 crop (14400
tokens) would cost ~53 GFLOP and a 14400^2 score matrix per head and pallet; stride 4 (900 tokens)
costs ~0.2 GFLOP.

Two graphs:

- `FusionNet` (``sample_stride`` 0): rgb (B, 3, h, w) normalised RGB, depth (B, 1, h, w) encoded depth ->
  features (B, 2*branch_dim, h, w), the dense map at crop resolution; the runtime gathers the N chosen pixels.
- `SampledFusionNet` (``sample_stride`` 8 or 4): rgb, depth and choose (B, N) int64 flat pixel indices
  ``row * w + col`` into the crop -> features (B, N, 2*branch_dim): the fused map stays at stride 8 (or a
  light stride-4 decoder) and is sampled bilinearly at the chosen pixels inside the graph, so no
  full-resolution map is ever computed for the few hundred pixels the pose network reads.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import MultiHeadSelfAttention
from .config import FusionConfig
from .resnet_psp import PSPNet

__all__ = ["FusionNet", "SampledFusionNet", "build_fusion", "sample_bilinear"]


class FusionNet(nn.Module):
    def __init__(self, cfg: FusionConfig) -> None:
        super().__init__()
        if cfg.sampled:
            raise ValueError("FusionNet makes the dense map; a config with sample_stride needs SampledFusionNet")
        self.cfg = cfg

        def branch(c_in: int) -> PSPNet:
            return PSPNet(c_in, cfg.crop_hw, cfg.resnet_widths, cfg.psp_sizes, cfg.psp_out, cfg.up_channels,
                          cfg.branch_dim, cfg.dilated, project_layer4=cfg.project_layer4)

        self.rgb = branch(3)
        self.depth = branch(1)
        self.attention = None
        if cfg.attention:
            s = cfg.attention_stride
            n_tokens = (cfg.crop_hw[0] // s) * (cfg.crop_hw[1] // s)
            self.attention = MultiHeadSelfAttention(cfg.feature_dim, cfg.attention_heads)
            self.pos = nn.Parameter(torch.zeros(1, n_tokens, cfg.feature_dim))
            nn.init.trunc_normal_(self.pos, std=0.02)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """:param rgb: (B, 3, h, w). :param depth: (B, 1, h, w). :return: (B, feature_dim, h, w)."""
        fused = torch.cat((self.rgb(rgb), self.depth(depth)), 1)          # eq. 1, per location
        if self.attention is None:
            return fused
        return _attend(fused, self.attention, self.pos, self.cfg.attention_stride, self.cfg.crop_hw)


def _attend(fused: torch.Tensor, attention: MultiHeadSelfAttention, pos: torch.Tensor, s: int,
            map_hw: tuple[int, int]) -> torch.Tensor:
    """Residual self-attention over `fused` (B, d, h, w) pooled by `s`, with position embedding `pos`.

    :param map_hw: (h, w) as Python ints, so the exported reshapes have static sizes (and B may be 0)."""
    b, d = fused.shape[0], pos.shape[2]
    pooled = F.avg_pool2d(fused, s, s) if s > 1 else fused
    hs, ws = map_hw[0] // s, map_hw[1] // s
    tokens = pooled.reshape(b, d, hs * ws).transpose(1, 2) + pos            # (B, hs*ws, d); no -1: B may be 0
    att = attention(tokens).transpose(1, 2).reshape(b, d, hs, ws)
    if s > 1:
        att = F.interpolate(att, scale_factor=float(s), mode="bilinear", align_corners=False)
    return fused + att


def sample_bilinear(fmap: torch.Tensor, choose: torch.Tensor, crop_hw: tuple[int, int], stride: int) -> torch.Tensor:
    """Features of a stride-`stride` map at crop pixels, bilinear with half-pixel centres (what upsampling
    the map by `stride` with ``F.interpolate(mode="bilinear", align_corners=False)`` and gathering gives).

    :param fmap: (B, C, hs, ws) map of a (hs*stride, ws*stride) = `crop_hw` crop.
    :param choose: (B, N) int64 flat crop pixel indices ``row * crop_w + col``.
    :param crop_hw: Python ints, so that the exported graph's shapes are static but for B (which may be 0).
    :return: (B, N, C).
    """
    b, c = fmap.shape[0], fmap.shape[1]
    crop_w = crop_hw[1]
    hs, ws = crop_hw[0] // stride, crop_hw[1] // stride
    row = torch.div(choose, crop_w, rounding_mode="floor")
    col = choose - row * crop_w
    # source coordinate of the pixel centre in map cells; clamped at the borders like F.interpolate
    y = ((row.to(fmap.dtype) + 0.5) / stride - 0.5).clamp(0.0, hs - 1.0)
    x = ((col.to(fmap.dtype) + 0.5) / stride - 0.5).clamp(0.0, ws - 1.0)
    y0, x0 = y.floor(), x.floor()
    wy, wx = (y - y0)[:, None], (x - x0)[:, None]                             # (B, 1, N)
    y0i, x0i = y0.long(), x0.long()
    y1i, x1i = (y0i + 1).clamp(max=hs - 1), (x0i + 1).clamp(max=ws - 1)
    flat = fmap.reshape(b, c, hs * ws)

    def at(yi: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
        return torch.gather(flat, 2, (yi * ws + xi)[:, None, :].expand(-1, c, -1))   # (B, C, N)

    top = at(y0i, x0i) * (1 - wx) + at(y0i, x1i) * wx
    bottom = at(y1i, x0i) * (1 - wx) + at(y1i, x1i) * wx
    return (top * (1 - wy) + bottom * wy).transpose(1, 2)


class _Stride4Decoder(nn.Module):
    """Light decoder: stride-8 features upsampled x2, plus a 1x1 projection of layer1 (stride 4), then a 3x3 conv."""

    def __init__(self, skip_channels: int, dim: int) -> None:
        super().__init__()
        self.skip = nn.Conv2d(skip_channels, dim, 1)
        self.conv = nn.Sequential(nn.ReLU(inplace=True), nn.Conv2d(dim, dim, 3, padding=1))

    def forward(self, s8: torch.Tensor, s4: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(s8, scale_factor=2.0, mode="bilinear", align_corners=False)
        return self.conv(up + self.skip(s4))


class SampledFusionNet(nn.Module):
    """Two ResNet18+PSP branches to stride 8, concatenation (eq. 1), self-attention over the stride-8 tokens
    (eqs. 2-3), then the fused features at the chosen pixels (bilinear from the stride-8 map, or from the
    stride-4 decoder's). Module names follow `FusionNet` where the weights are the same (backbones, PSP)."""

    def __init__(self, cfg: FusionConfig) -> None:
        super().__init__()
        if not cfg.sampled:
            raise ValueError("SampledFusionNet needs a config with sample_stride 8 or 4")
        self.cfg = cfg
        self.map_hw = (cfg.crop_hw[0] // 8, cfg.crop_hw[1] // 8)

        def branch(c_in: int) -> PSPNet:
            return PSPNet(c_in, cfg.crop_hw, cfg.resnet_widths, cfg.psp_sizes, cfg.psp_out, (), cfg.branch_dim,
                          cfg.dilated, with_stride4=cfg.sample_stride == 4, project_layer4=cfg.project_layer4)

        self.rgb = branch(3)
        self.depth = branch(1)
        self.decoder = None
        if cfg.sample_stride == 4:
            self.decoder = nn.ModuleList(_Stride4Decoder(cfg.resnet_widths[0], cfg.branch_dim) for _ in range(2))
        self.attention = None
        if cfg.attention:
            n_tokens = (cfg.crop_hw[0] // 8) * (cfg.crop_hw[1] // 8)
            self.attention = MultiHeadSelfAttention(cfg.feature_dim, cfg.attention_heads)
            self.pos = nn.Parameter(torch.zeros(1, n_tokens, cfg.feature_dim))
            nn.init.trunc_normal_(self.pos, std=0.02)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor, choose: torch.Tensor) -> torch.Tensor:
        """:param rgb: (B, 3, h, w). :param depth: (B, 1, h, w). :param choose: (B, N) int64 row * w + col.
        :return: (B, N, feature_dim)."""
        f_rgb, f_d = self.rgb(rgb), self.depth(depth)     # (B, branch_dim, h/8, w/8), or with layer1's map
        if self.decoder is not None:
            (f_rgb, s4_rgb), (f_d, s4_d) = f_rgb, f_d
        fused = torch.cat((f_rgb, f_d), 1)                                  # eq. 1, per stride-8 location
        if self.attention is not None:
            fused = _attend(fused, self.attention, self.pos, 1, self.map_hw)
        if self.decoder is None:
            return sample_bilinear(fused, choose, self.cfg.crop_hw, 8)
        d = self.cfg.branch_dim
        fine = torch.cat((self.decoder[0](fused[:, :d], s4_rgb), self.decoder[1](fused[:, d:], s4_d)), 1)
        return sample_bilinear(fine, choose, self.cfg.crop_hw, 4)


def build_fusion(cfg: FusionConfig) -> FusionNet | SampledFusionNet:
    """The fusion network for `cfg` (random weights)."""
    return SampledFusionNet(cfg) if cfg.sampled else FusionNet(cfg)
