"""Detector training: the YOLOv8-style detector on letterboxed frames with YOLOv8's loss (`losses.DetectorLoss`).

The detector is fully convolutional and runs at one of several inputs of about the same pixel count, the one
that draws a camera's frame largest (`runtime.detector.choose_input_hw`): wide for the paper's 1224x370 frames,
squarer for 4:3 and 16:9 cameras. Frames are kept at their own size (longest side capped, cached); each
training batch takes one input size (mostly the one its first frame would run at, sometimes another) and draws
every frame into it with a random zoom and position (`place_in_window`), HSV gains, blur, noise and horizontal
flips, from an epoch-seeded generator. With `mosaic`, that share of the inputs holds four frames, a quarter each
(`place_mosaic`, YOLOv8's mosaic): simulated and real scenes side by side, more backgrounds per batch, pallets cut at
the quarters' borders. Validation letterboxes each frame exactly as the runtime does. Targets
are the visible boxes of pallets at least 10 % visible, the boxes the evaluation matches against. Validation:
loss, and precision/recall at IoU 0.5 of the runtime's decoding (`runtime.detector.decode_yolov8`, score 0.25).

Real photographs (`real=`: a dataset imported by `real_data.py`) join the simulated frames: their train split,
cut again by capture sequence for validation (`real_samples.py`). They carry no pallet type, so their boxes are
class -1 for `DetectorLoss` (box and "is a pallet" only) while simulated boxes also teach the type. Validation
reports precision and recall on the simulated and the real validation frames apart, and recall on the real
boxes at least 8 % of the image tall (`recall_real_near`: the pallets a forklift approaches; LOCO's many far,
small pallets would otherwise dominate the real numbers).

An RGB-D detector (`DetectorConfig.depth_max_m`) also reads each simulated frame's depth, drawn into the input
with the same zoom and position, with stereo-like noise and holes; in `DEPTH_OFF_PROB` of the simulated frames, and
in every real photograph (they have none), the depth channel is empty, so the detector also works without depth.
In `DEPTH_MISMATCH_PROB` of the simulated frames the depth does not belong to the image (a plane, another frame's
depth, the frame's own depth mirrored) and the frame has no pallet to find: valid depth that shows no pallet
where the image shows one is not a pallet (the inputs the fit check also refuses), while no depth at all is
"unknown", not "no pallet".

Near pallets are few among the real photographs (LOCO is mostly far pallets): `real_repeat_large` repeats the
real training photographs that hold a box at least 20 % of the image tall, and `select="near_f1"` keeps the
checkpoint with the best F1 of near-box recall and real precision instead of the lowest validation loss.
"""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.detector import choose_input_hw, decode_yolov8, depth_channel, letterbox, letterbox_depth
from pallet6d.runtime.evaluation import box_iou

from .config import ModelConfig
from .detector import build_detector
from .losses import DetectorLoss, detector_distill_loss
from .train_data import AugmentConfig, DetectorSamples, augment_depth, augment_rgb, build_detector_samples, \
    flip_horizontal, load_or_build, place_mosaic, place_rgbd_in_window, repeat_train, repeated_roots
from .train_loop import LoopSettings, autocast, conv_input, conv_layout, load_init_weights, train_epochs

__all__ = ["DetectorData", "load_detector_data", "DetectorTrainer", "train_detector"]

log = logging.getLogger(__name__)

MAX_SIDE = 1280          # frames are kept at most this large: a 640-wide input zoomed 2x stays sharp
OWN_SIZE_PROB = 0.75     # share of batches at the input size their first frame runs at; the rest at any size
NEAR_FRACTION = 0.08     # real boxes at least this fraction of the image tall count as near (medium + large)
LARGE_FRACTION = 0.2     # real photographs with a box this tall are the ones `real_repeat_large` repeats
SELECTIONS = ("loss", "near_f1")
DEPTH_OFF_PROB = 0.3     # RGB-D detector: share of simulated training frames shown without depth
DEPTH_MISMATCH_PROB = 0.15   # RGB-D detector: share of simulated frames shown with depth of another scene, no targets


