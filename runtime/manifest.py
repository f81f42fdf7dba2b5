"""The bundle manifest's schema: frozen dataclasses that `pallet6d export` writes (`to_dict`) and the runtime
reads (`from_dict`), so writer and reader cannot disagree. numpy only; no file access (see `bundle.py`).

manifest.json (format_version 2) is the immutable contract: everything the runtime needs and the sha256 of
every file. How the bundle was made and what it scored live in `report.json` beside it (`bundle.py`)::

    {
      "format": "pallet6d-bundle", "format_version": 2,
      "name": "epal-default", "config": "edge",        # config: the export config it came from
      "precision": ["fp32", "int8"],                   # "int8" only when every graph has a file_int8
      "detector": {
        "file": "detector.onnx", "file_int8": "detector.int8.onnx" | null,
        "input_name": "images", "output_name": "output0",
        "input_hw": [192, 640],                        # letterboxed input, multiples of 32 (the reference size)
        "input_sizes": [[192, 640], [256, 480]],       # optional: inputs the graph takes, one chosen per frame
                                                       # (`detector.choose_input_hw`); absent = [input_hw]
        "letterbox_pad_value": 114, "pixel_scale": 0.00392156862745098,   # 1/255; then (x - mean) / std
        "rgb_mean": [0, 0, 0], "rgb_std": [1, 1, 1], "channel_order": "RGB",
        "layout": "yolov8",                            # output (B, 4 + nc, A): cx, cy, w, h (input px), scores
        "classes": ["epal", "eur3"],                   # class names, index = class id
        "source": "pallet6d" | "external",             # an external graph's classes need not all be pallets
        "depth_max_m": 10.0                            # optional, RGB-D detector: a 4th input channel,
                                                       # clip(depth_m / depth_max_m, 0, 1), 0 where no depth
      },
      "fusion": {
        "file": "fusion.onnx", "file_int8": "fusion.int8.onnx" | null,
        "rgb_input": "rgb", "depth_input": "depth",    # (B, 3, h, w), (B, 1, h, w) float32
        "choose_input": null | "choose",               # (B, N) int64 row * w + col: then the output is (B, N, C)
        "output_name": "features",                     # (B, C, h, w) without choose_input
        "crop_hw": [96, 96], "crop_resize": "stretch", # the box is resized to crop_hw, aspect not kept
        "pixel_scale": 0.00392156862745098, "rgb_mean": [0.485, 0.456, 0.406], "rgb_std": [0.229, 0.224, 0.225],
        "depth_encoding": {"type": "metres_minus_median", "clip_m": 1.0, "invalid_value": 0.0,
                           "interpolation": "nearest"},   # clip(d - median, +-clip_m) / clip_m, 0 where no depth
        "feature_dim": 64
      },
      "pose": {
        "file": "pose.onnx", "file_int8": "pose.onnx" | null,   # a float graph may serve precision int8
        "points_input": "points", "features_input": "features",  # (B, N, 3) centred metres, (B, N, C)
        "quat_output": "quat", "trans_output": "trans", "conf_output": "conf",   # (B, N, 4), (B, N, 3), (B, N)
        "hypotheses": "per_point" | "most_confident",  # optional, absent = per_point; most_confident: the graph
                                                       # picks the most confident point itself and gives (B, 4),
                                                       # (B, 3) = that point + its offset, (B,)
        "num_points": 256, "depth_range_m": [0.1, 10.0],
        "points_centring": "mean", "translation": "point_offset", "quaternion_order": "wxyz"
      },
      "pallet_types": [{
        "name": "epal", "class_id": 0,                 # the detector class that reports this type; types that
                                                       # share a class are told apart by their fit to the depth
        "size_m": [1.2, 0.8, 0.144], "diameter_m": 1.449,
        "points_file": "pallets/epal.npy",             # (n, 3) float32 model points, pallet frame, metres
        "boxes_m": [[[x0, y0, z0], [x1, y1, z1]], ...] | null,   # (k, 2, 3) boards/blocks (ICP needs them)
        "symmetries": [[[1, 0, 0, 0], ...], ...],      # (S, 4, 4) rigid, identity first
        "pockets_m": {"+x": [[[..], [..]], [[..], [..]]], ...},   # face -> (2, 2, 3) left, right opening
        "refine_starts": [[15.0, 0.0, 0.0], ...]       # (S, 3) extra ICP starts: yaw deg, dx m, dy m
      }],
      "files": {"detector.onnx": "<sha256 hex>", ...}  # exactly the files named above
    }

A format_version 1 manifest (one `pallet_model`, `classes` at the top, provenance/checks/scores inside)
reads as one pallet type (`upgrade_v1`). Every key is checked: unknown keys are errors.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from .manifest_fields import (BundleError, FieldError, Fields, constant, graph_file, nonempty_name, positive,
                              relative_name, rgb_norm)
from .pallet_geometry import default_refine_starts, derive_pockets_m
from .pallet_type import PalletType

__all__ = ["BundleError", "FieldError", "DetectorSpec", "FusionSpec", "PoseSpec", "PalletType", "Manifest",
           "FORMAT", "FORMAT_VERSION", "POSE_HYPOTHESES", "read_manifest", "relative_name", "upgrade_v1"]

FORMAT = "pallet6d-bundle"
FORMAT_VERSION = 2
# keys of format_version 1 that carry nothing the runtime uses (model config, the runtime's own choices)
_V1_IGNORED = {"detector": ("scale",), "fusion": ("attention", "attention_stride"), "pose": ("attention",)}
_V1_REPORT = ("provenance", "checks", "scores")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


# -- the schema -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DetectorSpec:
    """The detector graph: letterboxed RGB in, YOLOv8 boxes and class scores out."""

    file: str
    file_int8: str | None
    input_name: str
    output_name: str
    input_hw: tuple[int, int]
    letterbox_pad_value: int
    pixel_scale: float
    rgb_mean: tuple[float, float, float]
    rgb_std: tuple[float, float, float]
    channel_order: str
    classes: tuple[str, ...]
    source: str = "pallet6d"
    layout: str = "yolov8"
    input_sizes: tuple[tuple[int, int], ...] | None = None   # None: (input_hw,)
    depth_max_m: float | None = None   # None: RGB in; else RGB-D (`detector.depth_channel`)

    def __post_init__(self) -> None:
        graph_file("file", self.file)
        graph_file("file_int8", self.file_int8)
        if self.depth_max_m is not None and not (math.isfinite(self.depth_max_m) and self.depth_max_m > 0):
            raise FieldError("depth_max_m", f"must be a positive number of metres or absent, got {self.depth_max_m}")
        _check_input_hw("input_hw", self.input_hw)
        sizes = (tuple(self.input_hw),) if self.input_sizes is None else \
            tuple(tuple(int(v) for v in hw) for hw in self.input_sizes)
        if not sizes:
            raise FieldError("input_sizes", "must list at least one [H, W] (leave it out for input_hw alone)")
        for i, hw in enumerate(sizes):
            if len(hw) != 2:
                raise FieldError(f"input_sizes[{i}]", f"must be [H, W], got {list(hw)}")
            _check_input_hw(f"input_sizes[{i}]", hw)
        dup = next((hw for i, hw in enumerate(sizes) if hw in sizes[:i]), None)
        if dup is not None:
            raise FieldError("input_sizes", f"lists {list(dup)} twice")
        if tuple(self.input_hw) not in sizes:
            raise FieldError("input_hw", f"{list(self.input_hw)} must be one of input_sizes "
                                         f"{[list(hw) for hw in sizes]} (it is the reference size)")
        object.__setattr__(self, "input_hw", tuple(self.input_hw))
        object.__setattr__(self, "input_sizes", sizes)
        if not 0 <= self.letterbox_pad_value <= 255:
            raise FieldError("letterbox_pad_value", f"must be in [0, 255], got {self.letterbox_pad_value}")
        rgb_norm(self.pixel_scale, self.rgb_std)
        if self.channel_order not in ("RGB", "BGR"):
            raise FieldError("channel_order", f"must be 'RGB' or 'BGR', got {self.channel_order!r}")
        constant("layout", self.layout, "yolov8")
        if not self.classes or not all(isinstance(c, str) and c.strip() for c in self.classes) \
                or len(set(self.classes)) != len(self.classes):
            raise FieldError("classes", f"must be a non-empty list of distinct names, got {list(self.classes)}")
        if self.source not in ("pallet6d", "external"):
            raise FieldError("source", f"must be 'pallet6d' or 'external', got {self.source!r}")
        for key in ("input_name", "output_name"):
            nonempty_name(key, getattr(self, key))

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def input_channels(self) -> int:
        """3 (RGB), or 4 when the graph also takes depth."""
        return 3 if self.depth_max_m is None else 4

    @property
    def multi_size(self) -> bool:
        """Whether the graph takes more than one input size (then its height and width axes are dynamic)."""
        return len(self.input_sizes) > 1

    @classmethod
    def from_fields(cls, d: Fields) -> "DetectorSpec":
        return d.build(cls, file=d.str("file"), file_int8=d.str("file_int8", None), input_name=d.str("input_name"),
                       output_name=d.str("output_name"), input_hw=d.ints("input_hw", 2),
                       letterbox_pad_value=d.int("letterbox_pad_value"), pixel_scale=d.num("pixel_scale"),
                       rgb_mean=d.nums("rgb_mean", 3), rgb_std=d.nums("rgb_std", 3),
                       channel_order=d.str("channel_order"), classes=d.names("classes"), source=d.str("source"),
                       layout=d.str("layout"), input_sizes=d.int_rows("input_sizes", 2, None),
                       depth_max_m=_opt_num(d.get("depth_max_m", (int, float), None)))

    def to_dict(self) -> dict:
        """The section as written; `input_sizes` only when it lists more than `input_hw`, so a single-size
        bundle's manifest stays readable by runtimes that do not know the field (they refuse unknown keys)."""
        out = {"file": self.file, "file_int8": self.file_int8, "input_name": self.input_name,
               "output_name": self.output_name, "input_hw": list(self.input_hw),
               "letterbox_pad_value": self.letterbox_pad_value, "pixel_scale": self.pixel_scale,
               "rgb_mean": list(self.rgb_mean), "rgb_std": list(self.rgb_std), "channel_order": self.channel_order,
               "layout": self.layout, "classes": list(self.classes), "source": self.source}
        if self.multi_size:
            out["input_sizes"] = [list(hw) for hw in self.input_sizes]
        if self.depth_max_m is not None:   # absent for RGB: older runtimes refuse unknown keys
            out["depth_max_m"] = self.depth_max_m
        return out


