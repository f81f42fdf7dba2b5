"""Which levels of our detector fire, and recall by box width in detector-input pixels.

    python benchmarks/detector_levels.py --bundle models/epal-default --data DIR [DIR ...] [--max-frames 100]

The YOLOv8 head predicts at strides 8, 16 and 32; each anchor's distance bins reach reg_max - 1 strides from it, so
the stride-8 level cannot draw a box wider than 2 x 15 x 8 = 240 input pixels. Per level: the highest class score
any anchor reaches over the frames and the detections it gives alone (before NMS across levels) at the score
threshold; then recall at IoU 0.5
by the visible box's width after letterboxing (the evaluation's counted pallets).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

WIDTH_BINS_PX = ((0, 60), (60, 120), (120, 180), (180, 240), (240, 300), (300, 100000))
STRIDES = (8, 16, 32)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="BOP dataset roots")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--score-threshold", type=float, default=0.25)
    ap.add_argument("--max-frames", type=int, default=100, help="per dataset")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, help="also write the report here (markdown)")
    args = ap.parse_args(argv)

    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.detector import decode_yolov8, undo_letterbox
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.evaluation import box_iou, counted_pallets

    est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision="int8" if args.int8 else "fp32")
    stage = est.detector
    best = np.zeros(len(STRIDES))
    fired = np.zeros(len(STRIDES), np.int64)
    rows = []                                                     # input width px, found
    for data in args.data:
        ds = BopDataset(data)
        for i in range(min(len(ds), args.max_frames)):
            f = ds[i]
            x, lb = stage.preprocess(f.rgb, f.depth_m)
            raw = stage.infer(x)[0]                               # (4 + nc, A), anchors level by level
            h, w = x.shape[2:]
            sizes = [(h // s) * (w // s) for s in STRIDES]
            level = np.repeat(np.arange(len(STRIDES)), sizes)
            score = raw[4:].max(axis=0)
            for k in range(len(STRIDES)):
                best[k] = max(best[k], float(score[level == k].max()))
            decode = lambda out: decode_yolov8(out, args.score_threshold, stage.iou_threshold,  # noqa: E731
                                               stage.class_ids, stage.max_detections, agnostic=True)
            for k in range(len(STRIDES)):                         # each level alone, before NMS across levels
                fired[k] += len(decode(raw[:, level == k]))
            det = decode(raw)
            boxes = undo_letterbox(det.boxes_xyxy, lb)
            for g, counted in zip(f.gts, counted_pallets(f.gts)):
                if not counted:
                    continue
                gx, gy, gw, gh = g.bbox_visib_xywh
                ok = len(boxes) > 0 and bool((box_iou(boxes, np.array([[gx, gy, gx + gw, gy + gh]], float)) >= 0.5).any())
                rows.append((gw * lb.scale_x, ok))
    r = np.array(rows, dtype=np.float64).reshape(-1, 2)
    lines = [f"# Detector levels: {args.bundle}{' (int8)' if args.int8 else ''}", "",
             f"{', '.join(str(d) for d in args.data)}; first {args.max_frames} frames each; score {args.score_threshold}",
             "", "| level (stride) | highest class score | detections of the level alone |", "|---|---|---|"]
    lines += [f"| {s} | {best[k]:.3f} | {fired[k]} |" for k, s in enumerate(STRIDES)]
    lines += ["", f"{len(r)} pallets, recall {r[:, 1].mean():.3f}", "",
              "| visible box width at the detector's input | pallets | recall |", "|---|---|---|"]
    for lo, hi in WIDTH_BINS_PX:
        m = (r[:, 0] >= lo) & (r[:, 0] < hi)
        label = f"{lo}-{hi} px" if hi < 100000 else f">= {lo} px"
        lines.append(f"| {label} | {m.sum()} | {r[m, 1].mean():.2f} |" if m.any() else f"| {label} | 0 | - |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
