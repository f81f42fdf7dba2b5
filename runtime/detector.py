"""Detector pre- and post-processing in numpy: letterbox, YOLOv8 output decoding, NMS.

The detector graph takes a letterboxed RGB image (1, 3, H_in, W_in) float32 and returns the YOLOv8 ONNX
layout (B, 4 + nc, A): for each of A anchors, box centre x, centre y, width, height in input pixels, then
nc class scores (already sigmoid). Any YOLOv8 toolchain's export drops in.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Letterbox", "choose_input_hw", "letterbox", "letterbox_depth", "depth_channel", "to_nchw", "decode_yolov8",
           "unmirror_yolov8", "nms", "undo_letterbox", "Detections"]


@dataclass(frozen=True)
class Letterbox:
    """How an image was fitted into the detector input: input = image * scale + pad.

    Separate x/y scales because the resized size is rounded to whole pixels; undoing with these is exact.
    """

    scale_x: float
    scale_y: float
    pad_x: int
    pad_y: int
    image_hw: tuple[int, int]
    input_hw: tuple[int, int]


def choose_input_hw(image_hw: tuple[int, int], input_sizes) -> tuple[int, int]:
    """The detector input size (H_in, W_in) of `input_sizes` that draws an image of `image_hw` largest when
    letterboxed (the largest min(H_in / H, W_in / W)); ties go to the smaller input, then to the earlier size.

    One fully convolutional detector serves cameras of every aspect ratio at about the same cost: a 1224x370 frame
    gets a wide input, a 640x480 frame a squarer one, each filled instead of padded.

    :param image_hw: (H, W) of the image, both >= 1. :param input_sizes: non-empty sequence of (H_in, W_in).
    """
    h, w = int(image_hw[0]), int(image_hw[1])
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {image_hw}")
    sizes = [(int(s[0]), int(s[1])) for s in input_sizes]
    if not sizes:
        raise ValueError("input_sizes is empty: the detector needs at least one input size")
    return min(sizes, key=lambda s: (-round(min(s[0] / h, s[1] / w), 9), s[0] * s[1]))


def letterbox(rgb: np.ndarray, input_hw: tuple[int, int], pad_value: int = 114,
              out: np.ndarray | None = None) -> tuple[np.ndarray, Letterbox]:
    """Resize keeping the aspect ratio, centred, padded with `pad_value` (YOLOv8's grey).

    :param rgb: (H, W, 3) uint8.
    :param input_hw: (H_in, W_in) detector input size.
    :param out: optional (H_in, W_in, 3) uint8 buffer to write into (reused across frames).
    :return: (H_in, W_in, 3) uint8 image and the `Letterbox` to undo it.
    """
    h, w = rgb.shape[:2]
    h_in, w_in = int(input_hw[0]), int(input_hw[1])
    r = min(h_in / h, w_in / w)
    new_w, new_h = max(1, int(round(w * r))), max(1, int(round(h * r)))
    pad_x, pad_y = (w_in - new_w) // 2, (h_in - new_h) // 2
    if out is None or out.shape != (h_in, w_in, 3) or out.dtype != np.uint8:
        out = np.empty((h_in, w_in, 3), dtype=np.uint8)
    out[...] = pad_value
    resized = rgb if (new_w, new_h) == (w, h) else cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    out[pad_y:pad_y + new_h, pad_x:pad_x + new_w] = resized
    return out, Letterbox(new_w / w, new_h / h, pad_x, pad_y, (h, w), (h_in, w_in))


def letterbox_depth(depth_m: np.ndarray, lb: Letterbox, out: np.ndarray | None = None) -> np.ndarray:
    """Depth drawn into the detector input exactly where `letterbox` drew its colour image (nearest neighbour, so
    no depth is invented between a pallet and the wall behind it), 0 (no data) in the padding.

    :param depth_m: (H, W) float metres, 0 = no data, the image `lb` was made from.
    :param out: optional (H_in, W_in) float32 buffer. :return: (H_in, W_in) float32 metres.
    """
    h, w = lb.image_hw
    if depth_m.shape != (h, w):
        raise ValueError(f"depth is {depth_m.shape}, the letterboxed image was {(h, w)}")
    h_in, w_in = lb.input_hw
    new_w, new_h = max(1, int(round(w * lb.scale_x))), max(1, int(round(h * lb.scale_y)))
    if out is None or out.shape != (h_in, w_in) or out.dtype != np.float32:
        out = np.empty((h_in, w_in), dtype=np.float32)
    out[...] = 0.0
    d = depth_m.astype(np.float32, copy=False)
    resized = d if (new_w, new_h) == (w, h) else cv2.resize(d, (new_w, new_h), interpolation=cv2.INTER_NEAREST)
    out[lb.pad_y:lb.pad_y + new_h, lb.pad_x:lb.pad_x + new_w] = resized
    return out


def depth_channel(depth_m: np.ndarray, depth_max_m: float, out: np.ndarray | None = None) -> np.ndarray:
    """An RGB-D detector's depth input: depth / `depth_max_m` clipped to [0, 1]; no data (0, NaN) stays 0.

    :param depth_m: (H, W) float metres. :param out: optional (H, W) float32 buffer. :return: (H, W) float32.
    """
    if not depth_max_m > 0:
        raise ValueError(f"depth_max_m must be > 0, got {depth_max_m}")
    if out is None or out.shape != depth_m.shape or out.dtype != np.float32:
        out = np.empty(depth_m.shape, dtype=np.float32)
    np.multiply(depth_m, np.float32(1.0 / depth_max_m), out=out, casting="unsafe")
    np.nan_to_num(out, copy=False, nan=0.0)
    np.clip(out, 0.0, 1.0, out=out)
    return out


def to_nchw(image: np.ndarray, mean: np.ndarray, std: np.ndarray, pixel_scale: float = 1.0 / 255.0,
            bgr: bool = False, out: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 3, H, W) float32, (x * pixel_scale - mean) / std per channel.

    :param mean: (3,); :param std: (3,) per channel of the output order.
    :param bgr: the graph wants BGR channel order (the channels are swapped).
    :param out: optional (1, 3, H, W) float32 buffer to write into.
    """
    h, w = image.shape[:2]
    if out is None or out.shape != (1, 3, h, w):
        out = np.empty((1, 3, h, w), dtype=np.float32)
    std = np.asarray(std, dtype=np.float32)
    scale = (np.float32(pixel_scale) / std).reshape(3, 1, 1)
    shift = (np.asarray(mean, dtype=np.float32) / std).reshape(3, 1, 1)
    chw = image.transpose(2, 0, 1)
    np.multiply(chw[::-1] if bgr else chw, scale, out=out[0], casting="unsafe")
    out[0] -= shift
    return out


@dataclass(frozen=True)
class Detections:
    """Detections of one image.

    :ivar boxes_xyxy: (n, 4) float64 x1, y1, x2, y2 (pixels of the image they refer to).
    :ivar scores: (n,) float64.
    :ivar class_ids: (n,) int64.
    :ivar class_scores: (n, nc) float64 every class's score of each detection (the detector's, before NMS), or
        None where only the best class is known (boxes from elsewhere).
    """

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    class_ids: np.ndarray
    class_scores: np.ndarray | None = None

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes_xyxy, dtype=np.float64).reshape(-1, 4) if np.size(self.boxes_xyxy) == 0 \
            else np.asarray(self.boxes_xyxy, dtype=np.float64)
        scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        class_ids = np.asarray(self.class_ids, dtype=np.int64).reshape(-1)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"Detections.boxes_xyxy: expected (n, 4), got {boxes.shape}")
        if not (len(boxes) == len(scores) == len(class_ids)):
            raise ValueError(f"Detections: {len(boxes)} boxes, {len(scores)} scores, {len(class_ids)} class ids")
        object.__setattr__(self, "boxes_xyxy", boxes)
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "class_ids", class_ids)
        if self.class_scores is not None:
            cs = np.asarray(self.class_scores, dtype=np.float64)
            cs = cs.reshape(len(boxes), 0) if cs.size == 0 and cs.ndim != 2 else cs
            if cs.ndim != 2 or len(cs) != len(boxes):
                raise ValueError(f"Detections.class_scores: expected ({len(boxes)}, nc), got {cs.shape}")
            object.__setattr__(self, "class_scores", cs)

    def __len__(self) -> int:
        return len(self.scores)

    @classmethod
    def empty(cls) -> "Detections":
        return cls(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))

    def take(self, idx: np.ndarray) -> "Detections":
        return Detections(self.boxes_xyxy[idx], self.scores[idx], self.class_ids[idx],
                          None if self.class_scores is None else self.class_scores[idx])


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression.

    :param boxes_xyxy: (n, 4); :param scores: (n,).
    :return: (k,) int64 indices of kept boxes, highest score first.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")
    area = np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        xx1 = np.maximum(boxes[i, 0], boxes[rest, 0])
        yy1 = np.maximum(boxes[i, 1], boxes[rest, 1])
        xx2 = np.minimum(boxes[i, 2], boxes[rest, 2])
        yy2 = np.minimum(boxes[i, 3], boxes[rest, 3])
        inter = np.clip(xx2 - xx1, 0, None) * np.clip(yy2 - yy1, 0, None)
        union = area[i] + area[rest] - inter
        iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def decode_yolov8(output: np.ndarray, score_threshold: float, iou_threshold: float,
                  class_ids: tuple[int, ...] | None = None, max_detections: int = 100,
                  agnostic: bool = False) -> Detections:
    """Decode one image's YOLOv8 output and run NMS, class-aware (as ultralytics) or across classes.

    :param output: (4 + nc, A) or (1, 4 + nc, A): cx, cy, w, h in input pixels, then class scores.
    :param score_threshold: keep anchors whose best class score is above this (as ultralytics: 1.0 keeps nothing).
    :param iou_threshold: NMS IoU above which the lower-scoring box of the same class (of any kept class, with
        `agnostic`) is dropped.
    :param class_ids: classes to keep (None = all).
    :param max_detections: at most this many, highest score first.
    :param agnostic: NMS across classes: classes that are kinds of one object (pallet types) never give one
        object two boxes.
    :return: `Detections` in detector-input pixels, with every class's score.
    """
    out = np.asarray(output)
    if out.ndim == 3:
        if out.shape[0] != 1:
            raise ValueError(f"decode_yolov8 decodes one image, got batch {out.shape[0]}")
        out = out[0]
    if out.ndim != 2 or out.shape[0] < 5:
        raise ValueError(f"YOLOv8 output must be (4 + nc, anchors), got shape {out.shape}")
    cls_scores = out[4:]                                   # (nc, A)
    best = cls_scores.argmax(axis=0)
    score = cls_scores[best, np.arange(out.shape[1])]
    keep = score > score_threshold
    if class_ids is not None:
        keep &= np.isin(best, np.asarray(class_ids, dtype=np.int64))
    keep &= np.all(np.isfinite(out[:4]), axis=0)
    if not np.any(keep):
        return Detections.empty()
    cx, cy, w, h = (out[i, keep].astype(np.float64) for i in range(4))
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    score, best = score[keep].astype(np.float64), best[keep].astype(np.int64)
    # Class-aware NMS in one pass: shift each class's boxes to a disjoint region.
    offset = 0.0 if agnostic else best[:, None] * (np.abs(boxes).max() + 1.0)
    idx = nms(boxes + offset, score, iou_threshold)[:max_detections]
    return Detections(boxes[idx], score[idx], best[idx], cls_scores[:, keep][:, idx].T)


