"""What an export starts from: a training checkpoint, or fresh networks warmed up on calibration inputs, and
optionally a YOLOv8 detector graph made elsewhere (`--detector-onnx`).

Checkpoint format (`--checkpoint FILE`, written by training): ``torch.save({"config": name,
"detector": state_dict | absent, "fusion": state_dict, "pose": state_dict})``.

External detector: any YOLOv8 ONNX graph in the ultralytics export layout, e.g.
``yolo export model=best.pt format=onnx imgsz=384,1216`` (static batch, opset >= 12), which has one
input (1, 3, H, W) float RGB in [0, 1] (letterboxed with grey 114) and one output (1, 4 + nc, A)
with cx, cy, w, h in input pixels and sigmoid class scores. H, W come from its input shape; class names
from its `names` metadata (ultralytics writes it) unless given; nc must match.
"""
from __future__ import annotations

import ast
import logging
import subprocess
from pathlib import Path

import numpy as np
import onnx
import torch

from .config import DETECTOR_ACTIVATIONS, DETECTOR_ARCHITECTURES, ModelConfig
from .onnx_io import ort_session

__all__ = ["ExportError", "DET_IN", "DET_OUT", "git_commit", "warm_up_batchnorm", "read_checkpoint",
           "trained_input_hw", "trained_input_sizes", "trained_depth_max_m", "trained_activation",
           "trained_architecture",
           "load_checkpoint", "external_detector"]

log = logging.getLogger(__name__)

DET_IN, DET_OUT = "images", "output0"


class ExportError(ValueError):
    """The export cannot proceed (bad checkpoint, bad external detector, ...)."""


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


@torch.no_grad()
def warm_up_batchnorm(model: torch.nn.Module, batches: list[tuple[torch.Tensor, ...]]) -> None:
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


def read_checkpoint(path: Path) -> dict:
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ExportError(f"cannot read checkpoint {path}: {exc}") from None
    if not isinstance(ckpt, dict):
        raise ExportError(f"checkpoint {path}: expected a dict with 'detector'/'fusion'/'pose' state dicts")
    return ckpt


def _detector_provenance(ckpt: dict) -> dict:
    """The detector stage's provenance: a detector checkpoint's own, or a merged one's "detector" entry."""
    prov = ckpt.get("provenance")
    if not isinstance(prov, dict):
        return {}
    det = prov if prov.get("stage") == "detector" else prov.get("detector")
    return det if isinstance(det, dict) else {}


def trained_input_hw(ckpt: dict) -> tuple[int, int] | None:
    """The detector input (H, W) a checkpoint's detector was trained at (`pallet6d train detector
    --detector-input`), from its provenance; None when not recorded (then the config's size applies)."""
    hw = _detector_provenance(ckpt).get("input_hw")
    return (int(hw[0]), int(hw[1])) if hw is not None else None


def trained_depth_max_m(ckpt: dict) -> float | None:
    """The depth scale of a checkpoint's RGB-D detector (`pallet6d train detector --detector-depth-max-m`), from
    its provenance; None for an RGB detector (or a checkpoint that does not record it)."""
    v = _detector_provenance(ckpt).get("depth_max_m")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
        raise ExportError(f"the checkpoint's detector provenance has depth_max_m {v!r}, not a positive number")
    return float(v)


def _recorded_choice(ckpt: dict, key: str, choices: tuple[str, ...]) -> str:
    """A detector provenance entry that names one of `choices`; the first choice when not recorded (every
    detector trained before the option was of that kind)."""
    v = _detector_provenance(ckpt).get(key, choices[0])
    if v not in choices:
        raise ExportError(f"the checkpoint's detector provenance has {key} {v!r}, not one of {choices}")
    return v


def trained_activation(ckpt: dict) -> str:
    """The activation of a checkpoint's detector (`pallet6d train detector --detector-activation`); "silu" when
    not recorded."""
    return _recorded_choice(ckpt, "activation", DETECTOR_ACTIVATIONS)


def trained_architecture(ckpt: dict) -> str:
    """The architecture of a checkpoint's detector (`pallet6d train detector --detector-architecture`); "yolov8"
    when not recorded."""
    return _recorded_choice(ckpt, "architecture", DETECTOR_ARCHITECTURES)


def trained_classes(ckpt: dict) -> tuple[str, ...] | None:
    """The class names a checkpoint's detector was trained with (provenance key `classes`: one per pallet
    type, or one for every type); None when not recorded (then the config's classes apply).

    :raises ExportError: the record is not a non-empty list of names.
    """
    names = _detector_provenance(ckpt).get("classes")
    if names is None:
        return None
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise ExportError(f"the checkpoint's detector provenance has classes {names!r}, not a list of names")
    return tuple(names)


def trained_input_sizes(ckpt: dict) -> tuple[tuple[int, int], ...] | None:
    """The detector input sizes [[H, W], ...] a checkpoint's detector was trained on (provenance key
    `input_sizes`); None when not recorded (then it was trained at `input_hw` alone).

    :raises ExportError: the record is not a list of [H, W].
    """
    sizes = _detector_provenance(ckpt).get("input_sizes")
    if sizes is None:
        return None
    try:
        out = tuple((int(h), int(w)) for h, w in sizes)
    except (TypeError, ValueError):
        raise ExportError(f"the checkpoint's detector provenance has input_sizes {sizes!r}, not a list of "
                          "[H, W]") from None
    return out or None


def load_checkpoint(path: Path, ckpt: dict, nets: dict[str, torch.nn.Module], cfg: ModelConfig,
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


def external_detector(path: Path, classes: tuple[str, ...] | None) -> tuple[tuple[int, int], tuple[str, ...]]:
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
