"""Detector training samples from the imported real photographs (`real_data.py`): the photographs themselves
(longest side capped), read from their files at every run (decoding them costs seconds, a cache would cost GB).

Only the `train` split is ever read here: the held-out split is for `benchmarks/real_data.py` alone. The train
split is cut again by capture sequence into training and validation images, so validation never sees a
neighbouring frame of a training image. Boxes whose convention is not the detector's (`loaded_unit`) are left
out unless asked for; pallet-free photos are kept as frames without boxes.
"""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from .real_data import ImageRecord, load_records, sequence_of, split_by_sequence
from .train_data import DetectorSamples, _objects, cap_image

__all__ = ["real_train_val", "build_real_samples", "load_real_samples"]

log = logging.getLogger(__name__)

VAL_WINDOW_S = 600   # capture-time window kept together by the validation cut


def real_train_val(records: Sequence[ImageRecord], val_fraction: float, conventions: Sequence[str] = ("whole_pallet",),
                   max_images: int | None = None, seed: int = 0,
                   keep_kinds: Sequence[str] = ()) -> tuple[list[ImageRecord], list[ImageRecord]]:
    """The train split's usable records, cut by sequence into (train, validation).

    :param max_images: keep at most this many (an even subsample, deterministic in `seed`), before the cut.
    :param keep_kinds: photos showing one of these pallet kinds (e.g. "plastic", rare among the sources) are always
        among the `max_images`; the subsample draws the rest.
    """
    recs = [r for r in records if r.split == "train" and (r.convention in conventions or r.negative)]
    if max_images is not None and len(recs) > max_images:
        always = np.array([bool(set(r.kinds) & set(keep_kinds)) for r in recs], bool)
        rest = np.flatnonzero(~always)
        drawn = np.random.default_rng(seed).choice(len(rest), max(max_images - int(always.sum()), 0), replace=False)
        keep = np.sort(np.concatenate([np.flatnonzero(always), rest[drawn]]))
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


def build_real_samples(root: str | Path, records: Sequence[ImageRecord], max_side: int) -> DetectorSamples:
    """Every record's photograph, longest side capped at `max_side`; boxes in its pixels. `frame` is the
    record's index."""
    import cv2

    root = Path(root)
    images, boxes = [], []
    for r in records:
        if r.split != "train":
            raise ValueError(f"{r.image}: only the train split may be used for training, got split {r.split!r}")
        bgr = cv2.imread(str(root / r.image), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"cannot read {root / r.image}")
        img, scale = cap_image(np.ascontiguousarray(bgr[:, :, ::-1]), max_side)
        images.append(img)
        boxes.append((r.box_array() * scale).astype(np.float32))
    return DetectorSamples(_objects(images), _objects(boxes), np.arange(len(records), dtype=np.int64))


def load_real_samples(root: str | Path, max_side: int, val_fraction: float, max_images: int | None = None,
                      seed: int = 0, keep_kinds: Sequence[str] = ()
                      ) -> tuple[DetectorSamples, DetectorSamples, dict, np.ndarray]:
    """(train samples, validation samples, fingerprint, which train samples show one of `keep_kinds`) of the
    imported real data under `root`."""
    root = Path(root)
    labels = root / "labels.json"
    records = load_records(root)
    sha = hashlib.sha256(labels.read_bytes()).hexdigest()
    train, val = real_train_val(records, val_fraction, max_images=max_images, seed=seed, keep_kinds=keep_kinds)
    parts = [build_real_samples(root, recs, max_side) for recs in (train, val)]
    log.info("real frames: %d train, %d val", len(parts[0]), len(parts[1]))
    fp = {"root": str(root.resolve()), "labels_sha256": sha, "max_side": max_side, "val_fraction": val_fraction,
          "max_images": max_images, "seed": seed, **({"keep_kinds": list(keep_kinds)} if keep_kinds else {})}
    kept = np.array([bool(set(r.kinds) & set(keep_kinds)) for r in train], bool)
    return parts[0], parts[1], {**fp, "train": len(parts[0]), "val": len(parts[1])}, kept
