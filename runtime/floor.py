"""The floor plane in a depth image: RANSAC fit, and the check that a calibrated camera still sees it where the
calibration says (a knocked camera moves the floor, a wrong calibration puts it elsewhere). Pure numpy.

Plane convention: n . p + d = 0 in the camera frame, n a unit normal pointing up (towards the camera), so d is
the camera's height above the floor.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .geometry import backproject_pixels

__all__ = ["FloorPlane", "FloorCheck", "fit_floor_plane", "floor_points", "image_points", "find_floor_anywhere",
           "check_floor", "plane_angle_deg", "refine_floor", "on_floor"]

log = logging.getLogger(__name__)

REFIT_BAND_M = 0.15     # a floor found in the whole image is refitted on the lower image's points this close to it
SEARCH_RANGE_M = 5.0    # the whole-image search ignores farther points (stereo noise there bends planes)
BELOW_M = 0.1           # points this far below a plane lie below it (beyond depth noise) ...
MAX_BELOW = 0.05        # ... and a plane with more than this fraction of the points below it is not the floor


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


def _plane_in_inverse_depth(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane n . p + d = 0 through camera-frame points (z > 0), fitted as 1/z = a x/z + b y/z + c
    (every plane not through the camera centre is one there: n = -(a, b, c) / |(a, b, c)|, d = 1 / |(a, b, c)|).
    Stereo depth noise grows as z**2, so inverse depth carries the same noise near and far: this fit weighs each
    point by what it knows, where a 3D fit lets the far, noisy points tilt the plane."""
    z = pts[:, 2]
    A = np.c_[pts[:, 0] / z, pts[:, 1] / z, np.ones(len(pts))]
    abc, *_ = np.linalg.lstsq(A, 1.0 / z, rcond=None)
    norm = float(np.linalg.norm(abc))
    return -abc / norm, 1.0 / norm


def refine_floor(expected: FloorPlane, depth_m: np.ndarray, K: np.ndarray, max_tilt_deg: float = 2.0,
                 max_height_diff_m: float = 0.05, min_points: int = 300, max_points: int = 6000,
                 max_range_m: float = SEARCH_RANGE_M,
                 tols_m: tuple = (0.06, 0.06, 0.06, 0.03, 0.015, 0.01),
                 min_spread_m: float = 0.5) -> FloorPlane | None:
    """The floor of this frame near the `expected` one (the calibration's), or None where the depth does not show it
    clearly: least-squares fits on the lower image's points (`floor_points` on a pixel grid of about `max_points`,
    up to `max_range_m`) within `tols_m` of the plane so far, starting from `expected`: three rounds at 6 cm walk a
    plane tilted a degree or two onto the floor (at 5 m it lies 9-17 cm off), the tighter ones leave the bottoms of
    pallet faces and fork tines out. The band does not widen with the range: the far points' stereo noise would tilt
    the fit. No search: a calibration holds the floor within a degree or two and a few centimetres, where no deck (a
    pallet's height above it) is confused with it. None when a round keeps fewer than `min_points` points, the
    result is tilted more than `max_tilt_deg` or its height differs by more than `max_height_diff_m` from `expected`,
    or more than `MAX_BELOW` of the points lie `BELOW_M` below it, or where the fitted points spread less than
    `min_spread_m` (standard deviation) along one of the plane's directions: a patch of floor seen between pallets and
    forks, or a strip, leaves the tilt across it to the depth's noise (on stereo depth such fits were off by 0.3-0.8
    degrees where the others were within 0.12).

    :param depth_m: (H, W) metres, 0 or NaN = no data. :param K: (3, 3).
    """
    h, w = np.shape(depth_m)[:2]
    step = max(1, int(np.sqrt(0.6 * h * w / max_points)))        # floor_points reads the lower 60 % of the rows
    pts = floor_points(depth_m, K, step=step, max_range_m=max_range_m)
    if len(pts) < min_points:
        return None
    n, d = expected.normal, expected.d
    for tol in tols_m:
        near = np.abs(pts @ n + d) < tol
        if near.sum() < min_points:
            return None
        n, d = _plane_from_points(pts[near])
        if n @ expected.normal < 0:
            n, d = -n, -d
    if d <= 0 or plane_angle_deg(n, expected.normal) > max_tilt_deg or abs(d - expected.d) > max_height_diff_m:
        return None
    if np.mean(pts @ n + d < -BELOW_M) > MAX_BELOW:
        return None
    spread = np.sqrt(np.linalg.eigvalsh(np.cov(pts[near].T))[1])          # the narrower in-plane direction
    if spread < min_spread_m:
        return None
    return FloorPlane(normal=n, d=d, inlier_ratio=float(near.mean()),
                      rms_m=float(np.sqrt(np.mean((pts[near] @ n + d) ** 2))))