YOLOV8_STRIDES = (8, 16, 32)      # the anchor levels of YOLOv8's output (`export.detector.STRIDES`; no torch here)


def unmirror_yolov8(output: np.ndarray, input_hw: tuple[int, int], strides: tuple[int, ...] = YOLOV8_STRIDES
                    ) -> np.ndarray:
    """A YOLOv8 output for the left-right mirrored input, put back in the unmirrored input's frame: each anchor's
    row moved to the anchor it mirrors (columns reversed within each stride's grid, in YOLOv8's order: strides
    ascending, rows then columns) and cx mirrored (W - cx). Averaged with the output for the input itself, it gives
    the mirror-averaged prediction of every anchor.

    :param output: (1, 4 + nc, A) or (4 + nc, A). :param input_hw: the detector input (H, W) the output is for.
    :return: a new array of the same shape.
    :raises ValueError: A is not the anchor count of `strides` at `input_hw`.
    """
    out = np.array(output, dtype=np.float32, copy=True)
    flat = out.reshape(-1, *out.shape[-2:])
    H, W = (int(v) for v in input_hw)
    grids = [(H // s, W // s) for s in strides]
    if sum(h * w for h, w in grids) != flat.shape[-1]:
        raise ValueError(f"a mirrored detection needs the YOLOv8 anchor layout (strides {list(strides)} at "
                         f"{H}x{W}: {sum(h * w for h, w in grids)} anchors), the detector gave {flat.shape[-1]}")
    k = 0
    for h, w in grids:
        level = flat[:, :, k:k + h * w].reshape(flat.shape[0], flat.shape[1], h, w)
        flat[:, :, k:k + h * w] = level[..., ::-1].reshape(flat.shape[0], flat.shape[1], h * w).copy()
        k += h * w
    flat[:, 0] = W - flat[:, 0]
    return out


def undo_letterbox(boxes_xyxy: np.ndarray, lb: Letterbox, clip: bool = True) -> np.ndarray:
    """Map (n, 4) boxes from detector-input pixels back to image pixels (optionally clipped to the image)."""
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4).copy()
    boxes[:, [0, 2]] = (boxes[:, [0, 2]] - lb.pad_x) / lb.scale_x
    boxes[:, [1, 3]] = (boxes[:, [1, 3]] - lb.pad_y) / lb.scale_y
    if clip:
        h, w = lb.image_hw
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h)
    return boxes
