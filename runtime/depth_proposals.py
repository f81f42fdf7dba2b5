"""Pallet proposals from the depth alone in a calibrated view: boxes around what stands a pallet's height on the floor,
or on a rack's beam or another pallet, where a pair of fork pockets shows the level it stands on.

The detector knows pallets by their look, and a look it has not learnt (a blue or black plastic pallet, an
unusual wood, a face seen at 40 degrees) scores under its threshold or not at all. With the camera's calibration
the depth says where the floor is, and every pallet, of any colour, is a block of points standing up to its deck
height (0.1-0.16 m) on it. The points in that band above the floor, joined where neighbouring pixels show no jump in
depth and where they share a cell of the floor, make one object each; those of a pallet's size across are proposed
as boxes. A pallet off the floor (on a rack's beam, on a stack) stands on no floor the calibration knows; its face
shows two fork pockets side by side: openings along the image's rows where the depth falls back behind the face and
comes forward again, a pocket's width and height across, at one height. Each such pair gives a level, and the same
band above that level, around the pair, makes the proposal. The estimator poses them like weak detections and keeps
them only where the posed pallet's structure is clear (`weak_boxes.py`) and the pose fills the box (`framing_iou`),
which a carton stack, a load's foot or a post does not show. Pure numpy and OpenCV.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from .evaluation import box_iou
from .geometry import check_K, invert_T, project_points, transform_points
from .structure import projected_bounds

__all__ = ["DepthProposals", "propose_boxes", "framing_iou"]


@dataclass(frozen=True)
class DepthProposals:
    """What a depth proposal is.

    :ivar band_m: (low, high) heights above the floor, metres, of the points that make a proposal: above the floor's
        noise and the lowered fork tines (4-5 cm thick), up to just over a pallet's deck.
    :ivar max_range_m: farthest point, metres along the floor from the camera; farther pallets are too few pixels
        for the structure check to judge.
    :ivar width_m: (least, most) horizontal extent of an object, metres: part of a pallet's face to a pallet seen
        corner-on (a 1200 x 1000 pallet's diagonal is 1.56 m).
    :ivar min_height_m: least height an object's points span within the band, metres: floor speckle and low clutter
        span less.
    :ivar max_jump: neighbouring pixels whose depths differ by more than this fraction of their depth lie on
        different surfaces.
    :ivar cell_m: side of the floor's cells, metres: surfaces with points in one cell are one object.
    :ivar min_points: least points of an object (at `stride`).
    :ivar stride: the depth is read every `stride` pixels in each direction.
    :ivar margin: each box grows by this fraction of its size on every side; it reaches down to the floor under
        the object's points already.
    :ivar max_iou: a proposal overlapping a detection at this IoU or more (or lying mostly inside its box,
        `WeakBoxes.max_inside`) is held back: the estimator poses it only where no accepted pose of the frame covers
        it, which recovers the pallet whose detection's box was poor and its pose refused.
    :ivar max_boxes: at most this many proposals, the nearest first, are posed. They do not take the places of the
        detector's boxes (`EstimatorOptions.max_pallets`): a frame full of far pallets on racks would leave none
        for the pallet on the floor ahead.
    :ivar min_framing_iou: a proposal's pose is kept only where the posed pallet's projected bounding box (clipped
        to the image) overlaps the proposal at least this much (IoU): a proposal is the object's whole extent, and
        a pose that leaves most of it empty (or reaches far beyond it) is the pose of something else. On calibrated
        forklift validation frames the correct poses mostly frame their proposals at 0.5-0.9, the two poses accepted
        on pallet-free frames at 0.08 and 0.23.
    :ivar off_floor: also propose pallets off the floor, at the levels their fork pockets show.
    :ivar pocket_gap_m: an opening's depth lies at least this far behind the face on both its sides (or shows no
        data), metres.
    :ivar pocket_width_m: (least, most) width of an opening along a row between its two face points, metres: a
        stringer pallet's or a plastic pallet's pocket is up to about 0.5 m wide, an EPAL's 0.23 or 0.38 m.
    :ivar pocket_height_m: (least, most) height an opening spans, metres (pockets are 0.08-0.13 m high).
    :ivar pocket_spacing_m: (least, most) distance between two pockets' centres, metres (an EPAL's 0.34 or 0.53 m).
    :ivar max_levels: at most this many levels off the floor are searched, those of the nearest pocket pairs first.
    """

    band_m: tuple[float, float] = (0.05, 0.19)
    max_range_m: float = 6.0
    width_m: tuple[float, float] = (0.4, 1.7)
    min_height_m: float = 0.07
    max_jump: float = 0.1
    cell_m: float = 0.05
    min_points: int = 12
    stride: int = 2
    margin: float = 0.02
    max_iou: float = 0.5
    max_boxes: int = 4
    min_framing_iou: float = 0.4
    off_floor: bool = True
    pocket_gap_m: float = 0.15
    pocket_width_m: tuple[float, float] = (0.12, 0.6)
    pocket_height_m: tuple[float, float] = (0.04, 0.2)
    pocket_spacing_m: tuple[float, float] = (0.25, 0.85)
    max_levels: int = 6

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.band_m)
        if not 0.0 <= lo < hi:
            raise ValueError(f"DepthProposals.band_m must be 0 <= low < high metres, got {self.band_m!r}")
        for name in ("width_m", "pocket_width_m", "pocket_height_m", "pocket_spacing_m"):
            wlo, whi = (float(v) for v in getattr(self, name))
            if not 0.0 < wlo < whi:
                raise ValueError(f"DepthProposals.{name} must be 0 < least < most metres, got {getattr(self, name)!r}")
        if not isinstance(self.off_floor, bool):
            raise TypeError(f"DepthProposals.off_floor must be a bool, got {type(self.off_floor).__name__}")
        for name in ("max_range_m", "min_height_m", "max_jump", "cell_m", "pocket_gap_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v) > 0.0:
                raise ValueError(f"DepthProposals.{name} must be a positive number, got {v!r}")
        for name in ("stride", "min_points", "max_boxes", "max_levels"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"DepthProposals.{name} must be an integer >= 1, got {v!r}")
        for name in ("margin", "max_iou", "min_framing_iou"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"DepthProposals.{name} must be a number in [0, 1], got {v!r}")


def propose_boxes(depth_m: np.ndarray, K: np.ndarray, T_vehicle_cam: np.ndarray,
                  params: DepthProposals = DepthProposals()) -> np.ndarray:
    """Boxes around the objects that stand a pallet's height on the floor, and (`params.off_floor`) on the levels
    off the floor that pairs of fork pockets show.

    :param depth_m: (H, W) metres, 0 = no data. :param K: (3, 3). :param T_vehicle_cam: (4, 4) the camera's
        calibration (vehicle frame: z up, the floor at z = 0).
    :return: (n, 4) boxes, x1 y1 x2 y2 image pixels, nearest first; (0, 4) where nothing stands on the floor.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    K = check_K(K)
    T_vehicle_cam = np.asarray(T_vehicle_cam, dtype=np.float64)
    if T_vehicle_cam.shape != (4, 4):
        raise ValueError(f"T_vehicle_cam must be (4, 4), got {T_vehicle_cam.shape}")
    s = params.stride
    z = depth_m[::s, ::s].astype(np.float32)
    z[~(np.isfinite(z) & (z > 0))] = 0.0                # no data
    h, w = z.shape
    # the grid's points in the vehicle frame, in float32 (a frame's worth of points: half the time of float64)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32) * s
    x = (u - np.float32(K[0, 2])) / np.float32(K[0, 0]) * z
    y = (v - np.float32(K[1, 2])) / np.float32(K[1, 1]) * z
    T = T_vehicle_cam.astype(np.float32)
    fwd = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
    side = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
    height = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
    grid = _Grid(z, fwd, side, height, s, depth_m.shape, K, invert_T(T_vehicle_cam))
    boxes, ranges = _band_objects(grid, 0.0, params)
    if params.off_floor:
        for level, at_rc, reach in _pocket_levels(grid, params):
            lo, hi = at_rc.min(axis=0), at_rc.max(axis=0)
            b, r = _band_objects(grid.window(int(lo[0] - reach[0]), int(hi[0] + reach[0]) + 1,
                                             int(lo[1] - reach[1]), int(hi[1] + reach[1]) + 1), level, params)
            # the object around the pockets (its box holds a pair's centre), not whatever else stands on that level
            holds = [bool(np.any((bx[0] <= at_rc[:, 1] * s) & (at_rc[:, 1] * s <= bx[2])
                                 & (bx[1] <= at_rc[:, 0] * s) & (at_rc[:, 0] * s <= bx[3]))) for bx in b]
            boxes += [bx for bx, k in zip(b, holds) if k]
            ranges += [rg for rg, k in zip(r, holds) if k]
    if not boxes:
        return np.zeros((0, 4))
    boxes_a = np.asarray(boxes, dtype=np.float64)[np.argsort(ranges, kind="stable")]
    keep = []                                           # one box per object seen from two levels
    for i in range(len(boxes_a)):
        if not keep or box_iou(boxes_a[i:i + 1], boxes_a[keep]).max() < 0.7:
            keep.append(i)
    return boxes_a[keep]


