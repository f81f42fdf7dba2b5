"""The model bundle: a folder with the ONNX graphs and a `manifest.json`, the one contract between
`pallet6d export` (writer) and the runtime (reader). numpy + json + onnxruntime only.

manifest.json (format_version 1)::

    {
      "format": "pallet6d-bundle", "format_version": 1,
      "name": "edge-random", "config": "edge",                 # config: the export config it came from
      "classes": ["pallet"],                                   # detector class names, index = class id
      "depth_units": "metres",                                 # depth fed to pose_inputs, points, translations
      "precision": ["fp32", "int8"],                           # graphs available ("int8" only if all three have file_int8)
      "detector": {
        "file": "detector.onnx", "file_int8": "detector.int8.onnx" | null,
        "input_name": "images", "output_name": "output0",
        "input_hw": [192, 640],                                # letterboxed input, multiples of 32
        "letterbox_pad_value": 114, "pixel_scale": 0.00392156862745098,   # = 1/255
        "rgb_mean": [0, 0, 0], "rgb_std": [1, 1, 1],           # applied after pixel_scale
        "channel_order": "RGB",
        "layout": "yolov8",                                    # output (B, 4 + nc, A): cx, cy, w, h (input px), sigmoid scores
        "num_classes": 1, "source": "pallet6d" | "external"
      },
      "fusion": {
        "file": "fusion.onnx", "file_int8": "fusion.int8.onnx" | null,
        "rgb_input": "rgb", "depth_input": "depth",            # (B, 3, h, w), (B, 1, h, w) float32, B dynamic
        "output_name": "features",                             # (B, feature_dim, h, w)
        "crop_hw": [96, 96], "crop_resize": "stretch",         # box resized to crop_hw, aspect not kept
        "pixel_scale": 0.00392156862745098, "rgb_mean": [0.485, 0.456, 0.406], "rgb_std": [0.229, 0.224, 0.225],
        "depth_encoding": {"type": "metres_minus_median", "clip_m": 1.0, "invalid_value": 0.0,
                           "interpolation": "nearest"},        # clip(d - median_valid, +-clip) / clip
        "feature_dim": 64
      },
      "pose": {
        "file": "pose.onnx", "file_int8": "pose.int8.onnx" | "pose.onnx" | null,   # a float graph may run at int8
        "points_input": "points", "features_input": "features",        # (B, N, 3) centred metres, (B, N, C)
        "quat_output": "quat", "trans_output": "trans", "conf_output": "conf",   # (B, N, 4), (B, N, 3), (B, N)
        "num_points": 256, "depth_range_m": [0.1, 10.0],
        "points_centring": "mean",            # points = sampled points - their mean (the centre)
        "translation": "point_offset",        # object translation = centre + points[i] + trans[i]
        "quaternion_order": "wxyz",           # R(quat) maps pallet-frame points into the camera frame
        "selection": "max_confidence"
      },
      "pallet_model": {
        "name": "epal", "size_m": [1.2, 0.8, 0.144], "diameter_m": 1.44,
        "points_file": "pallet_points.npy",   # (n, 3) float32, pallet frame, metres
        "boxes_m": [[[x0,y0,z0],[x1,y1,z1]], ...],   # optional: boards/blocks as (k, 2, 3) min/max corners
                                                     # (pose refinement; without them it is skipped)
        "symmetries": [[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], ...]   # (S, 4, 4), identity first, metres
      },
      "files": {"detector.onnx": "<sha256 hex>", ...},          # every file above; verified on load
      "provenance": {"command": "...", "seed": 0, "git_commit": "...", "created": "ISO-8601 UTC",
                     "random_init": true, "checkpoint": null, "training": null | {...},
                     "calibration": null | "sim:virtual-occluded ..." | "synthetic ..."},
      "checks": {"parity": {"detector": {"max_abs": ..., "tolerance": ...}, ...},
                 "int8": {"fusion": {"max_abs": ..., "rel_rms": ..., "corr": ...}, ...},
                 "gflops": {"detector_per_frame": ..., "fusion_per_pallet": ..., "pose_per_pallet": ...},
                 "params": {...}},
      "scores": {}                            # accuracy on a dataset, filled after training/evaluation
    }

`load_bundle(path)` parses and validates it into a `Bundle` (paths resolved, sha256 verified), raising
`BundleError` naming the file and field; `check_bundle(path)` additionally opens every graph with
onnxruntime and checks input/output names and shapes against the manifest, returning a list of problems.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .pose_inputs import PoseInputSpec

__all__ = ["BundleError", "Bundle", "DetectorSpec", "FusionSpec", "PoseSpec", "PalletSpec", "load_bundle",
           "check_bundle", "sha256_file", "FORMAT", "FORMAT_VERSION", "MANIFEST"]

log = logging.getLogger(__name__)

FORMAT = "pallet6d-bundle"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"


class BundleError(ValueError):
    """A bundle that cannot be used: the message names the bundle file and the field or graph at fault."""


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class _Reader:
    """Typed access to one manifest section; errors name `manifest.json: section.key`."""

    def __init__(self, data: Any, where: str, manifest: Path) -> None:
        if not isinstance(data, dict):
            raise BundleError(f"{manifest}: '{where}' must be an object, got {type(data).__name__}")
        self.data, self.where, self.manifest = data, where, manifest

    def fail(self, key: str, msg: str) -> BundleError:
        return BundleError(f"{self.manifest}: field '{self.where}.{key}' {msg}")

    def get(self, key: str, types, default: Any = ...) -> Any:
        if key not in self.data:
            if default is ...:
                raise self.fail(key, "is missing")
            return default
        value = self.data[key]
        if value is None and default is None:
            return None
        if not isinstance(value, types):
            raise self.fail(key, f"must be {types}, got {value!r}")
        return value

    def str(self, key: str, default: Any = ...) -> str:
        return self.get(key, str, default)

    def num(self, key: str, default: Any = ...) -> float:
        value = self.get(key, (int, float), default)
        if isinstance(value, bool) or not np.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        return float(value)

    def posint(self, key: str) -> int:
        value = self.get(key, int)
        if isinstance(value, bool) or value <= 0:
            raise self.fail(key, f"must be a positive integer, got {value!r}")
        return value

    def ints(self, key: str, n: int) -> tuple[int, ...]:
        value = self.get(key, list)
        if len(value) != n or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value):
            raise self.fail(key, f"must be a list of {n} positive integers, got {value!r}")
        return tuple(value)

    def floats(self, key: str, n: int) -> tuple[float, ...]:
        value = self.get(key, list)
        if len(value) != n or not all(isinstance(v, (int, float)) and np.isfinite(v) for v in value):
            raise self.fail(key, f"must be a list of {n} numbers, got {value!r}")
        return tuple(float(v) for v in value)

    def section(self, key: str) -> "_Reader":
        return _Reader(self.get(key, dict), f"{self.where}.{key}" if self.where else key, self.manifest)

    def file(self, key: str, root: Path, optional: bool = False) -> Path | None:
        rel = self.get(key, str, None if optional else ...)
        if rel is None:
            return None
        path = (root / rel).resolve()
        if root.resolve() not in path.parents:
            raise self.fail(key, f"points outside the bundle folder: {rel!r}")
        if not path.is_file():
            raise self.fail(key, f"names {rel!r}, which is not in the bundle ({path} does not exist)")
        return path


@dataclass(frozen=True)
class DetectorSpec:
    file: Path
    file_int8: Path | None
    input_name: str
    output_name: str
    input_hw: tuple[int, int]
    letterbox_pad_value: int
    pixel_scale: float
    rgb_mean: tuple[float, float, float]
    rgb_std: tuple[float, float, float]
    channel_order: str
    layout: str
    num_classes: int


@dataclass(frozen=True)
class FusionSpec:
    file: Path
    file_int8: Path | None
    rgb_input: str
    depth_input: str
    output_name: str
    crop_hw: tuple[int, int]
    pixel_scale: float
    rgb_mean: tuple[float, float, float]
    rgb_std: tuple[float, float, float]
    depth_clip_m: float
    feature_dim: int


@dataclass(frozen=True)
class PoseSpec:
    file: Path
    file_int8: Path | None
    points_input: str
    features_input: str
    quat_output: str
    trans_output: str
    conf_output: str
    num_points: int
    depth_range_m: tuple[float, float]


@dataclass(frozen=True)
class PalletSpec:
    """:ivar symmetries: (S, 4, 4) float64, identity first. :ivar points_file: (n, 3) float32 metres.
    :ivar boxes_m: (k, 2, 3) float64 min/max corners of the boards and blocks, pallet frame, or None."""

    name: str
    size_m: tuple[float, float, float]
    diameter_m: float
    points_file: Path
    symmetries: np.ndarray
    boxes_m: np.ndarray | None = None

    def points(self) -> np.ndarray:
        """(n, 3) float32 model points in the pallet frame, metres."""
        pts = np.load(self.points_file, allow_pickle=False)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise BundleError(f"{self.points_file}: expected (n, 3) model points, got {pts.shape}")
        return pts.astype(np.float32)


@dataclass(frozen=True)
class Bundle:
    """A validated model bundle (`load_bundle`). Paths are absolute."""

    root: Path
    name: str
    config: str
    classes: tuple[str, ...]
    precision: tuple[str, ...]
    detector: DetectorSpec
    fusion: FusionSpec
    pose: PoseSpec
    pallet: PalletSpec
    provenance: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)
    scores: dict = field(default_factory=dict)
    manifest: dict = field(default_factory=dict, repr=False)

    def graph(self, stage: str, precision: str = "fp32") -> Path:
        """Path of the `stage` ("detector", "fusion", "pose") graph at `precision` ("fp32" or "int8")."""
        spec = {"detector": self.detector, "fusion": self.fusion, "pose": self.pose}.get(stage)
        if spec is None:
            raise ValueError(f"unknown stage {stage!r}; use detector, fusion or pose")
        if precision == "fp32":
            return spec.file
        if precision == "int8":
            if spec.file_int8 is None:
                raise BundleError(f"bundle {self.root} has no int8 {stage} graph (precision: {list(self.precision)}); "
                                  "export it with --int8 or run with fp32")
            return spec.file_int8
        raise ValueError(f"precision must be 'fp32' or 'int8', got {precision!r}")

    def pose_input_spec(self) -> PoseInputSpec:
        """The preprocessing parameters for `pose_inputs.prepare_pose_inputs`."""
        f = self.fusion
        return PoseInputSpec(crop_hw=f.crop_hw, rgb_mean=f.rgb_mean, rgb_std=f.rgb_std, depth_clip_m=f.depth_clip_m,
                             num_points=self.pose.num_points, depth_range_m=self.pose.depth_range_m,
                             pixel_scale=f.pixel_scale)


def _read_manifest(root: Path) -> dict:
    if not root.is_dir():
        raise BundleError(f"model bundle {root} is not a folder")
    path = root / MANIFEST
    if not path.is_file():
        raise BundleError(f"model bundle {root} has no {MANIFEST}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BundleError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise BundleError(f"{path}: must hold a JSON object")
    if data.get("format") != FORMAT:
        raise BundleError(f"{path}: field 'format' must be {FORMAT!r}, got {data.get('format')!r}")
    if data.get("format_version") != FORMAT_VERSION:
        raise BundleError(f"{path}: format_version {data.get('format_version')!r} is not supported "
                          f"(this pallet6d reads version {FORMAT_VERSION})")
    return data


def _verify_files(m: _Reader, root: Path, referenced: list[Path]) -> None:
    files = m.get("files", dict)
    for path in referenced:
        rel = path.relative_to(root.resolve()).as_posix()
        if rel not in files:
            raise m.fail("files", f"lacks the sha256 of {rel!r}")
    for rel, digest in files.items():
        path = (root / rel)
        if not path.is_file():
            raise m.fail("files", f"lists {rel!r}, which is not in the bundle")
        actual = sha256_file(path)
        if actual != digest:
            raise BundleError(f"{root / MANIFEST}: sha256 of {rel!r} is {actual}, the manifest says {digest}: "
                              "the file was changed or damaged after export")


def load_bundle(path: str | Path, verify_sha256: bool = True) -> Bundle:
    """Read and validate a bundle folder (does not open the graphs; see `check_bundle`).

    :raises BundleError: naming the file and field at fault.
    """
    root = Path(path).resolve()
    data = _read_manifest(root)
    man = root / MANIFEST
    m = _Reader(data, "", man)
    classes = m.get("classes", list)
    if not classes or not all(isinstance(c, str) for c in classes):
        raise BundleError(f"{man}: field 'classes' must be a non-empty list of names, got {classes!r}")
    d = m.section("detector")
    if d.str("layout") != "yolov8":
        raise d.fail("layout", f"must be 'yolov8', got {d.data.get('layout')!r}")
    if d.str("channel_order") not in ("RGB", "BGR"):
        raise d.fail("channel_order", "must be 'RGB' or 'BGR'")
    nc = d.posint("num_classes")
    if nc != len(classes):
        raise d.fail("num_classes", f"is {nc} but 'classes' names {len(classes)}")
    input_hw = d.ints("input_hw", 2)
    if input_hw[0] % 32 or input_hw[1] % 32:
        raise d.fail("input_hw", f"must be multiples of 32 (YOLOv8 stride), got {list(input_hw)}")
    detector = DetectorSpec(
        file=d.file("file", root), file_int8=d.file("file_int8", root, optional=True),
        input_name=d.str("input_name"), output_name=d.str("output_name"), input_hw=input_hw,
        letterbox_pad_value=int(d.num("letterbox_pad_value")), pixel_scale=d.num("pixel_scale"),
        rgb_mean=d.floats("rgb_mean", 3), rgb_std=d.floats("rgb_std", 3), channel_order=d.str("channel_order"),
        layout="yolov8", num_classes=nc)
    f = m.section("fusion")
    enc = f.section("depth_encoding")
    if enc.str("type") != "metres_minus_median":
        raise enc.fail("type", f"must be 'metres_minus_median', got {enc.data.get('type')!r}")
    fusion = FusionSpec(
        file=f.file("file", root), file_int8=f.file("file_int8", root, optional=True),
        rgb_input=f.str("rgb_input"), depth_input=f.str("depth_input"), output_name=f.str("output_name"),
        crop_hw=f.ints("crop_hw", 2), pixel_scale=f.num("pixel_scale"), rgb_mean=f.floats("rgb_mean", 3),
        rgb_std=f.floats("rgb_std", 3), depth_clip_m=enc.num("clip_m"), feature_dim=f.posint("feature_dim"))
    p = m.section("pose")
    for key, expected in (("points_centring", "mean"), ("translation", "point_offset"), ("quaternion_order", "wxyz")):
        if p.str(key) != expected:
            raise p.fail(key, f"must be {expected!r} (the only convention this runtime knows), got {p.data.get(key)!r}")
    pose = PoseSpec(
        file=p.file("file", root), file_int8=p.file("file_int8", root, optional=True),
        points_input=p.str("points_input"), features_input=p.str("features_input"), quat_output=p.str("quat_output"),
        trans_output=p.str("trans_output"), conf_output=p.str("conf_output"), num_points=p.posint("num_points"),
        depth_range_m=p.floats("depth_range_m", 2))
    pm = m.section("pallet_model")
    sym = np.asarray(pm.get("symmetries", list), dtype=np.float64)
    if sym.ndim != 3 or sym.shape[1:] != (4, 4) or not np.allclose(sym[0], np.eye(4)):
        raise pm.fail("symmetries", f"must be (S, 4, 4) rigid transforms with the identity first, got shape {sym.shape}")
    boxes = None
    if pm.data.get("boxes_m") is not None:
        boxes = np.asarray(pm.get("boxes_m", list), dtype=np.float64)
        if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0 or not np.all(np.isfinite(boxes)) \
                or np.any(boxes[:, 1] <= boxes[:, 0]):
            raise pm.fail("boxes_m", f"must be (k, 2, 3) finite min/max corners with max > min, got shape {boxes.shape}")
    pallet = PalletSpec(name=pm.str("name"), size_m=pm.floats("size_m", 3), diameter_m=pm.num("diameter_m"),
                        points_file=pm.file("points_file", root), symmetries=sym, boxes_m=boxes)
    precision = m.get("precision", list)
    if "fp32" not in precision or not set(precision) <= {"fp32", "int8"}:
        raise m.fail("precision", f"must list 'fp32' and optionally 'int8', got {precision!r}")
    if "int8" in precision and None in (detector.file_int8, fusion.file_int8, pose.file_int8):
        raise m.fail("precision", "lists 'int8' but not every graph has a file_int8")
    referenced = [x for x in (detector.file, detector.file_int8, fusion.file, fusion.file_int8, pose.file,
                              pose.file_int8, pallet.points_file) if x is not None]
    if verify_sha256:
        _verify_files(m, root, referenced)
    bundle = Bundle(root=root, name=m.str("name"), config=m.str("config"), classes=tuple(classes),
                    precision=tuple(precision), detector=detector, fusion=fusion, pose=pose, pallet=pallet,
                    provenance=m.get("provenance", dict, {}), checks=m.get("checks", dict, {}),
                    scores=m.get("scores", dict, {}), manifest=data)
    log.debug("loaded bundle %s (%s, %s)", bundle.name, bundle.config, ", ".join(bundle.precision))
    return bundle


def _dims_match(actual: list, expected: list) -> bool:
    """Declared ONNX dims vs expected (None = any); dynamic dims (str/None) match anything."""
    if len(actual) != len(expected):
        return False
    return all(e is None or not isinstance(a, int) or a == e for a, e in zip(actual, expected))


def _check_graph(path: Path, label: str, inputs: dict[str, list], outputs: dict[str, list], run: bool,
                 feeds_hw: dict[str, list]) -> list[str]:
    import onnxruntime as ort

    problems: list[str] = []
    try:
        so = ort.SessionOptions()
        so.log_severity_level = 3
        so.intra_op_num_threads = 1
        sess = ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        return [f"{label} ({path.name}): onnxruntime cannot load it: {exc}"]
    g_in = {i.name: list(i.shape) for i in sess.get_inputs()}
    g_out = {o.name: list(o.shape) for o in sess.get_outputs()}
    for kind, declared, wanted in (("input", g_in, inputs), ("output", g_out, outputs)):
        for name, shape in wanted.items():
            if name not in declared:
                problems.append(f"{label} ({path.name}): has no {kind} named {name!r} (the manifest says so); "
                                f"its {kind}s are {sorted(declared)}")
            elif not _dims_match(declared[name], shape):
                problems.append(f"{label} ({path.name}): {kind} {name!r} has shape {declared[name]}, the manifest "
                                f"implies {['*' if s is None else s for s in shape]}")
    if run and not problems:
        feeds = {n: np.zeros(s, np.float32) for n, s in feeds_hw.items()}
        try:
            result = dict(zip(g_out, sess.run(list(g_out), feeds)))
        except Exception as exc:
            return [f"{label} ({path.name}): running it on zeros of the manifest's shapes failed: {exc}"]
        for name, shape in outputs.items():
            got = list(result[name].shape)
            if not _dims_match(got, shape):
                problems.append(f"{label} ({path.name}): output {name!r} came out {got}, the manifest implies "
                                f"{['*' if s is None else s for s in shape]}")
            elif not np.all(np.isfinite(result[name])):
                problems.append(f"{label} ({path.name}): output {name!r} is not finite on a zero input")
    return problems


def check_bundle(path: str | Path, run: bool = True) -> list[str]:
    """Every problem with a bundle: manifest fields, files, sha256, and each graph's input/output names
    and shapes against the manifest (opened with onnxruntime; with `run`, also run once on zeros).

    :return: human-readable problems; empty when the bundle is usable.
    """
    try:
        b = load_bundle(path)
    except BundleError as exc:
        return [str(exc)]
    problems: list[str] = []
    try:
        pts = b.pallet.points()
        if not np.all(np.isfinite(pts)):
            problems.append(f"{b.pallet.points_file.name}: model points are not finite")
    except (BundleError, ValueError, OSError) as exc:
        problems.append(f"pallet_model.points_file: cannot read it: {exc}")
    d, f, p = b.detector, b.fusion, b.pose
    h, w = d.input_hw
    ch, cw = f.crop_hw
    n, c = p.num_points, f.feature_dim
    for prec in b.precision:
        suffix = "" if prec == "fp32" else " int8"
        problems += _check_graph(
            b.graph("detector", prec), "detector" + suffix, {d.input_name: [None, 3, h, w]},
            {d.output_name: [None, 4 + d.num_classes, None]}, run, {d.input_name: [1, 3, h, w]})
        problems += _check_graph(
            b.graph("fusion", prec), "fusion" + suffix, {f.rgb_input: [None, 3, ch, cw], f.depth_input: [None, 1, ch, cw]},
            {f.output_name: [None, c, ch, cw]}, run, {f.rgb_input: [2, 3, ch, cw], f.depth_input: [2, 1, ch, cw]})
        problems += _check_graph(
            b.graph("pose", prec), "pose" + suffix, {p.points_input: [None, n, 3], p.features_input: [None, n, c]},
            {p.quat_output: [None, n, 4], p.trans_output: [None, n, 3], p.conf_output: [None, n]}, run,
            {p.points_input: [2, n, 3], p.features_input: [2, n, c]})
    return problems
