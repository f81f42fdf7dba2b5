"""A bundle's detector on the held-out real photographs: recall and precision at IoU 0.5, false positives on
pallet-free photos.

    python benchmarks/real_data.py --bundle models/epal-default [--int8] --data data/real \
        --out benchmarks/results/real-data/epal-default

The data is what `python -m pallet6d.export.real_data import` writes (`labels.json`, one record per image).
A detection (score >= --score-threshold, any pallet class: the benchmark is class-agnostic) is a true positive
when it is matched to a labelled box at IoU >= 0.5, greedily by descending score, each box matched at most once.
Recall and precision are reported overall (sources labelled with the detector's whole-pallet convention), by box
size (box height as a fraction of the image height, the real-data importer's bins: recall by the labelled box's
size, precision by the detection's own size) and by pallet kind; sources whose boxes cover a loaded unit are
reported on their own, since their boxes are not the convention the detector is trained for. Pallet-free
photos (no depth) give detector false positives per frame. The detector runs at a score threshold of at most
0.02 (`AP_SCORE_THRESHOLD`): recall and precision count the detections at --score-threshold, the average precision
(AP) every one, so that detectors whose scores are shifted are compared over all thresholds. Only runtime code runs
the bundle (onnxruntime).
The uploaders' augmented copies (rotated by up to 15 degrees, boxes of the rotated rectangles) are left out
unless --include-augmented.

With --sim-negatives N, N simulated pallet-free RGB-D frames per preset (the preset's scenes with every pallet's
boards and blocks removed, `sim.pallet_free`; loads stay, hanging where their pallets were, a hard negative, or with
--sim-loads set-down stand where their pallets stood, as a warehouse shows them) go through the whole estimator at
its default options (or `--sim-score-threshold`): accepted poses per frame there are false accepts.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pallet6d.export.real_data_report import RealDataReport, markdown   # numpy only: no torch

AP_SCORE_THRESHOLD = 0.02   # the detector's threshold here: the average precision counts the detections down to it


def pallet_free_frame(preset: str, seed: int, index: int, set_down: bool, cache: Path | None = None):
    """`sim.pallet_free.render_pallet_free`, kept in `cache` (one .npz a frame) when given, so that a second bundle
    is measured on the same frames without rendering them again.
    :return: (rgb, depth_m, K, T_vehicle_cam or None)."""
    from pallet6d.sim.pallet_free import render_pallet_free

    path = None if cache is None else cache / ("set-down" if set_down else "hanging") / f"{preset}-{seed}-{index}.npz"
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return z["rgb"], z["depth_m"], z["K"], (z["T_vehicle_cam"] if "T_vehicle_cam" in z else None)
    rgb, depth_m, K, T_vc = render_pallet_free(preset, seed, index, set_down)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        extra = {} if T_vc is None else {"T_vehicle_cam": T_vc}
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, rgb=rgb, depth_m=depth_m.astype(np.float32), K=K, **extra)
        tmp.replace(path)
    return rgb, depth_m, K, T_vc


def sim_negatives(est, presets: list[str], n_frames: int, seed: int, calibrated: bool = False,
                  set_down: bool = False, cache: Path | None = None) -> dict:
    """Accepted poses and detections per frame on simulated pallet-free frames, per preset; `calibrated`: the
    forklift views' camera calibration goes to the estimator, as a forklift's would; `set_down`: the loads stand
    where their pallets stood; `cache`: a folder that keeps the rendered frames (`pallet_free_frame`). Each
    preset's `accepted_by_frame` lists the poses accepted on each frame, so that two bundles can be compared frame
    by frame."""
    out = {}
    for preset in presets:
        accepted_by_frame, detections, fits = [], 0, []
        for i in range(n_frames):
            rgb, depth_m, K, T_vc = pallet_free_frame(preset, seed, i, set_down, cache)
            res = est.estimate(rgb, depth_m.astype(np.float32), K, T_vehicle_cam=T_vc if calibrated else None)
            accepted_by_frame.append(len(res.poses))
            detections += len(est.detect(rgb))
            fits += [float(p.fit.score) for p in res.poses]
        out[preset] = {"frames": n_frames, "accepted_poses_per_frame": sum(accepted_by_frame) / n_frames,
                       "accepted_by_frame": accepted_by_frame, "detections_per_frame": detections / n_frames,
                       "fit_scores_of_false_accepts": [round(f, 3) for f in fits]}
    return out


def evaluate(est, records: list[dict], root: Path, iou_threshold: float = 0.5,
             progress: bool = False, detections: list | None = None,
             score_threshold: float = 0.0) -> RealDataReport:
    """Run `est.detect` (a `PalletEstimator`) on every record's image and tally the report (recall and precision of
    the detections scored >= `score_threshold`, AP of all); with `detections` (a list), also append each image's
    `Detections` scored >= `score_threshold` to it."""
    import cv2

    report = RealDataReport()
    for k, rec in enumerate(records):
        bgr = cv2.imread(str(root / rec["image"]), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"cannot read {root / rec['image']}")
        det = est.detect(np.ascontiguousarray(bgr[:, :, ::-1]))
        report.add_image(rec, det.boxes_xyxy, det.scores, iou_threshold, score_threshold)
        if detections is not None:
            detections.append(det.take(np.flatnonzero(det.scores >= score_threshold)))
        if progress and (k + 1) % 200 == 0:
            print(f"{k + 1}/{len(records)} images", file=sys.stderr)
    return report


def write_examples(records: list[dict], detections: list, root: Path, out_dir: Path, per_source: int = 2,
                   iou_threshold: float = 0.5) -> list[Path]:
    """Overlays of the photographs where the detector failed most (missed boxes plus false detections, from the
    `detections` that `evaluate` kept), the worst `per_source` of each source: labelled boxes green when found,
    yellow when missed; detections blue when right, red when wrong, with their scores. JPEGs at most 960 px wide."""
    import cv2

    from pallet6d.runtime.evaluation import match_greedy

    scored = []
    for rec, det in zip(records, detections):
        gt = np.asarray(rec["boxes_xyxy"], float).reshape(-1, 4)
        pred_match, gt_found = match_greedy(det.boxes_xyxy, det.scores, gt, iou_threshold)
        fails = int((~gt_found).sum() + (pred_match < 0).sum())
        if fails:
            scored.append((rec["source"], -fails, rec["image"], det, gt, pred_match, gt_found))
    out_dir.mkdir(parents=True, exist_ok=True)
    written, taken = [], {}
    for source, _, name, det, gt, pred_match, gt_found in sorted(scored, key=lambda t: t[:3]):
        if taken.get(source, 0) >= per_source:
            continue
        taken[source] = taken.get(source, 0) + 1
        img = cv2.imread(str(root / name), cv2.IMREAD_COLOR)
        for box, found in zip(gt.astype(int), gt_found):
            cv2.rectangle(img, tuple(box[:2]), tuple(box[2:]), (0, 200, 0) if found else (0, 220, 255), 2)
        for box, score, m in zip(det.boxes_xyxy.astype(int), det.scores, pred_match):
            colour = (255, 120, 0) if m >= 0 else (0, 0, 255)
            cv2.rectangle(img, tuple(box[:2]), tuple(box[2:]), colour, 1)
            cv2.putText(img, f"{score:.2f}", (int(box[0]), max(10, int(box[1]) - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        colour, 1)
        scale = min(1.0, 960 / img.shape[1])
        if scale < 1.0:
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        path = out_dir / f"{source}-{Path(name).stem}.jpg"
        cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=Path("data/real"), help="the imported real data")
    ap.add_argument("--split", default="heldout", help="split to measure (default: the held-out one)")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--score-threshold", type=float, default=0.25)
    ap.add_argument("--detector-mirror", action="store_true",
                    help="the detector also run on the mirrored image, the two views' scores averaged "
                         "(EstimatorOptions.detector_mirror)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-images", type=int, default=0, help="0: all")
    ap.add_argument("--source", help="only these sources of the data (comma-separated), e.g. a site's own photographs "
                                     "(python -m pallet6d.export.site_data)")
    ap.add_argument("--include-augmented", action="store_true",
                    help="also the uploaders' augmented (rotated) copies of held-out images")
    ap.add_argument("--sim-negatives", type=int, default=0,
                    help="also N simulated pallet-free RGB-D frames per preset through the whole estimator")
    ap.add_argument("--sim-presets", default="virtual-clean,virtual-occluded,indoor-noisy")
    ap.add_argument("--sim-seed", type=int, default=9100, help="seed of the simulated pallet-free frames")
    ap.add_argument("--sim-loads", choices=("hanging", "set-down"), default="hanging",
                    help="the pallet-free frames' loads: where they were (over pallet-shaped gaps) or set down")
    ap.add_argument("--sim-score-threshold", type=float, default=None,
                    help="the detector threshold of the estimator on the pallet-free frames (default: the estimator's)")
    ap.add_argument("--sim-calibrated", action="store_true",
                    help="give the estimator the forklift views' camera calibration (poses levelled on the floor)")
    ap.add_argument("--out", type=Path, help="write OUT.md and OUT.json")
    ap.add_argument("--examples", type=Path,
                    help="also write overlays of the photographs where the detector fails most, per source, here")
    args = ap.parse_args(argv)

    from pallet6d.runtime.estimator import PalletEstimator

    labels = args.data / "labels.json"
    if not labels.is_file():
        print(f"real_data.py: {labels} not found: import the licensed photographs first (docs/data.md, "
              f"python -m pallet6d.export.real_data import ... --out {args.data}) or name them with --data",
              file=sys.stderr)
        return 2
    records = [r for r in json.loads(labels.read_text())
               if r["split"] == args.split and (args.include_augmented or not r["augmented"])
               and (args.source is None or r["source"] in args.source.split(","))]
    if args.max_images:
        records = records[:args.max_images]
    if not records:
        print(f"no images in split {args.split!r} of {args.data}"
              + (f" from source(s) {args.source}" if args.source else ""), file=sys.stderr)
        return 2
    est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision="int8" if args.int8 else "fp32",
                                      score_threshold=min(args.score_threshold, AP_SCORE_THRESHOLD), max_pallets=300,
                                      detector_mirror=args.detector_mirror)
    detections = [] if args.examples else None
    report = evaluate(est, records, args.data, progress=True, detections=detections,
                      score_threshold=args.score_threshold).to_dict()
    if args.examples:
        for path in write_examples(records, detections, args.data, args.examples):
            print(f"wrote {path}", file=sys.stderr)
    if args.sim_negatives:
        threshold = {} if args.sim_score_threshold is None else {"score_threshold": args.sim_score_threshold}
        full = PalletEstimator.from_bundle(args.bundle, threads=args.threads,
                                           precision="int8" if args.int8 else "fp32",
                                           detector_mirror=args.detector_mirror, **threshold)
        report["sim_negatives"] = sim_negatives(full, args.sim_presets.split(","), args.sim_negatives,
                                                args.sim_seed, args.sim_calibrated, args.sim_loads == "set-down")
    settings = {"bundle": str(args.bundle), "precision": "int8" if args.int8 else "fp32", "split": args.split,
                "score_threshold": args.score_threshold, "detector_mirror": args.detector_mirror, "iou": 0.5,
                "data": str(args.data), "source": args.source,
                "augmented_copies": args.include_augmented, "sim_calibrated": args.sim_calibrated,
                "sim_loads": args.sim_loads, "sim_score_threshold": args.sim_score_threshold}
    text = markdown(f"Real photographs: {args.bundle.name}{' (int8)' if args.int8 else ''}", report, settings)
    for preset, r in report.get("sim_negatives", {}).items():
        text += (f"Simulated pallet-free {preset} (seed {args.sim_seed}, loads {args.sim_loads}): {r['frames']} "
                 f"frames, {r['accepted_poses_per_frame']:.2f} accepted poses per frame ("
                 + ("default options" if args.sim_score_threshold is None
                    else f"detector threshold {args.sim_score_threshold}") + "), "
                 f"{r['detections_per_frame']:.2f} detections per frame.\n")
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".md").write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps({"settings": settings, **report}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
