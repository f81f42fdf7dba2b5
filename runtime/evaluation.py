"""Dataset-level accuracy of pose estimates against ground truth (numpy only).

Protocol (used by `pallet6d eval` and `benchmarks/accuracy.py`):
- A ground-truth pallet counts when at least `min_visib_fract` (10 %, the BOP convention) of it is visible.
- Estimates are matched to ground truth greedily, highest detector score first, by IoU of the estimate's box
  with the ground truth's visible box (>= `iou_threshold`). An estimate matched to a pallet that does not count
  (too hidden) is ignored: it is neither a true nor a false positive.
- Precision = matched estimates / all estimates that are not ignored; recall = matched / counted pallets.
- Pose accuracy at a threshold = fraction of counted pallets whose error is below it; a missed pallet is a
  failure (its error is infinite).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Sequence

import numpy as np

from . import metrics

__all__ = ["GroundTruth", "Estimate", "PalletRecord", "box_iou", "ground_truths_from_bop", "evaluate_frame",
           "summarize", "records_to_dicts", "DEFAULT_THRESHOLDS_M", "DEFAULT_DISTANCE_BINS_M",
           "DEFAULT_VISIBILITY_BINS", "MIN_VISIB_FRACT"]

MIN_VISIB_FRACT = 0.1   # the BOP convention: a pallet counts (is trained on, scored) when >= 10 % visible
DEFAULT_THRESHOLDS_M = (0.02, 0.05, 0.1)
DEFAULT_DISTANCE_BINS_M = (0.0, 2.0, 3.0, 4.0, 5.0, 8.0, np.inf)
DEFAULT_VISIBILITY_BINS = (0.1, 0.3, 0.6, 1.0)


@dataclass(frozen=True)
class GroundTruth:
    """:param T_cam_model: (4, 4) metres; :param box_visib_xyxy: (4,) visible 2D box, pixels;
    :param truncated: the pallet's whole projected box reaches beyond the image (KITTI's truncation): part of it
        is out of view, not hidden behind something."""

    T_cam_model: np.ndarray
    box_visib_xyxy: np.ndarray
    visib_fract: float
    truncated: bool = False


@dataclass(frozen=True)
class Estimate:
    """:param T_cam_model: (4, 4) metres; :param box_xyxy: (4,) detector box, pixels."""

    T_cam_model: np.ndarray
    box_xyxy: np.ndarray
    score: float


@dataclass(frozen=True)
class PalletRecord:
    """One counted ground-truth pallet and how it was estimated (errors are inf when missed)."""

    frame: int
    distance_m: float
    visib_fract: float
    detected: bool
    add_m: float
    add_sym_m: float
    adds_m: float
    rot_err_sym_deg: float
    trans_err_m: float
    truncated: bool = False


def ground_truths_from_bop(bop_gts: Sequence, image_hw: tuple[int, int] | None = None
                           ) -> tuple[list[GroundTruth], int]:
    """`GroundTruth`s of one BOP frame's annotations (`pallet6d.runtime.bop.BopGT`).

    Annotations without a visible box (a BOP set without scene_gt_info.json) cannot be matched and are
    skipped; an unknown visible fraction (NaN) counts as fully visible.
    :param image_hw: (H, W) of the frame: marks pallets whose whole box (`bbox_obj`) leaves the image as
        truncated. Without it, or without `bbox_obj`, none is.
    :return: (ground truths, number of annotations skipped).
    """
    out, skipped = [], 0
    for g in bop_gts:
        if g.bbox_visib_xywh is None:
            skipped += 1
            continue
        x, y, w, h = (float(v) for v in g.bbox_visib_xywh)
        visib = float(g.visib_fract) if np.isfinite(g.visib_fract) else 1.0
        out.append(GroundTruth(g.T_cam_model, np.array([x, y, x + w, y + h]), visib,
                               _leaves_image(g.bbox_obj_xywh, image_hw)))
    return out, skipped


def _leaves_image(box_xywh, image_hw: tuple[int, int] | None) -> bool:
    if box_xywh is None or image_hw is None:
        return False
    x, y, w, h = (float(v) for v in box_xywh)
    return x < 0 or y < 0 or x + w > image_hw[1] or y + h > image_hw[0]


def box_iou(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> np.ndarray:
    """Pairwise IoU. :param a_xyxy: (n, 4); :param b_xyxy: (m, 4); :return: (n, m)."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def evaluate_frame(frame: int, estimates: Sequence[Estimate], gts: Sequence[GroundTruth], model_pts: np.ndarray,
                   symmetries: np.ndarray, iou_threshold: float = 0.5,
                   min_visib_fract: float = MIN_VISIB_FRACT) -> tuple[list[PalletRecord], int, int]:
    """Match one frame's estimates to its ground truth and measure the pose errors.

    :param model_pts: (n, 3) model points, metres; :param symmetries: (S, 4, 4).
    :return: (records for counted pallets, true positives, false positives).
    """
    order = sorted(range(len(estimates)), key=lambda i: -estimates[i].score)
    counted = [g.visib_fract >= min_visib_fract for g in gts]
    iou = box_iou(np.array([estimates[i].box_xyxy for i in order]).reshape(-1, 4),
                  np.array([g.box_visib_xyxy for g in gts]).reshape(-1, 4))
    matched_est: dict[int, int] = {}  # gt index -> estimate index
    tp = fp = 0
    for row, i in enumerate(order):
        candidates = [j for j in np.argsort(-iou[row]) if iou[row, j] >= iou_threshold and j not in matched_est]
        if not candidates:
            fp += 1
            continue
        j = int(candidates[0])
        matched_est[j] = i
        if counted[j]:
            tp += 1
    records = []
    for j, g in enumerate(gts):
        if not counted[j]:
            continue
        R_gt, t_gt = g.T_cam_model[:3, :3], g.T_cam_model[:3, 3]
        errs = dict(add_m=np.inf, add_sym_m=np.inf, adds_m=np.inf, rot_err_sym_deg=np.inf, trans_err_m=np.inf)
        if j in matched_est:
            T = estimates[matched_est[j]].T_cam_model
            R, t = T[:3, :3], T[:3, 3]
            errs = dict(add_m=metrics.add(R, t, R_gt, t_gt, model_pts),
                        add_sym_m=metrics.add_sym(R, t, R_gt, t_gt, model_pts, symmetries),
                        adds_m=metrics.adds(R, t, R_gt, t_gt, model_pts),
                        rot_err_sym_deg=metrics.rotation_error_sym_deg(R, R_gt, symmetries),
                        trans_err_m=metrics.translation_error_m(t, t_gt))
        records.append(PalletRecord(frame=frame, distance_m=float(np.linalg.norm(t_gt)),
                                    visib_fract=float(g.visib_fract), detected=j in matched_est,
                                    truncated=bool(g.truncated), **errs))
    return records, tp, fp


