"""`pallet6d eval`: accuracy of a model bundle on a BOP dataset (runtime only: no torch).

Runs `PalletEstimator` on every frame, matches estimates to ground truth and scores them with
`pallet6d.runtime.evaluation` (pallets >= 10 % visible count; a missed pallet is a failure), prints a
table and optionally writes a JSON summary (`summarize`'s keys: n_gt, precision, recall, add_acc,
add_sym_acc, adds_acc, AUCs, by_distance) with per-pallet records.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from .estimator_cli import add_estimator_arguments, load_estimator

HELP = "accuracy of a model bundle on a BOP dataset (precision, recall, ADD / symmetric ADD accuracy)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_estimator_arguments(parser)
    parser.add_argument("--data", required=True, type=Path, help="BOP dataset root (e.g. from `pallet6d sim`)")
    parser.add_argument("--split", help="split folder (default: the only one)")
    parser.add_argument("--json", type=Path, help="write the summary and per-pallet records here")
    parser.add_argument("--max-frames", type=int, default=0, help="evaluate at most N frames (0: all)")
    parser.add_argument("--gt-boxes", action="store_true",
                        help="skip the detector: feed the ground-truth visible boxes to the pose stage "
                             "(scores the pose stage alone)")
    parser.add_argument("--calibrated", action="store_true",
                        help="give the estimator each frame's camera calibration on its vehicle where the dataset "
                             "has one (scene_forklift.json: the generator's forklift views), as a forklift's "
                             "calibrated camera does: poses stand level on its floor")


def evaluate_dataset(estimator, data: str | Path, split: str | None = None, max_frames: int = 0,
                     progress: bool = False, gt_boxes: bool = False, calibrated: bool = False) -> dict:
    """Run `estimator` on a BOP dataset and score it.

    :param gt_boxes: give the pose stage the visible boxes of the counted pallets instead of detections.
    :param calibrated: pass each frame's `T_vehicle_cam` (where the dataset has one) to the estimator.

    :return: {"summary": summarize(...) + frames/seconds, "records": per-pallet dicts}.
    :raises ValueError: not a BOP dataset, or a frame the estimator rejects.
    """
    from .bop import BopDataset
    from .evaluation import (ScoreTally, counted_pallets, dataset_models, evaluate_poses, ground_truths_from_bop,
                             records_to_dicts)

    ds = BopDataset(data, split)
    models = dataset_models(ds, estimator.pallet_types)   # each ground truth scored with its own model
    n = len(ds) if not max_frames else min(len(ds), max_frames)
    tally = ScoreTally()
    n_no_box = n_calibrated = 0
    t0 = time.perf_counter()
    frames = range(n)
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc=f"eval {Path(data).name}", unit="frame", file=sys.stderr)
    for i in frames:
        f = ds[i]
        gts, skipped = ground_truths_from_bop(f.gts, f.rgb.shape[:2])
        n_no_box += skipped
        T_vc = f.T_vehicle_cam if calibrated else None
        n_calibrated += T_vc is not None
        if gt_boxes:
            boxes = np.array([g.box_visib_xyxy for g, c in zip(gts, counted_pallets(gts)) if c]).reshape(-1, 4)
            result = estimator.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
        else:
            result = estimator.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
        tally.add(evaluate_poses(i, result.poses, gts, estimator.model_points_m, estimator.symmetries, models=models,
                                 rejected=result.rejected))
    if n_no_box:
        log.warning("%s: %d annotations without a visible box (no scene_gt_info.json entry) were not scored",
                    data, n_no_box)
    if calibrated and n_calibrated < n:
        log.warning("%s: %d of %d frames have no vehicle calibration (scene_forklift.json): estimated without one",
                    data, n - n_calibrated, n)
    names = {int(k): info.get("name") for k, info in ds.models_info.items()}
    summary = {"frames": n, "detector": "ground-truth boxes" if gt_boxes else "bundle",
               "calibrated_frames": n_calibrated,
               "seconds": round(time.perf_counter() - t0, 2), **tally.summary(),
               "true_positives": tally.true_positives, "false_positives": tally.false_positives}
    for b in summary.get("by_object", []):
        b["name"] = names.get(b["obj_id"])
    return {"summary": summary, "records": records_to_dicts(tally.records)}


RESCORED_ERROR_KEYS = ("add_m", "add_sym_m", "adds_m", "rot_err_sym_deg", "trans_err_m")


def rescore(results: dict, data: str | Path, split: str | None = None, tol_m: float = 1e-6) -> dict:
    """The summary of `results` (an `evaluate_dataset` / `pallet6d eval --json` document with its records and
    true / false positives) under `data`'s annotations, without running a model again.

    Each pallet's error does not depend on which pallets count, so re-annotated frames whose visible fractions are
    never larger than before are re-scored exactly: a pallet that no longer counts is dropped and its detection
    becomes ignored, not a true positive. Pallets are matched to the annotations by frame and camera distance.
    :raises ValueError: a record has no pallet at its distance in that frame (not the same dataset).
    """
    import math

    from .bop import BopDataset
    from .evaluation import PalletRecord, counted_pallets, ground_truths_from_bop, summarize

    ds = BopDataset(data, split)
    gts_of: dict[int, tuple] = {}
    records, dropped_detected = [], 0
    for r in results["records"]:
        frame = int(r["frame"])
        if frame not in gts_of:
            f = ds[frame]
            gts = ground_truths_from_bop(f.gts, f.rgb.shape[:2])[0]
            gts_of[frame] = (gts, counted_pallets(gts))
        gts, counted = gts_of[frame]
        dist = np.array([np.linalg.norm(g.T_cam_model[:3, 3]) for g in gts])
        j = int(np.argmin(np.abs(dist - r["distance_m"]))) if len(dist) else -1
        if j < 0 or abs(dist[j] - r["distance_m"]) > tol_m:
            raise ValueError(f"frame {frame}: no pallet at {r['distance_m']:.6f} m in {data}; "
                             "the results were made on another dataset")
        if not counted[j]:
            dropped_detected += bool(r["detected"])
            continue
        g = gts[j]
        errors = {k: math.inf if r[k] is None else float(r[k]) for k in RESCORED_ERROR_KEYS}
        refused = r.get("refused_add_sym_m")
        records.append(PalletRecord(frame=frame, distance_m=float(r["distance_m"]), visib_fract=float(g.visib_fract),
                                    detected=bool(r["detected"]), truncated=bool(g.truncated), obj_id=g.obj_id,
                                    missed_reason=r.get("missed_reason"),
                                    refused_add_sym_m=math.inf if refused is None else float(refused), **errors))
    return summarize(records, results["true_positives"] - dropped_detected, results["false_positives"])


def format_table(summary: dict) -> str:
    """A human-readable table of a summary."""
    lines = [f"frames {summary['frames']}   pallets (>= 10% visible) {summary['n_gt']}   "
             f"detected {summary['n_detected']}",
             f"precision {summary['precision']:.3f}   recall {summary['recall']:.3f}",
             f"{'threshold':>10} {'ADD':>8} {'ADD-sym':>8} {'ADD-S':>8}"]
    for t in summary["add_acc"]:
        lines.append(f"{float(t) * 100:>8.0f}cm {summary['add_acc'][t]:>8.3f} {summary['add_sym_acc'][t]:>8.3f} "
                     f"{summary['adds_acc'][t]:>8.3f}")
    lines.append(f"{'AUC<10cm':>10} {summary['add_auc_10cm']:>8.3f} {summary['add_sym_auc_10cm']:>8.3f} "
                 f"{summary['adds_auc_10cm']:>8.3f}")
    for b in summary.get("by_distance", []):
        to = "inf" if b["to_m"] is None else f"{b['to_m']:g}"
        acc = ", ".join(f"@{float(k) * 100:.0f}cm {v:.2f}" for k, v in b["add_sym_acc"].items())
        lines.append(f"  {b['from_m']:g}-{to} m: n={b['n_gt']:<4} ADD-sym {acc}")
    def outcome(label: str, b: dict) -> str:
        return (f"  {label}: n={b['n_gt']:<4} ADD-sym <5cm {b['add_sym_lt_5cm']:.2f}, "
                f"5-10cm {b['add_sym_5_10cm']:.2f}, "
                f">=10cm {b['add_sym_ge_10cm']:.2f}, missed {b['missed']:.2f}")

    lines += [outcome(f"{b['from']:g}-{b['to']:g} visible", b) for b in summary.get("by_visibility", [])]
    lines += [outcome("cut by the image border" if b["truncated"] else "wholly in view", b)
              for b in summary.get("by_truncation", [])]
    lines += [outcome(b.get("name") or f"object {b['obj_id']}", b) for b in summary.get("by_object", [])]
    missed = summary.get("missed_by_reason") or {}
    if missed:
        lines.append("  missed, why: " + ", ".join(
            f"{k} {v['n_gt']}" + (f" ({v['refused_within_5cm']} posed within 5 cm)" if v["refused_within_5cm"] else "")
            for k, v in missed.items()))
    return "\n".join(lines)


def _json_problem(path: Path | None) -> str | None:
    """Why `--json` cannot be written (checked before the evaluation, not after it), or None."""
    if path is None:
        return None
    if path.is_dir():
        return f"--json {path} is a folder; give a file name"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"--json {path}: cannot create its folder: {exc.strerror or exc}"
    return None


def main(args: argparse.Namespace) -> int:
    if args.max_frames < 0:
        print(f"pallet6d eval: --max-frames must be >= 0 (0: all), got {args.max_frames}", file=sys.stderr)
        return 2
    problem = _json_problem(args.json)
    if problem:
        print(f"pallet6d eval: {problem}", file=sys.stderr)
        return 2
    est = load_estimator(args, "eval")
    if est is None:
        return 2
    try:
        out = evaluate_dataset(est, args.data, args.split, args.max_frames, progress=True, gt_boxes=args.gt_boxes,
                               calibrated=args.calibrated)
    except (ValueError, OSError) as exc:
        print(f"pallet6d eval: {args.data}: {exc}", file=sys.stderr)
        return 1
    print(format_table(out["summary"]))
    if args.json:
        doc = {"bundle": str(args.bundle), "data": str(args.data), "graphs": "int8" if args.int8 else "fp32",
               **out["summary"], "records": out["records"]}
        try:
            args.json.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        except OSError as exc:
            print(f"pallet6d eval: cannot write --json {args.json}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"wrote {args.json}")
    return 0
