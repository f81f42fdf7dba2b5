"""Dataset-level accuracy of pose estimates against ground truth (numpy only).

Protocol (used by `pallet6d eval`, `pallet6d run` on a BOP source and `benchmarks/accuracy.py`):
- A ground-truth pallet counts when `counted_pallets` says so: it has a visible box and at least `MIN_VISIB_FRACT`
  (10 %, the BOP convention) of it is visible. Training asks the same function, with its own box-size rule.
- Estimates are matched to ground truth greedily, highest detector score first, by IoU of the estimate's box
  with the ground truth's visible box (>= `iou_threshold`; `match_greedy`). An estimate matched to a pallet that
  does not count (too hidden) is ignored: it is neither a true nor a false positive.
- Precision = matched estimates / all estimates that are not ignored; recall = matched / counted pallets.
- Pose accuracy at a threshold = fraction of counted pallets whose error is below it; a missed pallet is a
  failure (its error is infinite).
- A missed pallet is told why: the reason of the refused detection whose box matches its visible box best (IoU >=
  `iou_threshold`), or `NO_DETECTION` where none does; where the refused detection had a pose (the fit check
  refused it), that pose's error tells whether the refusal cost a right pose.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from . import metrics

Models = Mapping[int, tuple[np.ndarray, np.ndarray]]   # obj_id -> model points (n, 3) metres, symmetries (S, 4, 4)

__all__ = ["GroundTruth", "Estimate", "Refused", "PalletRecord", "FrameScore", "ScoreTally", "counted_pallets",
           "box_iou", "match_greedy", "ground_truths_from_bop", "evaluate_frame", "evaluate_poses", "dataset_models",
           "summarize", "records_to_dicts", "DEFAULT_THRESHOLDS_M", "DEFAULT_DISTANCE_BINS_M", "DEFAULT_VISIBILITY_BINS",
           "MIN_VISIB_FRACT", "NO_DETECTION"]

# The BOP convention (bop_toolkit's `visib_gt_min`): a pallet less visible is too hidden to be found or posed, so
# it is neither scored nor trained on.
MIN_VISIB_FRACT = 0.1
DEFAULT_THRESHOLDS_M = (0.02, 0.05, 0.1)
DEFAULT_DISTANCE_BINS_M = (0.0, 2.0, 3.0, 4.0, 5.0, 8.0, np.inf)
DEFAULT_VISIBILITY_BINS = (0.1, 0.3, 0.6, 1.0)
NO_DETECTION = "no_detection"     # a missed pallet that no refused detection matches either


@dataclass(frozen=True)
class GroundTruth:
    """:param T_cam_model: (4, 4) metres; :param box_visib_xyxy: (4,) visible 2D box, pixels;
    :param truncated: the pallet's whole projected box reaches beyond the image (KITTI's truncation): part of it
        is out of view, not hidden behind something.
    :param obj_id: its model in the dataset (BOP obj_id), for datasets of several pallet types."""

    T_cam_model: np.ndarray
    box_visib_xyxy: np.ndarray
    visib_fract: float
    truncated: bool = False
    obj_id: int | None = None

    @property
    def bbox_visib_xywh(self) -> np.ndarray:
        """(4,) the visible box as x, y, width, height (the BOP annotations' form, for `counted_pallets`)."""
        x1, y1, x2, y2 = (float(v) for v in self.box_visib_xyxy)
        return np.array([x1, y1, x2 - x1, y2 - y1])


@dataclass(frozen=True)
class Estimate:
    """:param T_cam_model: (4, 4) metres; :param box_xyxy: (4,) detector box, pixels."""

    T_cam_model: np.ndarray
    box_xyxy: np.ndarray
    score: float


@dataclass(frozen=True)
class Refused:
    """A detection the estimator did not report. :param box_xyxy: (4,) pixels; :param reason: its rejection
    reason; :param T_cam_model: (4, 4) metres, the pose it was refused with, or None (refused before a pose)."""

    box_xyxy: np.ndarray
    reason: str
    T_cam_model: np.ndarray | None = None


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
    obj_id: int | None = None     # the ground truth's model (pallet type) in the dataset
    missed_reason: str | None = None    # missed: the matching refused detection's reason, or NO_DETECTION
    refused_add_sym_m: float = np.inf   # missed: the symmetric ADD of that detection's pose (inf: it had none)


class FrameScore(NamedTuple):
    """One frame's evaluation: a record per counted pallet, and the frame's true and false positives."""

    records: list[PalletRecord]
    true_positives: int
    false_positives: int


def counted_pallets(gts: Sequence, min_visib_fract: float = MIN_VISIB_FRACT, min_box_side_px: float = 0.0,
                    unknown_visib_counts: bool = True) -> np.ndarray:
    """Which ground-truth pallets count: are scored by the evaluation, or trained on. The one definition of it.

    :param gts: n annotations, each with `visib_fract` (float; NaN: unknown) and `bbox_visib_xywh` ((4,) visible
        box x, y, width, height in pixels, or None): `pallet6d.runtime.bop.BopGT`, the simulator's pallets, or
        `GroundTruth`. A pallet without a visible box never counts: nothing can be matched to it or cropped of it.
    :param min_visib_fract: the least visible fraction that counts (`MIN_VISIB_FRACT`, the BOP convention).
    :param min_box_side_px: the least width and height of the visible box (0: not checked). The evaluation
        checks none (a tiny box is a pallet to find); training asks for a box a target or a crop can be made of.
    :param unknown_visib_counts: whether a pallet of unknown visible fraction counts. The evaluation counts it (a
        set annotated without visible fractions is scored on every pallet with a box); training does not (the
        pallet could be hidden entirely).
    :return: (n,) bool.
    """
    out = np.zeros(len(gts), dtype=bool)
    for k, g in enumerate(gts):
        box = g.bbox_visib_xywh
        if box is None:
            continue
        visib = float(g.visib_fract)
        if np.isnan(visib):
            ok = unknown_visib_counts
        else:
            ok = visib >= min_visib_fract
        if min_box_side_px > 0:
            ok = ok and float(box[2]) >= min_box_side_px and float(box[3]) >= min_box_side_px
        out[k] = ok
    return out


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
                               _leaves_image(g.bbox_obj_xywh, image_hw), int(g.obj_id)))
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


