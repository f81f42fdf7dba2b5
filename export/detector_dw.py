"""A depthwise CSP detector laid out as YOLOX-Nano (CSPDarknet with a Focus stem and depthwise 3x3 convolutions,
PAFPN neck, a decoupled head with a shared 1x1 stem per level), so that the published COCO weights of that
network can start it (`pretrained_dw.load_yolox_onnx`), with the YOLOv8 anchor-free DFL outputs of `detector`:
the same training loss and the same ONNX output layout (B, 4 + nc, A) as `YoloDetector`.

The convolutions carry biases and no BatchNorm: the published weights come with BatchNorm folded into them, and
fine-tuning keeps them that way (batches of 16 on two cores would make BatchNorm statistics noisy anyway).
0.74 GFLOP at 192 x 640, against 2.42 for the YOLOv8n-style detector of the shipped bundle.
"""
from __future__ import annotations

import torch
from torch import nn

from .config import DetectorConfig
from .detector import DFL, DetectHead

__all__ = ["DepthwiseDetector", "DW_WIDTHS", "DW_HEAD_WIDTH"]

DW_WIDTHS = (16, 32, 64, 128, 256)   # stem, stride 4, 8, 16, 32 channels
DW_HEAD_WIDTH = 64


class ConvAct(nn.Module):
    """Conv2d with bias + SiLU."""

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1, groups: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, groups=groups, bias=True)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(x))


