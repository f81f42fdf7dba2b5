"""Re-score saved per-pallet results against re-annotated ground truth, without running a model again.

    python benchmarks/rescore.py --results benchmarks/results/accuracy-epal-default/virtual-clean.json \
        --data benchmarks/data/virtual-clean-seed9001-300

For results made before `pallet6d sim` counted the part of a pallet outside the image as not visible
(`GT_INFO_VERSION` 2): regenerate the dataset with the same seed (same images, new annotations) and re-score
(`pallet6d.runtime.eval_cli.rescore`: exact, since the new visible fractions are never larger than the old).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pallet6d.runtime.eval_cli import rescore


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
