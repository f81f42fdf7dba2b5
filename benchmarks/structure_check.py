"""Structure check on posed pallets: true poses kept, poses on mismatched inputs refused.

For each frame of BOP datasets, runs the estimator on the frame as recorded and on inputs that do not belong
together (a flat wall's depth under the image, another frame's depth, depth 10x too near, a focal length 2x too
long), and scores every pose the estimator would accept (today's fit check) with `runtime/structure.py`. Reports, per
dataset and variant: accepted poses, how many are within 5 cm (ADD-sym) of a ground-truth pallet, and how many of
each survive the structure check. Measures only; the thresholds live in `StructureParams`.

    python benchmarks/structure_check.py --bundle models/epal-default --data DIR [DIR ...] --frames 40 --out FILE.json
"""
from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.metrics import add_sym
from pallet6d.runtime.structure import StructureParams, structure_check

VARIANTS = ("as_recorded", "flat_wall", "other_frame", "depth_x0.1", "focal_x2")


def _variant(name: str, frame, other) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m, K) of a mismatched input built from `frame` (and `other`, another frame of the set)."""
    d, K = frame.depth_m, frame.K.copy()
    if name == "as_recorded":
        return d, K
    if name == "flat_wall":
        valid = d[d > 0]
        return np.full_like(d, float(np.median(valid)) if len(valid) else 3.0), K
    if name == "other_frame":
        od = other.depth_m
        return (od if od.shape == d.shape else np.resize(od, d.shape)), K
    if name == "depth_x0.1":
        return d * np.float32(0.1), K
    if name == "focal_x2":
        K[0, 0] *= 2.0
        K[1, 1] *= 2.0
        return d, K
    raise ValueError(name)


def run(bundle: str, data: list[str], frames: int, params: StructureParams, int8: bool) -> dict:
    est = PalletEstimator.from_bundle(bundle, threads=2, precision="int8" if int8 else "fp32")
    pts, sym, boxes_m = est.model_points_m, est.symmetries, np.asarray(est.model_boxes_m)
    out = {}
    for root in data:
        ds = BopDataset(root)
        n = min(frames, len(ds))
        for variant in VARIANTS:
            c = Counter()
            reasons = Counter()
            for i in range(n):
                f = ds[i]
                depth_m, K = _variant(variant, f, ds[(i + n // 2) % n] if variant == "other_frame" else None)
                res = est.estimate(f.rgb, depth_m, K)
                c["frames"] += 1
                if not res.poses:
                    continue
                T = np.stack([p.T_cam_pallet for p in res.poses])
                scores = structure_check(T, boxes_m, depth_m, K, np.stack([p.box_xyxy for p in res.poses]), params)
                for p, s in zip(res.poses, scores):
                    err = min((add_sym(p.T_cam_pallet[:3, :3], p.T_cam_pallet[:3, 3], g.T_cam_model[:3, :3],
                                       g.T_cam_model[:3, 3], pts, sym) for g in f.gts), default=np.inf)
                    good = variant == "as_recorded" and err < 0.05
                    c["accepted"] += 1
                    c["within_5cm"] += good
                    c["kept"] += s.ok
                    c["kept_within_5cm"] += s.ok and good
                    reasons[s.reason or "ok"] += 1
            out[f"{Path(root).name}/{variant}"] = {**c, "reasons": dict(reasons)}
            print(f"{Path(root).name:>24} {variant:>12}: {dict(c)} {dict(reasons)}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default="models/epal-default")
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    res = run(args.bundle, args.data, args.frames, StructureParams(), args.int8)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
