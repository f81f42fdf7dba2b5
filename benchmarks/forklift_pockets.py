"""Forklift outputs on cached forklift-approach frames (`benchmarks/forklift_frames.py`): pocket centres and
face yaw against the simulator's ground truth, and the `pick_safe` confusion table, on exact and D435-like depth.

    python benchmarks/forklift_pockets.py --frames /work/data/forklift-frames \
        --out benchmarks/results/forklift/pockets.json
    python benchmarks/forklift_pockets.py --frames /work/data/forklift-frames-epal --estimator models/epal-default \
        [--gt-boxes] --out benchmarks/results/forklift/pockets-e2e.json

Without `--estimator` the ground-truth poses are used (this tests the geometry and the pocket check); with it
the estimator's poses (the detection whose box overlaps the target's most), reported for the pallet types the
bundle knows; `--gt-boxes` poses the ground truth's visible boxes instead of the detector's (the pose stage
alone). Pallets are the targets (the pallet the forklift approaches, 1-4 m ahead); `--all` adds every
other pallet with its face in view.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pallet6d.runtime.forklift import ForkliftParams, forklift_info
from pallet6d.sim.pallets import get_pallet_model


def _iou(a, b) -> float:
    x1, y1 = max(a[0], b[0]), max(a[1], b[1])
    x2, y2 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x2 - x1) * max(0.0, y2 - y1)
    return inter / max((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter, 1e-9)


def evaluate(frames_dir: Path, depth_key: str, params: ForkliftParams, estimator=None, all_pallets=False,
             gt_boxes=False) -> dict:
    rows = []
    for path in sorted(frames_dir.glob("*.npz")):
        z = np.load(path)
        faces = json.loads(str(z["faces"]))
        T_vc = z["T_vehicle_cam"]
        depth = z[depth_key]
        result = None
        if estimator is not None and gt_boxes:        # the pose stage on the ground truth's visible boxes
            boxes = [[x, y, x + w, y + h] for x, y, w, h in (fc["box_xywh"] for fc in faces
                                                               if fc["target"] or all_pallets)]
            result = estimator.estimate_boxes(z["rgb"], depth, z["K"], boxes_xyxy=np.asarray(boxes, float))
        elif estimator is not None:
            result = estimator.estimate(z["rgb"], depth, z["K"])
        for fc in faces:
            if not (fc["target"] or all_pallets) or fc["face_centre_vehicle_mm"] is None:
                continue
            model = get_pallet_model(fc["model"])
            T_cp = np.asarray(fc["T_cam_pallet"])
            row = {"frame": path.stem, "model": fc["model"], "target": fc["target"],
                   "distance_m": fc["face_centre_vehicle_mm"][0] / 1000,
                   "gt_yaw_deg": fc["face_yaw_deg"], "gt_blocked": any(p["blocked"] for p in fc["pockets"]),
                   "visib": [p["visib_fract"] for p in fc["pockets"]], "fork_length_m": float(z["fork_length_m"])}
            if estimator is not None:
                x, y, w, h = fc["box_xywh"]
                best = max(result.poses, key=lambda p: _iou(p.box_xyxy, (x, y, x + w, y + h)), default=None)
                if best is None or _iou(best.box_xyxy, (x, y, x + w, y + h)) < 0.3:
                    rows.append({**row, "detected": False})
                    continue
                T_cp = best.T_cam_pallet
                row["detected"] = True
            info = forklift_info(T_cp, T_vc, model.size_m, model.pockets_m, model.boxes_m, depth, z["K"], params)
            gt_c = np.array([p["centre_vehicle_mm"] for p in fc["pockets"]]) / 1000
            est_c = np.array([p.centre_vehicle_m for p in info.pockets])
            # a symmetric pallet seen from its other side has the same pockets in the other order
            err = min(np.linalg.norm(est_c - gt_c, axis=1).max(), np.linalg.norm(est_c[::-1] - gt_c, axis=1).max())
            dyaw = (info.face_yaw_deg - fc["face_yaw_deg"] + 180) % 360 - 180
            rows.append({**row, "face_ok": bool(info.face == fc["face"] or err < 0.05), "pocket_err_m": float(err),
                         "yaw_err_deg": float(abs(dyaw)), "pick_safe": bool(info.pick_safe), "reason": info.reason,
                         "states": [p.state for p in info.pockets]})
    return summarize(rows) | {"rows": rows}


def summarize(rows: list[dict]) -> dict:
    posed = [r for r in rows if "pocket_err_m" in r]
    ok = [r for r in posed if r["pocket_err_m"] <= 0.02 and r["yaw_err_deg"] <= 1.0]
    table = {f"{'blocked' if b else 'clear'}->{'safe' if s else 'unsafe'}":
             sum(1 for r in posed if r["gt_blocked"] == b and r["pick_safe"] == s) for b in (True, False)
             for s in (True, False)}
    reasons: dict[str, int] = {}
    for r in posed:
        if not r["gt_blocked"] and not r["pick_safe"]:
            reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    err = np.array([r["pocket_err_m"] for r in posed]) if posed else np.zeros(0)
    yaw = np.array([r["yaw_err_deg"] for r in posed]) if posed else np.zeros(0)
    return {"pallets": len(rows), "posed": len(posed),
            "within_2cm_1deg": len(ok) / max(len(rows), 1),
            "pocket_err_m_median": float(np.median(err)) if err.size else None,
            "pocket_err_m_p95": float(np.percentile(err, 95)) if err.size else None,
            "yaw_err_deg_median": float(np.median(yaw)) if yaw.size else None,
            "yaw_err_deg_p95": float(np.percentile(yaw, 95)) if yaw.size else None,
            "pick_safe_table": table, "clear_but_unsafe_reasons": reasons}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=Path, required=True)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--estimator", help="a bundle: use its poses instead of the ground truth")
    ap.add_argument("--all", action="store_true", help="every pallet with its face in view, not only targets")
    ap.add_argument("--gt-boxes", action="store_true",
                    help="with --estimator: pose the ground truth's visible boxes (no detector)")
    args = ap.parse_args()
    est = None
    if args.estimator:
        from pallet6d.runtime.estimator import PalletEstimator
        est = PalletEstimator.from_bundle(args.estimator)
    out = {}
    for key, name in (("depth_ideal_m", "clean"), ("depth_m", "d435")):
        res = evaluate(args.frames, key, ForkliftParams(), est, args.all, args.gt_boxes)
        out[name] = res
        print(name, json.dumps({k: v for k, v in res.items() if k != "rows"}))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
