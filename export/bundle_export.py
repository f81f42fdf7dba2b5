"""Write a model bundle (schema: `runtime/manifest.py`) in steps, each returning a typed record:

1. `build_networks`: the networks from a checkpoint or freshly initialised (`export_inputs`);
2. `export_graphs`: the three ONNX graphs, each checked against its torch model (parity), with sizes;
3. `quantize_graphs`: static int8 copies of the chosen stages, compared with float on held-out inputs;
4. `store_float_weights`: the float graphs' weights stored compactly (float16, or int8 per output channel;
   float32 arithmetic either way), each checked against the float32-weight graph;
5. `write_bundle`: the pallet types' model points, `manifest.json` (the contract, sha256 of every file)
   and `report.json` (provenance, checks, scores), read back with the runtime's own `load_bundle`.

`export_bundle` runs them in order. Without a checkpoint, `random_init=True` exports freshly initialised
networks (BatchNorm statistics warmed up on the calibration inputs so activations have realistic ranges) so
the runtime can be built and tested before any training. A detector graph made elsewhere
(`detector_onnx`) is copied unchanged; with `int8`, it is quantized like our own. `keep_from` keeps another
bundle's detector or fusion graphs, float and int8, when the checkpoint's network is that bundle's (`graph_reuse`).
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from pallet6d.runtime.bundle import MANIFEST, REPORT, Bundle, BundleError, load_bundle, sha256_file
from pallet6d.runtime.manifest import DetectorSpec, FusionSpec, Manifest, PoseSpec
from pallet6d.runtime.pose_inputs import gather_features

from .calib_data import CalibrationSet, make_calibration_set
from .config import ModelConfig
from .detector import build_detector
from .graph_reuse import KEEPABLE, take_graphs
from .export_inputs import (DET_IN, DET_OUT, ExportError, external_detector, git_commit, load_checkpoint,
                            read_checkpoint, trained_activation, trained_architecture, trained_classes,
                            trained_depth_max_m, trained_input_hw, trained_input_sizes, warm_up_batchnorm)
from .flops import count_gflops
from .fusion import build_fusion
from .onnx_io import check_parity, export_graph, graph_diff, ort_session
from .pallet_types import class_ids_for_types, trained_pallet_types, write_pallet_types
from .pose import MostConfidentPose, build_pose
from .quantize import int8_recipe, quantize_graph
from .weights_fp16 import store_weights_fp16
from .weights_int8 import store_weights_int8

__all__ = ["export_bundle", "ExportError", "INT8_STAGES", "Networks", "Graphs", "Int8Graphs", "ExportedBundle",
           "build_networks", "export_graphs", "quantize_graphs", "store_float_weights", "write_bundle",
           "trained_input_hw", "FLOAT_WEIGHTS"]

log = logging.getLogger(__name__)

STAGES = ("detector", "fusion", "pose")
# How the float graphs store their weights on disk (float32 arithmetic in every case): the writer, and per
# stage the largest relative RMS change of the outputs (held-out inputs, vs the float32-weight graph) allowed.
# float16 measured ~1e-4 (detector), <1e-6 (fusion, pose); int8 per channel: docs/experiments/bundle-size.md.
FLOAT_WEIGHTS = {
    "fp32": (None, {}),
    "fp16": (store_weights_fp16, dict.fromkeys(STAGES, 5e-3)),
    "int8": (store_weights_int8, {"detector": 0.02, "fusion": 0.02, "pose": 0.02}),
}
# the storage to fall back to when one changes the outputs too much
FLOAT_WEIGHTS_FALLBACK = {"int8": "fp16", "fp16": "fp32"}
# Stages quantized by default. The pose net stays float: quantizing it cost 2-3 points of ADD-sym at 5 cm
# on noisy depth (validation indoor-noisy: int8 pose 75.7 %, float pose 78.0 %, all float 78.7 %)
# and saved only 2 ms per pallet on 2 cores (0.7 of a pallet's 5.6 GFLOP).
INT8_STAGES = ("detector", "fusion")
POSE_OUTPUTS = ("quat", "trans", "conf")
# a detector that takes several input sizes: its graph's height and width axes (and the anchors) are dynamic
DET_DYNAMIC_AXES = {DET_IN: {2: "height", 3: "width"}, DET_OUT: {2: "anchors"}}


def _hw_name(hw: tuple[int, int]) -> str:
    return f"{hw[0]}x{hw[1]}"


def _detector_sizes(sizes, what: str) -> tuple[tuple[int, int], ...]:
    """`sizes` as distinct (H, W) tuples, each a positive multiple of 32. :raises ExportError:"""
    out = tuple(dict.fromkeys((int(h), int(w)) for h, w in sizes))
    bad = [hw for hw in out if min(hw) <= 0 or hw[0] % 32 or hw[1] % 32]
    if not out or bad:
        raise ExportError(f"{what}: detector input sizes must be positive multiples of 32 (YOLOv8 stride), got "
                          f"{[list(hw) for hw in (bad or out)]}")
    return out


def _batches(arrays: list[np.ndarray], size: int) -> list[list[np.ndarray]]:
    n = len(arrays[0])
    return [[a[i:i + size] for a in arrays] for i in range(0, n, size)]


@dataclass(frozen=True)
class Networks:
    """Step 1: the torch networks in eval mode and what they came from.

    :ivar cfg: the config, with the detector's input size and classes as exported.
    :ivar nets: "detector" (absent with an external detector graph), "fusion", "pose".
    :ivar point_feats: (B, N, C) fusion features of the calibration crops at their points.
    :ivar fusion_inputs: the fusion graph's input names: rgb, depth, and choose for a fusion network that
        samples its features at the chosen pixels itself (`cfg.fusion.sampled`).
    :ivar training: the checkpoint's training provenance, if any.
    :ivar detector_sizes: the detector input sizes (H, W) the graph takes; `cfg.detector.input_hw` (the
        reference size) is one of them.
    """

    cfg: ModelConfig
    nets: dict
    calib: CalibrationSet
    point_feats: np.ndarray
    detector_onnx: Path | None
    training: dict | None
    fusion_inputs: tuple[str, ...] = ("rgb", "depth")
    detector_sizes: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        if not self.detector_sizes:
            object.__setattr__(self, "detector_sizes", (tuple(self.cfg.detector.input_hw),))

    def fusion_arrays(self) -> list[np.ndarray]:
        """The calibration arrays fed to the fusion graph's inputs, in order."""
        c = self.calib
        return [c.rgb_crops, c.depth_crops, c.choose][:len(self.fusion_inputs)]


