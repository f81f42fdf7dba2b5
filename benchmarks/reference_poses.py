"""Record every accepted and rejected pose of `PalletEstimator` on BOP datasets, or compare against a record.

A refactoring of the estimator must give the same poses. `record` runs the estimator (default options, the
given bundle, fp32 and int8) over every frame of the datasets and writes, per frame, each accepted pose and
each rejection (reason, box, score and the rejected pose when one was computed) to a JSON file (floats
written at full precision). `compare` runs the estimator again and reports the largest differences.

    python benchmarks/reference_poses.py record --bundle models/epal-default --data DIR [DIR ...] --out REF.json
    python benchmarks/reference_poses.py compare --bundle models/epal-default --ref REF.json [--tol-m 1e-9]

`compare` exits 1 when a frame's outcome differs (other count, order, reason) or a pose moved by more than
`--tol-m` (largest element of T_cam_pallet, translation in metres, rotation unitless).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _pose_record(p) -> dict:
    return {"T_cam_pallet": p.T_cam_pallet.tolist(), "confidence": p.confidence, "fit": p.fit.score,
            "class": p.class_name}


def frame_records(result) -> dict:
    """One frame's outcome as plain JSON: accepted poses and rejections, in the result's order."""
    return {"accepted": [{"box": p.box_xyxy.tolist(), "score": p.detector_score, **_pose_record(p)}
                         for p in result.poses],
            "rejected": [{"box": r.box_xyxy.tolist(), "score": r.detector_score, "reason": r.reason,
                          "pose": None if r.pose is None else _pose_record(r.pose)} for r in result.rejected]}


def run(bundle: str, data: list[Path], precision: str, threads: int) -> dict:
    """{dataset name: [frame records]} for one precision."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision)
    out = {}
    for root in data:
        ds = BopDataset(root)
        out[str(root)] = [frame_records(est.estimate(f.rgb, f.depth_m, f.K)) for f in (ds[i] for i in range(len(ds)))]
    return out


def compare_frames(ref: list[dict], new: list[dict], tol_m: float) -> tuple[float, list[str]]:
    """Largest pose difference over matching records, and the differences in outcome (empty: same outcome).

    :param ref, new: frame records (`frame_records`) of the same frames.
    """
    worst, problems = 0.0, []
    if len(ref) != len(new):
        return np.inf, [f"{len(ref)} frames recorded, {len(new)} now"]
    for i, (a, b) in enumerate(zip(ref, new)):
        for kind in ("accepted", "rejected"):
            if len(a[kind]) != len(b[kind]):
                problems.append(f"frame {i}: {len(a[kind])} {kind} recorded, {len(b[kind])} now")
                continue
            for j, (x, y) in enumerate(zip(a[kind], b[kind])):
                if x.get("reason") != y.get("reason") or x["box"] != y["box"]:
                    problems.append(f"frame {i} {kind} {j}: {x.get('reason')} {x['box']} recorded, "
                                    f"{y.get('reason')} {y['box']} now")
                    continue
                px, py = (x, y) if kind == "accepted" else (x["pose"], y["pose"])
                if (px is None) != (py is None):
                    problems.append(f"frame {i} {kind} {j}: pose present in one run only")
                    continue
                if px is None:
                    continue
                d = float(np.abs(np.asarray(px["T_cam_pallet"]) - np.asarray(py["T_cam_pallet"])).max())
                worst = max(worst, d)
                if d > tol_m:
                    problems.append(f"frame {i} {kind} {j}: pose differs by {d:.3g}")
    return worst, problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("--data", type=Path, nargs="+", required=True)
    rec.add_argument("--out", type=Path, required=True)
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("--ref", type=Path, required=True)
    cmp_.add_argument("--tol-m", type=float, default=1e-9)
    for p in (rec, cmp_):
        p.add_argument("--bundle", default="models/epal-default")
        p.add_argument("--precision", nargs="+", default=["fp32", "int8"])
        p.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if args.cmd == "record":
        doc = {"bundle": args.bundle, "data": [str(d) for d in args.data],
               "runs": {p: run(args.bundle, args.data, p, args.threads) for p in args.precision}}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc))
        n = sum(len(f["accepted"]) + len(f["rejected"]) for r in doc["runs"].values() for fs in r.values() for f in fs)
        print(f"recorded {n} detections to {args.out}")
        return 0
    doc = json.loads(args.ref.read_text())
    data = [Path(d) for d in doc["data"]]
    failed = False
    for precision in args.precision:
        now = run(args.bundle, data, precision, args.threads)
        for name, frames in doc["runs"][precision].items():
            worst, problems = compare_frames(frames, now[name], args.tol_m)
            n = sum(len(f["accepted"]) + len(f["rejected"]) for f in frames)
            print(f"{precision} {Path(name).name}: {n} detections, largest pose difference {worst:.3g}, "
                  f"{len(problems)} differences")
            for p in problems[:20]:
                print("  " + p)
            failed |= bool(problems)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
