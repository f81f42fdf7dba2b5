"""The model bundle: a folder with the ONNX graphs, the pallet types' model points, `manifest.json` (the
immutable contract between `pallet6d export` and the runtime; schema in `manifest.py`) and `report.json`
(how it was made and what it scored: provenance, checks, scores; benchmarks may update it).

`load_bundle(path)` reads and validates the contract into a `Bundle`: every field, every file confined to the
folder with its sha256 verified, each graph's ONNX structure, each pallet type's model points.
`check_bundle(path)` applies exactly that validation, then also opens every graph with onnxruntime, checks
its input/output names and shapes against the manifest and runs it once on zeros. What `check_bundle`
passes, the runtime loads; what the runtime refuses, `check_bundle` reports with the same message.
numpy + json + onnxruntime only.
"""
from __future__ import annotations

import dataclasses
import fcntl
import json
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bundle_files import check_onnx_file, confined_file, read_json, sha256_file
from .manifest import (FORMAT, FORMAT_VERSION, BundleError, DetectorSpec, FieldError, FusionSpec, Manifest,
                       PalletType, PoseSpec, read_manifest)
from .pose_inputs import PoseInputSpec

__all__ = ["BundleError", "Bundle", "DetectorSpec", "FusionSpec", "PoseSpec", "PalletType", "Manifest", "load_bundle",
           "check_bundle", "update_report", "sha256_file", "FORMAT", "FORMAT_VERSION", "MANIFEST", "REPORT"]

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
REPORT = "report.json"
STAGES = ("detector", "fusion", "pose")


@dataclass(frozen=True)
class Bundle:
    """A validated model bundle (`load_bundle`).

    :ivar root: the bundle folder, absolute. :ivar manifest: the contract.
    :ivar pallet_types: every pallet type, model points loaded (`PalletType.points()`).
    :ivar report: provenance, checks and scores (report.json; in a version 1 bundle, the manifest's own).
    """

    root: Path
    manifest: Manifest
    pallet_types: tuple[PalletType, ...]
    report: dict = field(default_factory=dict, repr=False)

    @property
    def name(self) -> str:
        return self.manifest.name

    @property
    def config(self) -> str:
        return self.manifest.config

    @property
    def classes(self) -> tuple[str, ...]:
        return self.manifest.detector.classes

    @property
    def precision(self) -> tuple[str, ...]:
        return self.manifest.precision

    @property
    def detector(self) -> DetectorSpec:
        return self.manifest.detector

    @property
    def fusion(self) -> FusionSpec:
        return self.manifest.fusion

    @property
    def pose(self) -> PoseSpec:
        return self.manifest.pose

    @property
    def pallet(self) -> PalletType:
        """The first pallet type (a bundle of one type: its only one)."""
        return self.pallet_types[0]

    @property
    def pallet_class_ids(self) -> tuple[int, ...]:
        """Detector classes that report a pallet type (an external detector may know other classes too)."""
        return tuple(sorted(t.class_id for t in self.pallet_types))

    def pallet_type_for_class(self, class_id: int) -> PalletType:
        """The pallet type the detector's class `class_id` reports. :raises BundleError: no type for it."""
        for t in self.pallet_types:
            if t.class_id == int(class_id):
                return t
        names = self.classes
        label = f" ({names[int(class_id)]!r})" if 0 <= int(class_id) < len(names) else ""
        raise BundleError(f"bundle {self.root}: detector class {class_id}{label} is no pallet type; types: "
                          + ", ".join(f"{t.class_id} {t.name}" for t in self.pallet_types))

    @property
    def provenance(self) -> dict:
        return self.report.get("provenance") or {}

    @property
    def checks(self) -> dict:
        return self.report.get("checks") or {}

    @property
    def scores(self) -> dict:
        return self.report.get("scores") or {}

    def graph(self, stage: str, precision: str = "fp32") -> Path:
        """Path of the `stage` ("detector", "fusion", "pose") graph at `precision` ("fp32" or "int8")."""
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; use detector, fusion or pose")
        spec = getattr(self.manifest, stage)
        if precision == "fp32":
            return self.root / spec.file
        if precision == "int8":
            if spec.file_int8 is None:
                raise BundleError(f"bundle {self.root} has no int8 {stage} graph (precision: {list(self.precision)}); "
                                  "export it with --int8 or run with fp32")
            return self.root / spec.file_int8
        raise ValueError(f"precision must be 'fp32' or 'int8', got {precision!r}")

    def pose_input_spec(self) -> PoseInputSpec:
        """The preprocessing parameters for `pose_inputs.prepare_pose_inputs`."""
        f = self.fusion
        return PoseInputSpec(crop_hw=f.crop_hw, rgb_mean=f.rgb_mean, rgb_std=f.rgb_std, depth_clip_m=f.depth_clip_m,
                             num_points=self.pose.num_points, depth_range_m=self.pose.depth_range_m,
                             pixel_scale=f.pixel_scale)


