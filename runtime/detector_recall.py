"""The detector stage alone on a BOP dataset: recall by the visible box's height, what the misses are, and the
precision and average precision over every score.

A counted pallet (`evaluation.counted_pallets`) is found when a detection at or above the score threshold overlaps
its visible box with IoU >= 0.5 (the evaluation's rule). A miss is told apart by its best detection among those the
estimator kept (run it at a low score threshold, e.g. 0.02): one at IoU >= 0.5 but a low score, one at IoU 0.3-0.5
(a loose box), or none near it. Unlike `pallet6d eval`, no pallet is lost to `max_pallets`, the fit check or
missing depth, so the two differ by what the pose stage drops.

Recall at one score threshold moves with anything that shifts the scores (an int8 graph's calibration does, by a few
points): the average precision (`average_precision`, IoU 0.5, every detection matched greedily by score to the
counted pallets, those on a pallet under 10 % visible left out) compares detectors over all thresholds.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["HEIGHT_BINS_PX", "average_precision", "class_types", "detector_tally", "recall_rows", "recall_report",
           "type_names"]

HEIGHT_BINS_PX = ((0, 15), (15, 25), (25, 40), (40, 100000))


def recall_rows(est, data: str | Path, max_frames: int = 0) -> np.ndarray:
    """One row per counted pallet of the dataset's frames (`max_frames` 0: all), with `est.detect`'s detections.

    :param est: a `PalletEstimator`.
    :return: (n, 6) visible fraction, visible box height px, best IoU, that detection's score, the pallet's
        BOP object id, that detection's class id (-1: no detection).
    """
    return detector_tally(est, data, max_frames)[0]


def detector_tally(est, data: str | Path, max_frames: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`recall_rows`, and every detection's score and whether it found a counted pallet, from one detector run.

    :return: (n, 6) `recall_rows`; (m, 2) score, 1.0 for a detection matched to a counted pallet else 0.0, matched
        as the evaluation matches (`evaluation.match_greedy`: by descending score, IoU >= 0.5 with the visible box);
        one matched to a pallet under 10 % visible, neither counted nor background, is left out.
    """
    from .bop import BopDataset
    from .evaluation import box_iou, counted_pallets, match_greedy

    ds = BopDataset(data)
    rows, scored = [], []
    for i in range(min(len(ds), max_frames) if max_frames else len(ds)):
        f = ds[i]
        det = est.detect(f.rgb, f.depth_m)
        boxes = [(g, np.array([x, y, x + w, y + h], float)) for g in f.gts if g.bbox_visib_xywh is not None
                 for x, y, w, h in [g.bbox_visib_xywh]]
        counted = np.array(counted_pallets([g for g, _ in boxes]), bool)
        match, _ = match_greedy(det.boxes_xyxy, det.scores, np.array([b for _, b in boxes], float).reshape(-1, 4))
        keep = (match < 0) | counted[np.maximum(match, 0)] if len(boxes) else np.ones(len(det), bool)
        scored += [(float(sc), float(m >= 0)) for sc, m in zip(det.scores[keep], match[keep])]
        for (g, b), is_counted in zip(boxes, counted):
            if not is_counted:
                continue
            h = b[3] - b[1]
            if len(det) == 0:
                rows.append((g.visib_fract, h, 0.0, 0.0, g.obj_id, -1))
                continue
            iou = box_iou(det.boxes_xyxy, b[None])[:, 0]
            # the highest-scoring overlapping detection, else the best-overlapping one
            j = int(np.argmax(np.where(iou >= 0.5, det.scores, -1.0))) if (iou >= 0.5).any() else int(np.argmax(iou))
            rows.append((g.visib_fract, h, iou[j], det.scores[j], g.obj_id, det.class_ids[j]))
    return np.array(rows, dtype=np.float64).reshape(-1, 6), np.array(scored, dtype=np.float64).reshape(-1, 2)


