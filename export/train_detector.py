"""Detector training: the YOLOv8-style detector on letterboxed frames with YOLOv8's loss (`losses.DetectorLoss`).

The detector is fully convolutional and runs at one of several inputs of about the same pixel count, the one
that draws a camera's frame largest (`runtime.detector.choose_input_hw`): wide for the paper's 1224x370 frames,
squarer for 4:3 and 16:9 cameras. Frames are kept at their own size (longest side capped, cached); each
training batch takes one input size (mostly the one its first frame would run at, sometimes another) and draws
every frame into it with a random zoom and position (`place_in_window`), HSV gains, blur, noise and horizontal
flips, from an epoch-seeded generator. Validation letterboxes each frame exactly as the runtime does. Targets
are the visible boxes of pallets at least 10 % visible, the boxes the evaluation matches against. Validation:
loss, and precision/recall at IoU 0.5 of the runtime's decoding (`runtime.detector.decode_yolov8`, score 0.25).

Real photographs (`real=`: a dataset imported by `real_data.py`) join the simulated frames: their train split,
cut again by capture sequence for validation (`real_samples.py`). They carry no pallet type, so their boxes are
class -1 for `DetectorLoss` (box and "is a pallet" only) while simulated boxes also teach the type. Validation
reports precision and recall on the simulated and the real validation frames apart.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.detector import choose_input_hw, decode_yolov8, letterbox
from pallet6d.runtime.evaluation import box_iou

from .config import ModelConfig
from .detector import build_detector
from .losses import DetectorLoss
from .train_data import AugmentConfig, DetectorSamples, augment_rgb, build_detector_samples, flip_horizontal, \
    load_or_build, place_in_window
from .train_loop import LoopSettings, autocast, train_epochs

__all__ = ["DetectorData", "load_detector_data", "DetectorTrainer", "train_detector"]

log = logging.getLogger(__name__)

MAX_SIDE = 1280          # frames are kept at most this large: a 640-wide input zoomed 2x stays sharp
OWN_SIZE_PROB = 0.75     # share of batches at the input size their first frame runs at; the rest at any size


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
                       real_max_images: int | None = None) -> DetectorData:
    """Letterboxed frames of every dataset (cached), split into train/val frames; with `real`, the imported
    real photographs' train split joins them (its own sequence-wise validation cut)."""
    from tqdm import tqdm

    parts, fps = [], []
    for root in data:
        n = len(BopDataset(root))
        settings = {"max_side": MAX_SIDE, "max_frames": max_frames}
        with tqdm(total=n if max_frames is None else min(n, max_frames), desc=f"frames {Path(root).name}",
                  unit="frame", disable=not progress, leave=False) as bar:
            s, fp = load_or_build("detector", root, settings, cache_dir,
                                  lambda: build_detector_samples(root, MAX_SIDE, max_frames, bar.update))
        parts.append(s)
        fps.append(fp)
    samples = DetectorSamples.concat(parts)
    n = len(samples)
    rng = np.random.default_rng(seed)
    n_val = int(round(val_fraction * n)) if n > 2 else 0
    perm = rng.permutation(n)
    val_idx, train_idx = np.sort(perm[:n_val]), np.sort(perm[n_val:])
    if n_val == 0:   # tiny datasets: validate on the training frames
        val_idx = train_idx
    is_real = np.zeros(n, bool)
    if real is not None:
        from .real_samples import load_real_samples

        r_train, r_val, r_fp = load_real_samples(real, MAX_SIDE, val_fraction, real_max_images, seed)
        samples = DetectorSamples.concat([samples, r_train, r_val])
        train_idx = np.concatenate([train_idx, n + np.arange(len(r_train))])
        val_idx = np.concatenate([val_idx, n + len(r_train) + np.arange(len(r_val))])
        is_real = np.concatenate([is_real, np.ones(len(r_train) + len(r_val), bool)])
        fps.append({"real": r_fp})
    log.info("detector frames: %d train, %d val (%d real)", len(train_idx), len(val_idx), int(is_real.sum()))
    return DetectorData(samples, train_idx, val_idx, fps, is_real)


