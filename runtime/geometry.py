"""Geometry core: back-projection, cropping, point sampling, rotations, rigid transforms, projection.

Pure numpy functions. Conventions (DESIGN.md): camera frame is OpenCV's (x right, y down, z forward),
`K` is the 3x3 pinhole matrix, `T_a_b` is a 4x4 matrix that maps points in frame b into frame a,
quaternions are (w, x, y, z) with w >= 0, lengths are metres unless a name says otherwise.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "check_K",
    "depth_to_metres",
    "backproject_pixels",
    "backproject_depth",
    "clamp_box",
    "crop",
    "select_pixels",
    "sample_indices",
    "quat_to_rot",
    "rot_to_quat",
    "make_T",
    "invert_T",
    "transform_points",
    "project_points",
]


# A pinhole camera's focal length in pixels is W / (2 tan(HFOV / 2)): 0.1 W is a 157 degree lens, 20 W a
# 2.9 degree one. Outside that range the numbers are not a camera that a forklift carries (a K in metres,
# a K scaled for another resolution, 1e9 placeholders) and every back-projected point would be wrong.
FOCAL_RANGE_OF_SIZE = (0.1, 20.0)
MAX_SKEW_OF_FOCAL = 0.01       # |K[0, 1]| / fx; real calibrations give 0 or a rounding residue
MAX_ASPECT = 2.0               # fy / fx and fx / fy; square pixels give 1


def check_K(K: np.ndarray, image_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Validate a 3x3 pinhole camera matrix and return it as float64.

    Always: finite, last row (0, 0, 1), K[1, 0] = 0, positive focal lengths, |skew| <= 1 % of fx, fy / fx
    within [1/2, 2]. With `image_hw` (H, W) also: fx and fy within 0.1-20 times the image's larger side and
    the principal point inside the image.

    :param K: (3, 3) [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
    :param image_hw: (H, W) of the image K belongs to, or None when it is not known here.
    :raises ValueError: saying which entry is wrong.
    """
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"intrinsics K must be a 3x3 matrix of numbers, got {type(K).__name__}") from None
    if K.shape != (3, 3):
        raise ValueError(f"intrinsics K must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError(f"intrinsics K must be finite, got {K.tolist()}")
    # scalar tests: called by several stages per frame, where np.allclose's overhead adds up
    if not (abs(K[2, 0]) <= 1e-6 and abs(K[2, 1]) <= 1e-6 and abs(K[2, 2] - 1.0) <= 1e-6 and abs(K[1, 0]) <= 1e-6):
        raise ValueError(f"intrinsics K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (transposed?), got {K.tolist()}")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise ValueError(f"intrinsics K must have positive focal lengths, got fx={fx}, fy={fy}")
    if abs(K[0, 1]) > MAX_SKEW_OF_FOCAL * fx:
        raise ValueError(f"intrinsics K has skew {K[0, 1]} (more than {MAX_SKEW_OF_FOCAL:.0%} of fx={fx}); "
                         "a pinhole camera has K[0, 1] = 0")
    if not 1 / MAX_ASPECT <= fy / fx <= MAX_ASPECT:
        raise ValueError(f"intrinsics K: fx={fx} and fy={fy} differ more than {MAX_ASPECT}x")
    if image_hw is not None:
        h, w = int(image_hw[0]), int(image_hw[1])
        lo, hi = FOCAL_RANGE_OF_SIZE[0] * max(h, w), FOCAL_RANGE_OF_SIZE[1] * max(h, w)
        if not (lo <= fx <= hi and lo <= fy <= hi):
            raise ValueError(f"intrinsics K: focal lengths fx={fx:g}, fy={fy:g} px are implausible for a {w}x{h} "
                             f"image (expected {lo:g}-{hi:g} px): intrinsics of another resolution, or not in pixels?")
        if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
            raise ValueError(f"intrinsics K: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {w}x{h} "
                             "image: intrinsics of another resolution?")
    return K


def depth_to_metres(depth: np.ndarray, depth_scale_m: float | None = None) -> np.ndarray:
    """Convert a depth image to float32 metres, 0 where there is no data.

    :param depth: (H, W) uint16 in units of `depth_scale_m` metres (0.001 = millimetres),
        or float32/float64 metres (then `depth_scale_m` must be None or 1). NaN/inf become 0.
    :param depth_scale_m: metres per depth unit for integer depth; defaults to 0.001 (mm) for uint16.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a (H, W) image, got shape {depth.shape}")
    if np.issubdtype(depth.dtype, np.integer):
        scale = 0.001 if depth_scale_m is None else float(depth_scale_m)
        if not scale > 0:
            raise ValueError(f"depth_scale_m must be positive, got {depth_scale_m}")
        return depth.astype(np.float32) * np.float32(scale)
    if np.issubdtype(depth.dtype, np.floating):
        if depth_scale_m not in (None, 1, 1.0):
            raise ValueError("float depth is taken as metres; pass depth_scale_m=None for it")
        out = depth.astype(np.float32, copy=True)
        out[~np.isfinite(out)] = 0.0
        out[out < 0] = 0.0
        return out
    raise TypeError(f"depth must be uint16 (units) or float (metres), got dtype {depth.dtype}")


def backproject_pixels(u: np.ndarray, v: np.ndarray, z_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project pixels with known depth to camera-frame points.

    :param u: (n,) pixel columns (pixel centres are integers).
    :param v: (n,) pixel rows.
    :param z_m: (n,) depth along the optical axis in metres.
    :param K: 3x3 intrinsics.
    :return: (n, 3) float32 points in the camera frame, metres.
    """
    K = check_K(K)
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    z = np.asarray(z_m, dtype=np.float64)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=-1).astype(np.float32)


