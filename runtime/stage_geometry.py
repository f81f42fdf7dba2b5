"""The pallet geometry the refiner and the fit check need, per pallet type of a bundle (numpy only).

A bundle's detector class reports one pallet type, or several (`Bundle.pallet_types`: a detector trained on
photographs without type labels has one class, "pallet", for all of them; `stage_type` then picks the type by
its fit to the depth). Each candidate is refined, symmetry-checked and fit-checked with its own type's model.
`PalletGeometry` holds one type's arrays, ready for the stages (float64, loaded once); `bundle_geometries`
reads them from a bundle together with the types each detector class reports.
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
    :ivar refine_starts: (S, 3) float64 extra ICP starts, rows of (yaw_deg, dx_m, dy_m), most useful first.
    """

    name: str
    points_m: np.ndarray
    boxes_m: np.ndarray | None
    symmetries: np.ndarray
    size_m: np.ndarray
    refine_starts: np.ndarray

    @classmethod
    def from_type(cls, t) -> "PalletGeometry":
        """From a bundle's `PalletType` (model points loaded)."""
        boxes = None if t.boxes_m is None else np.asarray(t.boxes_m, dtype=np.float64)
        return cls(name=str(t.name), points_m=np.asarray(t.points(), dtype=np.float64), boxes_m=boxes,
                   symmetries=np.asarray(t.symmetries, dtype=np.float64), size_m=np.asarray(t.size_m, dtype=np.float64),
                   refine_starts=np.asarray(t.refine_starts, dtype=np.float64).reshape(-1, 3))


def bundle_geometries(bundle, site_types: tuple[str, ...] | None = None
                      ) -> tuple[tuple[PalletGeometry, ...], dict[int, tuple[int, ...]]]:
    """Every pallet type of a bundle and which detector class reports which types.

    :param site_types: names of the types to pose (`EstimatorOptions.pallet_types`); None: all of them.
    :return: (geometries in the bundle's order, {detector class id: indexes into geometries, in the bundle's
        order}); a detector class without a type (an external detector's other classes) or whose types are not
        among `site_types` is absent.
    :raises ValueError: a name in `site_types` is not one of the bundle's types.
    """
    geometries = tuple(PalletGeometry.from_type(t) for t in bundle.pallet_types)
    names = [g.name for g in geometries]
    if site_types is not None:
        unknown = sorted(set(site_types) - set(names))
        if unknown:
            raise ValueError(f"pallet types {unknown} are not in bundle {bundle.name} (its types: {', '.join(names)})")
    types_of_class: dict[int, tuple[int, ...]] = {}
    for i, t in enumerate(bundle.pallet_types):
        if site_types is None or names[i] in site_types:
            types_of_class[int(t.class_id)] = types_of_class.get(int(t.class_id), ()) + (i,)
    return geometries, types_of_class
