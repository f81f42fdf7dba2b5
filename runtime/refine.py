"""Pose refinement: robust point-to-plane ICP of the observed depth onto the pallet's box model (numpy, and the
same ICP compiled: `kernels`).

The network's pose is a good first guess (a few cm, a few degrees); the depth points of the detection then
pin it down, as classical registration does after PoseCNN or DenseFusion. A pallet is a union of boards and
blocks, so the closest model surface point and its normal are exact and cheap (no k-d tree, no mesh).

Points of the box that are not pallet (floor, rack, load, what shows through the fork pockets) must not pull
the pose: only correspondences within a distance that shrinks over the iterations count, each with a Tukey
weight, and a prior on the network's pose keeps directions the visible surfaces do not constrain (sliding
along a single visible face) where the network put them.

Measured on the simulator: from poses a few cm / degrees off, exact depth brings most back to < 1 mm (a
few stop in a local minimum about 2 cm off, where boards repeat); D435-like depth at 3-5 m (sigma of
several cm, half of it correlated over patches) leaves several cm, which is the data's own limit.
From 15-30 degrees or 10-20 cm off, ICP stops in a wrong minimum: `best_landing` runs it again from
starts around the pose (`start_offsets`, batched by `refine_poses`) and a fit score picks the landing.

`refine_batch` does all of it for every detection of a frame at once: ICP from the network's poses, the
gate, the starts and the landings' choice, each one pass over padded arrays (docs/refinement.md). ICP itself
runs in the compiled kernel when the package has it, else one numpy pass per step.
"""
from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from . import kernels
from .fit import ModelPointIndex, check_poses, distance_to_boxes, fit_scores
from .geometry import backproject_pixels, check_K, clamp_box, select_pixels, transform_points
from .results import FitScore

__all__ = ["best_landing", "box_points", "closest_on_boxes", "default_starts", "FrameRefinement", "offsets_from_starts",
           "refine_batch", "RefineGeometry", "RefineOptions", "RefineResult", "refine_pose", "refine_poses",
           "start_offsets"]


def box_points(depth_m: np.ndarray, K: np.ndarray, box_xyxy: np.ndarray, max_points: int,
               depth_range_m: tuple[float, float]) -> np.ndarray:
    """Observed points of a detection box for refinement: every valid pixel, thinned by an even stride.

    :return: (n, 3) camera frame, metres, n <= max_points (0 when the box holds no valid depth).
    """
    box_i = clamp_box(box_xyxy, depth_m.shape)
    if box_i is None:
        return np.zeros((0, 3))
    v, u = select_pixels(depth_m, box_i, None, depth_range_m[0], depth_range_m[1])
    if len(v) > max_points:
        keep = np.linspace(0, len(v) - 1, max_points).round().astype(np.int64)  # deterministic, spread over the box
        v, u = v[keep], u[keep]
    return backproject_pixels(u, v, depth_m[v, u], K)


