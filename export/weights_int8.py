"""Store a float32 graph's weights as 8-bit integers on disk: a quarter of the file, float32 arithmetic at run time.

Each large weight of a Conv (input 1), Gemm (input B) or MatMul (second input) becomes a symmetric int8
tensor per output channel `q = round(w / s)` with `s = max|w_c| / 127` for channel c, stored with its float32
scales, and is rebuilt as `Cast(q, float) * s` (the scales broadcast along the output-channel axis) under
its own name. onnxruntime folds that Cast and Mul of constants into a float32 initializer when it builds the
session, so the graph that runs is the float32 graph with its weights rounded to 255 levels per channel
(error at most s / 2 per value), at the float32 graph's speed and memory.

Cast + Mul rather than DequantizeLinear: onnxruntime's constant folding skips DequantizeLinear (its
quantization passes look for those nodes), so a DequantizeLinear-stored weight would be dequantized at every
run. This is weight storage only; activations stay float32 (static int8 graphs are `quantize.py`).

Everything else is stored as float16 where it fits (`weights_fp16`), else float32: biases, norms, tensors
other nodes read (attention embeddings, ...), tensors below `min_elements`, and any tensor with a channel of
zeros or non-finite values (its scale would be 0 or not finite).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from onnx import TensorProto, helper, numpy_helper

from .weight_storage import Encoded, Use, WeightStorage, rewrite_weights
from .weights_fp16 import encode_fp16

__all__ = ["store_weights_int8", "encode_int8", "quantize_per_channel", "output_channel_axis", "INT8_LEVELS"]

INT8_LEVELS = 127   # symmetric: -127..127, so that -w is stored as exactly -q


def output_channel_axis(shape: tuple[int, ...], uses: list[Use]) -> int | None:
    """The axis of a weight of `shape` that indexes its consumers' output channels, or None when some reader
    is not a Conv / Gemm / MatMul taking it as its weight (or the readers disagree).

    Conv W (M, C/g, k...) -> 0; Gemm B (K, N) -> 1, transposed (N, K) -> 0; MatMul's second input (..., K, N) -> last.
    """
    axes = set()
    for node, index in uses:
        if node.op_type == "Conv" and index == 1 and len(shape) >= 3:
            axes.add(0)
        elif node.op_type == "Gemm" and index == 1 and len(shape) == 2:
            trans_b = next((a.i for a in node.attribute if a.name == "transB"), 0)
            axes.add(0 if trans_b else 1)
        elif node.op_type == "MatMul" and index == 1 and len(shape) >= 2:
            axes.add(len(shape) - 1)
        else:
            return None
    return axes.pop() if len(axes) == 1 else None


def quantize_per_channel(w32: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Symmetric int8 per slice along `axis`: `(q, scale)` with `q * scale ~ w32`, `scale` float32 shaped to
    broadcast (1 except along `axis`), |w - q * scale| <= scale / 2. None when a slice is all zeros or a value
    or scale is not finite (scale 0 or inf)."""
    if not np.all(np.isfinite(w32)):
        return None
    reduce = tuple(a for a in range(w32.ndim) if a != axis)
    peak = np.abs(w32).max(axis=reduce, keepdims=True).astype(np.float32)
    scale = (peak / np.float32(INT8_LEVELS)).astype(np.float32)
    if not np.all(np.isfinite(scale)) or not np.all(scale >= np.finfo(np.float32).tiny):
        return None
    q = np.clip(np.rint(w32 / scale), -INT8_LEVELS, INT8_LEVELS).astype(np.int8)
    return q, scale


def encode_int8(name: str, w32: np.ndarray, uses: list[Use]) -> Encoded | None:
    """`w32` as int8 `<name>__int8` and scales `<name>__scale` rebuilt by Cast + Mul into `name`, when it is a
    Conv/Gemm/MatMul weight that quantizes; otherwise float16 (`encode_fp16`) or None (float32)."""
    axis = output_channel_axis(w32.shape, uses) if uses else None
    packed = quantize_per_channel(w32, axis) if axis is not None else None
    if packed is None:
        return encode_fp16(name, w32)
    q, scale = packed
    q_name, s_name, f_name = f"{name}__int8", f"{name}__scale", f"{name}__int8_fp32"
    nodes = [helper.make_node("Cast", [q_name], [f_name], to=TensorProto.FLOAT, name=f"{name}__to_fp32"),
             helper.make_node("Mul", [f_name, s_name], [name], name=f"{name}__times_scale")]
    return Encoded([numpy_helper.from_array(q, q_name), numpy_helper.from_array(scale, s_name)], nodes, "int8")


def store_weights_int8(src: str | Path, dst: str | Path, min_elements: int = 1024) -> WeightStorage:
    """Write `src` to `dst` (may be the same path) with its large Conv/Gemm/MatMul weights stored as int8 per
    output channel and its other large float32 tensors as float16 (where they fit).

    :param min_elements: initializers smaller than this stay float32.
    :raises ValueError: `src` has an initializer that is also a graph input (weights must be constants).
    """
    return rewrite_weights(src, dst, encode_int8, "int8 per output channel on disk (float16 where not), "
                           "float32 compute", "int8", min_elements)
