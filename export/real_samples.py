"""Detector training samples from the imported real photographs (`real_data.py`): letterboxed, cached.

Only the `train` split is ever read here: the held-out split is for `benchmarks/real_data.py` alone. The train
split is cut again by capture sequence into training and validation images, so validation never sees a
neighbouring frame of a training image. Boxes whose convention is not the detector's (`loaded_unit`) are left
out unless asked for; pallet-free photos are kept as frames without boxes.
"""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from pallet6d.runtime.detector import letterbox

from .real_data import ImageRecord, load_records, sequence_of, split_by_sequence
from .train_data import DetectorSamples

__all__ = ["real_train_val", "build_real_samples", "load_real_samples"]

log = logging.getLogger(__name__)

VAL_WINDOW_S = 600   # capture-time window kept together by the validation cut


def real_train_val(records: Sequence[ImageRecord], val_fraction: float, conventions: Sequence[str] = ("whole_pallet",),
                   max_images: int | None = None, seed: int = 0) -> tuple[list[ImageRecord], list[ImageRecord]]:
    """The train split's usable records, cut by sequence into (train, validation).

    :param max_images: keep at most this many (an even subsample, deterministic in `seed`), before the cut.
    """
    recs = [r for r in records if r.split == "train" and (r.convention in conventions or r.negative)]
    if max_images is not None and len(recs) > max_images:
        keep = np.sort(np.random.default_rng(seed).choice(len(recs), max_images, replace=False))
        recs = [recs[i] for i in keep]
    if val_fraction <= 0 or len(recs) < 2:
        return recs, []
    split = split_by_sequence([validation_unit(r) for r in recs], val_fraction, salt=f"val{seed}")
    return ([r for r, s in zip(recs, split) if s == "train"], [r for r, s in zip(recs, split) if s == "heldout"])


def validation_unit(rec: ImageRecord, window_s: int = VAL_WINDOW_S) -> str:
    """What the validation cut keeps together: the record's sequence, narrowed to a `window_s` window of capture
    time where the stem carries one (a whole LOCO capture day would take a third of the training images)."""
    head = rec.stem.split("-")[0]
    if sequence_of(rec.stem, "capture-day") is None:
        return rec.sequence
    t = int(head) / (1000.0 if len(head) == 13 else 1.0)
    return f"{rec.sequence}/{int(t // window_s)}"


def build_real_samples(root: str | Path, records: Sequence[ImageRecord], input_hw: tuple[int, int]) -> DetectorSamples:
    """Letterbox every record's image to `input_hw`; boxes in input pixels. `frame` is the record's index."""
    import cv2

    root = Path(root)
    images = np.empty((len(records), *input_hw, 3), np.uint8)
    boxes = np.empty(len(records), dtype=object)
    for i, r in enumerate(records):
        if r.split != "train":
            raise ValueError(f"{r.image}: only the train split may be used for training, got split {r.split!r}")
        bgr = cv2.imread(str(root / r.image), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"cannot read {root / r.image}")
        img, lb = letterbox(np.ascontiguousarray(bgr[:, :, ::-1]), input_hw)
        images[i] = img
        b = r.box_array().copy()
        b[:, [0, 2]] = b[:, [0, 2]] * lb.scale_x + lb.pad_x
        b[:, [1, 3]] = b[:, [1, 3]] * lb.scale_y + lb.pad_y
        boxes[i] = b.astype(np.float32)
    return DetectorSamples(images, boxes, np.arange(len(records), dtype=np.int64))


def load_real_samples(root: str | Path, input_hw: tuple[int, int], val_fraction: float, cache_dir: str | Path | None,
                      max_images: int | None = None, seed: int = 0) -> tuple[DetectorSamples, DetectorSamples, dict]:
    """(train samples, validation samples, fingerprint) of the imported real data under `root`, cached in
    `cache_dir` by the labels file's sha256 and the settings."""
    root = Path(root)
    labels = root / "labels.json"
    records = load_records(root)
    sha = hashlib.sha256(labels.read_bytes()).hexdigest()
    settings = {"input_hw": list(input_hw), "val_fraction": val_fraction, "max_images": max_images, "seed": seed}
    key = hashlib.sha256(json.dumps([sha, settings], sort_keys=True).encode()).hexdigest()[:16]
    fp = {"root": str(root.resolve()), "labels_sha256": sha, **settings}
    path = Path(cache_dir) / f"real_{key}.npz" if cache_dir is not None else None
    if path is not None and path.exists():
        with np.load(path, allow_pickle=True) as z:
            parts = [DetectorSamples(z[f"{p}_images"], z[f"{p}_boxes"], z[f"{p}_frame"]) for p in ("train", "val")]
        log.info("real samples from cache %s", path)
    else:
        train, val = real_train_val(records, val_fraction, max_images=max_images, seed=seed)
        parts = [build_real_samples(root, recs, input_hw) for recs in (train, val)]
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, **{f"{p}_{f}": getattr(s, f) for p, s in zip(("train", "val"), parts)
                             for f in ("images", "boxes", "frame")})
            tmp.replace(path)
    log.info("real frames: %d train, %d val", len(parts[0]), len(parts[1]))
    return parts[0], parts[1], {**fp, "train": len(parts[0]), "val": len(parts[1])}
