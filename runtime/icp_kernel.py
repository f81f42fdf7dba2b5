"""The compiled ICP kernel (`icp_kernel.c`): refinement's point-to-plane ICP at compiled speed.

The package builds it as an optional C extension (setup.py) and loads it here with ctypes: no Python C API,
a library of a few tens of kB, loaded in well under a millisecond. Where no C compiler was at hand when the
package was built, `available()` is False and `refine` runs the same algorithm in numpy (several times
slower; the estimator logs a warning then, and the latency benchmark says which one ran).
"""
from __future__ import annotations

import ctypes
import functools
import importlib.util
import logging

import numpy as np

__all__ = ["available", "icp", "library_path", "MAX_BOXES"]

log = logging.getLogger(__name__)

_MODULE = "pallet6d.runtime._icp_kernel"
MAX_BOXES = 256                      # boxes of one pallet model the kernel takes (icp_kernel.c)
_f64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
_f32 = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
_i64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
_u8 = np.ctypeslib.ndpointer(np.uint8, flags="C_CONTIGUOUS")
_i = ctypes.c_int64
_d = ctypes.c_double


def library_path() -> str | None:
    """Path of the built kernel (an extension-module file of this package), or None when it was not built."""
    try:
        spec = importlib.util.find_spec(_MODULE)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.origin else None


@functools.lru_cache(maxsize=1)
def _function():
    """The kernel's C function with its argument types, or None when the library is missing or will not load."""
    path = library_path()
    if path is None:
        return None
    try:
        fn = ctypes.CDLL(path).pallet6d_icp
    except (OSError, AttributeError) as e:
        log.warning("compiled ICP kernel %s does not load (%s): refinement runs in numpy", path, e)
        return None
    fn.restype = ctypes.c_int
    fn.argtypes = [_i, _i, _f32, _i64, _i, _f64, _f64, _f64, _i, _d, _d, _i, _d, ctypes.c_void_p, _d, _i,
                   _f64, _i64, _i64, _f64, _u8, _u8]
    return fn


def available() -> bool:
    """Whether the compiled kernel is built and loads."""
    return _function() is not None


def icp(T0: np.ndarray, pts: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray, prior: np.ndarray,
        iterations: int, corr_start_m: float, corr_end_m: float, min_inliers: int, tol: float,
        stop_near: np.ndarray | None, stop_near_m: float, threads: int = 1) -> tuple[np.ndarray, ...]:
    """ICP from P poses at once, each on its own points (the arguments as `refine._icp` takes them).

    :param T0: (P, 4, 4) starting poses, pallet -> camera. :param pts: (P, N, 3) camera frame, metres; pose i
        uses its first `n_pts[i]` rows. :param boxes_m: (k, 2, 3) min/max corners, pallet frame, 1 <= k <= MAX_BOXES.
    :param prior: (P, 6) the prior's inverse variances (rotation about, then translation along, x y z).
    :param stop_near: None or (P, 4, 4): a pose per start at which it stops.
    :param threads: the poses are shared among this many threads (each pose's result does not depend on it).
    :return: (T_cam_pallet (P, 4, 4), iterations (P,), n_inliers (P,), rms_m (P,), converged (P,) bool,
        stopped_near (P,) bool).
    :raises RuntimeError: when the kernel is not available (check `available()` first).
    """
    fn = _function()
    if fn is None:
        raise RuntimeError("the compiled ICP kernel is not built (pallet6d.runtime.icp_kernel.available())")
    T0 = np.ascontiguousarray(T0, dtype=np.float64)
    m = len(T0)
    pts = np.ascontiguousarray(pts, dtype=np.float32)
    n_pts = np.ascontiguousarray(n_pts, dtype=np.int64)
    boxes = np.ascontiguousarray(boxes_m, dtype=np.float64)
    prior = np.ascontiguousarray(np.broadcast_to(prior, (m, 6)), dtype=np.float64)
    if pts.ndim != 3 or pts.shape[0] != m or pts.shape[2] != 3 or n_pts.shape != (m,) \
            or np.any(n_pts > pts.shape[1]) or np.any(n_pts < 0):
        raise ValueError(f"pts must be ({m}, N, 3) with 0 <= n_pts <= N, got {pts.shape} and n_pts {n_pts.shape}")
    near = None if stop_near is None else np.ascontiguousarray(np.broadcast_to(stop_near, (m, 4, 4)),
                                                               dtype=np.float64)
    T_out = np.empty((m, 4, 4))
    done, n_in = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    rms = np.empty(m)
    converged, stopped = np.empty(m, dtype=np.uint8), np.empty(m, dtype=np.uint8)
    rc = fn(m, pts.shape[1], pts, n_pts, len(boxes), boxes, T0, prior, int(iterations), float(corr_start_m),
            float(corr_end_m), int(min_inliers), float(tol), None if near is None else near.ctypes.data,
            float(stop_near_m), max(int(threads), 1), T_out, done, n_in, rms, converged, stopped)
    if rc == -1:
        raise ValueError(f"the compiled ICP kernel takes 1 to {MAX_BOXES} boxes, got {len(boxes)}")
    if rc != 0:
        raise MemoryError("the compiled ICP kernel could not allocate its work area")
    return T_out, done, n_in, rms, converged.astype(bool), stopped.astype(bool)
