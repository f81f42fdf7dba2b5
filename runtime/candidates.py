"""`Candidates`: the one record the estimator's stages pass on, one row per detection (struct of arrays).

The detector stage makes it from its detections (highest score first); each later stage fills its own
fields for the rows still alive and sets `reason` for the rows it gives up on. A row whose `reason` is
empty is alive; a row with a reason never becomes an accepted pose. Rows are selected with a boolean
mask or an index array (`cands[mask]`, a copy) and written back with `assign(idx, field=values)`.

Fields (n rows, N sampled points per row):

- `boxes_xyxy` (n, 4) float64 image pixels; `scores` (n,) float64; `class_ids` (n,) int64 detector classes;
- `type_index` (n,) int64: the row's pallet type, an index into the estimator's `pallet_types`;
- `type_options` (n,) object: each row's tuple of the type indexes it may be (the type choice picks one where
  there are several);
- `n_valid` (n,) int64 valid depth pixels in the box; `points_cam` (n, N, 3) float64 the sampled points,
  camera frame, metres; `pixels` (n,) object: each row's candidate depth pixels, a (v, u) pair of int64
  arrays (rows, columns; row-major), selected once and reused by the refiner;
- `T_net` (n, 4, 4) the pose network's pose; `confidence` (n,) its per-point confidence;
- `T_cam_pallet` (n, 4, 4) the pose after refinement (the network's when not refined);
- `fit` (n, 3) float64 inlier fraction, free-space violation, score of `T_cam_pallet` (NaN: not computed);
- `reason` (n,) object: "" alive, else a `results.REJECT_REASONS` code; `detail` (n,) object: its sentence.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

__all__ = ["Candidates"]


@dataclass
class Candidates:
    """Per-detection state of one frame, one row per detection (module docstring)."""

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    class_ids: np.ndarray
    type_index: np.ndarray
    type_options: np.ndarray
    n_valid: np.ndarray
    points_cam: np.ndarray
    pixels: np.ndarray
    T_net: np.ndarray
    confidence: np.ndarray
    T_cam_pallet: np.ndarray
    fit: np.ndarray
    reason: np.ndarray
    detail: np.ndarray

    @classmethod
    def new(cls, boxes_xyxy, scores, class_ids, type_index, num_points: int, type_options=None) -> "Candidates":
        """Rows for detections (n, 4) boxes, (n,) scores, (n,) class ids, (n,) type indexes, and n tuples of the
        type indexes each row may be (None: its type index alone); the rest empty."""
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        n = len(boxes)
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        class_ids = np.asarray(class_ids, dtype=np.int64).reshape(-1)
        type_index = np.asarray(type_index, dtype=np.int64).reshape(-1)
        if not len(scores) == len(class_ids) == len(type_index) == n:
            raise ValueError(f"Candidates: {n} boxes but {len(scores)} scores, {len(class_ids)} class ids, "
                             f"{len(type_index)} type indexes")
        options = [(int(t),) for t in type_index] if type_options is None else \
            [tuple(int(j) for j in o) for o in type_options]
        if len(options) != n or any(int(t) not in o for t, o in zip(type_index, options)):
            raise ValueError(f"Candidates: {n} boxes need {n} type options, each with its row's type index "
                             f"{type_index.tolist()}, got {options}")
        eye = np.tile(np.eye(4), (n, 1, 1))
        pixels, type_options = np.empty(n, dtype=object), np.empty(n, dtype=object)
        for i in range(n):
            pixels[i] = (np.zeros(0, np.int64), np.zeros(0, np.int64))
            type_options[i] = options[i]
        return cls(boxes, scores, class_ids, type_index, type_options, n_valid=np.zeros(n, np.int64),
                   points_cam=np.zeros((n, int(num_points), 3)), pixels=pixels, T_net=eye,
                   confidence=np.zeros(n), T_cam_pallet=eye.copy(), fit=np.full((n, 3), np.nan),
                   reason=np.full(n, "", dtype=object), detail=np.full(n, "", dtype=object))

    def __post_init__(self) -> None:
        n = len(self.boxes_xyxy)
        for f in fields(self):
            arr = getattr(self, f.name)
            if not isinstance(arr, np.ndarray) or len(arr) != n:
                raise ValueError(f"Candidates.{f.name}: expected an array of {n} rows, got "
                                 f"{getattr(arr, 'shape', type(arr).__name__)}")

    @classmethod
    def concat(cls, parts: list["Candidates"]) -> "Candidates":
        """The rows of `parts`, in order, as one record."""
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    def __len__(self) -> int:
        return len(self.boxes_xyxy)

    def __getitem__(self, idx) -> "Candidates":
        """The rows `idx` (a boolean mask or integer indexes), as a new record (copies)."""
        idx = np.asarray(idx)
        if idx.dtype != bool and not np.issubdtype(idx.dtype, np.integer):
            raise TypeError(f"Candidates: index with a boolean mask or integer indexes, got {idx.dtype}")
        return Candidates(*(getattr(self, f.name)[idx] for f in fields(self)))

    @property
    def alive(self) -> np.ndarray:
        """(n,) bool: rows no stage has rejected."""
        return self.reason == ""

    def assign(self, idx, **values) -> None:
        """Write `values` (field name -> rows) into the rows `idx` of this record."""
        idx = np.asarray(idx)
        for name, value in values.items():
            if name not in self.__dataclass_fields__:
                raise AttributeError(f"Candidates has no field {name!r}")
            target = getattr(self, name)
            if target.dtype == object:
                for i, v in zip(np.arange(len(self))[idx], value):
                    target[i] = v
            else:
                target[idx] = value

    def reject(self, idx, reason: str, details) -> None:
        """Mark the rows `idx` as rejected with `reason`; `details` is one sentence per row (or one for all)."""
        rows = np.arange(len(self))[np.asarray(idx)]
        details = [details] * len(rows) if isinstance(details, str) else list(details)
        if len(details) != len(rows):
            raise ValueError(f"reject: {len(rows)} rows but {len(details)} details")
        for i, d in zip(rows, details):
            self.reason[i], self.detail[i] = reason, d
