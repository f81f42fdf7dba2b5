"""Pallet proposals from the depth alone in a calibrated view: boxes around what stands a pallet's height on the floor.

The detector knows pallets by their look, and a look it has not learnt (a blue or black plastic pallet, an
unusual wood, a face seen at 40 degrees) scores under its threshold or not at all. With the camera's calibration
the depth says where the floor is, and every pallet, of any colour, is a block of points standing up to its deck
height (0.1-0.16 m) on it. The points in that band above the floor, joined where neighbouring pixels show no jump in
depth and where they share a cell of the floor, make one object each; those of a pallet's size across are proposed
as boxes. The estimator poses them like weak detections and keeps them only where the posed pallet's structure is
clear (`weak_boxes.py`) and the pose fills the box (`framing_iou`), which a carton stack, a load's foot or a post
does not show. Pallets on racks or on other pallets stand on no floor and are not proposed. Pure numpy and OpenCV.
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

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.band_m)
        if not 0.0 <= lo < hi:
            raise ValueError(f"DepthProposals.band_m must be 0 <= low < high metres, got {self.band_m!r}")
        wlo, whi = (float(v) for v in self.width_m)
        if not 0.0 < wlo < whi:
            raise ValueError(f"DepthProposals.width_m must be 0 < least < most metres, got {self.width_m!r}")
        for name in ("max_range_m", "min_height_m", "max_jump", "cell_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v) > 0.0:
                raise ValueError(f"DepthProposals.{name} must be a positive number, got {v!r}")
        for name in ("stride", "min_points", "max_boxes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"DepthProposals.{name} must be an integer >= 1, got {v!r}")
        for name in ("margin", "max_iou", "min_framing_iou"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"DepthProposals.{name} must be a number in [0, 1], got {v!r}")


def propose_boxes(depth_m: np.ndarray, K: np.ndarray, T_vehicle_cam: np.ndarray,
                  params: DepthProposals = DepthProposals()) -> np.ndarray:
    """Boxes around the objects that stand a pallet's height on the floor.

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
    H, W = depth_m.shape
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
    lo, hi = params.band_m
    band = (z > 0) & (height >= lo) & (height <= hi) & (np.hypot(fwd, side) <= params.max_range_m)
    # pieces: neighbouring pixels of the band without a jump in depth between them (a pallet's face and its deck
    # seen at a grazing angle; not a pallet and the wall behind it)
    jump = params.max_jump * np.maximum(z, 1e-3)
    cut = np.zeros_like(band)
    cut[:, 1:] |= np.abs(z[:, 1:] - z[:, :-1]) > jump[:, 1:]
    cut[1:, :] |= np.abs(z[1:, :] - z[:-1, :]) > jump[1:, :]
    n_pieces, pieces = cv2.connectedComponents((band & ~cut).astype(np.uint8), connectivity=4)
    pix = np.flatnonzero(pieces.reshape(-1) > 0)
    if len(pix) == 0:
        return np.zeros((0, 4))
    # pieces that share a cell of the floor are one object (a pallet's blocks seen between its boards)
    r = params.max_range_m
    n_cells = int(np.ceil(2 * r / params.cell_m))
    f, sd, ht = fwd.reshape(-1)[pix], side.reshape(-1)[pix], height.reshape(-1)[pix]
    ci = np.clip(((f + r) / params.cell_m).astype(np.int64), 0, n_cells - 1)
    cj = np.clip(((sd + r) / params.cell_m).astype(np.int64), 0, n_cells - 1)
    lab = _merge_sharing(pieces.reshape(-1)[pix], ci * n_cells + cj, n_pieces)
    order = np.argsort(lab, kind="stable")
    pix, lab, f, sd, ht = pix[order], lab[order], f[order], sd[order], ht[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], len(lab)]
    boxes, ranges = [], []
    T_cam_vehicle = invert_T(T_vehicle_cam)
    for a, b in zip(starts, ends):
        if b - a < params.min_points:
            continue
        if np.percentile(ht[a:b], 95) - np.percentile(ht[a:b], 5) < params.min_height_m:
            continue
        xy = np.stack([f[a:b], sd[a:b]], axis=1)
        if not params.width_m[0] <= _extent_m(xy) <= params.width_m[1]:
            continue
        rows, cols = np.divmod(pix[a:b], w)
        # the object stands on the floor: its box reaches down to where its points' feet are seen
        feet = project_points(transform_points(T_cam_vehicle, np.column_stack([xy, np.zeros(len(xy))])), K)
        feet = feet[np.isfinite(feet).all(axis=1)]
        us = np.concatenate([[cols.min() * s, (cols.max() + 1) * s], feet[:, 0]])
        vs = np.concatenate([[rows.min() * s, (rows.max() + 1) * s], feet[:, 1]])
        x0, x1, y0, y1 = us.min(), us.max(), vs.min(), vs.max()
        mx, my = params.margin * (x1 - x0), params.margin * (y1 - y0)
        boxes.append([max(0.0, x0 - mx), max(0.0, y0 - my), min(float(W), x1 + mx), min(float(H), y1 + my)])
        ranges.append(float(np.median(np.hypot(xy[:, 0], xy[:, 1]))))
    if not boxes:
        return np.zeros((0, 4))
    return np.asarray(boxes, dtype=np.float64)[np.argsort(ranges, kind="stable")]


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
