"""Accuracy of a model bundle on held-out synthetic test sets, plotted like the paper's Fig. 4.

    python benchmarks/accuracy.py --bundle models/edge [--int8] [--frames 300] [--out benchmarks/results/accuracy]

Test sets: one per sim preset, generated once (or reused) under `--data-root` with the seeds of
`pallet6d.export.accuracy_report.TEST_SEEDS`, never used for training.

Writes to `--out`: `<preset>.json` (the `pallet6d eval` summary + per-pallet records), `accuracy_vs_threshold.png`
(ADD and symmetric ADD accuracy vs threshold 0-20 cm, one line per preset), `add_histogram.png` (per-pallet
symmetric-ADD distribution), `accuracy_by_distance.png`, and `accuracy.md` (our numbers beside the paper's).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from pallet6d.export.accuracy_report import PAPER, TEST_SEEDS, ensure_test_set, markdown, write_scores
from pallet6d.runtime.bundle import REPORT

log = logging.getLogger("accuracy")

CURVE_THRESHOLDS_M = np.linspace(0.0, 0.2, 81)


def accuracy_curve(errors_m: list, thresholds_m: np.ndarray) -> np.ndarray:
    """Fraction of JSON per-pallet errors below each threshold; None (missed) counts as a failure."""
    from pallet6d.runtime.metrics import accuracy_curve as curve

    return curve(np.array([np.inf if v is None else v for v in errors_m], dtype=np.float64), thresholds_m)


def plot(results: dict[str, dict], out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, key, title in ((axes[0], "add_m", "ADD"), (axes[1], "add_sym_m", "symmetric ADD")):
        for preset, doc in results.items():
            acc = accuracy_curve([r[key] for r in doc["records"]], CURVE_THRESHOLDS_M)
            ax.plot(CURVE_THRESHOLDS_M * 100, acc * 100, label=f"{preset} (n={doc['n_gt']})")
            paper = PAPER.get(preset, {})
            for t, v in paper.items():
                if v is not None and key == "add_m":
                    ax.plot(float(t) * 100, v * 100, "x", color=ax.lines[-1].get_color())
        ax.set_xlabel("threshold (cm)")
        ax.set_title(f"{title} accuracy (x: paper)" if key == "add_m" else f"{title} accuracy")
        ax.grid(alpha=0.3)
        ax.set_xlim(0, 20)
        ax.set_ylim(0, 100)
    axes[0].set_ylabel("accuracy (%) of pallets >= 10% visible")
    axes[0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    paths.append(out / "accuracy_vs_threshold.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(results), figsize=(4 * len(results), 3.5), squeeze=False)
    for ax, (preset, doc) in zip(axes[0], results.items()):
        e = np.array([r["add_sym_m"] for r in doc["records"] if r["add_sym_m"] is not None])
        missed = sum(r["add_sym_m"] is None for r in doc["records"])
        ax.hist(np.clip(e, 0, 1.0), bins=40, range=(0, 1.0), color="tab:blue")
        ax.set_title(f"{preset}: {len(e)} estimated, {missed} missed", fontsize=9)
        ax.set_xlabel("symmetric ADD per pallet (m, clipped at 1)")
    axes[0][0].set_ylabel("pallets")
    fig.tight_layout()
    paths.append(out / "add_histogram.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for preset, doc in results.items():
        bins = doc["by_distance"]
        if bins:
            centres = [(b["from_m"] + (b["to_m"] if b["to_m"] is not None else b["from_m"] + 2)) / 2 for b in bins]
            ax.plot(centres, [b["add_sym_acc"]["0.05"] * 100 for b in bins], "o-", label=f"{preset} @5cm")
            ax.plot(centres, [b["add_sym_acc"]["0.1"] * 100 for b in bins], "s--", label=f"{preset} @10cm",
                    color=ax.lines[-1].get_color())
    ax.set_xlabel("distance to pallet (m)")
    ax.set_ylabel("symmetric ADD accuracy (%)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "accuracy_by_distance.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--frames", type=int, default=300, help="frames per test set (default 300)")
    ap.add_argument("--presets", nargs="+", default=list(TEST_SEEDS), choices=list(TEST_SEEDS))
    ap.add_argument("--data-root", type=Path, default=Path("benchmarks/data"), help="where test sets are kept")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/accuracy"))
    ap.add_argument("--gt-boxes", action="store_true", help="score the pose stage alone on ground-truth boxes")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-refine", action="store_true", help="the network's poses without the ICP refinement")
    ap.add_argument("--refine-starts", type=int, default=None,
                    help="extra ICP starts around each pose (default: EstimatorOptions.refine_starts)")
    ap.add_argument("--max-pallets", type=int, default=None,
                    help="pose at most this many detections per frame (default: EstimatorOptions.max_pallets)")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the per-pallet point sampling (EstimatorOptions.seed): run a few to see the spread")
    ap.add_argument("--pallet-types", default=None,
                    help="comma-separated pallet types the site uses (EstimatorOptions.pallet_types; the paper presets "
                         "hold EPAL pallets only: epal); default: every type of the bundle")
    ap.add_argument("--type-candidates", type=int, default=None,
                    help="types refined per detection where its class reports several (EstimatorOptions."
                         "type_candidates)")
    ap.add_argument("--type-margin", type=float, default=None,
                    help="how much better another type must fit to replace a detection's first type "
                         "(EstimatorOptions.type_margin)")
    ap.add_argument("--structure", default=None,
                    help="StructureParams overrides as JSON, e.g. '{\"min_registration_peak\": 0}' (the structure "
                         "check's thresholds; default: the estimator's)")
    ap.add_argument("--write-scores", action="store_true",
                    help="record the summary in the bundle's report.json under scores.<fp32|int8>")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")

    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.eval_cli import evaluate_dataset, format_table

    precision = "int8" if args.int8 else "fp32"
    options = {k: v for k, v in (("refine_starts", args.refine_starts), ("max_pallets", args.max_pallets),
                                 ("type_candidates", args.type_candidates), ("type_margin", args.type_margin))
               if v is not None}
    if args.pallet_types:
        options["pallet_types"] = tuple(t.strip() for t in args.pallet_types.split(",") if t.strip())
    if args.structure is not None:
        from pallet6d.runtime.structure import StructureParams
        options["structure"] = StructureParams(**json.loads(args.structure))
    est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision=precision,
                                      refine=not args.no_refine, seed=args.seed, **options)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for preset in args.presets:
        data = ensure_test_set(preset, args.frames, args.data_root)
        out = evaluate_dataset(est, data, max_frames=args.frames, progress=True, gt_boxes=args.gt_boxes)
        doc = {"bundle": str(args.bundle), "graphs": precision, "data": str(data), "preset": preset,
               "test_seed": TEST_SEEDS[preset], **out["summary"], "records": out["records"]}
        (args.out / f"{preset}.json").write_text(json.dumps(doc, indent=1) + "\n")
        results[preset] = doc
        print(f"== {preset}\n{format_table(out['summary'])}")
    paths = plot(results, args.out)
    md = args.out / "accuracy.md"
    variant = precision + (", GT boxes" if args.gt_boxes else "") + (", no refinement" if args.no_refine else "") \
        + (f", {args.refine_starts} extra ICP starts" if args.refine_starts is not None and not args.no_refine else "") \
        + (f", at most {args.max_pallets} pallets per frame" if args.max_pallets is not None else "") \
        + (f", sampling seed {args.seed}" if args.seed else "") \
        + (f", site pallet types {args.pallet_types}" if args.pallet_types else "") \
        + (f", {args.type_candidates} types refined" if args.type_candidates is not None else "") \
        + (f", type margin {args.type_margin}" if args.type_margin is not None else "") \
        + (f", structure check {args.structure}" if args.structure is not None else "")
    md.write_text(markdown(results, str(args.bundle), variant, args.frames))
    print(f"wrote {md} and {', '.join(p.name for p in paths)}")
    if args.write_scores:
        write_scores(args.bundle, precision, results, " ".join(["python benchmarks/accuracy.py", *sys.argv[1:]]))
        print(f"wrote scores.{precision} into {args.bundle / REPORT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
