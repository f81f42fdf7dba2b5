"""Camera-to-vehicle extrinsics from the floor plane seen in one depth image.

A forklift camera sees the warehouse floor. Fitting that plane gives the camera's mounting height, pitch and
roll, the three extrinsic parameters that drift when a camera bracket is knocked, without any target.
Yaw and the position along the floor cannot be seen from the floor: they come from a board
(`calib/board.py`) or from the mount drawing.

Vehicle frame: x forward along the forks, y left, z up, origin on the floor between the fork roots.
"""
from __future__ import annotations

import numpy as np

from pallet6d.runtime.floor import FloorPlane, fit_floor_plane

__all__ = ["FloorPlane", "fit_floor_plane", "fit_floor_for_calibration", "T_vehicle_cam_from_floor", "pitch_roll_deg"]


def T_vehicle_cam_from_floor(plane: FloorPlane, yaw_deg: float = 0.0, x_m: float = 0.0,
                             y_m: float = 0.0) -> np.ndarray:
    """4x4 transform mapping camera-frame points into the vehicle frame.

    :param plane: the floor in the camera frame (gives pitch, roll and height).
    :param yaw_deg: the optical axis' heading in the vehicle frame, anticlockwise seen from above (0: along x).
    :param x_m, y_m: the camera's position over the floor, relative to the point between the fork roots.
    """
    z_v = plane.normal                                  # vehicle up, in camera coordinates
    forward = np.array([0.0, 0.0, 1.0]) - z_v[2] * z_v  # optical axis projected on the floor
    if np.linalg.norm(forward) < 1e-6:
        raise ValueError("camera looks straight down: forward direction is undefined")
    x_h = forward / np.linalg.norm(forward)             # heading of the optical axis, camera coordinates
    y_h = np.cross(z_v, x_h)
    a = np.radians(yaw_deg)
    x_v = np.cos(a) * x_h - np.sin(a) * y_h             # vehicle x is the heading turned back by the yaw
    y_v = np.cross(z_v, x_v)
    T = np.eye(4)
    T[:3, :3] = np.stack([x_v, y_v, z_v])               # rows: vehicle axes in camera coordinates
    T[:3, 3] = [x_m, y_m, plane.d]
    return T


def pitch_roll_deg(R_vehicle_cam: np.ndarray) -> tuple[float, float]:
    """The camera's pitch (degrees below the horizon of its optical axis) and roll (degrees, positive when the
    image's right side is higher) from a (3, 3) camera-to-vehicle rotation."""
    R = np.asarray(R_vehicle_cam, dtype=np.float64)
    axis, right, down = R[:, 2], R[:, 0], R[:, 1]
    pitch = np.degrees(np.arcsin(np.clip(-axis[2], -1.0, 1.0)))
    roll = np.degrees(np.arctan2(right[2], -down[2]))
    return float(pitch), float(roll)


# a camera mounted upright (image rows down): the floor's normal is its -y, give or take the pitch and roll
UPRIGHT_UP_CAM = np.array([0.0, -1.0, 0.0])


def fit_floor_for_calibration(depths_m: list[np.ndarray], K: np.ndarray, max_range_m: float = 8.0,
                              max_tilt_deg: float = 45.0, seed: int = 0) -> FloorPlane:
    """The floor plane for `calib floor`: one fit over the lower image part of one or more depth images of a
    still camera, within `max_range_m`, tilted at most `max_tilt_deg` from an upright camera's up (walls and box
    faces are never taken for the floor). The least squares run in inverse depth, where stereo noise is the same
    near and far, so the far floor adds what it knows without tilting the plane: a camera high and pitched little
    sees its floor only from 3-4 m on.

    :param depths_m: (H, W) metres each. :param K: (3, 3). :raises ValueError: no floor plane found.
    """
    from pallet6d.runtime.floor import floor_points

    if not depths_m:
        raise ValueError("no depth images to fit the floor on")
    pts = np.concatenate([floor_points(d, K, step=8, max_range_m=max_range_m) for d in depths_m])
    return fit_floor_plane(pts, np.random.default_rng(seed), up_hint=UPRIGHT_UP_CAM, max_tilt_deg=max_tilt_deg,
                           inverse_depth=True)
