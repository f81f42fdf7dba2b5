"""Detector stage: RGB image -> pallet detections (letterbox, detector.onnx, YOLOv8 decode + NMS)."""
from __future__ import annotations

import numpy as np

from .detector import Detections, Letterbox, decode_yolov8, letterbox, to_nchw, undo_letterbox
from .sessions import OnnxModel

__all__ = ["DetectorStage"]


class DetectorStage:
    """The bundle's detector graph with its pre- and post-processing.

    :param bundle: a loaded `Bundle`. :param precision: "fp32" or "int8". :param threads: onnxruntime threads.
    :param class_ids: the detector classes that are pallets (the others are dropped in `postprocess`).
    :param score_threshold, iou_threshold, max_detections: decoding and NMS (`decode_yolov8`).
    """

    def __init__(self, bundle, precision: str, threads: int, class_ids: tuple[int, ...], score_threshold: float,
                 iou_threshold: float, max_detections: int) -> None:
        self.spec = d = bundle.detector
        self.model = OnnxModel(bundle.graph("detector", precision), threads, (d.input_name,), (d.output_name,))
        self.class_ids = tuple(int(c) for c in class_ids)
        self.score_threshold, self.iou_threshold = float(score_threshold), float(iou_threshold)
        self.max_detections = int(max_detections)
        # reused across frames: the letterboxed image and the graph's input tensor
        self._lb_buf = np.empty((*d.input_hw, 3), np.uint8)
        self._input = np.empty((1, 3, *d.input_hw), np.float32)

    def preprocess(self, rgb: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """(H, W, 3) uint8 RGB -> the graph's (1, 3, h, w) float32 input (a buffer reused by the next call)
        and the letterbox to undo."""
        d = self.spec
        img, lb = letterbox(rgb, d.input_hw, d.letterbox_pad_value, out=self._lb_buf)
        to_nchw(img, d.rgb_mean, d.rgb_std, d.pixel_scale, d.channel_order == "BGR", out=self._input)
        return self._input, lb

    def infer(self, x: np.ndarray) -> np.ndarray:
        """The graph's raw YOLOv8 output (1, 4 + nc, A)."""
        d = self.spec
        return self.model.run({d.input_name: x}, [d.output_name])[d.output_name]

    def postprocess(self, raw: np.ndarray, lb: Letterbox) -> Detections:
        """Pallet detections in image pixels after NMS, highest score first, at most `max_detections`."""
        det = decode_yolov8(raw, self.score_threshold, self.iou_threshold, self.class_ids, self.max_detections)
        return Detections(undo_letterbox(det.boxes_xyxy, lb), det.scores, det.class_ids)
