"""Store a float32 graph's weights as float16 on disk: half the file, float32 arithmetic at run time.

Each float32 initializer of at least `min_elements` values is replaced by a float16 copy feeding a Cast
back to float32. onnxruntime folds those Casts into float32 constants when it builds the session, so the
graph that runs is the float32 graph with its weights rounded to float16 (relative rounding <= 2**-11),
at the same speed; only the file shrinks. Small tensors (biases, shapes, scales) and any tensor whose
values do not fit float16 stay float32. The int8 graphs are quantized from the full float32 weights,
before this step.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

__all__ = ["WeightStorage", "store_weights_fp16", "FP16_MAX"]

log = logging.getLogger(__name__)

FP16_MAX = float(np.finfo(np.float16).max)


@dataclass(frozen=True)
class WeightStorage:
    """What `store_weights_fp16` did: tensors converted, tensors kept float32, file sizes in bytes."""
    converted: int
    kept_fp32: int
    bytes_before: int
    bytes_after: int

    def to_dict(self) -> dict:
        return {"weights": "float16 on disk, float32 compute", **self.__dict__}


def store_weights_fp16(src: str | Path, dst: str | Path, min_elements: int = 1024) -> WeightStorage:
    """Write `src` to `dst` (may be the same path) with its large float32 weights stored as float16.

    :param min_elements: initializers smaller than this stay float32.
    :raises ValueError: `src` has an initializer that is also a graph input (weights must be constants).
    """
    src, dst = Path(src), Path(dst)
    model = onnx.load(str(src))
    graph = model.graph
    graph_inputs = {i.name for i in graph.input}
    casts, keep, converted, kept = [], [], 0, 0
    for init in graph.initializer:
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < min_elements:
            keep.append(init)
            continue
        if init.name in graph_inputs:
            raise ValueError(f"{src.name}: initializer {init.name!r} is also a graph input; cannot store it as a constant")
        w32 = numpy_helper.to_array(init)
        if not np.all(np.isfinite(w32)) or np.abs(w32).max() > FP16_MAX:
            keep.append(init)
            kept += 1
            continue
        half_name = f"{init.name}__fp16"
        keep.append(numpy_helper.from_array(w32.astype(np.float16), half_name))
        casts.append(helper.make_node("Cast", [half_name], [init.name], to=TensorProto.FLOAT,
                                      name=f"{init.name}__to_fp32"))
        converted += 1
    del graph.initializer[:]
    graph.initializer.extend(keep)
    nodes = casts + list(graph.node)   # the Casts first: the node list stays topologically sorted
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model, full_check=True)
    before = src.stat().st_size
    onnx.save(model, str(dst))
    storage = WeightStorage(converted, kept, before, dst.stat().st_size)
    log.info("%s: %d weight tensors stored as float16 (%.1f -> %.1f MB)", dst.name, converted, before / 1e6,
             storage.bytes_after / 1e6)
    return storage
