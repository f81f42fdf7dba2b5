"""The runtime's compiled kernels (`kernels.c`): refinement's point-to-plane ICP (`icp`), the fit scores (`fit`),
the levelled refinement's moves along the viewing rays and its ray scores (`along_rays`, `ray_scores`), the
structure check's rays (`cast_rays`) and the registration test's pair counts (`registration_counts`), the per-point
loops that numpy runs as thousands of small calls a frame.

The package builds them as an optional C extension (setup.py) and loads it here with ctypes: no Python C API,
a library of a few tens of kB, loaded in well under a millisecond. Where no C compiler was at hand when the
package was built, `available()` is False and `refine`, `fit` and `registration` run the same algorithms in numpy
(several times slower; the estimator logs a warning then, and the latency benchmark says which one ran).
"""
from __future__ import annotations

import ctypes
import functools
import importlib.util
import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["along_rays", "available", "box_grid", "BoxGrid", "cast_rays", "fit", "icp", "library_path", "MAX_BOXES",
           "ray_scores", "registration_counts"]

log = logging.getLogger(__name__)

_MODULE = "pallet6d.runtime._kernels"
MAX_BOXES = 256                      # boxes of one pallet model the kernel takes (kernels.c)
_f64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
_f32 = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
_i64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
_u8 = np.ctypeslib.ndpointer(np.uint8, flags="C_CONTIGUOUS")
_ptr = ctypes.c_void_p
_i = ctypes.c_int64
_d = ctypes.c_double
ABI = 4                              # kernels.c's PALLET6D_KERNELS_ABI: the signatures below


def library_path() -> str | None:
    """Path of the built kernel (an extension-module file of this package), or None when it was not built."""
    try:
        spec = importlib.util.find_spec(_MODULE)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.origin else None


# each C function's argument types (all return an int status)
_ARGTYPES = {
    "pallet6d_icp": [_i, _i, _f32, _i64, _i, _f64, _f64, _f64, _i, _d, _d, _i, _d, _ptr, _d,
                     _ptr, _d, _ptr, _ptr, _ptr, _i, _f64, _i64, _i64, _f64, _u8, _u8],
    "pallet6d_fit": [_i, _i, _f64, _i64, _f64, _i, _f64, _f64, _f64, _i, _ptr, _i, _ptr, _ptr, _d, _ptr, _ptr, _ptr,
                     _f32, _i, _i, _f64, _d, _i, _f64, _f64],
    "pallet6d_registration_counts": [_f32, _i, _i, _i, _i, _i, _i, _u8, _i64, _i64, _i, _i, _i, _d, _d, _i, _i64,
                                     _i64],
    "pallet6d_ray_scores": [_i, _f64, _i, _f64, _i, _f64, _d, _i, _i, _f64],
    "pallet6d_along_rays": [_i, _f64, _i, _f64, _i64, _i, _f64, _d, _i, _f64, _i64, _f64, _f64],
    "pallet6d_cast_rays": [_i, _i, _f64, _f64, _i64, _i64, _f64, _f64, _f64],
}


@functools.lru_cache(maxsize=1)
def _functions() -> dict | None:
    """The library's C functions with their argument types, or None when it is missing or will not load."""
    path = library_path()
    if path is None:
        return None
    try:
        lib = ctypes.CDLL(path)
        out = {name: getattr(lib, name) for name in _ARGTYPES}
        abi = lib.pallet6d_kernels_abi
    except (OSError, AttributeError) as e:
        log.warning("the compiled kernels %s do not load (%s): refinement runs in numpy", path, e)
        return None
    abi.restype, abi.argtypes = ctypes.c_int, []
    if abi() != ABI:
        log.warning("the compiled kernels %s were built from another version of kernels.c (ABI %d, not %d; "
                    "reinstall the package to rebuild them): refinement runs in numpy", path, abi(), ABI)
        return None
    for name, fn in out.items():
        fn.restype, fn.argtypes = ctypes.c_int, _ARGTYPES[name]
    return out


def _function(name: str):
    """One C function of the library; RuntimeError when the kernels are not available."""
    fns = _functions()
    if fns is None:
        raise RuntimeError("the compiled kernels are not built (pallet6d.runtime.kernels.available())")
    return fns[name]


