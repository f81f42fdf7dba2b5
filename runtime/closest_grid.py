"""Closest point on a union of axis-aligned boxes (a pallet's boards and blocks): the search over all boxes,
and a grid that lists per cell the only boxes that can be nearest to a point in it (numpy only).

The closest box of a point is the one whose surface is nearest: outside a box its distance to the box,
inside it the depth below its nearest face; the first of equals in box order wins. Each box's surface
distance f_b is 1-Lipschitz, so over a grid cell it stays between a lower and an upper bound computed from the
cell (its distance to the box, its corners). A box whose lower bound exceeds some box's upper bound can never
be nearest in that cell: the grid keeps, per cell, the other boxes in ascending order, and a point in it is
tested against those alone, with the same arithmetic as the full search. The answer (box, closest point,
normal, distance, ties) is the full search's bit for bit; only fewer boxes are tested (1-2 for most
points of a pallet's surface instead of 20).
"""
from __future__ import annotations

import numpy as np

__all__ = ["BoxGrid", "box_extents", "closest_all"]


def box_extents(boxes: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis, the distinct (min, max) extents of (k, 2, 3) boxes, (u, 2), and each box's extent, (k,)."""
    out = []
    for a in range(3):
        extent, box_col = np.unique(boxes[:, :, a], axis=0, return_inverse=True)
        out.append((extent, box_col.reshape(-1)))
    return out


def _finish(p: np.ndarray, lo_hi: np.ndarray, d: np.ndarray,
            off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point and outward normal of (n, 3) points on their chosen boxes `lo_hi` (n, 2, 3), at distance
    d (n,): clamped into the box where the point is off it (`off`: its outside distance to the box is > 0),
    else moved to the box's nearest face (the first of -x -y -z +x +y +z)."""
    lo, hi = lo_hi[:, 0], lo_hi[:, 1]
    q = np.minimum(np.maximum(p, lo), hi)                         # np.clip's arithmetic, without its overhead
    normal = np.zeros((len(p), 3))
    np.divide(p - q, d[:, None], out=normal, where=off[:, None])
    face = np.flatnonzero(~off)
    if len(face):
        pf, lf, hf = p.take(face, 0), lo.take(face, 0), hi.take(face, 0)
        f = np.concatenate([pf - lf, hf - pf], axis=1).argmin(1)
        axis, positive = f % 3, f >= 3
        own = np.arange(0, 3 * len(face), 3) + axis               # flat (face row, axis)
        at = face * 3 + axis                                      # flat (point, axis)
        q.reshape(-1)[at] = np.where(positive, hf.take(own), lf.take(own))
        normal.reshape(-1)[at] = np.where(positive, 1.0, -1.0)
    return q, normal, d


def closest_all(p: np.ndarray, boxes: np.ndarray,
                extents: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on the surface of (k, 2, 3) boxes for (n, 3) float64 points, testing every box.

    :param extents: the boxes' `box_extents`.
    :return: (closest (n, 3), unit outward normal (n, 3), distance (n,)), metres.
    """
    n = len(p)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    # squared distance outside each box, one axis at a time: a pallet's boards and blocks share few distinct
    # extents per axis (EPAL: 16 over the three axes for 20 boxes), so each axis' squared gap is computed once
    # per distinct extent and gathered per box. Arrays are (boxes, points): numpy's inner loops then run
    # along the points.
    p_axes = np.ascontiguousarray(p.T)                           # (3, n)
    d_out2 = np.zeros((len(boxes), n))
    for a, (extent, box_col) in enumerate(extents):
        pa = p_axes[a]
        gap = np.subtract(extent[:, 0, None], pa)
        np.maximum(gap, pa - extent[:, 1, None], out=gap)
        np.maximum(gap, 0.0, out=gap)
        np.multiply(gap, gap, out=gap)
        d_out2 += gap.take(box_col, 0)
    j = d_out2.argmin(0)                                     # nearest box per point
    d = np.sqrt(d_out2.take(j * n + np.arange(n)))
    off = d > 0.0
    ins = np.flatnonzero(~off)
    if len(ins):
        # inside a box: its nearest face is a candidate at the depth below it, every box the point is outside
        # of at its outside distance (boxes may overlap); the nearest wins
        m = len(ins)
        o2 = d_out2.take(ins, 1)
        d_in = np.full(o2.shape, np.inf)                          # (k, m) depth below each box's nearest face
        for a, (extent, box_col) in enumerate(extents):
            pa = p_axes[a].take(ins)
            below = np.minimum(pa - extent[:, 0, None], extent[:, 1, None] - pa)
            np.minimum(d_in, below.take(box_col, 0), out=d_in)
        dist = np.where(o2 > 0.0, np.sqrt(o2), np.maximum(d_in, 0.0))
        ji = dist.argmin(0)
        at = ji * m + np.arange(m)
        j[ins], d[ins], off[ins] = ji, dist.take(at), o2.take(at) > 0.0
    return _finish(p, boxes.take(j, 0), d, off)


def _separable_distance(bx: np.ndarray, by: np.ndarray, bz: np.ndarray) -> np.ndarray:
    """Surface distance to each of k boxes on a lattice: outside distance, or depth below the nearest face.

    :param bx: (nx, k) per lattice x, max(box min - x, x - box max) (< 0 inside the box's x range); by (ny, k),
        bz (nz, k) alike. :return: (nx, ny, nz, k).
    """
    x, y, z = bx[:, None, None], by[None, :, None], bz[None, None]
    outside = np.sqrt(np.maximum(x, 0.0) ** 2 + np.maximum(y, 0.0) ** 2 + np.maximum(z, 0.0) ** 2)
    return np.where(outside > 0.0, outside, -np.maximum(np.maximum(x, y), z))


def _distinct_rows(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of a (n, k) bool array, (R, k), and each row's index among them, (n,).

    Rows are packed 64 booleans to a word and numbered word by word (sorting integers, not rows)."""
    n, k = mask.shape
    packed = np.packbits(mask, axis=1, bitorder="little")                       # (n, ceil(k / 8))
    packed = np.pad(packed, ((0, 0), (0, -packed.shape[1] % 8)))
    words = packed.view(np.uint64)                                              # (n, ceil(k / 64))
    _, first, inverse = np.unique(words[:, 0], return_index=True, return_inverse=True)
    for w in range(1, words.shape[1]):
        _, word_id = np.unique(words[:, w], return_inverse=True)
        _, first, inverse = np.unique(inverse.reshape(-1).astype(np.int64) * n + word_id.reshape(-1),
                                      return_index=True, return_inverse=True)
    return mask[first], inverse.reshape(-1)


class BoxGrid:
    """Per cell of a cubic grid around (k, 2, 3) boxes, the boxes that can be nearest to a point in the cell.

    Box b is dropped from a cell when its surface distance is, everywhere in the cell, more than some box's
    is anywhere in it (lower bound of f_b: the cell's distance to the box, or inside the box the least depth
    of the cell's corners; upper bound of f_b': the farthest corner where the cell does not enter the box, a
    convex distance there, else the centre's value plus the half-diagonal). Every box a point of the cell
    lies in stays (lower bound 0), so "inside some box" is decided as by the full search. The bounds use the
    cell grown by `_GROW_M` and a `_GROW_M` slack, far above rounding. Points outside the grid go through the
    full search (`closest_all`).

    Each distinct candidate set is padded to the largest one's size by repeating its last box (argmin keeps
    the first of equals). A query costs about as many numpy calls as the full search: ICP asks for a few
    hundred to a few thousand points at a time, where each call's overhead counts as much as its arithmetic.

    :param boxes_m: (k, 2, 3) min/max corners, metres. :param margin_m: the grid reaches this far beyond the
        boxes' bounding box (ICP's largest correspondence distance). :param cell_m: cell edge, metres.
    """

    _GROW_M = 1e-7

    def __init__(self, boxes_m: np.ndarray, margin_m: float, cell_m: float) -> None:
        boxes = np.asarray(boxes_m, dtype=np.float64)
        if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0 or not np.all(np.isfinite(boxes)):
            raise ValueError(f"boxes_m must be finite (k, 2, 3) with k >= 1, got shape {boxes.shape}")
        if not (margin_m >= 0 and cell_m > 0):
            raise ValueError(f"need margin_m >= 0 and cell_m > 0, got {margin_m}, {cell_m}")
        self.boxes = boxes
        self.extents = box_extents(boxes)
        self.cell_m = float(cell_m)
        self.origin = boxes[:, 0].min(0) - margin_m
        self.shape = np.ceil((boxes[:, 1].max(0) + margin_m - self.origin) / self.cell_m).astype(np.int64)
        self.end = self.origin + self.shape * self.cell_m                 # grid's far corner
        cand = self._candidates()                                         # (cells, k) bool
        lists, cell_list = _distinct_rows(cand)                            # distinct candidate sets
        count = lists.sum(1)
        self.width = w = int(count.max())
        self.ids = np.zeros((len(lists), w), dtype=np.int64)            # each set, padded
        for i, row in enumerate(lists):
            b = np.flatnonzero(row)
            self.ids[i] = np.concatenate([b, np.full(w - len(b), b[-1])])
        # (2, 3, W, R): a cell's candidates min/max corners; gathered per point to (2, 3, W, n), the points
        # innermost, so numpy's loops run along them
        self.table = np.ascontiguousarray(boxes[self.ids].transpose(2, 3, 1, 0))
        self.ids = np.ascontiguousarray(self.ids.T)                                  # (W, R)
        self.cell_row = cell_list.astype(np.int16 if len(lists) <= np.iinfo(np.int16).max else np.int32)
        self.strides = np.array([self.shape[1] * self.shape[2], self.shape[2], 1], dtype=np.float64)

    @property
    def nbytes(self) -> int:
        """Memory the index holds, bytes."""
        return int(self.cell_row.nbytes + self.table.nbytes + self.ids.nbytes)

    def _candidates(self, chunk: int = 8) -> np.ndarray:
        """(cells, k) whether each box can be nearest somewhere in each cell (C order over `shape`).

        Every term is a per-axis (cells along the axis, k) array broadcast over the other two axes; slabs of
        `chunk` cells along x bound the (cells, k) temporaries."""
        s, g, boxes = self.cell_m, self._GROW_M, self.boxes
        blo, bhi = boxes[:, 0], boxes[:, 1]                                          # (k, 3)
        corner, lo, hi, centre = [], [], [], []
        for a in range(3):
            x = self.origin[a] + np.arange(self.shape[a] + 1) * s                   # cell boundaries
            l, h = x[:-1, None] - g, x[1:, None] + g                                # grown cells (n_a, 1)
            c = 0.5 * (x[:-1, None] + x[1:, None])
            corner.append(np.maximum(blo[:, a] - x[:, None], x[:, None] - bhi[:, a]))   # (n_a + 1, k)
            centre.append(np.maximum(blo[:, a] - c, c - bhi[:, a]))                     # (n_a, k)
            lo.append(l)
            hi.append(h)
        half_diag = 0.5 * np.sqrt(3.0) * (s + 2 * g)                                # of a grown cell
        per_axis = [(np.maximum(np.maximum(blo[:, a] - hi[a], lo[a] - bhi[:, a]), 0.0) ** 2,    # gap to the box
                     (lo[a] >= blo[:, a]) & (hi[a] <= bhi[:, a]),                             # within it
                     (hi[a] > blo[:, a]) & (lo[a] < bhi[:, a])) for a in range(3)]            # meets its inside
        ny, nz = int(self.shape[1]), int(self.shape[2])
        out = []
        for x0 in range(0, int(self.shape[0]), chunk):
            x1 = min(x0 + chunk, int(self.shape[0]))
            fc = _separable_distance(corner[0][x0:x1 + 1], corner[1], corner[2])      # (cx + 1, ny + 1, nz + 1, k)
            cx = x1 - x0
            views = [fc[i:i + cx, j:j + ny, m:m + nz] for i in (0, 1) for j in (0, 1) for m in (0, 1)]
            f_min, f_max = np.minimum.reduce(views), np.maximum.reduce(views)          # (cx, ny, nz, k)
            (gx, wx, ex), (gy, wy, ey), (gz, wz, ez) = per_axis
            apart = np.sqrt(gx[x0:x1, None, None] + gy[None, :, None] + gz[None, None])   # cell to box
            within = wx[x0:x1, None, None] & wy[None, :, None] & wz[None, None]
            enters = ex[x0:x1, None, None] & ey[None, :, None] & ez[None, None]
            # the grown cell's corners lie within sqrt(3) g of the cell's: 2 g more each way keeps the bounds
            lower = np.where(within, f_min - 2 * g, apart)
            upper = np.where(enters, _separable_distance(centre[0][x0:x1], centre[1], centre[2]) + half_diag,
                             f_max + 2 * g)
            keep = lower <= upper.min(-1, keepdims=True) + g
            out.append(keep.reshape(-1, len(boxes)))
        return np.concatenate(out)

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`closest_all` of (n, 3) float64 points (same results), testing only the candidates of each point's
        cell; points outside the grid (or not finite) test every box."""
        u = p - self.origin
        u /= self.cell_m
        np.floor(u, out=u)                                            # each point's cell, per axis
        if len(p) and not (u.min() >= 0.0 and (u.max(0) < self.shape).all()):
            inside = np.all((u >= 0.0) & (u < self.shape), axis=1)
            q, normal, d = np.empty((len(p), 3)), np.empty((len(p), 3)), np.empty(len(p))
            for sel, fn in ((np.flatnonzero(~inside), lambda x: closest_all(x, self.boxes, self.extents)),
                            (np.flatnonzero(inside), self.closest)):
                if len(sel):
                    q[sel], normal[sel], d[sel] = fn(p.take(sel, 0))
            return q, normal, d
        row = self.cell_row.take((u @ self.strides).astype(np.intp))   # whole numbers: exact
        return _closest_among(p, self.table.take(row, 3), self.ids.take(row, 1), self.boxes)


def _closest_among(p: np.ndarray, table: np.ndarray, ids: np.ndarray,
                   boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`closest_all` of finite (n, 3) points among each point's own candidates: `table` (2, 3, W, n) their
    min and max corners, `ids` (W, n) their box indices in ascending order. The same arithmetic as
    `closest_all`, on (3, W, n) arrays."""
    w, n = ids.shape
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    pw = np.ascontiguousarray(p.T)[:, None]                           # (3, 1, n)
    gap = np.subtract(table[0], pw)
    np.maximum(gap, pw - table[1], out=gap)
    np.maximum(gap, 0.0, out=gap)
    np.multiply(gap, gap, out=gap)
    o2 = gap[0] + gap[1]
    o2 += gap[2]                                       # ((x + y) + z), as the full search sums
    at = o2.argmin(0) * n + np.arange(n)               # flat (candidate, point) of the nearest
    box = ids.take(at)
    d = np.sqrt(o2.take(at))
    off = d > 0.0
    ins = np.flatnonzero(~off)
    if len(ins):
        m = len(ins)
        o2, t, pw = o2.take(ins, 1), table.take(ins, 3), pw.take(ins, 2)
        d_in = np.minimum(pw - t[0], t[1] - pw).min(0)              # (W, m) depth below the nearest face
        dist = np.where(o2 > 0.0, np.sqrt(o2), np.maximum(d_in, 0.0))
        at = dist.argmin(0) * m + np.arange(m)
        box[ins], d[ins], off[ins] = ids.take(ins, 1).take(at), dist.take(at), o2.take(at) > 0.0
    return _finish(p, boxes.take(box, 0), d, off)
