"""Write a model bundle (runtime/bundle.py documents the manifest): the three ONNX graphs, optional int8
copies, the pallet model points and manifest.json, with parity, int8 and GFLOP checks recorded.

Checkpoint format (`--checkpoint FILE`, written by training): ``torch.save({"config": name,
"detector": state_dict | absent, "fusion": state_dict, "pose": state_dict})``. Without a checkpoint,
`random_init=True` exports freshly initialised networks (BatchNorm statistics warmed up on the
calibration inputs so activations have realistic ranges) so the runtime can be built and tested
before any training.

External detector (`detector_onnx`): any YOLOv8 ONNX graph in the ultralytics export layout, e.g.
``yolo export model=best.pt format=onnx imgsz=384,1216`` (static batch, opset >= 12), which has one
input (1, 3, H, W) float RGB in [0, 1] (letterboxed with grey 114) and one output (1, 4 + nc, A)
with cx, cy, w, h in input pixels and sigmoid class scores. The graph is copied into the bundle
unchanged; H, W come from its input shape; class names from its `names` metadata (ultralytics writes
it) unless `classes` is given; nc must match. With `int8`, it is quantized like our own detector.
"""
from __future__ import annotations

import ast
import dataclasses
import datetime as dt
import json
import logging
import shutil
import subprocess
from pathlib import Path

import numpy as np
import onnx
import torch

from pallet6d.runtime.bundle import FORMAT, FORMAT_VERSION, MANIFEST, load_bundle, sha256_file
from pallet6d.runtime.pose_inputs import gather_features

from .calib_data import CalibrationSet, make_calibration_set
from .config import ModelConfig
from .detector import build_detector
from .flops import count_gflops
from .fusion import build_fusion
from .onnx_io import check_parity, compare_outputs, export_graph, ort_session, run_session
from .pose import build_pose
from .quantize import quantize_graph
from .weights_fp16 import store_weights_fp16

__all__ = ["export_bundle", "ExportError", "INT8_STAGES"]

log = logging.getLogger(__name__)

DET_IN, DET_OUT = "images", "output0"
# float16 weight storage may change a graph's outputs by at most this relative RMS (measured: ~5e-4)
FP16_WEIGHTS_REL_RMS = 5e-3
STAGES = ("detector", "fusion", "pose")
# Stages quantized by default. The pose net stays float: quantizing it cost 2-3 points of ADD-sym at 5 cm
# on noisy depth (validation indoor-noisy, session-7 networks: int8 pose 75.7 %, float pose 78.0 %, all float 78.7 %)
# and saved only 2 ms per pallet on 2 cores (0.7 of a pallet's 5.6 GFLOP).
INT8_STAGES = ("detector", "fusion")


class ExportError(ValueError):
    """The export cannot proceed (bad checkpoint, bad external detector, ...)."""


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


@torch.no_grad()
def _warm_up_batchnorm(model: torch.nn.Module, batches: list[tuple[torch.Tensor, ...]]) -> None:
    """Set BatchNorm running statistics from `batches` (cumulative average), then back to eval."""
    bns = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    if not bns:
        return
    for m in bns:
        m.reset_running_stats()
        m.momentum = None
    model.train()
    for args in batches:
        model(*args)
    model.eval()


def _read_checkpoint(path: Path) -> dict:
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ExportError(f"cannot read checkpoint {path}: {exc}") from None
    if not isinstance(ckpt, dict):
        raise ExportError(f"checkpoint {path}: expected a dict with 'detector'/'fusion'/'pose' state dicts")
    return ckpt


def trained_input_hw(ckpt: dict) -> tuple[int, int] | None:
    """The detector input (H, W) a checkpoint's detector was trained at (`pallet6d train detector
    --detector-input`), from its provenance; None when not recorded (then the config's size applies)."""
    prov = ckpt.get("provenance")
    if not isinstance(prov, dict):
        return None
    det = prov if prov.get("stage") == "detector" else prov.get("detector")
    hw = det.get("input_hw") if isinstance(det, dict) else None
    return (int(hw[0]), int(hw[1])) if hw is not None else None


