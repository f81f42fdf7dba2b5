"""Geometric fit score: does a posed pallet model agree with the observed depth? (numpy only)

DenseFusion's per-point confidence ranks its own hypotheses but cannot tell a right pose from a wrong one,
so every pose is checked against the depth image with two complementary terms:

- inlier fraction: observed points of the detection (the sampled points, in the camera frame) within
  `tol_m` of the posed model. A pose shifted or turned away from the data explains few of them.
- free-space violation: posed model points facing the camera (a coarse z-buffer of the model) that
  project onto valid depth and lie more than `tol_m` in front of it: the camera saw through space the model says is wood. A pose pushed towards the camera
  or turned so the pallet's length points at the camera violates free space; a right pose only at
  silhouette edges. Model points behind the observed surface are occluded, which is no evidence either way.

score = inlier_fraction * (1 - free_space_violation), in [0, 1].

The pallet model is given as a union of axis-aligned boxes in its own frame (exact distances, cheap),
or as surface points (nearest-point distances) when a bundle carries no boxes.
"""
from __future__ import annotations

import numpy as np

from . import kernels
from .geometry import check_K
from .results import FitScore

__all__ = ["check_poses", "distance_to_boxes", "distance_to_points", "fit_score", "fit_scores", "ModelPointIndex"]


def distance_to_boxes(pts: np.ndarray, boxes_m: np.ndarray) -> np.ndarray:
    """Distance from points to a solid union of axis-aligned boxes (0 inside).

    :param pts: (n, 3) points in the boxes' frame, metres.
    :param boxes_m: (k, 2, 3) min and max corners.
    :return: (n,) metres.
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    boxes = np.asarray(boxes_m, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3):
        raise ValueError(f"boxes_m must be (k, 2, 3), got shape {boxes.shape}")
    # (k, n) arrays, one axis at a time: numpy reduces slowly over a short last axis
    d2 = np.zeros((len(boxes), len(pts)))
    for c in range(3):
        p = pts[:, c]
        gap = np.maximum(np.maximum(boxes[:, 0, c, None] - p, p - boxes[:, 1, c, None]), 0.0)
        d2 += gap * gap
    return np.sqrt(d2.min(0)) if len(boxes) else np.full(len(pts), np.inf)


def distance_to_points(pts: np.ndarray, model_pts: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Distance from each point to its nearest model point (brute force, in chunks).

    :param pts: (n, 3); :param model_pts: (m, 3) in the same frame, metres.
    :return: (n,) metres.
    """
    pts = np.asarray(pts, dtype=np.float32).reshape(-1, 3)
    model = np.asarray(model_pts, dtype=np.float32).reshape(-1, 3)
    if len(model) == 0:
        raise ValueError("model_pts is empty")
    m2 = (model * model).sum(1)
    out = np.empty(len(pts), dtype=np.float64)
    for i in range(0, len(pts), chunk):
        p = pts[i:i + chunk]
        d2 = (p * p).sum(1)[:, None] + m2[None] - 2.0 * p @ model.T
        out[i:i + chunk] = np.sqrt(np.maximum(d2.min(1), 0.0))
    return out


