"""Pallet-free scenes for measuring false accepts: a scene's pallets removed, their loads set down or left hanging.

A scene without its pallets is the negative a pose estimator must refuse. Left where they were, the loads hang over
pallet-shaped gaps (a hard negative, but one no warehouse shows); set down, each load drops by the height of the
pallets it stood on, onto what held them (the floor, a rack beam, a truck bed), as a carton stack stands where no
pallet is under it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .scene import Box

__all__ = ["without_pallets", "render_pallet_free", "generate_pallet_free_frame", "LOADS"]

_CONTACT_M = 0.02          # a box within this of a surface below it stands on it
LOADS = ("set-down", "hanging")   # where a pallet-free scene's loads go


def _aabb(b: Box) -> tuple[np.ndarray, np.ndarray]:
    """World-frame axis-aligned bounds (lo (3,), hi (3,)) of a box."""
    ext = np.abs(b.T_world_box[:3, :3]) @ b.half_size_m
    c = b.T_world_box[:3, 3]
    return c - ext, c + ext


def without_pallets(boxes: list[Box], set_down: bool = True) -> list[Box]:
    """The scene's boxes without its pallets' parts (`instance_id` > 0).

    :param set_down: a box standing on a pallet (its underside within 2 cm of the pallet's top, its centre over the
        pallet's footprint) drops by the height of that pallet and of the pallets it stood on in turn (a stack),
        and every box standing on a dropped box drops with it. False: every box stays where it was.
    :return: the background boxes, in their order.
    """
    pallets: dict[int, list[np.ndarray]] = {}
    for b in boxes:
        if b.instance_id > 0:
            lo, hi = _aabb(b)
            p = pallets.setdefault(b.instance_id, [lo, hi])
            p[0], p[1] = np.minimum(p[0], lo), np.maximum(p[1], hi)
    rest = [b for b in boxes if b.instance_id == 0]
    if not set_down or not pallets:
        return rest
    bounds = list(pallets.values())

    def support_drop(x: float, y: float, z: float) -> float:
        """How far a point at (x, y) resting at height z falls through a chain of removed pallets (0: none)."""
        bottom = z
        while True:
            below = [lo[2] for lo, hi in bounds if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]
                     and abs(hi[2] - bottom) <= _CONTACT_M]
            if not below:
                return z - bottom
            bottom = min(below)

    aabbs = [_aabb(b) for b in rest]
    drop = np.zeros(len(rest))
    for i, (lo, hi) in enumerate(aabbs):
        c = (lo + hi) / 2
        drop[i] = support_drop(c[0], c[1], lo[2])
    changed = True
    while changed:                            # boxes standing on a dropped box fall with it
        changed = False
        for i, (lo, hi) in enumerate(aabbs):
            if drop[i] > 0:
                continue
            c = (lo + hi) / 2
            for j, (lo_j, hi_j) in enumerate(aabbs):
                if (drop[j] > 0 and j != i and lo_j[0] <= c[0] <= hi_j[0] and lo_j[1] <= c[1] <= hi_j[1]
                        and abs(hi_j[2] - lo[2]) <= _CONTACT_M):
                    drop[i], changed = drop[j], True
                    break
    out = []
    for b, d in zip(rest, drop):
        if d > 0:
            T = b.T_world_box.copy()
            T[2, 3] -= d
            b = replace(b, T_world_box=T)
        out.append(b)
    return out


def render_pallet_free(preset: str, seed: int, index: int, set_down: bool = False):
    """A scene of `preset` drawn without any pallet (its loads and racks stay; `set_down`: the loads drop onto what
    held their pallets), rendered through the preset's sensors.

    Frame `index` of `seed` uses `np.random.default_rng((seed, index))`: reproducible frame by frame.
    :return: (rgb (H, W, 3) uint8, depth_m (H, W) float, K (3, 3), T_vehicle_cam (4, 4) or None): the camera's
        calibration on its vehicle in forklift views, else None.
    :raises SceneError: no valid scene within the preset's attempts.
    """
    from .depth_sensors import depth_model_for
    from .generate import render_scene
    from .presets import get_preset
    from .scene import SceneError
    from .sensors import RgbCameraModel
    from .warehouse import build_scene

    cfg = get_preset(preset)
    rng = np.random.default_rng((int(seed), int(index)))
    for _ in range(cfg.max_attempts):
        scene = build_scene(cfg, rng)
        scene.boxes = without_pallets(scene.boxes, set_down)          # pallet parts carry their instance id
        try:
            scene.validate()
        except SceneError:
            continue
        sensor_rng = np.random.default_rng((int(seed), int(index), 1))
        rgb_model = RgbCameraModel(exposure=sensor_rng.uniform(*cfg.exposure),
                                   noise_sigma=sensor_rng.uniform(*cfg.rgb_noise_sigma))
        f = render_scene(scene, depth_model_for(cfg.sensor), rgb_model, sensor_rng)
        vehicle = getattr(scene, "vehicle", None)
        return f.rgb, f.depth_m, f.K, None if vehicle is None else vehicle.T_vehicle_cam
    raise SceneError(f"no valid pallet-free scene of {preset} (seed {seed}, frame {index})")


def generate_pallet_free_frame(config, seed: int, index: int = 0, loads: str = "set-down"):
    """Frame `index` of a pallet-free dataset drawn from `config` (a `SimConfig`) with `seed`: a scene of the preset
    without its pallets, through the preset's own sensors and appearance (`generate.render_with_sensors`), with no
    pallet ground truth (a negative for training and measuring detectors).

    :param loads: "set-down" (the loads stand where their pallets stood) or "hanging".
    :return: a `SimFrame` whose `pallets` and `faces` are empty.
    :raises SceneError: no valid scene within the preset's attempts.
    """
    from .generate import render_with_sensors
    from .scene import SceneError
    from .warehouse import build_scene

    if loads not in LOADS:
        raise ValueError(f"loads must be one of {', '.join(LOADS)}, got {loads!r}")
    rng = np.random.default_rng((int(seed), int(index)))
    for _ in range(config.max_attempts):
        scene = build_scene(config, rng)
        scene.boxes = without_pallets(scene.boxes, loads == "set-down")
        try:
            scene.validate()
        except SceneError:
            continue
        frame = render_with_sensors(config, scene, seed, index)
        frame.pallets, frame.faces, frame.vehicle = [], [], scene.vehicle
        return frame
    raise SceneError(f"no valid pallet-free scene of {config.name} (seed {seed}, frame {index})")
