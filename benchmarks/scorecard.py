"""A bundle's scorecard: every measure the open targets are set on, for one or more bundles, in one table.

    python benchmarks/scorecard.py --bundle CANDIDATE --bundle models/epal-default [--precision int8] \\
        [--measures presets,forklift,mismatched,mismatched-heldout,negatives,negatives-heldout,pockets,...] \\
        [--quick] [--split val] --out benchmarks/results/scorecard

The ship decision compares a candidate with the shipped bundle on all of these at once, measured the same way on
the same data (a candidate that gains on one set and loses on another must show both):

- `presets`: ADD-sym within 5 cm on the paper's three presets (the held-out test sets of `benchmarks/accuracy.py`,
  seeds 9001-9003, 100 frames each); the results file keeps why the missed pallets were missed (`pallet6d eval`'s
  `missed_by_reason`), as `forklift`'s does.
- `forklift`: the calibrated forklift-approach and mixed test frames (seeds 9004, 9005, 100 frames each; each frame's
  camera calibration goes to the estimator): within 5 cm, and the precision of the accepted poses.
- `mismatched`: poses the estimator accepts from inputs that do not belong together (another frame's depth, a flat
  wall's, depth 10x too near, focal length 2x too long, a transposed K, fx = fy = 1e9; `benchmarks/structure_check.py`
  builds them), before its structure check and with it, and correct poses kept as recorded, on the validation frames
  (seeds 8011-8013, 30 frames each). A kept pose is made up where it lies 5 cm or more (ADD-sym) from every pallet of
  the image; another frame's depth of a scene that stands where the image's does shows the image's pallets where
  they are, and a pose found there is right. `mismatched-heldout`: the same on 30 frames of each test set (seeds
  9001-9003), which no threshold was chosen on.
- `negatives`: accepted poses on simulated pallet-free frames (`benchmarks/real_data.py --sim-negatives`): loads set
  down (five presets x 40 frames, seeds 9100 and 9200), the same in calibrated forklift views (forklift-approach and
  mixed), loads hanging (seed 9100); the rendered frames are kept under `DATA/pallet-free/`. The structure check's
  thresholds were chosen on these seeds: `negatives-heldout` counts the same on seeds 9300-9500, which nothing was
  tuned on (loads set down 600 frames, calibrated views 240, hanging 200 of seed 9300). Bundles are also compared
  frame by frame there: a few accepted poses in all cannot rank two detectors, the frames only one of them keeps
  clear can.
- `pockets`: the 60 EPAL forklift targets 1-4 m ahead (`benchmarks/forklift_pockets.py` on
  `data/forklift-frames-epal`, made here when missing): both pockets within 2 cm and the face yaw within 1 degree,
  exact and D435-like depth; blocked pockets called safe. `pockets-all`: the same on 100 targets of every pallet
  type (`data/forklift-frames`).
- `real`: detector recall and precision at IoU 0.5 on the held-out real photographs (`data/real`, imported as in
  docs/data.md; not measured, with a note, where it is missing).

Every measure runs the bundle at `--precision` (int8: the edge configuration) with its default options, and once
more for each `--variant LABEL=JSON` with those `EstimatorOptions` overrides (`"structure"`: `StructureParams`
overrides), so a change of the runtime's options is judged like a new bundle:

    python benchmarks/scorecard.py --bundle models/epal-default --variant 'peak05={"structure":
        {"min_registration_peak": 0.05}}' --out runs/scorecard

`--split val` runs `presets`, `forklift`, `pockets` and `pockets-all` on validation frames instead (seeds 8011-8013
pooled with 60 frames each of seeds 8021-8023 and 300 frames of the noisy preset's seed 8033, 8015 / 8016, 8031 (200
EPAL targets) and 819, under `--data`, made when missing; one seed's 100 frames hold too few pallets to choose on, the
noisy preset's 100 above all): a change or a training round is chosen there and judged once on the test frames.
`mismatched` (validation frames), `mismatched-heldout` (test frames), the negatives (the seeds their thresholds were
chosen on, and a held-out one) and `real` (the held-out photographs) keep their frames either way.

Results are kept per bundle, variant and measure (`OUT/<bundle name>[+<label>]/<measure>[-val]-<precision>.json`):
a second call measures only what is missing (delete a file to measure it again). `--quick` uses a fraction of the
frames, for trying the command, never for a decision. Writes `OUT/scorecard.md`. Latency is not here: it needs an
otherwise idle machine (`benchmarks/latency.py`).

With two or more bundles the scorecard also compares each with the first pallet by pallet on the presets, the
forklift views and the pocket targets: the pallets (targets) only one of them gets right, and the exact sign test's p
on them (is a difference of a few pallets more than the draw of pallets?). Results kept from before those files held
each pallet's outcome show "-" there until they are measured again.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from datetime import datetime, timezone
from pathlib import Path


MEASURES = ("presets", "forklift", "mismatched", "mismatched-heldout", "negatives", "negatives-heldout", "pockets",
            "pockets-all", "real")
SPLITS = ("test", "val")
SPLIT_MEASURES = ("presets", "forklift", "pockets", "pockets-all")    # the measures whose frames `--split` chooses
PAPER_PRESETS = ("virtual-clean", "virtual-occluded", "indoor-noisy")
VAL_SEEDS = {"virtual-clean": 8011, "virtual-occluded": 8012, "indoor-noisy": 8013}
# the validation presets' further seeds and their frames, pooled with VAL_SEEDS' 100 frames: one seed's frames hold
# too few pallets to choose on, the noisy preset's above all (one pallet a frame), which gets 300 frames more
VAL_POOLED = {"virtual-clean": ((8021, 60),), "virtual-occluded": ((8022, 60),),
              "indoor-noisy": ((8023, 60), (8033, 300))}
FORKLIFT_SEEDS = {"test": {"forklift-approach": 9004, "mixed": 9005}, "val": {"forklift-approach": 8015, "mixed": 8016}}
# forklift targets (`benchmarks/forklift_frames.py`) per measure and split: folder under --data, seed, frames (quick:
# a quarter), pallet types (None: every type)
TARGET_SETS = {("pockets", "test"): ("forklift-frames-epal", 8, 60, "epal"),
               ("pockets", "val"): ("forklift-frames-epal-val", 8031, 200, "epal"),
               ("pockets-all", "test"): ("forklift-frames", 7, 100, None),
               ("pockets-all", "val"): ("forklift-frames-val", 819, 100, None)}
NEGATIVE_PRESETS = ("virtual-clean", "virtual-occluded", "indoor-noisy", "forklift-approach", "mixed")
# the pallet-free seeds the structure check's thresholds were chosen on, and three it never saw
TUNED_NEGATIVE_SEEDS = (9100, 9200)
HELDOUT_NEGATIVE_SEEDS = (9300, 9400, 9500)
NEGATIVE_SEEDS = {"negatives": TUNED_NEGATIVE_SEEDS, "negatives-heldout": HELDOUT_NEGATIVE_SEEDS}

# (key, what, target): the rows of the table, in order; a target states the open issues' goal for that figure
ROWS = (
    ("presets.virtual-clean", "ADD-sym within 5 cm, virtual-clean (%)", ">= 98.1"),
    ("presets.virtual-occluded", "ADD-sym within 5 cm, virtual-occluded (%)", ">= 83.0"),
    ("presets.indoor-noisy", "ADD-sym within 5 cm, indoor-noisy (%)", ">= 93.7"),
    ("forklift.forklift-approach", "forklift-approach within 5 cm, calibrated (%)", ">= 95"),
    ("forklift.mixed", "mixed within 5 cm, calibrated (%)", ""),
    ("forklift.forklift-approach-precision", "forklift-approach, precision of the accepted poses", ""),
    ("forklift.mixed-precision", "mixed, precision of the accepted poses", ""),
    ("mismatched.made_up", "mismatched inputs: made-up poses kept (5 cm or more off every pallet)", "0"),
    ("mismatched.kept", "mismatched inputs: poses kept", ""),
    ("mismatched.accepted", "mismatched inputs: poses before the structure check", ""),
    ("mismatched.recorded_within_5cm", "as recorded: poses within 5 cm before the structure check", ""),
    ("mismatched.recorded_kept_within_5cm", "as recorded: poses within 5 cm kept", ""),
    ("mismatched-heldout.made_up", "mismatched inputs, test frames: made-up poses kept", "0"),
    ("mismatched-heldout.kept", "mismatched inputs, test frames: poses kept", ""),
    ("mismatched-heldout.accepted", "mismatched inputs, test frames: poses before the structure check", ""),
    ("negatives.set_down", "pallet-free, loads set down: accepted poses", "0"),
    ("negatives.calibrated", "pallet-free, calibrated forklift views: accepted poses", "0"),
    ("negatives.hanging", "pallet-free, loads hanging: accepted poses", "0"),
    ("negatives-heldout.set_down", "pallet-free, held-out seeds, loads set down: accepted poses", "0"),
    ("negatives-heldout.calibrated", "pallet-free, held-out seeds, calibrated forklift views: accepted poses", "0"),
    ("negatives-heldout.hanging", "pallet-free, held-out seed 9300, loads hanging: accepted poses", "0"),
    ("pockets.exact", "EPAL pockets within 2 cm and 1 degree, exact depth (%)", ">= 95"),
    ("pockets.d435", "EPAL pockets within 2 cm and 1 degree, D435-like depth (%)", "report"),
    ("pockets.blocked_safe", "blocked pockets called safe", "0"),
    ("pockets-all.exact", "every type's pockets within 2 cm and 1 degree, exact depth (%)", ">= 95"),
    ("pockets-all.d435", "every type's pockets within 2 cm and 1 degree, D435-like depth (%)", "report"),
    ("pockets-all.blocked_safe", "every type: blocked pockets called safe", "0"),
    ("real.recall", "real photographs: recall (%)", ">= 90"),
    ("real.precision", "real photographs: precision (%)", ">= 90"),
    ("real.ap", "real photographs: average precision over every score", ""),
    ("real.negative_fp", "real pallet-free photographs: false boxes per photo", ""),
)


def _stale(measure: str, split: str, path: Path) -> bool:
    """Whether a kept result was measured on other frames than `measure` now takes: validation presets pooled from
    other seeds, pallet-free frames of other seeds or kept without each frame's outcome."""
    if measure in NEGATIVE_SEEDS:
        kept = json.loads(path.read_text())
        return kept.get("seeds") != list(NEGATIVE_SEEDS[measure]) or "set_down-clear" not in kept
    if measure != "presets" or split != "val":
        return False
    return json.loads(path.read_text()).get("seeds") != {p: val_seeds(p) for p in PAPER_PRESETS}


