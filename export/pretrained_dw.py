"""Published YOLOX-Nano COCO weights (an ONNX export, BatchNorm folded) into `detector_dw.DepthwiseDetector`.

The published network reads BGR in 0-255; ours reads RGB in [0, 1]: the stem's kernels are scaled by 255 and
their colour channels reversed within each of the four space-to-depth groups, so both compute the same maps.
The class, box and objectness output convolutions are not taken (their outputs are COCO's 80 classes and
another box code); the detector's own output convolutions keep their initialisation.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch

from .detector_dw import DepthwiseDetector

__all__ = ["PretrainedError", "PUBLISHED_WEIGHTS", "load_yolox_onnx", "published_convs"]

_OUTPUT_PREFIXES = ("head.cls_preds.", "head.reg_preds.", "head.obj_preds.")

# Weight files whose source and licence are known, by sha256: a bundle's data card lists the one its detector
# started from (`real_data.ship_card`), and refuses a file not listed here (no licence, no use).
PUBLISHED_WEIGHTS: dict[str, dict[str, str]] = {
    "695e750a5d5754bb5a8d5325643b59282191a7e7a564e435a415fd3c578eab14": {
        "name": "YOLOX-Nano, COCO 2017 (80 classes), ONNX at 416 x 416",
        "repository": "github.com/Kazuhito00/YOLOX-ONNX-TFLite-Sample", "path": "model/yolox_nano.onnx",
        "licence": "Apache-2.0 (the repository; the weights are Megvii's YOLOX-Nano release, Apache-2.0)",
        "attribution": "YOLOX: Exceeding YOLO Series in 2021, Z. Ge, S. Liu, F. Wang, Z. Li, J. Sun (Megvii); "
                       "ONNX export by the GitHub user Kazuhito00"},
}


class PretrainedError(ValueError):
    """The file is not the published network this detector is laid out as."""


def published_convs(path: str | Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The convolutions of an ONNX graph in the order its nodes run, output convolutions left out:
    [(node name, weight (O, I/groups, k, k), bias (O,))]. :raises PretrainedError: a conv without a bias."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    init = {t.name: t for t in graph.initializer}
    out = []
    for node in graph.node:
        if node.op_type != "Conv" or node.input[1].startswith(_OUTPUT_PREFIXES):
            continue
        if len(node.input) < 3 or node.input[1] not in init or node.input[2] not in init:
            raise PretrainedError(f"{path}: convolution {node.name!r} has no constant weight and bias "
                                  "(BatchNorm folded): not the published ONNX export")
        out.append((node.name, numpy_helper.to_array(init[node.input[1]]), numpy_helper.to_array(init[node.input[2]])))
    return out


def load_yolox_onnx(model: DepthwiseDetector, path: str | Path) -> dict:
    """Fill `model`'s pretrained convolutions from the published ONNX export at `path`.

    :return: a provenance record (file name, sha256, convolutions filled, parameters filled).
    :raises PretrainedError: the graph's convolutions do not match the detector's, in number or shape.
    """
    path = Path(path)
    src = published_convs(path)
    dst = model.pretrained_convs()
    if len(src) != len(dst):
        raise PretrainedError(f"{path}: {len(src)} convolutions besides the outputs, the detector has {len(dst)}")
    n_params = 0
    with torch.no_grad():
        for k, ((name, w, b), conv) in enumerate(zip(src, dst)):
            if k == 0:
                w = stem_for_rgb01(w)
            if tuple(w.shape) != tuple(conv.weight.shape) or tuple(b.shape) != tuple(conv.bias.shape):
                raise PretrainedError(f"{path}: convolution {k} ({name}) is {tuple(w.shape)}, the detector's is "
                                      f"{tuple(conv.weight.shape)}")
            conv.weight.copy_(torch.from_numpy(np.array(w)))
            conv.bias.copy_(torch.from_numpy(np.array(b)))
            n_params += w.size + b.size
    return {"file": path.name, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "convolutions": len(dst),
            "parameters": int(n_params)}


def stem_for_rgb01(w_bgr255: np.ndarray) -> np.ndarray:
    """The stem's (O, 12, k, k) kernels for BGR 0-255 space-to-depth input, made for RGB [0, 1] input."""
    if w_bgr255.ndim != 4 or w_bgr255.shape[1] != 12:
        raise PretrainedError(f"the stem convolution must read 12 channels (4 x BGR), got {w_bgr255.shape}")
    order = [3 * g + c for g in range(4) for c in (2, 1, 0)]
    return w_bgr255[:, order] * 255.0
