"""Torch -> ONNX export of one graph, checked with `onnx.checker`, and torch-vs-onnxruntime parity."""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import onnx
import onnxruntime as ort
import torch

from pallet6d.runtime.sessions import session_options

__all__ = ["OPSET", "PARITY_TOLERANCE", "ParityError", "export_graph", "check_parity", "compare_outputs", "graph_diff", "ort_session",
           "run_session", "has_grouped_convs"]

log = logging.getLogger(__name__)

OPSET = 17
# Export fails when max |torch - onnxruntime| > PARITY_TOLERANCE * max(1, max |torch|), per output.
PARITY_TOLERANCE = 1e-4


class ParityError(RuntimeError):
    """The exported graph does not reproduce the torch model within PARITY_TOLERANCE."""


def export_graph(model: torch.nn.Module, args: tuple[torch.Tensor, ...], path: Path, input_names: list[str],
                 output_names: list[str], dynamic_axes: dict[str, dict[int, str]] | None = None) -> Path:
    """Export `model(*args)` in eval mode with the TorchScript exporter (dynamo=False), check it, return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and tracer warnings
        torch.onnx.export(model, args, str(path), input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes or {}, opset_version=OPSET, do_constant_folding=True, dynamo=False)
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    log.info("exported %s (%.1f MB)", path.name, path.stat().st_size / 1e6)
    return path


def has_grouped_convs(path: str | Path) -> bool:
    """Whether the graph at `path` has a grouped (e.g. depthwise) convolution."""
    return any(n.op_type == "Conv" and any(a.name == "group" and a.i > 1 for a in n.attribute)
               for n in onnx.load(str(path)).graph.node)


def ort_session(path: Path, threads: int = 2) -> ort.InferenceSession:
    """An onnxruntime session with the runtime's own options, so parity and int8 checks see what the runtime runs."""
    return ort.InferenceSession(str(path), sess_options=session_options(threads), providers=["CPUExecutionProvider"])


def run_session(sess: ort.InferenceSession, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(names, feeds)))


@dataclass(frozen=True)
class OutputDiff:
    max_abs: float
    ref_max_abs: float
    rel_rms: float
    corr: float

    def to_dict(self) -> dict:
        return {k: float(round(v, 7)) for k, v in self.__dict__.items()}


def compare_outputs(ref: np.ndarray, test: np.ndarray) -> OutputDiff:
    """Differences of `test` from `ref` (same shape): max abs, max |ref|, rms(diff)/rms(ref), Pearson r."""
    ref = np.asarray(ref, np.float64).ravel()
    test = np.asarray(test, np.float64).ravel()
    if ref.shape != test.shape:
        raise ValueError(f"outputs differ in size: {ref.shape} vs {test.shape}")
    diff = test - ref
    rms_ref = float(np.sqrt(np.mean(ref ** 2))) or 1.0
    corr = float(np.corrcoef(ref, test)[0, 1]) if ref.std() > 0 and test.std() > 0 else float(np.allclose(ref, test))
    return OutputDiff(float(np.abs(diff).max()), float(np.abs(ref).max()), float(np.sqrt(np.mean(diff ** 2)) / rms_ref),
                      corr)


def graph_diff(ref_path: Path, test_path: Path, feeds: list[dict[str, np.ndarray]],
               read_ref: Callable[[dict, dict], dict] | None = None) -> dict:
    """Per output: how `test_path`'s outputs differ from `ref_path`'s on `feeds` (compare_outputs); the feeds
    may differ in shape (a detector's input sizes). `read_ref(outputs, feed)` turns the reference graph's outputs
    into what the tested graph gives (e.g. an older layout of them), when they differ."""
    ref_sess, test_sess = ort_session(ref_path), ort_session(test_path)
    ref, got = {}, {}
    for f in feeds:
        ref_out = run_session(ref_sess, f)
        for k, v in (ref_out if read_ref is None else read_ref(ref_out, f)).items():
            ref.setdefault(k, []).append(v.ravel())
        for k, v in run_session(test_sess, f).items():
            got.setdefault(k, []).append(v.ravel())
    return {k: compare_outputs(np.concatenate(ref[k]), np.concatenate(got[k])).to_dict() for k in ref}


def check_parity(model: torch.nn.Module, args: tuple[torch.Tensor, ...], path: Path, input_names: list[str],
                 output_names: list[str], tolerance: float = PARITY_TOLERANCE) -> dict:
    """Run torch and onnxruntime on the same inputs; raise ParityError above `tolerance` (relative to max |ref|).

    :return: {output name: OutputDiff dict, "tolerance": ...}.
    """
    model.eval()
    with torch.no_grad():
        ref = model(*args)
    ref = (ref,) if isinstance(ref, torch.Tensor) else tuple(ref)
    got = run_session(ort_session(path), {n: a.numpy() for n, a in zip(input_names, args)})
    report: dict = {"tolerance_rel_max": tolerance}
    for name, r in zip(output_names, ref):
        d = compare_outputs(r.numpy(), got[name])
        report[name] = d.to_dict()
        limit = tolerance * max(1.0, d.ref_max_abs)
        if not d.max_abs <= limit:
            raise ParityError(f"{path.name}: output {name!r} differs from torch by {d.max_abs:.3g} "
                              f"(limit {limit:.3g}); the ONNX graph does not reproduce the model")
    return report
