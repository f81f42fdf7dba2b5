"""Forklift outputs against the simulator's ground truth: pocket centres and face yaw, and the `pick_safe`
confusion table, per pallet type, on cached forklift-approach frames (`benchmarks/forklift_frames.py`, exact and
D435-like depth) or on a generated BOP dataset with `scene_forklift.json` (its one depth).

    python benchmarks/forklift_pockets.py --frames data/forklift-frames \
        --out benchmarks/results/forklift/pockets.json
    python benchmarks/forklift_pockets.py --bop data/gen/test-forklift-approach --max-frames 20
    python benchmarks/forklift_pockets.py --frames data/forklift-frames-epal --estimator models/epal-default \
        [--int8] [--gt-boxes] --out benchmarks/results/forklift/pockets-e2e.json

Each pallet is scored with its own type: without `--estimator` the ground-truth pose with the geometry and
pockets of the ground truth's type (the BOP obj_id, or the cached name, in the `pallet6d.sim.pallets`
catalogue), which tests the geometry and the pocket check. With it, the estimator's pose (the detection whose
box overlaps the pallet's most) with the geometry of the type the estimator reports (the bundle's `PalletType`,
as the daemon does); a pallet whose type the bundle lacks (with `--gt-boxes` the ground truth's, else the
reported one) is counted apart (`type_unknown`), and `type_ok` says whether the reported type is the ground
truth's. A pose whose centre lies nearer another ground-truth pallet than the one its box overlaps (one up a
stack) is that pallet's: counted apart (`other_pallet`), not scored as the pallet's own. A pallet without a pose
counts under `missed` by why: the reason of the rejected detection over it, or `no_box`. `--gt-boxes` poses the
ground truth's visible boxes with the detector class of the ground truth's type instead of the detector's boxes
(the pose stage alone). `--pallet-types` poses only the types named, as a site that names its types does
(`EstimatorOptions.pallet_types`).
Pallets are the targets (the pallet the forklift approaches); `--all` adds every other pallet with its face in
view.
"""
from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import Iterator

import numpy as np

from pallet6d.runtime.forklift import ForkliftParams, forklift_info, pallet_types_by_name
from pallet6d.sim.pallets import PALLET_MODELS, get_pallet_model


