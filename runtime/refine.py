"""Pose refinement: robust point-to-plane ICP of the observed depth onto the pallet's box model (numpy only).

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
"""
from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .geometry import backproject_pixels, clamp_box, invert_T, select_pixels, transform_points

__all__ = ["best_landing", "box_points", "closest_on_boxes", "RefineResult", "refine_pose", "refine_poses",
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
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    boxes = _check_boxes(boxes_m)
    n = len(p)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    lo, hi = boxes[:, 0], boxes[:, 1]                           # (k, 3)
    # squared distance outside each box, one axis at a time, in place on two (n, k) buffers (ICP calls this
    # every iteration; with (n, k, 3) temporaries it was most of the refinement's time)
    d_out2, gap, tmp = np.zeros((n, len(boxes))), np.empty((n, len(boxes))), np.empty((n, len(boxes)))
    for a in range(3):
        pa = p[:, a, None]
        np.subtract(lo[None, :, a], pa, out=gap)
        np.subtract(pa, hi[None, :, a], out=tmp)
        np.maximum(gap, tmp, out=gap)
        np.maximum(gap, 0.0, out=gap)
        np.multiply(gap, gap, out=gap)
        d_out2 += gap
    j = d_out2.argmin(1)                                         # nearest box per point
    d = np.sqrt(d_out2[np.arange(n), j])
    q = np.clip(p, lo[j], hi[j])
    normal = np.zeros((n, 3))
    out = d > 0.0
    normal[out] = (p[out] - q[out]) / d[out, None]
    ins = np.flatnonzero(~out)
    if len(ins) == 0:
        return q, normal, d
    # inside a box: its nearest face is a candidate at the depth below it, every box the point is outside
    # of at its outside distance (boxes may overlap); the nearest wins
    pi, o2 = p[ins], d_out2[ins]
    d_in = np.full(o2.shape, np.inf)                              # (m, k) depth below each box's nearest face
    for a in range(3):
        pa = pi[:, a, None]
        np.minimum(d_in, pa - lo[None, :, a], out=d_in)
        np.minimum(d_in, hi[None, :, a] - pa, out=d_in)
    dist = np.where(o2 > 0.0, np.sqrt(o2), np.maximum(d_in, 0.0))
    ji = dist.argmin(1)
    r = np.arange(len(ins))
    di = dist[r, ji]
    blo, bhi = lo[ji], hi[ji]
    qi = np.clip(pi, blo, bhi)
    ni = np.zeros((len(ins), 3))
    via_out = o2[r, ji] > 0.0
    ni[via_out] = (pi[via_out] - qi[via_out]) / di[via_out, None]
    face = np.flatnonzero(~via_out)                               # move to the nearest face
    to_face = np.concatenate([pi[face] - blo[face], bhi[face] - pi[face]], axis=1)   # -x -y -z +x +y +z
    f = to_face.argmin(1)
    axis, positive = f % 3, f >= 3
    qi[face, axis] = np.where(positive, bhi[face, axis], blo[face, axis])
    ni[face, axis] = np.where(positive, 1.0, -1.0)
    q[ins], normal[ins], d[ins] = qi, ni, di
    return q, normal, d


# Extra ICP starts around a pose, in the pallet frame (applied on the right: T_cam_pallet @ offset), most
# useful first. On clean depth the network's large errors are yaw errors of 10-30 degrees and slides along
# the pallet's length, outside ICP's basin from the network's pose; from one of these starts ICP often
# lands on the right pose, and the fit score tells which landing is right (validation, virtual-occluded:
# 70.7 -> 78.9 % of detected pallets within 5 cm with yaw +-15/30 degrees and +-10/20 cm along the length;
# `benchmarks/results/refine-starts.md`). Pallets cut by the image border or half hidden keep 5-10 cm
# slides along the length or the width, where the few visible boards and blocks let ICP stop early: slides
# of 5 and 10 cm along both axes found the right pose for 11 more of 475 detected pallets of validation
# virtual-clean (cut by the border) and virtual-occluded (session 10).
# (yaw degrees, shift along x metres, shift along y metres)
_STARTS = ((15.0, 0.0, 0.0), (-15.0, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, -0.1, 0.0),
           (0.0, 0.0, 0.1), (0.0, 0.0, -0.1),
           (0.0, 0.05, 0.0), (0.0, -0.05, 0.0), (0.0, 0.0, 0.05), (0.0, 0.0, -0.05),
           (30.0, 0.0, 0.0), (-30.0, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, -0.2, 0.0))
MAX_STARTS = len(_STARTS)


def start_offsets(n: int) -> np.ndarray:
    """The first `n` extra ICP starts: (n, 4, 4) pallet-frame offsets (a yaw about z, or a slide along x or y)."""
    if not 0 <= int(n) <= MAX_STARTS:
        raise ValueError(f"number of starts must be in [0, {MAX_STARTS}], got {n}")
    out = np.tile(np.eye(4), (int(n), 1, 1))
    for i in range(int(n)):
        yaw_deg, dx_m, dy_m = _STARTS[i]
        a = np.deg2rad(yaw_deg)
        out[i, :2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        out[i, :2, 3] = dx_m, dy_m
    return out


def _exp_se3(delta: np.ndarray) -> np.ndarray:
    """(4, 4) transform of a small motion (rotation vector w, translation v) = delta[:3], delta[3:]."""
    w, v = delta[:3], delta[3:]
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        R = np.eye(3) + K
    else:
        R = np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta ** 2 * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, v
    return T


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
    :param prior_rot_rad: how far (1 sigma) the input rotation may be off, radians.
    :param prior_trans_m: how far (1 sigma) the input translation may be off, metres.
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
                 stop_near: np.ndarray | None = None, stop_near_m: float = 0.005) -> list[RefineResult]:
    """`refine_pose` from several starting poses on the same points at once (one numpy pass per step).

    Each start runs exactly as `refine_pose` would run it alone (its own prior, stopping and result);
    batching saves only the per-call overhead (about 7 % for 9 starts of 600 points: the closest-point
    search is most of the time either way).

    :param T_cam_pallet: (m, 4, 4) starting poses, pallet -> camera.
    :param stop_near: optional (4, 4) pose, e.g. an ICP result the starts surround: a start that comes within
        `stop_near_m` of it (largest displacement of the model box's corners) stops there, flagged
        `stopped_near`, since it would only land on that pose again. Saves the rest of its iterations.
    :return: m RefineResults, in the order of the starts.
    """
    T0 = np.asarray(T_cam_pallet, dtype=np.float64)
    if T0.ndim != 3 or T0.shape[1:] != (4, 4) or not np.all(np.isfinite(T0)):
        raise ValueError(f"T_cam_pallet must be finite (4, 4) transforms, got shape {T0.shape}")
    if not 0 < corr_end_m <= corr_start_m:
        raise ValueError(f"need 0 < corr_end_m <= corr_start_m, got {corr_end_m}, {corr_start_m}")
    pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    m, n = len(T0), len(pts)
    boxes = _check_boxes(boxes_m)
    model_lo, model_hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    T_pal_cam = np.stack([invert_T(T) for T in T0])
    prior = np.diag([prior_rot_rad ** -2] * 3 + [prior_trans_m ** -2] * 3)
    xi = np.zeros((m, 6))
    n_in, rms, done = np.zeros(m, dtype=np.int64), np.full(m, np.nan), np.zeros(m, dtype=np.int64)
    converged, stopped = np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)
    active = np.ones(m, dtype=bool)
    if stop_near is not None:
        corners = np.array(list(itertools.product(*zip(model_lo, model_hi))))               # (8, 3) pallet frame
        corners_cam = transform_points(np.asarray(stop_near, dtype=np.float64), corners)
    steps = max(int(iterations), 0)
    for it in range(steps):
        a = np.flatnonzero(active)
        if len(a) == 0:
            break
        thr = corr_start_m * (corr_end_m / corr_start_m) ** (it / max(steps - 1, 1))
        p = transform_points(T_pal_cam[a], np.broadcast_to(pts, (len(a), n, 3)))        # (a, n, 3)
        # only points within thr of the model's bounding box can correspond: skip the rest of the box's
        # background (floor, rack, load) in the closest-point search, which is most of the time
        near = np.all((p > model_lo - thr) & (p < model_hi + thr), axis=-1)                 # (a, n)
        q, nrm, d = np.zeros_like(p), np.zeros_like(p), np.full((len(a), n), np.inf)
        if near.any():
            q[near], nrm[near], d[near] = closest_on_boxes(p[near], boxes_m)
        use = d < thr                                                                     # (a, n)
        n_use = use.sum(1)
        starved = n_use < min_inliers                 # this start stops here, keeping its pose so far
        active[a[starved]] = False
        keep = ~starved
        a, p, q, nrm, d, use, n_use = a[keep], p[keep], q[keep], nrm[keep], d[keep], use[keep], n_use[keep]
        if len(a) == 0:
            break
        w = np.where(use, (1.0 - (np.minimum(d, thr) / thr) ** 2) ** 2, 0.0)           # Tukey biweight
        r = ((p - q) * nrm).sum(-1)                                                       # point-to-plane
        J = np.empty(p.shape[:-1] + (6,))                    # d r / d (w, v) of a motion applied to p
        for c, (c1, c2) in enumerate(((1, 2), (2, 0), (0, 1))):                         # p x nrm
            np.subtract(p[..., c1] * nrm[..., c2], p[..., c2] * nrm[..., c1], out=J[..., c])
        J[..., 3:] = nrm
        wsum = w.sum(1)
        var = np.maximum((w * r * r).sum(1) / wsum, 0.002 ** 2)                          # noise, metres^2
        Jw = J * w[..., None]
        H = np.einsum("ani,anj->aij", Jw, J) / var[:, None, None] + prior
        g = np.einsum("ani,an->ai", Jw, r) / var[:, None] + xi[a] @ prior
        delta = -np.linalg.solve(H, g[..., None])[..., 0]
        xi[a] += delta                                                                    # small-motion sum
        for k, i in enumerate(a):
            T_pal_cam[i] = _exp_se3(delta[k]) @ T_pal_cam[i]
        n_in[a], rms[a], done[a] = n_use, np.sqrt((w * r * r).sum(1) / wsum), it + 1
        conv = (np.abs(delta).sum(1) < tol) & (it >= steps // 2)    # converged at a tight threshold
        converged[a[conv]], active[a[conv]] = True, False
        if stop_near is not None:
            # stop_near's box corners (camera frame) taken into each start's pallet frame come back
            # unmoved when the two poses agree
            here = transform_points(T_pal_cam[a], np.broadcast_to(corners_cam, (len(a), 8, 3)))
            near_pose = np.linalg.norm(here - corners, axis=-1).max(1) < stop_near_m
            stopped[a[near_pose]], active[a[near_pose]] = True, False
    out = []
    for i in range(m):
        T = invert_T(T_pal_cam[i])
        out.append(RefineResult(T, int(done[i]), int(n_in[i]), float(rms[i]),
                                float(np.linalg.norm(T[:3, 3] - T0[i, :3, 3])), bool(converged[i]),
                                bool(stopped[i])))
    return out


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
