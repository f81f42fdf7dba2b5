"""Frame-level registration test: does the depth belong to this colour image, at this alignment? (numpy, OpenCV)

Where a surface ends, the depth jumps and the colour image usually changes too. Over a grid of pixels in the
candidates' boxes (each dilated), pairs of pixels `pair_px` apart along rows and columns with valid depth are split
into *jumping* pairs (depths differ by more than twice the range-dependent tolerance, and by more than twice the
change beside each end: a step, not a noise spike) and the others (depths within that tolerance). The rank
statistic (Mann-Whitney AUC) of the colour differences of jumping pairs against the others is AUC(0): about 0.5 when
depth and colour are unrelated, higher when the depth's edges lie on the image's. Then the same with the depth
shifted by `shift_px` left, right, up and down against the image: a depth registered to the image has its edges on
the image's only at zero shift, so AUC(0) stands above every shifted AUC (the *registration peak*); the depth of
another frame, or depth not registered to the image, shows no such peak. One score per frame, pooled over all
candidates, because per candidate the pairs are too few to judge on stereo-noisy depth.

Colour differences are the sum of absolute RGB differences of the box-filtered image, integers 0-765, so each AUC
comes from two histograms (no sort): a few milliseconds per frame with the grid's step chosen so that at most about
`max_samples` pixels are read.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import kernels

__all__ = ["auc_of_counts", "RegistrationScore", "registration_region", "registration_score", "pair_auc"]

_COLOUR_LEVELS = 3 * 255 + 1


@dataclass(frozen=True)
class RegistrationScore:
    """Registration evidence of one frame (pair counts are at zero shift).

    :ivar auc_0: AUC of colour differences across depth jumps against the other pairs, depth as given (NaN: too
        few jumping or other pairs, or too few colour edges, to judge).
    :ivar auc_shifted: the largest AUC over the shifted depths that have enough pairs (NaN: none has).
    :ivar jump_pairs: pairs whose depths jump.
    :ivar other_pairs: pairs with valid depth that do not jump.
    :ivar colour_edge_pairs: pairs (valid depth or not) whose colour difference is at least `colour_edge`.
    """

    auc_0: float
    auc_shifted: float
    jump_pairs: int
    other_pairs: int
    colour_edge_pairs: int

    @property
    def peak(self) -> float:
        """auc_0 - auc_shifted, NaN without evidence."""
        return self.auc_0 - self.auc_shifted

    @property
    def judged(self) -> bool:
        """Enough pairs to judge the frame (else no evidence either way)."""
        return bool(np.isfinite(self.peak))

    def mismatch(self, min_peak: float, registered_auc: float, weak_auc: float = 0.0) -> bool:
        """Is the depth not this image's? Judged, the peak below `min_peak` and AUC(0) below `registered_auc`, or
        AUC(0) below `weak_auc` (the depth's edges barely follow the image's) and the peak below twice `min_peak`;
        `min_peak` 0 never refuses."""
        if not (min_peak > 0 and self.judged):
            return False
        return bool((self.peak < min_peak and self.auc_0 < registered_auc)
                    or (self.auc_0 < weak_auc and self.peak < 2.0 * min_peak))

    def flat(self, min_pairs: int, min_jump_fraction: float) -> bool:
        """Does the depth show no surface ending where the image shows edges? At least `min_pairs` pairs with valid
        depth and as many colour edges, and fewer than `min_jump_fraction` of those pairs jump: a flat wall's depth,
        a depth stuck at one value. A pallet's outline and its openings are steps in its depth.
        `min_jump_fraction` 0 never refuses."""
        pairs = self.jump_pairs + self.other_pairs
        return bool(min_jump_fraction > 0 and pairs >= min_pairs and self.colour_edge_pairs >= min_pairs
                    and self.jump_pairs < min_jump_fraction * pairs)

    @classmethod
    def unjudged(cls, colour_edge_pairs: int = 0) -> "RegistrationScore":
        """No evidence either way (empty frame, no box, too few pairs)."""
        return cls(float("nan"), float("nan"), 0, 0, int(colour_edge_pairs))


def pair_auc(colour_diff: np.ndarray, jump: np.ndarray, min_pairs: int) -> float:
    """Mann-Whitney AUC of integer colour differences of jumping pairs against the others (ties count half).

    :param colour_diff: (m,) integers in [0, 765].
    :param jump: (m,) bool, True for a pair whose depth jumps.
    :param min_pairs: fewer jumping or fewer other pairs -> NaN.
    :return: AUC in [0, 1] or NaN.
    """
    return auc_of_counts(np.bincount(colour_diff[jump], minlength=_COLOUR_LEVELS),
                         np.bincount(colour_diff[~jump], minlength=_COLOUR_LEVELS), min_pairs)


def auc_of_counts(pos: np.ndarray, neg: np.ndarray, min_pairs: int) -> float:
    """`pair_auc` from the histograms of the jumping pairs' colour differences (pos) and the others' (neg).

    :param pos, neg: (levels,) counts per colour difference.
    """
    n_pos, n_neg = int(pos.sum()), int(neg.sum())
    if n_pos < min_pairs or n_neg < min_pairs:
        return float("nan")
    below = np.cumsum(neg) - neg                        # other pairs with a smaller colour difference
    return float((pos * (below + 0.5 * neg)).sum() / (float(n_pos) * n_neg))


def registration_region(boxes_xyxy: np.ndarray, shape_hw: tuple[int, int], margin_of_box: float,
                        pair_px: int) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The boxes dilated by `margin_of_box` of their width and height on each side, and the pixel rectangle around
    them where a pair (p, p + pair_px) lies inside the image.

    :param boxes_xyxy: (n, 4) image pixels; rows that are not finite are ignored.
    :param shape_hw: the image's (H, W).
    :param margin_of_box: dilation per side as a fraction of the box's size.
    :param pair_px: pixels between the two pixels of a pair.
    :return: (m, 4) dilated finite boxes and (x0, y0, x1, y1), half-open; x1 <= x0 or y1 <= y0 when empty.
    """
    h, w = shape_hw
    b = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    b = b[np.all(np.isfinite(b), 1)]
    size = np.maximum(b[:, 2:] - b[:, :2], 0.0)
    dil = np.concatenate([b[:, :2] - margin_of_box * size, b[:, 2:] + margin_of_box * size], 1)
    if len(dil) == 0:
        return dil, (0, 0, 0, 0)
    x0 = int(np.clip(np.floor(dil[:, 0].min()), 0, w))
    y0 = int(np.clip(np.floor(dil[:, 1].min()), 0, h))
    x1 = int(np.clip(np.ceil(dil[:, 2].max()), 0, w - pair_px))
    y1 = int(np.clip(np.ceil(dil[:, 3].max()), 0, h - pair_px))
    return dil, (x0, y0, x1, y1)