def _iou(a, b) -> float:
    x1, y1 = max(a[0], b[0]), max(a[1], b[1])
    x2, y2 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x2 - x1) * max(0.0, y2 - y1)
    return inter / max((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter, 1e-9)


def catalogue_name(obj_id: int, models_info: dict[int, dict] | None = None) -> str:
    """The `sim.pallets` type of a BOP obj_id; a dataset's models_info naming another type is an error."""
    by_id = {get_pallet_model(n).obj_id: n for n in PALLET_MODELS}
    if int(obj_id) not in by_id:
        raise ValueError(f"obj_id {obj_id} is not a pallet type of the sim catalogue ({sorted(by_id)})")
    name = by_id[int(obj_id)]
    named = (models_info or {}).get(int(obj_id), {}).get("name", name)
    if named != name:
        raise ValueError(f"models_info names obj_id {obj_id} {named!r}, the catalogue {name!r}")
    return name


def npz_frames(frames_dir: Path) -> Iterator[dict]:
    """Cached frames: rgb, K, T_vehicle_cam, depths {"clean", "d435"}, fork_length_m, faces (with "model",
    "T_cam_pallet", "box_xywh", "target" and the simulator's face and pockets)."""
    for path in sorted(frames_dir.glob("*.npz")):
        z = np.load(path)
        yield {"frame": path.stem, "rgb": z["rgb"], "K": z["K"], "T_vehicle_cam": z["T_vehicle_cam"],
               "depths": {"clean": z["depth_ideal_m"], "d435": z["depth_m"]},
               "fork_length_m": float(z["fork_length_m"]), "faces": json.loads(str(z["faces"]))}


def bop_frames(root: Path, split: str | None = None, max_frames: int | None = None) -> Iterator[dict]:
    """The frames of a generated BOP dataset as `npz_frames` gives them (one depth, "bop"): each pallet of
    `scene_forklift.json` with its type from its ground truth's obj_id."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.sim.dataset import read_forklift_gt

    ds = BopDataset(root, split)
    forklift: dict[int, dict] = {}
    for i in range(len(ds) if max_frames is None else min(len(ds), max_frames)):
        f = ds[i]
        if f.scene_id not in forklift:
            forklift[f.scene_id] = read_forklift_gt(ds.root / ds.split / f"{f.scene_id:06d}")
        entry = forklift[f.scene_id].get(f.im_id)
        if entry is None or entry.get("cam_R_c2v") is None:
            raise ValueError(f"{root}: scene {f.scene_id} image {f.im_id} has no forklift ground truth "
                             "(scene_forklift.json): not a forklift view")
        T_vc = np.eye(4)
        T_vc[:3, :3] = np.asarray(entry["cam_R_c2v"], dtype=np.float64).reshape(3, 3)
        T_vc[:3, 3] = np.asarray(entry["cam_t_c2v"], dtype=np.float64) / 1000
        faces = []
        for p in entry["pallets"]:
            gt = f.gts[p["gt_index"]]
            if gt.obj_id != p["obj_id"]:
                raise ValueError(f"{root}: scene {f.scene_id} image {f.im_id}: scene_forklift.json's obj_id "
                                 f"{p['obj_id']} differs from scene_gt.json's {gt.obj_id}")
            box = gt.bbox_visib_xywh if gt.bbox_visib_xywh is not None else gt.bbox_obj_xywh
            faces.append({**p, "model": catalogue_name(gt.obj_id, ds.models_info),
                          "T_cam_pallet": gt.T_cam_model.tolist(), "box_xywh": [int(v) for v in box]})
        yield {"frame": f"{f.scene_id:06d}/{f.im_id:06d}", "rgb": f.rgb, "K": f.K, "T_vehicle_cam": T_vc,
               "depths": {"bop": f.depth_m}, "fork_length_m": entry["forks"]["length_mm"] / 1000, "faces": faces}


def evaluate(frames, params: ForkliftParams, estimator=None, all_pallets=False, gt_boxes=False) -> dict:
    """Rows per pallet and depth, and their summary per depth (all types, and per type)."""
    types = pallet_types_by_name(estimator.bundle) if estimator is not None else {}
    rows: dict[str, list[dict]] = {}
    for fr in frames:
        for depth_name, depth in fr["depths"].items():
            rows.setdefault(depth_name, []).extend(_frame_rows(fr, depth, types, params, estimator, all_pallets,
                                                               gt_boxes))
    return {name: summarize(r) | {"per_type": {m: summarize([x for x in r if x["model"] == m])
                                               for m in sorted({x["model"] for x in r})}, "rows": r}
            for name, r in rows.items()}


def nearest_pallet(faces: list[dict], T_cam_pallet: np.ndarray) -> dict:
    """The ground-truth pallet (an entry of a frame's `faces`) whose centre lies nearest a posed pallet's centre."""
    t = np.asarray(T_cam_pallet, dtype=np.float64)[:3, 3]
    return min(faces, key=lambda fc: float(np.linalg.norm(np.asarray(fc["T_cam_pallet"])[:3, 3] - t)))


def _frame_rows(fr: dict, depth: np.ndarray, types: dict, params: ForkliftParams, estimator, all_pallets: bool,
                gt_boxes: bool) -> list[dict]:
    faces = [fc for fc in fr["faces"] if (fc["target"] or all_pallets) and fc["face_centre_vehicle_mm"] is not None]
    result = None
    if estimator is not None and gt_boxes:        # the pose stage on the ground truth's visible boxes and types
        known = [fc for fc in faces if fc["model"] in types]
        boxes = np.asarray([[x, y, x + w, y + h] for x, y, w, h in (fc["box_xywh"] for fc in known)], float)
        result = estimator.estimate_boxes(fr["rgb"], depth, fr["K"], boxes_xyxy=boxes.reshape(-1, 4),
                                          class_ids=[types[fc["model"]].class_id for fc in known],
                                          T_vehicle_cam=fr["T_vehicle_cam"])
    elif estimator is not None:
        result = estimator.estimate(fr["rgb"], depth, fr["K"], T_vehicle_cam=fr["T_vehicle_cam"])
    rows = []
    for fc in faces:
        row = {"frame": fr["frame"], "model": fc["model"], "target": fc["target"],
               "distance_m": fc["face_centre_vehicle_mm"][0] / 1000,
               "gt_yaw_deg": fc["face_yaw_deg"], "gt_blocked": any(p["blocked"] for p in fc["pockets"]),
               "visib": [p["visib_fract"] for p in fc["pockets"]], "fork_length_m": fr["fork_length_m"]}
        geometry = get_pallet_model(fc["model"])
        T_cp = np.asarray(fc["T_cam_pallet"])
        if estimator is not None and gt_boxes and fc["model"] not in types:     # not posed: no such class
            rows.append({**row, "type_unknown": True})
            continue
        if estimator is not None:
            x, y, w, h = fc["box_xywh"]
            best = max(result.poses, key=lambda p: _iou(p.box_xyxy, (x, y, x + w, y + h)), default=None)
            if best is None or _iou(best.box_xyxy, (x, y, x + w, y + h)) < 0.3:
                rows.append({**row, "detected": False, "missed": miss_reason(result, (x, y, x + w, y + h))})
                continue
            if nearest_pallet(fr["faces"], best.T_cam_pallet) is not fc:
                # the pose is another pallet's (one up a stack, a neighbour whose box overlaps the target's): its
                # pockets are that pallet's, so they say nothing of the target's
                rows.append({**row, "detected": False, "other_pallet": True})
                continue
            name = best.pallet_type or best.class_name
            geometry = types.get(name)
            row.update(detected=True, type=name, type_ok=name == fc["model"])
            if geometry is None:
                rows.append({**row, "type_unknown": True})
                continue
            T_cp = best.T_cam_pallet
        info = forklift_info(T_cp, fr["T_vehicle_cam"], geometry.size_m, geometry.pockets_m, geometry.boxes_m,
                             depth, fr["K"], params, None if estimator is None else best.box_xyxy)
        if info is None:
            rows.append({**row, "no_pockets": True})
            continue
        gt_c = np.array([p["centre_vehicle_mm"] for p in fc["pockets"]]) / 1000
        est_c = np.array([p.centre_vehicle_m for p in info.pockets])
        # a symmetric pallet seen from its other side has the same pockets in the other order
        err = min(np.linalg.norm(est_c - gt_c, axis=1).max(), np.linalg.norm(est_c[::-1] - gt_c, axis=1).max())
        dyaw = (info.face_yaw_deg - fc["face_yaw_deg"] + 180) % 360 - 180
        rows.append({**row, "face_ok": bool(info.face == fc["face"] or err < 0.05), "pocket_err_m": float(err),
                     "yaw_err_deg": float(abs(dyaw)), "pick_safe": bool(info.pick_safe), "reason": info.reason,
                     "states": [p.state for p in info.pockets]})
    return rows


def miss_reason(result, box_xyxy) -> str:
    """Why a target has no pose: the reason of the rejected detection whose box overlaps its box most (IoU at least
    0.3, as for poses), else "no_box" (the detector, and the depth's proposals, found nothing there)."""
    nearest = max(result.rejected, key=lambda r: _iou(r.box_xyxy, box_xyxy), default=None)
    return nearest.reason if nearest is not None and _iou(nearest.box_xyxy, box_xyxy) >= 0.3 else "no_box"


def target_met(row: dict) -> bool:
    """A target posed with both pockets within 2 cm and the face's yaw within 1 degree (the forks' figure)."""
    return "pocket_err_m" in row and row["pocket_err_m"] <= 0.02 and row["yaw_err_deg"] <= 1.0


def summarize(rows: list[dict]) -> dict:
    posed = [r for r in rows if "pocket_err_m" in r]
    ok = [r for r in posed if target_met(r)]
    table = {f"{'blocked' if b else 'clear'}->{'safe' if s else 'unsafe'}":
             sum(1 for r in posed if r["gt_blocked"] == b and r["pick_safe"] == s) for b in (True, False)
             for s in (True, False)}
    reasons: dict[str, int] = {}
    for r in posed:
        if not r["gt_blocked"] and not r["pick_safe"]:
            reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    err = np.array([r["pocket_err_m"] for r in posed]) if posed else np.zeros(0)
    yaw = np.array([r["yaw_err_deg"] for r in posed]) if posed else np.zeros(0)
    typed = [r for r in rows if "type_ok" in r]
    return {"pallets": len(rows), "detected": len(typed), "posed": len(posed),
            "type_unknown": sum(1 for r in rows if r.get("type_unknown")),
            "no_pockets": sum(1 for r in rows if r.get("no_pockets")),
            "other_pallet": sum(1 for r in rows if r.get("other_pallet")),
            "missed": dict(sorted(Counter(r["missed"] for r in rows if "missed" in r).items())),
            "type_ok": sum(r["type_ok"] for r in typed) / len(typed) if typed else None,
            "within_2cm_1deg": len(ok) / max(len(rows), 1),
            "pocket_err_m_median": float(np.median(err)) if err.size else None,
            "pocket_err_m_p95": float(np.percentile(err, 95)) if err.size else None,
            "yaw_err_deg_median": float(np.median(yaw)) if yaw.size else None,
            "yaw_err_deg_p95": float(np.percentile(yaw, 95)) if yaw.size else None,
            "pick_safe_table": table, "clear_but_unsafe_reasons": reasons}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", type=Path, help="cached frames (benchmarks/forklift_frames.py)")
    src.add_argument("--bop", type=Path, help="a generated BOP dataset with scene_forklift.json")
    ap.add_argument("--split", help="with --bop: the split (default: the only one)")
    ap.add_argument("--max-frames", type=int, help="with --bop: the first N frames only")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--estimator", help="a bundle: use its poses instead of the ground truth")
    ap.add_argument("--all", action="store_true", help="every pallet with its face in view, not only targets")
    ap.add_argument("--gt-boxes", action="store_true",
                    help="with --estimator: pose the ground truth's visible boxes (no detector)")
    ap.add_argument("--score-threshold", type=float, default=0.25, help="with --estimator: the detector's")
    ap.add_argument("--int8", action="store_true", help="with --estimator: the bundle's int8 graphs")
    ap.add_argument("--threads", type=int, default=2, help="with --estimator: onnxruntime threads")
    ap.add_argument("--pallet-types", help="with --estimator: comma-separated, the only types posed (default: all)")
    args = ap.parse_args()
    if (args.int8 or args.gt_boxes or args.pallet_types) and not args.estimator:
        ap.error("--int8, --gt-boxes and --pallet-types need --estimator")
    est = None
    if args.estimator:
        from pallet6d.runtime.estimator import PalletEstimator
        types = {} if not args.pallet_types else {"pallet_types": tuple(args.pallet_types.split(","))}
        est = PalletEstimator.from_bundle(args.estimator, score_threshold=args.score_threshold, threads=args.threads,
                                          precision="int8" if args.int8 else "fp32", **types)
    frames = npz_frames(args.frames) if args.frames else bop_frames(args.bop, args.split, args.max_frames)
    out = evaluate(frames, ForkliftParams(), est, args.all, args.gt_boxes)
    for name, res in out.items():
        print(name, json.dumps({k: v for k, v in res.items() if k not in ("rows", "per_type")}))
        for model, s in res["per_type"].items():
            print(f"  {model:22s} {json.dumps({k: v for k, v in s.items() if k not in ('rows', 'per_type')})}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
