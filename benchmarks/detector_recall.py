"""The detector stage alone on BOP datasets: recall by the visible box's height, and what the misses are.

    python benchmarks/detector_recall.py --bundle models/epal-default --data data/val/virtual-occluded [...]

A pallet at least 10 % visible is found when a detection at or above --score-threshold overlaps its visible box
with IoU >= 0.5 (the evaluation's rule). A miss is told apart by the best detection at score >= 0.02: one at
IoU >= 0.5 but a low score, one at IoU 0.3-0.5 (a loose box), or none near it. Unlike `pallet6d eval`, no
pallet is lost to `max_pallets`, the fit check or missing depth, so the two differ by what the pose stage drops.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HEIGHT_BINS_PX = ((0, 15), (15, 25), (25, 40), (40, 100000))


def rows_for(est, data: Path, max_frames: int) -> np.ndarray:
    """(n, 4): visible fraction, visible box height px, best IoU, that detection's score; one row per pallet."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.evaluation import MIN_VISIB_FRACT, box_iou

    ds = BopDataset(data)
    rows = []
    for i in range(min(len(ds), max_frames) if max_frames else len(ds)):
        f = ds[i]
        det = est.detect(f.rgb)
        for g in f.gts:
            if g.bbox_visib_xywh is None or g.visib_fract < MIN_VISIB_FRACT:
                continue
            x, y, w, h = g.bbox_visib_xywh
            if len(det) == 0:
                rows.append((g.visib_fract, h, 0.0, 0.0))
                continue
            iou = box_iou(det.boxes_xyxy, np.array([[x, y, x + w, y + h]], float))[:, 0]
            # the highest-scoring overlapping detection, else the best-overlapping one
            j = int(np.argmax(np.where(iou >= 0.5, det.scores, -1.0))) if (iou >= 0.5).any() else int(np.argmax(iou))
            rows.append((g.visib_fract, h, iou[j], det.scores[j]))
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def report(name: str, r: np.ndarray, score_threshold: float) -> str:
    found = (r[:, 2] >= 0.5) & (r[:, 3] >= score_threshold)
    miss = r[~found]
    lines = [f"## {name}", "", f"{len(r)} pallets, recall {found.mean():.3f} at score {score_threshold}", "",
             "| visible box height | pallets | recall |", "|---|---|---|"]
    for lo, hi in HEIGHT_BINS_PX:
        sel = (r[:, 1] >= lo) & (r[:, 1] < hi)
        label = f"{lo}-{hi} px" if hi < 100000 else f">= {lo} px"
        lines.append(f"| {label} | {sel.sum()} | {found[sel].mean():.2f} |" if sel.any() else f"| {label} | 0 | - |")
    lines += ["", f"misses: {np.sum(miss[:, 2] >= 0.5)} found with a score below {score_threshold}, "
              f"{np.sum((miss[:, 2] >= 0.3) & (miss[:, 2] < 0.5))} with a loose box (IoU 0.3-0.5), "
              f"{np.sum(miss[:, 2] < 0.3)} with nothing near", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="BOP dataset roots")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--score-threshold", type=float, default=0.25)
    ap.add_argument("--max-frames", type=int, default=0, help="per dataset (0: all)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, help="also write the report here (markdown)")
    args = ap.parse_args(argv)

    from pallet6d.runtime.estimator import PalletEstimator

    # score 0.02 and no cap: the report needs the low-scoring detections to tell the misses apart
    est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision="int8" if args.int8 else "fp32",
                                      score_threshold=0.02, max_pallets=1000)
    parts = [f"# Detector recall: {args.bundle}{' (int8)' if args.int8 else ''}", ""]
    for data in args.data:
        parts.append(report(str(data), rows_for(est, data, args.max_frames), args.score_threshold))
    text = "\n".join(parts)
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