def registration_score(depth_m: np.ndarray, rgb: np.ndarray, boxes_xyxy: np.ndarray, *, shift_px: int = 24,
                       pair_px: int = 3, margin_of_box: float = 0.5, max_samples: int = 16384, tol_m: float = 0.02,
                       tol_quad_per_m: float = 0.004, min_pairs: int = 50, colour_edge: int = 30, blur_px: int = 3,
                       compiled: bool = True) -> RegistrationScore:
    """AUC(0) and the largest AUC with the depth shifted by +-`shift_px` along rows and columns, over the
    candidates' dilated boxes.

    :param depth_m: (H, W) metres; 0, NaN or inf = no data.
    :param rgb: (H, W, 3) uint8 colour image.
    :param boxes_xyxy: (n, 4) the frame's candidate boxes, image pixels; none -> no evidence.
    :param shift_px: the depth's shift against the image, pixels.
    :param pair_px: pixels between the two pixels of a pair.
    :param margin_of_box: each box is dilated by this fraction of its width and height on each side.
    :param max_samples: the grid's step grows until at most about this many pixels are read.
    :param tol_m: depth tolerance at zero range; a pair jumps beyond twice the tolerance at its farther depth.
    :param tol_quad_per_m: tolerance growth with range, metres per metre squared.
    :param min_pairs: fewer jumping, other or colour-edge pairs -> no evidence (NaN AUC).
    :param colour_edge: a pair whose colour difference (sum of absolute RGB differences) is at least this counts
        as a colour edge; an image without enough of them (constant, dark) cannot judge.
    :param blur_px: the colour image is box-filtered over this many pixels first (1: not at all).
    :param compiled: count the pairs in the compiled kernel when the package has it (the same counts); False: numpy.
    :return: the frame's `RegistrationScore`.
    """
    depth = np.asarray(depth_m)
    colour = np.asarray(rgb)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth.shape}")
    if colour.shape != (*depth.shape, 3):
        raise ValueError(f"rgb must be (H, W, 3) like depth_m {depth.shape}, got shape {colour.shape}")
    if colour.dtype != np.uint8:
        raise TypeError(f"rgb must be uint8, got {colour.dtype}")
    if min(int(shift_px), int(pair_px), int(max_samples), int(blur_px)) < 1:
        raise ValueError(f"shift_px, pair_px, max_samples and blur_px must be >= 1, got {shift_px}, {pair_px}, "
                         f"{max_samples}, {blur_px}")
    s, a, blur_px = int(shift_px), int(pair_px), int(blur_px)
    h, w = depth.shape
    dil, (x0, y0, x1, y1) = registration_region(boxes_xyxy, (h, w), margin_of_box, a)
    if x1 <= x0 or y1 <= y0:
        return RegistrationScore.unjudged()
    step = max(1, int(np.ceil(np.sqrt((x1 - x0) * (y1 - y0) / max_samples))))
    xs, ys = np.arange(x0, x1, step), np.arange(y0, y1, step)
    inside = ((xs[None, None, :] >= dil[:, 0, None, None]) & (xs[None, None, :] < dil[:, 2, None, None])
              & (ys[None, :, None] >= dil[:, 1, None, None]) & (ys[None, :, None] < dil[:, 3, None, None])).any(0)

    # colour differences of the pairs (p, p + a along x) and (p, p + a along y), once for all shifts
    # (a box filter first: on a dark, noisy image the sensor noise would drown weak edges)
    crop = colour[y0:y1 + a, x0:x1 + a]
    if blur_px > 1:
        crop = cv2.blur(np.ascontiguousarray(crop), (blur_px, blur_px))
    c = crop[0:y1 - y0:step, 0:x1 - x0:step].astype(np.int16)
    diff_x = np.abs(c - crop[0:y1 - y0:step, a:x1 - x0 + a:step]).sum(-1)
    diff_y = np.abs(c - crop[a:y1 - y0 + a:step, 0:x1 - x0:step]).sum(-1)
    edges = int(((diff_x >= colour_edge) & inside).sum() + ((diff_y >= colour_edge) & inside).sum())
    if edges < min_pairs:
        return RegistrationScore.unjudged(edges)

    # the depth around the rectangle, zero (no data) beyond the image, so every shift reads with plain slices
    m = s + 2 * a                                       # the widest read: a shift, then a pair's flanks
    hh, ww = y1 - y0 + 2 * m + step, x1 - x0 + 2 * m + step
    pad = np.zeros((hh, ww), np.float32)
    sy0, sx0 = max(y0 - m, 0), max(x0 - m, 0)
    sy1, sx1 = min(y0 - m + hh, h), min(x0 - m + ww, w)
    z_crop = depth[sy0:sy1, sx0:sx1].astype(np.float32)
    pad[sy0 - (y0 - m):sy1 - (y0 - m), sx0 - (x0 - m):sx1 - (x0 - m)] = np.where(np.isfinite(z_crop), z_crop, 0.0)
    ny, nx = len(ys), len(xs)

    def z_at(dy: int, dx: int) -> np.ndarray:
        """(ny, nx) depth at the grid's pixels + (dy, dx)."""
        return pad[m + dy:m + dy + ny * step:step, m + dx:m + dx + nx * step:step]

    compiled = compiled and kernels.available()
    inside_u8 = inside.astype(np.uint8) if compiled else None

    def auc(dy: int, dx: int) -> tuple[float, int, int]:
        """AUC with the depth read at the image's pixel + (dy, dx), and the pair counts."""
        if compiled:
            pos, neg = kernels.registration_counts(pad, m, step, inside_u8, diff_x, diff_y, a, dy, dx, tol_m,
                                                   tol_quad_per_m, _COLOUR_LEVELS)
            n_jump = int(pos.sum())
            return auc_of_counts(pos, neg, min_pairs), n_jump, int(neg.sum())
        d, j = [], []
        for (ey, ex), diff in (((0, 1), diff_x), ((1, 0), diff_y)):
            z_b, z0, z1, z_a = (z_at(dy + k * a * ey, dx + k * a * ex) for k in (-1, 0, 1, 2))
            valid = inside & (z0 > 0) & (z1 > 0)
            far = np.maximum(z0, z1)
            step_m = np.abs(z0 - z1)
            jump = step_m > 2.0 * (tol_m + tol_quad_per_m * far * far)
            # a surface's end is a step between flatter flanks; a noise spike changes as much beside it, so such
            # a pair counts neither as a jump nor as another pair
            flat = (np.abs(z_b - z0) < 0.5 * step_m) & (np.abs(z_a - z1) < 0.5 * step_m)
            valid &= ~jump | flat
            d.append(diff[valid])
            j.append(jump[valid])
        dd, jj = np.concatenate(d), np.concatenate(j)
        n_jump = int(jj.sum())
        return pair_auc(dd, jj, min_pairs), n_jump, len(jj) - n_jump

    auc_0, n_jump, n_other = auc(0, 0)
    shifted = [auc(dy, dx)[0] for dy, dx in ((0, s), (0, -s), (s, 0), (-s, 0))]
    judged = [v for v in shifted if np.isfinite(v)]
    return RegistrationScore(auc_0, max(judged) if judged else float("nan"), n_jump, n_other, edges)