def on_floor(T_vehicle_cam: np.ndarray, floor: FloorPlane) -> np.ndarray:
    """(4, 4) `T_vehicle_cam` turned and raised the least (about the camera) to put its floor (z = 0) on `floor`:
    its up axis becomes `floor.normal`, its height `floor.d`; the horizontal position and heading stay.
    :param floor: camera frame."""
    T = np.array(T_vehicle_cam, dtype=np.float64)
    up, n = T[2, :3], floor.normal
    axis = np.cross(n, up)
    s, c = float(np.linalg.norm(axis)), float(n @ up)
    R = np.eye(3)                                         # Rodrigues: the rotation taking n to up
    if s > 1e-12:
        k = axis / s
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        R = R + s * kx + (1.0 - c) * kx @ kx
    T[:3, :3] = T[:3, :3] @ R
    T[2, 3] = floor.d
    return T


def fit_floor_plane(points_cam: np.ndarray, rng: np.random.Generator, inlier_tol_m: float = 0.02,
                    iterations: int = 300, min_inlier_ratio: float = 0.2, up_hint: np.ndarray | None = None,
                    max_tilt_deg: float = 90.0, inlier_tol_quad_per_m: float = 0.0, refits: int = 2,
                    inverse_depth: bool = False) -> FloorPlane:
    """RANSAC plane fit, refined by least squares on the inliers.

    :param points_cam: (n, 3) camera-frame points, metres (e.g. the lower part of a back-projected depth image).
    :param rng: random generator (the fit is deterministic for a given generator state).
    :param up_hint: (3,) the expected floor normal (camera frame); with it, planes tilted more than
        `max_tilt_deg` from it are never chosen (walls, pallet faces).
    :param inlier_tol_quad_per_m: the inlier tolerance grows as `inlier_tol_m + this * z**2` (stereo depth noise
        grows with z**2; a band narrower than the noise far away cuts it unevenly and tilts the fit).
    :param refits: least-squares refits, each on the inliers of the previous plane.
    :param inverse_depth: fit the least squares in inverse depth (`_plane_in_inverse_depth`: stereo depth reaching
        far), not as orthogonal distances in 3D.
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
    least_squares = _plane_in_inverse_depth if inverse_depth else _plane_from_points
    n, d = least_squares(pts[inliers])
    for _ in range(int(refits)):
        again = np.abs(pts @ n + d) < tol
        if again.sum() < 3:
            break
        inliers = again
        n, d = least_squares(pts[inliers])
    if d < 0:  # orient the normal towards the camera origin
        n, d = -n, -d
    rms = float(np.sqrt(np.mean((pts[inliers] @ n + d) ** 2)))
    return FloorPlane(normal=n, d=max(d, 1e-9), inlier_ratio=ratio, rms_m=rms)


def floor_points(depth_m: np.ndarray, K: np.ndarray, step: int = 4, rows_from: float = 0.4,
                 max_range_m: float = 8.0) -> np.ndarray:
    """Camera-frame points where the floor usually is: every `step`-th pixel of the image's rows below
    `rows_from` (a fraction of the height), with finite depth in (0, max_range_m].

    :param depth_m: (H, W) metres, 0 or NaN = no data. :return: (n, 3) float64.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    if int(step) < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    r0 = int(depth_m.shape[0] * rows_from)
    v, u = np.mgrid[r0:depth_m.shape[0]:step, 0:depth_m.shape[1]:step]
    z = depth_m[r0::step, ::step].astype(np.float64)
    keep = np.isfinite(z) & (z > 0) & (z <= max_range_m)
    return backproject_pixels(u[keep], v[keep], z[keep], K).astype(np.float64)