def val_seeds(preset: str) -> list[int]:
    """The validation seeds of a paper preset, its first one first."""
    return [VAL_SEEDS[preset]] + [seed for seed, _ in VAL_POOLED[preset]]


def _pct(x: float) -> float:
    return round(100.0 * float(x), 2)


def _nested_options() -> dict:
    """The options given as a dict of a dataclass's fields in the JSON overrides: option name -> (that dataclass,
    what it is called in an error)."""
    from pallet6d.runtime.depth_proposals import DepthProposals
    from pallet6d.runtime.level import LevelParams
    from pallet6d.runtime.structure import StructureParams
    from pallet6d.runtime.weak_boxes import WeakBoxes
    return {"structure": (StructureParams, "structure check"), "weak_boxes": (WeakBoxes, "weak box"),
            "depth_proposals": (DepthProposals, "depth proposal"), "level": (LevelParams, "levelling")}


def estimator_options(overrides: dict) -> dict:
    """`EstimatorOptions` keyword arguments from JSON overrides ("structure", "weak_boxes", "depth_proposals",
    "level": a dict of `StructureParams`, `WeakBoxes`, `DepthProposals`, `LevelParams` fields).
    :raises ValueError: an unknown option or field, or a value the options refuse."""
    from dataclasses import fields

    from pallet6d.runtime.estimator import EstimatorOptions

    known = {f.name for f in fields(EstimatorOptions)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"unknown estimator options {unknown}")
    out = dict(overrides)
    for name, (cls, called) in _nested_options().items():
        if isinstance(out.get(name), dict):
            bad = sorted(set(out[name]) - {f.name for f in fields(cls)})
            if bad:
                raise ValueError(f"unknown {called} fields {bad}")
            out[name] = cls(**out[name])
    EstimatorOptions(**out)                      # its own checks, before any measuring
    return out


