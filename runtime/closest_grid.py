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


def _take(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Rows `idx` of `a` (numpy's `take`: many times faster than fancy indexing of rows of a few values)."""
    return a.take(idx, 0)


def _put(dst: np.ndarray, idx: np.ndarray, src: np.ndarray) -> None:
    """dst[idx] = src for (n, c) dst, one column at a time (fast 1-d scatters)."""
    for c in range(dst.shape[1]):
        dst[:, c][idx] = src[:, c]


def _outside_result(p: np.ndarray, d: np.ndarray, lo_j: np.ndarray,
                    hi_j: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point and normal on the chosen boxes (n, 3) at outside distances d (n,); normal 0 where d is 0."""
    q = np.clip(p, lo_j, hi_j)
    normal = np.zeros((len(p), 3))
    out = d > 0.0
    np.divide(p - q, d[:, None], out=normal, where=out[:, None])
    return q, normal, out


def _inside_result(pi: np.ndarray, di: np.ndarray, via_out: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
                   argmin_rows=lambda v: v.argmin(1)) -> tuple[np.ndarray, np.ndarray]:
    """Closest point and normal of points inside some box, on their chosen boxes (m, 3): at the outside
    distance di where `via_out`, else on the chosen box's nearest face (the first of equals, -x -y -z +x +y +z,
    by `argmin_rows`)."""
    qi = np.clip(pi, blo, bhi)
    ni = np.zeros((len(pi), 3))
    out = np.flatnonzero(via_out)
    _put(ni, out, (_take(pi, out) - _take(qi, out)) / di[out, None])
    face = np.flatnonzero(~via_out)                               # move to the nearest face
    pf, lf, hf = _take(pi, face), _take(blo, face), _take(bhi, face)
    to_face = np.concatenate([pf - lf, hf - pf], axis=1)          # -x -y -z +x +y +z
    f = argmin_rows(to_face)
    axis, positive = f % 3, f >= 3
    at = face * 3 + axis                                          # flat index of (face, axis)
    qi.reshape(-1)[at] = np.where(positive, hf.reshape(-1)[np.arange(len(face)) * 3 + axis],
                                  lf.reshape(-1)[np.arange(len(face)) * 3 + axis])
    ni.reshape(-1)[at] = np.where(positive, 1.0, -1.0)
    return qi, ni


def closest_all(p: np.ndarray, boxes: np.ndarray,
                extents: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on the surface of (k, 2, 3) boxes for (n, 3) float64 points, testing every box.

    :param extents: the boxes' `box_extents`.
    :return: (closest (n, 3), unit outward normal (n, 3), distance (n,)), metres.
    """
    n = len(p)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    lo, hi = boxes[:, 0], boxes[:, 1]                           # (k, 3)
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
        d_out2 += gap[box_col]
    j = d_out2.argmin(0)                                     # nearest box per point
    d = np.sqrt(d_out2[j, np.arange(n)])
    q, normal, out = _outside_result(p, d, _take(lo, j), _take(hi, j))
    ins = np.flatnonzero(~out)
    if len(ins) == 0:
        return q, normal, d
    # inside a box: its nearest face is a candidate at the depth below it, every box the point is outside
    # of at its outside distance (boxes may overlap); the nearest wins
    o2 = d_out2[:, ins]
    d_in = np.full(o2.shape, np.inf)                              # (k, m) depth below each box's nearest face
    for a, (extent, box_col) in enumerate(extents):
        pa = p_axes[a, ins]
        below = np.minimum(pa - extent[:, 0, None], extent[:, 1, None] - pa)
        np.minimum(d_in, below[box_col], out=d_in)
    dist = np.where(o2 > 0.0, np.sqrt(o2), np.maximum(d_in, 0.0))
    ji = dist.argmin(0)
    r = np.arange(len(ins))
    qi, ni = _inside_result(_take(p, ins), dist[ji, r], o2[ji, r] > 0.0, _take(lo, ji), _take(hi, ji))
    _put(q, ins, qi)
    _put(normal, ins, ni)
    d[ins] = dist[ji, r]
    return q, normal, d


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

    Cells are grouped by how many candidates they keep (1, 2, up to 4, more), each group's candidates padded by
    repeating its last box (argmin keeps the first of equals): a point is tested against its group's width.

    :param boxes_m: (k, 2, 3) min/max corners, metres. :param margin_m: the grid reaches this far beyond the
        boxes' bounding box (ICP's largest correspondence distance). :param cell_m: cell edge, metres.
    """

    _GROW_M = 1e-7
    _WIDTHS = (1, 2, 4)

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
        widths = self._WIDTHS + (max(int(count.max()), self._WIDTHS[-1] + 1),)
        group = np.searchsorted(widths, count)                            # smallest width that holds each set
        self.widths = widths
        self.group = np.zeros(len(lists), dtype=np.int8)
        self.pos = np.zeros(len(lists), dtype=np.int64)
        self.ids, self.tables = [], []                                   # per group: (R, W) boxes, (R, 6, W)
        for g, w in enumerate(widths):
            rows = np.flatnonzero(group == g)
            self.group[rows], self.pos[rows] = g, np.arange(len(rows))
            ids = np.zeros((len(rows), w), dtype=np.int64)
            for i, row in enumerate(rows):
                b = np.flatnonzero(lists[row])
                ids[i] = np.concatenate([b, np.full(w - len(b), b[-1])])
            self.ids.append(ids)
            # per candidate: min x y z, max x y z, laid out (R, 6, W) so that each is a (points, W) slice
            self.tables.append(np.ascontiguousarray(boxes[ids].reshape(len(rows), w, 6).transpose(0, 2, 1)))
        flat = cell_list.reshape(-1)
        small = np.int16 if len(lists) < np.iinfo(np.int16).max else np.int32
        self.cell_group = self.group[flat]                                # (cells,) int8
        self.cell_pos = self.pos[flat].astype(small)                      # (cells,)
        self.max_candidates = int(count.max())

    @property
    def nbytes(self) -> int:
        """Memory the index holds, bytes."""
        return int(self.cell_group.nbytes + self.cell_pos.nbytes + sum(t.nbytes for t in self.tables)
                   + sum(i.nbytes for i in self.ids))

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
        n = len(p)
        if n == 0:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        u = p - self.origin
        u /= self.cell_m                                              # position in cells
        inside = np.all((u >= 0.0) & (u < self.shape), axis=1)
        if not inside.all():
            q, normal, d = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
            for sel, fn in ((np.flatnonzero(~inside), lambda x: closest_all(x, self.boxes, self.extents)),
                            (np.flatnonzero(inside), self.closest)):
                if len(sel):
                    qs, ns, d[sel] = fn(_take(p, sel))
                    _put(q, sel, qs)
                    _put(normal, sel, ns)
            return q, normal, d
        ijk = u.astype(np.int64)                                      # u >= 0: truncation is floor
        cell = (ijk[:, 0] * self.shape[1] + ijk[:, 1]) * self.shape[2] + ijk[:, 2]
        group, pos = self.cell_group[cell], self.cell_pos[cell]
        q, normal, d = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
        for g in range(len(self.widths)):
            sel = np.flatnonzero(group == g)
            if len(sel) == n:
                return _closest_among(p, _take(self.tables[g], pos), _take(self.ids[g], pos), self.boxes)
            if len(sel):
                rows = pos[sel]
                qs, ns, d[sel] = _closest_among(_take(p, sel), _take(self.tables[g], rows),
                                                _take(self.ids[g], rows), self.boxes)
                _put(q, sel, qs)
                _put(normal, sel, ns)
        return q, normal, d


def _argmin_rows(v: np.ndarray) -> np.ndarray:
    """(n,) index of the first least value of each row of finite (n, W), as `argmin(1)`."""
    j = np.zeros(len(v), dtype=np.int64)
    if v.shape[1] == 1:
        return j
    best = v[:, 0].copy()
    for c in range(1, v.shape[1]):
        less = v[:, c] < best
        j[less] = c
        np.minimum(best, v[:, c], out=best)
    return j


def _pick(v: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(n,) v[r, j[r]] of (n, W) v."""
    if v.shape[1] == 1:
        return v[:, 0].copy()
    return v.reshape(-1)[np.arange(len(v)) * v.shape[1] + j]


def _closest_among(p: np.ndarray, table: np.ndarray, ids: np.ndarray,
                   boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`closest_all` of finite (n, 3) points among each point's own candidates: `table` (n, 6, W) their min
    x y z, max x y z, `ids` (n, W) their box indices in ascending order. The same arithmetic as `closest_all`."""
    o2 = None
    for a in range(3):
        pa = p[:, a, None]
        gap = np.subtract(table[:, a], pa)
        np.maximum(gap, pa - table[:, 3 + a], out=gap)
        np.maximum(gap, 0.0, out=gap)
        np.multiply(gap, gap, out=gap)
        o2 = gap if o2 is None else o2 + gap           # ((x + y) + z), as the full search sums
    j = _argmin_rows(o2)
    box = _pick(ids, j)
    d = np.sqrt(_pick(o2, j))
    lo, hi = boxes[:, 0], boxes[:, 1]
    q, normal, out = _outside_result(p, d, _take(lo, box), _take(hi, box))
    ins = np.flatnonzero(~out)
    if len(ins) == 0:
        return q, normal, d
    o2, t, pi = _take(o2, ins), _take(table, ins), _take(p, ins)
    d_in = np.full(o2.shape, np.inf)
    for a in range(3):
        pa = pi[:, a, None]
        np.minimum(d_in, np.minimum(pa - t[:, a], t[:, 3 + a] - pa), out=d_in)
    dist = np.where(o2 > 0.0, np.sqrt(o2), np.maximum(d_in, 0.0))
    ji = _argmin_rows(dist)
    bi = _pick(_take(ids, ins), ji)
    di = _pick(dist, ji)
    qi, ni = _inside_result(pi, di, _pick(o2, ji) > 0.0, _take(lo, bi), _take(hi, bi), _argmin_rows)
    _put(q, ins, qi)
    _put(normal, ins, ni)
    d[ins] = di
    return q, normal, d