class ModelPointIndex:
    """Model points bucketed on a grid of `tol_m` cells: the distance to the nearest model point of every query
    point within `tol_m` of one, from only the points of its cell and the 26 around it (no search over all of them).

    A model point within `tol_m` of a query point lies in the query's cell or a neighbouring one, so the nearest
    distance found there is exact wherever it is at most `tol_m`. Cell k holds `points[offsets[k]:offsets[k + 1]]`
    (cells x-major): each model point once, about 24 kB a thousand points.

    :param model_pts: (m, 3) model points, model frame, metres. :param tol_m: the largest distance asked for.
    """

    def __init__(self, model_pts: np.ndarray, tol_m: float) -> None:
        model = np.asarray(model_pts, dtype=np.float64).reshape(-1, 3)
        if len(model) == 0 or not tol_m > 0:
            raise ValueError(f"need model points and a positive tol_m, got {len(model)} points, tol_m={tol_m}")
        self.tol_m = float(tol_m)
        self.origin = model.min(0) - 2.0 * self.tol_m
        self.shape = np.floor((model.max(0) + 2.0 * self.tol_m - self.origin) / self.tol_m).astype(np.int64) + 1
        cell = np.ravel_multi_index(np.floor((model - self.origin) / self.tol_m).astype(np.int64).T, self.shape)
        order = np.argsort(cell, kind="stable")
        counts = np.bincount(cell, minlength=int(np.prod(self.shape)))
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)          # (cells + 1,)
        self.points = np.ascontiguousarray(model[order])                                   # (m, 3)

    def distances(self, pts: np.ndarray) -> np.ndarray:
        """(n,) distance from (n, 3) points (model frame, metres) to the nearest model point where that is
        at most `tol_m`; some value above `tol_m` elsewhere."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        idx = np.floor((pts - self.origin) / self.tol_m).astype(np.int64)
        inside = np.flatnonzero(np.all((idx >= 0) & (idx < self.shape), axis=1))
        out = np.full(len(pts), np.inf)
        if len(inside):
            # the query's cell and its neighbours inside the grid: (n', 27) cell numbers, -1 outside
            near = idx[inside, None, :] + np.array(list(np.ndindex(3, 3, 3)))[None] - 1        # (n', 27, 3)
            ok = np.all((near >= 0) & (near < self.shape), axis=2)
            cells = np.where(ok, np.ravel_multi_index(np.where(ok[..., None], near, 0).transpose(2, 0, 1),
                                                      self.shape), -1)
            query, k = np.nonzero(cells >= 0)
            cell = cells[query, k]
            start, count = self.offsets[cell], self.offsets[cell + 1] - self.offsets[cell]
            pair_query = np.repeat(query, count)                    # one pair per (query point, model point near it)
            entry = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
            p = pts[inside]
            d2 = np.zeros(len(pair_query))
            for c in range(3):                        # not a sum over the short last axis: slow in numpy
                diff = self.points[entry, c] - p[pair_query, c]
                d2 += diff * diff
            best = np.full(len(inside), np.inf)
            np.minimum.at(best, pair_query, d2)
            out[inside] = np.sqrt(best)
        return out


def _free_space_violations(model_cam: np.ndarray, depth_m: np.ndarray, K: np.ndarray, tol_m: float,
                           cell_px: int = 4) -> np.ndarray:
    """Per pose, the fraction of the model's camera-facing points more than `tol_m` in front of the observed depth.

    Only points the camera would see of the model itself count (a coarse z-buffer of the model on
    `cell_px` pixel cells, one per pose): the far side of a correctly posed pallet sits behind its near
    side, not in free space, and must not dilute the fraction.

    :param model_cam: (P, m, 3) posed model points, camera frame, metres.
    :return: (P,) fractions in [0, 1]; 0 for a pose with no visible model point on valid depth.
    """
    h, w = depth_m.shape
    P = len(model_cam)
    z_all = model_cam[..., 2]
    ok = z_all > 1e-6
    pose, idx = np.nonzero(ok)
    x, y, z = model_cam[pose, idx, 0], model_cam[pose, idx, 1], z_all[pose, idx]
    u = np.round(x * K[0, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(y * K[1, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pose, u, v, z = pose[inside], u[inside], v[inside], z[inside]
    if len(z) == 0:
        return np.zeros(P)
    cell = (v // cell_px) * ((w + cell_px - 1) // cell_px) + u // cell_px
    # one z-buffer per pose, each over the span of cells its points reach, laid end to end
    lo, hi = np.full(P, np.iinfo(np.int64).max), np.full(P, -1)
    np.minimum.at(lo, pose, cell)
    np.maximum.at(hi, pose, cell)
    span = np.maximum(hi - lo + 1, 0)
    start = np.concatenate([[0], np.cumsum(span)[:-1]])
    key = start[pose] + cell - lo[pose]
    z_near = np.full(int(span.sum()), np.inf)
    np.minimum.at(z_near, key, z)
    d_obs = depth_m[v, u]
    use = (z <= z_near[key] + tol_m) & (d_obs > 0)
    n_use = np.bincount(pose[use], minlength=P)
    n_bad = np.bincount(pose[use], weights=z[use] < d_obs[use] - tol_m, minlength=P)
    return np.where(n_use > 0, n_bad / np.maximum(n_use, 1), 0.0)


def check_poses(T: np.ndarray, name: str) -> np.ndarray:
    """(P, 4, 4) float64 finite transforms, or ValueError naming `name`."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be finite (4, 4) transforms, got shape {T.shape}")
    return T


