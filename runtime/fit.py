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

from .geometry import check_K, invert_T, transform_points
from .results import FitScore

__all__ = ["distance_to_boxes", "distance_to_points", "fit_score"]


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
    gap = np.maximum(np.maximum(boxes[None, :, 0] - pts[:, None], pts[:, None] - boxes[None, :, 1]), 0.0)
    return np.sqrt((gap * gap).sum(-1)).min(1)


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


def _free_space_violation(model_cam: np.ndarray, depth_m: np.ndarray, K: np.ndarray, tol_m: float,
                          cell_px: int = 4) -> float:
    """Fraction of the model's camera-facing points that lie more than `tol_m` in front of the observed depth.

    Only points the camera would see of the model itself count (a coarse z-buffer of the model on
    `cell_px` pixel cells): the far side of a correctly posed pallet sits behind its near side, not
    in free space, and must not dilute the fraction.

    :param model_cam: (m, 3) posed model points, camera frame, metres.
    :return: fraction in [0, 1]; 0 when no visible model point lands on valid depth.
    """
    h, w = depth_m.shape
    mc = model_cam[model_cam[:, 2] > 1e-6]
    if len(mc) == 0:
        return 0.0
    u = np.round(mc[:, 0] * K[0, 0] / mc[:, 2] + K[0, 2]).astype(np.int64)
    v = np.round(mc[:, 1] * K[1, 1] / mc[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if not np.any(inside):
        return 0.0
    u, v, z = u[inside], v[inside], mc[inside, 2]
    cell = (v // cell_px) * ((w + cell_px - 1) // cell_px) + u // cell_px
    z_near = np.full(int(cell.max()) + 1, np.inf)
    far_first = np.argsort(-z, kind="stable")
    z_near[cell[far_first]] = z[far_first]      # fancy assignment: the last (nearest) write wins
    d_obs = depth_m[v, u]
    use = (z <= z_near[cell] + tol_m) & (d_obs > 0)
    if not np.any(use):
        return 0.0
    return float((z[use] < d_obs[use] - tol_m).mean())


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
    if not tol_m > 0:
        raise ValueError(f"tol_m must be positive, got {tol_m}")
    K = check_K(K)
    T = np.asarray(T_cam_model, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_cam_model must be a finite (4, 4) transform, got shape {T.shape}")
    obs = np.asarray(pts_obs_cam, dtype=np.float64).reshape(-1, 3)

    if len(obs):
        obs_model = transform_points(invert_T(T), obs)
        d = distance_to_boxes(obs_model, model_boxes_m) if model_boxes_m is not None \
            else distance_to_points(obs_model, model_pts)
        inlier = float((d <= tol_m).mean())
    else:
        inlier = 0.0

    violation = _free_space_violation(transform_points(T, np.asarray(model_pts, dtype=np.float64).reshape(-1, 3)),
                                      depth_m, K, tol_m)
    return FitScore(inlier_fraction=inlier, free_space_violation=violation, score=inlier * (1.0 - violation))
