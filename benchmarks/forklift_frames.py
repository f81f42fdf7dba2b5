"""Render forklift-approach frames once and cache what the forklift benchmarks need (numpy .npz per frame).

    python benchmarks/forklift_frames.py --out data/forklift-frames --frames 100 --seed 7
    python benchmarks/forklift_frames.py --out data/forklift-frames-epal --frames 60 --seed 8 --models epal

Target 1-4 m ahead (`target_distance_m`), obstacles in pockets with probability `--obstacle-prob`, depth both
D435-like (`depth_m`) and exact (`depth_ideal_m`).
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from pallet6d.sim.generate import generate_frame
from pallet6d.sim.presets import get_preset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--obstacle-prob", type=float, default=0.4)
    ap.add_argument("--models", help="comma-separated pallet types (default: the preset's, all types)")
    args = ap.parse_args()
    cfg = replace(get_preset("forklift-approach"), target_distance_m=(1.0, 4.0),
                  pocket_obstacle_prob=args.obstacle_prob)
    if args.models:
        cfg = replace(cfg, pallet_models=tuple(args.models.split(",")))
    args.out.mkdir(parents=True, exist_ok=True)
    for i in range(args.start, args.start + args.frames):
        path = args.out / f"{i:05d}.npz"
        if path.exists():
            continue
        f = generate_frame(cfg, args.seed, i)
        by_id = {p.instance_id: p for p in f.pallets}
        faces = [{"instance_id": int(fc.instance_id), "model": by_id[fc.instance_id].model_name,
                  "target": fc.instance_id == f.target_instance,
                  "T_cam_pallet": by_id[fc.instance_id].T_cam_pallet.tolist(),
                  "visib_fract": float(by_id[fc.instance_id].visib_fract),
                  "box_xywh": by_id[fc.instance_id].bbox_visib_xywh.tolist(), **fc.to_json()}
                 for fc in f.faces]
        np.savez_compressed(path, rgb=f.rgb, depth_m=f.depth_m.astype(np.float32),
                            depth_ideal_m=f.depth_ideal_m.astype(np.float32), K=f.K,
                            T_vehicle_cam=f.T_vehicle_cam, faces=json.dumps(faces),
                            fork_length_m=float(f.vehicle.fork_length_m))
        print(i, len(faces), flush=True)


if __name__ == "__main__":
    main()