def average_precision(scored: np.ndarray, n_gt: int) -> float:
    """Area under the precision-recall curve, precision made non-increasing in recall (every point counted, as
    PASCAL VOC 2010 on). :param scored: (m, 2) score, 1 true / 0 false positive (`detector_tally`).
    :param n_gt: the pallets to find. :return: in [0, 1]; 0 when there is nothing to find."""
    scored = np.asarray(scored, np.float64).reshape(-1, 2)
    if n_gt <= 0 or len(scored) == 0:
        return 0.0
    tp = scored[np.argsort(-scored[:, 0], kind="stable"), 1]
    recall = np.cumsum(tp) / n_gt
    precision = np.cumsum(tp) / np.arange(1, len(tp) + 1)
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    steps = np.diff(np.concatenate([[0.0], recall]))
    return float(np.sum(steps * precision))


def type_names(data: str | Path) -> dict[int, str]:
    """BOP object id -> the pallet type's name in the dataset's `models_info.json` (the id itself when unnamed)."""
    from .bop import BopDataset

    return {int(k): str(v.get("name", k)) for k, v in BopDataset(data).models_info.items()}


def class_types(est) -> dict[int, str]:
    """Detector class id -> the pallet type it reports, for the classes of an estimator that report one type each
    (a typed detector); a class that reports several (the depth tells them apart) is absent."""
    return {c: est.pallet_types[t[0]].name for c, t in est.type_choice.types_of_class.items()
            if len(t) == 1}


def recall_report(name: str, rows: np.ndarray, score_threshold: float, names: dict[int, str] | None = None,
                  classes: dict[int, str] | None = None, scored: np.ndarray | None = None) -> str:
    """Markdown: recall at `score_threshold` overall, by visible box height and (when the rows hold more than one
    object id) by pallet type, and the misses split by kind. With `classes`, the type table also says how many of
    the found pallets the detector gave their own type, and which type it gave the others. With `scored`, the
    precision at `score_threshold` and the average precision.

    :param rows: (n, 6) `recall_rows`. :param names: object id -> type name (`type_names`).
    :param classes: detector class id -> the type it reports (`class_types`).
    :param scored: (m, 2) `detector_tally`'s detections (of the detector run at a low threshold).
    """
    found = (rows[:, 2] >= 0.5) & (rows[:, 3] >= score_threshold)
    miss = rows[~found]
    lines = [f"## {name}", "", f"{len(rows)} pallets, recall {found.mean():.3f} at score {score_threshold}"]
    if scored is not None:
        above = scored[scored[:, 0] >= score_threshold]
        precision = f"{above[:, 1].mean():.3f}" if len(above) else "-"
        lines[-1] += (f", precision {precision} ({int(len(above) - above[:, 1].sum())} false boxes); "
                      f"average precision (IoU 0.5) {average_precision(scored, len(rows)):.3f}")
    lines += ["", "| visible box height | pallets | recall |", "|---|---|---|"]
    for lo, hi in HEIGHT_BINS_PX:
        sel = (rows[:, 1] >= lo) & (rows[:, 1] < hi)
        label = f"{lo}-{hi} px" if hi < 100000 else f">= {lo} px"
        lines.append(f"| {label} | {sel.sum()} | {found[sel].mean():.2f} |" if sel.any() else f"| {label} | 0 | - |")
    ids = np.unique(rows[:, 4]).astype(int)
    if len(ids) > 1:
        typed = bool(classes)
        lines += ["", "| pallet type | pallets | recall |" + (" type right | typed as (the others) |" if typed else ""),
                  "|---|---|---|" + ("---|---|" if typed else "")]
        for k in ids:
            sel = rows[:, 4] == k
            name = (names or {}).get(int(k), str(int(k)))
            line = f"| {name} | {sel.sum()} | {found[sel].mean():.2f} |"
            if typed:
                given = [classes.get(int(c), str(int(c))) for c in rows[sel & found, 5]]
                wrong = [t for t in given if t != name]
                right = f"{1 - len(wrong) / len(given):.2f}" if given else "-"
                others = ", ".join(f"{t} {wrong.count(t)}" for t in sorted(set(wrong), key=lambda t: -wrong.count(t)))
                line += f" {right} | {others} |"
            lines.append(line)
    lines += ["", f"misses: {np.sum(miss[:, 2] >= 0.5)} found with a score below {score_threshold}, "
              f"{np.sum((miss[:, 2] >= 0.3) & (miss[:, 2] < 0.5))} with a loose box (IoU 0.3-0.5), "
              f"{np.sum(miss[:, 2] < 0.3)} with nothing near", ""]
    return "\n".join(lines)
