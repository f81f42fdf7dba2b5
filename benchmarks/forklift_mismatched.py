"""Accepted poses on calibrated forklift frames whose inputs do not belong together, with and without the levelled
search and climb.

    python benchmarks/forklift_mismatched.py --bundle models/epal-default --data data/val/forklift-approach

Every frame of a BOP dataset with `scene_forklift.json` goes to `PalletEstimator.estimate(..., T_vehicle_cam=...)` as
recorded and mismatched: the next frame's depth, the focal lengths doubled, the depth 10x too near, a flat wall at the
frame's median depth. The calibrated path is run three times: as it is without the levelled search and climb
(`LevelParams(search_yaw_step_deg=0, refine_iterations=5, climb_step_deg=0)`,
`StructureParams(min_agreement_levelled=0.6)`), without the climb (`LevelParams(climb_step_deg=0)`), and with the
defaults.
Any pose accepted on mismatched inputs is made up.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

CASES = ("as recorded", "another frame's depth", "focal length 2x", "depth 10x too near", "flat wall")


def mismatched(frames: list, i: int, case: str) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m float32, K) of frame i for one of `CASES`."""
    f = frames[i]
    depth, K = f.depth_m.astype(np.float32), np.array(f.K, dtype=np.float64)
    if case == "another frame's depth":
        depth = frames[(i + 1) % len(frames)].depth_m.astype(np.float32)
    elif case == "focal length 2x":
        K[0, 0] *= 2.0
        K[1, 1] *= 2.0
    elif case == "depth 10x too near":
        depth = depth * np.float32(0.1)
    elif case == "flat wall":
        valid = depth[depth > 0]
        depth = np.full_like(depth, float(np.median(valid)) if len(valid) else 3.0)
    return depth, K


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="BOP dataset root with scene_forklift.json")
    ap.add_argument("--split", help="split folder (default: the only one)")
    ap.add_argument("--fp32", action="store_true", help="fp32 graphs (default: int8)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.level import LevelParams
    from pallet6d.runtime.structure import StructureParams

    ds = BopDataset(args.data, args.split)
    frames = [ds[i] for i in range(len(ds))]
    if not frames or any(f.T_vehicle_cam is None for f in frames):
        raise SystemExit(f"{args.data}: every frame needs its calibration (scene_forklift.json)")
    settings = {"without the search": dict(level=LevelParams(search_yaw_step_deg=0, refine_iterations=5,
                                                             climb_step_deg=0),
                                           structure=StructureParams(min_agreement_levelled=0.6)),
                "without the climb": dict(level=LevelParams(climb_step_deg=0)),
                "defaults": {}}
    print(f"accepted poses on {len(frames)} calibrated frames of {args.data.name}")
    print("| inputs | " + " | ".join(settings) + " |\n|---|" + "---|" * len(settings))
    ests = [PalletEstimator.from_bundle(args.bundle, threads=args.threads, precision="fp32" if args.fp32 else "int8",
                                        **kw) for kw in settings.values()]
    for case in CASES:
        counts = []
        for est in ests:
            n = 0
            for i, f in enumerate(frames):
                depth, K = mismatched(frames, i, case)
                try:
                    n += len(est.estimate(f.rgb, depth, K, T_vehicle_cam=f.T_vehicle_cam).poses)
                except ValueError:          # inputs the estimator refuses outright: no pose
                    pass
            counts.append(n)
        print(f"| {case} | " + " | ".join(str(c) for c in counts) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
