"""A forklift camera looking at one EPAL on the floor, rendered by ray casting (exact depth, no simulator)."""
from __future__ import annotations

import numpy as np

from pallet6d.runtime.geometry import invert_T, make_T
from pallet6d.runtime.structure import cast_rays_boxes
from pallet6d.sim.pallets import get_pallet_model

H, W = 240, 424
K = np.array([[305.0, 0, 211.5], [0, 305.0, 119.5], [0, 0, 1]])
EPAL = get_pallet_model("epal")


def rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def camera(height_m: float = 0.5, pitch_deg: float = 8.0, roll_deg: float = 0.0, x_m: float = 0.0) -> np.ndarray:
    """T_vehicle_cam of a camera looking along the forks, pitched down."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return make_T(Rx @ Ry @ R0, [x_m, 0.0, height_m])


def pallet_pose(distance_m: float = 2.0, yaw_deg: float = 0.0, lateral_m: float = 0.0) -> np.ndarray:
    """T_vehicle_pallet of an EPAL on the floor, its -x face towards the forks at `distance_m` (yaw 0)."""
    T = make_T(rz(yaw_deg), [0.0, lateral_m, EPAL.size_m[2] / 2])
    T[:3, 3] += T[:3, :3] @ np.array([EPAL.size_m[0] / 2, 0, 0]) + np.array([distance_m, 0, 0])
    return T


def render(T_vehicle_cam: np.ndarray, T_vehicle_pallet: np.ndarray, extra_boxes_pallet=None,
           floor: bool = True) -> np.ndarray:
    """(H, W) exact depth of the floor (z = 0 of the vehicle frame), the pallet and boxes given in its frame."""
    v, u = np.mgrid[0:H, 0:W]
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(-1, 3)
    rays_v = rays_c @ T_vehicle_cam[:3, :3].T
    o = T_vehicle_cam[:3, 3]
    t = np.full(len(rays_c), np.inf)
    if floor:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(rays_v[:, 2] < -1e-9, -o[2] / rays_v[:, 2], np.inf)
    T_pv = invert_T(T_vehicle_pallet)
    boxes = EPAL.boxes_m if extra_boxes_pallet is None else np.concatenate([EPAL.boxes_m, extra_boxes_pallet])
    t_box, _ = cast_rays_boxes((T_pv[:3, :3] @ o + T_pv[:3, 3])[None], (rays_v @ T_pv[:3, :3].T)[None], boxes)
    t = np.minimum(t, t_box[0])
    return np.where(np.isfinite(t) & (t < 20), t, 0.0).reshape(H, W).astype(np.float32)
