"""The floor plane in a depth image: RANSAC fit, and the check that a calibrated camera still sees it where the
calibration says (a knocked camera moves the floor). Pure numpy.

Plane convention: n . p + d = 0 in the camera frame, n a unit normal pointing up (towards the camera), so d is
the camera's height above the floor.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .geometry import backproject_depth

__all__ = ["FloorPlane", "FloorCheck", "fit_floor_plane", "floor_points", "check_floor", "plane_angle_deg"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FloorPlane:
    """Plane n . p + d = 0 in the camera frame, n a unit normal pointing up (towards the camera).

    :ivar normal: (3,) unit normal, camera frame. :ivar d: metres, the camera's height above the floor.
    :ivar inlier_ratio: fraction of the fitted points within the RANSAC tolerance. :ivar rms_m: inliers' RMS.
    """

    normal: np.ndarray
    d: float
    inlier_ratio: float = 1.0
    rms_m: float = 0.0

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise ValueError(f"FloorPlane.normal must be a finite unit (3,) vector, got {self.normal!r}")
        if not np.isfinite(self.d) or self.d <= 0:
            raise ValueError(f"FloorPlane.d (camera height above the floor) must be positive, got {self.d}")
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "d", float(self.d))

    @property
    def camera_height_m(self) -> float:
        return float(self.d)


def plane_angle_deg(n_a: np.ndarray, n_b: np.ndarray) -> float:
    """Angle between two unit normals, degrees."""
    return float(np.degrees(np.arccos(np.clip(float(np.dot(n_a, n_b)), -1.0, 1.0))))


def _plane_from_points(pts: np.ndarray) -> tuple[np.ndarray, float]:
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    n = vt[-1]
    return n, float(-n @ centroid)


def fit_floor_plane(points_cam: np.ndarray, rng: np.random.Generator, inlier_tol_m: float = 0.02,
                    iterations: int = 300, min_inlier_ratio: float = 0.2, up_hint: np.ndarray | None = None,
                    max_tilt_deg: float = 90.0, inlier_tol_quad_per_m: float = 0.0, refits: int = 2) -> FloorPlane:
    """RANSAC plane fit, refined by least squares on the inliers.

    :param points_cam: (n, 3) camera-frame points, metres (e.g. the lower part of a back-projected depth image).
    :param rng: random generator (the fit is deterministic for a given generator state).
    :param up_hint: (3,) the expected floor normal (camera frame); with it, planes tilted more than
        `max_tilt_deg` from it are never chosen (walls, pallet faces).
    :param inlier_tol_quad_per_m: the inlier tolerance grows as `inlier_tol_m + this * z**2` (stereo depth noise
        grows with z**2; a band narrower than the noise far away cuts it unevenly and tilts the fit).
    :param refits: least-squares refits, each on the inliers of the previous plane.
    :raises ValueError: too few points, or no plane supported by `min_inlier_ratio` of them.
    """
    pts = np.asarray(points_cam, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_cam must be (n, 3), got shape {pts.shape}")
    pts = pts[np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)]
    if len(pts) < 3:
        raise ValueError(f"need at least 3 valid points to fit the floor, got {len(pts)}")
    min_cos = np.cos(np.radians(max_tilt_deg)) if up_hint is not None else -np.inf
    tol = inlier_tol_m + inlier_tol_quad_per_m * pts[:, 2] ** 2
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        if up_hint is not None and abs(float(n @ up_hint)) < min_cos:
            continue
        count = int((np.abs(pts @ n - n @ a) < tol).sum())
        if count > best_count:
            best_count, best = count, (n, float(-n @ a))
    if best is None:
        raise ValueError("no floor plane: no sampled point triple spans a plane of the expected tilt")
    n, d = best
    inliers = np.abs(pts @ n + d) < tol
    ratio = float(inliers.mean())
    if ratio < min_inlier_ratio:
        raise ValueError(f"no floor plane: best plane explains {ratio:.0%} of the points "
                         f"(need {min_inlier_ratio:.0%}); aim the camera so the floor is visible")
    n, d = _plane_from_points(pts[inliers])
    for _ in range(int(refits)):
        again = np.abs(pts @ n + d) < tol
        if again.sum() < 3:
            break
        inliers = again
        n, d = _plane_from_points(pts[inliers])
    if d < 0:  # orient the normal towards the camera origin
        n, d = -n, -d
    rms = float(np.sqrt(np.mean((pts[inliers] @ n + d) ** 2)))
    return FloorPlane(normal=n, d=max(d, 1e-9), inlier_ratio=ratio, rms_m=rms)


def floor_points(depth_m: np.ndarray, K: np.ndarray, step: int = 4, rows_from: float = 0.4,
                 max_range_m: float = 8.0) -> np.ndarray:
    """Camera-frame points where the floor usually is: every `step`-th pixel of the image's rows below
    `rows_from` (a fraction of the height), with depth in (0, max_range_m].

    :param depth_m: (H, W) metres, 0 = no data. :return: (n, 3) float64.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    h = depth_m.shape[0]
    sub = np.zeros_like(depth_m, dtype=np.float32)
    r0 = int(h * rows_from)
    sub[r0::step, ::step] = depth_m[r0::step, ::step]
    sub[~np.isfinite(sub) | (sub > max_range_m)] = 0
    pts = backproject_depth(sub, K).reshape(-1, 3)
    return pts[pts[:, 2] > 0].astype(np.float64)