def match_greedy(pred_xyxy: np.ndarray, scores: np.ndarray, gt_xyxy: np.ndarray,
                 iou_threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching by descending score (ties: the earlier box first): each prediction takes the unmatched
    ground-truth box it overlaps most (the first of equal ones), if at IoU >= `iou_threshold`.

    :param pred_xyxy: (n, 4) predicted boxes; :param scores: (n,); :param gt_xyxy: (m, 4) ground-truth boxes.
    :return: (n,) int index of the matched ground-truth box per prediction (-1: none), (m,) bool matched.
    :raises ValueError: scores and boxes disagree in number.
    """
    pred = np.asarray(pred_xyxy, np.float64).reshape(-1, 4)
    gt = np.asarray(gt_xyxy, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(scores) != len(pred):
        raise ValueError(f"match_greedy: {len(pred)} boxes but {len(scores)} scores")
    match, matched = np.full(len(pred), -1, np.int64), np.zeros(len(gt), bool)
    if len(pred) == 0 or len(gt) == 0:
        return match, matched
    iou = box_iou(pred, gt)
    for i in np.argsort(-scores, kind="stable"):
        cand = np.where(matched, -1.0, iou[i])
        j = int(np.argmax(cand))
        if cand[j] >= iou_threshold:
            match[i], matched[j] = j, True
    return match, matched


def evaluate_frame(frame: int, estimates: Sequence[Estimate], gts: Sequence[GroundTruth], model_pts: np.ndarray,
                   symmetries: np.ndarray, iou_threshold: float = 0.5,
                   min_visib_fract: float = MIN_VISIB_FRACT, models: Models | None = None,
                   refused: Sequence[Refused] = ()) -> FrameScore:
    """Match one frame's estimates to its ground truth and measure the pose errors.

    :param model_pts: (n, 3) model points, metres; :param symmetries: (S, 4, 4): the model of every ground
        truth that `models` does not name.
    :param models: {obj_id: (model points (n, 3) metres, symmetries (S, 4, 4))}, each ground truth's own model
        (`dataset_models`); None: `model_pts` for all.
    :param refused: the frame's refused detections: each missed pallet's `missed_reason` and `refused_add_sym_m`
        (without them every missed pallet is `NO_DETECTION`).
    :return: records for counted pallets, true positives, false positives.
    """
    counted = counted_pallets(gts, min_visib_fract)
    match, _ = match_greedy(np.array([e.box_xyxy for e in estimates]).reshape(-1, 4),
                            np.array([e.score for e in estimates]),
                            np.array([g.box_visib_xyxy for g in gts]).reshape(-1, 4), iou_threshold)
    matched_est = {int(j): i for i, j in enumerate(match) if j >= 0}  # gt index -> estimate index
    fp = int(np.sum(match < 0))
    tp = sum(1 for j in matched_est if counted[j])
    refused_iou = box_iou(np.array([r.box_xyxy for r in refused]).reshape(-1, 4),
                          np.array([g.box_visib_xyxy for g in gts]).reshape(-1, 4))
    records = []
    for j, g in enumerate(gts):
        if not counted[j]:
            continue
        R_gt, t_gt = g.T_cam_model[:3, :3], g.T_cam_model[:3, 3]
        errs = dict(add_m=np.inf, add_sym_m=np.inf, adds_m=np.inf, rot_err_sym_deg=np.inf, trans_err_m=np.inf)
        pts, sym = (models or {}).get(g.obj_id, (model_pts, symmetries))
        missed_reason, refused_err = None, np.inf
        if j not in matched_est:
            k = int(np.argmax(refused_iou[:, j])) if len(refused) else -1
            if k >= 0 and refused_iou[k, j] >= iou_threshold:
                missed_reason, T = refused[k].reason, refused[k].T_cam_model
                if T is not None:
                    refused_err = metrics.add_sym(T[:3, :3], T[:3, 3], R_gt, t_gt, pts, sym)
            else:
                missed_reason = NO_DETECTION
        else:
            T = estimates[matched_est[j]].T_cam_model
            R, t = T[:3, :3], T[:3, 3]
            errs = dict(add_m=metrics.add(R, t, R_gt, t_gt, pts),
                        add_sym_m=metrics.add_sym(R, t, R_gt, t_gt, pts, sym),
                        adds_m=metrics.adds(R, t, R_gt, t_gt, pts),
                        rot_err_sym_deg=metrics.rotation_error_sym_deg(R, R_gt, sym),
                        trans_err_m=metrics.translation_error_m(t, t_gt))
        records.append(PalletRecord(frame=frame, distance_m=float(np.linalg.norm(t_gt)),
                                    visib_fract=float(g.visib_fract), detected=j in matched_est,
                                    truncated=bool(g.truncated), obj_id=g.obj_id, missed_reason=missed_reason,
                                    refused_add_sym_m=float(refused_err), **errs))
    return FrameScore(records, tp, fp)


def evaluate_poses(frame: int, poses: Sequence, gts: Sequence[GroundTruth], model_pts: np.ndarray,
                   symmetries: np.ndarray, models: Models | None = None, rejected: Sequence = ()) -> FrameScore:
    """The per-frame evaluation of the estimator's output (`pallet6d eval`, `pallet6d run` on a BOP source).

    :param poses: the frame's `PalletPose`s (their `T_cam_pallet`, `box_xyxy`, `detector_score`); empty when
        the estimation failed (its counted pallets are then missed).
    :param gts: its ground truth (`ground_truths_from_bop`); :param model_pts: (n, 3) metres;
    :param symmetries: (S, 4, 4). :param models: each ground truth's own model (`evaluate_frame`).
    :param rejected: the frame's `Rejection`s (why the missed pallets were missed).
    """
    estimates = [Estimate(p.T_cam_pallet, p.box_xyxy, p.detector_score) for p in poses]
    refused = [Refused(r.box_xyxy, r.reason, None if r.pose is None else r.pose.T_cam_pallet) for r in rejected]
    return evaluate_frame(frame, estimates, gts, model_pts, symmetries, models=models, refused=refused)


def dataset_models(ds, geometries: Sequence = ()) -> Models:
    """Each model of a BOP dataset for `evaluate_frame`: the bundle's pallet type of the same name (its points and
    symmetries) where the dataset names it (`models_info.json` "name"), else points sampled on the dataset's mesh
    with its symmetries. :param ds: `bop.BopDataset`; :param geometries: `PalletGeometry`s (name, points_m,
    symmetries)."""
    by_name = {g.name: (g.points_m, g.symmetries) for g in geometries}
    out = {}
    for obj_id, info in ds.models_info.items():
        name = info.get("name")
        if name in by_name:
            out[obj_id] = by_name[name]
        elif ds.model_path(obj_id).exists():
            out[obj_id] = (ds.model_points(obj_id), ds.model_symmetries(obj_id))
    return out


class ScoreTally:
    """The running evaluation of a sequence of frames: `add` each frame's `FrameScore`, then `summary()`."""

    def __init__(self) -> None:
        self.records: list[PalletRecord] = []
        self.true_positives = self.false_positives = 0

    def add(self, score: FrameScore) -> FrameScore:
        self.records.extend(score.records)
        self.true_positives += score.true_positives
        self.false_positives += score.false_positives
        return score

    def __bool__(self) -> bool:
        """Whether anything was scored: a pallet, or an estimate."""
        return bool(self.records or self.true_positives or self.false_positives)

    def summary(self, **kwargs) -> dict:
        """`summarize` of everything added (kwargs: its bins and thresholds)."""
        return summarize(self.records, self.true_positives, self.false_positives, **kwargs)