def _opt_num(v) -> float | None:
    return None if v is None else float(v)


def _check_input_hw(key: str, hw: tuple[int, ...]) -> None:
    if min(hw) <= 0 or any(v % 32 for v in hw):
        raise FieldError(key, f"must be positive multiples of 32 (YOLOv8 stride), got {list(hw)}")


@dataclass(frozen=True)
class FusionSpec:
    """The fusion graph: RGB and depth crops in, per-pixel fused features out (or per-point ones, when the
    graph takes `choose_input` and gathers the sampled pixels itself)."""

    file: str
    file_int8: str | None
    rgb_input: str
    depth_input: str
    output_name: str
    crop_hw: tuple[int, int]
    pixel_scale: float
    rgb_mean: tuple[float, float, float]
    rgb_std: tuple[float, float, float]
    depth_clip_m: float
    feature_dim: int
    choose_input: str | None = None

    def __post_init__(self) -> None:
        graph_file("file", self.file)
        graph_file("file_int8", self.file_int8)
        if min(self.crop_hw) <= 0:
            raise FieldError("crop_hw", f"must be positive, got {list(self.crop_hw)}")
        rgb_norm(self.pixel_scale, self.rgb_std)
        positive("depth_encoding.clip_m", self.depth_clip_m)
        if self.feature_dim <= 0:
            raise FieldError("feature_dim", f"must be a positive integer, got {self.feature_dim}")
        names = [self.rgb_input, self.depth_input] + ([self.choose_input] if self.choose_input is not None else [])
        for key, value in zip(("rgb_input", "depth_input", "choose_input"), names):
            nonempty_name(key, value)
        if len(set(names)) != len(names):
            raise FieldError("rgb_input", f"the graph's inputs need distinct names, got {names}")

    @classmethod
    def from_fields(cls, f: Fields) -> "FusionSpec":
        f.constant("crop_resize", "stretch")
        enc = f.section("depth_encoding")
        enc.constant("type", "metres_minus_median")
        enc.constant("interpolation", "nearest")
        if enc.num("invalid_value") != 0.0:
            raise enc.fail("invalid_value", f"must be 0.0 (pixels without depth), got {enc.data['invalid_value']!r}")
        clip_m = enc.num("clip_m")
        enc.build(dict)
        return f.build(cls, file=f.str("file"), file_int8=f.str("file_int8", None), rgb_input=f.str("rgb_input"),
                       depth_input=f.str("depth_input"), choose_input=f.str("choose_input", None),
                       output_name=f.str("output_name"), crop_hw=f.ints("crop_hw", 2),
                       pixel_scale=f.num("pixel_scale"), rgb_mean=f.nums("rgb_mean", 3), rgb_std=f.nums("rgb_std", 3),
                       depth_clip_m=clip_m, feature_dim=f.int("feature_dim"))

    def to_dict(self) -> dict:
        return {"file": self.file, "file_int8": self.file_int8, "rgb_input": self.rgb_input,
                "depth_input": self.depth_input, "choose_input": self.choose_input, "output_name": self.output_name,
                "crop_hw": list(self.crop_hw), "crop_resize": "stretch", "pixel_scale": self.pixel_scale,
                "rgb_mean": list(self.rgb_mean), "rgb_std": list(self.rgb_std),
                "depth_encoding": {"type": "metres_minus_median", "clip_m": self.depth_clip_m, "invalid_value": 0.0,
                                   "interpolation": "nearest"},
                "feature_dim": self.feature_dim}


