"""The held-out synthetic test sets of a bundle's accuracy, its markdown table beside the paper's numbers, and its
scores in the bundle's report (`benchmarks/accuracy.py` runs the model and plots).

Test seeds 9001-9003 are never used for training (the `pallet6d train` recipe uses seeds 1000 and up), so test
scenes are never seen during training.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

__all__ = ["TEST_SEEDS", "PAPER", "ensure_test_set", "markdown", "write_scores"]

log = logging.getLogger(__name__)

TEST_SEEDS = {"virtual-clean": 9001, "virtual-occluded": 9002, "indoor-noisy": 9003}
# paper section 4.2: ADD accuracy at 5 cm / 10 cm (None: not reported)
PAPER = {"virtual-clean": {"0.05": 1.00, "0.1": None}, "virtual-occluded": {"0.05": 0.88, "0.1": None},
         "indoor-noisy": {"0.05": 0.56, "0.1": 0.82}}


def ensure_test_set(preset: str, frames: int, root: Path, seed: int | None = None) -> Path:
    """The test set of `preset` with `frames` frames (generated when missing, of another size, or annotated by
    an older generator: `GT_INFO_VERSION`), from `seed` (default: the preset's `TEST_SEEDS` entry)."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.sim.dataset import GT_INFO_VERSION, write_dataset
    from pallet6d.sim.presets import get_preset

    seed = TEST_SEEDS[preset] if seed is None else int(seed)
    out = root / f"{preset}-seed{seed}-{frames}"
    try:
        meta = json.loads((out / "test" / "sim_config_000000.json").read_text())
        if len(BopDataset(out)) == frames and meta.get("gt_info_version", 1) == GT_INFO_VERSION:
            log.info("reusing %s", out)
            return out
    except (OSError, ValueError):
        pass
    if out.exists():
        shutil.rmtree(out)
    log.info("generating %s (%d frames, seed %d)", out, frames, seed)
    t = time.perf_counter()
    write_dataset(get_preset(preset), frames, seed, out, split="test")
    log.info("generated in %.0f s", time.perf_counter() - t)
    return out


def markdown(results: dict[str, dict], bundle: str, precision: str, frames: int) -> str:
    """The accuracy page: per preset (`results`: `pallet6d eval` summaries) the scores beside the paper's, where the
    failures are by visible fraction and by the image border, and the plots' links."""
    def pct(v):
        return "-" if v is None else f"{100 * v:.0f}%"

    lines = [f"# Accuracy of `{bundle}` ({precision})", "",
             f"Held-out sim test sets ({frames} frames each; seeds {TEST_SEEDS}); pallets >= 10% visible; "
             "a missed pallet is a failure. Paper numbers: section 4.2 (ADD, its own datasets).", "",
             "| dataset | pallets | recall | precision | ADD @5cm | ADD @10cm | ADD-sym @5cm | ADD-sym @10cm "
             "| paper ADD @5cm | paper ADD @10cm |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for preset, d in results.items():
        p = PAPER.get(preset, {})
        lines.append(f"| {preset} | {d['n_gt']} | {pct(d['recall'])} | {pct(d['precision'])} | "
                     f"{pct(d['add_acc']['0.05'])} | {pct(d['add_acc']['0.1'])} | {pct(d['add_sym_acc']['0.05'])} | "
                     f"{pct(d['add_sym_acc']['0.1'])} | {pct(p.get('0.05'))} | {pct(p.get('0.1'))} |")
    lines += ["", "Where the failures are, by visible fraction of the pallet (share of that bin's pallets; symmetric ADD):",
              "", "| dataset | visible | pallets | < 5 cm | 5-10 cm | >= 10 cm | missed |", "|---|---|---|---|---|---|---|"]
    for preset, d in results.items():
        for b in d.get("by_visibility", []):
            lines.append(f"| {preset} | {b['from']:g}-{b['to']:g} | {b['n_gt']} | {pct(b['add_sym_lt_5cm'])} | "
                         f"{pct(b['add_sym_5_10cm'])} | {pct(b['add_sym_ge_10cm'])} | {pct(b['missed'])} |")
    lines += ["", "Pallets wholly in view and pallets cut by the image border (whose pose rests on the part in view):",
              "", "| dataset | where | pallets | < 5 cm | 5-10 cm | >= 10 cm | missed |", "|---|---|---|---|---|---|---|"]
    for preset, d in results.items():
        for b in d.get("by_truncation", []):
            where = "cut by the border" if b["truncated"] else "in view"
            lines.append(f"| {preset} | {where} | {b['n_gt']} | {pct(b['add_sym_lt_5cm'])} | "
                         f"{pct(b['add_sym_5_10cm'])} | {pct(b['add_sym_ge_10cm'])} | {pct(b['missed'])} |")
    lines += ["", "![accuracy vs threshold](accuracy_vs_threshold.png)", "", "![histogram](add_histogram.png)", "",
              "![by distance](accuracy_by_distance.png)", ""]
    return "\n".join(lines)


def write_scores(bundle: Path, precision: str, results: dict[str, dict], command: str) -> None:
    """Put the summaries in the bundle's report.json under scores.<precision> (`update_report`: locked and
    atomic, the fp32 and int8 runs may finish together; the manifest is not touched)."""
    from pallet6d.runtime.bundle import REPORT, update_report

    keep = ("n_gt", "frames", "precision", "recall", "add_acc", "add_sym_acc", "add_sym_median_m", "adds_acc")
    update_report(bundle, ("scores", precision), {
        "command": command, "protocol": "held-out sim test sets, pallets >= 10% visible, a miss is a failure",
        **{preset: {"test_seed": d["test_seed"], **{k: d[k] for k in keep if k in d}}
           for preset, d in results.items()}})
    log.info("wrote scores.%s into %s", precision, bundle / REPORT)