def _check_boxes(boxes_m: np.ndarray) -> np.ndarray:
    """(k, 2, 3) float64 min/max corners with k >= 1, or ValueError."""
    boxes = np.asarray(boxes_m, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0:
        raise ValueError(f"boxes_m must be (k, 2, 3) with k >= 1, got shape {boxes.shape}")
    return boxes


def closest_on_boxes(pts: np.ndarray, boxes_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on the surface of a union of axis-aligned boxes, with its outward normal.

    Inside a box the nearest face of that box counts (faces shared by touching boxes are rare targets:
    observed points lie on the outer surface).

    :param pts: (n, 3) points in the boxes' frame, metres.
    :param boxes_m: (k, 2, 3) min and max corners.
    :return: (closest (n, 3), unit normal (n, 3), distance (n,)) in metres.
    """
    boxes = _check_boxes(boxes_m)
    return _closest(np.asarray(pts, dtype=np.float64).reshape(-1, 3), boxes, _extents(boxes))


def _extents(boxes: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis, the distinct (min, max) extents of the boxes (u, 2) and each box's extent (k,)."""
    out = []
    for a in range(3):
        extent, box_col = np.unique(boxes[:, :, a], axis=0, return_inverse=True)
        out.append((extent, box_col.reshape(-1)))
    return out


def _finish(p: np.ndarray, lo_hi: np.ndarray, d: np.ndarray,
            off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point and outward normal of (n, 3) points on their chosen boxes `lo_hi` (n, 2, 3), at distance
    d (n,): clamped into the box where the point is off it (`off`: its outside distance to the box is > 0),
    else moved to the box's nearest face (the first of -x -y -z +x +y +z)."""
    lo, hi = lo_hi[:, 0], lo_hi[:, 1]
    q = np.minimum(np.maximum(p, lo), hi)                         # np.clip's arithmetic, without its overhead
    face = np.flatnonzero(~off)
    if len(face) == 0:
        return q, np.divide(p - q, d[:, None]), d
    # off the box the normal points from q to p; in it p - q is exactly 0 (q is p): the face sets one axis below
    normal = (p - q) / np.where(off, d, 1.0)[:, None]
    pf, lf, hf = p.take(face, 0), lo.take(face, 0), hi.take(face, 0)
    f = np.concatenate([pf - lf, hf - pf], axis=1).argmin(1)
    axis, positive = f % 3, f >= 3
    own = np.arange(0, 3 * len(face), 3) + axis                   # flat (face row, axis)
    at = face * 3 + axis                                          # flat (point, axis)
    q.reshape(-1)[at] = np.where(positive, hf.take(own), lf.take(own))
    normal.reshape(-1)[at] = np.where(positive, 1.0, -1.0)
    return q, normal, d


def _argmin_rows(a: np.ndarray) -> np.ndarray:
    """`a.argmin(0)` of a (k, n) array of non-negative values (the first row wins ties).

    numpy's argmin along the first axis is several times slower than its min there (ICP calls this for every
    point at every step); for float32 the min of (value bits << b | row) finds the same row, since the bits of
    non-negative float32 values order as the values do (the sign bit is dropped: -0.0 counts as 0.0).
    """
    if a.dtype != np.float32 or len(a) < 2:
        return a.argmin(0)
    bits = int(len(a) - 1).bit_length()
    key = (a.view(np.int32) & 0x7FFFFFFF).astype(np.int64)
    key <<= bits
    key |= np.arange(len(a))[:, None]
    return key.min(0) & ((1 << bits) - 1)


def _closest(p: np.ndarray, boxes: np.ndarray,
             extents: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`closest_on_boxes` of (n, 3) points, with the boxes' `_extents` (both float64, or both float32 in ICP)."""
    n = len(p)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    # squared distance outside each box, one axis at a time: a pallet's boards and blocks share few distinct
    # extents per axis (EPAL: 16 over the three axes for 20 boxes), so each axis' squared gap is computed once
    # per distinct extent and gathered per box (ICP calls this every iteration for every point). Arrays are
    # (boxes, points): numpy's inner loops then run along the points; rows are gathered with `take` (numpy's
    # fancy indexing of short rows costs ten times more).
    p_axes = np.ascontiguousarray(p.T)                           # (3, n)
    for a, (extent, box_col) in enumerate(extents):
        pa = p_axes[a]
        gap = np.subtract(extent[:, 0, None], pa)
        np.maximum(gap, pa - extent[:, 1, None], out=gap)
        np.maximum(gap, 0.0, out=gap)
        np.multiply(gap, gap, out=gap)                        # squares >= +0: 0 + x is x exactly
        if a == 0:
            d_out2 = gap.take(box_col, 0)                     # (k, n)
        else:
            d_out2 += gap.take(box_col, 0)
    j = _argmin_rows(d_out2)                                 # nearest box per point
    d = np.sqrt(d_out2.take(j * n + np.arange(n)))
    off = d > 0.0
    ins = np.flatnonzero(~off)
    if len(ins):
        # inside a box: its nearest face is a candidate at the depth below it, every box the point is outside
        # of at its outside distance (boxes may overlap); the nearest wins
        m = len(ins)
        o2 = d_out2.take(ins, 1)                                 # (k, m)
        dist = np.sqrt(o2)
        held = ~(o2 > 0.0)                                       # the boxes each point is in
        # the box found above holds the point: its depth below its nearest face (one box, not all of them)
        first, pi = j.take(ins), p.take(ins, 0)
        lo_hi = boxes.take(first, 0)
        below = np.minimum(pi - lo_hi[:, 0], lo_hi[:, 1] - pi)               # (m, 3)
        dist.reshape(-1)[first * m + np.arange(m)] = np.maximum(
            np.minimum(np.minimum(below[:, 0], below[:, 1]), below[:, 2]), 0.0)
        multi = np.flatnonzero(held.sum(0) > 1)                  # in touching or overlapping boxes: each depth
        if len(multi):
            d_in = np.full((len(boxes), len(multi)), np.inf)     # depth below each box's nearest face
            for a, (extent, box_col) in enumerate(extents):
                pa = p_axes[a].take(ins.take(multi))
                below = np.minimum(pa - extent[:, 0, None], extent[:, 1, None] - pa)
                np.minimum(d_in, below.take(box_col, 0), out=d_in)
            dist[:, multi] = np.where(held[:, multi], np.maximum(d_in, 0.0), dist[:, multi])
        ji = _argmin_rows(dist)
        at = ji * m + np.arange(m)
        j[ins], d[ins], off[ins] = ji, dist.take(at), o2.take(at) > 0.0
    return _finish(p, boxes.take(j, 0), d, off)


# ICP's per-point arithmetic (closest points, residuals, Jacobians) runs in float32: half the memory traffic
# of float64, and far finer than depth noise (1e-7 relative: under a micrometre at 10 m); sums and the 6x6
# solve stay float64.
_ICP_DTYPE = np.float32


# Extra ICP starts around a pose, in the pallet frame (applied on the right: T_cam_pallet @ offset), most
# useful first. On clean depth the network's large errors are yaw errors of 10-30 degrees and slides along
# the pallet's length, outside ICP's basin from the network's pose; from one of these starts ICP often
# lands on the right pose, and the fit score tells which landing is right (validation, virtual-occluded:
# 70.7 -> 78.9 % of detected pallets within 5 cm with yaw +-15/30 degrees and +-10/20 cm along the length;
# `benchmarks/results/refine-starts.md`). Pallets cut by the image border or half hidden keep 5-10 cm
# slides along the length or the width, where the few visible boards and blocks let ICP stop early: slides
# of 5 and 10 cm along both axes found the right pose for 11 more of 475 detected pallets of validation
# virtual-clean (cut by the border) and virtual-occluded.
# (yaw degrees, shift along x metres, shift along y metres)
_STARTS = ((15.0, 0.0, 0.0), (-15.0, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, -0.1, 0.0),
           (0.0, 0.0, 0.1), (0.0, 0.0, -0.1),
           (0.0, 0.05, 0.0), (0.0, -0.05, 0.0), (0.0, 0.0, 0.05), (0.0, 0.0, -0.05),
           (30.0, 0.0, 0.0), (-30.0, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, -0.2, 0.0))
MAX_STARTS = len(_STARTS)


DEFAULT_STARTS = 6


def default_starts(n: int = DEFAULT_STARTS) -> np.ndarray:
    """The first `n` extra ICP starts as (n, 3) rows of (yaw_deg, dx_m, dy_m), for the EPAL pallet."""
    if not 0 <= int(n) <= MAX_STARTS:
        raise ValueError(f"number of starts must be in [0, {MAX_STARTS}], got {n}")
    return np.array(_STARTS[:int(n)], dtype=np.float64).reshape(-1, 3)


def offsets_from_starts(starts: np.ndarray) -> np.ndarray:
    """(S, 4, 4) pallet-frame offsets (a yaw about z, then a slide along x and y) of (S, 3) start rows
    (yaw_deg, dx_m, dy_m)."""
    rows = np.asarray(starts, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 3 or not np.all(np.isfinite(rows)):
        raise ValueError(f"starts must be finite (S, 3) rows of (yaw_deg, dx_m, dy_m), got shape {rows.shape}")
    a = np.deg2rad(rows[:, 0])
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    out[:, :2, 3] = rows[:, 1:]
    return out


def start_offsets(n: int) -> np.ndarray:
    """The first `n` extra ICP starts: (n, 4, 4) pallet-frame offsets (a yaw about z, or a slide along x or y)."""
    return offsets_from_starts(default_starts(n))


@dataclass(frozen=True)
class RefineResult:
    """:ivar T_cam_pallet: refined pose. :ivar iterations: steps run. :ivar n_inliers: correspondences in
    the last step. :ivar rms_m: their weighted point-to-plane RMS, metres. :ivar moved_m: translation
    change from the input pose, metres. :ivar converged: the last step was below the tolerance.
    :ivar stopped_near: stopped early on reaching the `stop_near` pose of `refine_poses`."""

    T_cam_pallet: np.ndarray
    iterations: int
    n_inliers: int
    rms_m: float
    moved_m: float
    converged: bool
    stopped_near: bool = False


def refine_pose(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, boxes_m: np.ndarray, iterations: int = 20,
                corr_start_m: float = 0.08, corr_end_m: float = 0.015, prior_rot_rad: float = 0.1,
                prior_trans_m: float = 0.1, min_inliers: int = 30, tol: float = 1e-4) -> RefineResult:
    """Refine a pallet pose on observed points: robust point-to-plane Gauss-Newton with a prior.

    The prior (the input pose, with standard deviations `prior_rot_rad`, `prior_trans_m`) weighs against
    the data scaled by their own noise, estimated from the residuals: exact depth moves the pose freely,
    while noisy stereo depth at 4-5 m (sigma of several cm) cannot drag it along directions only grazing
    surfaces constrain.

    :param T_cam_pallet: (4, 4) initial pose, pallet -> camera.
    :param pts_cam: (n, 3) observed points of the detection, camera frame, metres (background included).
    :param boxes_m: (k, 2, 3) the pallet's boards and blocks, pallet frame.
    :param corr_start_m: correspondence distance of the first step; it shrinks geometrically to
        `corr_end_m` at the last step.
    :param prior_rot_rad: how far (1 sigma) the input rotation may be off, radians; or (3,), one per pallet-frame
        axis (a small one holds the rotation about that axis).
    :param prior_trans_m: how far (1 sigma) the input translation may be off, metres; or (3,) per pallet-frame axis.
    :param min_inliers: with fewer correspondences the step stops (the pose reached so far is kept).
    :param tol: stop when a step moves by less than this (radians + metres).
    :return: RefineResult; with too few inliers at the first step the input pose comes back unchanged.
    """
    T0 = np.asarray(T_cam_pallet, dtype=np.float64)
    if T0.shape != (4, 4):
        raise ValueError(f"T_cam_pallet must be a finite (4, 4) transform, got shape {T0.shape}")
    return refine_poses(T0[None], pts_cam, boxes_m, iterations, corr_start_m, corr_end_m, prior_rot_rad,
                        prior_trans_m, min_inliers, tol)[0]


def refine_poses(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, boxes_m: np.ndarray, iterations: int = 20,
                 corr_start_m: float = 0.08, corr_end_m: float = 0.015, prior_rot_rad: float = 0.1,
                 prior_trans_m: float = 0.1, min_inliers: int = 30, tol: float = 1e-4,
                 stop_near: np.ndarray | None = None, stop_near_m: float = 0.005,
                 compiled: bool = True) -> list[RefineResult]:
    """`refine_pose` from several starting poses on the same points at once (one kernel call, or one numpy pass
    per step).

    Each start runs exactly as `refine_pose` would run it alone (its own prior, stopping and result).

    :param T_cam_pallet: (m, 4, 4) starting poses, pallet -> camera.
    :param stop_near: optional (4, 4) pose, e.g. an ICP result the starts surround: a start that comes within
        `stop_near_m` of it (largest displacement of the model box's corners) stops there, flagged
        `stopped_near`, since it would only land on that pose again. Saves the rest of its iterations.
    :param compiled: use the compiled kernel when the package has it (`kernels`); False runs numpy.
    :return: m RefineResults, in the order of the starts.
    """
    T0 = check_poses(T_cam_pallet, "T_cam_pallet")
    pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    m = len(T0)
    near = None if stop_near is None else np.broadcast_to(np.asarray(stop_near, dtype=np.float64), (m, 4, 4))
    run = _icp(T0, np.broadcast_to(pts, (m,) + pts.shape), np.full(m, len(pts)), boxes_m, iterations,
               corr_start_m, corr_end_m, prior_rot_rad, prior_trans_m, min_inliers, tol, near, stop_near_m, compiled)
    return [RefineResult(run.T_cam_pallet[i], int(run.iterations[i]), int(run.n_inliers[i]), float(run.rms_m[i]),
                         float(np.linalg.norm(run.T_cam_pallet[i, :3, 3] - T0[i, :3, 3])), bool(run.converged[i]),
                         bool(run.stopped_near[i])) for i in range(m)]


def _exp_se3_batch(delta: np.ndarray) -> np.ndarray:
    """(P, 4, 4) transforms of small motions (rotation vector w, translation v) = delta[:, :3], delta[:, 3:]."""
    w = delta[:, :3]
    theta = np.linalg.norm(w, axis=1)
    Kx = np.zeros((len(delta), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)[:, None, None]
    b = np.where(small, 0.0, (1 - np.cos(th)) / th ** 2)[:, None, None]
    T = np.tile(np.eye(4), (len(delta), 1, 1))
    T[:, :3, :3] += a * Kx + b * (Kx @ Kx)
    T[:, :3, 3] = delta[:, 3:]
    return T


@dataclass(frozen=True)
class _IcpRun:
    """Per pose (P,): final pose (P, 4, 4), steps run, inliers and RMS of the last step, flags."""

    T_cam_pallet: np.ndarray
    iterations: np.ndarray
    n_inliers: np.ndarray
    rms_m: np.ndarray
    converged: np.ndarray
    stopped_near: np.ndarray


def _icp(T0: np.ndarray, pts: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray, iterations: int,
         corr_start_m: float, corr_end_m: float, prior_rot_rad: float, prior_trans_m: float, min_inliers: int,
         tol: float, stop_near: np.ndarray | None, stop_near_m: float, compiled: bool = True,
         threads: int = 1, grid: kernels.BoxGrid | None = None) -> _IcpRun:
    """`refine_pose` for P poses at once, each on its own points: the compiled kernel (`kernels`, the poses
    shared among `threads` threads) when `compiled` and the package has it, else one numpy pass per step for all.

    :param T0: (P, 4, 4) starting poses. :param pts: (P, N, 3) camera frame, metres; pose i uses its first
    `n_pts[i]` rows. :param stop_near: None or (P, 4, 4), a pose per start at which it stops.
    :param prior_rot_rad, prior_trans_m: the prior's sigmas: a number, (3,) per pallet-frame axis, or (P, 3).
    :param grid: the kernel's `kernels.box_grid` of these boxes (fewer boxes measured per point), or None.
    """
    if not 0 < corr_end_m <= corr_start_m:
        raise ValueError(f"need 0 < corr_end_m <= corr_start_m, got {corr_end_m}, {corr_start_m}")
    boxes64 = _check_boxes(boxes_m)
    m, n = pts.shape[:2]
    # the prior's diagonal per pose: one value for all axes, 3 per pallet-frame axis (a level pallet: tight about x
    # and y), or (P, 3), one row per pose
    prior = np.concatenate([np.broadcast_to(np.asarray(prior_rot_rad, dtype=np.float64), (m, 3)) ** -2,
                            np.broadcast_to(np.asarray(prior_trans_m, dtype=np.float64), (m, 3)) ** -2], axis=1)
    if compiled and len(boxes64) <= kernels.MAX_BOXES and kernels.available():
        return _IcpRun(*kernels.icp(T0, pts, n_pts, boxes64, prior, iterations, corr_start_m, corr_end_m,
                                    min_inliers, tol, stop_near, stop_near_m, threads, grid))
    boxes = boxes64.astype(_ICP_DTYPE)
    extents = _extents(boxes)
    pts_f = np.asarray(pts, dtype=_ICP_DTYPE)
    valid = np.arange(n)[None] < np.asarray(n_pts)[:, None]                             # (P, N)
    model_lo, model_hi = boxes64[:, 0].min(0), boxes64[:, 1].max(0)
    R0, t0 = T0[:, :3, :3], T0[:, :3, 3]
    T_pal_cam = np.tile(np.eye(4), (m, 1, 1))
    T_pal_cam[:, :3, :3] = np.swapaxes(R0, 1, 2)
    T_pal_cam[:, :3, 3] = -(np.swapaxes(R0, 1, 2) @ t0[..., None])[..., 0]
    diag = np.arange(6)
    xi = np.zeros((m, 6))
    n_in, rms, done = np.zeros(m, dtype=np.int64), np.full(m, np.nan), np.zeros(m, dtype=np.int64)
    converged, stopped = np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)
    active = np.ones(m, dtype=bool)
    if stop_near is not None:
        corners = np.array(list(itertools.product(*zip(model_lo, model_hi))))               # (8, 3) pallet frame
        corners_cam = transform_points(stop_near, np.broadcast_to(corners, (m, 8, 3)))    # (P, 8, 3)
    steps = max(int(iterations), 0)
    for it in range(steps):
        a = np.flatnonzero(active)
        if len(a) == 0:
            break
        thr = corr_start_m * (corr_end_m / corr_start_m) ** (it / max(steps - 1, 1))
        T_f = T_pal_cam[a].astype(_ICP_DTYPE)
        p = pts_f[a] @ np.swapaxes(T_f[:, :3, :3], 1, 2) + T_f[:, None, :3, 3]            # (a, n, 3)
        # only points within thr of the model's bounding box can correspond: skip the rest of the box's
        # background (floor, rack, load) in the closest-point search, which is most of the time
        near = valid[a]                                                                   # (a, n)
        for c in range(3):
            near &= p[..., c] > model_lo[c] - thr
            near &= p[..., c] < model_hi[c] + thr
        q, nrm = np.zeros(p.shape, p.dtype), np.zeros(p.shape, p.dtype)                    # C order: views below
        d = np.full((len(a), n), np.inf, p.dtype)
        at = np.flatnonzero(near)                         # flat (pose, point) rows; `take` beats mask indexing
        if len(at):
            q_at, n_at, d.reshape(-1)[at] = _closest(p.reshape(-1, 3).take(at, 0), boxes, extents)
            q_rows, n_rows = q.reshape(-1, 3), nrm.reshape(-1, 3)                       # views
            for c in range(3):
                q_rows[:, c][at] = q_at[:, c]
                n_rows[:, c][at] = n_at[:, c]
        use = d < thr                                                                     # (a, n)
        n_use = use.sum(1)
        starved = n_use < min_inliers                 # this start stops here, keeping its pose so far
        active[a[starved]] = False
        if starved.any():
            keep = ~starved
            a, p, q, nrm, d, use, n_use = a[keep], p[keep], q[keep], nrm[keep], d[keep], use[keep], n_use[keep]
            if len(a) == 0:
                break
        w = np.where(use, (1.0 - (np.minimum(d, thr) / thr) ** 2) ** 2, 0.0)           # Tukey biweight
        r = (p[..., 0] - q[..., 0]) * nrm[..., 0] + (p[..., 1] - q[..., 1]) * nrm[..., 1] \
            + (p[..., 2] - q[..., 2]) * nrm[..., 2]                                        # point-to-plane
        J = np.empty(p.shape[:-1] + (6,), p.dtype)           # d r / d (w, v) of a motion applied to p
        for c, (c1, c2) in enumerate(((1, 2), (2, 0), (0, 1))):                         # p x nrm
            np.subtract(p[..., c1] * nrm[..., c2], p[..., c2] * nrm[..., c1], out=J[..., c])
        J[..., 3:] = nrm
        wsum = w.sum(1, dtype=np.float64)
        wrr = (w * r * r).sum(1, dtype=np.float64)
        var = np.maximum(wrr / wsum, 0.002 ** 2)                                          # noise, metres^2
        Jw = J * w[..., None]
        H = np.matmul(np.swapaxes(Jw, 1, 2), J).astype(np.float64) / var[:, None, None]
        H[:, diag, diag] += prior[a]
        g = np.matmul(np.swapaxes(Jw, 1, 2), r[..., None])[..., 0].astype(np.float64) / var[:, None] \
            + xi[a] * prior[a]
        delta = -np.linalg.solve(H, g[..., None])[..., 0]
        xi[a] += delta                                                                    # small-motion sum
        T_pal_cam[a] = _exp_se3_batch(delta) @ T_pal_cam[a]
        n_in[a], rms[a], done[a] = n_use, np.sqrt(wrr / wsum), it + 1
        conv = (np.abs(delta).sum(1) < tol) & (it >= steps // 2)    # converged at a tight threshold
        converged[a[conv]], active[a[conv]] = True, False
        if stop_near is not None:
            # stop_near's box corners (camera frame) taken into each start's pallet frame come back
            # unmoved when the two poses agree
            here = transform_points(T_pal_cam[a], corners_cam[a])
            near_pose = np.linalg.norm(here - corners, axis=-1).max(1) < stop_near_m
            stopped[a[near_pose]], active[a[near_pose]] = True, False
    T = np.tile(np.eye(4), (m, 1, 1))
    Rt = np.swapaxes(T_pal_cam[:, :3, :3], 1, 2)
    T[:, :3, :3] = Rt
    T[:, :3, 3] = -(Rt @ T_pal_cam[:, :3, 3, None])[..., 0]
    return _IcpRun(T, done, n_in, rms, converged, stopped)


def best_landing(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, boxes_m: np.ndarray, n_starts: int,
                 start_points: int, score: Callable[[np.ndarray], float], max_rms_m: float,
                 iterations: int = 20, stop_near_m: float = 0.005) -> tuple[np.ndarray, int]:
    """ICP from the first `n_starts` of `start_offsets` around a refined pose; the best-scoring landing wins.

    A landing counts only when ICP trusts it (final RMS below `max_rms_m`), as for the pose itself.

    :param T_cam_pallet: (4, 4) the refined pose the starts surround (it competes too).
    :param pts_cam: (n, 3) the detection's depth points, camera frame, metres; each start uses an even
        subset of `start_points` of them.
    :param score: pose -> how well it explains the depth (higher is better), e.g. a `fit_score`.
    :param stop_near_m: a start that comes this close to `T_cam_pallet` stops (0: every start runs to the end).
    :return: (the winning (4, 4) pose, the index of its start, or -1 for `T_cam_pallet` itself).
    """
    T = np.asarray(T_cam_pallet, dtype=np.float64)
    pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    best_T, best_k, best = T, -1, score(T)
    if n_starts <= 0 or len(pts) == 0:
        return best_T, best_k
    pick = np.linspace(0, len(pts) - 1, min(int(start_points), len(pts))).round().astype(np.int64)
    # a start that comes back to within stop_near_m of T stops there: it would only land on T again
    landings = refine_poses(T @ start_offsets(n_starts), pts[pick], boxes_m, iterations=iterations,
                            stop_near=T if stop_near_m > 0 else None, stop_near_m=stop_near_m)
    for k, r in enumerate(landings):
        if not r.stopped_near and np.isfinite(r.rms_m) and r.rms_m < max_rms_m:
            s = score(r.T_cam_pallet)
            if s > best:
                best_T, best_k, best = r.T_cam_pallet, k, s
    return best_T, best_k


@dataclass(frozen=True, eq=False)
class RefineGeometry:
    """One pallet type as refinement needs it (the pallet frame, metres).

    :ivar model_points_m: (m, 3) surface points (the fit score's free-space term and distances).
    :ivar boxes_m: (k, 2, 3) min/max corners of its boards, blocks, runners, legs (ICP's model).
    :ivar starts: (S, 3) extra ICP starts, rows of (yaw_deg, dx_m, dy_m); (0, 3) for none.
    """

    model_points_m: np.ndarray
    boxes_m: np.ndarray
    starts: np.ndarray = dataclasses.field(default_factory=default_starts)
    points_on_boxes: bool = dataclasses.field(init=False, repr=False, compare=False)
    _indexes: dict = dataclasses.field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self) -> None:
        pts = np.asarray(self.model_points_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"model_points_m must be (m, 3) with m >= 1, got shape {pts.shape}")
        object.__setattr__(self, "model_points_m", pts)
        object.__setattr__(self, "boxes_m", _check_boxes(self.boxes_m))
        starts = np.asarray(self.starts, dtype=np.float64)
        object.__setattr__(self, "starts", np.zeros((0, 3)) if starts.size == 0 else starts)
        offsets_from_starts(self.starts)                       # validates the rows
        # surface points sampled on the boxes let the fit score skip points far from the boxes
        object.__setattr__(self, "points_on_boxes", bool(distance_to_boxes(pts, self.boxes_m).max() <= 1e-6))

    @property
    def in_boxes(self) -> np.ndarray | None:
        """The boxes when they hold every model point (see `fit_scores`), else None."""
        return self.boxes_m if self.points_on_boxes else None

    def icp_grid(self) -> kernels.BoxGrid | None:
        """The compiled kernels's `kernels.box_grid` of the boxes, built on first use (tens of ms); None where the
        kernel cannot take them (not built, or more than `kernels.MAX_BOXES` boxes)."""
        if "icp_grid" not in self._indexes:
            usable = len(self.boxes_m) <= kernels.MAX_BOXES and kernels.available()
            self._indexes["icp_grid"] = kernels.box_grid(self.boxes_m) if usable else None
        return self._indexes["icp_grid"]

    def point_index(self, tol_m: float) -> ModelPointIndex:
        """The model points' `ModelPointIndex` for `tol_m`, built on first use."""
        key = float(tol_m)
        if key not in self._indexes:
            self._indexes[key] = ModelPointIndex(self.model_points_m, key)
        return self._indexes[key]


@dataclass(frozen=True)
class RefineOptions:
    """How `refine_batch` refines (the estimator's `refine_*` options).

    :ivar iterations: ICP steps, from the network's pose and from each start.
    :ivar max_rms_m: the ICP pose counts only when its final RMS is below this, metres.
    :ivar margin: and when its fit score beats the network pose's by this much (0: at least matches it).
    :ivar fit_tol_m: tolerance of that fit score (and of the returned one), metres.
    :ivar start_points: depth points each start uses (an even subset of the box's).
    :ivar select_tol_m: tolerance of the fit score that compares the starts' landings, metres.
    :ivar start_max_rms_m: a landing counts only when its ICP RMS is below this, metres.
    :ivar stop_near_m: a start that comes this close to the pose it surrounds stops (0: all run to the end).
    :ivar compiled: ICP and fit scores in the compiled kernel when the package has it (`kernels`); False: in
        numpy (the same algorithms, slower; poses within micrometres).
    :ivar threads: the compiled kernel shares a frame's ICP runs among this many threads (same poses).
    """

    iterations: int = 20
    max_rms_m: float = 0.004
    margin: float = 0.0
    fit_tol_m: float = 0.04
    start_points: int = 300
    select_tol_m: float = 0.015
    start_max_rms_m: float = 0.003
    stop_near_m: float = 0.005
    compiled: bool = True
    threads: int = 1

    def __post_init__(self) -> None:
        if int(self.threads) < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        if int(self.iterations) < 0 or int(self.start_points) < 1:
            raise ValueError(f"iterations must be >= 0 and start_points >= 1, got {self.iterations}, "
                             f"{self.start_points}")
        for name in ("max_rms_m", "fit_tol_m", "select_tol_m", "start_max_rms_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not -1.0 <= self.margin <= 1.0 or not self.stop_near_m >= 0:
            raise ValueError(f"need margin in [-1, 1] and stop_near_m >= 0, got {self.margin}, {self.stop_near_m}")


# where a refined pose came from (`FrameRefinement.source`; k >= 0 is the landing of start k)
FROM_NETWORK, FROM_ICP = -2, -1


@dataclass(frozen=True, eq=False)
class FrameRefinement:
    """`refine_batch`'s result for n detections.

    :ivar T_cam_pallet: (n, 4, 4) refined poses.
    :ivar fits: n `FitScore`s of those poses at `fit_tol_m` on the detections' sampled points.
    :ivar source: (n,) int: FROM_NETWORK (-2), FROM_ICP (-1), or k >= 0 (the landing of start k won).
    :ivar icp_rms_m: (n,) final RMS of ICP from the network's pose, metres (NaN when it never stepped).
    """

    T_cam_pallet: np.ndarray
    fits: tuple[FitScore, ...]
    source: np.ndarray
    icp_rms_m: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.fits)
        for name, shape in (("T_cam_pallet", (n, 4, 4)), ("source", (n,)), ("icp_rms_m", (n,))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"FrameRefinement.{name} must have shape {shape}, got {np.shape(getattr(self, name))}")


def _padded(rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(len(rows), max n, 3) zero-padded stack of (n_i, 3) arrays, and the (len(rows),) counts."""
    counts = np.array([len(r) for r in rows], dtype=np.int64)
    out = np.zeros((len(rows), int(counts.max(initial=0)), 3))
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out, counts


def refine_batch(T_net_cam_pallet: np.ndarray, obs_cam: np.ndarray, box_obs_cam: list[np.ndarray],
                 geometry: RefineGeometry | Sequence[RefineGeometry], depth_m: np.ndarray, K: np.ndarray,
                 options: RefineOptions | None = None) -> FrameRefinement:
    """Refine all detections of a frame at once: ICP from the network's pose, the RMS and fit-score gate,
    ICP from the geometry's starts around the pose so far, and the best-fitting trusted landing.

    Per detection this is what `refine_pose`, `fit_score` and `best_landing` do one after the other; here
    each of those steps runs once for all detections and all starts (one numpy pass per ICP step).

    :param T_net_cam_pallet: (n, 4, 4) the network's poses, pallet -> camera.
    :param obs_cam: (n, N, 3) each detection's sampled points (the fit score's), camera frame, metres.
    :param box_obs_cam: n arrays (m_i, 3): each box's depth points for ICP (`box_points`), camera frame.
    :param geometry: one `RefineGeometry` for all detections, or a list/tuple of one per detection
        (detections that share the same object refine together).
    :param depth_m: (H, W) float metres, 0 = no data. :param K: 3x3 intrinsics.
    :return: `FrameRefinement`.
    """
    o = options or RefineOptions()
    T_net = check_poses(T_net_cam_pallet, "T_net_cam_pallet")
    n = len(T_net)
    obs = np.asarray(obs_cam, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[0] != n or obs.shape[2] != 3:
        raise ValueError(f"obs_cam must be ({n}, N, 3), got shape {obs.shape}")
    if len(box_obs_cam) != n:
        raise ValueError(f"box_obs_cam must hold {n} arrays, got {len(box_obs_cam)}")
    box_obs = []
    for i, b in enumerate(box_obs_cam):
        b = np.asarray(b, dtype=np.float64)
        if b.ndim != 2 or b.shape[1] != 3:
            raise ValueError(f"box_obs_cam[{i}] must be (m, 3), got shape {b.shape}")
        box_obs.append(b[np.all(np.isfinite(b), axis=1)])
    geoms = [geometry] * n if isinstance(geometry, RefineGeometry) else \
        list(geometry) if isinstance(geometry, (list, tuple)) else None
    if geoms is None or len(geoms) != n or not all(isinstance(g, RefineGeometry) for g in geoms):
        raise TypeError(f"geometry must be a RefineGeometry or {n} of them")
    K = check_K(K)

    T_out, source, rms = T_net.copy(), np.full(n, FROM_NETWORK), np.full(n, np.nan)
    fit = np.full((n, 3), np.nan)                                  # inlier fraction, violation, score
    groups: dict[int, list[int]] = {}
    for i, g in enumerate(geoms):
        groups.setdefault(id(g), []).append(i)
    for idx in groups.values():
        sel = np.asarray(idx)
        _refine_group(T_net[sel], obs[sel], [box_obs[i] for i in idx], geoms[idx[0]], depth_m, K, o,
                      T_out, source, rms, fit, sel)
    fits = tuple(FitScore(float(a), float(b), float(c)) for a, b, c in fit)
    return FrameRefinement(T_out, fits, source, rms)


# refine_pose's defaults: corr_start_m, corr_end_m, prior_rot_rad, prior_trans_m, min_inliers, tol
_ICP_DEFAULTS = (0.08, 0.015, 0.1, 0.1, 30, 1e-4)


def _refine_group(T_net: np.ndarray, obs: np.ndarray, box_obs: list[np.ndarray], geom: RefineGeometry,
                  depth_m: np.ndarray, K: np.ndarray, o: RefineOptions, T_out: np.ndarray, source: np.ndarray,
                  rms_out: np.ndarray, fit_out: np.ndarray, sel: np.ndarray) -> None:
    """`refine_batch` for detections of one geometry; writes rows `sel` of the output arrays."""
    g = len(T_net)
    pts, n_pts = _padded(box_obs)
    grid = geom.icp_grid() if o.compiled else None          # the kernel's box grid (numpy never reads it)
    base = _icp(T_net, pts, n_pts, geom.boxes_m, o.iterations, *_ICP_DEFAULTS, None, 0.0, o.compiled, o.threads,
                grid)
    T = T_net.copy()
    src = np.full(g, FROM_NETWORK)
    fit = np.full((g, 3), np.nan)
    # noisy depth pulls ICP off: its residual tells whether the depth is clean enough to trust it, and
    # then it must explain the depth at least as well as the network's pose
    gate = np.flatnonzero(np.isfinite(base.rms_m) & (base.rms_m < o.max_rms_m))
    if len(gate):
        both = fit_scores(np.concatenate([base.T_cam_pallet[gate], T_net[gate]]),
                          np.concatenate([obs[gate], obs[gate]]), None, geom.model_points_m, depth_m, K, o.fit_tol_m,
                          points_in_boxes_m=geom.in_boxes, point_index=geom.point_index(o.fit_tol_m),
                          compiled=o.compiled)
        both = np.stack(both, 1)
        f_icp, f_net = both[:len(gate)], both[len(gate):]
        keep = f_icp[:, 2] >= f_net[:, 2] + o.margin
        T[gate[keep]], src[gate[keep]] = base.T_cam_pallet[gate[keep]], FROM_ICP
        fit[gate] = np.where(keep[:, None], f_icp, f_net)

    # the network's larger errors lie outside ICP's basin: ICP from starts around the pose, and a trusted
    # landing that explains the box's depth better at a tight tolerance replaces it
    S = len(geom.starts)
    run = np.flatnonzero(n_pts > 0) if S > 0 else np.zeros(0, dtype=np.int64)
    if len(run):
        subsets = []
        for i in run:
            pick = np.linspace(0, n_pts[i] - 1, min(int(o.start_points), int(n_pts[i]))).round().astype(np.int64)
            subsets.append(box_obs[i][pick])
        sub, n_sub = _padded(subsets)
        offsets = offsets_from_starts(geom.starts)                                        # (S, 4, 4)
        T_start = (T[run][:, None] @ offsets[None]).reshape(-1, 4, 4)                      # detection-major
        near = np.repeat(T[run], S, axis=0) if o.stop_near_m > 0 else None
        land = _icp(T_start, np.repeat(sub, S, axis=0), np.repeat(n_sub, S), geom.boxes_m, o.iterations,
                    *_ICP_DEFAULTS, near, o.stop_near_m, o.compiled, o.threads, grid)
        trusted = ~land.stopped_near & np.isfinite(land.rms_m) & (land.rms_m < o.start_max_rms_m)
        cand = np.flatnonzero(trusted)                                                    # landing rows
        owner = np.concatenate([np.arange(len(run)), cand // S])                         # row in `run`
        poses = np.concatenate([T[run], land.T_cam_pallet[cand]])
        score = fit_scores(poses, pts[run][owner], n_pts[run][owner], geom.model_points_m, depth_m, K,
                           o.select_tol_m, geom.boxes_m, compiled=o.compiled)[2]
        landing_score = np.full((len(run), S), -np.inf)
        landing_score[cand // S, cand % S] = score[len(run):]
        k = landing_score.argmax(1)                                   # the first of the best, as in order
        won = landing_score[np.arange(len(run)), k] > score[:len(run)]
        wins = run[won]
        T[wins] = land.T_cam_pallet[won.nonzero()[0] * S + k[won]]
        src[wins], fit[wins] = k[won], np.nan

    todo = np.flatnonzero(np.isnan(fit[:, 0]))
    if len(todo):
        fit[todo] = np.stack(fit_scores(T[todo], obs[todo], None, geom.model_points_m, depth_m, K, o.fit_tol_m,
                                        points_in_boxes_m=geom.in_boxes,
                                        point_index=geom.point_index(o.fit_tol_m), compiled=o.compiled), 1)
    T_out[sel], source[sel], rms_out[sel], fit_out[sel] = T, src, base.rms_m, fit
