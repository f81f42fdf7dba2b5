"""Pose error metrics, in metres (numpy only).

ADD is the mean distance between the object's model points under the estimated and the true pose
(Hinterstoisser et al. 2012) — the metric the paper means. Its eq. 5 as printed squares the norm and uses
observed points; that is neither ADD nor comparable to the thresholds, so it is not what is computed here.
Pallets are symmetric, so the symmetry-aware ADD (minimum over the model's discrete symmetries) is reported
beside it, and ADD-S (closest-point distance) for continuous or unknown symmetries.

Conventions follow bop_toolkit's pose_error: R is 3x3 (model to camera), t is (3,) in metres, pts is (n, 3)
model points in the model frame, metres.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "add",
    "add_sym",
    "adds",
    "rotation_error_deg",
    "rotation_error_sym_deg",
    "translation_error_m",
    "accuracy_curve",
    "auc",
]


def _check_pose(R: np.ndarray, t: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3):
        raise ValueError(f"{name}: rotation must be 3x3, got shape {R.shape}")
    if t.shape != (3,):
        raise ValueError(f"{name}: translation must have 3 elements, got shape {t.shape}")
    return R, t


def _check_pts(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"model points must be (n, 3) with n >= 1, got shape {pts.shape}")
    return pts


def _transform(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ R.T + t


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """Average distance of model points (ADD), metres.

    :param R_est: (3, 3), :param t_est: (3,) estimated pose (model -> camera).
    :param R_gt: (3, 3), :param t_gt: (3,) ground-truth pose.
    :param pts: (n, 3) model points, model frame, metres.
    """
    R_est, t_est = _check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = _check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    d = _transform(R_est, t_est, pts) - _transform(R_gt, t_gt, pts)
    return float(np.linalg.norm(d, axis=1).mean())


def add_sym(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray,
            symmetries: np.ndarray) -> float:
    """Symmetry-aware ADD: the minimum ADD over the ground truth composed with each model symmetry.

    :param symmetries: (S, 4, 4) transforms T_sym with model(T_sym p) == model(p), metres; identity included
        or not (it is always considered).
    """
    syms = np.asarray(symmetries, dtype=np.float64)
    if syms.ndim != 3 or syms.shape[1:] != (4, 4):
        raise ValueError(f"symmetries must be (S, 4, 4), got shape {syms.shape}")
    R_gt, t_gt = _check_pose(R_gt, t_gt, "ground truth")
    best = add(R_est, t_est, R_gt, t_gt, pts)
    for T_sym in syms:
        # pose of the symmetric copy: p -> R_gt (R_s p + t_s) + t_gt
        best = min(best, add(R_est, t_est, R_gt @ T_sym[:3, :3], R_gt @ T_sym[:3, 3] + t_gt, pts))
    return best


def adds(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray,
         chunk: int = 1024) -> float:
    """ADD-S: mean over ground-truth-posed points of the distance to the closest estimate-posed point, metres.

    Brute force in chunks of `chunk` points (memory O(chunk * n)).
    """
    R_est, t_est = _check_pose(R_est, t_est, "estimate")
    R_gt, t_gt = _check_pose(R_gt, t_gt, "ground truth")
    pts = _check_pts(pts)
    est = _transform(R_est, t_est, pts)
    gt = _transform(R_gt, t_gt, pts)
    est_sq = (est ** 2).sum(1)
    mins = np.empty(len(gt))
    for i in range(0, len(gt), chunk):
        g = gt[i:i + chunk]
        d2 = (g ** 2).sum(1)[:, None] + est_sq[None, :] - 2.0 * g @ est.T
        mins[i:i + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return float(mins.mean())


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of R_est R_gt^T in degrees, in [0, 180]."""
    R_est, _ = _check_pose(R_est, np.zeros(3), "estimate")
    R_gt, _ = _check_pose(R_gt, np.zeros(3), "ground truth")
    cos = (np.trace(R_est @ R_gt.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def rotation_error_sym_deg(R_est: np.ndarray, R_gt: np.ndarray, symmetries: np.ndarray) -> float:
    """Smallest rotation error over the model's symmetries, degrees."""
    syms = np.asarray(symmetries, dtype=np.float64)
    if syms.ndim != 3 or syms.shape[1:] != (4, 4):
        raise ValueError(f"symmetries must be (S, 4, 4), got shape {syms.shape}")
    R_gt = np.asarray(R_gt, dtype=np.float64)
    errors = [rotation_error_deg(R_est, R_gt)]
    errors += [rotation_error_deg(R_est, R_gt @ T[:3, :3]) for T in syms]
    return min(errors)


def translation_error_m(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Euclidean distance between translations, metres."""
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(-1)
    if t_est.shape != (3,) or t_gt.shape != (3,):
        raise ValueError(f"translations must have 3 elements, got {t_est.shape} and {t_gt.shape}")
    return float(np.linalg.norm(t_est - t_gt))


def accuracy_curve(errors_m: np.ndarray, thresholds_m: np.ndarray) -> np.ndarray:
    """Fraction of instances whose error is below each threshold.

    :param errors_m: (n,) per-instance errors; NaN or inf marks a failure (a missed pallet) and never counts.
    :param thresholds_m: (k,) thresholds in metres.
    :return: (k,) accuracies in [0, 1]; all zeros when n is 0.
    """
    errors = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    thresholds = np.asarray(thresholds_m, dtype=np.float64).reshape(-1)
    if errors.size == 0:
        return np.zeros(thresholds.shape)
    ok = np.where(np.isfinite(errors), errors, np.inf)
    return (ok[None, :] < thresholds[:, None]).mean(axis=1)


def auc(errors_m: np.ndarray, max_threshold_m: float = 0.1, steps: int = 1000) -> float:
    """Area under the accuracy-vs-threshold curve from 0 to `max_threshold_m`, normalised to [0, 1].

    As in PoseCNN/DenseFusion's ADD(-S) AUC (there with a 10 cm maximum).
    """
    if not max_threshold_m > 0:
        raise ValueError(f"max_threshold_m must be positive, got {max_threshold_m}")
    thresholds = np.linspace(0.0, max_threshold_m, steps + 1)
    acc = accuracy_curve(errors_m, thresholds)
    # trapezoid rule written out: np.trapz was renamed across numpy versions
    return float(((acc[1:] + acc[:-1]) * 0.5 * np.diff(thresholds)).sum() / max_threshold_m)
