"""A detector's recall and precision on labelled photographs (`real_data import`'s records): the tallies and the
report of `benchmarks/real_data.py`.

A detection is a true positive when it is matched to a labelled box at IoU >= the threshold, greedily by
descending score, each box matched at most once (`evaluation.match_greedy`, the evaluation's rule). Recall and
precision are tallied overall (sources labelled with the detector's whole-pallet convention), by box size (box
height as a fraction of the image height, `SIZE_BINS`: recall by the labelled box's size, precision by the
detection's own size) and by pallet kind; sources whose boxes cover a loaded unit are tallied on their own, since
their boxes are not the convention the detector is trained for. Pallet-free photos give false positives per frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pallet6d.runtime.evaluation import match_greedy

from .real_data import SIZE_BINS, box_size_bins

__all__ = ["Tally", "RealDataReport", "markdown"]


@dataclass
class Tally:
    """Counts for recall (labelled boxes, matched) and precision (detections, true positives)."""

    gt: int = 0
    matched: int = 0
    pred: int = 0
    tp: int = 0
    images: int = 0

    def add(self, gt: int, matched: int, pred: int, tp: int, images: int = 0) -> None:
        self.gt += gt
        self.matched += matched
        self.pred += pred
        self.tp += tp
        self.images += images

    def to_dict(self) -> dict:
        return {"images": self.images, "boxes": self.gt, "detections": self.pred,
                "recall": self.matched / self.gt if self.gt else None,
                "precision": self.tp / self.pred if self.pred else None}


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

    def add_image(self, rec: dict, pred_xyxy: np.ndarray, scores: np.ndarray, iou_threshold: float) -> None:
        gt = np.asarray(rec["boxes_xyxy"], np.float64).reshape(-1, 4)
        if rec.get("negative"):
            self.negatives += 1
            self.negative_detections += len(pred_xyxy)
            return
        match, matched = match_greedy(pred_xyxy, scores, gt, iou_threshold)
        tp = match >= 0
        counts = (len(gt), int(matched.sum()), len(pred_xyxy), int(tp.sum()), 1)
        if rec["convention"] != "whole_pallet":
            self.other_convention.setdefault(rec["source"], Tally()).add(*counts)
            return
        self.by_source.setdefault(rec["source"], Tally()).add(*counts)
        self.overall.add(*counts)
        for kind in rec["kinds"]:
            self.by_kind.setdefault(kind, Tally()).add(*counts)
        gt_bin = box_size_bins(gt[:, 3] - gt[:, 1], rec["height"])
        pred_bin = box_size_bins(pred_xyxy[:, 3] - pred_xyxy[:, 1], rec["height"])
        for s in SIZE_BINS:
            g, p = gt_bin == s, pred_bin == s
            self.by_size[s].add(int(g.sum()), int(matched[g].sum()), int(p.sum()), int(tp[p].sum()))

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
        return f"| {name} | {t['images'] or ''} | {t['boxes']} | {t['detections']} | {pct(t['recall'])} | " \
               f"{pct(t['precision'])} |"

    lines = [f"# {title}", "", ", ".join(f"{k}: {v}" for k, v in settings.items()), "",
             "| set | images | boxes | detections | recall | precision |", "|---|---|---|---|---|---|",
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