def summarize(records: Iterable[PalletRecord], true_positives: int, false_positives: int,
              thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M,
              distance_bins_m: Sequence[float] = DEFAULT_DISTANCE_BINS_M,
              visibility_bins: Sequence[float] = DEFAULT_VISIBILITY_BINS) -> dict:
    """Machine-readable summary: n_gt, precision, recall, add_acc / add_sym_acc / adds_acc per threshold
    (keys are the thresholds in metres as strings, e.g. "0.05"), AUC to 10 cm, accuracy by distance, and by
    visible fraction where the failures are: missed (no pose reported), symmetric ADD >= 10 cm, 5-10 cm, < 5 cm
    (fractions of that bin's pallets; the last bin includes its upper edge), and the same split for pallets
    wholly in view and pallets cut by the image border (`by_truncation`), per dataset model (`by_object`, when the
    pallets are of more than one: several pallet types), and the missed pallets by why they were missed
    (`missed_by_reason`: reason -> pallets, and how many of them the refused detection had posed within 5 cm)."""
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
    # why the missed pallets were missed, most often first; refused_within_5cm: refusals that cost a right pose
    reasons: dict[str, dict] = {}
    for r in records:
        if not r.detected and r.missed_reason is not None:
            c = reasons.setdefault(r.missed_reason, {"n_gt": 0, "refused_within_5cm": 0})
            c["n_gt"] += 1
            c["refused_within_5cm"] += int(r.refused_add_sym_m < 0.05)
    out["missed_by_reason"] = dict(sorted(reasons.items(), key=lambda kv: (-kv[1]["n_gt"], kv[0])))
    obj = np.array([-1 if r.obj_id is None else r.obj_id for r in records], int)
    if len(set(obj.tolist())) > 1:
        out["by_object"] = [{"obj_id": int(k), **outcome(obj == k)} for k in sorted(set(obj.tolist()))]
    return out


def records_to_dicts(records: Iterable[PalletRecord]) -> list[dict]:
    """JSON-ready per-pallet records (inf errors become None)."""
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(r).items()}
            for r in records]
