"""A copy of a BOP dataset whose pallets wear a colour the detector never saw: a stress test of looks.

Real pallets come in looks the simulator does not draw (blue, black or grey plastic, painted or stained wood), and
a detector trained on the simulator's looks may not find them. This copies a dataset and repaints every pallet's
visible pixels (`mask_visib`) with one random hue per pallet, keeping the rendered shading (the pixel's brightness),
so the depth, the ground truth and the calibration stay exact while the look is new. Measures nothing itself: run
`pallet6d eval` on the copy.

    python benchmarks/recolour.py --data DIR --out DIR [--seed 0]
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np


def recolour(rgb: np.ndarray, masks: list[np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """`rgb` (H, W, 3) uint8 with each mask's pixels repainted in one random saturated hue, their brightness kept.

    :param masks: (H, W) bool, one per pallet."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    for m in masks:
        hsv[m, 0] = rng.integers(0, 180)               # OpenCV's hue: 0-179
        hsv[m, 1] = rng.integers(150, 256)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a BOP dataset folder (with mask_visib)")
    ap.add_argument("--out", required=True, help="the copy; must not exist")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    src, dst = Path(a.data), Path(a.out)
    if dst.exists():
        raise SystemExit(f"recolour: {dst} exists")
    shutil.copytree(src, dst)
    rng = np.random.default_rng(a.seed)
    n = 0
    for rgb_path in sorted(dst.glob("*/*/rgb/*.png")):
        scene = rgb_path.parent.parent
        masks = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0
                 for p in sorted((scene / "mask_visib").glob(f"{rgb_path.stem}_*.png"))]
        bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        rgb = recolour(bgr[..., ::-1], masks, rng)
        if not cv2.imwrite(str(rgb_path), np.ascontiguousarray(rgb[..., ::-1])):
            raise SystemExit(f"recolour: could not write {rgb_path}")
        n += 1
    print(f"recolour: {n} frames repainted into {dst}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
