"""Whole-pallet boxes from loaded-unit boxes, found by the pallet's colour.

Some image sets box the loaded unit (pallet and load together); the detector's convention is the pallet alone. Where
the pallet has a colour the load lacks (red plastic under tan cartons), the pallet is the large regions of that
colour in the lower part of the unit's box, and its box is their extent. A pallet that cannot be found that way (no
such region, too thin, too narrow) is `None`: the image then keeps its loaded-unit boxes and is not trained on.
Checked by eye on the conveyor set's photographs: the rule finds every pallet of about three in ten of them; the
others hold a unit whose pallet is mostly hidden (by the conveyor's frame or another unit: too narrow) or runs into
red outside every unit's box.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ColourRule", "PALLET_COLOURS", "colour_mask", "pallet_boxes_in_units"]


@dataclass(frozen=True)
class ColourRule:
    """A pallet colour in OpenCV's HSV (H 0-179, S and V 0-255): hue in [hue_lo, 180) or [0, hue_hi]."""

    hue_lo: int
    hue_hi: int
    min_saturation: int
    min_value: int


# Red plastic: hue wraps around 0; tan cartons lie at H 8-22 with S under ~120, kept out by hue.
PALLET_COLOURS = {"red": ColourRule(hue_lo=160, hue_hi=7, min_saturation=100, min_value=40)}


def colour_mask(rgb: np.ndarray, rule: ColourRule) -> np.ndarray:
    """(H, W) bool: the pixels of `rgb` ((H, W, 3) uint8 RGB) whose colour matches `rule`."""
    import cv2

    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    return ((h >= rule.hue_lo) | (h <= rule.hue_hi)) & (s >= rule.min_saturation) & (v >= rule.min_value)


def pallet_boxes_in_units(mask: np.ndarray, units_xyxy: np.ndarray, min_area_frac: float = 0.005,
                          min_inside: float = 0.5, min_top_frac: float = 0.45, min_height_frac: float = 0.03,
                          max_height_frac: float = 0.5, min_width_frac: float = 0.6,
                          min_row_share: float = 0.15, max_outside_units: float = 0.1) -> list[np.ndarray | None]:
    """Each loaded unit's pallet box: the extent, inside the unit's box, of the pallet-coloured regions of its lower
    part.

    A region (8-connected component of `mask`) belongs to a unit's pallet where at least `min_inside` of its pixels
    lie in the unit's box (or all but `max_outside_units` of them in the units' boxes: neighbours' pallets that touch
    are split at their boxes), its pixels there cover at least `min_area_frac` of the box (the load's printed logos are
    smaller) and none of them lies in the box's upper `min_top_frac` (the load stands on the pallet; coloured goods
    behind the unit reach higher). The box spans the rows where those regions hold at least `min_row_share` of their
    fullest row's pixels.

    :param mask: (H, W) bool, the pallet-coloured pixels of the image (`colour_mask`).
    :param units_xyxy: (n, 4) the loaded units' boxes, pixels, x1 y1 x2 y2.
    :return: n entries, each a (4,) float64 xyxy pixel box, or None where no region qualifies or their extent is
        implausible (its height outside [`min_height_frac`, `max_height_frac`] of the unit's box, or narrower than
        `min_width_frac` of it).
    """
    import cv2

    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {mask.shape}")
    units = np.asarray(units_xyxy, np.float64).reshape(-1, 4)
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    sizes = np.bincount(labels.ravel(), minlength=count)
    h_img, w_img = mask.shape
    spans = [(max(int(np.floor(x1)), 0), max(int(np.floor(y1)), 0), min(int(np.ceil(x2)), w_img),
              min(int(np.ceil(y2)), h_img)) for x1, y1, x2, y2 in units]     # pixel columns / rows, in the image
    in_units = np.zeros(mask.shape, bool)
    for c1, r1, c2, r2 in spans:
        in_units[r1:r2, c1:c2] = True
    shared = np.bincount(labels[in_units], minlength=count) >= (1.0 - max_outside_units) * sizes
    out: list[np.ndarray | None] = []
    for c1, r1, c2, r2 in spans:
        if c2 - c1 < 4 or r2 - r1 < 8:
            out.append(None)
            continue
        crop = labels[r1:r2, c1:c2]
        inside = np.bincount(crop.ravel(), minlength=count)
        top_row = np.full(count, r2 - r1, np.int64)
        rows = np.broadcast_to(np.arange(r2 - r1)[:, None], crop.shape)
        np.minimum.at(top_row, crop.ravel(), rows.ravel())
        keep = (((inside >= min_inside * np.maximum(sizes, 1)) | shared) & (inside >= min_area_frac * crop.size)
                & (top_row >= min_top_frac * (r2 - r1)))
        keep[0] = False                               # background
        pallet = keep[crop]
        row_count = pallet.sum(axis=1)
        if row_count.max() == 0:
            out.append(None)
            continue
        # rows the pallet barely reaches are a logo touching its deck, not the pallet
        rows_in = np.flatnonzero(row_count >= min_row_share * row_count.max())
        top, bottom = rows_in[0], rows_in[-1] + 1
        xs = np.flatnonzero(pallet[top:bottom].any(axis=0))
        box = np.array([c1 + xs[0], r1 + top, c1 + xs[-1] + 1, r1 + bottom], np.float64)
        height_frac = (box[3] - box[1]) / (r2 - r1)
        if not min_height_frac <= height_frac <= max_height_frac or box[2] - box[0] < min_width_frac * (c2 - c1):
            out.append(None)
            continue
        out.append(box)
    return out