def _estimator(bundle: Path, precision: str, options: dict, **fixed):
    from pallet6d.runtime.estimator import PalletEstimator
    return PalletEstimator.from_bundle(bundle, threads=2, precision=precision, **{**options, **fixed})


# (measure, key of each pallet's outcome as "0"/"1", row label) for the pallet-by-pallet comparison
PAIRED_ROWS = (tuple(("presets", f"{p}-within5", f"{p} within 5 cm") for p in PAPER_PRESETS)
               + tuple(("forklift", f"{p}-within5", f"{p} within 5 cm, calibrated") for p in FORKLIFT_SEEDS["test"])
               + (("pockets", "exact-ok", "EPAL pocket targets, exact depth"),
                  ("pockets", "d435-ok", "EPAL pocket targets, D435-like depth"),
                  ("pockets-all", "exact-ok", "every type's pocket targets, exact depth"),
                  ("pockets-all", "d435-ok", "every type's pocket targets, D435-like depth"))
               + tuple((m, f"{run}-clear", f"pallet-free frames{seed}, {what}: without a pose")
                       for m, seed in (("negatives", ""), ("negatives-heldout", " of the held-out seeds"))
                       for run, what in (("set_down", "loads set down"), ("calibrated", "calibrated forklift views"),
                                         ("hanging", "loads hanging"))))


