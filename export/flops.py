"""Count multiply-accumulate work in an ONNX graph (Conv, ConvTranspose, MatMul, Gemm; 1 MAC = 2 FLOP).

Element-wise ops, pooling and resizing are left out (a few percent on these networks). Dynamic axes
are fixed to 1 (batch) before shape inference, so the count is per image / per pallet.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import shape_inference

__all__ = ["count_gflops"]


def _shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    shapes = {}
    for vi in list(model.graph.value_info) + list(model.graph.input) + list(model.graph.output):
        dims = [d.dim_value if d.HasField("dim_value") else None for d in vi.type.tensor_type.shape.dim]
        shapes[vi.name] = dims
    for init in model.graph.initializer:
        shapes[init.name] = list(init.dims)
    return shapes


def count_gflops(path: str | Path, fixed_dims: dict[str, int] | None = None) -> float:
    """GFLOP of one forward pass.

    :param fixed_dims: values for named dynamic axes (default: every dynamic axis = 1).
    """
    model = onnx.load(str(path))
    fixed_dims = fixed_dims or {}
    for vi in model.graph.input:
        for d in vi.type.tensor_type.shape.dim:
            if not d.HasField("dim_value"):
                d.dim_value = int(fixed_dims.get(d.dim_param, 1))
    model = shape_inference.infer_shapes(model, data_prop=True)
    shapes = _shapes(model)
    macs = 0.0
    for node in model.graph.node:
        if node.op_type in ("Conv", "ConvTranspose"):
            w = shapes.get(node.input[1])
            out = shapes.get(node.output[0])
            if not w or not out or None in out:
                raise ValueError(f"{Path(path).name}: no shape for {node.name} ({node.op_type})")
            # weight (C_out, C_in/groups, k...) ; each output element costs C_in/groups * prod(k) MACs
            macs += float(np.prod(out)) * float(np.prod(w[1:]))
        elif node.op_type in ("MatMul", "Gemm"):
            a = shapes.get(node.input[0])
            out = shapes.get(node.output[0])
            if not a or not out or None in out or a[-1] is None:
                raise ValueError(f"{Path(path).name}: no shape for {node.name} ({node.op_type})")
            transa = any(at.name == "transA" and at.i for at in node.attribute)
            k = a[-2] if transa else a[-1]
            macs += float(np.prod(out)) * float(k)
    return 2.0 * macs / 1e9
