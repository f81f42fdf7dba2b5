"""Tiny hand-made RGB-D frames for the camera tests (no dataset, no hardware)."""
from __future__ import annotations

import numpy as np

from pallet6d.runtime.cameras import RGBDFrame

K_SMALL = np.array([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])


def box_frame(i: int = 0, seed: int = 0, h: int = 60, w: int = 80) -> RGBDFrame:
    """A floor at 3 m with a 'pallet' box at 2 m whose position shifts with `i`; some holes."""
    rng = np.random.default_rng(seed + i)
    rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    depth_mm = np.full((h, w), 3000, dtype=np.uint16)
    x0 = 10 + (i % 5) * 4
    depth_mm[20:40, x0:x0 + 30] = 2000 + i
    rgb[20:40, x0:x0 + 30] = (200, 150, 60)
    depth_mm[rng.random((h, w)) < 0.05] = 0
    return RGBDFrame(rgb, depth_mm, K_SMALL, 0.001, timestamp_s=10.0 + i / 30, frame_number=100 + i,
                     source="test")
