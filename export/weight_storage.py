"""Rewrite a float32 graph's large weights into a compact storage type, decoded back to float32 by constant nodes.

The storage modules (`weights_fp16`, `weights_int8`) each give a per-tensor encoder; `rewrite_weights` walks
the initializers, lets the encoder replace each large float32 one by smaller initializers plus the nodes that
rebuild it under its own name, and saves the checked model. onnxruntime folds such constant-only nodes (Cast,
Mul) into float32 initializers when it builds the session, so the graph that runs is a float32 graph with
the decoded weights, at the float32 graph's speed and memory.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import onnx
from onnx import NodeProto, TensorProto, numpy_helper

__all__ = ["WeightStorage", "Encoded", "Use", "rewrite_weights"]

log = logging.getLogger(__name__)


class Use(NamedTuple):
    """A node that reads a weight, and at which of its inputs."""
    node: NodeProto
    index: int


class Encoded(NamedTuple):
    """One weight's storage: the initializers and nodes that rebuild it (float32, under its own name), and the
    storage type ("int8", "float16")."""
    initializers: list
    nodes: list
    dtype: str


# tensor name -> float32 values -> the nodes that read it -> its encoding, or None to keep it float32
Encoder = Callable[[str, np.ndarray, list], "Encoded | None"]


@dataclass(frozen=True)
class WeightStorage:
    """What a storage rewrite did: tensors stored in the compact type (`converted`), large tensors left in
    float16 or float32 because they did not qualify, file sizes in bytes.

    :ivar weights: the storage in words, as recorded in report.json.
    """
    weights: str
    converted: int
    kept_fp16: int
    kept_fp32: int
    bytes_before: int
    bytes_after: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _uses(graph: onnx.GraphProto) -> dict[str, list[Use]]:
    uses: dict[str, list[Use]] = defaultdict(list)
    for node in graph.node:
        for k, name in enumerate(node.input):
            uses[name].append(Use(node, k))
    return uses


def rewrite_weights(src: str | Path, dst: str | Path, encode: Encoder, weights: str, converted_dtype: str,
                    min_elements: int) -> WeightStorage:
    """Write `src` to `dst` (may be the same path) with each float32 initializer of at least `min_elements`
    values replaced by `encode`'s storage; a tensor `encode` declines stays float32.

    :param weights: the storage in words, for the record.
    :param converted_dtype: the dtype counted as `converted`; float16 encodings of other tensors count as kept
        float16.
    :raises ValueError: `src` has a large initializer that is also a graph input (weights must be constants).
    """
    src, dst = Path(src), Path(dst)
    model = onnx.load(str(src))
    graph = model.graph
    graph_inputs = {i.name for i in graph.input}
    uses = _uses(graph)
    decoders, keep, counts = [], [], {"int8": 0, "float16": 0, "float32": 0}
    for init in graph.initializer:
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < min_elements:
            keep.append(init)
            continue
        if init.name in graph_inputs:
            raise ValueError(f"{src.name}: initializer {init.name!r} is also a graph input; cannot store it as a constant")
        enc = encode(init.name, numpy_helper.to_array(init), uses.get(init.name, []))
        if enc is None:
            keep.append(init)
            counts["float32"] += 1
            continue
        keep.extend(enc.initializers)
        decoders.extend(enc.nodes)
        counts[enc.dtype] += 1
    del graph.initializer[:]
    graph.initializer.extend(keep)
    nodes = decoders + list(graph.node)   # the decoders first: the node list stays topologically sorted
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model, full_check=True)
    before = src.stat().st_size
    onnx.save(model, str(dst))
    converted = counts.pop(converted_dtype)
    storage = WeightStorage(weights, converted, counts.get("float16", 0), counts["float32"], before,
                            dst.stat().st_size)
    log.info("%s: %d weight tensors stored as %s (%.1f -> %.1f MB)", dst.name, converted, converted_dtype,
             before / 1e6, storage.bytes_after / 1e6)
    return storage
