"""Detector stage: RGB (or RGB-D) image -> pallet detections (letterbox, detector.onnx, YOLOv8 decode + NMS)."""
from __future__ import annotations

import numpy as np

from .detector import (Detections, Letterbox, choose_input_hw, decode_yolov8, depth_channel, letterbox, letterbox_depth,
                       to_nchw, undo_letterbox, unmirror_yolov8)
from .sessions import OnnxModel

__all__ = ["DetectorStage"]


class DetectorStage:
    """The bundle's detector graph with its pre- and post-processing.

    Each frame is letterboxed to the manifest's input size that draws it largest (`choose_input_hw` over
    `detector.input_sizes`; a single-size bundle always uses `input_hw`). An RGB-D detector (`detector.depth_max_m`)
    takes the depth letterboxed the same way as a fourth channel; without depth (an RGB photograph) that channel
    is 0, "no data", which such a detector is trained to accept.

    :param bundle: a loaded `Bundle`. :param precision: "fp32" or "int8". :param threads: onnxruntime threads.
    :param class_ids: the detector classes that are pallets (the others are dropped in `postprocess`).
    :param score_threshold, iou_threshold, max_detections: decoding and NMS (`decode_yolov8`).
    :param mirror: also run the graph on the left-right mirrored input and average each anchor's class scores with
        those of the anchor it mirrors before decoding; the boxes stay the unmirrored run's (`unmirror_yolov8`;
        `EstimatorOptions.detector_mirror`).
    """

    def __init__(self, bundle, precision: str, threads: int, class_ids: tuple[int, ...], score_threshold: float,
                 iou_threshold: float, max_detections: int, mirror: bool = False) -> None:
        self.spec = bundle.detector
        self.model = OnnxModel(bundle.graph("detector", precision), threads, (self.spec.input_name,),
                               (self.spec.output_name,))
        self.class_ids = tuple(int(c) for c in class_ids)
        self.score_threshold, self.iou_threshold = float(score_threshold), float(iou_threshold)
        self.max_detections = int(max_detections)
        self.mirror = bool(mirror)
        # reused across frames, per input size: the letterboxed image and the graph's input tensor
        self._buffers: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}

    def input_hw_for(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """The detector input (H_in, W_in) a frame of `image_hw` (H, W) is letterboxed to."""
        return choose_input_hw(image_hw, self.spec.input_sizes)

    def preprocess(self, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> tuple[np.ndarray, Letterbox]:
        """(H, W, 3) uint8 RGB (and, for an RGB-D detector, (H, W) float32 depth in metres or None) -> the
        graph's (1, C, h, w) float32 input (a buffer reused by the next call of the same input size) and the
        letterbox to undo. An RGB detector ignores `depth_m`."""
        d = self.spec
        hw = self.input_hw_for(rgb.shape[:2])
        c = d.input_channels
        if hw not in self._buffers:
            self._buffers[hw] = (np.empty((*hw, 3), np.uint8), np.empty((1, c, *hw), np.float32),
                                 np.empty(hw, np.float32) if c == 4 else None)
        lb_buf, x, depth_buf = self._buffers[hw]
        img, lb = letterbox(rgb, hw, d.letterbox_pad_value, out=lb_buf)
        to_nchw(img, d.rgb_mean, d.rgb_std, d.pixel_scale, d.channel_order == "BGR", out=x[:, :3])
        if c == 4:
            if depth_m is None:
                x[0, 3] = 0.0
            else:
                depth_channel(letterbox_depth(depth_m, lb, out=depth_buf), d.depth_max_m, out=x[0, 3])
        return x, lb

    def infer(self, x: np.ndarray) -> np.ndarray:
        """The graph's raw YOLOv8 output (1, 4 + nc, A); with `mirror`, its class scores the mean of its own and the
        mirrored input's (its boxes its own)."""
        d = self.spec
        raw = self.model.run({d.input_name: x}, [d.output_name])[d.output_name]
        if not self.mirror:
            return raw
        mirrored = self.model.run({d.input_name: np.ascontiguousarray(x[..., ::-1])}, [d.output_name])[d.output_name]
        raw[:, 4:] = (raw[:, 4:] + unmirror_yolov8(mirrored, x.shape[-2:])[:, 4:]) / 2      # onnxruntime's own array
        return raw

    def postprocess(self, raw: np.ndarray, lb: Letterbox) -> Detections:
        """Pallet detections in image pixels after NMS across the pallet classes (a detector that reports the
        type may score one pallet as two types), highest score first, at most `max_detections`."""
        det = decode_yolov8(raw, self.score_threshold, self.iou_threshold, self.class_ids, self.max_detections,
                            agnostic=True)
        return Detections(undo_letterbox(det.boxes_xyxy, lb), det.scores, det.class_ids, det.class_scores)
