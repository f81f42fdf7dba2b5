"""A synthetic scene: oriented boxes with materials and instance ids, the pallets among them, a camera, a light.

World frame: z up, floor at z = 0, metres. Instance id 0 is background; pallet instances are 1, 2, ...
and every box of a pallet carries its pallet's instance id.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pallet6d.runtime.geometry import check_K, invert_T
from pallet6d.sim.pallets import get_pallet_model

__all__ = ["MATERIALS", "SceneError", "Box", "PalletPlacement", "Light", "ForkliftVehicle", "Scene", "pallet_boxes",
           "look_at_T_world_cam", "obb_overlap", "box_at"]

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


@dataclass(frozen=True)
class ForkliftVehicle:
    """The forklift that carries the camera.

    Vehicle frame: x forward along the forks, y left, z up, origin on the floor between the fork roots.

    :param T_world_vehicle: (4, 4) vehicle pose in the world. :param T_vehicle_cam: (4, 4) camera-to-vehicle.
    :param boxes: the vehicle's own boxes (fork tines and tips), also in `Scene.boxes`.
    :param target_face: the face of the scene's target pallet ("+x", ...) the forks are to enter.
    :param fork_z_m: height of the forks' underside above the floor. :param fork_spread_m: tine centre to
        centre. :param fork_length_m, fork_width_m, fork_thickness_m: one tine.
    """

    T_world_vehicle: np.ndarray
    T_vehicle_cam: np.ndarray
    boxes: tuple[Box, ...]
    fork_z_m: float
    fork_spread_m: float
    fork_length_m: float
    fork_width_m: float
    fork_thickness_m: float
    target_face: str | None = None      # the target pallet's face the forks are to enter

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_vehicle", _pose(self.T_world_vehicle, "ForkliftVehicle.T_world_vehicle"))
        object.__setattr__(self, "T_vehicle_cam", _pose(self.T_vehicle_cam, "ForkliftVehicle.T_vehicle_cam"))
        if min(self.fork_spread_m, self.fork_length_m, self.fork_width_m, self.fork_thickness_m) <= 0:
            raise ValueError("fork dimensions must be positive")


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
    vehicle: ForkliftVehicle | None = None   # the forklift carrying the camera, in forklift views

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

        if self.vehicle is not None:
            if not np.allclose(self.vehicle.T_world_vehicle @ self.vehicle.T_vehicle_cam, self.T_world_cam, atol=1e-6):
                raise SceneError("the camera is not where the vehicle carries it (T_world_vehicle @ T_vehicle_cam)")
            own = {id(b) for b in self.vehicle.boxes}
            others = [b for b in self.boxes if id(b) not in own]
            if others:
                T = np.stack([b.T_world_box for b in others])
                half = np.stack([b.half_size_m for b in others])
                for fork in self.vehicle.boxes:
                    hit = obb_overlap(fork.T_world_box, fork.half_size_m, T, half, margin_m=0.002)
                    if hit.any():
                        b = others[int(np.flatnonzero(hit)[0])]
                        raise SceneError(f"a fork runs into a box ({MATERIALS[b.material]}, instance "
                                         f"{b.instance_id})")

    @property
    def T_cam_world(self) -> np.ndarray:
        return invert_T(self.T_world_cam)


def pallet_boxes(placement: PalletPlacement, color: np.ndarray, texture_seed: int, material: str | None = None,
                 missing: tuple[int, ...] = (), part_colors: np.ndarray | None = None) -> list[Box]:
    """The boards and blocks of a placed pallet as boxes carrying its instance id.

    :param material: a MATERIALS name; None = the model's own ("wood" or "plastic").
    :param missing: indices into the model's boxes left out (a missing board: the ground truth model stays
        the type's). :param part_colors: optional (k, 3) colour per part (worn or dirty boards), else `color`.
    """
    model = get_pallet_model(placement.model_name)
    mat = MATERIALS.index(material or model.material)
    out = []
    for k, (lo, hi) in enumerate(model.boxes_m):
        if k in missing:
            continue
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2
        out.append(Box(placement.T_world_pallet @ T, (hi - lo) / 2, mat, color if part_colors is None else
                       part_colors[k], placement.instance_id, texture_seed * 64 + k))
    return out


def box_at(center, size_m, material: str, color, seed: int = 0, R: np.ndarray | None = None,
           instance_id: int = 0) -> Box:
    """A box of full size `size_m` (3,) centred at `center` (3,), rotated by R (3, 3; None = identity)."""
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = center
    return Box(T, np.asarray(size_m, dtype=np.float64) / 2, MATERIALS.index(material), color, instance_id, seed)


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


def obb_overlap(T_a: np.ndarray, half_a: np.ndarray, T_b: np.ndarray, half_b: np.ndarray,
                margin_m: float = 0.0) -> np.ndarray:
    """Whether one oriented box overlaps each of many (separating axis test, 15 axes).

    :param T_a: (4, 4) pose of box A's centre, :param half_a: (3,) its half sizes.
    :param T_b: (n, 4, 4) poses of the other boxes, :param half_b: (n, 3) their half sizes.
    :param margin_m: both boxes shrink by this much first, so boxes that only touch do not overlap.
    :return: (n,) bool.
    """
    T_b = np.asarray(T_b, dtype=np.float64).reshape(-1, 4, 4)
    ha = np.maximum(np.asarray(half_a, dtype=np.float64) - margin_m, 0.0)
    hb = np.maximum(np.asarray(half_b, dtype=np.float64).reshape(-1, 3) - margin_m, 0.0)
    Ra = np.asarray(T_a, dtype=np.float64)[:3, :3]
    R = np.einsum("ji,njk->nik", Ra, T_b[:, :3, :3])                 # B's axes in A's frame
    t = (T_b[:, :3, 3] - T_a[:3, 3]) @ Ra                            # B's centre in A's frame
    absR = np.abs(R) + 1e-12
    sep = np.zeros(len(T_b), dtype=bool)
    for i in range(3):
        sep |= np.abs(t[:, i]) > ha[i] + (hb * absR[:, i, :]).sum(1)
    for j in range(3):
        sep |= np.abs(np.einsum("ni,ni->n", t, R[:, :, j])) > (ha[:, None] * absR[:, :, j].T).sum(0) + hb[:, j]
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            ra = ha[i1] * absR[:, i2, j] + ha[i2] * absR[:, i1, j]
            rb = hb[:, j1] * absR[:, i, j2] + hb[:, j2] * absR[:, i, j1]
            sep |= np.abs(t[:, i2] * R[:, i1, j] - t[:, i1] * R[:, i2, j]) > ra + rb
    return ~sep