# Off the floor the band starts lower than on it: no floor noise or lowered fork tines lie on a beam, and a pallet's
# face seen level from the side shows only its height above the level its pockets give (a centimetre or two off).
OFF_FLOOR_BAND_LOW_M = 0.02
_MAX_WALL_CELLS = 24


@dataclass(frozen=True)
class _Grid:
    """The depth read every `stride` pixels: z (h, w) metres (0 = no data), its points' vehicle-frame coordinates
    fwd / side / height (h, w) metres, the full image's (H, W), K and T_cam_vehicle."""

    z: np.ndarray
    fwd: np.ndarray
    side: np.ndarray
    height: np.ndarray
    stride: int
    image_hw: tuple[int, int]
    K: np.ndarray
    T_cam_vehicle: np.ndarray
    origin: tuple[int, int] = (0, 0)

    def window(self, r0: int, r1: int, c0: int, c1: int) -> "_Grid":
        """The grid's rows r0:r1 and columns c0:c1 (clipped to it), knowing where they lie."""
        h, w = self.z.shape
        r0, r1, c0, c1 = max(0, r0), min(h, r1), max(0, c0), min(w, c1)
        cut = (slice(r0, r1), slice(c0, c1))
        return _Grid(self.z[cut], self.fwd[cut], self.side[cut], self.height[cut], self.stride, self.image_hw, self.K,
                     self.T_cam_vehicle, (self.origin[0] + r0, self.origin[1] + c0))


