"""The pallet types a bundle carries, built from the simulator's pallet catalogue (`pallet6d.sim.pallets`).

Pose training records ``{"obj_id": name}`` of every type in its data (provenance ``pallet_types``; a merged
checkpoint keeps it under ``provenance["pose"]``): by default a bundle carries the types its pose stage was
trained on, in obj_id order (the first is the bundle's default `pallet`).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pallet6d.runtime.manifest import PalletType
from pallet6d.runtime.pallet_geometry import default_refine_starts, derive_pockets_m
from pallet6d.sim.pallets import PALLET_MODELS, PalletModel, get_pallet_model

from .export_inputs import ExportError

__all__ = ["MODEL_POINTS", "parse_pallet_types", "trained_pallet_types", "trained_pallet_models", "class_ids_for_types",
           "write_pallet_types"]

log = logging.getLogger(__name__)

MODEL_POINTS = 2000   # model points per type: the fit score's model and the ADD metric's


def parse_pallet_types(text: str) -> tuple[str, ...]:
    """"epal,eur3" -> ("epal", "eur3"), each a known sim pallet model, none twice. :raises ExportError:"""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in PALLET_MODELS]
    if not names or unknown:
        raise ExportError(f"--pallet-types: unknown pallet type(s) {unknown or text!r}; known: {', '.join(PALLET_MODELS)}")
    if len(set(names)) != len(names):
        raise ExportError(f"--pallet-types: a type is named twice in {text!r}")
    return names


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


def class_ids_for_types(names: tuple[str, ...], classes: tuple[str, ...], external: bool) -> tuple[int, ...]:
    """The detector class of each pallet type.

    Our own detector has one class for every type (the runtime tells the types apart by the depth), or one
    class per type: the class named after it, else (classes named otherwise) the types in order. An external
    detector's
    class that reports a type is the one with the type's name; a single type in a detector without such a class
    is its first class whose name says "pallet" (class 0 when none does).

    :raises ExportError: the classes and the types do not match.
    """
    if not external:
        if len(classes) == 1:
            return (0,) * len(names)
        if all(n in classes for n in names):
            return tuple(classes.index(n) for n in names)
        if len(classes) != len(names):
            raise ExportError(f"the detector has {len(classes)} classes {list(classes)} but {len(names)} pallet "
                              f"types {list(names)} were asked for")
        return tuple(range(len(names)))
    lowered = [c.lower() for c in classes]
    if len(names) == 1 and names[0].lower() not in lowered:
        return (next((i for i, c in enumerate(lowered) if "pallet" in c), 0),)
    missing = [n for n in names if n.lower() not in lowered]
    if missing:
        raise ExportError(f"the external detector has no class named {missing[0]!r} (its classes: {list(classes)})")
    return tuple(lowered.index(n.lower()) for n in names)


def write_pallet_types(names: tuple[str, ...], class_ids: tuple[int, ...], out: Path) -> tuple[PalletType, ...]:
    """Write each type's model points to `out/pallets/<name>.npy` and describe it.

    Fork pockets and ICP starts come from the sim model where it defines them; else the pockets its boards
    and blocks leave open and the default starts scaled to its size.
    """
    (out / "pallets").mkdir(parents=True, exist_ok=True)
    types = []
    for name, class_id in zip(names, class_ids):
        model = get_pallet_model(name)
        rel = f"pallets/{name}.npy"
        np.save(out / rel, model.surface_points(MODEL_POINTS, seed=0).astype(np.float32))
        pockets = getattr(model, "pockets_m", None)
        starts = getattr(model, "refine_starts", None)
        types.append(PalletType(
            name=name, class_id=class_id, size_m=tuple(float(v) for v in model.size_m),
            diameter_m=float(model.diameter_m), points_file=rel, symmetries=np.asarray(model.symmetries),
            boxes_m=np.round(np.asarray(model.boxes_m), 6),
            pockets_m=derive_pockets_m(model.boxes_m) if pockets is None else dict(pockets),
            refine_starts=default_refine_starts(model.size_m) if starts is None else np.asarray(starts)))
        log.info("pallet type %s: detector class %d, %d fork faces", name, class_id, len(types[-1].pockets_m))
    return tuple(types)
