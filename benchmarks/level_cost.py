"""What the levelled refinement costs on calibrated frames: with and without its yaw and position search and climb.

    python benchmarks/level_cost.py --bundle models/epal-default --data data/val/forklift-approach [--int8]

Runs `PalletEstimator.estimate(..., T_vehicle_cam=...)` on every frame of a BOP dataset with `scene_forklift.json`
(each frame's calibration) with the search and the climb off (`LevelParams(search_yaw_step_deg=0,
climb_step_deg=0)`), with the climb off (`LevelParams(climb_step_deg=0)`) and with the defaults, and prints the
refine stage's time per candidate (it holds the levelled refinement and the climb) and the frames' p50 total. Run it
on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def measure(est, frames) -> dict:
    """Refine milliseconds per candidate, refine and total p50 per frame, candidates."""
    refine, total, n = [], [], 0
    for f in frames:
        r = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
        refine.append(r.timings_ms.get("refine", 0.0))
        total.append(r.timings_ms["total"])
        n += len(r.poses) + len(r.rejected)
    return {"refine_ms_per_candidate": sum(refine) / max(n, 1), "refine_p50_ms": float(np.median(refine)),
            "total_p50_ms": float(np.median(total)), "candidates": n}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="BOP dataset root with scene_forklift.json")
    ap.add_argument("--split", help="split folder (default: the only one)")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--max-frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.level import LevelParams

    ds = BopDataset(args.data, args.split)
    frames = [ds[i] for i in range(min(len(ds), args.max_frames))]
    if not frames or any(f.T_vehicle_cam is None for f in frames):
        raise SystemExit(f"{args.data}: every frame needs its calibration (scene_forklift.json)")
    precision = "int8" if args.int8 else "fp32"
    for name, level in (("no search, no climb", LevelParams(search_yaw_step_deg=0, climb_step_deg=0)),
                        ("search, no climb", LevelParams(climb_step_deg=0)), ("defaults", LevelParams())):
        est = PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision=precision, level=level)
        est.estimate(frames[0].rgb, frames[0].depth_m, frames[0].K, T_vehicle_cam=frames[0].T_vehicle_cam)  # warm
        m = measure(est, frames)
        print(f"{name:19s} refine {m['refine_ms_per_candidate']:.2f} ms per candidate ({m['candidates']}), "
              f"refine p50 {m['refine_p50_ms']:.1f} ms, frame p50 {m['total_p50_ms']:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