_POSE_CONVENTIONS = (("points_centring", "mean"), ("translation", "point_offset"), ("quaternion_order", "wxyz"))
POSE_HYPOTHESES = ("per_point", "most_confident")


@dataclass(frozen=True)
class PoseSpec:
    """The pose graph: centred points and their features in, per-point quaternion, translation offset and
    confidence out (`hypotheses` "per_point"), or the most confident point's alone (`hypotheses` "most_confident":
    quaternion (B, 4), that point plus its offset (B, 3), confidence (B,))."""

    file: str
    file_int8: str | None
    points_input: str
    features_input: str
    quat_output: str
    trans_output: str
    conf_output: str
    num_points: int
    depth_range_m: tuple[float, float]
    hypotheses: str = "per_point"

    def __post_init__(self) -> None:
        graph_file("file", self.file)
        if self.hypotheses not in POSE_HYPOTHESES:
            raise FieldError("hypotheses", f"must be one of {', '.join(POSE_HYPOTHESES)}, got {self.hypotheses!r}")
        graph_file("file_int8", self.file_int8)
        if self.num_points <= 0:
            raise FieldError("num_points", f"must be a positive integer, got {self.num_points}")
        lo, hi = self.depth_range_m
        if not 0 <= lo < hi:
            raise FieldError("depth_range_m", f"must be [min, max] with 0 <= min < max, got {list(self.depth_range_m)}")
        for key in ("points_input", "features_input", "quat_output", "trans_output", "conf_output"):
            nonempty_name(key, getattr(self, key))

    @classmethod
    def from_fields(cls, p: Fields) -> "PoseSpec":
        for key, expected in _POSE_CONVENTIONS:
            p.constant(key, expected)
        return p.build(cls, file=p.str("file"), file_int8=p.str("file_int8", None),
                       points_input=p.str("points_input"), features_input=p.str("features_input"),
                       quat_output=p.str("quat_output"), trans_output=p.str("trans_output"),
                       conf_output=p.str("conf_output"), num_points=p.int("num_points"),
                       depth_range_m=p.nums("depth_range_m", 2), hypotheses=p.str("hypotheses", "per_point"))

    def to_dict(self) -> dict:
        return {"file": self.file, "file_int8": self.file_int8, "points_input": self.points_input,
                "features_input": self.features_input, "quat_output": self.quat_output,
                "trans_output": self.trans_output, "conf_output": self.conf_output, "hypotheses": self.hypotheses,
                "num_points": self.num_points, "depth_range_m": list(self.depth_range_m), **dict(_POSE_CONVENTIONS)}