def available() -> bool:
    """Whether the compiled kernels are built and load."""
    return _functions() is not None


@dataclass(frozen=True, eq=False)
class BoxGrid:
    """The boxes that can hold the closest surface point for any point of each cell of a grid over a pallet
    model (pallet frame): ICP then measures a point against a few boards and blocks instead of all of them.

    :ivar origin_m: (3,) the grid's lowest corner. :ivar cell_m: cell edge. :ivar dims: (3,) cells per axis.
    :ivar offsets: (n_cells + 1,) int32: cell c (x-major) lists `lists[offsets[c]:offsets[c + 1]]`.
    :ivar lists: uint8 box indices, ascending within a cell.
    """

    origin_m: np.ndarray
    cell_m: float
    dims: np.ndarray
    offsets: np.ndarray
    lists: np.ndarray


def box_grid(boxes_m: np.ndarray, margin_m: float = 0.1, cell_m: float = 0.03) -> BoxGrid:
    """The `BoxGrid` of a union of boxes, over their bounding box grown by `margin_m`.

    A box is listed for a cell unless it is certainly farther from every point of the cell than some other box:
    its smallest distance to the cell (0 where they overlap) exceeds the smallest, over the boxes, of the largest
    distance from a point of the cell (outside distance at the cell's farthest corner; inside a box, at most half
    its thinnest extent). The closest box, as the kernel measures it, is therefore always listed.

    :param boxes_m: (k, 2, 3) min/max corners, 1 <= k <= MAX_BOXES. :param margin_m: points farther out are
        measured against every box. :param cell_m: cell edge, metres.
    """
    boxes = np.asarray(boxes_m, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or not 1 <= len(boxes) <= MAX_BOXES:
        raise ValueError(f"boxes_m must be (k, 2, 3) with 1 <= k <= {MAX_BOXES}, got shape {boxes.shape}")
    if not (cell_m > 0 and margin_m >= 0):
        raise ValueError(f"need cell_m > 0 and margin_m >= 0, got {cell_m}, {margin_m}")
    origin = boxes[:, 0].min(0) - margin_m
    dims = np.ceil((boxes[:, 1].max(0) + margin_m - origin) / cell_m).astype(np.int64)
    idx = np.stack(np.meshgrid(*(np.arange(d) for d in dims), indexing="ij"), -1).reshape(-1, 3)
    c_lo = origin + idx * cell_m                                              # (cells, 3)
    c_hi = c_lo + cell_m

    def bounds(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(cells,) smallest and largest distance, as the kernel measures it, from the cells' points to one box."""
        lower = np.sqrt((np.maximum(np.maximum(lo - c_hi, c_lo - hi), 0.0) ** 2).sum(-1))
        gap_far = np.maximum(np.maximum(lo - c_lo, c_lo - hi), np.maximum(lo - c_hi, c_hi - hi))
        upper = np.sqrt((np.maximum(gap_far, 0.0) ** 2).sum(-1))
        return lower, np.where(lower > 0.0, upper, np.maximum(upper, (hi - lo).min() / 2))

    # one box at a time: (cells, k, 3) temporaries would cost tens of MB of peak memory on a forklift computer
    nearest_far = np.full(len(idx), np.inf)
    for lo, hi in boxes:
        nearest_far = np.minimum(nearest_far, bounds(lo, hi)[1])
    # 1e-5 m: float32 rounding in the kernel (its points and boxes) can only add boxes, never drop the closest
    listed = np.stack([bounds(lo, hi)[0] <= nearest_far + 1e-5 for lo, hi in boxes], 1)     # (cells, k)
    offsets = np.zeros(len(listed) + 1, dtype=np.int32)
    np.cumsum(listed.sum(1), out=offsets[1:])
    lists = np.nonzero(listed)[1].astype(np.uint8)                            # row-major: ascending per cell
    return BoxGrid(origin, float(cell_m), dims, offsets, lists)


def icp(T0: np.ndarray, pts: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray, prior: np.ndarray,
        iterations: int, corr_start_m: float, corr_end_m: float, min_inliers: int, tol: float,
        stop_near: np.ndarray | None, stop_near_m: float, threads: int = 1,
        grid: BoxGrid | None = None) -> tuple[np.ndarray, ...]:
    """ICP from P poses at once, each on its own points (the arguments as `refine._icp` takes them).

    :param T0: (P, 4, 4) starting poses, pallet -> camera. :param pts: (P, N, 3) camera frame, metres; pose i
        uses its first `n_pts[i]` rows. :param boxes_m: (k, 2, 3) min/max corners, pallet frame, 1 <= k <= MAX_BOXES.
    :param prior: (P, 6) the prior's inverse variances (rotation about, then translation along, x y z).
    :param stop_near: None or (P, 4, 4): a pose per start at which it stops.
    :param threads: the poses are shared among this many threads (each pose's result does not depend on it).
    :param grid: `box_grid(boxes_m)`, or None to measure every point against every box (the same result).
    :return: (T_cam_pallet (P, 4, 4), iterations (P,), n_inliers (P,), rms_m (P,), converged (P,) bool,
        stopped_near (P,) bool).
    :raises RuntimeError: when the kernel is not available (check `available()` first).
    """
    fn = _function("pallet6d_icp")
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
    g = None if grid is None else (np.ascontiguousarray(grid.origin_m, dtype=np.float64),
                                   np.ascontiguousarray(grid.dims, dtype=np.int64),
                                   np.ascontiguousarray(grid.offsets, dtype=np.int32),
                                   np.ascontiguousarray(grid.lists, dtype=np.uint8))
    if g is not None and (g[0].shape != (3,) or g[1].shape != (3,) or len(g[2]) != int(np.prod(g[1])) + 1
                          or g[2][-1] != len(g[3]) or (len(g[3]) and int(g[3].max()) >= len(boxes))):
        raise ValueError("grid does not fit these boxes: build it with box_grid(boxes_m)")
    rc = fn(m, pts.shape[1], pts, n_pts, len(boxes), boxes, T0, prior, int(iterations), float(corr_start_m),
            float(corr_end_m), int(min_inliers), float(tol), None if near is None else near.ctypes.data,
            float(stop_near_m), *((None, 0.0, None, None, None) if g is None else
                                  (g[0].ctypes.data, grid.cell_m, g[1].ctypes.data, g[2].ctypes.data,
                                   g[3].ctypes.data)),
            max(int(threads), 1), T_out, done, n_in, rms, converged, stopped)
    if rc == -1:
        raise ValueError(f"the compiled ICP kernel takes 1 to {MAX_BOXES} boxes, got {len(boxes)}")
    if rc != 0:
        raise MemoryError("the compiled ICP kernel could not allocate its work area")
    return T_out, done, n_in, rms, converged.astype(bool), stopped.astype(bool)


def fit(T: np.ndarray, obs: np.ndarray, n_obs: np.ndarray, model_pts: np.ndarray, lo: np.ndarray, hi: np.ndarray,
        boxes_m: np.ndarray | None, in_boxes_m: np.ndarray | None, index, depth_m: np.ndarray, K: np.ndarray,
        tol_m: float, cell_px: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """`fit.fit_scores`' inlier fractions and free-space violations of P poses (its arguments, checked there).

    :param T: (P, 4, 4) model -> camera. :param obs: (P, N, 3) camera frame; pose i uses its first `n_obs[i]` rows.
    :param model_pts: (m, 3) model frame. :param lo, hi: (3,) the box around the model for the inlier pre-test.
    :param boxes_m: (k, 2, 3) distances to these boxes, or None for distances to the points (then `in_boxes_m`,
        optional, a pre-test, and `index`, an optional `fit.ModelPointIndex`, the search).
    :param depth_m: (H, W) float32 metres, C-contiguous (the caller converts). :param K: (3, 3).
    :return: (inlier_fraction (P,), free_space_violation (P,)).
    """
    fn = _function("pallet6d_fit")
    c64 = functools.partial(np.ascontiguousarray, dtype=np.float64)
    T, obs, model, lo, hi, K = c64(T), c64(obs), c64(model_pts), c64(lo), c64(hi), c64(K)
    n_obs = np.ascontiguousarray(n_obs, dtype=np.int64)
    if depth_m.dtype != np.float32 or not depth_m.flags.c_contiguous:
        raise ValueError("depth_m must be C-contiguous float32")
    keep = []                                              # arrays passed by address must outlive the call

    def ptr(a, dtype=np.float64):
        if a is None:
            return None
        a = np.ascontiguousarray(a, dtype=dtype)
        keep.append(a)
        return a.ctypes.data

    P = len(T)
    inlier, violation = np.empty(P), np.empty(P)
    idx = (None, 0.0, None, None, None) if index is None else (
        ptr(index.origin), float(index.tol_m), ptr(index.shape, np.int64), ptr(index.offsets, np.int64),
        ptr(index.points))
    rc = fn(P, obs.shape[1], obs, n_obs, T, len(model), model, lo, hi, 0 if boxes_m is None else len(boxes_m),
            ptr(boxes_m), 0 if in_boxes_m is None else len(in_boxes_m), ptr(in_boxes_m), *idx, depth_m,
            depth_m.shape[0], depth_m.shape[1], K, float(tol_m), int(cell_px), inlier, violation)
    if rc != 0:
        raise MemoryError("the compiled fit-score kernel could not allocate its z-buffer")
    return inlier, violation


def _check_boxes(boxes_m: np.ndarray) -> None:
    if len(boxes_m) > MAX_BOXES:
        raise ValueError(f"the kernels take pallet models of at most {MAX_BOXES} boxes, got {len(boxes_m)}")


def along_rays(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray,
               window_m: float, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pose's points whose depth lies within `window_m` of the posed boxes' first surface along their viewing
    rays: how many, the median of those residuals and the sum of their unit viewing directions
    (`pallet6d_along_rays` in kernels.c; `level._along_rays`' numpy path is the specification).

    :param T_cam_pallet: (P, 4, 4). :param pts_cam: (P, N, 3) camera frame, metres; pose i uses its first `n_pts[i]`
        rows. :param boxes_m: (k, 2, 3). :param threads: the poses are shared among this many threads (the same
        results).
    :return: count (P,) int64, median residual (P,) metres (0 where the count is 0; > 0: beyond the surface), summed
        unit directions (P, 3), camera frame.
    """
    fn = _function("pallet6d_along_rays")
    c64 = functools.partial(np.ascontiguousarray, dtype=np.float64)
    T, pts, boxes = c64(T_cam_pallet).reshape(-1, 4, 4), c64(pts_cam), c64(boxes_m).reshape(-1, 2, 3)
    if pts.ndim != 3 or pts.shape[0] != len(T) or pts.shape[2] != 3:
        raise ValueError(f"pts_cam must be ({len(T)}, N, 3), got shape {pts.shape}")
    n = np.ascontiguousarray(np.clip(n_pts, 0, pts.shape[1]), dtype=np.int64).reshape(len(T))
    _check_boxes(boxes)
    P = len(T)
    count, shift, ray = np.zeros(P, dtype=np.int64), np.zeros(P), np.zeros((P, 3))
    fn(P, T, pts.shape[1], pts, n, len(boxes), boxes, float(window_m), max(int(threads), 1),
       np.empty(pts.shape[:2]), count, shift, ray)
    return count, shift, ray


def cast_rays(origin: np.ndarray, dirs: np.ndarray, boxes_m: np.ndarray, box_start: np.ndarray,
              box_count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`structure.cast_rays_boxes` for poses that may each have their own boxes (`pallet6d_cast_rays` in kernels.c).

    :param origin: (P, 3) ray origins in each pose's pallet frame. :param dirs: (P, R, 3) ray directions.
    :param boxes_m: (K, 2, 3) min / max corners of every box set, one after the other (`structure.BoxSets`).
    :param box_start, box_count: (P,) pose i's boxes are `boxes_m[box_start[i]:box_start[i] + box_count[i]]`.
    :return: (P, R) parameter of the first box hit (inf when none), (P, R) where the ray enters the boxes' bounding
        box (inf when it misses it).
    """
    fn = _function("pallet6d_cast_rays")
    c64 = functools.partial(np.ascontiguousarray, dtype=np.float64)
    o, d, boxes = c64(origin).reshape(-1, 3), c64(dirs), c64(boxes_m).reshape(-1, 2, 3)
    if d.ndim != 3 or d.shape[0] != len(o) or d.shape[2] != 3:
        raise ValueError(f"dirs must be ({len(o)}, R, 3), got shape {d.shape}")
    start = np.ascontiguousarray(box_start, dtype=np.int64).reshape(len(o))
    count = np.ascontiguousarray(box_count, dtype=np.int64).reshape(len(o))
    if len(o) and (start.min() < 0 or count.min() < 1 or count.max() > MAX_BOXES
                   or (start + count).max() > len(boxes)):
        raise ValueError(f"each pose needs 1 to {MAX_BOXES} boxes within the {len(boxes)} given, got starts "
                         f"{start.min()}..{start.max()} and counts {count.min()}..{count.max()}")
    t_box, t_bbox = np.empty(d.shape[:2]), np.empty(d.shape[:2])
    fn(len(o), d.shape[1], o, d, start, count, boxes, t_box, t_bbox)
    return t_box, t_bbox


def ray_scores(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, boxes_m: np.ndarray, window_m: float,
               threads: int = 1, soft: bool = False) -> np.ndarray:
    """`level`'s ray scores of P poses on the same observed points (`pallet6d_ray_scores` in kernels.c).

    :param T_cam_pallet: (P, 4, 4). :param pts_cam: (m, 3) camera frame, metres. :param boxes_m: (k, 2, 3).
    :param threads: the poses are shared among this many threads (the same scores).
    :param soft: the mean of 1 - (residual / window)^2 over the points within the window, no penalty beyond
        (`level.ray_scores`).
    :return: (P,) scores in [-1, 1].
    """
    fn = _function("pallet6d_ray_scores")
    c64 = functools.partial(np.ascontiguousarray, dtype=np.float64)
    T, pts, boxes = c64(T_cam_pallet).reshape(-1, 4, 4), c64(pts_cam).reshape(-1, 3), c64(boxes_m).reshape(-1, 2, 3)
    _check_boxes(boxes)
    out = np.empty(len(T))
    fn(len(T), T, len(pts), pts, len(boxes), boxes, float(window_m), int(bool(soft)), max(int(threads), 1), out)
    return out


def registration_counts(pad: np.ndarray, m: int, step: int, inside: np.ndarray, diff_x: np.ndarray,
                        diff_y: np.ndarray, a: int, dy: int, dx: int, tol_m: float, tol_quad_per_m: float,
                        levels: int) -> tuple[np.ndarray, np.ndarray]:
    """`registration.registration_score`'s pair counts at one shift of the depth: histograms of the colour
    differences of the pairs whose depth jumps and of the others (its arguments, named as there).

    :param pad: (H', W') float32 depth around the grid; grid pixel (iy, ix) at (m + iy * step, m + ix * step).
    :param inside: (ny, nx) uint8 grid mask. :param diff_x, diff_y: (ny, nx) int64 colour differences in [0, levels).
    :return: (pos (levels,), neg (levels,)) int64 counts.
    """
    fn = _function("pallet6d_registration_counts")
    pad = np.ascontiguousarray(pad, dtype=np.float32)
    inside = np.ascontiguousarray(inside, dtype=np.uint8)
    diff_x = np.ascontiguousarray(diff_x, dtype=np.int64)
    diff_y = np.ascontiguousarray(diff_y, dtype=np.int64)
    if not (inside.shape == diff_x.shape == diff_y.shape and inside.ndim == 2 and pad.ndim == 2):
        raise ValueError(f"inside, diff_x, diff_y must share one (ny, nx) shape, got {inside.shape}, "
                         f"{diff_x.shape}, {diff_y.shape}")
    pos, neg = np.zeros(levels, dtype=np.int64), np.zeros(levels, dtype=np.int64)
    rc = fn(pad, pad.shape[0], pad.shape[1], int(m), int(step), inside.shape[0], inside.shape[1], inside, diff_x,
            diff_y, int(a), int(dy), int(dx), float(tol_m), float(tol_quad_per_m), int(levels), pos, neg)
    if rc != 0:
        raise ValueError("registration_counts: a read leaves the padded depth or a colour difference is out of range")
    return pos, neg
