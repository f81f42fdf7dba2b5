"""Training crops with no pose to find: what a bundle's detector boxes in pallet-free simulated scenes, and pallets
under depth or intrinsics that do not belong to the image.

A student fusion network distilled on pallet crops alone learns the teacher's features where pallets are, and
nothing about the carton stacks, rack edges and floors the detector also boxes: there its features drift, and the
pose network posed on them passes the fit checks more often than under the teacher. And the pose network's
confidence, trained on pallets alone, has never been told what no pallet looks like. These crops are the runtime's
inputs on such boxes (`prepare_pose_inputs` on the detector's boxes, at a low score threshold so that the near
misses count too); training matches the teacher's features on them, or teaches the confidence to be low there
(`train_pose.PoseTrainer`); they have no pose. So are crops of real pallets whose depth or intrinsics do not belong
to the image (`build_mismatched_crops`: another frame's depth, a wrong depth scale, a wrong focal length, a flat
wall), the inputs a wrongly wired camera gives: no pose is right there either.

Frames come from `sim.pallet_free.render_pallet_free` with the training seed: keep it away from the seeds the
negative benchmarks use (`benchmarks/real_data.py --sim-seed`, 9100 and 9200).
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from pallet6d.runtime.bundle import BundleError, load_bundle
from pallet6d.runtime.pose_inputs import PoseInputSpec, prepare_pose_inputs
from pallet6d.sim.mismatch import MISMATCHES, mismatched

__all__ = ["NegativeCrops", "build_negative_crops", "build_mismatched_crops", "detector_graph", "load_negative_crops",
           "load_mismatched_crops"]

log = logging.getLogger(__name__)

MIN_POINTS = 50          # as the pose samples: a box with fewer valid depth pixels is never posed


@dataclass
class NegativeCrops:
    """:ivar rgb_crops: (B, 3, h, w) float32. :ivar depth_crops: (B, 1, h, w) float32.
    :ivar choose: (B, N) int64 flat pixel index into the crop, as `PoseBatch.choose`.
    :ivar points: (B, N, 3) float32 the sampled points, centred on their mean (metres), as `PoseBatch.points`."""

    rgb_crops: np.ndarray
    depth_crops: np.ndarray
    choose: np.ndarray
    points: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.rgb_crops)
        if not len(self.depth_crops) == len(self.choose) == len(self.points) == n:
            raise ValueError(f"negative crops: {n} rgb crops, {len(self.depth_crops)} depth crops, "
                             f"{len(self.choose)} point index rows, {len(self.points)} point sets; expected equal "
                             "counts")

    def take(self, idx) -> "NegativeCrops":
        return NegativeCrops(self.rgb_crops[idx], self.depth_crops[idx], self.choose[idx], self.points[idx])

    def __len__(self) -> int:
        return len(self.rgb_crops)


def build_negative_crops(detector_bundle: str | Path, spec: PoseInputSpec, presets: Sequence[str], frames: int,
                         seed: int, score_threshold: float = 0.1, max_boxes: int = 4,
                         progress=None) -> NegativeCrops:
    """The crops of the boxes `detector_bundle`'s detector (int8 when it has one, as it ships) finds in pallet-free
    frames.

    :param presets: sim presets; each gives `frames` frames with the loads set down and `frames` left hanging.
    :param seed: the frames' seed (module docstring). :param score_threshold: the detector's score cut.
    :param max_boxes: at most this many boxes a frame, the highest scoring.
    :param progress: called with 1 after each frame, or None.
    :raises ValueError: no box in any frame.
    """
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.sim.pallet_free import render_pallet_free

    if frames < 1 or max_boxes < 1:
        raise ValueError(f"frames and max_boxes must be >= 1, got {frames} and {max_boxes}")
    precision, _ = detector_graph(detector_bundle)
    est = PalletEstimator.from_bundle(detector_bundle, threads=1, precision=precision, score_threshold=score_threshold)
    rgb_rows, depth_rows, choose_rows, point_rows = [], [], [], []
    try:
        for p, preset in enumerate(presets):
            for set_down in (False, True):
                for i in range(frames):
                    index = 2 * p * frames + int(set_down) * frames + i
                    rgb, depth_m, K, _ = render_pallet_free(preset, seed, index, set_down)
                    boxes = est.detect(rgb).boxes_xyxy[:max_boxes]
                    if len(boxes):
                        batch = prepare_pose_inputs(rgb, depth_m, K, boxes, spec, np.random.default_rng((seed, index)))
                        keep = batch.n_valid >= MIN_POINTS
                        rgb_rows.append(batch.rgb_crops[keep])
                        depth_rows.append(batch.depth_crops[keep])
                        choose_rows.append(batch.choose[keep])
                        point_rows.append(batch.points[keep])
                    if progress is not None:
                        progress(1)
    finally:
        est.close()
    crops = NegativeCrops(*(np.concatenate(r) if r else np.zeros(0)
                            for r in (rgb_rows, depth_rows, choose_rows, point_rows)))
    if not len(crops):
        raise ValueError(f"no detection above score {score_threshold} in {2 * frames * len(presets)} pallet-free "
                         f"frames of {', '.join(presets)}: nothing to distill on")
    return crops


def build_mismatched_crops(datasets: Sequence[str | Path], spec: PoseInputSpec, frames: int, seed: int,
                           kinds: Sequence[str] = MISMATCHES, progress=None) -> NegativeCrops:
    """Crops of real pallets whose depth or intrinsics do not belong to the image (`sim.mismatch`): each of `frames`
    frames drawn at random from `datasets` (BOP), its ground-truth pallets' boxes (jittered as the pose samples'),
    once per kind; "other_frame" takes the depth of another drawn frame of the same size.

    :raises ValueError: no usable crop.
    """
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.evaluation import counted_pallets

    from .train_data import AugmentConfig, jitter_box

    aug = AugmentConfig()
    sets = [BopDataset(d) for d in datasets]
    rng = np.random.default_rng((seed, 7))
    picks = [(int(k), int(rng.integers(len(sets[k])))) for k in rng.integers(len(sets), size=frames)]
    rows: list[tuple] = []
    for n, (k, i) in enumerate(picks):
        f = sets[k][i]
        gts = [g for g, c in zip(f.gts, counted_pallets(f.gts, min_box_side_px=2, unknown_visib_counts=False)) if c]
        # the first other drawn frame of the same size, read lazily: a frame read is an image and a depth from disk
        others = (sets[kk][ii] for kk, ii in picks if (kk, ii) != (k, i))
        other = next((o for o in others if o.depth_m.shape == f.depth_m.shape), None)
        for kind in kinds:
            if not gts or (kind == "other_frame" and other is None):
                continue
            frng = np.random.default_rng((seed, n, MISMATCHES.index(kind) if kind in MISMATCHES else 99))
            depth_m, K = mismatched(kind, f.depth_m, f.K, None if other is None else other.depth_m)
            boxes = np.array([jitter_box(np.array([x, y, x + w, y + h], float), frng, aug.box_scale_sigma,
                                         aug.box_shift_sigma) for x, y, w, h in (g.bbox_visib_xywh for g in gts)])
            batch = prepare_pose_inputs(f.rgb, depth_m, K, boxes, spec, frng)
            keep = batch.n_valid >= MIN_POINTS
            rows += [(batch.rgb_crops[j], batch.depth_crops[j], batch.choose[j], batch.points[j])
                     for j in np.flatnonzero(keep)]
        if progress is not None:
            progress(1)
    if not rows:
        raise ValueError(f"no usable mismatched crop in {frames} frames of {len(sets)} datasets")
    return NegativeCrops(*(np.stack(c) for c in zip(*rows)))


def detector_graph(bundle: str | Path) -> tuple[str, Path]:
    """(precision, path) of the detector graph the crops are boxed with: int8 when the bundle has it.

    :raises ValueError: `bundle` is not a model bundle (e.g. a training checkpoint)."""
    try:
        b = load_bundle(bundle, verify_sha256=False)
    except (BundleError, OSError) as exc:
        raise ValueError(f"{bundle}: the negative crops need a model bundle's detector ({exc})") from exc
    precision = "int8" if "int8" in b.precision else "fp32"
    return precision, b.graph("detector", precision)


def load_negative_crops(detector_bundle: str | Path, spec: PoseInputSpec, presets: Sequence[str], frames: int,
                        seed: int, cache_dir: str | Path | None, score_threshold: float = 0.1,
                        max_boxes: int = 4, progress=None) -> tuple[NegativeCrops, dict]:
    """`build_negative_crops`, read from `cache_dir` when the same settings and detector graph made it before.

    :return: (crops, what to record of them in the run's provenance).
    """
    precision, graph = detector_graph(detector_bundle)
    record = {"format": 2, "detector": str(detector_bundle), "detector_precision": precision,
              "detector_sha256": hashlib.sha256(graph.read_bytes()).hexdigest(),
              "presets": list(presets), "frames_per_preset_and_load": frames, "seed": seed,
              "score_threshold": score_threshold, "max_boxes": max_boxes}
    crops = _cached("negatives", {**record, "spec": repr(spec)}, cache_dir,
                    lambda: build_negative_crops(detector_bundle, spec, presets, frames, seed, score_threshold,
                                                 max_boxes, progress))
    return crops, {**record, "crops": len(crops)}


def load_mismatched_crops(datasets: Sequence[str | Path], spec: PoseInputSpec, frames: int, seed: int,
                          cache_dir: str | Path | None, progress=None) -> tuple[NegativeCrops, dict]:
    """`build_mismatched_crops` (every kind), read from `cache_dir` when the same settings and data made it before.

    :return: (crops, what to record of them in the run's provenance).
    """
    from .train_data import dataset_fingerprint

    record = {"format": 1, "datasets": [dataset_fingerprint(d) for d in datasets], "frames": frames, "seed": seed,
              "kinds": list(MISMATCHES)}
    crops = _cached("mismatched", {**record, "spec": repr(spec)}, cache_dir,
                    lambda: build_mismatched_crops(datasets, spec, frames, seed, MISMATCHES, progress))
    return crops, {**record, "datasets": [str(d) for d in datasets], "crops": len(crops)}


def _cached(kind: str, settings: dict, cache_dir: str | Path | None, build) -> NegativeCrops:
    """`build()`'s crops, or the ones a build with the same `settings` cached in `cache_dir` (None: no cache)."""
    key = hashlib.sha256(repr(sorted(settings.items())).encode()).hexdigest()[:16]
    path = None if cache_dir is None else Path(cache_dir) / f"{kind}_{key}.npz"
    if path is not None and path.exists():
        with np.load(path, allow_pickle=False) as z:
            log.info("cache hit: %s", path)
            return NegativeCrops(z["rgb_crops"], z["depth_crops"], z["choose"], z["points"])
    crops = build()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, rgb_crops=crops.rgb_crops, depth_crops=crops.depth_crops, choose=crops.choose,
                 points=crops.points)
        tmp.replace(path)
    return crops
