"""Network configurations: one dataclass per network, one `ModelConfig` per named variant.

Variants (`CONFIGS`):

- ``paper``: the paper's networks. YOLOv8s detector at 384x1216 (fits a 1224x370 frame letterboxed),
  two ResNet18+PSP branches at full width (DenseFusion's PSPNet: stride 8, dilated layer3/4, PSP
  pooling 1/2/3/6, three x2 upsampling stages back to the crop), crop 120x120, N=500 points,
  multi-head self-attention on the fused map (eqs. 1-3) at stride 4 (30x30 = 900 tokens: full-resolution
  attention over 14400 locations would cost ~53 GFLOP and an 830 MB score matrix per pallet), and on the
  per-point geometric features (3.1.3).
- ``edge``: for the forklift's 2 CPU cores. YOLOv8n at 192x640; ResNet18+PSP at half width with a
  512-channel PSP bottleneck and halved upsampling convs, crop 96x96, N=256, fused-map attention at
  stride 8 (12x12 tokens); pose MLPs at half width. The paper-sized pose stage is ~30 GFLOP/pallet
  (~150 ms fp32 on 2 cores); width/2 cuts conv cost ~4x and crop 96 vs 120 another ~1.56x, which puts
  fusion+pose at a few GFLOP per pallet (measured numbers in the export report / manifest `scores`).
- ``edge2``: the edge network rebuilt for per-pallet latency: the fusion graph stops at stride 8 (no
  upsampling stages, layer3/4 not dilated), samples the fused stride-8 map bilinearly at the N chosen
  pixels inside the graph (third input `choose`, output (B, N, C)), on an 80x80 crop; attention over the
  10x10 stride-8 tokens; the pose network as in ``edge``. Costs and accuracy in docs/experiments/edge-net.md.
- ``edge2-dilated``: ``edge2`` with ``edge``'s crop (96) and dilated layer3/4: the backbone computes exactly what
  the shipped ``edge`` backbone computes, so a warm start from it loses only the two output convs (0.7 ms more
  per pallet at int8 than ``edge2``); the fallback if ``edge2`` does not reach ``edge``'s accuracy.
- ``edge2-verified``: ``edge2-dilated`` with a verifier head (`PoseConfig.verifier`): started from an
  ``edge2-dilated`` bundle and trained alone (``pallet6d train pose --verifier-only``), every pose stays that bundle's
  and the graph's confidence becomes the verifier's.
- ``edge2-slim``: ``edge2-dilated`` with layer4 and the PSP bottleneck at half its width (128 and 256 channels):
  about half its fusion work (layer4 at stride 8 is most of it), trained from it (``--init`` copies every other
  layer) with its fused features as a target (``pallet6d train pose --distill``).
- ``edge2-pruned``: ``edge2-slim`` with a projection shortcut at the start of layer4, so that ``--init`` from
  ``edge2-dilated`` fills layer4, the PSP stages and bottleneck and the output convs with the most important half
  of their channels (`export/channel_prune.py`) instead of leaving them to train from scratch.
- ``edge2-pruned-verified``: ``edge2-pruned`` with a verifier head, as ``edge2-verified`` is to ``edge2-dilated``.
- ``densefusion``: ``paper`` without any attention block (the paper's ablation baseline).
- ``edge-densefusion``: ``edge`` without any attention block (the same ablation at the shipped size).
- ``tiny``: minimal widths for fast tests (never for deployment).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

__all__ = ["DetectorConfig", "FusionConfig", "PoseConfig", "ModelConfig", "CONFIGS", "get_config",
           "DETECTOR_SCALES", "DETECTOR_ACTIVATIONS", "DETECTOR_ARCHITECTURES"]

# YOLOv8 (depth multiple, width multiple, max channels) per scale.
DETECTOR_SCALES: dict[str, tuple[float, float, int]] = {
    "n": (0.33, 0.25, 1024),
    "s": (0.33, 0.50, 1024),
    "m": (0.67, 0.75, 768),
}
DETECTOR_ACTIVATIONS = ("silu", "relu")
# "yolov8": C2f backbone of `scale`, BatchNorm; "yolox-nano": depthwise CSP network that published COCO weights
# can start (`export.detector_dw`), fixed width, RGB and SiLU only
DETECTOR_ARCHITECTURES = ("yolov8", "yolox-nano")


def _check_positive(name: str, values) -> None:
    for v in values if isinstance(values, (tuple, list)) else (values,):
        if not (isinstance(v, (int, float)) and v > 0):
            raise ValueError(f"{name} must be positive, got {values}")


@dataclass(frozen=True)
class DetectorConfig:
    """YOLOv8-style detector.

    :ivar scale: one of DETECTOR_SCALES, or "custom" with `depth_multiple`, `width_multiple` set.
    :ivar input_hw: letterboxed input (H, W), multiples of 32.
    :ivar depth_max_m: None: RGB in. Else an RGB-D detector: depth is a 4th input channel, depth / depth_max_m
        clipped to [0, 1], 0 where there is none (`runtime.detector.depth_channel`).
    :ivar activation: one of DETECTOR_ACTIVATIONS. "silu" is YOLOv8's; "relu" folds into the int8 convolutions
        (a SiLU stays two uint8 passes between them), about a quarter less detector time on 2 cores.
    :ivar architecture: one of DETECTOR_ARCHITECTURES; both give the same outputs and loss.
    """

    scale: str = "n"
    input_hw: tuple[int, int] = (192, 640)
    classes: tuple[str, ...] = ("pallet",)
    reg_max: int = 16
    depth_multiple: float | None = None
    width_multiple: float | None = None
    max_channels: int | None = None
    depth_max_m: float | None = None
    activation: str = "silu"
    architecture: str = "yolov8"

    def __post_init__(self) -> None:
        if self.architecture not in DETECTOR_ARCHITECTURES:
            raise ValueError(f"detector architecture {self.architecture!r} unknown; use one of "
                             f"{DETECTOR_ARCHITECTURES}")
        if self.activation not in DETECTOR_ACTIVATIONS:
            raise ValueError(f"detector activation {self.activation!r} unknown; use one of {DETECTOR_ACTIVATIONS}")
        if self.depth_max_m is not None and not self.depth_max_m > 0:
            raise ValueError(f"detector depth_max_m must be > 0 metres (or None for RGB), got {self.depth_max_m}")
        if self.scale != "custom" and self.scale not in DETECTOR_SCALES:
            raise ValueError(f"detector scale {self.scale!r} unknown; use one of {sorted(DETECTOR_SCALES)} or 'custom'")
        if self.scale == "custom" and (self.depth_multiple is None or self.width_multiple is None):
            raise ValueError("detector scale 'custom' needs depth_multiple and width_multiple")
        h, w = self.input_hw
        if h % 32 or w % 32 or h <= 0 or w <= 0:
            raise ValueError(f"detector input_hw must be positive multiples of 32 (stride 32), got {self.input_hw}")
        if not self.classes:
            raise ValueError("detector needs at least one class")
        _check_positive("reg_max", self.reg_max)

    @property
    def multiples(self) -> tuple[float, float, int]:
        """(depth multiple, width multiple, max channels)."""
        if self.scale == "custom":
            return float(self.depth_multiple), float(self.width_multiple), int(self.max_channels or 1024)
        return DETECTOR_SCALES[self.scale]

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def input_channels(self) -> int:
        """3 (RGB) or 4 (RGB-D)."""
        return 3 if self.depth_max_m is None else 4


@dataclass(frozen=True)
class FusionConfig:
    """RGB and depth ResNet18+PSP branches, concatenation (eq. 1), self-attention (eqs. 2-3).

    :ivar crop_hw: crop size fed to the network; multiple of 8 (the backbone's output stride).
    :ivar resnet_widths: channels of ResNet18's four stages (64, 128, 256, 512 at full width).
    :ivar psp_out: channels after the PSP bottleneck (DenseFusion: 1024).
    :ivar up_channels: channels of the three x2 upsampling stages (DenseFusion: 256, 64, 64).
    :ivar branch_dim: per-modality feature dimension at crop resolution (DenseFusion: 32).
    :ivar attention: apply multi-head self-attention to the fused map.
    :ivar attention_stride: attention runs on the fused map average-pooled by this factor, then its
        output is upsampled and added back (residual), because full-resolution attention is too costly.
    :ivar dilated: layer3/4 dilated (2, 4) as in DenseFusion; False: plain 3x3 convolutions at stride 8.
    :ivar sample_stride: 0: the graph outputs the dense (B, C, h, w) map at crop resolution (three
        upsampling stages, `up_channels`). 8 or 4: no upsampling stages (`up_channels` must be empty); the
        graph takes `choose` (B, N) pixel indices and returns the fused features sampled bilinearly at
        those pixels (B, N, C), from the stride-8 map, or from a light stride-4 decoder (the stride-8
        features upsampled and added to a projection of layer1). Attention then runs at stride 8.
    :ivar project_layer4: layer4 starts with a 1x1 projection shortcut also when it is as wide as layer3 (the
        layout of every wider layer4, which a channel-pruned copy of one then fills: `export/channel_prune.py`).
    """

    crop_hw: tuple[int, int] = (120, 120)
    resnet_widths: tuple[int, int, int, int] = (64, 128, 256, 512)
    psp_sizes: tuple[int, ...] = (1, 2, 3, 6)
    psp_out: int = 1024
    up_channels: tuple[int, ...] = (256, 64, 64)
    branch_dim: int = 32
    attention: bool = True
    attention_heads: int = 4
    attention_stride: int = 4
    dilated: bool = True
    sample_stride: int = 0
    project_layer4: bool = False

    def __post_init__(self) -> None:
        h, w = self.crop_hw
        if h % 8 or w % 8 or h <= 0 or w <= 0:
            raise ValueError(f"crop_hw must be positive multiples of 8 (backbone stride), got {self.crop_hw}")
        _check_positive("resnet_widths", self.resnet_widths)
        _check_positive("up_channels", self.up_channels)
        if self.sample_stride not in (0, 4, 8):
            raise ValueError(f"sample_stride must be 0 (dense output), 4 or 8, got {self.sample_stride}")
        if self.sample_stride and self.up_channels:
            raise ValueError(f"sample_stride {self.sample_stride} samples the stride-{self.sample_stride} map: "
                             f"up_channels must be empty, got {self.up_channels}")
        if not self.sample_stride and len(self.up_channels) != 3:
            raise ValueError(f"a dense fusion output needs three upsampling stages, got up_channels {self.up_channels}")
        if self.sample_stride and self.attention and self.attention_stride != 8:
            raise ValueError(f"with sample_stride, attention runs on the stride-8 map: attention_stride must be 8, "
                             f"got {self.attention_stride}")
        _check_positive("psp_sizes", self.psp_sizes)
        if self.attention:
            if h % self.attention_stride or w % self.attention_stride:
                raise ValueError(f"attention_stride {self.attention_stride} must divide crop_hw {self.crop_hw}")
            if self.feature_dim % self.attention_heads:
                raise ValueError(f"feature_dim {self.feature_dim} must be divisible by attention_heads "
                                 f"{self.attention_heads}")

    @property
    def feature_dim(self) -> int:
        """Channels of the fused per-pixel feature map (RGB + depth)."""
        return 2 * self.branch_dim

    @property
    def sampled(self) -> bool:
        """The graph takes `choose` and returns per-point features (B, N, feature_dim)."""
        return self.sample_stride > 0


@dataclass(frozen=True)
class PoseConfig:
    """DenseFusion's PoseNetFeat + PoseNet heads, with self-attention over per-point features.

    :ivar num_points: N, points sampled per pallet.
    :ivar point_dims: per-point geometric (and fused-embedding) conv widths (DenseFusion: 64, 128).
    :ivar global_dims: the two convs before average pooling (DenseFusion: 512, 1024).
    :ivar head_dims: hidden widths of each head (DenseFusion: 640, 256, 128).
    :ivar verifier: a fourth head of the confidence head's shape, read at the chosen point alone: the confidence the
        graph gives (and the runtime compares with `min_confidence`), while the confidence head keeps choosing the
        hypothesis. Ranking a crop's points and judging whether the crop holds a pallet at all are two questions; one
        head trained for both moves the chosen hypotheses.
    """

    num_points: int = 500
    point_dims: tuple[int, int] = (64, 128)
    global_dims: tuple[int, int] = (512, 1024)
    head_dims: tuple[int, int, int] = (640, 256, 128)
    attention: bool = True
    attention_heads: int = 4
    verifier: bool = False

    def __post_init__(self) -> None:
        _check_positive("num_points", self.num_points)
        _check_positive("point_dims", self.point_dims)
        _check_positive("global_dims", self.global_dims)
        _check_positive("head_dims", self.head_dims)
        if self.attention and self.point_dims[1] % self.attention_heads:
            raise ValueError(f"point_dims[1]={self.point_dims[1]} must be divisible by attention_heads")


@dataclass(frozen=True)
class ModelConfig:
    """A named variant: detector + fusion + pose, plus the preprocessing they were trained with."""

    name: str
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    pallet: str = "epal"
    rgb_mean: tuple[float, float, float] = (0.485, 0.456, 0.406)   # ImageNet, as DenseFusion
    rgb_std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    depth_clip_m: float = 1.0        # depth crop = clip(d - median, +-clip) / clip, 0 where no data
    depth_range_m: tuple[float, float] = (0.1, 10.0)   # valid depth for back-projection

    def replace(self, **changes) -> "ModelConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


CONFIGS: dict[str, ModelConfig] = {
    "paper": ModelConfig(
        name="paper",
        detector=DetectorConfig(scale="s", input_hw=(384, 1216)),
        fusion=FusionConfig(crop_hw=(120, 120), attention=True, attention_stride=4),
        pose=PoseConfig(num_points=500, attention=True),
    ),
    "edge": ModelConfig(
        name="edge",
        detector=DetectorConfig(scale="n", input_hw=(192, 640)),
        fusion=FusionConfig(crop_hw=(96, 96), resnet_widths=(32, 64, 128, 256), psp_out=512,
                            up_channels=(128, 64, 32), branch_dim=32, attention=True, attention_stride=8),
        pose=PoseConfig(num_points=256, point_dims=(64, 128), global_dims=(256, 512), head_dims=(320, 128, 64),
                        attention=True),
    ),
    # the edge network without either attention block: the DenseFusion ablation at the shipped size
    "edge-densefusion": ModelConfig(
        name="edge-densefusion",
        detector=DetectorConfig(scale="n", input_hw=(192, 640)),
        fusion=FusionConfig(crop_hw=(96, 96), resnet_widths=(32, 64, 128, 256), psp_out=512,
                            up_channels=(128, 64, 32), branch_dim=32, attention=False),
        pose=PoseConfig(num_points=256, point_dims=(64, 128), global_dims=(256, 512), head_dims=(320, 128, 64),
                        attention=False),
    ),
    "edge2": ModelConfig(
        name="edge2",
        detector=DetectorConfig(scale="n", input_hw=(192, 640)),
        fusion=FusionConfig(crop_hw=(80, 80), resnet_widths=(32, 64, 128, 256), psp_out=512, up_channels=(),
                            branch_dim=32, attention=True, attention_stride=8, dilated=False, sample_stride=8),
        pose=PoseConfig(num_points=256, point_dims=(64, 128), global_dims=(256, 512), head_dims=(320, 128, 64),
                        attention=True),
    ),
    "densefusion": ModelConfig(
        name="densefusion",
        detector=DetectorConfig(scale="s", input_hw=(384, 1216)),
        fusion=FusionConfig(crop_hw=(120, 120), attention=False),
        pose=PoseConfig(num_points=500, attention=False),
    ),
    "tiny": ModelConfig(
        name="tiny",
        detector=DetectorConfig(scale="custom", depth_multiple=0.33, width_multiple=0.0625, max_channels=64,
                                input_hw=(64, 128)),
        fusion=FusionConfig(crop_hw=(32, 32), resnet_widths=(8, 8, 16, 16), psp_out=32, up_channels=(16, 8, 8),
                            branch_dim=8, attention=True, attention_heads=2, attention_stride=8),
        pose=PoseConfig(num_points=32, point_dims=(16, 16), global_dims=(32, 64), head_dims=(32, 16, 16),
                        attention=True, attention_heads=2),
    ),
}

# edge2 with edge's crop and dilated layers: the backbone computes what edge's computes
CONFIGS["edge2-dilated"] = CONFIGS["edge2"].replace(
    name="edge2-dilated", fusion=dataclasses.replace(CONFIGS["edge2"].fusion, crop_hw=(96, 96), dilated=True))
# edge2-dilated's networks with a verifier head (`PoseConfig.verifier`): started from an edge2-dilated bundle, every
# pose stays that bundle's
CONFIGS["edge2-verified"] = CONFIGS["edge2-dilated"].replace(
    name="edge2-verified", pose=dataclasses.replace(CONFIGS["edge2-dilated"].pose, verifier=True))
CONFIGS["edge2-slim"] = CONFIGS["edge2-dilated"].replace(
    name="edge2-slim", fusion=dataclasses.replace(CONFIGS["edge2-dilated"].fusion, resnet_widths=(32, 64, 128, 128),
                                                  psp_out=256))
CONFIGS["edge2-pruned"] = CONFIGS["edge2-slim"].replace(
    name="edge2-pruned", fusion=dataclasses.replace(CONFIGS["edge2-slim"].fusion, project_layer4=True))
CONFIGS["edge2-pruned-verified"] = CONFIGS["edge2-pruned"].replace(
    name="edge2-pruned-verified", pose=dataclasses.replace(CONFIGS["edge2-pruned"].pose, verifier=True))


def get_config(name: str) -> ModelConfig:
    """The named variant (one of CONFIGS)."""
    if name not in CONFIGS:
        raise ValueError(f"unknown config {name!r}; choose one of {', '.join(CONFIGS)}")
    return CONFIGS[name]
