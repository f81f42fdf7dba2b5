"""Pose network (paper 3.1.3-3.1.5): DenseFusion's PoseNetFeat + PoseNet heads, with multi-head
self-attention over the per-point geometric features.

Per point: geometric features from a PointNet-like MLP on the (centred) point, fused features gathered
from the fusion map at the point's pixel; both at two depths are concatenated with a global feature
(MLP + average over points) = the dense per-point feature; three per-point heads predict a unit
quaternion (w, x, y, z), a translation offset from the point, and a confidence in (0, 1).

Graph: points (B, N, 3) metres, centred; features (B, N, C) -> quat (B, N, 4), trans (B, N, 3), conf (B, N).
The object's translation from point i is points[i] + trans[i] (+ the centre the runtime subtracted).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import MultiHeadSelfAttention
from .config import PoseConfig

__all__ = ["PoseNet", "build_pose"]


def _head(c_in: int, dims: tuple[int, int, int], c_out: int) -> nn.Sequential:
    d1, d2, d3 = dims
    return nn.Sequential(nn.Conv1d(c_in, d1, 1), nn.ReLU(inplace=True), nn.Conv1d(d1, d2, 1), nn.ReLU(inplace=True),
                         nn.Conv1d(d2, d3, 1), nn.ReLU(inplace=True), nn.Conv1d(d3, c_out, 1))


class PoseNet(nn.Module):
    def __init__(self, cfg: PoseConfig, feature_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        p1, p2 = cfg.point_dims
        g1, g2 = cfg.global_dims
        self.conv1, self.conv2 = nn.Conv1d(3, p1, 1), nn.Conv1d(p1, p2, 1)
        self.e_conv1, self.e_conv2 = nn.Conv1d(feature_dim, p1, 1), nn.Conv1d(p1, p2, 1)
        self.conv5, self.conv6 = nn.Conv1d(2 * p2, g1, 1), nn.Conv1d(g1, g2, 1)
        self.attention = MultiHeadSelfAttention(p2, cfg.attention_heads) if cfg.attention else None
        dense = 2 * p1 + 2 * p2 + g2
        self.head_r = _head(dense, cfg.head_dims, 4)
        self.head_t = _head(dense, cfg.head_dims, 3)
        self.head_c = _head(dense, cfg.head_dims, 1)

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:param points: (B, N, 3). :param features: (B, N, C).
        :return: quat (B, N, 4) unit wxyz, trans (B, N, 3) metres, conf (B, N)."""
        x = F.relu(self.conv1(points.transpose(1, 2)))
        e = F.relu(self.e_conv1(features.transpose(1, 2)))
        pf1 = torch.cat((x, e), 1)
        x = F.relu(self.conv2(x))
        if self.attention is not None:
            x = x + self.attention(x.transpose(1, 2)).transpose(1, 2)
        e = F.relu(self.e_conv2(e))
        pf2 = torch.cat((x, e), 1)
        g = F.relu(self.conv6(F.relu(self.conv5(pf2))))
        g = g.mean(2, keepdim=True).expand(-1, -1, pf2.shape[2])
        dense = torch.cat((pf1, pf2, g), 1)
        quat = F.normalize(self.head_r(dense), dim=1, eps=1e-8).transpose(1, 2)
        trans = self.head_t(dense).transpose(1, 2)
        conf = torch.sigmoid(self.head_c(dense))[:, 0]
        return quat, trans, conf


def build_pose(cfg: PoseConfig, feature_dim: int) -> PoseNet:
    """The pose network for `cfg`, reading `feature_dim` fused features per point (random weights)."""
    return PoseNet(cfg, feature_dim)
