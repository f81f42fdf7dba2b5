"""Training data: BOP datasets -> detector samples and pose samples, with domain randomisation and caching.

Pose samples go through the runtime's own `prepare_pose_inputs` (crop, depth encoding, mask-free pixel
selection, sampling, back-projection, centring), fed with ground-truth visible boxes jittered like a
detector's boxes, so training sees exactly what the forklift will see. Each pallet is prepared `variants`
times (different augmentation, box jitter and point sampling) and the result cached in one `.npz` per
dataset + config, keyed by a fingerprint of the data and of every preprocessing setting; epochs then only
read arrays, which keeps CPU training cheap.

Targets: the network predicts, per centred point p_i, a rotation and an offset; the runtime's pose is
``t = centre + p_i + trans_i``. The loss therefore compares against the ground truth expressed in the
centred frame: ``T_gt_centred = T_cam_pallet`` with ``centre`` subtracted from its translation.

Detector samples are the source frames (cached as uint8, longest side capped, boxes in frame pixels); each
training batch draws one of the detector's input sizes and places every frame in it with a random zoom and
position (`place_in_window`; or four frames to an input, `place_mosaic`), then flips, HSV jitter, blur and noise.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.detector import letterbox
from pallet6d.runtime.evaluation import MIN_VISIB_FRACT, counted_pallets
from pallet6d.runtime.pose_inputs import PoseInputSpec, prepare_pose_inputs

__all__ = ["AugmentConfig", "PoseSamples", "DetectorSamples", "dataset_fingerprint", "jitter_box",
           "augment_rgb", "augment_depth", "flip_horizontal", "place_in_window", "place_mosaic", "build_pose_samples",
           "build_detector_samples", "repeated_roots", "repeat_train",
           "load_or_build", "model_points_for", "pallet_type_name", "MIN_VISIB_FRACT", "CACHE_VERSION"]

log = logging.getLogger(__name__)

CACHE_VERSION = 3         # bump when the cached arrays' meaning changes


@dataclass(frozen=True)
class AugmentConfig:
    """Domain randomisation strengths (0 disables a term).

    :ivar box_scale_sigma: relative std of box width/height jitter (detector-like boxes).
    :ivar box_shift_sigma: std of box centre shift, as a fraction of the box size.
    :ivar hsv_gain: (hue, saturation, value) max relative gains (YOLOv8: 0.015, 0.7, 0.4).
    :ivar blur_prob: probability of a Gaussian blur. :ivar rgb_noise_sigma: max Gaussian noise std in [0, 255].
    :ivar depth_dropout_prob: probability of dropping random rectangles of depth (stereo holes).
    :ivar depth_noise_sigma_m: depth noise std at 1 m; grows with z^2 like stereo depth.
    :ivar flip_prob: probability of a horizontal flip (detector only: the pose stage needs true geometry).
    :ivar zoom_range, zoom_in_max: detector only: the frame is drawn at its letterbox scale times a factor
        log-uniform in [1 - zoom_range, zoom_in_max] (YOLOv8's `scale`): zooming out shows far, small pallets more
        often than the sim's camera paths do; zooming in shows the pallets of far-away photographs at the size a
        forklift sees them from a few metres.
    :ivar shift_fraction: detector only: the zoomed frame lands anywhere its slack in the input allows (or is cut
        anywhere, when larger), plus up to this fraction of the input size beyond.
    """

    box_scale_sigma: float = 0.08
    box_shift_sigma: float = 0.05
    hsv_gain: tuple[float, float, float] = (0.015, 0.5, 0.4)
    blur_prob: float = 0.2
    rgb_noise_sigma: float = 6.0
    depth_dropout_prob: float = 0.5
    depth_noise_sigma_m: float = 0.004
    flip_prob: float = 0.5
    zoom_range: float = 0.4
    shift_fraction: float = 0.1
    zoom_in_max: float = 2.0

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


NO_AUGMENT = AugmentConfig(0.0, 0.0, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


# --------------------------------------------------------------------------------------- fingerprints


def dataset_fingerprint(root: str | Path) -> dict:
    """What a dataset is, for provenance and cache keys: path, frame count, sim presets/seeds if recorded,
    and a sha256 over its annotation files (scene_gt / scene_camera / scene_gt_info).

    :raises ValueError: not a BOP dataset.
    """
    root = Path(root)
    ds = BopDataset(root)
    h = hashlib.sha256()
    for f in sorted((root / ds.split).glob("*/scene_*.json")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    sims = []
    for f in sorted((root / ds.split).glob("sim_config_*.json")):
        try:
            meta = json.loads(f.read_text())
            sims.append({"preset": meta.get("config", {}).get("name"), "seed": meta.get("seed"),
                         "start": meta.get("start"), "frames": meta.get("frames"),
                         "size": [meta.get("config", {}).get("width"), meta.get("config", {}).get("height")]})
        except (OSError, ValueError, AttributeError):
            log.warning("%s: unreadable sim config, not recorded", f)
    return {"path": str(root.resolve()), "split": ds.split, "frames": len(ds), "sim": sims,
            "annotations_sha256": h.hexdigest()}


def repeated_roots(data: Sequence[str | Path]) -> tuple[list[str | Path], np.ndarray]:
    """Each dataset of `data` once, in the order first named, and how many times it is named: a dataset named k
    times is loaded and validated once and trained k times (`repeat_train`), so that none of its frames is both
    trained on and held out."""
    roots: list[str | Path] = []
    counts: dict[Path, int] = {}
    for root in data:
        key = Path(root).resolve()
        if key not in counts:
            roots.append(root)
            counts[key] = 0
        counts[key] += 1
    return roots, np.array([counts[Path(r).resolve()] for r in roots], np.int64)


def repeat_train(train_idx: np.ndarray, sample_root: np.ndarray, repeats: np.ndarray) -> np.ndarray:
    """`train_idx` with each sample as many times as its dataset is named (`repeated_roots`).
    :param sample_root: (n_samples,) each sample's index into the unique roots."""
    train_idx = np.asarray(train_idx, np.int64)
    return np.repeat(train_idx, repeats[sample_root[train_idx]])


def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------- augmentation


def jitter_box(box_xyxy: np.ndarray, rng: np.random.Generator, scale_sigma: float, shift_sigma: float) -> np.ndarray:
    """A detector-like box: scale and shift noise relative to the box size.

    :param box_xyxy: (4,) pixels. :return: (4,) float64 pixels (not clamped; the pose inputs clamp).
    """
    x1, y1, x2, y2 = (float(v) for v in box_xyxy)
    w, h = x2 - x1, y2 - y1
    cx = (x1 + x2) / 2 + rng.normal(0.0, shift_sigma) * w
    cy = (y1 + y2) / 2 + rng.normal(0.0, shift_sigma) * h
    w *= float(np.clip(1.0 + rng.normal(0.0, scale_sigma), 0.7, 1.4))
    h *= float(np.clip(1.0 + rng.normal(0.0, scale_sigma), 0.7, 1.4))
    return np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])