def _band_objects(g: _Grid, level_m: float, params: DepthProposals) -> tuple[list[list[float]], list[float]]:
    """Boxes (image pixels) around the objects whose points stand in `params.band_m` above `level_m` (vehicle z,
    metres; off the floor the band starts `OFF_FLOOR_BAND_LOW_M` above it), and each one's range along the floor,
    metres."""
    z, fwd, side, height, s = g.z, g.fwd, g.side, g.height, g.stride
    H, W = g.image_hw
    w = z.shape[1]
    lo, hi = params.band_m
    if level_m != 0.0:
        lo = min(lo, OFF_FLOOR_BAND_LOW_M)
    above = height - np.float32(level_m)
    band = (z > 0) & (above >= lo) & (above <= hi) & (np.hypot(fwd, side) <= params.max_range_m)
    # pieces: neighbouring pixels of the band without a jump in depth between them (a pallet's face and its deck
    # seen at a grazing angle; not a pallet and the wall behind it)
    jump = params.max_jump * np.maximum(z, 1e-3)
    cut = np.zeros_like(band)
    cut[:, 1:] |= np.abs(z[:, 1:] - z[:, :-1]) > jump[:, 1:]
    cut[1:, :] |= np.abs(z[1:, :] - z[:-1, :]) > jump[1:, :]
    n_pieces, pieces = cv2.connectedComponents((band & ~cut).astype(np.uint8), connectivity=4)
    pix = np.flatnonzero(pieces.reshape(-1) > 0)
    if len(pix) == 0:
        return [], []
    # pieces that share a cell of the floor are one object (a pallet's blocks seen between its boards)
    r = params.max_range_m
    n_cells = int(np.ceil(2 * r / params.cell_m))
    f, sd, ht = fwd.reshape(-1)[pix], side.reshape(-1)[pix], above.reshape(-1)[pix]
    ci = np.clip(((f + r) / params.cell_m).astype(np.int64), 0, n_cells - 1)
    cj = np.clip(((sd + r) / params.cell_m).astype(np.int64), 0, n_cells - 1)
    lab = _merge_sharing(pieces.reshape(-1)[pix], ci * n_cells + cj, n_pieces)
    order = np.argsort(lab, kind="stable")
    pix, lab, f, sd, ht = pix[order], lab[order], f[order], sd[order], ht[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], len(lab)]
    boxes, ranges = [], []
    for a, b in zip(starts, ends):
        if b - a < params.min_points:
            continue
        if np.percentile(ht[a:b], 95) - np.percentile(ht[a:b], 5) < params.min_height_m:
            continue
        xy = np.stack([f[a:b], sd[a:b]], axis=1)
        if not params.width_m[0] <= _extent_m(xy) <= params.width_m[1]:
            continue
        rows, cols = np.divmod(pix[a:b], w)
        rows, cols = rows + g.origin[0], cols + g.origin[1]
        # the object stands on the level: its box reaches down to where its points' feet are seen
        feet_v = np.column_stack([xy, np.full(len(xy), level_m)])
        feet = project_points(transform_points(g.T_cam_vehicle, feet_v), g.K)
        feet = feet[np.isfinite(feet).all(axis=1)]
        us = np.concatenate([[cols.min() * s, (cols.max() + 1) * s], feet[:, 0]])
        vs = np.concatenate([[rows.min() * s, (rows.max() + 1) * s], feet[:, 1]])
        x0, x1, y0, y1 = us.min(), us.max(), vs.min(), vs.max()
        mx, my = params.margin * (x1 - x0), params.margin * (y1 - y0)
        boxes.append([max(0.0, x0 - mx), max(0.0, y0 - my), min(float(W), x1 + mx), min(float(H), y1 + my)])
        ranges.append(float(np.median(np.hypot(xy[:, 0], xy[:, 1]))))
    return boxes, ranges