@dataclass(frozen=True)
class Manifest:
    """The contract of a bundle (manifest.json). File names are relative to the bundle folder."""

    name: str
    config: str
    precision: tuple[str, ...]
    detector: DetectorSpec
    fusion: FusionSpec
    pose: PoseSpec
    pallet_types: tuple[PalletType, ...]
    files: Mapping[str, str]
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        nonempty_name("name", self.name)
        if "fp32" not in self.precision or not set(self.precision) <= {"fp32", "int8"} \
                or len(set(self.precision)) != len(self.precision):
            raise FieldError("precision", f"must list 'fp32' and optionally 'int8', got {list(self.precision)}")
        if "int8" in self.precision and None in (self.detector.file_int8, self.fusion.file_int8, self.pose.file_int8):
            raise FieldError("precision", "lists 'int8' but not every graph has a file_int8")
        types = tuple(self.pallet_types)
        if not types:
            raise FieldError("pallet_types", "must list at least one pallet type")
        nc = self.detector.num_classes
        for i, t in enumerate(types):
            if t.class_id >= nc:
                raise FieldError(f"pallet_types[{i}].class_id", f"is {t.class_id}, but the detector has {nc} "
                                                                f"classes {list(self.detector.classes)}")
        names = [t.name for t in types]
        dup = next((v for v in names if names.count(v) > 1), None)
        if dup is not None:
            raise FieldError("pallet_types", f"has two types with name {dup!r}")
        if self.detector.source == "pallet6d":
            missing = sorted(set(range(nc)) - {t.class_id for t in types})
            if missing:
                raise FieldError("pallet_types", f"has no type for detector class {missing[0]} "
                                                 f"({self.detector.classes[missing[0]]!r}); each class of a "
                                                 "pallet6d detector is a pallet type")
        for rel, digest in self.files.items():
            relative_name("files", rel)
            if not isinstance(digest, str) or not _SHA256.match(digest):
                raise FieldError(f"files.{rel}", f"must be a sha256 in lowercase hex, got {digest!r}")
        referenced = set(self.referenced_files())
        for rel in sorted(referenced - set(self.files)):
            raise FieldError("files", f"lacks the sha256 of {rel!r}")
        for rel in sorted(set(self.files) - referenced):
            raise FieldError("files", f"lists {rel!r}, which no field of the manifest names")
        object.__setattr__(self, "pallet_types", types)
        object.__setattr__(self, "precision", tuple(self.precision))

    @property
    def classes(self) -> tuple[str, ...]:
        return self.detector.classes

    def referenced_files(self) -> tuple[str, ...]:
        """Every file the manifest's fields name, each once."""
        names = [self.detector.file, self.detector.file_int8, self.fusion.file, self.fusion.file_int8, self.pose.file,
                 self.pose.file_int8, *(t.points_file for t in self.pallet_types)]
        return tuple(dict.fromkeys(n for n in names if n is not None))

    @classmethod
    def from_dict(cls, data: dict, source: str = "manifest.json") -> "Manifest":
        """Parse a format_version 2 manifest. :raises BundleError: naming `source` and the field."""
        m = Fields(data, "", source, FORMAT_VERSION)
        if m.get("format", str) != FORMAT:
            raise m.fail("format", f"must be {FORMAT!r}, got {data.get('format')!r}")
        version = m.get("format_version", int)
        if version not in (1, FORMAT_VERSION):
            raise BundleError(f"{source}: format_version {version!r} is not supported "
                              f"(this pallet6d reads versions 1 and {FORMAT_VERSION})")
        m.version = version
        types_raw = m.get("pallet_types", list)
        types = tuple(PalletType.from_fields(Fields(t, f"pallet_types[{i}]", source, version))
                      for i, t in enumerate(types_raw))
        files = m.get("files", dict)
        return m.build(cls, name=m.str("name"), config=m.str("config"), precision=tuple(m.names("precision")),
                       detector=DetectorSpec.from_fields(m.section("detector")),
                       fusion=FusionSpec.from_fields(m.section("fusion")),
                       pose=PoseSpec.from_fields(m.section("pose")), pallet_types=types, files=dict(files),
                       format_version=version)

    def to_dict(self) -> dict:
        """The manifest as written (always the current format version)."""
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "name": self.name, "config": self.config,
                "precision": list(self.precision), "detector": self.detector.to_dict(),
                "fusion": self.fusion.to_dict(), "pose": self.pose.to_dict(),
                "pallet_types": [t.to_dict() for t in self.pallet_types], "files": dict(self.files)}


