"""A detector's recall and precision on labelled photographs (`real_data import`'s records): the tallies and the
report of `benchmarks/real_data.py`.

A detection is a true positive when it is matched to a labelled box at IoU >= the threshold, greedily by
descending score, each box matched at most once (`evaluation.match_greedy`, the evaluation's rule). Recall and
precision are tallied overall (sources labelled with the detector's whole-pallet convention), by box size (box
height as a fraction of the image height, `SIZE_BINS`: recall by the labelled box's size, precision by the
detection's own size) and by pallet kind; sources whose boxes cover a loaded unit are tallied on their own, since
their boxes are not the convention the detector is trained for. Pallet-free photos give false positives per frame.

Recall and precision count the detections at or above the report's score threshold; the average precision (AP at
the IoU threshold, `detector_recall.average_precision`) counts every detection it is given, so a detector run at a
low threshold is compared with another over all thresholds (a retrained detector's scores shift). By size, AP follows
COCO's area ranges: a detection matched to a box counts for that box's size, an unmatched one for its own size.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pallet6d.runtime.detector_recall import average_precision
from pallet6d.runtime.evaluation import match_greedy

from .real_data import SIZE_BINS, box_size_bins

__all__ = ["Tally", "RealDataReport", "markdown"]


@dataclass
class Tally:
    """Counts for recall (labelled boxes, matched) and precision (detections, true positives) at the threshold, and
    every detection's (score, true positive) for the average precision."""

    gt: int = 0
    matched: int = 0
    pred: int = 0
    tp: int = 0
    images: int = 0
    scored: list = field(default_factory=list)

    def add(self, gt: int, matched: int, pred: int, tp: int, images: int = 0,
            scored: np.ndarray | None = None) -> None:
        self.gt += gt
        self.matched += matched
        self.pred += pred
        self.tp += tp
        self.images += images
        if scored is not None and len(scored):
            self.scored.append(np.asarray(scored, np.float64).reshape(-1, 2))

    def to_dict(self) -> dict:
        scored = np.concatenate(self.scored) if self.scored else np.zeros((0, 2))
        return {"images": self.images, "boxes": self.gt, "detections": self.pred,
                "recall": self.matched / self.gt if self.gt else None,
                "precision": self.tp / self.pred if self.pred else None,
                "average_precision": average_precision(scored, self.gt) if self.gt else None}


@dataclass
class RealDataReport:
    """Tallies of one benchmark run: whole-pallet sources overall, by size, kind and source; other conventions
    apart; pallet-free photos."""

    overall: Tally = field(default_factory=Tally)
    by_size: dict[str, Tally] = field(default_factory=lambda: {s: Tally() for s in SIZE_BINS})
    by_kind: dict[str, Tally] = field(default_factory=dict)
    by_source: dict[str, Tally] = field(default_factory=dict)
    other_convention: dict[str, Tally] = field(default_factory=dict)
    negatives: int = 0
    negative_detections: int = 0

    def add_image(self, rec: dict, pred_xyxy: np.ndarray, scores: np.ndarray, iou_threshold: float,
                  score_threshold: float = 0.0) -> None:
        """Tally one photo's detections: those scored >= `score_threshold` for recall and precision, all of them
        for the average precision (greedy matching by score gives the thresholded ones the same matches)."""
        gt = np.asarray(rec["boxes_xyxy"], np.float64).reshape(-1, 4)
        pred_xyxy = np.asarray(pred_xyxy, np.float64).reshape(-1, 4)
        scores = np.asarray(scores, np.float64).reshape(-1)
        above = scores >= score_threshold
        if rec.get("negative"):
            self.negatives += 1
            self.negative_detections += int(above.sum())
            return
        match, _ = match_greedy(pred_xyxy, scores, gt, iou_threshold)
        tp = match >= 0
        found = np.zeros(len(gt), bool)
        found[match[tp & above]] = True
        scored = np.stack([scores, tp.astype(np.float64)], axis=1)
        counts = (len(gt), int(found.sum()), int(above.sum()), int((tp & above).sum()), 1, scored)
        if rec["convention"] != "whole_pallet":
            self.other_convention.setdefault(rec["source"], Tally()).add(*counts)
            return
        self.by_source.setdefault(rec["source"], Tally()).add(*counts)
        self.overall.add(*counts)
        for kind in rec["kinds"]:
            self.by_kind.setdefault(kind, Tally()).add(*counts)
        gt_bin = box_size_bins(gt[:, 3] - gt[:, 1], rec["height"])
        pred_bin = box_size_bins(pred_xyxy[:, 3] - pred_xyxy[:, 1], rec["height"])
        # a detection's size for AP: its box's where unmatched, else the box it matched (COCO's area ranges)
        ap_bin = np.where(tp, gt_bin[np.maximum(match, 0)] if len(gt) else pred_bin, pred_bin)
        for s in SIZE_BINS:
            g, p = gt_bin == s, pred_bin == s
            self.by_size[s].add(int(g.sum()), int(found[g].sum()), int((p & above).sum()), int((tp & p & above).sum()),
                                scored=scored[ap_bin == s])

    def to_dict(self) -> dict:
        return {"overall": self.overall.to_dict(), "by_size": {k: v.to_dict() for k, v in self.by_size.items()},
                "by_kind": {k: v.to_dict() for k, v in self.by_kind.items()},
                "by_source": {k: v.to_dict() for k, v in self.by_source.items()},
                "other_convention": {k: v.to_dict() for k, v in self.other_convention.items()},
                "negative_frames": self.negatives,
                "false_positives_per_negative_frame":
                    self.negative_detections / self.negatives if self.negatives else None}


def markdown(title: str, d: dict, settings: dict) -> str:
    """The report (`RealDataReport.to_dict()`) as a markdown page under `title`, its settings first."""
    def pct(v):
        return "-" if v is None else f"{100 * v:.1f} %"

    def row(name, t):
        ap = "-" if t.get("average_precision") is None else f"{t['average_precision']:.3f}"
        return f"| {name} | {t['images'] or ''} | {t['boxes']} | {t['detections']} | {pct(t['recall'])} | " \
               f"{pct(t['precision'])} | {ap} |"

    lines = [f"# {title}", "", ", ".join(f"{k}: {v}" for k, v in settings.items()), "",
             "| set | images | boxes | detections | recall | precision | AP |", "|---|---|---|---|---|---|---|",
             row("**overall (whole-pallet labels)**", d["overall"])]
    lines += [row(f"size {k}", v) for k, v in d["by_size"].items()]
    lines += [row(f"kind {k}", v) for k, v in d["by_kind"].items()]
    lines += [row(f"source {k}", v) for k, v in d["by_source"].items()]
    lines += ["", "Sources whose boxes cover the whole loaded unit (not the detector's convention): "
              + (", ".join(f"{k} recall {pct(v['recall'])}, precision {pct(v['precision'])}"
                           for k, v in d["other_convention"].items()) or "none"), "",
              f"Pallet-free photos: {d['negative_frames']} frames, "
              + ("-" if d["false_positives_per_negative_frame"] is None else
                 f"{d['false_positives_per_negative_frame']:.2f}") + " detector false positives per frame.", ""]
    return "\n".join(lines)