@dataclass(frozen=True)
class FloorCheck:
    """Does the floor in one frame agree with the calibrated floor?

    :ivar agrees: True / False, or None when the frame shows too little floor to tell.
    :ivar tilt_deg: angle between the seen and the calibrated floor normal (NaN when unseen).
    :ivar height_diff_m: seen minus calibrated camera height (NaN when unseen).
    :ivar detail: a sentence for the log / the JSON line.
    """

    agrees: bool | None
    tilt_deg: float
    height_diff_m: float
    detail: str

    def to_dict(self) -> dict:
        def r(v: float, k: int):
            return None if not np.isfinite(v) else round(float(v), k)
        return {"agrees": self.agrees, "tilt_deg": r(self.tilt_deg, 3), "height_diff_m": r(self.height_diff_m, 4),
                "detail": self.detail}


def check_floor(calibrated: FloorPlane, depth_m: np.ndarray, K: np.ndarray, max_tilt_deg: float = 1.0,
                max_height_diff_m: float = 0.03, min_inlier_ratio: float = 0.1, band_m: float = 0.3,
                min_floor_points: int = 1000, seed: int = 0) -> FloorCheck:
    """Fit the floor of one frame near the calibrated one (points within `band_m` of it, planes within 15
    degrees) and compare. Many points far below the calibrated floor (where nothing can be) also disagree.

    A forklift's view is mostly pallets, loads and racks: the floor may be a tenth of the lower image, so a plane
    that `min_inlier_ratio` of those points support, and at least `min_floor_points` of them (every 4th pixel
    each way), counts as the floor seen: a few hundred points between pallets on a crowded floor are too few.

    :param calibrated: the floor plane stored in the calibration (camera frame).
    :param depth_m: (H, W) metres. :param K: (3, 3) of that image.
    """
    pts = floor_points(depth_m, K)
    height = pts @ calibrated.normal + calibrated.d                 # above the calibrated floor, metres
    below = float(np.mean(height < -band_m)) if len(pts) else 0.0
    if len(pts) >= 200 and below >= 0.2:
        return FloorCheck(False, float("nan"), float("nan"), f"{below:.0%} of the depth points low in the image lie "
                                                             f"more than {band_m} m below the calibrated floor")
    pts = pts[np.abs(height) <= band_m]     # racks, truck beds and pallet stacks are not the floor
    if len(pts) < 200:
        return FloorCheck(None, float("nan"), float("nan"), f"floor not seen: {len(pts)} depth points low in "
                                                               "the image")
    try:
        seen = fit_floor_plane(pts, np.random.default_rng(seed), min_inlier_ratio=min_inlier_ratio,
                               iterations=200, up_hint=calibrated.normal, max_tilt_deg=15.0)
    except ValueError as exc:
        return FloorCheck(None, float("nan"), float("nan"), f"floor not seen: {exc}")
    if seen.inlier_ratio * len(pts) < min_floor_points:
        return FloorCheck(None, float("nan"), float("nan"), f"floor not seen: {seen.inlier_ratio * len(pts):.0f} "
                                                               "floor points")
    tilt = plane_angle_deg(seen.normal, calibrated.normal)
    dh = seen.d - calibrated.d
    agrees = tilt <= max_tilt_deg and abs(dh) <= max_height_diff_m
    detail = (f"floor tilted {tilt:.2f} deg (max {max_tilt_deg}) and camera height off by {100 * dh:+.1f} cm "
              f"(max {100 * max_height_diff_m:.0f}) from the calibration")
    return FloorCheck(bool(agrees), tilt, float(dh), detail)

