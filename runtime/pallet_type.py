"""A pallet type of a bundle: one geometry, the detector class that reports it, its model points, boards and
blocks, symmetries, fork pockets and ICP starts (schema of `manifest.json`'s `pallet_types`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

import numpy as np

from .manifest_fields import BundleError, FieldError, Fields, frozen_array, nonempty_name, positive, relative_name
from .pallet_geometry import FACES, asymmetric, check_rigid
from .refine import offsets_from_starts

__all__ = ["PalletType"]

# geometry may stick out of the size's box by this much (rounding of the written numbers)
_GEOMETRY_TOL_M = 1e-4


@dataclass(frozen=True, eq=False)
class PalletType:
    """One pallet geometry of a bundle, in the pallet frame (origin at the bounding box's centre, x along the
    length, y along the width, z up; metres).

    :ivar class_id: the detector class that reports this type.
    :ivar size_m: (3,) length, width, height. :ivar diameter_m: largest distance between two model points.
    :ivar points_file: bundle file of the (n, 3) float32 model points (`points()` once loaded by `load_bundle`).
    :ivar boxes_m: (k, 2, 3) min/max corners of the boards/blocks/runners, or None (no ICP refinement).
    :ivar symmetries: (S, 4, 4) rigid transforms that leave the pallet unchanged, identity first.
    :ivar pockets_m: face ("+x", "-x", "+y", "-y") -> (2, 2, 3) min/max corners of its two fork openings,
        left then right seen from outside; faces without openings are absent.
    :ivar refine_starts: (S, 3) extra ICP starts, rows of (yaw degrees, dx metres along x, dy metres along y).
    """

    name: str
    class_id: int
    size_m: tuple[float, float, float]
    diameter_m: float
    points_file: str
    symmetries: np.ndarray
    boxes_m: np.ndarray | None = None
    pockets_m: Mapping[str, np.ndarray] = field(default_factory=dict)
    refine_starts: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    points_m: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        nonempty_name("name", self.name)
        relative_name("points_file", self.points_file)
        if isinstance(self.class_id, bool) or not isinstance(self.class_id, (int, np.integer)) or self.class_id < 0:
            raise FieldError("class_id", f"must be an integer >= 0, got {self.class_id!r}")
        size = tuple(float(v) for v in self.size_m)
        if len(size) != 3:
            raise FieldError("size_m", f"must be 3 numbers, got {self.size_m!r}")
        for v in size:
            positive("size_m", v)
        half = np.asarray(size) / 2 + _GEOMETRY_TOL_M
        positive("diameter_m", self.diameter_m)
        if not max(size) - _GEOMETRY_TOL_M <= self.diameter_m <= float(np.linalg.norm(size)) + _GEOMETRY_TOL_M:
            raise FieldError("diameter_m", f"{self.diameter_m} does not fit size_m {list(size)} (between the longest "
                                           f"side and the diagonal)")
        sym = frozen_array(self.symmetries)
        if sym.ndim != 3 or sym.shape[1:] != (4, 4) or len(sym) == 0:
            raise FieldError("symmetries", f"must be (S, 4, 4) with S >= 1, got shape {sym.shape}")
        if not np.allclose(sym[0], np.eye(4)):
            raise FieldError("symmetries", "must start with the identity")
        bad = check_rigid(sym)
        if bad:
            raise FieldError("symmetries", f"[{bad[0]}] is not a rigid transform (rotation with det +1, last row "
                                           "0 0 0 1)")
        boxes = None if self.boxes_m is None else frozen_array(self.boxes_m)
        if boxes is not None:
            if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0:
                raise FieldError("boxes_m", f"must be (k, 2, 3) min/max corners, got shape {boxes.shape}")
            if not np.all(np.isfinite(boxes)) or np.any(boxes[:, 1] <= boxes[:, 0]):
                raise FieldError("boxes_m", "must be finite min/max corners with max > min")
            if np.any(np.abs(boxes) > half):
                raise FieldError("boxes_m", f"reach outside size_m {list(size)} around the origin")
            wrong = asymmetric(sym, boxes)
            if wrong:
                raise FieldError("symmetries", f"[{wrong[0]}] does not map the pallet's boxes_m onto themselves")
        pockets = {}
        for face, corners in dict(self.pockets_m).items():
            arr = frozen_array(corners)
            key = f"pockets_m.{face}"
            if face not in FACES:
                raise FieldError("pockets_m", f"has face {face!r}; faces are {', '.join(FACES)}")
            if arr.shape != (2, 2, 3) or not np.all(np.isfinite(arr)) or np.any(arr[:, 1] <= arr[:, 0]):
                raise FieldError(key, f"must be (2, 2, 3) finite min/max corners with max > min, got shape {arr.shape}")
            if np.any(np.abs(arr) > half):
                raise FieldError(key, f"reaches outside size_m {list(size)} around the origin")
            pockets[face] = arr
        starts = frozen_array(self.refine_starts).reshape(-1, 3) if np.size(self.refine_starts) == 0 \
            else frozen_array(self.refine_starts)
        if starts.ndim != 2 or starts.shape[1] != 3 or not np.all(np.isfinite(starts)):
            raise FieldError("refine_starts", f"must be (S, 3) rows of (yaw_deg, dx_m, dy_m), got shape {starts.shape}")
        if np.any(np.abs(starts[:, 0]) > 180) or np.any(np.abs(starts[:, 1]) > size[0]) \
                or np.any(np.abs(starts[:, 2]) > size[1]):
            raise FieldError("refine_starts", f"must turn by at most 180 degrees and slide by at most the pallet's "
                                              f"length / width {size[:2]}")
        if self.points_m is not None:
            pts = frozen_array(self.points_m, np.float32)
            if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
                raise FieldError("points_file", f"must hold (n, 3) model points, got shape {pts.shape}")
            if not np.all(np.isfinite(pts)):
                raise FieldError("points_file", "holds model points that are not finite")
            if np.any(np.abs(pts) > half):
                raise FieldError("points_file", f"holds model points outside size_m {list(size)} around the origin")
            object.__setattr__(self, "points_m", pts)
        for key, value in (("class_id", int(self.class_id)), ("size_m", size), ("diameter_m", float(self.diameter_m)),
                           ("symmetries", sym), ("boxes_m", boxes), ("pockets_m", MappingProxyType(pockets)),
                           ("refine_starts", starts)):
            object.__setattr__(self, key, value)

    def points(self) -> np.ndarray:
        """(n, 3) float32 model points in the pallet frame, metres (read-only)."""
        if self.points_m is None:
            raise BundleError(f"pallet type {self.name!r}: its model points are not loaded (use load_bundle)")
        return self.points_m

    def start_offsets(self, n: int | None = None) -> np.ndarray:
        """The first `n` (default all) of `refine_starts` as (n, 4, 4) pallet-frame offsets (a yaw about z, then
        a slide along x and y), to right-multiply a pose."""
        rows = self.refine_starts if n is None else self.refine_starts[:int(n)]
        return offsets_from_starts(rows)

    @classmethod
    def from_fields(cls, t: Fields) -> "PalletType":
        pockets_raw = t.get("pockets_m", dict)
        pockets = {}
        for face, value in pockets_raw.items():
            pockets[face] = Fields({face: value}, t.path("pockets_m"), t.source).array(face)
        return t.build(cls, name=t.str("name"), class_id=t.int("class_id"), size_m=t.nums("size_m", 3),
                       diameter_m=t.num("diameter_m"), points_file=t.str("points_file"),
                       boxes_m=t.array("boxes_m", None), symmetries=t.array("symmetries"), pockets_m=pockets,
                       refine_starts=t.array("refine_starts"))

    def to_dict(self) -> dict:
        return {"name": self.name, "class_id": self.class_id, "size_m": list(self.size_m),
                "diameter_m": self.diameter_m, "points_file": self.points_file,
                "boxes_m": None if self.boxes_m is None else self.boxes_m.tolist(),
                "symmetries": self.symmetries.tolist(),
                "pockets_m": {face: v.tolist() for face, v in self.pockets_m.items()},
                "refine_starts": self.refine_starts.tolist()}

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PalletType):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]