def backproject_depth(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project a whole depth image: (H, W) metres -> (H, W, 3) camera-frame points (0 where no data)."""
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w]
    pts = backproject_pixels(u.ravel(), v.ravel(), depth_m.ravel(), K)
    return pts.reshape(h, w, 3)


def clamp_box(box_xyxy: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray | None:
    """Clamp a box to the image and round it outward to integer pixel bounds.

    :param box_xyxy: (4,) x1, y1, x2, y2 in pixels (x2, y2 exclusive edges).
    :param image_hw: (H, W).
    :return: (4,) int64 x1, y1, x2, y2 with 0 <= x1 < x2 <= W, 0 <= y1 < y2 <= H,
        or None when the box does not overlap the image or is not finite.
    """
    box = np.asarray(box_xyxy, dtype=np.float64)
    if box.shape != (4,):
        raise ValueError(f"box must be (4,) x1, y1, x2, y2, got shape {box.shape}")
    if not np.all(np.isfinite(box)):
        return None
    h, w = int(image_hw[0]), int(image_hw[1])
    x1 = int(np.clip(np.floor(box[0]), 0, w))
    y1 = int(np.clip(np.floor(box[1]), 0, h))
    x2 = int(np.clip(np.ceil(box[2]), 0, w))
    y2 = int(np.clip(np.ceil(box[3]), 0, h))
    if x2 <= x1 or y2 <= y1:
        return None
    return np.array([x1, y1, x2, y2], dtype=np.int64)


def crop(image: np.ndarray, box_xyxy_int: np.ndarray) -> np.ndarray:
    """Crop an image (H, W[, C]) to a clamped integer box from `clamp_box` (a view, not a copy)."""
    x1, y1, x2, y2 = (int(c) for c in box_xyxy_int)
    return image[y1:y2, x1:x2]


def select_pixels(depth_m: np.ndarray, box_xyxy_int: np.ndarray, mask: np.ndarray | None = None,
                  min_depth_m: float = 0.0, max_depth_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pixels for the point cloud of one object (paper 3.1.3).

    Pixels of `mask` when one is given, else every pixel of the box; in both cases only pixels
    with valid depth in [min_depth_m, max_depth_m] (and > 0) inside the box.

    :param depth_m: (H, W) float metres, 0 = no data.
    :param box_xyxy_int: (4,) clamped integer box.
    :param mask: optional (H, W) bool mask of the object in the full image.
    :return: (v, u) int64 arrays of image rows and columns, in row-major order.
    """
    x1, y1, x2, y2 = (int(c) for c in box_xyxy_int)
    d = depth_m[y1:y2, x1:x2]
    valid = (d > 0) & (d >= min_depth_m) & (d <= max_depth_m) & np.isfinite(d)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != depth_m.shape:
            raise ValueError(f"mask shape {mask.shape} does not match depth shape {depth_m.shape}")
        valid &= mask[y1:y2, x1:x2].astype(bool)
    v, u = np.nonzero(valid)
    return v.astype(np.int64) + y1, u.astype(np.int64) + x1


def sample_indices(n_available: int, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """Choose `n_points` of `n_available` candidates (paper 3.1.3).

    Uniformly without repetition when there are enough; otherwise every candidate once plus a
    uniform draw with repetition to fill up (oversampling), so no candidate is lost.

    :return: (n_points,) int64 indices into the candidates; empty when `n_available` is 0.
    """
    if n_points <= 0:
        raise ValueError(f"n_points must be positive, got {n_points}")
    if n_available < 0:
        raise ValueError(f"n_available must be >= 0, got {n_available}")
    if n_available == 0:
        return np.zeros((0,), dtype=np.int64)
    if n_available >= n_points:
        return rng.choice(n_available, size=n_points, replace=False).astype(np.int64)
    extra = rng.integers(0, n_available, size=n_points - n_available)
    idx = np.concatenate([np.arange(n_available), extra])
    rng.shuffle(idx)
    return idx.astype(np.int64)


def quat_to_rot(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) as (w, x, y, z) -> rotation matrices (..., 3, 3). Normalises the input."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have 4 components (w, x, y, z), got shape {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("quaternion has zero or non-finite norm")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,) as (w, x, y, z) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"rotation must be 3x3, got shape {R.shape}")
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.empty(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 rigid transform from R (3, 3) and t (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (uses R^T, not a general inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points.

    :param T: (4, 4), or (B, 4, 4) with pts (B, n, 3).
    :param pts: (n, 3) or (B, n, 3).
    """
    T = np.asarray(T, dtype=np.float64)
    pts = np.asarray(pts)
    if pts.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got shape {pts.shape}")
    R, t = T[..., :3, :3], T[..., :3, 3]
    return pts @ np.swapaxes(R, -1, -2) + t[..., None, :]


def project_points(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Project camera-frame points (n, 3) to pixels (n, 2) as (u, v); points with z <= 0 give NaN."""
    K = check_K(K)
    pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    z = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pts @ K.T)[:, :2] / z[:, None]
    uv[z <= 0] = np.nan
    return uv