def fit_scores(T_cam_model: np.ndarray, pts_obs_cam: np.ndarray, n_obs: np.ndarray | None, model_pts: np.ndarray,
               depth_m: np.ndarray, K: np.ndarray, tol_m: float = 0.04,
               model_boxes_m: np.ndarray | None = None, points_in_boxes_m: np.ndarray | None = None,
               point_index: ModelPointIndex | None = None,
               compiled: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`fit_score` of P poses at once, each against its own observed points: in the compiled kernel
    (`kernels.fit`) when `compiled`, the package has it and `depth_m` is C-contiguous float32 (as the
    estimator's is), else one numpy pass (the same scores, up to rounding at the tolerances' edges).

    :param T_cam_model: (P, 4, 4) poses to check.
    :param pts_obs_cam: (P, N, 3) observed points per pose, camera frame, metres; pose i uses its first
        `n_obs[i]` rows (the rest is padding).
    :param n_obs: (P,) valid rows per pose; None = all N.
    :param model_pts, depth_m, K, tol_m, model_boxes_m: as in `fit_score`.
    :param points_in_boxes_m: optional (k, 2, 3) boxes that hold every model point (the pallet's own boxes,
        when `model_pts` are sampled on them): with distances to points, an observed point farther than
        `tol_m` from these boxes is farther from every model point too and skips the nearest-point search.
    :param point_index: optional `ModelPointIndex` of `model_pts` for at least `tol_m`: distances to the
        points come from it instead of a search over all of them (same inliers).
    :param compiled: False scores in numpy even where the compiled kernel could.
    :return: (inlier_fraction, free_space_violation, score), each (P,).
    """
    if not tol_m > 0:
        raise ValueError(f"tol_m must be positive, got {tol_m}")
    K = check_K(K)
    T = check_poses(T_cam_model, "T_cam_model")
    P = len(T)
    obs = np.asarray(pts_obs_cam, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[0] != P or obs.shape[2] != 3:
        raise ValueError(f"pts_obs_cam must be ({P}, N, 3), got shape {obs.shape}")
    N = obs.shape[1]
    n_obs = np.full(P, N) if n_obs is None else np.asarray(n_obs, dtype=np.int64).reshape(P)
    if np.any(n_obs < 0) or np.any(n_obs > N):
        raise ValueError(f"n_obs must be in [0, {N}] (the rows of pts_obs_cam), got {n_obs.min()}..{n_obs.max()}")
    model = np.asarray(model_pts, dtype=np.float64).reshape(-1, 3)
    if model_boxes_m is not None:
        boxes = np.asarray(model_boxes_m, dtype=np.float64)
        lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    else:
        lo, hi = model.min(0), model.max(0)
    depth = np.asarray(depth_m)
    if compiled and depth.dtype == np.float32 and depth.ndim == 2 and depth.flags.c_contiguous \
            and kernels.available():
        index = point_index if point_index is not None and point_index.tol_m >= tol_m else None
        inlier, violation = kernels.fit(T, obs, n_obs, model, lo, hi, model_boxes_m,
                                        None if model_boxes_m is not None else points_in_boxes_m, index, depth,
                                        K, tol_m)
        return inlier, violation, inlier * (1.0 - violation)

    R, t = T[:, :3, :3], T[:, :3, 3]
    obs_model = (obs - t[:, None]) @ R                                      # (P, N, 3) model frame
    valid = np.arange(N)[None] < n_obs[:, None]
    # only points within tol_m of the model's bounding box can be inliers: the rest of the box's
    # background skips the exact distance
    gap = np.maximum(np.maximum(lo - obs_model, obs_model - hi), 0.0)
    cand = valid & ((gap * gap).sum(-1) <= (tol_m + 1e-6) ** 2)
    if model_boxes_m is None and points_in_boxes_m is not None and cand.any():
        cand[cand] = distance_to_boxes(obs_model[cand], points_in_boxes_m) <= tol_m + 1e-6
    inlier_pts = np.zeros((P, N), dtype=bool)
    if cand.any():
        if model_boxes_m is not None:
            d = distance_to_boxes(obs_model[cand], model_boxes_m)
        elif point_index is not None and point_index.tol_m >= tol_m:
            d = point_index.distances(obs_model[cand])
        else:
            d = distance_to_points(obs_model[cand], model)
        inlier_pts[cand] = d <= tol_m
    inlier = np.where(n_obs > 0, inlier_pts.sum(1) / np.maximum(n_obs, 1), 0.0)

    violation = _free_space_violations(model @ np.swapaxes(R, 1, 2) + t[:, None], depth_m, K, tol_m)
    return inlier, violation, inlier * (1.0 - violation)


def fit_score(T_cam_model: np.ndarray, pts_obs_cam: np.ndarray, model_pts: np.ndarray, depth_m: np.ndarray,
              K: np.ndarray, tol_m: float = 0.04, model_boxes_m: np.ndarray | None = None) -> FitScore:
    """Agreement of a posed pallet model with the observed depth.

    :param T_cam_model: (4, 4) pose to check.
    :param pts_obs_cam: (n, 3) observed points of the detection, camera frame, metres (duplicates from
        oversampling are fine; they weigh as sampled).
    :param model_pts: (m, 3) model surface points, model frame, metres (for the free-space term, and for
        distances when `model_boxes_m` is None).
    :param depth_m: (H, W) float32 metres, 0 = no data.
    :param K: 3x3 intrinsics.
    :param tol_m: distance tolerance, metres (a few depth-noise sigmas at the working range).
    :param model_boxes_m: optional (k, 2, 3) model as boxes, model frame, metres.
    :return: `FitScore`; inlier fraction 0 when there are no observed points, violation 0 when no model
        point lands on valid depth.
    """
    T = np.asarray(T_cam_model, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_cam_model must be a finite (4, 4) transform, got shape {T.shape}")
    obs = np.asarray(pts_obs_cam, dtype=np.float64).reshape(1, -1, 3)
    inlier, violation, score = fit_scores(T[None], obs, None, model_pts, depth_m, K, tol_m, model_boxes_m)
    return FitScore(inlier_fraction=float(inlier[0]), free_space_violation=float(violation[0]),
                    score=float(score[0]))
