"""Fusion network (paper 3.1.1-3.1.2): RGB and depth ResNet18+PSP branches, concatenation (eq. 1) and
multi-head self-attention over spatial locations (eqs. 2-3).

Attention runs on the fused map average-pooled by `attention_stride` (with a learned position
embedding, since attention alone is blind to where a location is), its output is upsampled bilinearly
and added back to the fused map (residual). Full-resolution attention over a 120x120 crop (14400
tokens) would cost ~53 GFLOP and a 14400^2 score matrix per head and pallet; stride 4 (900 tokens)
costs ~0.2 GFLOP.

Graph: rgb (B, 3, h, w) normalised RGB, depth (B, 1, h, w) encoded depth -> features (B, 2*branch_dim, h, w).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import MultiHeadSelfAttention
from .config import FusionConfig
from .resnet_psp import PSPNet

__all__ = ["FusionNet", "build_fusion"]


class FusionNet(nn.Module):
    def __init__(self, cfg: FusionConfig) -> None:
        super().__init__()
        self.cfg = cfg

        def branch(c_in: int) -> PSPNet:
            return PSPNet(c_in, cfg.crop_hw, cfg.resnet_widths, cfg.psp_sizes, cfg.psp_out, cfg.up_channels,
                          cfg.branch_dim)

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
        s = self.cfg.attention_stride
        b, d, h, w = fused.shape
        pooled = F.avg_pool2d(fused, s, s) if s > 1 else fused
        hs, ws = h // s, w // s
        tokens = pooled.flatten(2).transpose(1, 2) + self.pos               # (B, hs*ws, d)
        att = self.attention(tokens).transpose(1, 2).reshape(b, d, hs, ws)
        if s > 1:
            att = F.interpolate(att, scale_factor=float(s), mode="bilinear", align_corners=False)
        return fused + att


def build_fusion(cfg: FusionConfig) -> FusionNet:
    """The fusion network for `cfg` (random weights)."""
    return FusionNet(cfg)