def _file_fields(m: Manifest) -> list[tuple[str, str]]:
    """(field, file name) for every file the manifest names."""
    out = []
    for stage in STAGES:
        spec = getattr(m, stage)
        out.append((f"{stage}.file", spec.file))
        if spec.file_int8 is not None:
            out.append((f"{stage}.file_int8", spec.file_int8))
    out += [(f"pallet_types[{i}].points_file", t.points_file) for i, t in enumerate(m.pallet_types)]
    return out


def _load_points(path: Path, source: str, i: int, t: PalletType) -> PalletType:
    where = f"{source}: field 'pallet_types[{i}].points_file' ({t.points_file})"
    try:
        pts = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise BundleError(f"{where}: not a .npy array of model points ({exc})") from None
    if pts.dtype.kind != "f":
        raise BundleError(f"{where}: model points must be floats, got {pts.dtype}")
    try:
        return dataclasses.replace(t, points_m=pts)
    except FieldError as exc:
        raise BundleError(f"{where} {exc.msg}") from None


def read_report(root: Path, fallback: dict) -> dict:
    """report.json of `root` when there is one (else `fallback`). A damaged report is logged and ignored: it
    holds nothing the runtime needs."""
    path = root / REPORT
    if not path.exists():
        return fallback
    try:
        report = read_json(path, "report")
    except BundleError as exc:
        log.warning("ignoring the bundle's report: %s", exc)
        return fallback
    if not isinstance(report, dict):
        log.warning("ignoring the bundle's report: %s must hold a JSON object", path)
        return fallback
    return report


def load_bundle(path: str | Path, verify_sha256: bool = True) -> Bundle:
    """Read and validate a bundle folder (see the module docstring; does not open the graphs with onnxruntime).

    :raises BundleError: naming the file and field (or graph) at fault.
    """
    root = Path(path).resolve()
    if not root.is_dir():
        raise BundleError(f"model bundle {root} is not a folder")
    man = root / MANIFEST
    if not man.is_file():
        raise BundleError(f"model bundle {root} has no {MANIFEST}")
    manifest, legacy_report = read_manifest(read_json(man, "manifest"), str(man))
    # the fields name exactly the files of the `files` map (Manifest checks it)
    resolved = {rel: confined_file(root, rel, f"{man}: field '{key}'") for key, rel in _file_fields(manifest)}
    if verify_sha256:
        for rel, digest in manifest.files.items():
            actual = sha256_file(resolved[rel])
            if actual != digest:
                raise BundleError(f"{man}: sha256 of {rel!r} is {actual}, the manifest says {digest}: "
                                  "the file was changed or damaged after export")
    for stage in STAGES:
        spec = getattr(manifest, stage)
        for rel in dict.fromkeys(r for r in (spec.file, spec.file_int8) if r is not None):
            check_onnx_file(resolved[rel], f"{man}: {stage} graph {rel!r}")
    types = tuple(_load_points(resolved[t.points_file], str(man), i, t) for i, t in enumerate(manifest.pallet_types))
    bundle = Bundle(root=root, manifest=manifest, pallet_types=types, report=read_report(root, legacy_report))
    log.debug("loaded bundle %s (%s, %s; pallet types %s)", bundle.name, bundle.config, ", ".join(bundle.precision),
              ", ".join(t.name for t in types))
    return bundle


