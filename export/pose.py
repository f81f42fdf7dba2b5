"""Pose network (paper 3.1.3-3.1.5): DenseFusion's PoseNetFeat + PoseNet heads, with multi-head
self-attention over the per-point geometric features.

Per point: geometric features from a PointNet-like MLP on the (centred) point, fused features gathered
from the fusion map at the point's pixel; both at two depths are concatenated with a global feature
(MLP + average over points) = the dense per-point feature; three per-point heads predict a unit
quaternion (w, x, y, z), a translation offset from the point, and a confidence in (0, 1).

Graph: points (B, N, 3) metres, centred; features (B, N, C) -> quat (B, N, 4), trans (B, N, 3), conf (B, N).
The object's translation from point i is points[i] + trans[i] (+ the centre the runtime subtracted).

The shipped graph (`MostConfidentPose`, the same weights) keeps only what the runtime uses, DenseFusion's most
confident hypothesis: it runs the confidence head at every point and the rotation and translation heads at the
chosen point alone -> quat (B, 4), trans (B, 3) = that point + its offset, conf (B,). With a verifier head
(`PoseConfig.verifier`) the graph's conf is the verifier's at the chosen point; the confidence head still chooses.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import MultiHeadSelfAttention
from .config import PoseConfig

__all__ = ["MostConfidentPose", "PoseNet", "SplitInputConv1d", "build_pose"]


class SplitInputConv1d(nn.Conv1d):
    """A 1x1 convolution over `[per-point features; one global feature repeated at every point]`, computed without
    the repeat: the global columns of the weight meet the global feature once per sample, not once per point.

    The same parameters (and state-dict keys) as `nn.Conv1d(c_local + c_global, c_out, 1)` on the concatenation, and
    the same output; in the pose network's heads that is about a third of the graph's arithmetic saved.
    """

    def __init__(self, c_local: int, c_global: int, c_out: int) -> None:
        super().__init__(c_local + c_global, c_out, 1)
        self.c_local = c_local

    def forward(self, local: torch.Tensor, global_feat: torch.Tensor) -> torch.Tensor:
        """:param local: (B, c_local, N). :param global_feat: (B, c_global, 1). :return: (B, c_out, N)."""
        w = self.weight
        return F.conv1d(local, w[:, :self.c_local]) + F.conv1d(global_feat, w[:, self.c_local:], self.bias)


class _Head(nn.Sequential):
    """DenseFusion's per-point head: 1x1 convs with ReLUs, the first one on the dense feature (local + global)."""

    def forward(self, local: torch.Tensor, global_feat: torch.Tensor) -> torch.Tensor:   # type: ignore[override]
        x = self[0](local, global_feat)
        for layer in list(self)[1:]:
            x = layer(x)
        return x


def _head(c_local: int, c_global: int, dims: tuple[int, int, int], c_out: int) -> _Head:
    d1, d2, d3 = dims
    return _Head(SplitInputConv1d(c_local, c_global, d1), nn.ReLU(inplace=True), nn.Conv1d(d1, d2, 1),
                 nn.ReLU(inplace=True), nn.Conv1d(d2, d3, 1), nn.ReLU(inplace=True), nn.Conv1d(d3, c_out, 1))


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
        local = 2 * p1 + 2 * p2
        self.head_r = _head(local, g2, cfg.head_dims, 4)
        self.head_t = _head(local, g2, cfg.head_dims, 3)
        self.head_c = _head(local, g2, cfg.head_dims, 1)
        self.head_v = _head(local, g2, cfg.head_dims, 1) if cfg.verifier else None

    def dense(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The dense per-point feature, `[local; g at every point]`, as its two parts.

        :param points: (B, N, 3). :param features: (B, N, C). :return: local (B, 2*p1 + 2*p2, N), g (B, g2, 1)."""
        x = F.relu(self.conv1(points.transpose(1, 2)))
        e = F.relu(self.e_conv1(features.transpose(1, 2)))
        pf1 = torch.cat((x, e), 1)
        x = F.relu(self.conv2(x))
        if self.attention is not None:
            x = x + self.attention(x.transpose(1, 2)).transpose(1, 2)
        e = F.relu(self.e_conv2(e))
        pf2 = torch.cat((x, e), 1)
        g = F.relu(self.conv6(F.relu(self.conv5(pf2))))
        return torch.cat((pf1, pf2), 1), g.mean(2, keepdim=True)

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:param points: (B, N, 3). :param features: (B, N, C).
        :return: quat (B, N, 4) unit wxyz, trans (B, N, 3) metres, conf (B, N)."""
        local, g = self.dense(points, features)
        quat = F.normalize(self.head_r(local, g), dim=1, eps=1e-8).transpose(1, 2)
        trans = self.head_t(local, g).transpose(1, 2)
        conf = torch.sigmoid(self.head_c(local, g))[:, 0]
        return quat, trans, conf

    def verify(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The verifier head's confidence at every point, and the confidence head's (which chooses).

        :param points: (B, N, 3). :param features: (B, N, C). :return: verifier (B, N), conf (B, N), in (0, 1).
        :raises ValueError: the network has no verifier head."""
        if self.head_v is None:
            raise ValueError("this pose network has no verifier head (PoseConfig.verifier)")
        local, g = self.dense(points, features)
        return torch.sigmoid(self.head_v(local, g))[:, 0], torch.sigmoid(self.head_c(local, g))[:, 0]


class MostConfidentPose(nn.Module):
    """A pose network's most confident hypothesis per sample (DenseFusion's argmax), computed without the rotation
    and translation heads at the other points: the graph the runtime runs.

    Its layers are the network's own, registered under the same names: the same state-dict keys and graph node
    names, so a graph of it reads back into a `PoseNet` like a graph of the network (`bundle_weights`).
    """

    def __init__(self, net: PoseNet) -> None:
        super().__init__()
        for name, child in net.named_children():
            self.add_module(name, child)
        self.head_v = net.head_v
        self._dense = net.dense

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:param points: (B, N, 3) centred. :param features: (B, N, C).
        :return: quat (B, 4) unit wxyz, trans (B, 3) = the chosen point + its offset (metres, centred frame), conf
            (B,) (the verifier head's at the chosen point where the network has one); the chosen point is the first
            of the most confident ones, as numpy's argmax picks."""
        local, g = self._dense(points, features)
        conf = torch.sigmoid(self.head_c(local, g))[:, 0]                      # (B, N)
        best, idx = conf.max(1, keepdim=True)                                   # (B, 1)
        # the chosen point as a one-hot mask (exact: x * 1 plus zeros), which keeps every shape static for
        # shape inference, where a gather's index would not
        pick = (torch.arange(conf.shape[1], device=conf.device) == idx).to(local.dtype)   # (B, N)
        chosen = torch.bmm(local, pick[:, :, None])                             # (B, C, 1)
        quat = F.normalize(self.head_r(chosen, g), dim=1, eps=1e-8)[:, :, 0]
        point = (points * pick[:, :, None]).sum(1)
        if self.head_v is not None:
            best = torch.sigmoid(self.head_v(chosen, g))[:, 0]                  # (B, 1)
        return quat, point + self.head_t(chosen, g)[:, :, 0], best[:, 0]


def build_pose(cfg: PoseConfig, feature_dim: int) -> PoseNet:
    """The pose network for `cfg`, reading `feature_dim` fused features per point (random weights)."""
    return PoseNet(cfg, feature_dim)
