"""The detector stage alone on BOP datasets: recall by visible box height and pallet type, what the misses are,
precision and average precision.

    python benchmarks/detector_recall.py --bundle models/epal-default --data data/val/virtual-occluded [...]

The rule and the rows: `pallet6d.runtime.detector_recall`.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pallet6d.runtime.detector_recall import class_types, detector_tally, recall_report, type_names


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
        rows, scored = detector_tally(est, data, args.max_frames)
        parts.append(recall_report(str(data), rows, args.score_threshold, type_names(data), class_types(est), scored))
    text = "\n".join(parts)
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
