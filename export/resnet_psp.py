"""ResNet18 + PSP feature extractor (paper 3.1.1, DenseFusion's PSPNet with a ResNet18 backend).

ResNet18 to output stride 8: stem (7x7/2 conv, 3x3/2 max-pool), layer1, layer2 (stride 2), then layer3
and layer4 at stride 8, dilated (2 and 4) as in DenseFusion or plain 3x3 (`dilated=False`: the same
weights, FLOPs and measured speed; the plain ResNet18 layout, with the PSP pooling supplying the wide
context). PSP: average pooling to 1x1, 2x2, 3x3, 6x6 bins, a 1x1 conv per bin, bilinear upsampling,
concatenation with the input, a 1x1 bottleneck. Then x2 upsampling stages (bilinear, 3x3 conv, PReLU;
DenseFusion: three, back to the crop resolution; none when the features are sampled at stride 8), and a
1x1 conv to the branch's feature dimension. (DenseFusion ends with a log-softmax, a leftover of PSPNet's
segmentation use; the features here stay linear.)

Adaptive average pooling is written as two fixed pooling matrices (for the crop size given at build
time) so that the graph exports with any bin count, also when it does not divide the feature size.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ResNet18Dilated", "PSPNet", "adaptive_pool_matrix"]


class BasicBlock(nn.Module):
    """:param project: a 1x1 projection shortcut even where the identity would fit (same width, stride 1)."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, dilation: int = 1, project: bool = False) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, dilation, dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, dilation, dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.relu = nn.ReLU(inplace=True)
        self.down = None
        if stride != 1 or c_in != c_out or project:
            self.down = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.down is None else self.down(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + identity)


class ResNet18Dilated(nn.Module):
    """ResNet18 with output stride 8 (layer3/4 dilated 2/4, or not dilated). :param in_channels: 3 for RGB,
    1 for depth. :param project_layer4: layer4 starts with a projection shortcut also when it is as wide as layer3."""

    def __init__(self, in_channels: int, widths: tuple[int, int, int, int], dilated: bool = True,
                 project_layer4: bool = False) -> None:
        super().__init__()
        w1, w2, w3, w4 = widths
        self.stem = nn.Sequential(nn.Conv2d(in_channels, w1, 7, 2, 3, bias=False), nn.BatchNorm2d(w1),
                                  nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1))
        self.layer1 = nn.Sequential(BasicBlock(w1, w1), BasicBlock(w1, w1))
        self.layer2 = nn.Sequential(BasicBlock(w1, w2, stride=2), BasicBlock(w2, w2))
        d3, d4 = (2, 4) if dilated else (1, 1)
        self.layer3 = nn.Sequential(BasicBlock(w2, w3, dilation=d3), BasicBlock(w3, w3, dilation=d3))
        self.layer4 = nn.Sequential(BasicBlock(w3, w4, dilation=d4, project=project_layer4),
                                    BasicBlock(w4, w4, dilation=d4))
        self.out_channels = w4

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, widths[3], H/8, W/8)."""
        return self.layer4(self.layer3(self.layer2(self.layer1(self.stem(x)))))

    def forward_with_stride4(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C_in, H, W) -> layer1's (B, widths[0], H/4, W/4) and the (B, widths[3], H/8, W/8) output."""
        s4 = self.layer1(self.stem(x))
        return s4, self.layer4(self.layer3(self.layer2(s4)))


def adaptive_pool_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """(n_out, n_in) matrix equal to adaptive average pooling along one axis (PyTorch's bin edges)."""
    m = torch.zeros(n_out, n_in)
    for i in range(n_out):
        a = (i * n_in) // n_out
        b = -((-(i + 1) * n_in) // n_out)  # ceil
        m[i, a:b] = 1.0 / (b - a)
    return m


class PSPNet(nn.Module):
    """ResNet18 + PSP + upsampling: (B, C_in, H, W) -> (B, out_dim, H / 2^(3 - len(up_channels)), ...).

    :param in_hw: the crop size the network is built for (H, W multiples of 8).
    :param up_channels: one x2 upsampling stage per entry (three: back to the crop; none: stride 8).
    :param with_stride4: also return layer1's (B, widths[0], H/4, W/4) map (for a stride-4 decoder).
    :param project_layer4: see `ResNet18Dilated`.
    """

    def __init__(self, in_channels: int, in_hw: tuple[int, int], widths: tuple[int, int, int, int],
                 psp_sizes: tuple[int, ...], psp_out: int, up_channels: tuple[int, ...], out_dim: int,
                 dilated: bool = True, with_stride4: bool = False, project_layer4: bool = False) -> None:
        super().__init__()
        self.with_stride4 = with_stride4
        self.backbone = ResNet18Dilated(in_channels, widths, dilated, project_layer4)
        c = self.backbone.out_channels
        self.feat_hw = (in_hw[0] // 8, in_hw[1] // 8)
        for s in psp_sizes:
            self.register_buffer(f"pool_h{s}", adaptive_pool_matrix(self.feat_hw[0], s), persistent=False)
            self.register_buffer(f"pool_w{s}", adaptive_pool_matrix(self.feat_hw[1], s).t().contiguous(),
                                 persistent=False)
        self.psp_sizes = tuple(psp_sizes)
        self.stages = nn.ModuleList(nn.Conv2d(c, c, 1, bias=False) for _ in psp_sizes)
        self.bottleneck = nn.Sequential(nn.Conv2d(c * (len(psp_sizes) + 1), psp_out, 1), nn.ReLU(inplace=True))
        ups, c_prev = [], psp_out
        for c_up in up_channels:
            ups += [nn.Upsample(scale_factor=2.0, mode="bilinear", align_corners=False),
                    nn.Conv2d(c_prev, c_up, 3, padding=1), nn.PReLU()]
            c_prev = c_up
        self.up = nn.Sequential(*ups)
        self.final = nn.Conv2d(c_prev, out_dim, 1)

    def context(self, f: torch.Tensor) -> torch.Tensor:
        """PSP on the backbone's (B, C, H/8, W/8) output -> (B, psp_out, H/8, W/8) after the bottleneck."""
        h, w = self.feat_hw
        priors = [f]
        for s, stage in zip(self.psp_sizes, self.stages):
            pooled = getattr(self, f"pool_h{s}") @ f @ getattr(self, f"pool_w{s}")     # (B, C, s, s)
            priors.append(F.interpolate(stage(pooled), size=(h, w), mode="bilinear", align_corners=False))
        return self.bottleneck(torch.cat(priors, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        if not self.with_stride4:
            return self.final(self.up(self.context(self.backbone(x))))
        s4, s8 = self.backbone.forward_with_stride4(x)
        return self.final(self.up(self.context(s8))), s4
