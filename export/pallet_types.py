"""The pallet types a pose stage was trained on, as the exporter writes them into a bundle.

Pose training records ``{"obj_id": name}`` of every type in its data (`train_pose`, provenance
``pallet_types``; a merged checkpoint keeps it under ``provenance["pose"]``). The bundle carries one pallet
type per trained type, in obj_id order (the first is the bundle's default `pallet`).
"""
from __future__ import annotations

from pallet6d.sim.pallets import PalletModel, get_pallet_model

__all__ = ["trained_pallet_types", "trained_pallet_models"]


def trained_pallet_types(training: dict | None, default: str) -> tuple[str, ...]:
    """Type names in obj_id order from a checkpoint's training provenance; ``(default,)`` when it records none
    (checkpoints of single-type training, random-init exports).

    :raises ValueError: a recorded type that `sim.pallets` does not know.
    """
    record = None
    if isinstance(training, dict):
        record = training.get("pallet_types")
        if record is None and isinstance(training.get("pose"), dict):
            record = training["pose"].get("pallet_types")
    if not record:
        return (default,)
    names = tuple(name for _, name in sorted(((int(k), str(v)) for k, v in record.items())))
    for name in names:
        get_pallet_model(name)   # raises for a type with no model
    return names


def trained_pallet_models(training: dict | None, default: str) -> list[PalletModel]:
    """`trained_pallet_types` as the models (geometry, symmetries) the bundle's pallet types are written from."""
    return [get_pallet_model(n) for n in trained_pallet_types(training, default)]
