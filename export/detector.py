"""YOLOv8-style detector (paper 3.1): CSP-Darknet backbone with C2f blocks, SPPF, PAN neck,
anchor-free decoupled head with Distribution Focal Loss box regression (reg_max bins).

Training mode returns the raw per-level maps (B, 4*reg_max + nc, H_l, W_l); eval/export mode returns
the YOLOv8 ONNX layout (B, 4 + nc, A): cx, cy, w, h in input pixels, then sigmoid class scores, with
anchors ordered level by level (stride 8, 16, 32), row-major within a level.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from .config import DetectorConfig

__all__ = ["YoloDetector", "build_detector", "make_anchors", "STRIDES", "widen_class_outputs", "widen_input_channels"]

STRIDES = (8, 16, 32)


def _make_divisible(x: float, divisor: int = 8) -> int:
    return int(math.ceil(x / divisor) * divisor)


class ConvBnAct(nn.Module):
    """Conv2d (no bias) + BatchNorm + SiLU (ReLU in a detector whose config asks for it)."""

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, bias=False)
        self.bn = nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    def __init__(self, c: int, shortcut: bool) -> None:
        super().__init__()
        self.cv1 = ConvBnAct(c, c, 3)
        self.cv2 = ConvBnAct(c, c, 3)
        self.add = shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """CSP bottleneck with two convolutions: split, n bottlenecks on one half, concat every stage."""

    def __init__(self, c_in: int, c_out: int, n: int, shortcut: bool) -> None:
        super().__init__()
        self.c = c_out // 2
        self.cv1 = ConvBnAct(c_in, 2 * self.c, 1)
        self.cv2 = ConvBnAct((2 + n) * self.c, c_out, 1)
        self.m = nn.ModuleList(Bottleneck(self.c, shortcut) for _ in range(n))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = list(self.cv1(x).split((self.c, self.c), 1))
        for m in self.m:
            y.append(m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    """Spatial pyramid pooling, fast: three chained 5x5 max-pools, concatenated."""

    def __init__(self, c_in: int, c_out: int, k: int = 5) -> None:
        super().__init__()
        c_ = c_in // 2
        self.cv1 = ConvBnAct(c_in, c_, 1)
        self.cv2 = ConvBnAct(c_ * 4, c_out, 1)
        self.pool = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.pool(y[-1]))
        return self.cv2(torch.cat(y, 1))


def make_anchors(feat_hw: list[tuple[int, int]], strides=STRIDES, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor centres in grid units (A, 2) as (x, y) + 0.5, and the stride of each anchor (A, 1)."""
    points, stride_t = [], []
    for (h, w), s in zip(feat_hw, strides):
        sy, sx = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32) + 0.5,
                                torch.arange(w, device=device, dtype=torch.float32) + 0.5, indexing="ij")
        points.append(torch.stack((sx, sy), -1).reshape(-1, 2))
        stride_t.append(torch.full((h * w, 1), float(s), device=device))
    return torch.cat(points), torch.cat(stride_t)


class DFL(nn.Module):
    """Expected value of a softmax distribution over reg_max bins, per box side."""

    def __init__(self, reg_max: int) -> None:
        super().__init__()
        self.reg_max = reg_max
        self.register_buffer("bins", torch.arange(reg_max, dtype=torch.float32), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 4*reg_max, A) -> (B, 4, A) distances in grid units."""
        b, _, a = x.shape
        p = x.view(b, 4, self.reg_max, a).softmax(2)
        return (p * self.bins.view(1, 1, -1, 1)).sum(2)


class DetectHead(nn.Module):
    """Decoupled anchor-free head: a box branch (4*reg_max) and a class branch (nc) per level."""

    def __init__(self, nc: int, channels: tuple[int, ...], reg_max: int) -> None:
        super().__init__()
        self.nc, self.reg_max = nc, reg_max
        c2 = max(16, channels[0] // 4, reg_max * 4)
        c3 = max(channels[0], min(nc, 100))
        self.box = nn.ModuleList(nn.Sequential(ConvBnAct(c, c2, 3), ConvBnAct(c2, c2, 3), nn.Conv2d(c2, 4 * reg_max, 1))
                                 for c in channels)
        self.cls = nn.ModuleList(nn.Sequential(ConvBnAct(c, c3, 3), ConvBnAct(c3, c3, 3), nn.Conv2d(c3, nc, 1))
                                 for c in channels)
        self.dfl = DFL(reg_max)

    def init_biases(self, input_hw: tuple[int, int]) -> None:
        """YOLOv8's prior: box logits 1, class logits for ~5 objects per 640x640 image."""
        for box, cls, s in zip(self.box, self.cls, STRIDES):
            nn.init.constant_(box[-1].bias, 1.0)
            n_cells = (input_hw[0] / s) * (input_hw[1] / s)
            nn.init.constant_(cls[-1].bias, math.log(5 / self.nc / n_cells))

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        return [torch.cat((b(x), c(x)), 1) for x, b, c in zip(feats, self.box, self.cls)]

    def decode(self, raw: list[torch.Tensor]) -> torch.Tensor:
        """Per-level raw maps -> (B, 4 + nc, A): cx, cy, w, h in input pixels, sigmoid scores."""
        anchors, strides = make_anchors([tuple(x.shape[2:]) for x in raw], device=raw[0].device)
        x = torch.cat([r.flatten(2) for r in raw], 2)
        box, cls = x.split((4 * self.reg_max, self.nc), 1)
        dist = self.dfl(box)                                   # (B, 4, A) l, t, r, b
        lt, rb = dist.chunk(2, 1)
        a = anchors.t().unsqueeze(0)
        xy = (a + (rb - lt) / 2) * strides.t()
        wh = (lt + rb) * strides.t()
        return torch.cat((xy, wh, cls.sigmoid()), 1)


