"""`pallet6d sim`: generate a synthetic warehouse RGB-D dataset in the BOP format."""
from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

from pallet6d.runtime.cli_paths import writable_folder
from pallet6d.sim.presets import PRESETS, get_preset
from pallet6d.sim.scene import SceneError
from pallet6d.sim.sensors import SENSORS

HELP = "generate synthetic warehouse RGB-D scenes (BOP format)"
log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="virtual-occluded", choices=sorted(PRESETS),
                        help="scene/sensor preset: the paper's datasets (virtual-clean, virtual-occluded, "
                             "indoor-noisy) or real warehouses (forklift-approach, mixed; docs/sim-scenes.md) "
                             "(default: virtual-occluded)")
    parser.add_argument("--frames", type=int, default=100, help="number of frames (default: 100)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; same seed, same dataset (default: 0)")
    parser.add_argument("--out", type=Path, required=True, help="dataset root directory")
    parser.add_argument("--split", default="train", help="split folder name (default: train)")
    parser.add_argument("--start", type=int, default=0,
                        help="index of the first frame, to extend a dataset or split work (default: 0)")
    parser.add_argument("--size", metavar="WxH", default=None,
                        help="override the preset's image size, keeping its horizontal field of view")
    parser.add_argument("--pallet-types", default=None,
                        help="comma-separated pallet types the scenes draw from, instead of the preset's (e.g. epal; "
                             "the catalogue: pallet6d.sim.pallets.PALLET_MODELS)")
    parser.add_argument("--sensor", default=None, choices=sorted(SENSORS),
                        help="every frame's depth from this sensor model instead of the preset's (ideal: exact depth); "
                             "the scenes and their ground truth stay the same, the camera noise is drawn again")
    parser.add_argument("--pallet-free", choices=("set-down", "hanging"), default=None,
                        help="the preset's scenes without their pallets, written with no ground truth (negatives for "
                             "training and measuring detectors): their loads set down where the pallets stood, or "
                             "left hanging")
    parser.add_argument("--preview", action="store_true",
                        help="also write PNGs with each pallet's GT 3D box and axes, and the depth")


def main(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from pallet6d.sim.dataset import write_dataset

    try:
        config = get_preset(args.preset)
        if args.size:
            try:
                w, h = (int(v) for v in args.size.lower().split("x"))
            except ValueError:
                print(f"pallet6d sim: --size must look like 640x480, got {args.size!r}", file=sys.stderr)
                return 2
            config = config.with_image_size(w, h)
        if args.pallet_types:
            from pallet6d.sim.pallets import PALLET_MODELS
            names = tuple(t.strip() for t in args.pallet_types.split(",") if t.strip())
            unknown = [t for t in names if t not in PALLET_MODELS]
            if not names or unknown:
                print(f"pallet6d sim: unknown pallet type(s) {unknown or args.pallet_types!r}; known: "
                      f"{', '.join(PALLET_MODELS)}", file=sys.stderr)
                return 2
            config = replace(config, pallet_models=names)
        if args.sensor:
            config = replace(config, sensor=args.sensor, sensor_model=None, sensor_mix=())
        if args.frames < 1 or args.start < 0 or args.seed < 0:
            print("pallet6d sim: --frames must be >= 1, --start and --seed >= 0", file=sys.stderr)
            return 2
        problem = writable_folder(args.out)
        if problem:
            print(f"pallet6d sim: {problem}", file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        with tqdm(total=args.frames, desc=f"sim {config.name}", unit="frame", file=sys.stderr) as bar:
            previews = write_dataset(config, args.frames, args.seed, args.out, args.split, args.preview,
                                     start=args.start, progress=bar.update, pallet_free=args.pallet_free)
        dt = time.perf_counter() - t0
    except (SceneError, ValueError) as exc:
        print(f"pallet6d sim: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.frames} frames ({args.frames / dt:.2f} frames/s) to {args.out / args.split}")
    if previews:
        print(f"previews: {previews[0].parent} ({len(previews)} images, e.g. {previews[0]})")
    return 0
