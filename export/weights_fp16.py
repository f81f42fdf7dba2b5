"""Store a float32 graph's weights as float16 on disk: half the file, float32 arithmetic at run time.

Each float32 initializer of at least `min_elements` values is replaced by a float16 copy feeding a Cast
back to float32. onnxruntime folds those Casts into float32 constants when it builds the session, so the
graph that runs is the float32 graph with its weights rounded to float16 (relative rounding <= 2**-11),
at the same speed; only the file shrinks. Small tensors (biases, shapes, scales) and any tensor whose
values do not fit float16 stay float32. The int8 graphs are quantized from the full float32 weights,
before this step.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from onnx import TensorProto, helper, numpy_helper

from .weight_storage import Encoded, WeightStorage, rewrite_weights

__all__ = ["WeightStorage", "store_weights_fp16", "encode_fp16", "FP16_MAX"]

FP16_MAX = float(np.finfo(np.float16).max)


def encode_fp16(name: str, w32: np.ndarray, uses: list | None = None) -> Encoded | None:
    """`w32` as a float16 initializer `<name>__fp16` and a Cast to float32 named `name`; None when a value is
    not finite or beyond float16's range."""
    if not np.all(np.isfinite(w32)) or np.abs(w32).max() > FP16_MAX:
        return None
    half_name = f"{name}__fp16"
    cast = helper.make_node("Cast", [half_name], [name], to=TensorProto.FLOAT, name=f"{name}__to_fp32")
    return Encoded([numpy_helper.from_array(w32.astype(np.float16), half_name)], [cast], "float16")


def store_weights_fp16(src: str | Path, dst: str | Path, min_elements: int = 1024) -> WeightStorage:
    """Write `src` to `dst` (may be the same path) with its large float32 weights stored as float16.

    :param min_elements: initializers smaller than this stay float32.
    :raises ValueError: `src` has an initializer that is also a graph input (weights must be constants).
    """
    return rewrite_weights(src, dst, encode_fp16, "float16 on disk, float32 compute", "float16", min_elements)