def within_5cm_bits(records: list[dict] | None) -> str:
    """Each counted pallet's outcome in the dataset's order, "1" within 5 cm (ADD-sym) and "0" not (a missed
    pallet is a "0"): two bundles measured on the same frames are then compared pallet by pallet. "" without
    records."""
    return "".join("1" if r.get("add_sym_m") is not None and r["add_sym_m"] < 0.05 else "0" for r in records or ())


def sign_test(gained: int, lost: int) -> float:
    """The exact two-sided sign test (McNemar's exact test) on the pallets two bundles disagree on: how likely a
    split at least this uneven is when each such pallet goes either way with probability 1/2."""
    n, k = gained + lost, min(gained, lost)
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)     # exact integers: no overflow


def paired_table(names: list[str], results: list[dict]) -> str:
    """Each bundle after the first against the first, pallet by pallet on the frames both were measured on
    (`PAIRED_ROWS`): the pallets it alone gets right (+), those the first alone gets right (-), and the sign test's p;
    "" for one bundle or nothing to compare."""
    if len(names) < 2:
        return ""
    lines = ["| right for one bundle alone | " + " | ".join(f"`{n}`" for n in names[1:]) + " |",
             "|---|" + "---|" * (len(names) - 1)]
    for measure, key, what in PAIRED_ROWS:
        base = results[0].get(measure, {}).get(key)
        cells = []
        for r in results[1:]:
            other = r.get(measure, {}).get(key)
            if not base or not other or len(base) != len(other):
                cells.append("-")
                continue
            gained = sum(a == "0" and b == "1" for a, b in zip(base, other))
            lost = sum(a == "1" and b == "0" for a, b in zip(base, other))
            cells.append(f"+{gained} / -{lost} (p {sign_test(gained, lost):.2g})")
        if any(c != "-" for c in cells):
            lines.append(f"| {what} ({len(base)}) | " + " | ".join(cells) + " |")
    if len(lines) == 2:
        return ""
    return (f"Pallet by pallet against `{names[0]}` (right for the column's bundle alone +, for `{names[0]}` alone -; "
            "pallets within 5 cm, pocket targets with both pockets within 2 cm and the face within 1 degree, "
            "pallet-free frames without an accepted pose; p: the exact sign test on those, small where the draw of "
            "pallets or frames does not explain the difference):\n\n"
            + "\n".join(lines) + "\n")


