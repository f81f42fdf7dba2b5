"""Re-score saved per-pallet results against re-annotated ground truth, without running a model again.

    python benchmarks/rescore.py --results benchmarks/results/accuracy-epal-default/virtual-clean.json \
        --data benchmarks/data/virtual-clean-seed9001-300

For results made before `pallet6d sim` counted the part of a pallet outside the image as not visible
(`GT_INFO_VERSION` 2): regenerate the dataset with the same seed (same images, new annotations) and re-score.
Each pallet's error does not depend on which pallets count, and the new visible fractions are never larger than
the old, so dropping the pallets now under 10 % visible is exact: their detections become ignored, not true
positives. Pallets are matched to the new annotations by frame and camera distance.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.evaluation import MIN_VISIB_FRACT, PalletRecord, ground_truths_from_bop, summarize

ERROR_KEYS = ("add_m", "add_sym_m", "adds_m", "rot_err_sym_deg", "trans_err_m")


def rescore(results: dict, data: str | Path, tol_m: float = 1e-6) -> dict:
    """The summary of `results` (a `pallet6d eval --json` document with its records) under `data`'s annotations.

    :raises ValueError: a record has no pallet at its distance in that frame (not the same dataset).
    """
    ds = BopDataset(data)
    gts_of: dict[int, list] = {}
    records, dropped_detected = [], 0
    for r in results["records"]:
        frame = int(r["frame"])
        if frame not in gts_of:
            f = ds[frame]
            gts_of[frame] = ground_truths_from_bop(f.gts, f.rgb.shape[:2])[0]
        dist = np.array([np.linalg.norm(g.T_cam_model[:3, 3]) for g in gts_of[frame]])
        j = int(np.argmin(np.abs(dist - r["distance_m"]))) if len(dist) else -1
        if j < 0 or abs(dist[j] - r["distance_m"]) > tol_m:
            raise ValueError(f"frame {frame}: no pallet at {r['distance_m']:.6f} m in {data}; "
                             "the results were made on another dataset")
        g = gts_of[frame][j]
        if g.visib_fract < MIN_VISIB_FRACT:
            dropped_detected += bool(r["detected"])
            continue
        errors = {k: math.inf if r[k] is None else float(r[k]) for k in ERROR_KEYS}
        records.append(PalletRecord(frame=frame, distance_m=float(r["distance_m"]), visib_fract=float(g.visib_fract),
                                    detected=bool(r["detected"]), truncated=bool(g.truncated), **errors))
    return summarize(records, results["true_positives"] - dropped_detected, results["false_positives"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", required=True, type=Path, help="a `pallet6d eval --json` / accuracy.py JSON file")
    ap.add_argument("--data", required=True, type=Path, help="the same frames, re-annotated (BOP dataset root)")
    ap.add_argument("--json", type=Path, help="write the new summary here")
    args = ap.parse_args(argv)
    before = json.loads(args.results.read_text())
    try:
        after = rescore(before, args.data)
    except ValueError as exc:
        print(f"rescore: {exc}", file=sys.stderr)
        return 1
    for name, s in (("before", before), ("after", after)):
        print(f"{name:>6}: {s['n_gt']} pallets, recall {s['recall']:.3f}, ADD-sym @2/5/10 cm "
              + " / ".join(f"{100 * s['add_sym_acc'][k]:.1f}" for k in ("0.02", "0.05", "0.1"))
              + " %, ADD @5/10 cm " + " / ".join(f"{100 * s['add_acc'][k]:.1f}" for k in ("0.05", "0.1")) + " %")
    if args.json:
        args.json.write_text(json.dumps(after, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