def summarize(records: Iterable[PalletRecord], true_positives: int, false_positives: int,
              thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M,
              distance_bins_m: Sequence[float] = DEFAULT_DISTANCE_BINS_M,
              visibility_bins: Sequence[float] = DEFAULT_VISIBILITY_BINS) -> dict:
    """Machine-readable summary: n_gt, precision, recall, add_acc / add_sym_acc / adds_acc per threshold
    (keys are the thresholds in metres as strings, e.g. "0.05"), AUC to 10 cm, accuracy by distance, and by
    visible fraction where the failures are: missed (no pose reported), symmetric ADD >= 10 cm, 5-10 cm, < 5 cm
    (fractions of that bin's pallets; the last bin includes its upper edge), and the same split for pallets
    wholly in view and pallets cut by the image border (`by_truncation`)."""
    records = list(records)
    n_gt = len(records)
    n_pred = true_positives + false_positives
    out: dict = {
        "n_gt": n_gt,
        "n_detected": int(sum(r.detected for r in records)),
        "precision": true_positives / n_pred if n_pred else 0.0,
        "recall": true_positives / n_gt if n_gt else 0.0,
    }
    for key in ("add", "add_sym", "adds"):
        errors = np.array([getattr(r, f"{key}_m") for r in records])
        acc = metrics.accuracy_curve(errors, thresholds_m)
        out[f"{key}_acc"] = {f"{t:g}": float(a) for t, a in zip(thresholds_m, acc)}
        out[f"{key}_auc_10cm"] = metrics.auc(errors, 0.1) if n_gt else 0.0
        finite = errors[np.isfinite(errors)]
        out[f"{key}_median_m"] = float(np.median(finite)) if finite.size else None
    dist = np.array([r.distance_m for r in records])
    add_sym = np.array([r.add_sym_m for r in records])
    by_distance = []
    for lo, hi in zip(distance_bins_m[:-1], distance_bins_m[1:]):
        sel = (dist >= lo) & (dist < hi)
        if sel.any():
            acc = metrics.accuracy_curve(add_sym[sel], thresholds_m)
            by_distance.append({"from_m": lo, "to_m": None if np.isinf(hi) else hi, "n_gt": int(sel.sum()),
                                "add_sym_acc": {f"{t:g}": float(a) for t, a in zip(thresholds_m, acc)}})
    out["by_distance"] = by_distance
    visib = np.array([r.visib_fract for r in records])
    detected = np.array([r.detected for r in records], dtype=bool)

    def outcome(sel: np.ndarray) -> dict:
        n = int(sel.sum())
        e = add_sym[sel & detected]
        return {"n_gt": n, "missed": float((sel & ~detected).sum() / n),
                "add_sym_ge_10cm": float((e >= 0.1).sum() / n),
                "add_sym_5_10cm": float(((e >= 0.05) & (e < 0.1)).sum() / n),
                "add_sym_lt_5cm": float((e < 0.05).sum() / n)}

    by_visibility = []
    edges = list(visibility_bins)
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (visib >= lo) & ((visib < hi) | ((k == len(edges) - 2) & (visib <= hi)))
        if sel.any():
            by_visibility.append({"from": lo, "to": hi, **outcome(sel)})
    out["by_visibility"] = by_visibility
    truncated = np.array([r.truncated for r in records], dtype=bool)
    out["by_truncation"] = [{"truncated": bool(t), **outcome(truncated == t)} for t in (False, True)
                            if (truncated == t).any()]
    return out


def records_to_dicts(records: Iterable[PalletRecord]) -> list[dict]:
    """JSON-ready per-pallet records (inf errors become None)."""
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(r).items()}
            for r in records]