def _pocket_levels(g: _Grid, params: DepthProposals) -> list[tuple[float, np.ndarray, tuple[float, float]]]:
    """Levels off the floor that pairs of fork pockets show: [(level_m, (k, 2) grid row / column of the pairs'
    centres, (rows, columns) of the grid a pallet reaches from there)], the nearest pair's level first. A level is
    where the pallet stands: a little under its pockets' lowest edge (the bottom boards' top, or the beam itself
    where the pallet has none)."""
    op = _openings(g, params)
    if len(op) < 2:
        return []
    bottom, top, width, f, sd, row, col, z_m = op.T
    i, j = np.triu_indices(len(op), 1)
    centre_m = np.hypot(f[i] - f[j], sd[i] - sd[j])
    between_m = centre_m - (width[i] + width[j]) / 2    # the block or stringer between them
    tall_i, tall_j = top[i] - bottom[i], top[j] - bottom[j]
    # a pallet's two pockets: alike in width and height, at one height, a block's or stringer's width apart
    pair = ((np.abs(bottom[i] - bottom[j]) <= 0.04) & (np.maximum(tall_i, tall_j) <= 1.6 * np.minimum(tall_i, tall_j))
            & (np.maximum(width[i], width[j]) <= 1.4 * np.minimum(width[i], width[j]))
            & (params.pocket_spacing_m[0] <= centre_m) & (centre_m <= params.pocket_spacing_m[1])
            & (between_m >= 0.02))
    i, j = i[pair], j[pair]
    level = np.minimum(bottom[i], bottom[j]) - 0.03
    off = level > params.band_m[0] + 0.05              # pallets on the floor are the floor band's
    i, j, level = i[off], j[off], level[off]
    if len(level) == 0:
        return []
    at_rc = np.column_stack([(row[i] + row[j]) / 2, (col[i] + col[j]) / 2])
    rng = np.hypot((f[i] + f[j]) / 2, (sd[i] + sd[j]) / 2)
    # a pallet reaches 1.7 m across (a 1200 x 1000 pallet corner-on) and about as far up and down (seen from above)
    cells = 1.7 / (np.maximum(z_m[i] + z_m[j], 0.2) / 2 * g.stride)
    out: list[tuple[float, np.ndarray, tuple[float, float]]] = []
    for k in np.argsort(rng, kind="stable"):            # levels within 4 cm of one searched already are that level
        near = [n for n, (lv, _, _) in enumerate(out) if abs(lv - level[k]) <= 0.04]
        reach = (float(cells[k] * g.K[1, 1]), float(cells[k] * g.K[0, 0]))
        if near:
            lv, pts, r = out[near[0]]
            out[near[0]] = (lv, np.vstack([pts, at_rc[k:k + 1]]), (max(r[0], reach[0]), max(r[1], reach[1])))
        elif len(out) < params.max_levels:
            out.append((float(level[k]), at_rc[k:k + 1], reach))
    return out


