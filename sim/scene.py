"""A synthetic scene: oriented boxes with materials and instance ids, the pallets among them, a camera, a light.

World frame: z up, floor at z = 0, metres. Instance id 0 is background; pallet instances are 1, 2, ...
and every box of a pallet carries its pallet's instance id.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pallet6d.runtime.geometry import check_K, invert_T
from pallet6d.sim.pallets import get_pallet_model

__all__ = ["MATERIALS", "SceneError", "Box", "PalletPlacement", "Light", "Scene", "pallet_boxes",
           "look_at_T_world_cam"]

# Material kinds; a box's `material` is an index into this tuple.
MATERIALS: tuple[str, ...] = ("wood", "cardboard", "metal", "concrete", "wall", "plastic", "film")


class SceneError(ValueError):
    """A scene or scene configuration that cannot give a valid frame (no pallet, camera inside geometry...)."""


def _pose(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{what} must be a finite 4x4 transform, got shape {T.shape}")
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) < 0:
        raise ValueError(f"{what} must have a proper rotation matrix")
    return T


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in its own frame, placed in the world.

    :param T_world_box: (4, 4) pose of the box centre.
    :param half_size_m: (3,) half extents along the box axes.
    :param material: index into MATERIALS.
    :param color: (3,) base RGB in [0, 1].
    :param instance_id: 0 for background, the pallet's instance id for pallet parts.
    :param texture_seed: varies the procedural texture between boxes.
    """

    T_world_box: np.ndarray
    half_size_m: np.ndarray
    material: int
    color: np.ndarray
    instance_id: int = 0
    texture_seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_box", _pose(self.T_world_box, "Box.T_world_box"))
        half = np.asarray(self.half_size_m, dtype=np.float64)
        if half.shape != (3,) or not np.all(half > 0):
            raise ValueError(f"Box.half_size_m must be (3,) positive, got {half}")
        color = np.asarray(self.color, dtype=np.float64)
        if color.shape != (3,):
            raise ValueError(f"Box.color must be (3,) RGB, got shape {color.shape}")
        if not 0 <= self.material < len(MATERIALS):
            raise ValueError(f"Box.material must index MATERIALS {MATERIALS}, got {self.material}")
        object.__setattr__(self, "half_size_m", half)
        object.__setattr__(self, "color", np.clip(color, 0, 1))


@dataclass(frozen=True)
class PalletPlacement:
    """A pallet instance: its model and its pose in the world."""

    instance_id: int
    model_name: str
    T_world_pallet: np.ndarray

    def __post_init__(self) -> None:
        if self.instance_id < 1:
            raise ValueError(f"pallet instance ids start at 1, got {self.instance_id}")
        get_pallet_model(self.model_name)  # raises on unknown names
        object.__setattr__(self, "T_world_pallet", _pose(self.T_world_pallet, "PalletPlacement.T_world_pallet"))


@dataclass(frozen=True)
class Light:
    """Directional light plus ambient plus a light at the camera (the forklift's lamp).

    :param direction_world: (3,) unit vector the light travels along (pointing away from the sun).
    """

    direction_world: np.ndarray = field(default_factory=lambda: np.array([0.3, 0.5, -1.0]) / np.sqrt(1.34))
    intensity: float = 0.7
    ambient: float = 0.35
    headlight: float = 0.15

    def __post_init__(self) -> None:
        d = np.asarray(self.direction_world, dtype=np.float64)
        if d.shape != (3,) or not np.linalg.norm(d) > 0:
            raise ValueError("Light.direction_world must be a non-zero (3,) vector")
        object.__setattr__(self, "direction_world", d / np.linalg.norm(d))
        if min(self.intensity, self.ambient, self.headlight) < 0:
            raise ValueError("light intensities must be >= 0")


@dataclass
class Scene:
    """Everything needed to render one frame."""

    boxes: list[Box]
    pallets: list[PalletPlacement]
    T_world_cam: np.ndarray
    K: np.ndarray
    image_hw: tuple[int, int]
    light: Light = field(default_factory=Light)
    target_instance: int | None = None   # the pallet to pick up, when the scene has one

    def __post_init__(self) -> None:
        self.T_world_cam = _pose(self.T_world_cam, "Scene.T_world_cam")
        self.K = check_K(self.K)
        h, w = (int(x) for x in self.image_hw)
        if h < 8 or w < 8:
            raise ValueError(f"image must be at least 8x8 pixels, got {h}x{w}")
        self.image_hw = (h, w)

    def validate(self, near_m: float = 0.05) -> None:
        """Raise SceneError for scenes that cannot give a valid frame."""
        if not self.pallets:
            raise SceneError("scene has no pallet")
        ids = [p.instance_id for p in self.pallets]
        if len(set(ids)) != len(ids):
            raise SceneError(f"pallet instance ids must be unique, got {ids}")
        if self.target_instance is not None and self.target_instance not in ids:
            raise SceneError(f"target instance {self.target_instance} is not among the pallets {ids}")
        cam = self.T_world_cam[:3, 3]
        for i, b in enumerate(self.boxes):
            local = b.T_world_box[:3, :3].T @ (cam - b.T_world_box[:3, 3])
            if np.all(np.abs(local) < b.half_size_m + near_m):
                raise SceneError(f"camera at {np.round(cam, 3).tolist()} is inside (or within {near_m} m of) "
                                 f"box {i} ({MATERIALS[b.material]}, instance {b.instance_id})")

    @property
    def T_cam_world(self) -> np.ndarray:
        return invert_T(self.T_world_cam)


def pallet_boxes(placement: PalletPlacement, color: np.ndarray, texture_seed: int) -> list[Box]:
    """The boards and blocks of a placed pallet as wood boxes carrying its instance id."""
    model = get_pallet_model(placement.model_name)
    out = []
    for k, (lo, hi) in enumerate(model.boxes_m):
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2
        out.append(Box(placement.T_world_pallet @ T, (hi - lo) / 2, MATERIALS.index("wood"), color,
                       placement.instance_id, texture_seed * 64 + k))
    return out


def look_at_T_world_cam(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera pose (OpenCV axes: x right, y down, z forward) at `eye` looking at `target`."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T