def update_report(path: str | Path, key: str | tuple[str, ...], value: Any) -> dict:
    """Set `report[key] = value` in the bundle's report.json (created from the bundle's report when absent);
    a tuple key sets a nested entry (("scores", "int8") -> report["scores"]["int8"]). Atomic, and under a
    lock on the folder, so runs that finish together keep each other's entries. The manifest is never
    touched. :return: the new report."""
    root = Path(path).resolve()
    keys = (key,) if isinstance(key, str) else tuple(key)
    if not keys:
        raise ValueError("update_report needs a key")
    fd = os.open(root, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        report = json.loads(json.dumps(load_bundle(root, verify_sha256=False).report))   # a deep copy
        node = report
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[keys[-1]] = value
        with tempfile.NamedTemporaryFile("w", encoding="utf-8", dir=root, prefix=".report.", delete=False) as tmp:
            tmp.write(json.dumps(report, indent=2) + "\n")
        os.replace(tmp.name, root / REPORT)
    finally:
        os.close(fd)
    return report


def _dims_match(actual: list, expected: list) -> bool:
    """Declared ONNX dims vs expected (None = any); dynamic dims (str/None) match anything."""
    if len(actual) != len(expected):
        return False
    return all(e is None or not isinstance(a, int) or a == e for a, e in zip(actual, expected))


def _check_graph(path: Path, label: str, inputs: dict[str, list], outputs: dict[str, list], run: bool,
                 feeds: dict[str, np.ndarray]) -> list[str]:
    from .sessions import OnnxModel

    try:
        model = OnnxModel(path, threads=1)
    except BundleError as exc:
        return [f"{label}: {exc}"]
    sess = model.session
    problems: list[str] = []
    g_in = {i.name: list(i.shape) for i in sess.get_inputs()}
    g_out = {o.name: list(o.shape) for o in sess.get_outputs()}
    for kind, declared, wanted in (("input", g_in, inputs), ("output", g_out, outputs)):
        for name, shape in wanted.items():
            if name not in declared:
                problems.append(f"{label}: has no {kind} named {name!r} (the manifest says so); "
                                f"its {kind}s are {sorted(declared)}")
            elif not _dims_match(declared[name], shape):
                problems.append(f"{label}: {kind} {name!r} has shape {declared[name]}, the manifest "
                                f"implies {['*' if s is None else s for s in shape]}")
    extra = sorted(set(g_in) - set(inputs))
    if extra:
        problems.append(f"{label}: takes inputs {extra} that the manifest does not name")
    if run and not problems:
        try:
            result = dict(zip(g_out, sess.run(list(g_out), feeds)))
        except Exception as exc:  # onnxruntime raises its own exception types
            return [f"{label}: running it on zeros of the manifest's shapes failed: {exc}"]
        for name, shape in outputs.items():
            got = list(result[name].shape)
            if not _dims_match(got, shape):
                problems.append(f"{label}: output {name!r} came out {got}, the manifest implies "
                                f"{['*' if s is None else s for s in shape]}")
            elif not np.all(np.isfinite(result[name])):
                problems.append(f"{label}: output {name!r} is not finite on a zero input")
    return problems


def _zeros(shape: list[int], dtype=np.float32) -> np.ndarray:
    return np.zeros(shape, dtype)


def check_bundle(path: str | Path, run: bool = True) -> list[str]:
    """Every problem with a bundle: `load_bundle`'s validation, then each graph's input/output names and
    shapes against the manifest (opened with onnxruntime; with `run`, also run once on zeros).

    :return: human-readable problems; empty when the bundle is usable.
    """
    try:
        b = load_bundle(path)
    except BundleError as exc:
        return [str(exc)]
    problems: list[str] = []
    d, f, p = b.detector, b.fusion, b.pose
    ch, cw = f.crop_hw
    n, c = p.num_points, f.feature_dim
    fusion_in = {f.rgb_input: [None, 3, ch, cw], f.depth_input: [None, 1, ch, cw]}
    fusion_feeds = {f.rgb_input: _zeros([2, 3, ch, cw]), f.depth_input: _zeros([2, 1, ch, cw])}
    if f.choose_input is None:
        fusion_out = [None, c, ch, cw]
    else:
        fusion_in[f.choose_input] = [None, n]
        fusion_feeds[f.choose_input] = _zeros([2, n], np.int64)
        fusion_out = [None, n, c]
    if p.hypotheses == "most_confident":
        pose_out = {p.quat_output: [None, 4], p.trans_output: [None, 3], p.conf_output: [None]}
    else:
        pose_out = {p.quat_output: [None, n, 4], p.trans_output: [None, n, 3], p.conf_output: [None, n]}
    for prec in b.precision:
        suffix = "" if prec == "fp32" else " int8"
        for h, w in d.input_sizes:   # a multi-size graph must take (and run at) every size
            graph = b.graph("detector", prec)
            at = f" at {h}x{w}" if d.multi_size else ""
            problems += _check_graph(graph, f"detector{suffix} ({graph.name}){at}", {d.input_name: [None, 3, h, w]},
                                     {d.output_name: [None, 4 + d.num_classes, None]}, run,
                                     {d.input_name: _zeros([1, 3, h, w])})
        for stage, inputs, outputs, feeds in (
                ("fusion", fusion_in, {f.output_name: fusion_out}, fusion_feeds),
                ("pose", {p.points_input: [None, n, 3], p.features_input: [None, n, c]}, pose_out,
                 {p.points_input: _zeros([2, n, 3]), p.features_input: _zeros([2, n, c])})):
            graph = b.graph(stage, prec)
            problems += _check_graph(graph, f"{stage}{suffix} ({graph.name})", inputs, outputs, run, feeds)
    return problems
