"""Camera-to-vehicle extrinsics from the floor plane seen in one depth image.

A forklift camera sees the warehouse floor. Fitting that plane gives the camera's mounting height, pitch and
roll — the three extrinsic parameters that drift when a camera bracket is knocked — without any target.
Yaw and the position along the floor cannot be seen from the floor and stay as configured.

Vehicle frame: origin on the floor under the camera, z up, x forward (the camera's optical axis projected
onto the floor), y to the left.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FloorPlane", "fit_floor_plane", "T_vehicle_cam_from_floor"]


@dataclass(frozen=True)
class FloorPlane:
    """Plane n . p + d = 0 in the camera frame, with n a unit normal pointing up (towards the camera)."""

    normal: np.ndarray      # (3,)
    d: float                # metres; the camera's height above the floor is d (camera origin is on the + side)
    inlier_ratio: float
    rms_m: float

    @property
    def camera_height_m(self) -> float:
        return float(self.d)


def _plane_from_points(pts: np.ndarray) -> tuple[np.ndarray, float]:
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    n = vt[-1]
    return n, float(-n @ centroid)


def fit_floor_plane(points_cam: np.ndarray, rng: np.random.Generator, inlier_tol_m: float = 0.02,
                    iterations: int = 300, min_inlier_ratio: float = 0.2) -> FloorPlane:
    """RANSAC plane fit, refined by least squares on the inliers.

    :param points_cam: (n, 3) camera-frame points, metres (e.g. the lower part of a back-projected depth image).
    :param rng: random generator (the fit is deterministic for a given generator state).
    :raises ValueError: too few points, or no plane supported by `min_inlier_ratio` of them.
    """
    pts = np.asarray(points_cam, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_cam must be (n, 3), got shape {pts.shape}")
    pts = pts[np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)]
    if len(pts) < 3:
        raise ValueError(f"need at least 3 valid points to fit the floor, got {len(pts)}")
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        count = int((np.abs(pts @ n - n @ a) < inlier_tol_m).sum())
        if count > best_count:
            best_count, best = count, (n, float(-n @ a))
    if best is None:
        raise ValueError("all sampled point triples were collinear: no floor plane")
    n, d = best
    inliers = np.abs(pts @ n + d) < inlier_tol_m
    ratio = float(inliers.mean())
    if ratio < min_inlier_ratio:
        raise ValueError(f"no floor plane: best plane explains {ratio:.0%} of the points "
                         f"(need {min_inlier_ratio:.0%}); aim the camera so the floor is visible")
    n, d = _plane_from_points(pts[inliers])
    if d < 0:  # orient the normal towards the camera origin
        n, d = -n, -d
    rms = float(np.sqrt(np.mean((pts[inliers] @ n + d) ** 2)))
    return FloorPlane(normal=n, d=d, inlier_ratio=ratio, rms_m=rms)


def T_vehicle_cam_from_floor(plane: FloorPlane) -> np.ndarray:
    """4x4 transform mapping camera-frame points into the vehicle frame (see module docstring)."""
    z_v = plane.normal                                  # vehicle up, in camera coordinates
    forward = np.array([0.0, 0.0, 1.0]) - z_v[2] * z_v  # optical axis projected on the floor
    if np.linalg.norm(forward) < 1e-6:
        raise ValueError("camera looks straight down: forward direction is undefined")
    x_v = forward / np.linalg.norm(forward)
    y_v = np.cross(z_v, x_v)
    R_vehicle_cam = np.stack([x_v, y_v, z_v])           # rows: vehicle axes in camera coordinates
    T = np.eye(4)
    T[:3, :3] = R_vehicle_cam
    T[:3, 3] = [0.0, 0.0, plane.d]                      # camera origin is d above the floor, right above 0
    return T