class YoloDetector(nn.Module):
    """Backbone (CSP-Darknet, C2f, SPPF) + PAN neck + decoupled head."""

    def __init__(self, cfg: DetectorConfig) -> None:
        super().__init__()
        self.cfg = cfg
        dm, wm, max_c = cfg.multiples

        def ch(c: int) -> int:
            return _make_divisible(min(c, max_c) * wm, 8)

        def n(k: int) -> int:
            return max(round(k * dm), 1)

        c64, c128, c256, c512, c1024 = ch(64), ch(128), ch(256), ch(512), ch(1024)
        # backbone
        self.stem = ConvBnAct(cfg.input_channels, c64, 3, 2)                              # P1/2
        self.down2, self.c2f2 = ConvBnAct(c64, c128, 3, 2), C2f(c128, c128, n(3), True)   # P2/4
        self.down3, self.c2f3 = ConvBnAct(c128, c256, 3, 2), C2f(c256, c256, n(6), True)  # P3/8
        self.down4, self.c2f4 = ConvBnAct(c256, c512, 3, 2), C2f(c512, c512, n(6), True)  # P4/16
        self.down5, self.c2f5 = ConvBnAct(c512, c1024, 3, 2), C2f(c1024, c1024, n(3), True)  # P5/32
        self.sppf = SPPF(c1024, c1024)
        # PAN neck: top-down then bottom-up
        self.up = nn.Upsample(scale_factor=2.0, mode="nearest")
        self.td4 = C2f(c1024 + c512, c512, n(3), False)
        self.td3 = C2f(c512 + c256, c256, n(3), False)
        self.bu_down3 = ConvBnAct(c256, c256, 3, 2)
        self.bu4 = C2f(c256 + c512, c512, n(3), False)
        self.bu_down4 = ConvBnAct(c512, c512, 3, 2)
        self.bu5 = C2f(c512 + c1024, c1024, n(3), False)
        self.head = DetectHead(cfg.num_classes, (c256, c512, c1024), cfg.reg_max)
        self.head.init_biases(cfg.input_hw)

        if cfg.activation == "relu":
            for m in self.modules():
                if isinstance(m, ConvBnAct):
                    m.act = nn.ReLU(inplace=True)

    def forward_raw(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, C, H, W) in [0, 1] (C = 3 RGB, or 4 with depth) -> per-level raw maps (B, 4*reg_max + nc, H/s, W/s),
        s = 8, 16, 32."""
        x = self.c2f2(self.down2(self.stem(x)))
        p3 = self.c2f3(self.down3(x))
        p4 = self.c2f4(self.down4(p3))
        p5 = self.sppf(self.c2f5(self.down5(p4)))
        t4 = self.td4(torch.cat((self.up(p5), p4), 1))
        o3 = self.td3(torch.cat((self.up(t4), p3), 1))
        o4 = self.bu4(torch.cat((self.bu_down3(o3), t4), 1))
        o5 = self.bu5(torch.cat((self.bu_down4(o4), p5), 1))
        return self.head([o3, o4, o5])

    def forward(self, x: torch.Tensor):
        raw = self.forward_raw(x)
        return raw if self.training else self.head.decode(raw)


def build_detector(cfg: DetectorConfig) -> nn.Module:
    """The detector for `cfg` (random weights): `YoloDetector`, or `detector_dw.DepthwiseDetector` for the
    "yolox-nano" architecture (the same outputs, loss and ONNX layout)."""
    if cfg.architecture == "yolox-nano":
        from .detector_dw import DepthwiseDetector
        return DepthwiseDetector(cfg)
    return YoloDetector(cfg)


def widen_class_outputs(state: dict[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """A one-class detector's weights made to fit `model`'s several classes: each class starts as the one
    class (its output conv's row repeated), so a detector that tells pallet types apart starts from one that
    finds pallets. Other entries are returned unchanged (a mismatch there still fails at loading).

    :param state: the trained detector's state dict. :return: a new state dict.
    """
    target = model.state_dict()
    out = dict(state)
    for k, v in state.items():
        t = target.get(k)
        if (k.startswith("head.cls.") and t is not None and v.shape != t.shape and v.shape[0] == 1
                and v.shape[1:] == t.shape[1:]):
            out[k] = v.repeat(t.shape[0], *([1] * (v.ndim - 1)))
    return out


def widen_input_channels(state: dict[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """An RGB detector's weights made to fit an RGB-D `model`: the first convolution's kernels for the extra
    input channels start at zero, so the RGB-D detector starts out exactly as the RGB one and learns what depth
    adds. Other entries are returned unchanged.

    :param state: the trained detector's state dict. :return: a new state dict.
    """
    out = dict(state)
    key = "stem.conv.weight"
    t, v = model.state_dict().get(key), state.get(key)
    if t is not None and v is not None and v.shape != t.shape and v.shape[0] == t.shape[0] \
            and v.shape[2:] == t.shape[2:] and v.shape[1] < t.shape[1]:
        w = torch.zeros_like(t, dtype=v.dtype)
        w[:, :v.shape[1]] = v
        out[key] = w
    return out