class DetectorTrainer:
    """:param input_sizes: the detector's input sizes (H, W), multiples of 32; default: the config's one size."""

    def __init__(self, cfg: ModelConfig, data: DetectorData, aug: AugmentConfig, device: str = "cpu",
                 amp: bool = False, input_sizes: Sequence[tuple[int, int]] | None = None) -> None:
        self.cfg, self.data, self.aug, self.device, self.amp = cfg, data, aug, torch.device(device), amp
        self.input_sizes = [tuple(int(v) for v in hw) for hw in (input_sizes or [cfg.detector.input_hw])]
        for h, w in self.input_sizes:
            if h <= 0 or w <= 0 or h % 32 or w % 32:
                raise ValueError(f"detector input sizes must be positive multiples of 32, got {h}x{w}")
        self.detector = build_detector(cfg.detector).to(self.device)
        self.loss = DetectorLoss(self.detector)

    @property
    def nets(self) -> dict[str, torch.nn.Module]:
        return {"detector": self.detector}

    def input_hw_of(self, i: int) -> tuple[int, int]:
        """The input size the runtime runs frame `i` at."""
        return choose_input_hw(self.data.samples.images[i].shape[:2], self.input_sizes)

    def batch(self, idx: np.ndarray, rng: np.random.Generator | None,
              input_hw: tuple[int, int] | None = None) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Frames `idx` drawn into one input size (default: the first frame's), augmented (rng given) or
        letterboxed as the runtime does: (B, 3, H, W) float in [0, 1], B targets (n_i, 5) cls+xyxy."""
        s = self.data.samples
        hw = input_hw or self.input_hw_of(int(idx[0]))
        images, targets = [], []
        for i in idx:
            img, boxes = s.images[i], np.asarray(s.boxes[i], np.float32).reshape(-1, 4)
            if rng is not None:
                a = self.aug
                img, boxes = place_in_window(img, boxes, hw, rng, a.zoom_range, a.zoom_in_max, a.shift_fraction)
                img = augment_rgb(img, rng, a)
                if rng.random() < a.flip_prob:
                    img, boxes = flip_horizontal(img, boxes)
            else:
                img, lb = letterbox(img, hw)
                boxes = boxes.copy()
                boxes[:, [0, 2]] = boxes[:, [0, 2]] * lb.scale_x + lb.pad_x
                boxes[:, [1, 3]] = boxes[:, [1, 3]] * lb.scale_y + lb.pad_y
            images.append(img)
            t = np.zeros((len(boxes), 5), np.float32)   # class 0: pallet; -1: a real box, type unknown
            t[:, 0] = -1.0 if self.data.real[i] else 0.0
            t[:, 1:] = boxes
            targets.append(torch.from_numpy(t).to(self.device))
        x = torch.from_numpy(np.stack(images)).to(self.device).permute(0, 3, 1, 2).float().div_(255.0)
        return x.contiguous(), targets

    def step(self, idx: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, dict]:
        frames = self.data.train_idx[idx]
        hw = self.input_hw_of(int(frames[0])) if rng.random() < OWN_SIZE_PROB else \
            self.input_sizes[int(rng.integers(len(self.input_sizes)))]
        x, targets = self.batch(frames, rng, hw)
        with autocast(self.device.type, self.amp):
            raw = self.detector.forward_raw(x)
        loss, parts = self.loss([r.float() for r in raw], targets)
        return loss, {k: float(v) for k, v in parts.items() if k != "fg"}

    @torch.no_grad()
    def validate(self, batch: int = 8, score_threshold: float = 0.25, iou: float = 0.5) -> dict:
        """Validation loss over all validation frames; precision/recall over the simulated ones, and (`_real`)
        over the real ones when there are any."""
        idx_all = self.data.val_idx
        sizes = [self.input_hw_of(int(i)) for i in idx_all]
        groups = [idx_all[[k for k, hw in enumerate(sizes) if hw == size]] for size in dict.fromkeys(sizes)]
        chunks = [g[i:i + batch] for g in groups for i in range(0, len(g), batch)]   # one input size per batch
        total = 0.0
        counts = {False: [0, 0, 0], True: [0, 0, 0]}   # real? -> tp, n_pred, n_gt
        for idx in chunks:
            x, targets = self.batch(idx, None)
            raw = self.detector.forward_raw(x)
            loss, _ = self.loss(raw, targets)
            total += float(loss) * len(idx)
            decoded = self.detector.head.decode(raw).cpu().numpy()
            for k, t in enumerate(targets):
                det = decode_yolov8(decoded[k], score_threshold, 0.5, tuple(range(self.detector.head.nc)), 300)
                gt = t[:, 1:].cpu().numpy()
                c = counts[bool(self.data.real[idx[k]])]
                c[1], c[2] = c[1] + len(det.boxes_xyxy), c[2] + len(gt)
                if len(det.boxes_xyxy) and len(gt):
                    m = box_iou(det.boxes_xyxy, gt) >= iou
                    used: set[int] = set()
                    for row in m:   # decode returns boxes by descending score
                        j = next((j for j in np.flatnonzero(row) if j not in used), None)
                        if j is not None:
                            used.add(int(j))
                    c[0] += len(used)
        loss = total / max(len(idx_all), 1)
        out = {"metric": loss, "loss": loss}
        for is_real, suffix in ((False, ""), (True, "_real")):
            tp, n_pred, n_gt = counts[is_real]
            if is_real and n_gt == 0 and n_pred == 0:
                continue
            out.update({f"precision{suffix}": tp / n_pred if n_pred else 0.0,
                        f"recall{suffix}": tp / n_gt if n_gt else 0.0, f"n_gt{suffix}": n_gt})
        return out


def train_detector(cfg: ModelConfig, data: Sequence[str | Path], run_dir: str | Path, settings: LoopSettings,
                   aug: AugmentConfig | None = None, resume: bool = False, cache_dir: str | Path | None = None,
                   val_fraction: float = 0.1, max_frames: int | None = None, command: str = "",
                   progress: bool = True, init: str | Path | None = None, real: str | Path | None = None,
                   real_max_images: int | None = None, input_sizes: Sequence[tuple[int, int]] | None = None) -> dict:
    """Train the detector on BOP datasets (and the train split of imported real photographs, `real`);
    checkpoints and the log go to `run_dir`. Returns the last log entry."""
    run_dir = Path(run_dir)
    aug = aug or AugmentConfig()
    torch.manual_seed(settings.seed)
    dd = load_detector_data(cfg, data, settings.seed, cache_dir if cache_dir is not None else run_dir / "cache",
                            val_fraction, max_frames, progress, real, real_max_images)
    trainer = DetectorTrainer(cfg, dd, aug, settings.device, amp=settings.amp, input_sizes=input_sizes)
    # YOLOv8 practice: no weight decay on BatchNorm weights and biases
    decay = [p for n, p in trainer.detector.named_parameters() if p.ndim > 1]
    no_decay = [p for n, p in trainer.detector.named_parameters() if p.ndim <= 1]
    optimizer = torch.optim.AdamW([{"params": decay, "weight_decay": 5e-4}, {"params": no_decay, "weight_decay": 0.0}],
                                  lr=settings.lr, betas=(0.937, 0.999))
    provenance = {"stage": "detector", "config": cfg.name, "input_hw": list(cfg.detector.input_hw),
                  "input_sizes": [list(hw) for hw in trainer.input_sizes],
                  "seed": settings.seed, "command": command,
                  "data": dd.fingerprints, "epochs": settings.epochs, "batch": settings.batch, "lr": settings.lr,
                  "augment": aug.to_dict(), "val_fraction": val_fraction,
                  "samples": {"train": int(len(dd.train_idx)), "val": int(len(dd.val_idx)),
                              "real": int(dd.real.sum())},
                  "device": settings.device, "amp": "bf16" if settings.amp else None, "torch": str(torch.__version__)}
    return train_epochs(run_dir, "detector", cfg.name, trainer.nets, optimizer, settings, len(dd.train_idx),
                        trainer.step, trainer.validate, provenance, resume=resume, progress=progress, init=init)
