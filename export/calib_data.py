"""Representative network inputs for int8 calibration and parity checks.

Preferred source: frames from the synthetic warehouse generator (`pallet6d.sim`), run through the
runtime's own preprocessing (`runtime.detector.letterbox`, `runtime.pose_inputs.prepare_pose_inputs`)
with the ground-truth visible boxes (jittered like detector boxes). Fallback when the generator is
not installed: smooth random images and a box-shaped point cloud, recorded as such in the manifest.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from pallet6d.runtime.detector import depth_channel, letterbox, letterbox_depth
from pallet6d.runtime.evaluation import counted_pallets
from pallet6d.runtime.pose_inputs import PoseInputSpec, prepare_pose_inputs

from .config import ModelConfig

__all__ = ["CalibrationSet", "PAPER_PRESETS", "make_calibration_set", "pose_input_spec"]

log = logging.getLogger(__name__)

PAPER_PRESETS = ("virtual-occluded", "indoor-noisy", "virtual-clean")   # the default calibration presets


@dataclass(frozen=True)
class CalibrationSet:
    """:ivar images: (F, C, H, W) float32 in [0, 1], letterboxed detector inputs (C = 4 for an RGB-D detector:
        the depth channel last).
    :ivar rgb_crops: (P, 3, h, w). :ivar depth_crops: (P, 1, h, w). :ivar points: (P, N, 3). :ivar choose: (P, N).
    :ivar source: where the data came from (recorded in the manifest).
    :ivar crop_sources: (P,) the preset each crop was taken from.
    :ivar other_images: per further detector input size (H', W'), the same frames letterboxed at that size,
        (F, 3, H', W') (a detector that takes several sizes is calibrated and checked at each)."""

    images: np.ndarray
    rgb_crops: np.ndarray
    depth_crops: np.ndarray
    points: np.ndarray
    choose: np.ndarray
    source: str
    crop_sources: tuple[str, ...] = ()
    other_images: dict = field(default_factory=dict)

    def images_at(self, input_hw: tuple[int, int]) -> np.ndarray:
        """(F, 3, H, W) detector inputs letterboxed at `input_hw`. A size the set was not made for
        (`make_calibration_set(detector_sizes=...)`) is made, once, by letterboxing `images` again: their own
        padding then stays in the picture, so it serves checks better than calibration (a warning says so)."""
        hw = (int(input_hw[0]), int(input_hw[1]))
        if hw == tuple(self.images.shape[2:]):
            return self.images
        if hw not in self.other_images:
            log.warning("the calibration set has no detector inputs at %dx%d: letterboxing its %dx%d inputs to it "
                        "(make it with detector_sizes listing every size)", *hw, *self.images.shape[2:])
            rgb = (self.images[:, :3].transpose(0, 2, 3, 1) * 255.0).round().clip(0, 255).astype(np.uint8)
            out = []
            for k, im in enumerate(rgb):
                img, lb = letterbox(im, hw)
                chans = [_to_chw01(img)]
                if self.images.shape[1] == 4:   # the depth channel is letterboxed like depth (values already scaled)
                    chans.append(letterbox_depth(self.images[k, 3], lb)[None])
                out.append(np.concatenate(chans))
            self.other_images[hw] = np.stack(out)
        return self.other_images[hw]


def pose_input_spec(cfg: ModelConfig) -> PoseInputSpec:
    """The preprocessing spec a bundle exported from `cfg` will declare."""
    return PoseInputSpec(crop_hw=cfg.fusion.crop_hw, rgb_mean=cfg.rgb_mean, rgb_std=cfg.rgb_std,
                         depth_clip_m=cfg.depth_clip_m, num_points=cfg.pose.num_points,
                         depth_range_m=cfg.depth_range_m)


def _to_chw01(img: np.ndarray) -> np.ndarray:
    return img.transpose(2, 0, 1).astype(np.float32) / 255.0


def _detector_input(rgb: np.ndarray, depth_m: np.ndarray, hw: tuple[int, int], depth_max_m: float | None) -> np.ndarray:
    """The detector's (C, H, W) input of a frame, as the runtime's detector stage makes it (without normalisation:
    our detectors take [0, 1])."""
    img, lb = letterbox(rgb, hw)
    if depth_max_m is None:
        return _to_chw01(img)
    return np.concatenate([_to_chw01(img), depth_channel(letterbox_depth(depth_m, lb), depth_max_m)[None]])


def _from_sim(cfg: ModelConfig, frames: int, max_crops: int, seed: int, presets: tuple[str, ...],
              other_sizes: tuple[tuple[int, int], ...]) -> CalibrationSet:
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    rng = np.random.default_rng(seed)
    spec = pose_input_spec(cfg)
    images, batches = [], {p: [] for p in presets}
    others: dict = {hw: [] for hw in other_sizes}
    for i in range(frames):
        preset = presets[i % len(presets)]
        frame = generate_frame(get_preset(preset), seed, i)
        depth_max = cfg.detector.depth_max_m
        images.append(_detector_input(frame.rgb, frame.depth_m, cfg.detector.input_hw, depth_max))
        for hw, imgs in others.items():
            imgs.append(_detector_input(frame.rgb, frame.depth_m, hw, depth_max))
        boxes = []
        # calibration's own rule: clearly visible pallets (>= 25 %, a box >= 8 px each way, >= 50 depth pixels)
        counted = counted_pallets(frame.pallets, min_visib_fract=0.25, min_box_side_px=8)
        for gt, c in zip(frame.pallets, counted):
            if not c or gt.px_count_valid < 50:
                continue
            x, y, w, h = (float(v) for v in gt.bbox_visib_xywh)
            jitter = rng.normal(0.0, 0.05, 4) * np.array([w, h, w, h])   # detector-like box noise
            boxes.append(np.array([x, y, x + w, y + h]) + jitter)
        if boxes:
            b = prepare_pose_inputs(frame.rgb, frame.depth_m, frame.K, np.array(boxes), spec, rng)
            batches[preset].append(b.take(np.flatnonzero(b.usable)))
    keys = ("rgb_crops", "depth_crops", "points", "choose")
    pools = [{k: np.concatenate([getattr(b, k) for b in bs]) for k in keys} for bs in batches.values() if bs]
    if not pools or sum(len(p["points"]) for p in pools) == 0:
        raise RuntimeError("the simulator produced no usable pallet crops for calibration")
    # crops taken from the presets in turn: each preset gets an equal share (a cluttered virtual frame holds
    # several pallets, an indoor one usually one) and the held-out last quarter mixes them all
    order, rank = [], 0
    while len(order) < max_crops and any(rank < len(p["points"]) for p in pools):
        order += [(j, rank) for j, p in enumerate(pools) if rank < len(p["points"])]
        rank += 1
    order = order[:max_crops]
    cat = {k: np.stack([pools[j][k][i] for j, i in order]) for k in keys}
    names = [p for p, bs in batches.items() if bs]
    crop_sources = tuple(names[j] for j, _ in order)
    counts = {name: crop_sources.count(name) for name in names}
    return CalibrationSet(np.stack(images), **cat, crop_sources=crop_sources,
                          other_images={hw: np.stack(imgs) for hw, imgs in others.items()},
                          source=f"pallet6d.sim presets {list(presets)}, {frames} frames, seed {seed}, "
                                 f"{len(order)} ground-truth crops with 5% box jitter {counts}")


def _synthetic(cfg: ModelConfig, frames: int, max_crops: int, seed: int,
               other_sizes: tuple[tuple[int, int], ...]) -> CalibrationSet:
    """Smooth random images and box-surface points (used only when pallet6d.sim is missing)."""
    import cv2

    rng = np.random.default_rng(seed)
    spec = pose_input_spec(cfg)
    (H, W), (h, w), n = cfg.detector.input_hw, spec.crop_hw, spec.num_points

    def smooth(shape_hw, c):
        small = rng.random((max(2, shape_hw[0] // 16), max(2, shape_hw[1] // 16), c)).astype(np.float32)
        return cv2.resize(small, (shape_hw[1], shape_hw[0]), interpolation=cv2.INTER_CUBIC).reshape(*shape_hw, c)

    c_det = cfg.detector.input_channels
    images = np.stack([np.clip(smooth((H, W), c_det), 0, 1).transpose(2, 0, 1) for _ in range(frames)])
    others = {hw: np.stack([np.clip(smooth(hw, c_det), 0, 1).transpose(2, 0, 1)
                            for _ in range(frames)]).astype(np.float32) for hw in other_sizes}
    p = max_crops
    mean = np.asarray(spec.rgb_mean, np.float32).reshape(3, 1, 1)
    std = np.asarray(spec.rgb_std, np.float32).reshape(3, 1, 1)
    rgb = np.stack([(np.clip(smooth((h, w), 3), 0, 1).transpose(2, 0, 1) - mean) / std for _ in range(p)])
    depth = np.stack([np.clip(smooth((h, w), 1) * 2 - 1, -1, 1).transpose(2, 0, 1) for _ in range(p)])
    face = rng.integers(0, 3, (p, n))
    pts = rng.uniform(-0.5, 0.5, (p, n, 3)) * np.array([1.2, 0.8, 0.144])
    pts[np.arange(p)[:, None], np.arange(n)[None], face] = 0.5 * np.sign(rng.standard_normal((p, n))) * \
        np.array([1.2, 0.8, 0.144])[face]
    choose = rng.integers(0, h * w, (p, n))
    return CalibrationSet(images.astype(np.float32), rgb.astype(np.float32), depth.astype(np.float32),
                          pts.astype(np.float32), choose.astype(np.int64), crop_sources=("synthetic",) * p,
                          other_images=others,
                          source=f"synthetic: smooth random images/crops and box-surface points (seed {seed}); "
                                 "pallet6d.sim was not available")


def make_calibration_set(cfg: ModelConfig, frames: int = 8, max_crops: int = 96, seed: int = 0,
                         presets: tuple[str, ...] | None = None, synthetic: bool = False,
                         detector_sizes=()) -> CalibrationSet:
    """Calibration inputs from the simulator, or synthetic ones when it is not installed or `synthetic`.

    :param presets: the sim presets the frames and crops come from, in turn (None: `PAPER_PRESETS`).

    :param detector_sizes: detector input sizes (H, W) to letterbox the frames at besides the config's
        `input_hw` (`CalibrationSet.images_at`).
    """
    ref = tuple(cfg.detector.input_hw)
    other_sizes = tuple(dict.fromkeys(hw for hw in ((int(h), int(w)) for h, w in detector_sizes) if hw != ref))
    if synthetic:
        return _synthetic(cfg, frames, max_crops, seed, other_sizes)
    try:
        import pallet6d.sim.generate  # noqa: F401
    except ImportError:
        log.warning("pallet6d.sim is not available: calibrating on synthetic inputs")
        return _synthetic(cfg, frames, max_crops, seed, other_sizes)
    return _from_sim(cfg, frames, max_crops, seed, tuple(presets or PAPER_PRESETS), other_sizes)
