"""Preprocessing between the detector and the fusion/pose graphs, batched over the boxes of one frame.

The same function serves the runtime and training, so train and run cannot disagree. Per box:

1. clamp the box to the image (`geometry.clamp_box`); a box outside the image is not usable;
2. crop RGB and depth and resize both to `crop_hw` (the box is stretched; depth with nearest
   neighbour so no depth is invented between surfaces);
3. RGB: ``(rgb * pixel_scale - mean) / std`` per channel, (3, h, w);
   depth: ``clip(d - median, -clip_m, clip_m) / clip_m`` where d > 0 (median over the valid depth
   of the crop before resizing), 0 where there is no data, (1, h, w);
4. candidate pixels: valid depth in `depth_range_m` inside the box (and the mask when given)
   (`geometry.select_pixels`); sample N of them (`geometry.sample_indices`: without repetition
   when there are enough, oversampled otherwise); a box with no candidate has no valid depth and
   is flagged, not sent to the network;
5. back-project the samples (`geometry.backproject_pixels`) and centre them on their mean
   (`centres`); the pose graph's translation is an offset from each centred point, so the object's
   camera-frame translation from point i is ``centres + points[i] + trans[i]``;
6. `choose`: the flat index ``row * w + col`` of each sampled pixel in the resized crop, i.e. in the
   fusion graph's (h, w) feature map, for `gather_features`.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import geometry

__all__ = ["PoseInputSpec", "PoseBatch", "prepare_pose_inputs", "gather_features", "encode_depth"]


@dataclass(frozen=True)
class PoseInputSpec:
    """Everything the preprocessing needs, read from a bundle manifest (`Bundle.pose_input_spec()`).

    :ivar crop_hw: (h, w) of the fusion graph's input and output.
    :ivar rgb_mean, rgb_std: (3,) per-channel normalisation after `pixel_scale`.
    :ivar depth_clip_m: half-range of the depth encoding around the crop's median depth.
    :ivar num_points: N points per box.
    :ivar depth_range_m: (min, max) depth in metres for a pixel to become a point.
    """

    crop_hw: tuple[int, int]
    rgb_mean: tuple[float, float, float]
    rgb_std: tuple[float, float, float]
    depth_clip_m: float
    num_points: int
    depth_range_m: tuple[float, float] = (0.1, 10.0)
    pixel_scale: float = 1.0 / 255.0

    def __post_init__(self) -> None:
        h, w = (int(v) for v in self.crop_hw)
        if h <= 0 or w <= 0:
            raise ValueError(f"crop_hw must be positive, got {self.crop_hw}")
        if len(self.rgb_mean) != 3 or len(self.rgb_std) != 3 or min(self.rgb_std) <= 0:
            raise ValueError(f"rgb_mean/rgb_std must be 3 values with std > 0, got {self.rgb_mean}, {self.rgb_std}")
        if not self.depth_clip_m > 0:
            raise ValueError(f"depth_clip_m must be positive, got {self.depth_clip_m}")
        if int(self.num_points) <= 0:
            raise ValueError(f"num_points must be positive, got {self.num_points}")
        lo, hi = self.depth_range_m
        if not 0 <= lo < hi:
            raise ValueError(f"depth_range_m must be 0 <= min < max, got {self.depth_range_m}")
        object.__setattr__(self, "crop_hw", (h, w))
        object.__setattr__(self, "num_points", int(self.num_points))


@dataclass(frozen=True)
class PoseBatch:
    """Network inputs for B boxes of one frame (rows of unusable boxes are zeros).

    :ivar rgb_crops: (B, 3, h, w) float32. :ivar depth_crops: (B, 1, h, w) float32.
    :ivar points: (B, N, 3) float32 camera-frame points minus `centres`, metres.
    :ivar choose: (B, N) int64 flat pixel index into the (h, w) crop.
    :ivar centres: (B, 3) float64 camera-frame mean of the sampled points, metres.
    :ivar n_valid: (B,) int64 candidate pixels with valid depth (before sampling).
    :ivar boxes_xyxy: (B, 4) int64 clamped boxes, -1 where the box misses the image.
    :ivar box_in_image: (B,) bool. :ivar has_depth: (B,) bool: usable = has_depth (implies box_in_image).
    """

    rgb_crops: np.ndarray
    depth_crops: np.ndarray
    points: np.ndarray
    choose: np.ndarray
    centres: np.ndarray
    n_valid: np.ndarray
    boxes_xyxy: np.ndarray
    box_in_image: np.ndarray
    has_depth: np.ndarray

    def __post_init__(self) -> None:
        b = len(self.n_valid)
        n = self.points.shape[1] if self.points.ndim == 3 else -1
        h, w = self.rgb_crops.shape[2:] if self.rgb_crops.ndim == 4 else (-1, -1)
        expected = {
            "rgb_crops": ((b, 3, h, w), np.float32), "depth_crops": ((b, 1, h, w), np.float32),
            "points": ((b, n, 3), np.float32), "choose": ((b, n), np.int64), "centres": ((b, 3), np.float64),
            "n_valid": ((b,), np.int64), "boxes_xyxy": ((b, 4), np.int64), "box_in_image": ((b,), np.bool_),
            "has_depth": ((b,), np.bool_),
        }
        for name, (shape, dtype) in expected.items():
            arr = getattr(self, name)
            if arr.shape != shape or arr.dtype != dtype:
                raise ValueError(f"PoseBatch.{name}: expected {shape} {np.dtype(dtype)}, got {arr.shape} {arr.dtype}")

    def __len__(self) -> int:
        return len(self.n_valid)

    @property
    def usable(self) -> np.ndarray:
        """(B,) bool: boxes to send to the networks."""
        return self.has_depth

    def take(self, idx: np.ndarray) -> "PoseBatch":
        """The rows `idx` (e.g. `np.flatnonzero(batch.usable)`)."""
        return PoseBatch(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))


def encode_depth(depth_m: np.ndarray, clip_m: float) -> tuple[np.ndarray, float]:
    """Depth crop encoding: clip(d - median, +-clip_m) / clip_m where d > 0, 0 where there is no data.

    :param depth_m: (h, w) float metres, 0 = no data.
    :return: (h, w) float32 encoding and the median valid depth (0.0 when none is valid).
    """
    valid = depth_m > 0
    if not valid.any():
        return np.zeros(depth_m.shape, np.float32), 0.0
    med = float(np.median(depth_m[valid]))
    enc = np.clip((depth_m - med) / clip_m, -1.0, 1.0).astype(np.float32)
    enc[~valid] = 0.0
    return enc, med


def _check_frame(rgb: np.ndarray, depth_m: np.ndarray, boxes_xyxy, masks) -> tuple[np.ndarray, np.ndarray | None]:
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 array, got {getattr(rgb, 'shape', type(rgb))} "
                         f"{getattr(rgb, 'dtype', '')}")
    if not isinstance(depth_m, np.ndarray) or depth_m.shape != rgb.shape[:2] or \
            not np.issubdtype(depth_m.dtype, np.floating):
        raise ValueError(f"depth_m must be a float (H, W) array in metres matching rgb {rgb.shape[:2]}, got "
                         f"{getattr(depth_m, 'shape', type(depth_m))} {getattr(depth_m, 'dtype', '')}")
    boxes = np.asarray(boxes_xyxy, dtype=np.float64)
    if boxes.size == 0:
        boxes = boxes.reshape(0, 4)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes must be (B, 4) x1, y1, x2, y2, got shape {boxes.shape}")
    if masks is not None:
        masks = np.asarray(masks)
        if masks.shape != (len(boxes),) + depth_m.shape:
            raise ValueError(f"masks must be (B, H, W) = {(len(boxes),) + depth_m.shape}, got {masks.shape}")
        masks = masks.astype(bool)
    return boxes, masks


def prepare_pose_inputs(rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, boxes_xyxy, spec: PoseInputSpec,
                        rng, masks: np.ndarray | None = None, return_pixels: bool = False):
    """Crops, encodings, sampled centred points and feature-map indices for every box (module docstring).

    :param rgb: (H, W, 3) uint8 RGB.
    :param depth_m: (H, W) float metres, 0 = no data (NaN/inf/negative are treated as no data).
    :param K: (3, 3) intrinsics of the (registered) RGB-D pair.
    :param boxes_xyxy: (B, 4) boxes in image pixels (B may be 0).
    :param spec: the bundle's `PoseInputSpec`.
    :param rng: the generator for point sampling (seed it for reproducible results), or a sequence of B
        generators, one per box (a box's points then do not depend on the other boxes).
    :param masks: optional (B, H, W) bool object masks; points are then taken inside the mask only.
    :param return_pixels: also return, per box, the (v, u) int64 rows and columns of every candidate pixel
        (step 4, row-major; empty for an unusable box), so a caller need not select them again.
    :return: `PoseBatch`, or (`PoseBatch`, list of B (v, u) pairs) with `return_pixels`.
    """
    K = geometry.check_K(K)
    boxes, masks = _check_frame(rgb, depth_m, boxes_xyxy, masks)
    rngs = [rng] * len(boxes) if isinstance(rng, np.random.Generator) else \
        list(rng) if isinstance(rng, (list, tuple)) else []
    if len(rngs) != len(boxes) or not all(isinstance(r, np.random.Generator) for r in rngs):
        raise TypeError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)) or one per box "
                        f"({len(boxes)}), got {type(rng)}")
    # clean float32 depth (the estimator's, already validated) is only read; anything else becomes a float32 copy
    # with NaN/inf/negative -> 0 (NaN fails the min test)
    depth_m = np.asarray(depth_m)
    if depth_m.dtype != np.float32 or not (depth_m.size and float(depth_m.min()) >= 0
                                           and np.isfinite(float(depth_m.max()))):
        depth_m = geometry.depth_to_metres(depth_m)
    b, (h, w), n = len(boxes), spec.crop_hw, spec.num_points
    rgb_crops = np.zeros((b, 3, h, w), np.float32)
    depth_crops = np.zeros((b, 1, h, w), np.float32)
    points = np.zeros((b, n, 3), np.float32)
    choose = np.zeros((b, n), np.int64)
    centres = np.zeros((b, 3), np.float64)
    n_valid = np.zeros(b, np.int64)
    boxes_int = np.full((b, 4), -1, np.int64)
    in_image = np.zeros(b, bool)
    mean = np.asarray(spec.rgb_mean, np.float32).reshape(3, 1, 1)
    std = np.asarray(spec.rgb_std, np.float32).reshape(3, 1, 1)
    lo, hi = spec.depth_range_m
    empty = np.zeros(0, np.int64)
    pixels = [(empty, empty)] * b
    for i, box in enumerate(boxes):
        box_i = geometry.clamp_box(box, depth_m.shape)
        if box_i is None:
            continue
        in_image[i] = True
        boxes_int[i] = box_i
        x1, y1, x2, y2 = (int(c) for c in box_i)
        rgb_c = cv2.resize(geometry.crop(rgb, box_i), (w, h), interpolation=cv2.INTER_LINEAR)
        rgb_crops[i] = (rgb_c.transpose(2, 0, 1).astype(np.float32) * np.float32(spec.pixel_scale) - mean) / std
        d_c = cv2.resize(np.ascontiguousarray(geometry.crop(depth_m, box_i)), (w, h), interpolation=cv2.INTER_NEAREST)
        depth_crops[i, 0], _ = encode_depth(d_c, spec.depth_clip_m)
        v, u = geometry.select_pixels(depth_m, box_i, None if masks is None else masks[i], lo, hi)
        n_valid[i] = len(v)
        pixels[i] = (v, u)
        if len(v) == 0:
            continue
        idx = geometry.sample_indices(len(v), n, rngs[i])
        v, u = v[idx], u[idx]
        pts = geometry.backproject_pixels(u, v, depth_m[v, u], K).astype(np.float64)
        centres[i] = pts.mean(0)
        points[i] = (pts - centres[i]).astype(np.float32)
        # pixel centre (u + 0.5) in the box maps to (u - x1 + 0.5) * w / bw in the resized crop
        cu = np.clip(np.floor((u - x1 + 0.5) * w / (x2 - x1)), 0, w - 1).astype(np.int64)
        cv_ = np.clip(np.floor((v - y1 + 0.5) * h / (y2 - y1)), 0, h - 1).astype(np.int64)
        choose[i] = cv_ * w + cu
    batch = PoseBatch(rgb_crops, depth_crops, points, choose, centres, n_valid, boxes_int, in_image, n_valid > 0)
    return (batch, pixels) if return_pixels else batch


def gather_features(features: np.ndarray, choose: np.ndarray) -> np.ndarray:
    """Per-point features from the fusion graph's output.

    :param features: (B, C, h, w) feature maps.
    :param choose: (B, N) int flat indices into h * w.
    :return: (B, N, C) float32.
    """
    features = np.asarray(features)
    choose = np.asarray(choose)
    if features.ndim != 4 or choose.ndim != 2 or choose.shape[0] != features.shape[0]:
        raise ValueError(f"gather_features: expected features (B, C, h, w) and choose (B, N), got "
                         f"{features.shape} and {choose.shape}")
    b, c, h, w = features.shape
    if choose.size and (choose.min() < 0 or choose.max() >= h * w):
        raise ValueError(f"gather_features: choose indices must be in [0, {h * w}), got [{choose.min()}, {choose.max()}]")
    flat = features.reshape(b, c, h * w)
    out = np.take_along_axis(flat, choose[:, None, :].astype(np.int64), axis=2)   # (B, C, N)
    return np.ascontiguousarray(out.transpose(0, 2, 1), dtype=np.float32)