class DWConv(nn.Module):
    """Depthwise 3x3 (stride s) then pointwise 1x1, each with SiLU."""

    def __init__(self, c_in: int, c_out: int, s: int = 1) -> None:
        super().__init__()
        self.dconv = ConvAct(c_in, c_in, 3, s, groups=c_in)
        self.pconv = ConvAct(c_in, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pconv(self.dconv(x))

    def convs(self) -> list[nn.Conv2d]:
        return [self.dconv.conv, self.pconv.conv]


class Bottleneck(nn.Module):
    def __init__(self, c: int, shortcut: bool) -> None:
        super().__init__()
        self.conv1, self.conv2, self.add = ConvAct(c, c, 1), DWConv(c, c), shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv2(self.conv1(x))
        return x + y if self.add else y

    def convs(self) -> list[nn.Conv2d]:
        return [self.conv1.conv, *self.conv2.convs()]


class CSPLayer(nn.Module):
    """Two 1x1 halves, n bottlenecks on the first, concatenated and mixed by a 1x1."""

    def __init__(self, c_in: int, c_out: int, n: int, shortcut: bool) -> None:
        super().__init__()
        h = c_out // 2
        self.conv1, self.conv2, self.conv3 = ConvAct(c_in, h, 1), ConvAct(c_in, h, 1), ConvAct(2 * h, c_out, 1)
        self.m = nn.Sequential(*(Bottleneck(h, shortcut) for _ in range(n)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, b = self.conv1(x), self.conv2(x)          # the published order (`convs`)
        return self.conv3(torch.cat((self.m(a), b), 1))

    def convs(self) -> list[nn.Conv2d]:
        """In the order the published network runs them."""
        return [self.conv1.conv, self.conv2.conv, *(c for b in self.m for c in b.convs()), self.conv3.conv]


class SPP(nn.Module):
    """Max-pools of 5, 9 and 13 beside the input, concatenated."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        h = c_in // 2
        self.conv1, self.conv2 = ConvAct(c_in, h, 1), ConvAct(4 * h, c_out, 1)
        self.pools = nn.ModuleList(nn.MaxPool2d(k, 1, k // 2) for k in (5, 9, 13))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv1(x)
        return self.conv2(torch.cat([x, *(p(x) for p in self.pools)], 1))

    def convs(self) -> list[nn.Conv2d]:
        return [self.conv1.conv, self.conv2.conv]


def space_to_depth(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> (B, 4C, H/2, W/2): pixels (even row, even col), (odd, even), (even, odd), (odd, odd)."""
    return torch.cat((x[..., ::2, ::2], x[..., 1::2, ::2], x[..., ::2, 1::2], x[..., 1::2, 1::2]), 1)


class DepthwiseHead(DetectHead):
    """`DetectHead`'s outputs (box DFL bins and class logits per level) from a shared 1x1 stem and two depthwise
    convolutions per branch."""

    def __init__(self, nc: int, channels: tuple[int, ...], reg_max: int) -> None:
        nn.Module.__init__(self)           # DetectHead's layers are not these
        self.nc, self.reg_max = nc, reg_max
        w = DW_HEAD_WIDTH
        self.stems = nn.ModuleList(ConvAct(c, w, 1) for c in channels)
        self.cls = nn.ModuleList(nn.Sequential(DWConv(w, w), DWConv(w, w), nn.Conv2d(w, nc, 1)) for _ in channels)
        self.box = nn.ModuleList(nn.Sequential(DWConv(w, w), DWConv(w, w), nn.Conv2d(w, 4 * reg_max, 1))
                                 for _ in channels)
        self.dfl = DFL(reg_max)

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        out = []
        for x, stem, b, c in zip(feats, self.stems, self.box, self.cls):
            x = stem(x)
            out.append(torch.cat((b(x), c(x)), 1))
        return out

    def convs(self) -> list[nn.Conv2d]:
        """The pretrained convolutions in the published network's order (level by level: stem, class branch,
        box branch); the output convs are this network's own."""
        out: list[nn.Conv2d] = []
        for stem, c, b in zip(self.stems, self.cls, self.box):
            out += [stem.conv, *c[0].convs(), *c[1].convs(), *b[0].convs(), *b[1].convs()]
        return out


class DepthwiseDetector(nn.Module):
    """Focus stem, depthwise CSPDarknet, SPP, PAFPN neck, `DepthwiseHead`. Input (B, 3, H, W) RGB in [0, 1]."""

    def __init__(self, cfg: DetectorConfig) -> None:
        super().__init__()
        if cfg.input_channels != 3 or cfg.activation != "silu":
            raise ValueError(f"detector architecture {cfg.architecture!r} is RGB with SiLU only")
        self.cfg = cfg
        c0, c1, c2, c3, c4 = DW_WIDTHS
        self.stem = ConvAct(12, c0, 3)
        self.dark2 = nn.Sequential(DWConv(c0, c1, 2), CSPLayer(c1, c1, 1, True))
        self.dark3 = nn.Sequential(DWConv(c1, c2, 2), CSPLayer(c2, c2, 3, True))
        self.dark4 = nn.Sequential(DWConv(c2, c3, 2), CSPLayer(c3, c3, 3, True))
        self.dark5 = nn.Sequential(DWConv(c3, c4, 2), SPP(c4, c4), CSPLayer(c4, c4, 1, False))
        self.up = nn.Upsample(scale_factor=2.0, mode="nearest")
        self.lateral5 = ConvAct(c4, c3, 1)
        self.td4 = CSPLayer(2 * c3, c3, 1, False)
        self.reduce4 = ConvAct(c3, c2, 1)
        self.td3 = CSPLayer(2 * c2, c2, 1, False)
        self.bu_down3 = DWConv(c2, c2, 2)
        self.bu4 = CSPLayer(2 * c2, c3, 1, False)
        self.bu_down4 = DWConv(c3, c3, 2)
        self.bu5 = CSPLayer(2 * c3, c4, 1, False)
        self.head = DepthwiseHead(cfg.num_classes, (c2, c3, c4), cfg.reg_max)
        self.head.init_biases(cfg.input_hw)

    def neck_outputs(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) RGB in [0, 1] -> the three maps the head reads (strides 8, 16, 32)."""
        p3 = self.dark3(self.dark2(self.stem(space_to_depth(x))))
        p4 = self.dark4(p3)
        f5 = self.lateral5(self.dark5(p4))
        t4 = self.reduce4(self.td4(torch.cat((self.up(f5), p4), 1)))
        o3 = self.td3(torch.cat((self.up(t4), p3), 1))
        o4 = self.bu4(torch.cat((self.bu_down3(o3), t4), 1))
        return [o3, o4, self.bu5(torch.cat((self.bu_down4(o4), f5), 1))]

    def forward_raw(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) RGB in [0, 1] -> per-level raw maps (B, 4*reg_max + nc, H/s, W/s), s = 8, 16, 32."""
        return self.head(self.neck_outputs(x))

    def forward(self, x: torch.Tensor):
        raw = self.forward_raw(x)
        return raw if self.training else self.head.decode(raw)

    def pretrained_convs(self) -> list[nn.Conv2d]:
        """Every convolution the published weights fill, in the order the published network runs them."""
        out = [self.stem.conv]
        for stage in (self.dark2, self.dark3, self.dark4, self.dark5):
            for m in stage:
                out += m.convs()
        out.append(self.lateral5.conv)
        out += self.td4.convs() + [self.reduce4.conv] + self.td3.convs()
        out += self.bu_down3.convs() + self.bu4.convs() + self.bu_down4.convs() + self.bu5.convs()
        return out + self.head.convs()