def augment_rgb(rgb: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """HSV gains, optional blur, Gaussian noise. :param rgb: (H, W, 3) uint8 RGB. :return: a new uint8 image."""
    out = rgb
    hg, sg, vg = aug.hsv_gain
    if hg or sg or vg:
        gains = 1.0 + rng.uniform(-1, 1, 3) * np.array([hg, sg, vg])
        hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(np.float32)
        hsv[..., 0] = (hsv[..., 0] * gains[0]) % 180.0
        hsv[..., 1:] *= gains[1:]
        out = cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2RGB)
    if aug.blur_prob and rng.random() < aug.blur_prob:
        k = int(rng.choice([3, 5]))
        out = cv2.GaussianBlur(out, (k, k), 0)
    if aug.rgb_noise_sigma:
        sigma = rng.uniform(0.0, aug.rgb_noise_sigma)
        out = np.clip(out.astype(np.float32) + rng.normal(0.0, sigma, out.shape), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(out)


def augment_depth(depth_m: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """Stereo-like depth noise (std grows with z^2) and dropped rectangles.

    :param depth_m: (H, W) float metres, 0 = no data. :return: a new float32 array, 0 stays 0.
    """
    d = depth_m.astype(np.float32, copy=True)
    valid = d > 0
    if aug.depth_noise_sigma_m:
        d[valid] += (rng.normal(0.0, 1.0, int(valid.sum())) * aug.depth_noise_sigma_m * d[valid] ** 2).astype(np.float32)
        d[valid & (d <= 0)] = 0.0
    if aug.depth_dropout_prob and rng.random() < aug.depth_dropout_prob:
        h, w = d.shape
        for _ in range(int(rng.integers(1, 6))):
            rh, rw = int(rng.integers(2, max(3, h // 6))), int(rng.integers(2, max(3, w // 10)))
            y, x = int(rng.integers(0, max(1, h - rh))), int(rng.integers(0, max(1, w - rw)))
            d[y:y + rh, x:x + rw] = 0.0
    return d


def _box_rows(boxes_xyxy: np.ndarray) -> np.ndarray:
    """(n, 4 + k) float32 rows of xyxy boxes (a flat or empty input becomes (n, 4))."""
    boxes = np.asarray(boxes_xyxy, dtype=np.float32)
    if boxes.ndim != 2 or boxes.shape[1] < 4:
        boxes = boxes.reshape(-1, 4)
    return boxes


def flip_horizontal(image: np.ndarray, boxes_xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror an image left-right and its boxes with it.

    :param image: (H, W, 3). :param boxes_xyxy: (n, 4 + k) pixels; columns after the fourth (a class) ride along.
    :return: the flipped image and (n, 4 + k) boxes, still x1 < x2.
    """
    w = image.shape[1]
    boxes = _box_rows(boxes_xyxy).copy()
    boxes[:, [0, 2]] = w - boxes[:, [2, 0]]
    return np.ascontiguousarray(image[:, ::-1]), boxes


def _window_affine(image_hw: tuple[int, int], window_hw: tuple[int, int], rng: np.random.Generator,
                   zoom_range: float, zoom_in_max: float, shift_fraction: float) -> tuple[float, float, float]:
    """`place_in_window`'s random scale and offset (s, tx, ty): window = frame * s + (tx, ty)."""
    h, w = image_hw
    H, W = window_hw
    lo, hi = math.log(max(1.0 - zoom_range, 1e-3)), math.log(max(zoom_in_max, 1e-3))
    s = min(H / h, W / w) * (math.exp(rng.uniform(lo, hi)) if hi > lo else 1.0)
    new_w, new_h = w * s, h * s
    tx = (W - new_w) / 2 + float(rng.uniform(-1.0, 1.0)) * (abs(W - new_w) / 2 + shift_fraction * W) \
        if shift_fraction > 0 else (W - new_w) / 2
    ty = (H - new_h) / 2 + float(rng.uniform(-1.0, 1.0)) * (abs(H - new_h) / 2 + shift_fraction * H) \
        if shift_fraction > 0 else (H - new_h) / 2
    return s, tx, ty


def _moved_boxes(boxes: np.ndarray, s: float, tx: float, ty: float, window_hw: tuple[int, int],
                 min_area_kept: float, min_side_px: float) -> np.ndarray:
    H, W = window_hw
    moved = boxes.copy()
    moved[:, :4] = boxes[:, :4] * np.float32(s) + np.array([tx, ty, tx, ty], np.float32)
    clipped = moved.copy()
    clipped[:, [0, 2]] = np.clip(moved[:, [0, 2]], 0, W)
    clipped[:, [1, 3]] = np.clip(moved[:, [1, 3]], 0, H)
    side_w, side_h = clipped[:, 2] - clipped[:, 0], clipped[:, 3] - clipped[:, 1]
    area_moved = np.maximum((moved[:, 2] - moved[:, 0]) * (moved[:, 3] - moved[:, 1]), 1e-9)
    keep = (side_w >= min_side_px) & (side_h >= min_side_px) & (side_w * side_h >= min_area_kept * area_moved)
    return clipped[keep].astype(np.float32)


def place_in_window(image: np.ndarray, boxes_xyxy: np.ndarray, window_hw: tuple[int, int], rng: np.random.Generator,
                    zoom_range: float, zoom_in_max: float, shift_fraction: float, fill: int = 114,
                    min_area_kept: float = 0.2, min_side_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Draw a frame into a detector input of `window_hw`: at its letterbox scale times a random zoom
    (log-uniform in [1 - zoom_range, zoom_in_max]), at a random position (see `AugmentConfig.shift_fraction`),
    the uncovered area filled with `fill` (the letterbox grey), the boxes moved with it. Without zoom and shift
    it is the letterbox.

    Boxes are clipped to the window; one keeps when at least `min_area_kept` of its area stays inside and both
    sides stay `min_side_px` or longer (a pallet cut by the image border is still a pallet).

    :param image: (h, w, 3) uint8. :param boxes_xyxy: (n, 4 + k) frame pixels; columns after the fourth (a class)
        ride along. :param window_hw: (H, W).
    :return: the (H, W, 3) uint8 input and (m, 4 + k) float32 boxes in its pixels.
    """
    img, _, boxes = place_rgbd_in_window(image, None, boxes_xyxy, window_hw, rng, zoom_range, zoom_in_max,
                                         shift_fraction, fill, min_area_kept, min_side_px)
    return img, boxes


def place_rgbd_in_window(image: np.ndarray, depth_m: np.ndarray | None, boxes_xyxy: np.ndarray,
                         window_hw: tuple[int, int], rng: np.random.Generator, zoom_range: float, zoom_in_max: float,
                         shift_fraction: float, fill: int = 114, min_area_kept: float = 0.2,
                         min_side_px: float = 2.0) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """`place_in_window` for a colour image and its registered depth: the same zoom and position for both, the
    depth drawn with nearest neighbour (no depth invented at edges) and 0 (no data) where the frame does not reach.

    :param depth_m: (h, w) float metres, or None. :return: the (H, W, 3) uint8 input, the (H, W) float32 depth (None
        without one) and (m, 4 + k) float32 boxes.
    """
    H, W = int(window_hw[0]), int(window_hw[1])
    s, tx, ty = _window_affine(image.shape[:2], (H, W), rng, zoom_range, zoom_in_max, shift_fraction)
    out, depth_out = _draw(image, depth_m, s, tx, ty, (H, W), fill)
    boxes = _moved_boxes(_box_rows(boxes_xyxy), s, tx, ty, (H, W), min_area_kept, min_side_px)
    return np.ascontiguousarray(out), depth_out, boxes


def _draw(image: np.ndarray, depth_m: np.ndarray | None, s: float, tx: float, ty: float, out_hw: tuple[int, int],
          fill: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The frame scaled by `s` and moved by (tx, ty) into an (H, W) output: colour bilinear with `fill` beyond the
    frame, depth nearest neighbour (no depth invented at edges) with 0 (no data) beyond it."""
    if depth_m is not None and depth_m.shape != image.shape[:2]:
        raise ValueError(f"depth is {depth_m.shape}, the image {image.shape[:2]}")
    A = np.array([[s, 0.0, tx], [0.0, s, ty]], dtype=np.float64)
    size = (int(out_hw[1]), int(out_hw[0]))
    out = cv2.warpAffine(image, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=(fill, fill, fill))
    if depth_m is None:
        return out, None
    return out, cv2.warpAffine(depth_m.astype(np.float32, copy=False), A, size, flags=cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def place_mosaic(frames: Sequence[tuple[np.ndarray, np.ndarray | None, np.ndarray]], window_hw: tuple[int, int],
                 rng: np.random.Generator, zoom_range: float, zoom_in_max: float, shift_fraction: float,
                 fill: int = 114, min_area_kept: float = 0.2, min_side_px: float = 2.0
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """YOLOv8's mosaic: four frames share one detector input, split into quarters at a random point (the middle
    half of each side). Each frame is drawn as `place_rgbd_in_window` draws a frame alone (the same zoom and
    position, so its pallets keep the sizes they would have) and the part of it that falls in its quarter is shown.
    One input then holds four scenes' backgrounds and lights, and pallets cut at the quarters' borders.

    Boxes are clipped to their quarter and kept as `place_in_window` keeps them (at least `min_area_kept` of the
    box as drawn inside, both sides `min_side_px` or longer).

    :param frames: four (image (h, w, 3) uint8, depth (h, w) float metres or None, boxes (n, 4 + k) frame pixels);
        the depth of all four or of none.
    :return: the (H, W, 3) uint8 input, its (H, W) float32 depth (None without), (m, 4 + k) float32 boxes.
    """
    if len(frames) != 4:
        raise ValueError(f"a mosaic takes 4 frames, got {len(frames)}")
    with_depth = [d is not None for _, d, _ in frames]
    if any(with_depth) and not all(with_depth):
        raise ValueError("a mosaic takes the depth of all four frames or of none")
    H, W = int(window_hw[0]), int(window_hw[1])
    cx, cy = int(round(rng.uniform(0.25, 0.75) * W)), int(round(rng.uniform(0.25, 0.75) * H))
    quarters = [(0, 0, cx, cy), (cx, 0, W, cy), (0, cy, cx, H), (cx, cy, W, H)]    # x1, y1, x2, y2
    out = np.full((H, W, 3), fill, np.uint8)
    depth_out = np.zeros((H, W), np.float32) if all(with_depth) else None
    kept = []
    for (image, depth_m, boxes), (x1, y1, x2, y2) in zip(frames, quarters):
        s, tx, ty = _window_affine(image.shape[:2], (H, W), rng, zoom_range, zoom_in_max, shift_fraction)
        if x2 <= x1 or y2 <= y1:
            continue
        # the frame as drawn into the whole window, shifted so that only its quarter is drawn
        tile, tile_depth = _draw(image, depth_m, s, tx - x1, ty - y1, (y2 - y1, x2 - x1), fill)
        out[y1:y2, x1:x2] = tile
        if depth_out is not None:
            depth_out[y1:y2, x1:x2] = tile_depth
        b = _moved_boxes(_box_rows(boxes), s, tx - x1, ty - y1, (y2 - y1, x2 - x1), min_area_kept, min_side_px)
        b[:, [0, 2]] += x1
        b[:, [1, 3]] += y1
        kept.append(b)
    cols = _box_rows(frames[0][2]).shape[1]
    boxes_out = np.concatenate(kept) if kept else np.zeros((0, cols), np.float32)
    return out, depth_out, boxes_out.astype(np.float32)


# ------------------------------------------------------------------------------------------- models


def pallet_type_name(ds: BopDataset, obj_id: int, fallback: str) -> str:
    """The pallet type (`sim.pallets` model name) of a dataset's object: the name the sim writes into
    models_info.json; `fallback` for other datasets."""
    from pallet6d.sim.pallets import PALLET_MODELS

    name = ds.models_info.get(int(obj_id), {}).get("name")
    if name not in PALLET_MODELS:
        log.warning("%s: obj_id %s has no known pallet name; using the %r model", ds.root, obj_id, fallback)
        return fallback
    return name


def model_points_for(ds: BopDataset, obj_id: int, n: int, fallback: str) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) float32 pallet-frame surface points (metres) and (S, 4, 4) symmetries of a dataset's object
    (its type: `pallet_type_name`)."""
    from pallet6d.sim.pallets import get_pallet_model

    model = get_pallet_model(pallet_type_name(ds, obj_id, fallback))
    return model.surface_points(n, seed=0).astype(np.float32), np.array(model.symmetries, np.float64)


# --------------------------------------------------------------------------------------- pose samples


@dataclass(frozen=True)
class PoseSamples:
    """P prepared pallet crops (one per pallet per variant).

    :ivar rgb_crops: (P, 3, h, w) float32. :ivar depth_crops: (P, 1, h, w) float32.
    :ivar points: (P, N, 3) float32 centred camera-frame points, metres. :ivar choose: (P, N) int64.
    :ivar T_gt: (P, 4, 4) float32 ground truth in the centred camera frame (translation minus centre).
    :ivar obj_id: (P,) int64. :ivar frame: (P,) int64 frame index in its dataset (for splits).
    :ivar variant: (P,) int64 augmentation variant. :ivar distance_m: (P,) float32 GT distance.
    """

    rgb_crops: np.ndarray
    depth_crops: np.ndarray
    points: np.ndarray
    choose: np.ndarray
    T_gt: np.ndarray
    obj_id: np.ndarray
    frame: np.ndarray
    variant: np.ndarray
    distance_m: np.ndarray

    def __post_init__(self) -> None:
        p = len(self.obj_id)
        n = self.points.shape[1] if self.points.ndim == 3 else -1
        for name, shape in (("rgb_crops", (p, 3)), ("depth_crops", (p, 1)), ("points", (p, n, 3)),
                            ("choose", (p, n)), ("T_gt", (p, 4, 4)), ("frame", (p,)), ("variant", (p,)),
                            ("distance_m", (p,))):
            arr = getattr(self, name)
            if arr.shape[:len(shape)] != shape:
                raise ValueError(f"PoseSamples.{name}: expected leading shape {shape}, got {arr.shape}")

    def __len__(self) -> int:
        return len(self.obj_id)

    def take(self, idx: np.ndarray) -> "PoseSamples":
        return PoseSamples(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    @staticmethod
    def concat(parts: Sequence["PoseSamples"]) -> "PoseSamples":
        if not parts:
            raise ValueError("no pose samples to concatenate")
        return PoseSamples(*(np.concatenate([getattr(p, f) for p in parts]) for f in PoseSamples.__dataclass_fields__))


def build_pose_samples(root: str | Path, spec: PoseInputSpec, variants: int, seed: int, aug: AugmentConfig,
                       min_points: int = 50, max_frames: int | None = None,
                       progress: Callable[[int], None] | None = None) -> PoseSamples:
    """Prepare every usable pallet (visible >= 10 %, >= `min_points` valid depth pixels) `variants` times.

    Variant v of frame i uses `np.random.default_rng((seed, i, v))`: reproducible frame by frame.
    :raises ValueError: no usable pallet in the dataset.
    """
    if variants < 1:
        raise ValueError(f"variants must be >= 1, got {variants}")
    ds = BopDataset(root)
    n_frames = len(ds) if max_frames is None else min(len(ds), max_frames)
    rows: list[tuple] = []
    for i in range(n_frames):
        f = ds[i]
        # training's own rule: a crop at least 2 x 2 pixels, and no pallet of unknown visibility (it may be hidden)
        counted = counted_pallets(f.gts, min_box_side_px=2, unknown_visib_counts=False)
        gts = [g for g, c in zip(f.gts, counted) if c]
        for v in range(variants):
            if not gts:
                break
            rng = np.random.default_rng((seed, i, v))
            augment = v > 0 or variants == 1   # variant 0 is the clean view when there are several
            rgb = augment_rgb(f.rgb, rng, aug) if augment else f.rgb
            depth = augment_depth(f.depth_m, rng, aug) if augment else f.depth_m
            boxes = []
            for g in gts:
                x, y, w, h = (float(c) for c in g.bbox_visib_xywh)
                box = np.array([x, y, x + w, y + h])
                boxes.append(jitter_box(box, rng, aug.box_scale_sigma, aug.box_shift_sigma) if augment else box)
            batch = prepare_pose_inputs(rgb, depth, f.K, np.array(boxes), spec, rng)
            for k, g in enumerate(gts):
                if batch.n_valid[k] < min_points:
                    continue
                T = g.T_cam_model.copy()
                T[:3, 3] -= batch.centres[k]
                rows.append((batch.rgb_crops[k], batch.depth_crops[k], batch.points[k], batch.choose[k],
                             T.astype(np.float32), g.obj_id, i, v, np.linalg.norm(g.T_cam_model[:3, 3])))
        if progress is not None:
            progress(1)
    if not rows:
        raise ValueError(f"{root}: no usable pallet (visible >= {MIN_VISIB_FRACT:.0%} with >= {min_points} valid "
                         "depth pixels) in its frames; check the dataset's scene_gt_info.json and depth images")
    cols = list(zip(*rows))
    return PoseSamples(np.stack(cols[0]), np.stack(cols[1]), np.stack(cols[2]), np.stack(cols[3]), np.stack(cols[4]),
                       np.asarray(cols[5], np.int64), np.asarray(cols[6], np.int64), np.asarray(cols[7], np.int64),
                       np.asarray(cols[8], np.float32))


# ----------------------------------------------------------------------------------- detector samples


@dataclass
class DetectorSamples:
    """F source frames of any sizes.

    :ivar images: (F,) object array of (h_i, w_i, 3) uint8 RGB frames (or one (F, H, W, 3) array).
    :ivar boxes: (F,) object array of (n_i, 4) float32 xyxy boxes in frame pixels.
    :ivar frame: (F,) int64 frame index in its dataset.
    :ivar types: (F,) object array of (n_i,) int64: each box's pallet type as its index in
        `sim.pallets.PALLET_MODELS`, -1 when unknown (a real photograph); default all -1.
    :ivar depths: None, or (F,) object array of (h_i, w_i) uint16 millimetres registered to the images, a (0, 0)
        array for a frame without depth (a photograph); 0 = no data.
    """

    images: np.ndarray
    boxes: np.ndarray
    frame: np.ndarray
    types: np.ndarray | None = None
    depths: np.ndarray | None = None

    def __post_init__(self) -> None:
        f = len(self.frame)
        if len(self.images) != f or len(self.boxes) != f:
            raise ValueError(f"DetectorSamples: expected images (F,), boxes (F,), frame (F,), got "
                             f"{len(self.images)}, {len(self.boxes)}, {f}")
        if self.types is None:
            self.types = _objects([np.full(len(np.reshape(b, (-1, 4))), -1, np.int64) for b in self.boxes])
        if len(self.types) != f or any(len(t) != len(np.reshape(b, (-1, 4))) for t, b in zip(self.types, self.boxes)):
            raise ValueError("DetectorSamples: types must give one pallet type per box of every frame")
        for img in self.images:
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise ValueError(f"DetectorSamples: each image must be (h, w, 3) uint8, got {img.shape} {img.dtype}")
        if self.depths is not None:
            if len(self.depths) != f:
                raise ValueError(f"DetectorSamples: {f} frames but {len(self.depths)} depths")
            for img, d in zip(self.images, self.depths):
                if d.dtype != np.uint16 or (d.shape != img.shape[:2] and d.shape != (0, 0)):
                    raise ValueError(f"DetectorSamples: each depth must be (h, w) uint16 like its image "
                                     f"{img.shape[:2]} or (0, 0) for none, got {d.shape} {d.dtype}")

    def depth_m(self, i: int) -> np.ndarray | None:
        """Frame `i`'s depth in float32 metres, or None when it has none."""
        if self.depths is None or self.depths[i].size == 0:
            return None
        return self.depths[i].astype(np.float32) * np.float32(0.001)

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, idx: np.ndarray) -> "DetectorSamples":
        depths = None if self.depths is None else _objects([self.depths[i] for i in idx])
        return DetectorSamples(_objects([self.images[i] for i in idx]), self.boxes[idx], self.frame[idx],
                               self.types[idx], depths)

    @staticmethod
    def concat(parts: Sequence["DetectorSamples"]) -> "DetectorSamples":
        """The frames of `parts` in order; when any part has depth, the others' frames get "none" (0, 0)."""
        if not parts:
            raise ValueError("no detector samples to concatenate")
        depths = None
        if any(p.depths is not None for p in parts):
            none = np.zeros((0, 0), np.uint16)
            depths = _objects([d for p in parts for d in (p.depths if p.depths is not None else [none] * len(p))])
        return DetectorSamples(_objects([im for p in parts for im in p.images]),
                               _objects([b for p in parts for b in p.boxes]),
                               np.concatenate([p.frame for p in parts]),
                               _objects([t for p in parts for t in p.types]), depths)


def _objects(items: Sequence[np.ndarray]) -> np.ndarray:
    """A (len,) object array holding the arrays one by one (a list of equal-shape arrays would become one block)."""
    out = np.empty(len(items), dtype=object)
    for i, a in enumerate(items):
        out[i] = a
    return out


def cap_image(rgb: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """The image scaled down so that its longer side is at most `max_side` (unchanged when it already is), and
    the scale applied."""
    h, w = rgb.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s == 1.0:
        return np.ascontiguousarray(rgb), 1.0
    size = (max(1, int(round(w * s))), max(1, int(round(h * s))))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), s


def build_detector_samples(root: str | Path, max_side: int, max_frames: int | None = None,
                           progress: Callable[[int], None] | None = None, depth: bool = False) -> DetectorSamples:
    """Every frame, longest side capped at `max_side`; boxes = visible boxes of pallets visible >= 10 %, with
    their pallet types (-1 for an object the dataset does not name as a catalogue type); with `depth`, each
    frame's depth too (uint16 mm, resized with the image by nearest neighbour)."""
    from pallet6d.sim.pallets import PALLET_MODELS

    ds = BopDataset(root)
    n_frames = len(ds) if max_frames is None else min(len(ds), max_frames)
    type_of = {int(k): PALLET_MODELS.index(v["name"]) if v.get("name") in PALLET_MODELS else -1
               for k, v in ds.models_info.items()}
    images, boxes, types, depths = [], [], [], []
    for i in range(n_frames):
        f = ds[i]
        img, scale = cap_image(f.rgb, max_side)
        images.append(img)
        if depth:
            mm = np.clip(np.round(np.nan_to_num(f.depth_m) * 1000.0), 0, 65535).astype(np.uint16)
            if mm.shape != img.shape[:2]:
                mm = cv2.resize(mm, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
            depths.append(mm)
        # training's own rule: a target box of at least one pixel each way, no pallet of unknown visibility
        counted = counted_pallets(f.gts, min_box_side_px=1, unknown_visib_counts=False)
        bs = [g.bbox_visib_xywh.astype(np.float64) for g, c in zip(f.gts, counted) if c]
        b = np.array([[x, y, x + w, y + h] for x, y, w, h in bs], np.float64).reshape(-1, 4)
        boxes.append((b * scale).astype(np.float32))
        types.append(np.array([type_of.get(int(g.obj_id), -1) for g, c in zip(f.gts, counted) if c], np.int64))
        if progress is not None:
            progress(1)
    return DetectorSamples(_objects(images), _objects(boxes), np.arange(n_frames, dtype=np.int64),
                           _objects(types), _objects(depths) if depth else None)


# --------------------------------------------------------------------------------------------- cache


def _ragged(arrays: Sequence[np.ndarray], tail: tuple[int, ...], dtype) -> tuple[np.ndarray, np.ndarray]:
    """One flat array of `arrays` (each (n_i, *tail) after reshaping) and their (F, ndim) shapes."""
    flat = [np.asarray(a, dtype).reshape(-1, *tail) for a in arrays]
    shapes = np.array([np.shape(a) for a in arrays], np.int64).reshape(len(arrays), -1)
    return (np.concatenate(flat) if flat else np.zeros((0, *tail), dtype)), shapes


def _unragged(flat: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """The (F,) object array `_ragged` flattened."""
    counts = np.prod(shapes, axis=1) // int(np.prod(flat.shape[1:]))
    if counts.sum() != len(flat):
        raise ValueError(f"cached arrays {flat.shape} disagree with their shapes (sum {counts.sum()})")
    parts = np.split(flat, np.cumsum(counts)[:-1]) if len(counts) else []
    return _objects([p.reshape(tuple(sh)) for p, sh in zip(parts, shapes)])


def _to_cache(samples: PoseSamples | DetectorSamples) -> dict[str, np.ndarray]:
    """Plain numeric arrays (no object arrays, so the cache loads without pickle): a detector's ragged
    per-frame images and boxes become flat arrays and their shapes."""
    arrays = {f: getattr(samples, f) for f in type(samples).__dataclass_fields__}
    if isinstance(samples, DetectorSamples):
        arrays["images"], arrays["images_shape"] = _ragged(samples.images, (3,), np.uint8)
        boxes = [np.asarray(b, np.float32).reshape(-1, 4) for b in samples.boxes]
        arrays["boxes"], arrays["boxes_shape"] = _ragged(boxes, (4,), np.float32)
        arrays["types"], arrays["types_shape"] = _ragged(samples.types, (), np.int64)
        if samples.depths is None:
            del arrays["depths"]
        else:
            arrays["depths"], arrays["depths_shape"] = _ragged(samples.depths, (), np.uint16)
    return arrays


def _from_cache(cls: type, z) -> PoseSamples | DetectorSamples:
    """The samples `_to_cache` stored; a cache written without one of `cls`'s fields is refused."""
    optional = {"depths"} if cls is DetectorSamples else set()
    missing = sorted(set(cls.__dataclass_fields__) - set(z.files) - optional)
    if missing:
        raise ValueError(f"cache lacks {missing}: it was written by an older version; rebuild it")
    fields = {f: z[f] for f in cls.__dataclass_fields__ if f in z.files}
    if cls is DetectorSamples:
        fields["images"] = _unragged(fields["images"], z["images_shape"])
        fields["boxes"] = _unragged(fields["boxes"], z["boxes_shape"])
        fields["types"] = _unragged(fields["types"], z["types_shape"])
        if "depths" in fields:
            fields["depths"] = _unragged(fields["depths"], z["depths_shape"])
    return cls(**fields)


def load_or_build(kind: str, root: str | Path, settings: dict, cache_dir: str | Path | None,
                  build: Callable[[], PoseSamples | DetectorSamples]):
    """Read `cache_dir/<kind>_<dataset>_<key>.npz` when its key matches the dataset fingerprint and
    `settings`; otherwise build the samples and write the cache. `cache_dir=None` disables caching.

    :return: (samples, fingerprint dict of the dataset).
    """
    fp = dataset_fingerprint(root)
    key = _key(CACHE_VERSION, kind, fp, settings)
    cls = PoseSamples if kind == "pose" else DetectorSamples
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{kind}_{Path(root).resolve().name}_{key}.npz"
        if path.exists():
            try:
                with np.load(path, allow_pickle=False) as z:
                    if str(z["_key"]) == key:
                        log.info("cache hit: %s", path)
                        return _from_cache(cls, z), fp
            except (OSError, KeyError, ValueError) as exc:
                log.warning("ignoring unreadable cache %s: %s", path, exc)
    samples = build()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, _key=np.array(key), **_to_cache(samples))
        tmp.replace(path)
        log.info("cached %d %s samples in %s", len(samples), kind, path)
    return samples, fp
