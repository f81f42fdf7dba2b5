"""Static int8 quantization (onnxruntime QDQ format, per-channel int8 weights, uint8 activations).

Convolutions are nearly all of the work and where the int8 speed-up is (DESIGN.md: static QDQ ~3x faster
on 2 cores, dynamic not). In the fusion and pose graphs only they are quantized: MatMuls stay float
(quantizing the PSP pooling matrices and the attention products, both operands activations, dropped the
fusion output's correlation with fp32 from 0.99998 to 0.60 on the edge config), and so do the quaternion
normalisation and the sigmoids. The detector is a plain conv net whose SiLU activations (Sigmoid, Mul),
residual Adds, Concats, pooling and upsampling sit between its convs: left float, each costs a
dequantize/quantize pair and a float op, together more time than the int8 convs themselves; quantized
(`DETECTOR_OPS`), onnxruntime fuses them into uint8 kernels and the graph stays int8 from the stem to the
heads. Its box decoding (DFL softmax, pixel arithmetic) stays float. Activation ranges come from
calibration inputs (`calib_data`), MinMax.
"""
from __future__ import annotations

import fnmatch
import logging
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                      quantize_static)
from onnxruntime.quantization.shape_inference import quant_pre_process

from .onnx_io import has_grouped_convs

__all__ = ["CONV_OPS", "DETECTOR_OPS", "INT8_RECIPES", "int8_recipe", "quantize_graph"]

CONV_OPS = ("Conv",)
# the detector's backbone, neck and heads up to the box/class logits: convs, SiLU (or ReLU, which onnxruntime folds
# into the conv before it), residual adds, the neck's concats, SPPF's max pools, the upsampling, C2f's splits
DETECTOR_OPS = ("Conv", "Sigmoid", "Mul", "Relu", "Add", "Concat", "MaxPool", "Resize", "Split")

# per stage, `quantize_graph`'s keyword arguments. Detector: the whole graph up to and with its box output
# convs (validation recall unchanged, boxes within a pixel of fp32); the class output convs and the decoding
# after them stay float: uint8 class logits span the background's large negative logits in ~0.36 steps, which
# left 14 distinct scores above 0.1 (0.189, 0.251, 0.263, 0.326, ...), so a threshold between two of them meant
# the same and equal scores tied the ranking. Fusion: convs but the branches' output convs (1 % of the FLOPs;
# the fused features' error vs fp32 drops from 3.7 to 2.5 % RMS on the edge config). Pose: convs but its first
# layer (metric points in: 5 mm steps if quantized) and its heads' output convs (a uint8 translation offset has
# ~1 cm steps; a uint8 confidence ties the argmax). Every range is the extremes over all calibration batches: the
# mean of the batches' extremes (`moving_average`) clipped the fusion features (14-20 % RMS error against 2 %) and
# posed 11 fewer occluded validation pallets of 821 with the detector (docs/experiments/detector-levels.md).
# The depthwise detector (`detector_dw`, no BatchNorm) also keeps its stem and first downsampling float: a few
# channels there span far wider ranges than the rest, and one uint8 scale per tensor moved its class scores by up
# to 0.5 (indoor-noisy validation AP 0.95 -> 0.24); with the two float, 0.96 (docs/experiments/real-data.md).
INT8_RECIPES: dict[str, dict] = {
    "detector": {"op_types": DETECTOR_OPS, "exclude_nodes": ("/head/cls.*.2/Conv",),
                 "float_after": ("/head/box.*.2/Conv", "/head/cls.*.2/Conv")},
    "detector-depthwise": {"op_types": DETECTOR_OPS,
                           "exclude_nodes": ("/head/cls.*.2/Conv", "/stem/*", "/dark2/dark2.0/*"),
                           "float_after": ("/head/box.*.2/Conv", "/head/cls.*.2/Conv")},
    "fusion": {"exclude_nodes": ("/*/final/Conv",)},
    "pose": {"exclude_nodes": ("/conv1/Conv", "/head_[rtc]/head_[rtc].6/Conv")},
}

log = logging.getLogger(__name__)


def int8_recipe(stage: str, fp32_path: Path) -> dict:
    """`quantize_graph`'s keyword arguments for `stage`'s graph at `fp32_path` (a depthwise detector has its own)."""
    if stage == "detector" and has_grouped_convs(fp32_path):
        return INT8_RECIPES["detector-depthwise"]
    return INT8_RECIPES[stage]


def _downstream(graph: onnx.GraphProto, patterns: tuple[str, ...]) -> list[str]:
    """Names of the nodes fed, directly or not, by the nodes matching `patterns` (not those nodes)."""
    tensors = {o for n in graph.node if any(fnmatch.fnmatchcase(n.name, p) for p in patterns) for o in n.output}
    found: list[str] = []
    for n in graph.node:                        # ONNX graphs are topologically sorted
        if any(i in tensors for i in n.input):
            found.append(n.name)
            tensors.update(n.output)
    return found


class _FeedReader(CalibrationDataReader):
    def __init__(self, feeds: list[dict[str, np.ndarray]]) -> None:
        self._it = iter(feeds)

    def get_next(self):
        return next(self._it, None)


def quantize_graph(fp32_path: Path, int8_path: Path, feeds: list[dict[str, np.ndarray]],
                   exclude_nodes: tuple[str, ...] = (), op_types: tuple[str, ...] = CONV_OPS,
                   float_after: tuple[str, ...] = (), moving_average: bool = False) -> Path:
    """Write a static QDQ int8 copy of `fp32_path` calibrated on `feeds` (one dict of inputs per batch).

    :param exclude_nodes: fnmatch patterns of node names kept in float.
    :param op_types: the operator types to quantize (`CONV_OPS`, or `DETECTOR_OPS` for the detector).
    :param float_after: fnmatch patterns of node names whose downstream nodes all stay float (e.g. the
        detector's output convs: its box decoding computes in pixels).
    :param moving_average: each tensor's range is the mean of the batches' minima and maxima, not the extremes
        over all of them: one unusual calibration batch no longer sets the range for every input.
    """
    if not feeds:
        raise ValueError("int8 quantization needs at least one calibration batch")
    graph = onnx.load(str(fp32_path)).graph
    names = [n.name for n in graph.node]
    excluded = [n for n in names if any(fnmatch.fnmatchcase(n, e) for e in exclude_nodes)]
    after = _downstream(graph, float_after)
    if float_after and not after and set(op_types) != set(CONV_OPS):
        # e.g. a detector from another toolchain, named otherwise: its decoding must not become uint8
        log.warning("%s: no node matches %s; quantizing its convolutions only", Path(fp32_path).name, float_after)
        op_types = CONV_OPS
    excluded += [n for n in after if n not in excluded]
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(int8_path), _FeedReader(feeds), quant_format=QuantFormat.QDQ,
                        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        op_types_to_quantize=list(op_types), nodes_to_exclude=excluded,
                        calibrate_method=CalibrationMethod.MinMax,
                        extra_options={"CalibMovingAverage": bool(moving_average)})
    onnx.checker.check_model(onnx.load(str(int8_path)))
    log.info("quantized %s -> %s (%d calibration batches, %d nodes kept float)", Path(fp32_path).name,
             Path(int8_path).name, len(feeds), len(excluded))
    return Path(int8_path)
