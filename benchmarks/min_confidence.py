"""Network confidence of right, wrong and made-up poses: what `EstimatorOptions.min_confidence` should be.

On validation frames it poses every frame as given (with min_confidence 0) and splits the accepted poses into
right (symmetric ADD to the nearest ground truth < 5 cm) and wrong; then it poses the same images on mismatched
inputs (a flat wall at 3 m as depth, another frame's depth, uint16 depth read with a 10x too small scale, focal
lengths 2x too large) where every pose is made up. It prints the share of each group kept at a few thresholds.

    python benchmarks/min_confidence.py --bundle models/epal-default --int8 \\
        --data data/val-virtual-occluded data/val-indoor-noisy --frames 8
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.evaluation import ground_truths_from_bop
from pallet6d.runtime.metrics import add_sym

THRESHOLDS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3)


def mismatched(frame, other) -> dict[str, tuple]:
    """(depth, K, depth_scale) of each mismatched input built from a frame and another one."""
    K2 = frame.K.copy()
    K2[0, 0] *= 2
    K2[1, 1] *= 2
    mm = np.round(frame.depth_m * 1000).astype(np.uint16)
    return {"flat wall depth": (np.full_like(frame.depth_m, 3.0), frame.K, None),
            "another frame's depth": (other.depth_m, frame.K, None),
            "depth_scale 10x too small": (mm, frame.K, 0.0001),
            "focal 2x too large": (frame.depth_m, K2, None)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", default="models/epal-default")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--data", nargs="+", required=True, help="BOP dataset folders")
    ap.add_argument("--frames", type=int, default=8, help="frames per dataset, evenly spread")
    args = ap.parse_args(argv)
    est = PalletEstimator.from_bundle(args.bundle, precision="int8" if args.int8 else "fp32", min_confidence=0.0)
    pts, syms = est.model_points_m, est.symmetries
    conf: dict[str, list[float]] = {"right": [], "wrong": [], "made up": []}
    by_case: dict[str, list[float]] = {}
    for root in args.data:
        ds = BopDataset(root)
        idx = np.linspace(0, len(ds) - 1, min(args.frames, len(ds))).astype(int)
        for n, i in enumerate(idx):
            f = ds[int(i)]
            gts, _ = ground_truths_from_bop(f.gts, f.rgb.shape[:2])
            for p in est.predict(f.rgb, f.depth_m, f.K):
                T = p.T_cam_pallet
                e = min((add_sym(T[:3, :3], T[:3, 3], g.T_cam_model[:3, :3], g.T_cam_model[:3, 3], pts, syms)
                         for g in gts), default=np.inf)
                conf["right" if e < 0.05 else "wrong"].append(p.confidence)
            other = ds[int(idx[(n + len(idx) // 2) % len(idx)])]
            for case, (depth, K, scale) in mismatched(f, other).items():
                c = [p.confidence for p in est.predict(f.rgb, depth, K, scale)]
                conf["made up"] += c
                by_case.setdefault(case, []).extend(c)
    print(f"{args.bundle} ({'int8' if args.int8 else 'fp32'}), {args.frames} frames of each of {', '.join(args.data)}")
    print("\n| poses | n | " + " | ".join(f"kept at {t}" for t in THRESHOLDS) + " |")
    print("|---|---|" + "---|" * len(THRESHOLDS))
    for name, c in [*conf.items(), *by_case.items()]:
        c = np.asarray(c)
        kept = " | ".join(f"{np.mean(c >= t):.0%}" if len(c) else "-" for t in THRESHOLDS)
        print(f"| {name} | {len(c)} | {kept} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
