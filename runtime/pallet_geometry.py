"""The pallet geometry the refiner and the fit check need, per pallet type of a bundle (numpy only).

A bundle's detector reports one class per pallet type; each candidate is posed, refined, symmetry-checked
and fit-checked with its own type's model. `PalletGeometry` holds one type's arrays, ready for the stages
(float64, loaded once); `bundle_geometries` reads them from a bundle together with the detector classes
that report each type.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PalletGeometry", "bundle_geometries"]


@dataclass(frozen=True)
class PalletGeometry:
    """One pallet type's model, pallet frame, metres.

    :ivar name: the type's name (e.g. "epal").
    :ivar points_m: (n, 3) float64 model surface points (fit check, metrics).
    :ivar boxes_m: (k, 2, 3) float64 min/max corners of its boards/blocks, or None (then no refinement).
    :ivar symmetries: (S, 4, 4) float64, identity first.
    :ivar size_m: (3,) float64 length, width, height.
    """

    name: str
    points_m: np.ndarray
    boxes_m: np.ndarray | None
    symmetries: np.ndarray
    size_m: np.ndarray

    @classmethod
    def from_spec(cls, spec) -> "PalletGeometry":
        """From a bundle's pallet type (anything with `name`, `points()`, `boxes_m`, `symmetries`, `size_m`)."""
        boxes = None if spec.boxes_m is None else np.asarray(spec.boxes_m, dtype=np.float64)
        return cls(name=str(spec.name), points_m=np.asarray(spec.points(), dtype=np.float64), boxes_m=boxes,
                   symmetries=np.asarray(spec.symmetries, dtype=np.float64),
                   size_m=np.asarray(spec.size_m, dtype=np.float64))


def bundle_geometries(bundle) -> tuple[tuple[PalletGeometry, ...], dict[int, int]]:
    """Every pallet type of a bundle and which detector class reports which type.

    :return: (geometries, {detector class id: index into geometries}) for the detector's pallet classes.
        A bundle with one pallet model maps its pallet classes (names containing "pallet", or every class
        when none does: a detector from another toolchain may know more classes than pallets) to it.
    """
    types = getattr(bundle, "pallet_types", None)
    if types:
        geometries = tuple(PalletGeometry.from_spec(t) for t in types)
        return geometries, {int(t.class_id): i for i, t in enumerate(types)}
    names = [c.lower() for c in bundle.classes]
    pallet_ids = tuple(i for i, c in enumerate(names) if "pallet" in c) or tuple(range(len(names)))
    return (PalletGeometry.from_spec(bundle.pallet),), {i: 0 for i in pallet_ids}