def measure_presets(bundle: Path, precision: str, options: dict, frames: int, data_root: Path,
                    split: str = "test") -> dict:
    from pallet6d.export.accuracy_report import TEST_SEEDS, ensure_test_set
    from pallet6d.runtime.eval_cli import evaluate_dataset

    seeds = TEST_SEEDS if split == "test" else VAL_SEEDS
    est = _estimator(bundle, precision, options)
    out = {}
    for preset in PAPER_PRESETS:
        sets = [(seeds[preset], frames)]
        if split == "val":
            # --quick's fewer frames take as large a share of each pooled seed's
            sets += [(seed, max(1, n * min(frames, 100) // 100)) for seed, n in VAL_POOLED[preset]]
        within, n_gt, missed, by_seed, bits = 0.0, 0, {}, {}, ""
        for seed, n_frames in sets:
            ev = evaluate_dataset(est, ensure_test_set(preset, n_frames, data_root, seed), "test")
            s = ev["summary"]
            bits += within_5cm_bits(ev.get("records"))
            within += s["add_sym_acc"]["0.05"] * s["n_gt"]
            n_gt += s["n_gt"]
            by_seed[seed] = _pct(s["add_sym_acc"]["0.05"])
            for reason, counts in s["missed_by_reason"].items():
                into = missed.setdefault(reason, {})
                for k, v in counts.items():
                    into[k] = into.get(k, 0) + v
        out[preset] = _pct(within / n_gt if n_gt else 0.0)
        out[f"{preset}-pallets"] = n_gt
        out[f"{preset}-missed"] = missed
        out[f"{preset}-by_seed"] = by_seed
        out[f"{preset}-within5"] = bits
    out["seeds"] = {p: seeds[p] if split == "test" else val_seeds(p) for p in PAPER_PRESETS}
    return out


def measure_forklift(bundle: Path, precision: str, options: dict, frames: int, data_root: Path,
                     split: str = "test") -> dict:
    from pallet6d.export.accuracy_report import ensure_test_set
    from pallet6d.runtime.eval_cli import evaluate_dataset

    est = _estimator(bundle, precision, options)
    out = {}
    for preset, seed in FORKLIFT_SEEDS[split].items():
        root = ensure_test_set(preset, frames, data_root, seed)
        ev = evaluate_dataset(est, root, "test", calibrated=True)
        s = ev["summary"]
        out[preset] = _pct(s["add_sym_acc"]["0.05"])
        out[f"{preset}-within5"] = within_5cm_bits(ev.get("records"))
        out[f"{preset}-precision"] = round(float(s["precision"]), 3)
        out[f"{preset}-pallets"] = s["n_gt"]
        out[f"{preset}-missed"] = s["missed_by_reason"]
    return out


def measure_mismatched(bundle: Path, precision: str, options: dict, frames: int, root: Path,
                       seeds: dict[str, int] = VAL_SEEDS) -> dict:
    """Poses the estimator accepts, as it runs (its own type choice and structure check), from inputs that do not
    belong together, and the correct poses it keeps from the frames as recorded; and, from the same estimator with
    its structure check off, how many it accepts before that check. A kept pose more than 5 cm (ADD-sym) from every
    pallet of the image is made up (`made_up`); the others are the image's pallets found on a depth that shows them
    where they are (another frame's depth of the same scene)."""
    import structure_check

    from pallet6d.export.accuracy_report import ensure_test_set
    from pallet6d.runtime.bop import BopDataset

    roots = [ensure_test_set(p, frames, root, seed) for p, seed in seeds.items()]
    shipped = _estimator(bundle, precision, options)
    unchecked = _estimator(bundle, precision, options, structure=None)
    out = {"kept": 0, "made_up": 0, "accepted": 0, "by_variant": {}, "made_up_by_variant": {},
           "accepted_by_variant": {}, "recorded_kept_within_5cm": 0, "recorded_within_5cm": 0,
           "seeds": dict(seeds)}
    for root in roots:
        ds = BopDataset(root)
        n = min(frames, len(ds))
        for variant in structure_check.VARIANTS:
            kept, before = (structure_check.estimate(e, ds, variant, n)["err"] for e in (shipped, unchecked))
            if variant == "as_recorded":
                out["recorded_kept_within_5cm"] += int((kept < 0.05).sum())
                out["recorded_within_5cm"] += int((before < 0.05).sum())
                continue
            made_up = int((kept >= 0.05).sum())
            out["kept"] += len(kept)
            out["made_up"] += made_up
            out["accepted"] += len(before)
            out["by_variant"][variant] = out["by_variant"].get(variant, 0) + len(kept)
            out["made_up_by_variant"][variant] = out["made_up_by_variant"].get(variant, 0) + made_up
            out["accepted_by_variant"][variant] = out["accepted_by_variant"].get(variant, 0) + len(before)
    return out


def measure_negatives(bundle: Path, precision: str, options: dict, frames: int, cache: Path,
                      seeds: tuple[int, ...] = TUNED_NEGATIVE_SEEDS) -> dict:
    """Accepted poses on pallet-free frames of `seeds` (the hanging loads: the first seed alone)."""
    from real_data import sim_negatives

    est = _estimator(bundle, precision, options)
    runs = {"set_down": [(list(NEGATIVE_PRESETS), s, False, True) for s in seeds],
            "calibrated": [(["forklift-approach", "mixed"], s, True, True) for s in seeds],
            "hanging": [(list(NEGATIVE_PRESETS), seeds[0], False, False)]}
    out = {}
    for name, specs in runs.items():
        total, frames_seen, by_preset, clear = 0, 0, {}, ""
        for presets, seed, calibrated, set_down in specs:
            for preset, r in sim_negatives(est, presets, frames, seed, calibrated, set_down, cache).items():
                n = sum(r["accepted_by_frame"])
                total += n
                frames_seen += r["frames"]
                by_preset[f"{preset}/{seed}"] = n
                clear += "".join("0" if k else "1" for k in r["accepted_by_frame"])
        out[name] = total
        out[f"{name}-frames"] = frames_seen
        out[f"{name}-by_preset"] = by_preset
        out[f"{name}-clear"] = clear        # "1": a frame without an accepted pose, in the frames' order
    out["seeds"] = list(seeds)
    return out


def _forklift_frames(root: Path, frames: int, seed: int, models: str | None) -> Path:
    """Forklift targets' frames (`benchmarks/forklift_frames.py --frames N --seed S [--models M]`), rendered when
    fewer are there."""
    import subprocess

    if len(list(root.glob("*.npz"))) < frames:
        print(f"scorecard: rendering {root}", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, str(Path(__file__).with_name("forklift_frames.py")), "--out", str(root),
                        "--frames", str(frames), "--seed", str(seed), *(["--models", models] if models else [])],
                       check=True, stdout=subprocess.DEVNULL)
    return root


def measure_pockets(bundle: Path, precision: str, options: dict, frames: int, frames_dir: Path, seed: int = 8,
                    models: str | None = "epal") -> dict:
    from forklift_pockets import evaluate, npz_frames, target_met

    from pallet6d.runtime.forklift import ForkliftParams

    root = _forklift_frames(frames_dir, frames, seed, models)
    est = _estimator(bundle, precision, options)
    first = {p.stem for p in sorted(root.glob("*.npz"))[:frames]}
    res = evaluate((fr for fr in npz_frames(root) if fr["frame"] in first), ForkliftParams(), est)
    out = {}
    for depth, key in (("clean", "exact"), ("d435", "d435")):
        s = res[depth]
        out[key] = _pct(s["within_2cm_1deg"])
        out[f"{key}-targets"] = s["pallets"]
        out[f"{key}-detected"] = s["detected"]
        out[f"{key}-ok"] = "".join("1" if target_met(r) else "0" for r in s.get("rows", ()))
    out["blocked_safe"] = sum(res[d]["pick_safe_table"]["blocked->safe"] for d in ("clean", "d435"))
    out["seed"] = seed
    return out


def measure_real(bundle: Path, precision: str, options: dict, frames: int, real_root: Path) -> dict:
    from real_data import AP_SCORE_THRESHOLD, evaluate
    from pallet6d.runtime.estimator import EstimatorOptions

    labels = real_root / "labels.json"
    if not labels.is_file():
        return {"missing": f"{labels} not found: import the licensed photographs (docs/data.md)"}
    records = [r for r in json.loads(labels.read_text()) if r["split"] == "heldout" and not r["augmented"]]
    if frames:
        records = records[:frames]
    threshold = options.get("score_threshold", EstimatorOptions().score_threshold)
    est = _estimator(bundle, precision, options, max_pallets=300,
                     score_threshold=min(threshold, AP_SCORE_THRESHOLD))
    r = evaluate(est, records, real_root, score_threshold=threshold).to_dict()
    return {"recall": _pct(r["overall"]["recall"] or 0.0), "precision": _pct(r["overall"]["precision"] or 0.0),
            "ap": round(r["overall"]["average_precision"] or 0.0, 3),
            "images": r["overall"]["images"], "negative_fp": round(r["false_positives_per_negative_frame"] or 0.0, 2)}


def run_measure(name: str, bundle: Path, precision: str, options: dict, quick: bool, data_root: Path,
                data: Path, split: str = "test") -> dict:
    """One measure of one bundle with `options` (`estimator_options`) on `split`'s frames (`SPLITS`; the test sets
    under `data_root`, the validation sets under `data`): its figures, plus the frames it used and its seconds."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; known: {', '.join(SPLITS)}")
    t0 = time.perf_counter()
    root = data_root if split == "test" else data
    if name == "presets":
        frames = 30 if quick else 100
        res = measure_presets(bundle, precision, options, frames, root, split)
    elif name == "forklift":
        frames = 20 if quick else 100
        res = measure_forklift(bundle, precision, options, frames, root, split)
    elif name == "mismatched":
        frames = 10 if quick else 30
        res = measure_mismatched(bundle, precision, options, frames, data)
    elif name == "mismatched-heldout":
        from pallet6d.export.accuracy_report import TEST_SEEDS

        frames = 10 if quick else 30
        res = measure_mismatched(bundle, precision, options, frames, data_root,
                                 {p: TEST_SEEDS[p] for p in PAPER_PRESETS})
    elif name in NEGATIVE_SEEDS:
        frames = 8 if quick else 40
        res = measure_negatives(bundle, precision, options, frames, data / "pallet-free", NEGATIVE_SEEDS[name])
    elif name in ("pockets", "pockets-all"):
        folder, seed, frames, models = TARGET_SETS[name, split]
        frames = frames // 4 if quick else frames
        res = measure_pockets(bundle, precision, options, frames, data / folder, seed, models)
    elif name == "real":
        frames = 100 if quick else 0
        res = measure_real(bundle, precision, options, frames, data / "real")
    else:
        raise ValueError(f"unknown measure {name!r}; known: {', '.join(MEASURES)}")
    return {**res, "frames": frames, "quick": quick, "split": split, "graphs": precision,
            "options": options_json(options), "seconds": round(time.perf_counter() - t0, 1)}


def options_json(options: dict) -> dict:
    """`options` as JSON (the nested options' fields that differ from their defaults)."""
    from dataclasses import asdict

    out = dict(options)
    for name, (cls, _) in _nested_options().items():
        if isinstance(out.get(name), cls):
            default = asdict(cls())
            out[name] = {k: v for k, v in asdict(out[name]).items() if v != default[k]}
    return out


def lookup(results: dict, key: str):
    """`results[measure][figure]` for a row key "measure.figure", or None."""
    measure, figure = key.split(".", 1)
    value = results.get(measure, {}).get(figure)
    return value if isinstance(value, (int, float)) else None


def table(names: list[str], results: list[dict]) -> str:
    """The markdown table: one row per figure that any bundle has, one column per bundle, then the target."""
    lines = ["| | " + " | ".join(f"`{n}`" for n in names) + " | target |",
             "|---|" + "---|" * len(names) + "---|"]
    for key, what, target in ROWS:
        values = [lookup(r, key) for r in results]
        if all(v is None for v in values):
            continue
        cells = ["-" if v is None else (f"{v:g}" if isinstance(v, float) else str(v)) for v in values]
        lines.append(f"| {what} | " + " | ".join(cells) + f" | {target} |")
    notes = sorted({f"`{n}`: {r[m]['missing']}" for n, r in zip(names, results) for m in r
                    if isinstance(r[m], dict) and "missing" in r[m]})
    return "\n".join(lines + ([""] + [f"- {x}" for x in notes] if notes else [])) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, action="append", required=True, help="a bundle folder (repeat to compare)")
    ap.add_argument("--precision", choices=("int8", "fp32"), default="int8")
    ap.add_argument("--measures", default=",".join(MEASURES), help=f"comma-separated, of {', '.join(MEASURES)}")
    ap.add_argument("--quick", action="store_true", help="a fraction of the frames: to try the command only")
    ap.add_argument("--split", choices=SPLITS, default="test",
                    help="val: the presets, forklift and pockets measures on validation frames (to choose on)")
    ap.add_argument("--data-root", type=Path, default=Path("benchmarks/data"),
                    help="the held-out test sets (as benchmarks/accuracy.py)")
    ap.add_argument("--data", type=Path, default=Path("data"),
                    help="validation frames, forklift frames and the imported real photographs")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=JSON",
                    help="also measure each bundle with these EstimatorOptions overrides, e.g. "
                         "'grid24={\"structure\": {\"grid\": 24}}' (repeatable)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    variants, shown = [("", {})], []
    for v in args.variant:
        label, sep, text = v.partition("=")
        if not sep or not label.replace("-", "").replace("_", "").isalnum():
            ap.error(f"--variant {v!r}: give a label (letters, digits, - and _), '=' and the options as JSON")
        try:
            variants.append((label, estimator_options(json.loads(text))))
            shown.append(f"- `+{label}`: `{text}`")
        except (ValueError, TypeError) as exc:      # json.JSONDecodeError is a ValueError
            ap.error(f"--variant {label}: {exc}")
    if len({label for label, _ in variants}) != len(variants):
        ap.error("--variant labels must differ")
    measures = [m for m in args.measures.split(",") if m]
    unknown = sorted(set(measures) - set(MEASURES))
    if unknown:
        ap.error(f"unknown measures {unknown}; known: {', '.join(MEASURES)}")
    for b in args.bundle:
        if not (b / "manifest.json").is_file():
            ap.error(f"{b} is not a bundle folder (no manifest.json)")
    names = [b.resolve().name for b in args.bundle]
    if len(set(names)) != len(names):
        ap.error(f"bundle folders must have different names, got {names}")
    columns, results = [], []
    for bundle, name in zip(args.bundle, names):
        for label, options in variants:
            column = f"{name}+{label}" if label else name
            folder = args.out / column
            folder.mkdir(parents=True, exist_ok=True)
            res = {}
            for m in measures:
                val = "-val" if args.split == "val" and m in SPLIT_MEASURES else ""
                path = folder / f"{m}{'-quick' if args.quick else ''}{val}-{args.precision}.json"
                if not path.is_file() or _stale(m, args.split, path):
                    print(f"scorecard: {column}: {m}", file=sys.stderr, flush=True)
                    path.write_text(json.dumps(run_measure(m, bundle, args.precision, options, args.quick,
                                                           args.data_root, args.data, args.split), indent=1) + "\n")
                res[m] = json.loads(path.read_text())
            columns.append(column)
            results.append(res)
    from latency import cpu_model

    created = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    command = shlex.join(["python", "benchmarks/scorecard.py", *(argv if argv is not None else sys.argv[1:])])
    text = (f"# Scorecard\n\n`{command}` on {created}, {os.cpu_count()} CPUs ({cpu_model()}); {args.precision}"
            f"{', validation frames' if args.split == 'val' else ''}"
            f"{', quick (a fraction of the frames: not for a decision)' if args.quick else ''}.\n\n"
            + ("Variants (estimator options):\n\n" + "\n".join(shown) + "\n\n" if shown else "")
            + table(columns, results)
            + (f"\n{paired}" if (paired := paired_table(columns, results)) else ""))
    (args.out / "scorecard.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