def image_points(depth_m: np.ndarray, K: np.ndarray, max_points: int = 4000, max_range_m: float = 8.0) -> np.ndarray:
    """Camera-frame points of the whole image on a regular pixel grid of at most about `max_points` pixels.

    :param depth_m: (H, W) metres, 0 or NaN = no data. :return: (n, 3) float64, n <= max_points.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    step = max(1, int(np.ceil(np.sqrt(depth_m.size / max(int(max_points), 1)))))
    return floor_points(depth_m, K, step=step, rows_from=0.0, max_range_m=max_range_m)


def find_floor_anywhere(points_cam: np.ndarray, up_hint: np.ndarray, rng: np.random.Generator,
                        max_tilt_deg: float = 35.0, min_support: float = 0.06, min_support_points: int = 150,
                        max_planes: int = 3, inlier_tol_m: float = 0.02, inlier_tol_quad_per_m: float = 0.004,
                        iterations: int = 150) -> FloorPlane:
    """The floor wherever it is: the largest plane below the camera, facing up within `max_tilt_deg` of
    `up_hint`, with next to nothing below it.

    Up to `max_planes` planes are fitted one after another (RANSAC, each on the points the previous ones leave,
    so the largest first); each needs `min_support` of all points and at least `min_support_points`. Of those
    that face up and lie below the camera, the first with at most `MAX_BELOW` of all points more than `BELOW_M`
    (plus the inlier tolerance) below it is the floor: nothing lies below the floor, while fork tines, pallet
    decks and loads have floor around them, and a plane cutting through the scene has points on both sides.

    :param points_cam: (n, 3) camera-frame points, metres (e.g. `image_points`).
    :param up_hint: (3,) the expected floor normal, camera frame (the calibrated floor's).
    :param rng: random generator (deterministic for a given state).
    :raises ValueError: no plane of enough support faces up (a wall filling the view, no depth), or each that
        does has points below it.
    """
    pts = np.asarray(points_cam, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_cam must be (n, 3), got shape {pts.shape}")
    up = np.asarray(up_hint, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-9:
        raise ValueError(f"up_hint must be a finite non-zero (3,) vector, got {up_hint!r}")
    up = up / np.linalg.norm(up)
    pts = pts[np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)]
    need = max(int(min_support_points), int(np.ceil(min_support * len(pts))))
    if len(pts) < need:
        raise ValueError(f"no floor plane: {len(pts)} valid depth points in the image (need {need})")
    tol = inlier_tol_m + inlier_tol_quad_per_m * pts[:, 2] ** 2
    min_cos = np.cos(np.radians(max_tilt_deg))
    left = np.ones(len(pts), bool)
    found: list[FloorPlane] = []
    for _ in range(int(max_planes)):
        if left.sum() < need:
            break
        try:
            plane = fit_floor_plane(pts[left], rng, inlier_tol_m=inlier_tol_m, iterations=iterations,
                                    min_inlier_ratio=0.0, up_hint=up, max_tilt_deg=max_tilt_deg,
                                    inlier_tol_quad_per_m=inlier_tol_quad_per_m)
        except ValueError:
            break
        on = left & (np.abs(pts @ plane.normal + plane.d) < tol)
        if on.sum() < need:
            break
        if float(plane.normal @ up) >= min_cos:      # faces up and lies below the camera (not a shelf above it)
            found.append(plane)
        left &= ~on
    if not found:
        raise ValueError(f"no floor plane: no plane within {max_tilt_deg:g} deg of the expected floor holds "
                         f"{need} of the {len(pts)} depth points")
    below = [float(np.mean(pts @ p.normal + p.d < -(tol + BELOW_M))) for p in found]
    floors = [p for p, b in zip(found, below) if b <= MAX_BELOW]
    if not floors:
        k = int(np.argmin(below))
        raise ValueError(f"no floor plane: {below[k]:.0%} of the depth points lie below the large horizontal plane "
                         f"with the fewest below it (camera {found[k].d:.2f} m above it)")
    floor = floors[0]
    inliers = np.abs(pts @ floor.normal + floor.d) < tol
    return FloorPlane(floor.normal, floor.d, float(inliers.mean()), floor.rms_m)


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
                min_floor_points: int = 1000, seed: int = 0, search_tilt_deg: float = 35.0) -> FloorCheck:
    """Fit the floor of one frame near the calibrated one (points within `band_m` of it, planes within 15
    degrees) and compare; where it is not there, look for it in the whole image (`find_floor_anywhere`).

    A forklift's view is mostly pallets, loads and racks: the floor may be a tenth of the lower image, so a plane
    that `min_inlier_ratio` of those points support, and at least `min_floor_points` of them (every 4th pixel
    each way), with next to nothing below it, counts as the floor seen: a few hundred points between pallets on
    a crowded floor are too few, and a deck or load top has floor below it.

    A calibration far off (the camera more than `band_m` higher or lower than calibrated, or tilted more than
    15 degrees) leaves no floor in the band, or puts much of the view below the calibrated floor, where nothing
    can be. Then the floor is searched in the whole image (within `search_tilt_deg` of the calibrated one and
    `SEARCH_RANGE_M`), refitted on the lower image's points near it with the same standard of evidence, and
    disagrees with its measured tilt and height. Without one the check is "unknown" (`agrees` None), or
    disagrees without numbers when a fifth of the lower image lies below the calibrated floor.

    :param calibrated: the floor plane stored in the calibration (camera frame).
    :param depth_m: (H, W) metres, 0 or NaN = no data. :param K: (3, 3) of that image.
    :raises ValueError: `depth_m` not 2-D, or `K` not a valid intrinsic matrix.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    pts = floor_points(depth_m, K)
    below = float(np.mean(pts @ calibrated.normal + calibrated.d < -band_m)) if len(pts) else 0.0
    fails = len(pts) >= 200 and below >= 0.2      # nothing can be below the floor
    near = None
    try:
        if fails:
            raise ValueError(f"{below:.0%} of the depth points low in the image lie more than {band_m} m below the "
                             "calibrated floor")
        near = _fit_near(calibrated, pts, band_m, min_inlier_ratio, min_floor_points, seed)
        check = _compare(calibrated, near, max_tilt_deg, max_height_diff_m, "")
        if check.agrees:
            return check
        why = "the plane near the calibrated floor disagrees and holds fewer floor points"
    except ValueError as exc:
        why = str(exc)
    try:
        found = find_floor_anywhere(image_points(depth_m, K, max_range_m=SEARCH_RANGE_M), calibrated.normal,
                                    np.random.default_rng(seed), max_tilt_deg=search_tilt_deg)
        seen = _fit_near(found, pts, REFIT_BAND_M, min_inlier_ratio, min_floor_points, seed)
    except ValueError as exc:
        if near is not None:        # the plane near the calibrated floor is the best there is
            return check
        log.debug("floor not near the calibrated one (%s), nor anywhere: %s", why, exc)
        nan = float("nan")
        return FloorCheck(False if fails else None, nan, nan, why if fails else f"floor not seen: {why}; {exc}")
    if near is not None and _support(seen, pts) <= 1.2 * _support(near, pts):
        return check                # the disagreeing plane near the calibrated floor is (as good as) the floor
    check = _compare(calibrated, seen, max_tilt_deg, max_height_diff_m, f" (found in the whole image: {why})")
    if check.agrees:        # where the calibration expects it, yet not enough of it there to confirm
        return FloorCheck(None, float("nan"), float("nan"), f"floor not seen: {why}")
    return check


def _fit_near(expected: FloorPlane, pts: np.ndarray, band_m: float, min_inlier_ratio: float, min_floor_points: int,
              seed: int) -> FloorPlane:
    """The floor fitted on the points `pts` (n, 3) within `band_m` of `expected`, tilted at most 15 degrees from
    it, with `min_floor_points` on it and at most `MAX_BELOW` of `pts` more than `BELOW_M` below it.

    :raises ValueError: saying which of these fails."""
    near = pts[np.abs(pts @ expected.normal + expected.d) <= band_m]   # racks, truck beds, pallet stacks: no floor
    if len(near) < 200:
        raise ValueError(f"{len(near)} depth points low in the image near the expected floor")
    seen = fit_floor_plane(near, np.random.default_rng(seed), min_inlier_ratio=min_inlier_ratio, iterations=200,
                           up_hint=expected.normal, max_tilt_deg=15.0)
    if seen.inlier_ratio * len(near) < min_floor_points:
        raise ValueError(f"{seen.inlier_ratio * len(near):.0f} floor points near the expected floor")
    below = float(np.mean(pts @ seen.normal + seen.d < -BELOW_M))
    if below > MAX_BELOW:
        raise ValueError(f"the plane fitted near the expected floor has {below:.0%} of the depth points low in the "
                         f"image more than {100 * BELOW_M:.0f} cm below it: not the floor")
    return seen


def _support(plane: FloorPlane, pts: np.ndarray, tol_m: float = 0.02) -> int:
    """How many of `pts` (n, 3) lie within `tol_m` of `plane`."""
    return int(np.sum(np.abs(pts @ plane.normal + plane.d) < tol_m))


def _compare(calibrated: FloorPlane, seen: FloorPlane, max_tilt_deg: float, max_height_diff_m: float,
             where: str) -> FloorCheck:
    tilt = plane_angle_deg(seen.normal, calibrated.normal)
    dh = seen.d - calibrated.d
    agrees = tilt <= max_tilt_deg and abs(dh) <= max_height_diff_m
    detail = (f"floor tilted {tilt:.2f} deg (max {max_tilt_deg}) and camera height off by {100 * dh:+.1f} cm "
              f"(max {100 * max_height_diff_m:.0f}) from the calibration{where}")
    return FloorCheck(bool(agrees), tilt, float(dh), detail)