def build_networks(cfg: ModelConfig, *, seed: int = 0, checkpoint: str | Path | None = None,
                   random_init: bool = False, detector_onnx: str | Path | None = None,
                   classes: tuple[str, ...] | None = None, calib: CalibrationSet | None = None,
                   calib_frames: int = 8, calib_crops: int = 96, calib_presets: tuple[str, ...] | None = None,
                   detector_input_sizes: tuple[tuple[int, int], ...] | None = None) -> Networks:
    """The networks to export: a checkpoint's weights, or fresh ones with BatchNorm warmed up on calibration
    inputs. `classes` (our own detector) renames its classes; the count must stay the config's unless the
    networks are fresh.

    :param detector_input_sizes: the input sizes (H, W) our detector's graph takes (default: those the
        checkpoint's detector was trained on, `input_sizes` of its provenance, else its one `input_hw`). The
        reference size `input_hw` stays the trained one when listed, else becomes the first listed.
    :raises ExportError:"""
    if (checkpoint is None) == (not random_init):
        raise ExportError("give exactly one of --checkpoint FILE or --random-init")
    ckpt = read_checkpoint(Path(checkpoint)) if checkpoint is not None else None
    if detector_onnx is not None:
        det_hw, det_classes = external_detector(Path(detector_onnx), classes)
        cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=det_hw, classes=det_classes))
        if detector_input_sizes and set(_detector_sizes(detector_input_sizes, "--detector-input-sizes")) != {det_hw}:
            raise ExportError(f"--detector-onnx {detector_onnx} takes one input size, {_hw_name(det_hw)}; "
                              "--detector-input-sizes is for our own detector")
        sizes = (det_hw,)
    else:
        if ckpt is not None and (names := trained_classes(ckpt)) is not None:
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, classes=names))   # as trained
        if classes is not None:
            if ckpt is not None and len(classes) != len(cfg.detector.classes):
                raise ExportError(f"the checkpoint's detector has {len(cfg.detector.classes)} classes, not "
                                  f"{len(classes)} ({list(classes)})")
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, classes=tuple(classes)))
        if ckpt is not None and (depth_max := trained_depth_max_m(ckpt)) is not None:   # an RGB-D detector
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, depth_max_m=depth_max))
        if ckpt is not None:
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, activation=trained_activation(ckpt),
                                                           architecture=trained_architecture(ckpt)))
        if ckpt is not None and (hw := trained_input_hw(ckpt)) not in (None, cfg.detector.input_hw):
            # the detector is fully convolutional: export it at the size it was trained at
            log.info("detector input %s, as trained (config %s: %s)", hw, cfg.name, cfg.detector.input_hw)
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=hw))
        if detector_input_sizes:
            sizes = _detector_sizes(detector_input_sizes, "--detector-input-sizes")
        else:
            trained = trained_input_sizes(ckpt) if ckpt is not None else None
            sizes = _detector_sizes(trained, "the checkpoint's input_sizes") if trained else (cfg.detector.input_hw,)
        if tuple(cfg.detector.input_hw) not in sizes:
            log.info("detector reference input %s (the first input size; %s is not among %s)",
                     _hw_name(sizes[0]), _hw_name(cfg.detector.input_hw), [_hw_name(hw) for hw in sizes])
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=sizes[0]))
    torch.manual_seed(seed)
    nets = {"detector": build_detector(cfg.detector), "fusion": build_fusion(cfg.fusion),
            "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}
    if detector_onnx is not None:
        del nets["detector"]
    for net in nets.values():
        net.eval()
    calib = calib or make_calibration_set(cfg, frames=calib_frames, max_crops=calib_crops, seed=seed,
                                          presets=calib_presets, detector_sizes=sizes)
    sampled = bool(getattr(cfg.fusion, "sampled", False))   # the fusion graph takes `choose`, gives (B, N, C)
    fusion_in = [calib.rgb_crops, calib.depth_crops, calib.choose][:3 if sampled else 2]
    training = None
    t = torch.from_numpy
    if ckpt is not None:
        training = load_checkpoint(Path(checkpoint), ckpt, nets, cfg, tuple(nets))
    else:
        if "detector" in nets:
            warm_up_batchnorm(nets["detector"], [(t(calib.images[i:i + 4]),) for i in range(0, len(calib.images), 4)])
        warm_up_batchnorm(nets["fusion"], [tuple(t(a[i:i + 8]) for a in fusion_in)
                                           for i in range(0, len(calib.rgb_crops), 8)])
    with torch.no_grad():
        feats = nets["fusion"](*(t(a) for a in fusion_in)).numpy()
    return Networks(cfg, nets, calib, feats if sampled else gather_features(feats, calib.choose),
                    None if detector_onnx is None else Path(detector_onnx), training,
                    ("rgb", "depth", "choose") if sampled else ("rgb", "depth"), tuple(sizes))


@dataclass(frozen=True)
class Graphs:
    """Step 2: the float graphs in the bundle folder and their checks (parity, params, gflops).

    :ivar feeds: per stage, calibration input batches; the first `split[stage]` calibrate int8, the rest
        measure how far a changed graph strays.
    :ivar references: per stage, a graph of the same network whose outputs measure how far stored weights move it,
        where the bundle's own graph cannot: the pose network at every point (the bundle's graph gives the most
        confident point's hypothesis, which jumps to another point where a rounded weight moves the choice). Not part
        of the bundle: `export_bundle` removes them.
    """

    files: dict
    det_in: str
    det_out: str
    checks: dict
    feeds: dict
    split: dict
    detector_sizes: tuple[tuple[int, int], ...] = ()
    references: dict = field(default_factory=dict)

    def held_out(self, stage: str) -> list:
        return self.feeds[stage][self.split[stage]:] or self.feeds[stage][-1:]


def export_graphs(n: Networks, out: Path) -> Graphs:
    """Export each network to ONNX in `out` and check it reproduces the torch model.

    :raises onnx_io.ParityError: an exported graph does not reproduce its torch model.
    """
    calib, nets, t = n.calib, n.nets, torch.from_numpy
    files: dict[str, Path] = {}
    checks: dict = {"parity": {}, "gflops": {}, "params": {}}
    sizes, multi = n.detector_sizes, len(n.detector_sizes) > 1
    if n.detector_onnx is None:   # static batch 1, like ultralytics exports; height and width as the sizes need
        example = (t(calib.images_at(n.cfg.detector.input_hw)[:1]),)
        files["detector"] = export_graph(nets["detector"], example, out / "detector.onnx",
                                         [DET_IN], [DET_OUT], DET_DYNAMIC_AXES if multi else None)
        parity = {_hw_name(hw): check_parity(nets["detector"], (t(calib.images_at(hw)[:1]),), files["detector"],
                                             [DET_IN], [DET_OUT]) for hw in sizes}
        checks["parity"]["detector"] = parity if multi else parity[_hw_name(sizes[0])]
    else:
        files["detector"] = Path(shutil.copyfile(n.detector_onnx, out / "detector.onnx"))
        checks["parity"]["detector"] = "external graph, copied unchanged"
    det_sess = ort_session(files["detector"], threads=1)
    det_in, det_out = det_sess.get_inputs()[0].name, det_sess.get_outputs()[0].name
    fusion_names = list(n.fusion_inputs)
    fusion_args = tuple(t(a[:2]) for a in n.fusion_arrays())
    files["fusion"] = export_graph(nets["fusion"], fusion_args, out / "fusion.onnx", fusion_names, ["features"],
                                   {k: {0: "batch"} for k in [*fusion_names, "features"]})
    checks["parity"]["fusion"] = check_parity(nets["fusion"], fusion_args, files["fusion"], fusion_names,
                                              ["features"])
    pose_args = (t(calib.points[:2]), t(n.point_feats[:2]))
    pose_axes = {k: {0: "batch"} for k in ("points", "features", *POSE_OUTPUTS)}
    pose_graph = MostConfidentPose(nets["pose"])     # what the runtime uses of the network, and no more
    files["pose"] = export_graph(pose_graph, pose_args, out / "pose.onnx", ["points", "features"], list(POSE_OUTPUTS),
                                 pose_axes)
    checks["parity"]["pose"] = check_parity(pose_graph, pose_args, files["pose"], ["points", "features"],
                                            list(POSE_OUTPUTS))
    references = {"pose": export_graph(nets["pose"], pose_args, out / "pose.per-point.onnx", ["points", "features"],
                                       list(POSE_OUTPUTS), pose_axes)}
    checks["params"] = {stage: sum(p.numel() for p in net.parameters()) for stage, net in nets.items()}
    det_gflops = {_hw_name(hw): round(count_gflops(files["detector"], {"height": hw[0], "width": hw[1]}), 3)
                  for hw in sizes}
    checks["gflops"] = {"detector_per_frame": det_gflops[_hw_name(n.cfg.detector.input_hw)],
                        **({f"detector_per_frame_{k}": v for k, v in det_gflops.items()} if multi else {}),
                        "fusion_per_pallet": round(count_gflops(files["fusion"]), 3),
                        "pose_per_pallet": round(count_gflops(files["pose"]), 3)}
    n_cal = max(1, (3 * len(calib.rgb_crops)) // 4)   # calibrate on 3/4, report the difference on the rest
    # the detector calibrates on the first 3/4 of the frames at every input size, and is checked on the rest
    n_det = max(1, (3 * len(calib.images)) // 4)
    det_feeds = [[{det_in: calib.images_at(hw)[i:i + 1]} for hw in sizes] for i in range(len(calib.images))]
    feeds = {"detector": [f for frame in det_feeds for f in frame],
             "fusion": [dict(zip(fusion_names, b)) for b in _batches(n.fusion_arrays(), 4)],
             "pose": [{"points": p, "features": f} for p, f in _batches([calib.points, n.point_feats], 4)]}
    split = {"detector": n_det * len(sizes), "fusion": -(-n_cal // 4), "pose": -(-n_cal // 4)}
    return Graphs(files, det_in, det_out, checks, feeds, split, sizes, references)


@dataclass(frozen=True)
class Int8Graphs:
    """Step 3: per stage, the graph that runs at precision int8 (a quantized copy, or the float graph itself),
    and how each quantized one differs from float on held-out inputs."""

    files: dict
    checks: dict


def quantize_graphs(g: Graphs, out: Path, stages: tuple[str, ...] = INT8_STAGES,
                    kept: tuple[str, ...] = ()) -> Int8Graphs:
    """Static int8 (QDQ) copies of `stages`; the other stages run their float graph at int8 too. A stage in `kept`
    gets its int8 graph from another bundle (`graph_reuse.take_graphs`): its path is named, nothing is quantized."""
    files: dict[str, Path] = {}
    checks: dict = {}
    for stage in STAGES:
        if stage not in stages:
            files[stage] = g.files[stage]
            checks[stage] = "float graph (not quantized)"
            continue
        if stage in kept:
            files[stage] = out / f"{stage}.int8.onnx"
            checks[stage] = "kept from another bundle"
            continue
        # what each stage quantizes and keeps float: quantize.INT8_RECIPES
        files[stage] = quantize_graph(g.files[stage], out / f"{stage}.int8.onnx", g.feeds[stage][:g.split[stage]],
                                      **int8_recipe(stage, g.files[stage]))
        checks[stage] = graph_diff(g.files[stage], files[stage], g.held_out(stage))
        if stage == "detector" and len(g.detector_sizes) > 1:
            checks["detector_by_size"] = {
                _hw_name(hw): graph_diff(g.files[stage], files[stage],
                                          [f for f in g.held_out(stage) if f[g.det_in].shape[2:] == hw])
                for hw in g.detector_sizes}
    checks["note"] = "int8 vs fp32 on calibration inputs held out from calibration"
    return Int8Graphs(files, checks)


def store_float_weights(g: Graphs, out: Path, stages: tuple[str, ...], storage: str = "int8") -> dict:
    """Replace the float graphs of `stages` by copies with their weights stored as `storage` (a key of
    FLOAT_WEIGHTS other than fp32), after int8 quantization, which needs the float32 weights.

    :return: per stage, the storage and how it changes the outputs on held-out inputs ("vs_fp32_weights").
    :raises ExportError: unknown storage, or a stage's outputs change by more than its limit (the message
        names the storage to export with instead).
    """
    if storage not in FLOAT_WEIGHTS or FLOAT_WEIGHTS[storage][0] is None:
        raise ExportError(f"float weight storage must be one of {[k for k, v in FLOAT_WEIGHTS.items() if v[0]]}, "
                          f"got {storage!r}")
    write, limits = FLOAT_WEIGHTS[storage]
    checks = {}
    for stage in stages:
        ref = g.references.get(stage, g.files[stage])
        small = out / f"{stage}.{storage}-weights.onnx"
        stored = write(ref, small)
        diff = graph_diff(ref, small, g.held_out(stage))
        worst = max(v["rel_rms"] for v in diff.values())
        if not worst <= limits[stage]:
            small.unlink()
            raise ExportError(f"{stage}: {storage} weights change the output by {worst:.2g} relative RMS "
                              f"(limit {limits[stage]}); export with --float-weights "
                              f"{FLOAT_WEIGHTS_FALLBACK[storage]}")
        if ref != g.files[stage]:     # measured on the reference graph; the bundle's graph stores the same weights
            small.unlink()
            stored = write(g.files[stage], small)
        small.replace(g.files[stage])
        checks[stage] = {**stored.to_dict(), "vs_fp32_weights": diff, "limit_rel_rms": limits[stage]}
    return checks


@dataclass(frozen=True)
class ExportedBundle:
    """Step 5: the bundle written and read back: its contract and its report."""

    root: Path
    manifest: Manifest
    report: dict
    bundle: Bundle


def write_bundle(out: Path, n: Networks, g: Graphs, int8: Int8Graphs | None, pallet_types: tuple[str, ...],
                 name: str, checks: dict, provenance: dict) -> ExportedBundle:
    """Write the pallet types, manifest.json and report.json; load the bundle back with the runtime's reader.

    :raises ExportError: the detector's classes and the pallet types do not match.
    """
    cfg, rel = n.cfg, (lambda p: None if p is None else Path(p).relative_to(out).as_posix())  # noqa: E731
    external = n.detector_onnx is not None
    class_ids = class_ids_for_types(pallet_types, cfg.detector.classes, external)
    types = write_pallet_types(pallet_types, class_ids, out)
    i8 = int8.files if int8 is not None else dict.fromkeys(STAGES)
    try:
        detector = DetectorSpec(
            file=rel(g.files["detector"]), file_int8=rel(i8["detector"]), input_name=g.det_in, output_name=g.det_out,
            input_hw=tuple(cfg.detector.input_hw), input_sizes=n.detector_sizes, letterbox_pad_value=114,
            pixel_scale=1.0 / 255.0, rgb_mean=(0.0, 0.0, 0.0), rgb_std=(1.0, 1.0, 1.0), channel_order="RGB",
            classes=tuple(cfg.detector.classes), source="external" if external else "pallet6d",
            depth_max_m=cfg.detector.depth_max_m)
        fusion = FusionSpec(
            file=rel(g.files["fusion"]), file_int8=rel(i8["fusion"]), rgb_input="rgb", depth_input="depth",
            choose_input=n.fusion_inputs[2] if len(n.fusion_inputs) > 2 else None, output_name="features", crop_hw=tuple(cfg.fusion.crop_hw), pixel_scale=1.0 / 255.0,
            rgb_mean=tuple(cfg.rgb_mean), rgb_std=tuple(cfg.rgb_std), depth_clip_m=cfg.depth_clip_m,
            feature_dim=cfg.fusion.feature_dim)
        pose = PoseSpec(
            file=rel(g.files["pose"]), file_int8=rel(i8["pose"]), points_input="points", features_input="features",
            quat_output=POSE_OUTPUTS[0], trans_output=POSE_OUTPUTS[1], conf_output=POSE_OUTPUTS[2],
            num_points=cfg.pose.num_points, depth_range_m=tuple(cfg.depth_range_m), hypotheses="most_confident")
        names = [*(f for s in STAGES for f in (rel(g.files[s]), rel(i8[s])) if f), *(t.points_file for t in types)]
        manifest = Manifest(name=name, config=cfg.name, precision=("fp32", "int8") if int8 is not None else ("fp32",),
                            detector=detector, fusion=fusion, pose=pose, pallet_types=types,
                            files={f: sha256_file(out / f) for f in dict.fromkeys(names)})
    except BundleError as exc:
        raise ExportError(f"the bundle would not be valid: {exc}") from None
    report = {"provenance": provenance, "checks": checks, "scores": {}}
    (out / MANIFEST).write_text(json.dumps(manifest.to_dict(), indent=2) + "\n", encoding="utf-8")
    (out / REPORT).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    bundle = load_bundle(out)   # the writer must satisfy its own reader
    return ExportedBundle(out, manifest, report, bundle)


def _default_types(n: Networks) -> tuple[str, ...]:
    """The types the pose stage was trained on (the config's one without a record) when the detector reports
    each (a class per type, or one class for all: the runtime then tells them apart by the depth); else the
    first."""
    try:
        trained = trained_pallet_types(n.training, n.cfg.pallet)
    except ValueError as exc:
        raise ExportError(f"the checkpoint's pose stage was trained on a pallet type without a model: {exc}") from None
    try:
        class_ids_for_types(trained, n.cfg.detector.classes, n.detector_onnx is not None)
        return trained
    except ExportError as exc:
        log.warning("the bundle carries pallet type %s only: %s (export with --pallet-types to choose)",
                    trained[0], exc)
        return trained[:1]


def export_bundle(cfg: ModelConfig, out: str | Path, *, seed: int = 0, checkpoint: str | Path | None = None,
                  random_init: bool = False, int8: bool = False, detector_onnx: str | Path | None = None,
                  classes: tuple[str, ...] | None = None, name: str | None = None, command: str = "",
                  calib: CalibrationSet | None = None, calib_frames: int = 8, calib_crops: int = 96,
                  calib_presets: tuple[str, ...] | None = None, float_weights: str = "int8",
                  int8_stages: tuple[str, ...] = INT8_STAGES,
                  pallet_types: tuple[str, ...] | None = None,
                  detector_input_sizes: tuple[tuple[int, int], ...] | None = None,
                  keep_from: dict[str, str | Path] | None = None) -> ExportedBundle:
    """Export `cfg`'s networks to a new bundle folder `out` (the steps of the module docstring).

    :param classes: the external detector's class names (default: its metadata), or our detector's.
    :param pallet_types: sim pallet model names (default: the types the checkpoint's pose stage was trained
        on, where the detector has a class for each; else the first of them, or the config's pallet). A
        checkpoint's detector keeps its classes (one class for every type, or one named after each type); without
        a checkpoint our own detector gets one class per type, named after it; an external detector's classes
        are matched to the types by name.
    :param int8: also write int8 graphs: the stages in `int8_stages` quantized, the others' float graph.
    :param calib_presets: sim presets the int8 calibration frames and crops come from, in turn (default: the
        paper's three, `calib_data.make_calibration_set`); a bundle for other scenes calibrates on them too.
    :param detector_input_sizes: the input sizes (H, W) our detector's graph takes, one chosen per frame by
        the runtime (default: those its checkpoint was trained on; `build_networks`). With more than one, the
        graph's height and width axes are dynamic, and parity and int8 calibration cover every size.
    :param float_weights: how the float graphs store their weights on disk (FLOAT_WEIGHTS): "int8" (int8
        per output channel, a quarter of the size), "fp16" (half), "fp32"; the arithmetic is float32 in every
        case, and int8 graphs are quantized from the full float32 weights before that.
    :param keep_from: stage ("detector", "fusion") -> a bundle whose graphs of that stage the new bundle keeps
        unchanged (`graph_reuse`); the checkpoint's network of the stage must be that bundle's. A kept stage is
        not quantized again: its int8 graph is that bundle's.
    :raises ExportError: bad arguments, checkpoint or external detector.
    :raises onnx_io.ParityError: an exported graph does not reproduce its torch model.
    """
    if float_weights not in FLOAT_WEIGHTS:
        raise ExportError(f"float weight storage must be one of {tuple(FLOAT_WEIGHTS)}, got {float_weights!r}")
    if not set(int8_stages) <= set(STAGES):
        raise ExportError(f"int8 stages must be among {STAGES}, got {tuple(int8_stages)}")
    if calib_presets:
        from pallet6d.sim.presets import PRESETS
        unknown = [p for p in calib_presets if p not in PRESETS]
        if unknown:
            raise ExportError(f"unknown calibration preset(s) {unknown}; known: {', '.join(PRESETS)}")
    keep_from = dict(keep_from or {})
    if set(keep_from) - set(KEEPABLE):
        raise ExportError(f"only the {' and '.join(KEEPABLE)} graphs can be kept from another bundle, not "
                          f"{sorted(set(keep_from) - set(KEEPABLE))}")
    if keep_from and checkpoint is None:
        raise ExportError("--detector-from / --fusion-from keep a bundle's graphs beside a checkpoint's other "
                          "networks: give --checkpoint")
    if "detector" in keep_from and detector_onnx is not None:
        raise ExportError("--detector-from and --detector-onnx both name the detector: give one")
    if pallet_types and detector_onnx is None and classes is None and checkpoint is None:
        classes = tuple(pallet_types)     # a trained detector keeps its classes: one for all types, or one each
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ExportError(f"output folder {out} is not empty; choose a new folder")
    n = build_networks(cfg, seed=seed, checkpoint=checkpoint, random_init=random_init, detector_onnx=detector_onnx,
                       classes=classes, calib=calib, calib_frames=calib_frames, calib_crops=calib_crops,
                       calib_presets=calib_presets, detector_input_sizes=detector_input_sizes)
    types = tuple(pallet_types) if pallet_types else _default_types(n)
    class_ids_for_types(types, n.cfg.detector.classes, detector_onnx is not None)   # fail before the work
    out.mkdir(parents=True, exist_ok=True)
    g = export_graphs(n, out)
    checks = dict(g.checks)
    q = quantize_graphs(g, out, tuple(int8_stages), kept=tuple(keep_from)) if int8 else None
    if q is not None:
        checks["int8"] = q.checks
    if float_weights != "fp32":
        checks[f"weights_{float_weights}"] = store_float_weights(g, out, tuple(s for s in STAGES if s in n.nets),
                                                                 float_weights)
    for ref in g.references.values():
        ref.unlink()
    kept_fields = {
        "detector": {"input_hw": tuple(n.cfg.detector.input_hw), "input_sizes": tuple(n.detector_sizes),
                     "classes": tuple(n.cfg.detector.classes), "depth_max_m": n.cfg.detector.depth_max_m,
                     "input_name": g.det_in, "output_name": g.det_out},
        "fusion": {"crop_hw": tuple(n.cfg.fusion.crop_hw), "feature_dim": n.cfg.fusion.feature_dim,
                   "rgb_mean": tuple(n.cfg.rgb_mean), "rgb_std": tuple(n.cfg.rgb_std),
                   "depth_clip_m": n.cfg.depth_clip_m, "rgb_input": "rgb", "depth_input": "depth",
                   "choose_input": n.fusion_inputs[2] if len(n.fusion_inputs) > 2 else None,
                   "output_name": "features"}}
    for stage, source in keep_from.items():
        checks = take_graphs(stage, Path(source), out, g.files, None if q is None else q.files, g.held_out(stage),
                             kept_fields[stage], checks)
    provenance = {"command": command, "seed": seed, "git_commit": git_commit(),
                  "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                  "random_init": bool(random_init), "checkpoint": None if checkpoint is None else str(checkpoint),
                  "detector_onnx": None if detector_onnx is None else str(detector_onnx),
                  "graphs_kept_from": {k: str(v) for k, v in keep_from.items()} or None,
                  "training": n.training, "calibration": n.calib.source, "model_config": n.cfg.to_dict()}
    return write_bundle(out, n, g, q, types, name or out.name, checks, provenance)