@dataclass
class DetectorData:
    """Frames and their split. `real` (F,) bool marks real photographs: boxes without a pallet type."""

    samples: DetectorSamples
    train_idx: np.ndarray
    val_idx: np.ndarray
    fingerprints: list[dict]
    real: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.real is None:
            self.real = np.zeros(len(self.samples), bool)
        if len(self.real) != len(self.samples):
            raise ValueError(f"DetectorData: {len(self.samples)} frames but {len(self.real)} real flags")


def load_detector_data(cfg: ModelConfig, data: Sequence[str | Path], seed: int, cache_dir: str | Path | None,
                       val_fraction: float = 0.1, max_frames: int | None = None,
                       progress: bool = True, real: str | Path | None = None,
                       real_max_images: int | None = None, real_repeat_large: int = 1,
                       real_keep_kinds: Sequence[str] = ()) -> DetectorData:
    """Letterboxed frames of every dataset (cached), split into train/val frames; with `real`, the imported
    real photographs' train split joins them (its own sequence-wise validation cut), those with a large box
    `real_repeat_large` times (as are photos of `real_keep_kinds`, always among `real_max_images`). An RGB-D
    detector's frames keep their depth. A dataset named k times in `data` is loaded and held out from once and
    trained k times (`train_data.repeated_roots`)."""
    if real_repeat_large < 1:
        raise ValueError(f"real_repeat_large must be >= 1, got {real_repeat_large}")
    from tqdm import tqdm

    parts, fps = [], []
    with_depth = cfg.detector.depth_max_m is not None
    data, repeats = repeated_roots(data)
    for root, k in zip(data, repeats):
        n = len(BopDataset(root))
        settings = {"max_side": MAX_SIDE, "max_frames": max_frames, **({"depth": True} if with_depth else {})}
        with tqdm(total=n if max_frames is None else min(n, max_frames), desc=f"frames {Path(root).name}",
                  unit="frame", disable=not progress, leave=False) as bar:
            s, fp = load_or_build("detector", root, settings, cache_dir,
                                  lambda: build_detector_samples(root, MAX_SIDE, max_frames, bar.update, with_depth))
        parts.append(s)
        fps.append(fp | ({"repeat": int(k)} if k > 1 else {}))
    samples = DetectorSamples.concat(parts)
    n = len(samples)
    rng = np.random.default_rng(seed)
    n_val = int(round(val_fraction * n)) if n > 2 else 0
    perm = rng.permutation(n)
    val_idx, train_idx = np.sort(perm[:n_val]), np.sort(perm[n_val:])
    if n_val == 0:   # tiny datasets: validate on the training frames
        val_idx = train_idx
    sample_root = np.repeat(np.arange(len(parts)), [len(s) for s in parts])
    train_idx = repeat_train(train_idx, sample_root, repeats)
    is_real = np.zeros(n, bool)
    if real is not None:
        from .real_samples import load_real_samples

        r_train, r_val, r_fp, rare = load_real_samples(real, MAX_SIDE, val_fraction, real_max_images, seed,
                                                       real_keep_kinds)
        samples = DetectorSamples.concat([samples, r_train, r_val])
        large = np.array([has_large_box(b, img.shape[0]) for b, img in zip(r_train.boxes, r_train.images)], bool)
        repeats = np.where(large | rare, real_repeat_large, 1)
        train_idx = np.concatenate([train_idx, n + np.repeat(np.arange(len(r_train)), repeats)])
        log.info("real photographs with a large box or of a kept kind: %d of %d, each trained %d times",
                 int((large | rare).sum()), len(large), real_repeat_large)
        val_idx = np.concatenate([val_idx, n + len(r_train) + np.arange(len(r_val))])
        is_real = np.concatenate([is_real, np.ones(len(r_train) + len(r_val), bool)])
        fps.append({"real": r_fp})
    log.info("detector frames: %d train, %d val (%d real)", len(train_idx), len(val_idx), int(is_real.sum()))
    return DetectorData(samples, train_idx, val_idx, fps, is_real)


