"""Accuracy with and without the structure check, from one pass of the estimator.

Runs the estimator with the structure check off on BOP datasets, then applies `runtime/structure.py` to the poses it
accepts, and scores both sets of poses with `pallet6d eval`'s protocol (`runtime/evaluation.py`: pallets at least
10 % visible count, a miss is a failure). The difference is the check's cost (or gain) in accuracy and precision.

    python benchmarks/structure_accuracy.py --bundle models/epal-default --int8 --data DIR [DIR ...] --frames 100 \
        --out benchmarks/results/structure-check/accuracy.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.evaluation import ScoreTally, evaluate_poses, ground_truths_from_bop
from pallet6d.runtime.structure import StructureParams, structure_check


def run(bundle: str, data: list[str], frames: int, int8: bool) -> dict:
    est = PalletEstimator.from_bundle(bundle, threads=2, precision="int8" if int8 else "fp32", structure=None)
    geom = est.pallet_types[0]
    out = {}
    for root in data:
        ds = BopDataset(root)
        tallies = {"without": ScoreTally(), "with": ScoreTally()}
        for i in range(min(frames, len(ds))):
            f = ds[i]
            gts, _ = ground_truths_from_bop(f.gts, f.rgb.shape[:2])
            poses = est.estimate(f.rgb, f.depth_m, f.K).poses
            keep = [True] * len(poses)
            if poses:
                scores = structure_check(np.stack([p.T_cam_pallet for p in poses]), geom.boxes_m, f.depth_m, f.K,
                                         np.stack([p.box_xyxy for p in poses]), StructureParams(), rgb=f.rgb)
                keep = [s.ok for s in scores]
            for name, sel in (("without", poses), ("with", [p for p, k in zip(poses, keep) if k])):
                tallies[name].add(evaluate_poses(i, sel, gts, geom.points_m, geom.symmetries))
        res = {}
        for name, tally in tallies.items():
            s = tally.summary()
            res[name] = {k: s[k] for k in ("n_gt", "precision", "recall", "add_sym_acc", "add_acc")}
            res[name]["false_positives"] = tally.false_positives
        out[Path(root).name] = res
        print(Path(root).name, json.dumps(res), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default="models/epal-default")
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    res = run(args.bundle, args.data, args.frames, args.int8)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