def _openings(g: _Grid, params: DepthProposals) -> np.ndarray:
    """Openings in faces: runs along the grid's rows where the depth lies `pocket_gap_m` behind the face on both
    sides (or shows no data), a pocket's width across, joined over neighbouring rows, a pocket's height tall.

    :return: (n, 8) per opening: its lowest and highest face height (vehicle z, metres), mean width (metres), centre
        fwd / side (metres), centre grid row / column, the faces' mean depth (camera z, metres)."""
    z, s = g.z, g.stride
    h, w = z.shape
    if w < 3:
        return np.zeros((0, 8))
    gap = np.float32(params.pocket_gap_m)
    zc, zn = z[:, :-1], z[:, 1:]
    up = (zc > 0) & ((zn == 0) | (zn - zc > gap))         # the face ends at column j, the opening starts at j + 1
    down = (zn > 0) & ((zc == 0) | (zc - zn > gap))       # the opening ends at j, the face starts again at j + 1
    # a pocket's side wall climbs in several steps: the opening starts at the first, ends at the last
    first_up = up.copy()
    first_up[:, 1:] &= ~up[:, :-1]
    last_down = down.copy()
    last_down[:, :-1] &= ~down[:, 1:]
    ups_rc, downs_rc = np.flatnonzero(first_up), np.flatnonzero(last_down)
    if len(ups_rc) == 0 or len(downs_rc) == 0:
        return np.zeros((0, 8))
    k = np.searchsorted(downs_rc, ups_rc)
    ok = k < len(downs_rc)
    ups_rc, ends_rc = ups_rc[ok], downs_rc[k[ok]]
    nxt = np.r_[ups_rc[1:], np.iinfo(np.int64).max]
    ok = (ups_rc // (w - 1) == ends_rc // (w - 1)) & (nxt > ends_rc)     # one row; the innermost run
    ups_rc, ends_rc = ups_rc[ok], ends_rc[ok]
    if len(ups_rc) == 0:
        return np.zeros((0, 8))
    rows = ups_rc // (w - 1)
    a = rows * w + ups_rc % (w - 1)                       # the face's last pixel before the opening (flat index)
    b = rows * w + ends_rc % (w - 1) + 1                  # the face's first pixel after it
    # a pocket's side wall seen almost along its length climbs steeply, a step at a time: the face ends where the
    # climb starts (steeper than a face turned 68 degrees away climbs: 2.5 of a grid cell's width a cell), at most
    # `_MAX_WALL_CELLS` cells back
    zf, ff, sf, hf = (arr.reshape(-1) for arr in (z, g.fwd, g.side, g.height))
    inner = np.where(zf > 0, zf, np.inf)                 # the opening past the jumps lies behind both faces
    lowest = np.minimum.reduceat(inner, np.column_stack([a + 1, b]).reshape(-1))[::2]
    steep = np.float32(2.5 * s / g.K[0, 0])
    first_col, last_col = a - a % w, a - a % w + w - 1
    for _ in range(_MAX_WALL_CELLS):
        climbs = (a > first_col) & (zf[a - 1] > 0) & (zf[a] - zf[a - 1] > steep * zf[a - 1])
        falls = (b < last_col) & (zf[np.minimum(b + 1, h * w - 1)] > 0) \
            & (zf[b] - zf[np.minimum(b + 1, h * w - 1)] > steep * zf[np.minimum(b + 1, h * w - 1)])
        if not (climbs.any() or falls.any()):
            break
        a, b = a - climbs, b + falls
    width = np.hypot(ff[a] - ff[b], sf[a] - sf[b])
    keep = ((lowest > np.maximum(zf[a], zf[b]) + gap) & (np.abs(hf[a] - hf[b]) <= 0.05)
            & (params.pocket_width_m[0] <= width) & (width <= params.pocket_width_m[1]))
    a, b, width = a[keep], b[keep], width[keep]
    if len(a) < 2:
        return np.zeros((0, 8))
    # the runs joined over neighbouring rows
    mark = np.zeros(h * w + 1, dtype=np.int32)
    np.add.at(mark, a + 1, 1)
    np.add.at(mark, b, -1)
    runs = (np.cumsum(mark[:-1]).reshape(h, w) > 0).astype(np.uint8)
    n, labels = cv2.connectedComponents(runs, connectivity=8)
    lab = labels.reshape(-1)[a + 1]
    face_h = (hf[a] + hf[b]) / 2
    count = np.bincount(lab, minlength=n)
    bottom = np.full(n, np.inf)
    top = np.full(n, -np.inf)
    np.minimum.at(bottom, lab, face_h)
    np.maximum.at(top, lab, face_h)
    row_m = s * zf[a] / g.K[1, 1]                         # the metric height of one grid row there
    tall = top - bottom + np.bincount(lab, row_m, minlength=n) / np.maximum(count, 1)

    def mean(vals: np.ndarray) -> np.ndarray:
        return np.bincount(lab, vals, minlength=n) / np.maximum(count, 1)

    keep = ((count >= 3) & (params.pocket_height_m[0] <= tall) & (tall <= params.pocket_height_m[1]))
    keep[0] = False                                       # connectedComponents' background
    cols = (a % w + b % w) / 2
    return np.column_stack([bottom, top, mean(width), mean((ff[a] + ff[b]) / 2), mean((sf[a] + sf[b]) / 2),
                            mean(a // w), mean(cols), mean((zf[a] + zf[b]) / 2)])[keep]


def framing_iou(T_cam_pallet: np.ndarray, size_m: np.ndarray, K: np.ndarray, boxes_xyxy: np.ndarray,
                image_hw: tuple[int, int]) -> np.ndarray:
    """How well each box frames its posed pallet: IoU of the box with the pallet's projected bounding box, both
    clipped to the image.

    :param T_cam_pallet: (n, 4, 4). :param size_m: (n, 3) the pallets' bounding box sizes, metres (the pallet frame's
        origin is its centre). :param boxes_xyxy: (n, 4) pixels. :param image_hw: (H, W).
    :return: (n,) in [0, 1]; 0 where the pallet is behind the camera."""
    size = np.asarray(size_m, dtype=np.float64).reshape(-1, 3)
    with warnings.catch_warnings():                       # a pallet wholly behind the camera has no projection
        warnings.simplefilter("ignore", RuntimeWarning)
        proj = projected_bounds(np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4), -size / 2, size / 2,
                                np.asarray(K, dtype=np.float64))
    H, W = image_hw
    limit = np.array([W, H, W, H], dtype=np.float64)
    proj = np.clip(np.nan_to_num(proj, nan=0.0), 0.0, limit)
    boxes = np.clip(np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4), 0.0, limit)
    return np.diagonal(box_iou(proj, boxes)).copy()


def _merge_sharing(piece: np.ndarray, cell: np.ndarray, n_pieces: int) -> np.ndarray:
    """Each point's object: pieces (n,) whose points share a cell (n,) are merged, transitively."""
    order = np.lexsort((piece, cell))
    c, p = cell[order], piece[order]
    same = (c[1:] == c[:-1]) & (p[1:] != p[:-1])
    parent = np.arange(n_pieces)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in set(zip(p[:-1][same].tolist(), p[1:][same].tolist())):
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    while True:                                          # every piece points at its root
        nxt = parent[parent]
        if np.array_equal(nxt, parent):
            return parent[piece]
        parent = nxt


def _extent_m(xy: np.ndarray) -> float:
    """The horizontal extent of points (n, 2) along their principal direction, metres (2nd to 98th percentile)."""
    d = xy - xy.mean(axis=0)
    _, vecs = np.linalg.eigh(d.T @ d)
    t = d @ vecs[:, -1]
    lo, hi = np.percentile(t, [2, 98])
    return float(hi - lo)