def upgrade_v1(data: dict, source: str = "manifest.json") -> tuple[dict, dict]:
    """A format_version 1 manifest as a version 2 dict (still marked version 1) and its report.

    The one `pallet_model` becomes pallet type 0 for the first class whose name says "pallet" (else class 0),
    with the default ICP starts for its size and the fork pockets its boards and blocks leave open;
    `provenance`, `checks` and `scores` become the report. Keys that carried nothing the runtime uses are
    dropped; any other key stays and is refused like in version 2.
    """
    v1 = {k: v for k, v in data.items() if k not in _V1_REPORT}
    report = {k: data[k] for k in _V1_REPORT if isinstance(data.get(k), dict)}
    m = Fields(v1, "", source)
    classes = m.names("classes")
    units = m.str("depth_units")
    if units != "metres":
        raise m.fail("depth_units", f"must be 'metres', got {units!r}")
    sections = {}
    for key in ("detector", "fusion", "pose"):
        sec = dict(m.get(key, dict))
        for ignored in _V1_IGNORED[key]:
            sec.pop(ignored, None)
        sections[key] = sec
    det = sections["detector"]
    nc = det.pop("num_classes", len(classes))
    if nc != len(classes):
        raise m.fail("detector.num_classes", f"is {nc} but 'classes' names {len(classes)}")
    det["classes"] = list(classes)
    det.setdefault("source", "pallet6d")
    # the runtime picks the most confident point's pose: the only selection a version 1 bundle could name
    if sections["pose"].pop("selection", "max_confidence") != "max_confidence":
        raise m.fail("pose.selection", "must be 'max_confidence'")
    pm = dict(m.get("pallet_model", dict))
    lowered = [c.lower() for c in classes]
    pm["class_id"] = next((i for i, c in enumerate(lowered) if "pallet" in c), 0)
    if isinstance(pm.get("size_m"), list):
        size = Fields(pm, "pallet_model", source).nums("size_m", 3)
        pm.setdefault("refine_starts", default_refine_starts(size).tolist())
        boxes = pm.get("boxes_m")
        if boxes is not None and "pockets_m" not in pm:
            try:
                pm["pockets_m"] = {f: v.tolist() for f, v in derive_pockets_m(np.asarray(boxes, float)).items()}
            except (TypeError, ValueError):
                pm["pockets_m"] = {}   # malformed boxes: the type's own check names them
    pm.setdefault("pockets_m", {})
    pm.setdefault("refine_starts", [])
    out = {k: v for k, v in v1.items() if k not in ("classes", "depth_units", "pallet_model", *sections)}
    out.update(sections)
    out["pallet_types"] = [pm]
    return out, report


def read_manifest(data: Any, source: str = "manifest.json") -> tuple[Manifest, dict]:
    """Parse a manifest of format version 1 or 2: the `Manifest` and, for version 1, the report it held."""
    if not isinstance(data, dict):
        raise BundleError(f"{source}: must hold a JSON object")
    if data.get("format") == FORMAT and data.get("format_version") == 1:
        data, report = upgrade_v1(data, source)
        return Manifest.from_dict(data, source), report
    return Manifest.from_dict(data, source), {}