def has_large_box(boxes_xyxy: np.ndarray, image_h_px: int) -> bool:
    """:param boxes_xyxy: (n, 4) in pixels of an image `image_h_px` tall."""
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    return bool(len(b)) and float((b[:, 3] - b[:, 1]).max()) >= LARGE_FRACTION * image_h_px


class DetectorTrainer:
    """:param input_sizes: the detector's input sizes (H, W), multiples of 32; default: the config's one size.
    :param select: the validation metric that picks `best.pt`: "loss" or "near_f1" (1 - F1 of real near-box
        recall and real precision; needs real validation frames).
    :param mosaic: share of the training inputs that hold four frames (`place_mosaic`): the frame of the step and
        three drawn from the training frames at random. 0: one frame an input."""

    def __init__(self, cfg: ModelConfig, data: DetectorData, aug: AugmentConfig, device: str = "cpu",
                 amp: bool = False, input_sizes: Sequence[tuple[int, int]] | None = None,
                 select: str = "loss", loader_threads: int = 1, mosaic: float = 0.0,
                 teacher: torch.nn.Module | None = None, distill_weight: float = 1.0) -> None:
        if select not in SELECTIONS:
            raise ValueError(f"select must be one of {SELECTIONS}, got {select!r}")
        if select == "near_f1" and not data.real[data.val_idx].any():
            raise ValueError("select='near_f1' needs real validation photographs (--real)")
        if not 0.0 <= mosaic <= 1.0:
            raise ValueError(f"mosaic must be in [0, 1], got {mosaic}")
        self.select, self.mosaic = select, float(mosaic)
        self.cfg, self.data, self.aug, self.device, self.amp = cfg, data, aug, torch.device(device), amp
        self.class_of_type = detector_class_of_type(cfg.detector.classes, data)
        self.input_sizes = [tuple(int(v) for v in hw) for hw in (input_sizes or [cfg.detector.input_hw])]
        for h, w in self.input_sizes:
            if h <= 0 or w <= 0 or h % 32 or w % 32:
                raise ValueError(f"detector input sizes must be positive multiples of 32, got {h}x{w}")
        if loader_threads < 1:
            raise ValueError(f"loader_threads must be >= 1, got {loader_threads}")
        # OpenCV and numpy release the GIL on whole images: threads prepare a batch's frames side by side
        self.pool = ThreadPoolExecutor(loader_threads) if loader_threads > 1 else None
        self.depth_max_m = cfg.detector.depth_max_m
        self._sim_frames = np.flatnonzero(~data.real)   # frames with depth, for `_mismatched_depth`
        self.detector = conv_layout(build_detector(cfg.detector).to(self.device))
        self.loss = DetectorLoss(self.detector)
        if teacher is not None and not distill_weight > 0:
            raise ValueError(f"distill_weight must be positive, got {distill_weight}")
        # a fixed teacher (e.g. the SiLU detector a ReLU one starts from): its raw maps on the same inputs are a
        # target at every anchor, where the labelled boxes give one at a few (`detector_distill_loss`)
        self.teacher, self.distill_weight = teacher, float(distill_weight)
        if teacher is not None:
            conv_layout(teacher.to(self.device)).eval().requires_grad_(False)

    @property
    def nets(self) -> dict[str, torch.nn.Module]:
        return {"detector": self.detector}

    def input_hw_of(self, i: int) -> tuple[int, int]:
        """The input size the runtime runs frame `i` at."""
        return choose_input_hw(self.data.samples.images[i].shape[:2], self.input_sizes)

    def batch(self, idx: np.ndarray, rng: np.random.Generator | None,
              input_hw: tuple[int, int] | None = None) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Frames `idx` drawn into one input size (default: the first frame's), augmented (rng given) or
        letterboxed as the runtime does: (B, C, H, W) float in [0, 1] (C = 4 with depth), B targets (n_i, 5)
        cls+xyxy."""
        hw = input_hw or self.input_hw_of(int(idx[0]))
        # one seed per frame, drawn up front: the batch is the same whichever thread prepares which frame
        seeds = rng.integers(0, 2**63 - 1, size=len(idx)) if rng is not None else [None] * len(idx)
        jobs = [(int(i), hw, seed) for i, seed in zip(idx, seeds)]
        prepared = list(self.pool.map(self._prepare, jobs)) if self.pool else [self._prepare(j) for j in jobs]
        targets = [torch.from_numpy(t).to(self.device) for _, _, t in prepared]
        x = torch.from_numpy(np.stack([img for img, _, _ in prepared])).to(self.device).permute(0, 3, 1, 2).float()
        x = x.div_(255.0)
        if self.depth_max_m is not None:   # the depth channel, already in [0, 1]
            d = torch.from_numpy(np.stack([dc for _, dc, _ in prepared])).to(self.device).unsqueeze(1)
            x = torch.cat((x, d), 1)
        return conv_input(x), targets

    def _prepare(self, job: tuple[int, tuple[int, int], int | None]
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Frame `i` drawn into input size `hw`: augmented with a generator of `seed`, or letterboxed as the
        runtime does (seed None). :return: (H, W, 3) uint8 image, the RGB-D detector's (H, W) float32 depth channel
        (None for an RGB detector), (n, 5) float32 targets class, x1, y1, x2, y2."""
        i, hw, seed = job
        img, depth, boxes = self._frame(i)
        if seed is not None:
            a, rng = self.aug, np.random.default_rng(int(seed))
            if self.mosaic and rng.random() < self.mosaic:
                frames = [(img, depth, boxes)] + [self._frame(int(j)) for j in rng.choice(self.data.train_idx, 3)]
                if any(d is None for _, d, _ in frames):    # a real photograph among them: the input has no depth
                    frames = [(im, None, b) for im, _, b in frames]
                img, depth, boxes = place_mosaic(frames, hw, rng, a.zoom_range, a.zoom_in_max, a.shift_fraction)
            else:
                img, depth, boxes = place_rgbd_in_window(img, depth, boxes, hw, rng, a.zoom_range, a.zoom_in_max,
                                                         a.shift_fraction)
            img = augment_rgb(img, rng, a)
            if depth is not None and rng.random() < DEPTH_MISMATCH_PROB:   # kept: without depth it has pallets
                depth, boxes = augment_depth(self._mismatched_depth(depth, i, rng), rng, a), boxes[:0]
            elif depth is not None:
                depth = augment_depth(depth, rng, a) if rng.random() >= DEPTH_OFF_PROB else None
            if rng.random() < a.flip_prob:
                img, boxes = flip_horizontal(img, boxes)
                depth = None if depth is None else np.ascontiguousarray(depth[:, ::-1])
        else:
            img, lb = letterbox(img, hw)
            depth = None if depth is None else letterbox_depth(depth, lb)
            boxes = boxes.copy()
            boxes[:, [0, 2]] = boxes[:, [0, 2]] * lb.scale_x + lb.pad_x
            boxes[:, [1, 3]] = boxes[:, [1, 3]] * lb.scale_y + lb.pad_y
        channel = None
        if self.depth_max_m is not None:
            channel = np.zeros(img.shape[:2], np.float32) if depth is None else depth_channel(depth, self.depth_max_m)
        return img, channel, np.ascontiguousarray(boxes[:, [4, 0, 1, 2, 3]], np.float32)

    def _frame(self, i: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Frame `i` as stored: (h, w, 3) uint8 image, (h, w) depth in metres (an RGB-D detector's; else None),
        (n, 5) float32 boxes x1, y1, x2, y2, class (-1: a pallet of unknown type, a real photograph's box)."""
        s = self.data.samples
        depth = s.depth_m(i) if self.depth_max_m is not None else None
        cls = np.full(len(s.types[i]), -1.0) if self.data.real[i] else \
            self.class_of_type[np.asarray(s.types[i], np.int64)].astype(np.float64)
        boxes = np.column_stack([np.asarray(s.boxes[i], np.float32).reshape(-1, 4), cls]).astype(np.float32)
        return s.images[i], depth, boxes

    def _mismatched_depth(self, depth_m: np.ndarray, i: int, rng: np.random.Generator) -> np.ndarray:
        """A depth image of the window's size that does not belong to frame `i`'s image: a plane (a wall or a
        floor seen at a slant), another simulated frame's depth stretched to the window, or the frame's own depth
        mirrored. :param depth_m: (H, W) float32 metres, the frame's depth in the window."""
        h, w = depth_m.shape
        kind = int(rng.integers(3))
        if kind == 1 and len(self._sim_frames) > 1:
            j = int(rng.choice(self._sim_frames[self._sim_frames != i]))
            other = self.data.samples.depth_m(j)
            if other is not None:
                return cv2.resize(other, (w, h), interpolation=cv2.INTER_NEAREST)
        if kind == 2:
            return np.ascontiguousarray(depth_m[::-1] if rng.random() < 0.5 else depth_m[:, ::-1])
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        gx, gy = rng.uniform(-1.0, 1.0, 2) * np.float32(2.0 / max(h, w))
        plane = np.float32(rng.uniform(0.8, 8.0)) * (1.0 + gx * (xx - w / 2) + gy * (yy - h / 2))
        return np.where(plane > 0.1, plane, 0.0).astype(np.float32)

    def step(self, idx: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, dict]:
        frames = self.data.train_idx[idx]
        hw = self.input_hw_of(int(frames[0])) if rng.random() < OWN_SIZE_PROB else \
            self.input_sizes[int(rng.integers(len(self.input_sizes)))]
        x, targets = self.batch(frames, rng, hw)
        with autocast(self.device.type, self.amp):
            raw = self.detector.forward_raw(x)
        loss, parts = self.loss([r.float() for r in raw], targets)
        out = {k: float(v) for k, v in parts.items() if k != "fg"}
        if self.teacher is not None:
            with torch.no_grad(), autocast(self.device.type, self.amp):
                ref = self.teacher.forward_raw(x)
            cls, box = detector_distill_loss(raw, ref, self.detector.head.reg_max)
            loss = loss + self.distill_weight * (cls + box)
            out.update(distill_cls=float(cls.detach()), distill_box=float(box.detach()))
        return loss, out

    @torch.no_grad()
    def validate(self, batch: int = 8, score_threshold: float = 0.25, iou: float = 0.5) -> dict:
        """Validation loss over all validation frames; precision/recall over the simulated ones, and (`_real`)
        over the real ones when there are any, with the recall of the real near boxes; with several classes, the
        share of found simulated boxes given their own type, averaged over the types (`type_accuracy`; the worst type's
        in `type_accuracy_min`); `metric` by `select`."""
        idx_all = self.data.val_idx
        sizes = [self.input_hw_of(int(i)) for i in idx_all]
        groups = [idx_all[[k for k, hw in enumerate(sizes) if hw == size]] for size in dict.fromkeys(sizes)]
        chunks = [g[i:i + batch] for g in groups for i in range(0, len(g), batch)]   # one input size per batch
        total = 0.0
        counts = {False: [0, 0, 0], True: [0, 0, 0]}   # real? -> tp, n_pred, n_gt
        near = [0, 0]                                   # real boxes >= NEAR_FRACTION tall: found, all
        nc = self.detector.head.nc
        types = np.zeros((2, nc), np.int64)             # found boxes of a known type, per type: right type, all
        for idx in chunks:
            x, targets = self.batch(idx, None)
            raw = self.detector.forward_raw(x)
            loss, _ = self.loss(raw, targets)
            total += float(loss) * len(idx)
            decoded = self.detector.head.decode(raw).cpu().numpy()
            for k, t in enumerate(targets):
                det = decode_yolov8(decoded[k], score_threshold, 0.5, tuple(range(self.detector.head.nc)), 300,
                                    agnostic=True)
                gt = t[:, 1:].cpu().numpy()
                real = bool(self.data.real[idx[k]])
                c = counts[real]
                c[1], c[2] = c[1] + len(det.boxes_xyxy), c[2] + len(gt)
                matched = match_greedy(det.boxes_xyxy, gt, iou)
                found = matched >= 0
                c[0] += int(found.sum())
                gt_cls = t[:, 0].cpu().numpy()
                typed = found & (gt_cls >= 0) if self.detector.head.nc > 1 else np.zeros(len(gt), bool)
                truth = gt_cls[typed].astype(np.int64)
                np.add.at(types[0], truth, det.class_ids[matched[typed]] == truth)
                np.add.at(types[1], truth, 1)
                if real:   # near: tall relative to the letterboxed image's own height
                    content_h = letterboxed_height(self.data.samples.images[idx[k]].shape[:2], tuple(x.shape[2:]))
                    is_near = (gt[:, 3] - gt[:, 1]) >= NEAR_FRACTION * content_h
                    near[0] += int((found & is_near).sum())
                    near[1] += int(is_near.sum())
        loss = total / max(len(idx_all), 1)
        out = {"metric": loss, "loss": loss}
        if near[1]:
            out.update({"recall_real_near": near[0] / near[1], "n_gt_real_near": near[1]})
        if types[1].any():
            mean, worst = balanced_type_accuracy(types[0], types[1])
            out.update({"type_accuracy": mean, "type_accuracy_min": worst, "n_typed": int(types[1].sum())})
        for is_real, suffix in ((False, ""), (True, "_real")):
            tp, n_pred, n_gt = counts[is_real]
            if is_real and n_gt == 0 and n_pred == 0:
                continue
            out.update({f"precision{suffix}": tp / n_pred if n_pred else 0.0,
                        f"recall{suffix}": tp / n_gt if n_gt else 0.0, f"n_gt{suffix}": n_gt})
        if self.select == "near_f1":
            r, p = out.get("recall_real_near", 0.0), out.get("precision_real", 0.0)
            out["near_f1"] = 2 * r * p / (r + p) if r + p > 0 else 0.0
            out["metric"] = 1.0 - out["near_f1"]
        return out


def class_output_names(detector: torch.nn.Module) -> set[str]:
    """Parameter names of the detector head's last class convs (one output channel per class, at every level)."""
    last = {f"head.cls.{k}.{len(seq) - 1}" for k, seq in enumerate(detector.head.cls)}
    return {n for n, _ in detector.named_parameters() if n.rsplit(".", 1)[0] in last}


def balanced_type_accuracy(right: np.ndarray, found: np.ndarray) -> tuple[float, float]:
    """The share of found boxes given their own type, averaged over the types found at least once (a common type
    cannot hide the others: a detector that calls every pallet an EPAL scores 1 / types, not the EPAL's share),
    and the worst type's share. :param right, found: (nc,) counts per true type."""
    seen = np.asarray(found) > 0
    if not seen.any():
        raise ValueError("balanced_type_accuracy: no typed box was found")
    per_type = np.asarray(right, np.float64)[seen] / np.asarray(found, np.float64)[seen]
    return float(per_type.mean()), float(per_type.min())


def detector_class_of_type(classes: Sequence[str], data: DetectorData) -> np.ndarray:
    """The detector class that learns each catalogue pallet type (`sim.pallets.PALLET_MODELS` order, then -1 for
    an unknown type): one class for every type, or one class per type named after it. An unknown type's boxes,
    in a detector of several classes, are pallets of any type (class -1).

    :return: (len(PALLET_MODELS) + 1,) float array; index -1 is the unknown type.
    :raises ValueError: the simulated frames hold a type that none of several classes names.
    """
    from pallet6d.sim.pallets import PALLET_MODELS

    if len(classes) == 1:
        return np.zeros(len(PALLET_MODELS) + 1)
    out = np.array([float(classes.index(n)) if n in classes else np.nan for n in PALLET_MODELS] + [-1.0])
    sim_types = {int(t) for i in np.flatnonzero(~data.real) for t in data.samples.types[i]}
    missing = sorted(PALLET_MODELS[t] for t in sim_types if t >= 0 and np.isnan(out[t]))
    if missing:
        raise ValueError(f"the training frames hold pallet types {missing} that none of the detector's classes "
                         f"{list(classes)} names")
    return np.nan_to_num(out, nan=-1.0)


def letterboxed_height(image_hw: tuple[int, int], input_hw: tuple[int, int]) -> float:
    """Height in input pixels of an (H, W) image letterboxed into `input_hw` (scaled to fit, aspect kept)."""
    h, w = image_hw
    return h * min(input_hw[0] / h, input_hw[1] / w)


def match_greedy(det_xyxy: np.ndarray, gt_xyxy: np.ndarray, iou: float) -> np.ndarray:
    """Which detection claims each ground-truth box at IoU >= `iou`, detections taken in the given (descending
    score) order, each claiming the first unclaimed box it overlaps. :return: (n_gt,) detection index, -1 none."""
    claimed_by = np.full(len(gt_xyxy), -1, np.int64)
    if len(det_xyxy) and len(gt_xyxy):
        for i, row in enumerate(box_iou(det_xyxy, gt_xyxy) >= iou):
            j = next((j for j in np.flatnonzero(row) if claimed_by[j] < 0), None)
            if j is not None:
                claimed_by[j] = i
    return claimed_by


def train_detector(cfg: ModelConfig, data: Sequence[str | Path], run_dir: str | Path, settings: LoopSettings,
                   aug: AugmentConfig | None = None, resume: bool = False, cache_dir: str | Path | None = None,
                   val_fraction: float = 0.1, max_frames: int | None = None, command: str = "",
                   progress: bool = True, init: str | Path | None = None, real: str | Path | None = None,
                   real_max_images: int | None = None, input_sizes: Sequence[tuple[int, int]] | None = None,
                   real_repeat_large: int = 1, select: str = "loss", loader_threads: int = 1,
                   class_lr_mult: float = 1.0, mosaic: float = 0.0, distill: str | Path | None = None,
                   distill_weight: float = 1.0, pretrained: str | Path | None = None,
                   real_keep_kinds: Sequence[str] = ()) -> dict:
    """Train the detector on BOP datasets (and the train split of imported real photographs, `real`);
    checkpoints and the log go to `run_dir`. Returns the last log entry.

    :param class_lr_mult: the learning rate of the class outputs (`class_output_names`) relative to the rest (a
        detector given a class per type from a one-class one starts every class alike). 20x alone did not part the
        types in two CPU epochs (docs/experiments/pallet-types.md): the features below must learn them too.
    :param mosaic: share of the training inputs that hold four frames (`DetectorTrainer`).
    :param distill: a bundle or checkpoint whose detector (of its own activation) is the fixed teacher, matched at
        every anchor with `distill_weight` (`losses.detector_distill_loss`); e.g. the SiLU detector a ReLU one
        starts from.
    :param pretrained: the published YOLOX-Nano ONNX export whose weights start a "yolox-nano" detector
        (`pretrained_dw.load_yolox_onnx`; not with `init`).
    :param real_keep_kinds: real photographs of these pallet kinds (e.g. "plastic") are always among
        `real_max_images` and trained `real_repeat_large` times (`load_detector_data`)."""
    if not class_lr_mult > 0:
        raise ValueError(f"class_lr_mult must be positive, got {class_lr_mult}")
    run_dir = Path(run_dir)
    aug = aug or AugmentConfig()
    torch.manual_seed(settings.seed)
    dd = load_detector_data(cfg, data, settings.seed, cache_dir if cache_dir is not None else run_dir / "cache",
                            val_fraction, max_frames, progress, real, real_max_images, real_repeat_large,
                            real_keep_kinds)
    teacher, teacher_record = None, None
    if distill is not None:
        from .bundle_weights import detector_activation_of, detector_architecture_of
        teacher = build_detector(replace(cfg.detector, activation=detector_activation_of(distill),
                                         architecture=detector_architecture_of(distill)))
        teacher_record = {"weights": load_init_weights(distill, {"detector": teacher}), "weight": distill_weight,
                          "activation": teacher.cfg.activation}
    trainer = DetectorTrainer(cfg, dd, aug, settings.device, amp=settings.amp, input_sizes=input_sizes,
                              select=select, loader_threads=loader_threads, mosaic=mosaic, teacher=teacher,
                              distill_weight=distill_weight)
    pretrained_record = None
    if pretrained is not None:
        if cfg.detector.architecture != "yolox-nano" or init is not None:
            raise ValueError("pretrained weights start a 'yolox-nano' detector (and not one given --init)")
        from .pretrained_dw import load_yolox_onnx
        # a resumed run's checkpoint holds the weights; the record is the same file's
        pretrained_record = load_yolox_onnx(trainer.detector, pretrained)
    # YOLOv8 practice: no weight decay on BatchNorm weights and biases; the class outputs at their own rate
    params = dict(trainer.detector.named_parameters())
    class_out = [n for n in params if n in class_output_names(trainer.detector)] if class_lr_mult != 1.0 else []
    rest = [n for n in params if n not in class_out]
    groups = [{"params": [params[n] for n in rest if params[n].ndim > 1], "weight_decay": 5e-4},
              {"params": [params[n] for n in rest if params[n].ndim <= 1], "weight_decay": 0.0}]
    if class_out:
        groups.append({"params": [params[n] for n in class_out], "weight_decay": 0.0, "lr_mult": float(class_lr_mult)})
    optimizer = torch.optim.AdamW(groups, lr=settings.lr, betas=(0.937, 0.999))
    provenance = {"stage": "detector", "config": cfg.name, "input_hw": list(cfg.detector.input_hw),
                  "input_sizes": [list(hw) for hw in trainer.input_sizes], "classes": list(cfg.detector.classes),
                  "depth_max_m": cfg.detector.depth_max_m, "activation": cfg.detector.activation,
                  "architecture": cfg.detector.architecture, "pretrained": pretrained_record,
                  **({"depth_off_prob": DEPTH_OFF_PROB, "depth_mismatch_prob": DEPTH_MISMATCH_PROB}
                     if cfg.detector.depth_max_m is not None else {}),
                  "seed": settings.seed, "command": command,
                  "data": dd.fingerprints, "epochs": settings.epochs, "batch": settings.batch, "lr": settings.lr,
                  "augment": aug.to_dict(), "val_fraction": val_fraction,
                  "real_repeat_large": real_repeat_large, "select": select, "class_lr_mult": class_lr_mult,
                  "mosaic": mosaic, "distill": teacher_record,
                  "samples": {"train": int(len(dd.train_idx)), "val": int(len(dd.val_idx)),
                              "real": int(dd.real.sum())},
                  "device": settings.device, "amp": "bf16" if settings.amp else None, "torch": str(torch.__version__)}
    return train_epochs(run_dir, "detector", cfg.name, trainer.nets, optimizer, settings, len(dd.train_idx),
                        trainer.step, trainer.validate, provenance, resume=resume, progress=progress, init=init)