def _load_checkpoint(path: Path, ckpt: dict, nets: dict[str, torch.nn.Module], cfg: ModelConfig,
                     need: tuple[str, ...]) -> dict | None:
    """Load the networks' weights; return the checkpoint's training provenance (recipe, data, seeds) if any."""
    if ckpt.get("config") not in (None, cfg.name):
        raise ExportError(f"checkpoint {path} was trained with config {ckpt.get('config')!r}, not {cfg.name!r}")
    for key in need:
        if key not in ckpt:
            raise ExportError(f"checkpoint {path} has no {key!r} weights (keys: {sorted(ckpt)}); "
                              "pass --random-init to export untrained networks")
        try:
            nets[key].load_state_dict(ckpt[key])
        except RuntimeError as exc:
            raise ExportError(f"checkpoint {path}: {key} weights do not fit config {cfg.name!r}: {exc}") from None
    training = ckpt.get("provenance")
    return training if isinstance(training, dict) else None


def _external_detector(path: Path, classes: tuple[str, ...] | None) -> tuple[tuple[int, int], tuple[str, ...]]:
    """Validate a foreign YOLOv8 ONNX graph; return its input (H, W) and class names."""
    if not path.is_file():
        raise ExportError(f"--detector-onnx {path}: no such file")
    try:
        model = onnx.load(str(path))
        onnx.checker.check_model(model)
    except Exception as exc:
        raise ExportError(f"--detector-onnx {path}: not a valid ONNX model: {exc}") from None
    sess = ort_session(path, threads=1)
    ins, outs = sess.get_inputs(), sess.get_outputs()
    if len(ins) != 1 or len(outs) < 1:
        raise ExportError(f"--detector-onnx {path}: expected one input and a YOLOv8 output, got inputs "
                          f"{[i.name for i in ins]}, outputs {[o.name for o in outs]}")
    shape = list(ins[0].shape)
    if len(shape) != 4 or shape[1] != 3 or not all(isinstance(s, int) for s in shape[2:]):
        raise ExportError(f"--detector-onnx {path}: input {ins[0].name!r} must be (1, 3, H, W) with fixed H, W "
                          f"(export with a fixed imgsz), got {shape}")
    h, w = shape[2], shape[3]
    if h % 32 or w % 32:
        raise ExportError(f"--detector-onnx {path}: input size {h}x{w} is not a multiple of 32")
    out = sess.run(None, {ins[0].name: np.zeros((1, 3, h, w), np.float32)})[0]
    n_anchors = sum((h // s) * (w // s) for s in (8, 16, 32))
    if out.ndim != 3 or out.shape[2] != n_anchors or out.shape[1] < 5:
        raise ExportError(f"--detector-onnx {path}: output {out.shape} is not the YOLOv8 layout "
                          f"(1, 4 + nc, {n_anchors}) for a {h}x{w} input")
    nc = out.shape[1] - 4
    if classes is None:
        meta = {p.key: p.value for p in model.metadata_props}
        try:
            names = ast.literal_eval(meta["names"]) if "names" in meta else None
        except (ValueError, SyntaxError):
            names = None
        classes = tuple(names[i] for i in sorted(names)) if isinstance(names, dict) else None
        if classes is None:
            raise ExportError(f"--detector-onnx {path}: no class names in its metadata; pass --classes")
    if len(classes) != nc:
        raise ExportError(f"--detector-onnx {path}: the graph has {nc} classes but {len(classes)} names were given")
    if ins[0].name != DET_IN or outs[0].name != DET_OUT:
        log.info("external detector uses input %r / output %r", ins[0].name, outs[0].name)
    return (h, w), tuple(classes)


def _graph_diff(ref_path: Path, test_path: Path, feeds: list[dict[str, np.ndarray]]) -> dict:
    """Per output: how `test_path`'s outputs differ from `ref_path`'s on `feeds` (compare_outputs)."""
    ref_sess, test_sess = ort_session(ref_path), ort_session(test_path)
    ref, got = {}, {}
    for f in feeds:
        for k, v in run_session(ref_sess, f).items():
            ref.setdefault(k, []).append(v)
        for k, v in run_session(test_sess, f).items():
            got.setdefault(k, []).append(v)
    return {k: compare_outputs(np.concatenate(ref[k]), np.concatenate(got[k])).to_dict() for k in ref}


def _batches(arrays: list[np.ndarray], size: int) -> list[list[np.ndarray]]:
    n = len(arrays[0])
    return [[a[i:i + size] for a in arrays] for i in range(0, n, size)]


def export_bundle(cfg: ModelConfig, out: str | Path, *, seed: int = 0, checkpoint: str | Path | None = None,
                  random_init: bool = False, int8: bool = False, detector_onnx: str | Path | None = None,
                  classes: tuple[str, ...] | None = None, name: str | None = None, command: str = "",
                  calib: CalibrationSet | None = None, calib_frames: int = 8, calib_crops: int = 96,
                  fp16_weights: bool = True, int8_stages: tuple[str, ...] = INT8_STAGES) -> dict:
    """Export `cfg`'s networks to a bundle folder `out` and return its manifest.

    With `int8`, the stages in `int8_stages` get a quantized graph; the others run their float graph at
    precision int8 too (their `file_int8` names the float file).

    With `fp16_weights` the float32 graphs keep their weights as float16 on disk (`weights_fp16`: half the
    size, same float32 arithmetic); int8 graphs are quantized from the full float32 weights before that.

    :raises ExportError: bad arguments, checkpoint or external detector.
    :raises onnx_io.ParityError: an exported graph does not reproduce its torch model.
    """
    if (checkpoint is None) == (not random_init):
        raise ExportError("give exactly one of --checkpoint FILE or --random-init")
    if not set(int8_stages) <= set(STAGES):
        raise ExportError(f"int8 stages must be among {STAGES}, got {tuple(int8_stages)}")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ExportError(f"output folder {out} is not empty; choose a new folder")
    ckpt = _read_checkpoint(Path(checkpoint)) if checkpoint is not None else None
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    nets = {"detector": build_detector(cfg.detector), "fusion": build_fusion(cfg.fusion),
            "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}
    for net in nets.values():
        net.eval()
    if detector_onnx is not None:
        det_hw, det_classes = _external_detector(Path(detector_onnx), classes)
        cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=det_hw, classes=det_classes))
    elif ckpt is not None and (hw := trained_input_hw(ckpt)) not in (None, cfg.detector.input_hw):
        # the detector is fully convolutional: export it at the size it was trained at
        log.info("detector input %s, as trained (config %s: %s)", hw, cfg.name, cfg.detector.input_hw)
        cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=hw))
    calib = calib or make_calibration_set(cfg, frames=calib_frames, max_crops=calib_crops, seed=seed)
    need = ("fusion", "pose") if detector_onnx is not None else ("detector", "fusion", "pose")
    sampled = cfg.fusion.sampled   # the fusion graph takes `choose` and returns per-point features
    fusion_names = ["rgb", "depth", "choose"] if sampled else ["rgb", "depth"]
    fusion_arrays = [calib.rgb_crops, calib.depth_crops, calib.choose][:len(fusion_names)]
    training = None
    if checkpoint is not None:
        training = _load_checkpoint(Path(checkpoint), ckpt, nets, cfg, need)
    else:
        t = torch.from_numpy
        _warm_up_batchnorm(nets["detector"], [(t(calib.images[i:i + 4]),) for i in range(0, len(calib.images), 4)])
        _warm_up_batchnorm(nets["fusion"], [tuple(t(a[i:i + 8]) for a in fusion_arrays)
                                            for i in range(0, len(calib.rgb_crops), 8)])
    with torch.no_grad():
        fused = nets["fusion"](*(torch.from_numpy(a) for a in fusion_arrays)).numpy()
    point_feats = fused if sampled else gather_features(fused, calib.choose)

    files: dict[str, Path] = {}
    checks: dict = {"parity": {}, "gflops": {}, "params": {}}
    # detector: static batch 1 (like ultralytics exports)
    if detector_onnx is None:
        files["detector"] = export_graph(nets["detector"], (torch.from_numpy(calib.images[:1]),), out / "detector.onnx",
                                         [DET_IN], [DET_OUT])
        checks["parity"]["detector"] = check_parity(nets["detector"], (torch.from_numpy(calib.images[:1]),),
                                                    files["detector"], [DET_IN], [DET_OUT])
        checks["params"]["detector"] = sum(p.numel() for p in nets["detector"].parameters())
    else:
        files["detector"] = Path(shutil.copyfile(detector_onnx, out / "detector.onnx"))
        checks["parity"]["detector"] = "external graph, copied unchanged"
    det_sess = ort_session(files["detector"], threads=1)
    det_in, det_out = det_sess.get_inputs()[0].name, det_sess.get_outputs()[0].name
    fusion_args = tuple(torch.from_numpy(a[:2]) for a in fusion_arrays)
    files["fusion"] = export_graph(nets["fusion"], fusion_args, out / "fusion.onnx", fusion_names, ["features"],
                                   {n: {0: "batch"} for n in [*fusion_names, "features"]})
    checks["parity"]["fusion"] = check_parity(nets["fusion"], fusion_args, files["fusion"], fusion_names,
                                              ["features"])
    pose_args = (torch.from_numpy(calib.points[:2]), torch.from_numpy(point_feats[:2]))
    pose_names = ["quat", "trans", "conf"]
    files["pose"] = export_graph(nets["pose"], pose_args, out / "pose.onnx", ["points", "features"], pose_names,
                                 {"points": {0: "batch"}, "features": {0: "batch"}, "quat": {0: "batch"},
                                  "trans": {0: "batch"}, "conf": {0: "batch"}})
    checks["parity"]["pose"] = check_parity(nets["pose"], pose_args, files["pose"], ["points", "features"], pose_names)
    for stage in ("fusion", "pose"):
        checks["params"][stage] = sum(p.numel() for p in nets[stage].parameters())
    checks["gflops"] = {"detector_per_frame": round(count_gflops(files["detector"]), 3),
                        "fusion_per_pallet": round(count_gflops(files["fusion"]), 3),
                        "pose_per_pallet": round(count_gflops(files["pose"]), 3)}

    n_cal = max(1, (3 * len(calib.rgb_crops)) // 4)   # calibrate on 3/4, report the difference on the rest
    n_img = max(1, (3 * len(calib.images)) // 4)
    det_feeds = [{det_in: calib.images[i:i + 1]} for i in range(len(calib.images))]
    fus_feeds = [dict(zip(fusion_names, b)) for b in _batches(fusion_arrays, 4)]
    pose_feeds = [{"points": p, "features": f} for p, f in _batches([calib.points, point_feats], 4)]
    split = {"detector": n_img, "fusion": -(-n_cal // 4), "pose": -(-n_cal // 4)}
    feeds = {"detector": det_feeds, "fusion": fus_feeds, "pose": pose_feeds}
    int8_files: dict[str, Path | None] = {"detector": None, "fusion": None, "pose": None}
    if int8:
        # float, cheap and precise: the detector's last box/class convs (their logits feed the DFL softmax /
        # sigmoid directly); the fusion branches' output convs (1 % of the FLOPs; the fused features' error
        # vs fp32 drops from 3.7 to 2.5 % RMS on the edge config); the pose net's first layer (metric points
        # in: 5 mm steps if quantized) and its heads' output convs (a uint8 translation offset has ~1 cm
        # steps; a uint8 confidence ties the argmax)
        exclude = {"detector": ("/head/box.*.2/Conv", "/head/cls.*.2/Conv"), "fusion": ("/*/final/Conv",),
                   "pose": ("/conv1/Conv", "/head_[rtc]/head_[rtc].6/Conv")}
        checks["int8"] = {}
        for stage in STAGES:
            if stage not in int8_stages:
                int8_files[stage] = files[stage]
                checks["int8"][stage] = "float graph (not quantized)"
                continue
            cal, held = feeds[stage][:split[stage]], feeds[stage][split[stage]:] or feeds[stage][-1:]
            int8_files[stage] = quantize_graph(files[stage], out / f"{stage}.int8.onnx", cal, exclude[stage])
            checks["int8"][stage] = _graph_diff(files[stage], int8_files[stage], held)
        checks["int8"]["note"] = "int8 vs fp32 on calibration inputs held out from calibration"
    if fp16_weights:
        checks["weights_fp16"] = {}
        for stage in ("detector", "fusion", "pose") if detector_onnx is None else ("fusion", "pose"):
            half = out / f"{stage}.fp16-weights.onnx"
            storage = store_weights_fp16(files[stage], half)
            diff = _graph_diff(files[stage], half, feeds[stage][split[stage]:] or feeds[stage][-1:])
            worst = max(v["rel_rms"] for v in diff.values())
            if not worst <= FP16_WEIGHTS_REL_RMS:
                half.unlink()
                raise ExportError(f"{stage}: float16 weights change the output by {worst:.2g} relative RMS "
                                  f"(limit {FP16_WEIGHTS_REL_RMS}); export with --fp32-weights")
            half.replace(files[stage])
            checks["weights_fp16"][stage] = {**storage.to_dict(), "vs_fp32_weights": diff}

    from .pallet_types import trained_pallet_models   # the pallet geometry lives with the simulator
    # every type the pose stage was trained on (provenance); the manifest's `pallet_model` is the first
    pallet = trained_pallet_models(training, cfg.pallet)[0]
    points_file = out / "pallet_points.npy"
    np.save(points_file, pallet.surface_points(2000, seed=0).astype(np.float32))

    all_files = list(dict.fromkeys(p for p in [*files.values(), *int8_files.values(), points_file] if p is not None))
    rel = lambda p: None if p is None else p.relative_to(out).as_posix()  # noqa: E731
    d, f, ps = cfg.detector, cfg.fusion, cfg.pose
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "name": name or out.name, "config": cfg.name, "classes": list(d.classes), "depth_units": "metres",
        "precision": ["fp32", "int8"] if int8 else ["fp32"],
        "detector": {"file": rel(files["detector"]), "file_int8": rel(int8_files["detector"]),
                     "input_name": det_in, "output_name": det_out, "input_hw": list(d.input_hw),
                     "letterbox_pad_value": 114, "pixel_scale": 1.0 / 255.0, "rgb_mean": [0.0, 0.0, 0.0],
                     "rgb_std": [1.0, 1.0, 1.0], "channel_order": "RGB", "layout": "yolov8",
                     "num_classes": d.num_classes, "source": "external" if detector_onnx else "pallet6d",
                     "scale": None if detector_onnx else d.scale},
        "fusion": {"file": rel(files["fusion"]), "file_int8": rel(int8_files["fusion"]), "rgb_input": "rgb",
                   "depth_input": "depth", "output_name": "features", "crop_hw": list(f.crop_hw),
                   "crop_resize": "stretch", "pixel_scale": 1.0 / 255.0, "rgb_mean": list(cfg.rgb_mean),
                   "rgb_std": list(cfg.rgb_std),
                   "depth_encoding": {"type": "metres_minus_median", "clip_m": cfg.depth_clip_m, "invalid_value": 0.0,
                                      "interpolation": "nearest"},
                   "feature_dim": f.feature_dim, "attention": f.attention,
                   "attention_stride": f.attention_stride if f.attention else None,
                   "choose_input": "choose" if sampled else None},
        "pose": {"file": rel(files["pose"]), "file_int8": rel(int8_files["pose"]), "points_input": "points",
                 "features_input": "features", "quat_output": "quat", "trans_output": "trans", "conf_output": "conf",
                 "num_points": ps.num_points, "depth_range_m": list(cfg.depth_range_m), "points_centring": "mean",
                 "translation": "point_offset", "quaternion_order": "wxyz", "selection": "max_confidence",
                 "attention": ps.attention},
        "pallet_model": {"name": pallet.name, "size_m": [float(v) for v in pallet.size_m],
                         "diameter_m": float(pallet.diameter_m), "points_file": rel(points_file),
                         "symmetries": np.asarray(pallet.symmetries).tolist(),
                         "boxes_m": np.round(np.asarray(pallet.boxes_m), 6).tolist()},
        "files": {rel(p): sha256_file(p) for p in all_files},
        "provenance": {"command": command, "seed": seed, "git_commit": _git_commit(),
                       "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                       "random_init": bool(random_init), "checkpoint": None if checkpoint is None else str(checkpoint),
                       "detector_onnx": None if detector_onnx is None else str(detector_onnx),
                       "training": training, "calibration": calib.source, "model_config": cfg.to_dict()},
        "checks": checks,
        "scores": {},
    }
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    load_bundle(out)  # the writer must satisfy its own reader
    return manifest
