"""The rendered scene the estimator tests share (no dataset: the generator makes it)."""
from __future__ import annotations

import functools

import numpy as np

from pallet6d.sim.generate import generate_frame
from pallet6d.sim.presets import get_preset


@functools.lru_cache(maxsize=1)
def scene():
    """A virtual-clean frame (seed 0), rendered once per test process. Read-only: copy arrays before changing."""
    return generate_frame(get_preset("virtual-clean"), seed=0)


def visible_boxes(frame, n: int) -> np.ndarray:
    """(n, 4) the visible boxes of the frame's n most visible pallets, as a detector would give them."""
    out = []
    for p in sorted(frame.pallets, key=lambda p: -p.visib_fract)[:n]:
        x, y, w, h = p.bbox_visib_xywh
        out.append([x, y, x + w, y + h])
    return np.array(out, float)
