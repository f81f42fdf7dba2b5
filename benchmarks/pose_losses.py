"""Where a BOP dataset's pallets are lost: for each counted pallet (>= 10 % visible), what the estimator made of it.

    python benchmarks/pose_losses.py --bundle B --int8 --data data/val/forklift-approach [--gt-boxes]
        [--known-type] [--calibrated] [--out report.md]

A pallet is matched to the accepted pose or rejected detection whose box overlaps its visible box most (IoU >= 0.5,
the evaluation's detector rule); without one it is "not detected". An accepted pose is scored by ADD-sym with the
pallet's own type (within 5 cm, 5-10 cm, >= 10 cm) and its type is compared with the truth.
- `--gt-boxes`: the pose stages get the counted pallets' visible boxes instead of detections (the pose stage alone);
- `--known-type`: each box is posed with its true type only, as a site that names its one type would (with
  `--gt-boxes`: the pose stage's limit once the type is known);
- `--calibrated`: each frame's camera calibration on its vehicle (the dataset's `scene_forklift.json`) goes to the
  estimator, as a forklift's would (poses levelled on its floor; `pallet6d eval --calibrated`).
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np


def outcome(gt, poses, rejected, models, names) -> tuple[str, bool | None]:
    """(outcome label, whether the accepted pose has the pallet's type; None when not posed)."""
    from pallet6d.runtime.evaluation import box_iou
    from pallet6d.runtime.metrics import add_sym

    cands = [(p, True) for p in poses] + [(r, False) for r in rejected]
    iou = box_iou(gt.box_visib_xyxy, np.array([c.box_xyxy for c, _ in cands]))[0] if cands else np.zeros(0)
    if len(iou) == 0 or iou.max() < 0.5:
        return "not detected", None
    best, accepted = cands[int(np.argmax(iou))]
    if not accepted:
        return f"rejected: {best.reason}", None
    pts, syms = models[gt.obj_id]
    T, Tg = best.T_cam_pallet, gt.T_cam_model
    err = add_sym(T[:3, :3], T[:3, 3], Tg[:3, :3], Tg[:3, 3], pts, syms)
    label = "accepted, within 5 cm" if err < 0.05 else "accepted, 5-10 cm" if err < 0.10 else "accepted, >= 10 cm"
    return label, best.pallet_type == names.get(gt.obj_id)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="BOP dataset root")
    ap.add_argument("--split", help="split folder (default: the only one)")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--max-frames", type=int, default=0, help="0: all")
    ap.add_argument("--gt-boxes", action="store_true", help="the counted pallets' visible boxes instead of detections")
    ap.add_argument("--known-type", action="store_true", help="pose each box with its true type only")
    ap.add_argument("--calibrated", action="store_true", help="give the estimator scene_forklift.json's calibration")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, help="also write the report here (markdown)")
    args = ap.parse_args(argv)
    if args.known_type and not args.gt_boxes:
        ap.error("--known-type needs --gt-boxes (a detection's true type is known only through its pallet)")

    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.evaluation import counted_pallets, dataset_models, ground_truths_from_bop

    precision = "int8" if args.int8 else "fp32"
    est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision=precision)
    ds = BopDataset(args.data, args.split)
    models = dataset_models(ds, est.pallet_types)
    names = {obj_id: info.get("name") for obj_id, info in ds.models_info.items()}
    by_type = {}
    if args.known_type:
        by_type = {g.name: PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision=precision,
                                                       pallet_types=(g.name,)) for g in est.pallet_types}
    counts: collections.Counter = collections.Counter()
    type_right: collections.Counter = collections.Counter()
    n = len(ds) if not args.max_frames else min(len(ds), args.max_frames)
    for i in range(n):
        f = ds[i]
        all_gts, _ = ground_truths_from_bop(f.gts, f.rgb.shape[:2])
        gts = [g for g, c in zip(all_gts, counted_pallets(all_gts)) if c]
        T_vc = f.T_vehicle_cam if args.calibrated else None
        if not args.gt_boxes:
            r = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
            poses, rejected = list(r.poses), list(r.rejected)
        elif args.known_type:
            # one call per type with all its boxes: the frame-level registration test pools its candidates' boxes
            poses, rejected = [], []
            for name in sorted({names.get(g.obj_id) for g in gts}, key=str):
                if name not in by_type:
                    raise SystemExit(f"pallet type {name!r} is not in {args.bundle}")
                boxes = np.array([g.box_visib_xyxy for g in gts if names.get(g.obj_id) == name]).reshape(-1, 4)
                r = by_type[name].estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
                poses += r.poses
                rejected += r.rejected
        else:
            boxes = np.array([g.box_visib_xyxy for g in gts]).reshape(-1, 4)
            r = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
            poses, rejected = list(r.poses), list(r.rejected)
        for g in gts:
            label, right = outcome(g, poses, rejected, models, names)
            counts[label] += 1
            if right is not None:
                type_right[label] += int(right)
    total = sum(counts.values())
    mode = ", ".join(m for m, on in (("ground-truth boxes", args.gt_boxes), ("true type only", args.known_type),
                                     ("calibrated", args.calibrated)) if on) or "detector, as shipped"
    lines = [f"# Where the pallets are lost: {args.data.name}, {n} frames, {total} pallets ({precision}; {mode})", "",
             "| outcome | pallets | share | of them with the right type |", "|---|---|---|---|"]
    for label, k in sorted(counts.items(), key=lambda kv: -kv[1]):
        right = f"{type_right[label]}" if label.startswith("accepted") else ""
        lines.append(f"| {label} | {k} | {k / max(total, 1):.1%} | {right} |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
