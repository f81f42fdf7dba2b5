"""Pallet-type geometry a bundle carries besides its model points: fork pockets, ICP starts, symmetry checks.

Pallet frame: origin at the centre of the pallet's bounding box, x along its length, y along its width,
z up, metres. Pure numpy functions.
"""
from __future__ import annotations

import numpy as np

__all__ = ["FACES", "check_rigid", "asymmetric", "default_refine_starts", "derive_pockets_m"]

# the faces forks can enter through: the face whose outward normal is that axis
FACES = ("+x", "-x", "+y", "-y")
# the pallet the default ICP starts are tuned for (EUR/EPAL 1, length x width, metres)
_STARTS_TUNED_FOR_M = (1.2, 0.8)
# an opening narrower or lower than this is a gap between boards, not a fork pocket
_MIN_POCKET_WIDTH_M = 0.05
_MIN_POCKET_HEIGHT_M = 0.03


def check_rigid(T: np.ndarray, atol: float = 1e-6) -> list[int]:
    """Indexes of the transforms in `T` (S, 4, 4) that are not rigid (rotation with det +1, last row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    finite = np.isfinite(T).all(axis=(1, 2))
    T = np.where(finite[:, None, None], T, 0.0)
    R = T[:, :3, :3]
    ortho = np.abs(np.einsum("sji,sjk->sik", R, R) - np.eye(3)).max(axis=(1, 2)) <= atol
    det = np.abs(np.linalg.det(R) - 1.0) <= atol
    last = np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) <= atol
    return [int(i) for i in np.flatnonzero(~(finite & ortho & det & last))]


def asymmetric(T: np.ndarray, boxes_m: np.ndarray, atol: float = 1e-5) -> list[int]:
    """Indexes of the rigid transforms in `T` (S, 4, 4) that do not map the pallet's boxes onto themselves.

    Only transforms whose rotation permutes the axes (with signs: turns by multiples of 90 degrees) map boxes
    to boxes; others are not judged here.

    :param boxes_m: (k, 2, 3) min/max corners, pallet frame, metres.
    """
    boxes_m = np.asarray(boxes_m, dtype=np.float64)
    key = lambda b: np.round(b.reshape(len(b), 6) / atol).astype(np.int64)  # noqa: E731
    want = {tuple(r) for r in key(boxes_m)}
    bad = []
    for i, t in enumerate(np.asarray(T, dtype=np.float64)):
        R = t[:3, :3]
        if not np.allclose(np.abs(R).sum(0), 1.0) or not np.allclose(np.abs(R).max(0), 1.0):
            continue
        corners = boxes_m @ R.T + t[:3, 3]                                # (k, 2, 3)
        moved = np.stack([corners.min(1), corners.max(1)], axis=1)
        if {tuple(r) for r in key(moved)} != want:
            bad.append(i)
    return bad


def default_refine_starts(size_m) -> np.ndarray:
    """The runtime's default ICP starts (`refine.start_offsets`, tuned on EUR/EPAL 1200 x 800) with the
    slides scaled to a pallet of `size_m` (length, width, height).

    :return: (S, 3) rows of (yaw_deg, dx_m, dy_m).
    """
    from .refine import MAX_STARTS, default_starts

    rows = default_starts(MAX_STARTS)
    rows[:, 1:] *= np.asarray(size_m, dtype=np.float64)[:2] / np.asarray(_STARTS_TUNED_FOR_M)
    return rows


def _free_runs(occupied: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [i, j) of False in a 1-D bool array."""
    runs, start = [], None
    for i, occ in enumerate(list(occupied) + [True]):
        if not occ and start is None:
            start = i
        elif occ and start is not None:
            runs.append((start, i))
            start = None
    return runs


def _openings(boxes_m: np.ndarray, axis: int) -> list[tuple[float, float, float, float]]:
    """Openings that run through the whole pallet along `axis` (0 = x, 1 = y), between material on both sides
    and under material above: (u_min, u_max, z_min, z_max), u the other horizontal axis.

    The face is cut into cells at every box edge; a cell is free when no box covers it (a fork passes
    through the whole depth there). Candidates are the free rectangles of cells that cannot grow in any
    direction, are not open to either side of the face and have material above; of overlapping candidates
    the widest is the opening (a notch over a bottom board, not the deeper part beside the board).
    """
    u_ax = 1 - axis
    lo, hi = boxes_m[:, 0], boxes_m[:, 1]
    ue = np.unique(np.round(np.concatenate([lo[:, u_ax], hi[:, u_ax]]), 9))
    ze = np.unique(np.round(np.concatenate([lo[:, 2], hi[:, 2]]), 9))
    uc, zc = (ue[:-1] + ue[1:]) / 2, (ze[:-1] + ze[1:]) / 2
    covers = ((lo[:, None, None, u_ax] < uc[None, :, None]) & (uc[None, :, None] < hi[:, None, None, u_ax])
              & (lo[:, None, None, 2] < zc[None, None, :]) & (zc[None, None, :] < hi[:, None, None, 2]))
    blocked = covers.any(0)                                               # (nu, nz)
    nu, nz = blocked.shape
    candidates = []
    for zb in range(nz):
        for zt in range(zb + 1, nz):                                      # rows [zb, zt), material row zt
            for i, j in _free_runs(blocked[:, zb:zt].any(1)):             # columns [i, j) free over the rows
                grows_down = zb > 0 and not blocked[i:j, zb - 1].any()
                if grows_down or not blocked[i:j, zt].any() or i == 0 or j == nu:
                    continue
                rect = (ue[i], ue[j], ze[zb], ze[zt])
                if rect[1] - rect[0] >= _MIN_POCKET_WIDTH_M and rect[3] - rect[2] >= _MIN_POCKET_HEIGHT_M:
                    candidates.append(rect)
    candidates.sort(key=lambda r: (r[1] - r[0], r[3] - r[2]), reverse=True)
    out: list[tuple[float, float, float, float]] = []
    for r in candidates:
        if all(r[1] <= o[0] or o[1] <= r[0] or r[3] <= o[2] or o[3] <= r[2] for o in out):
            out.append(r)
    return sorted(out)


def derive_pockets_m(boxes_m: np.ndarray) -> dict[str, np.ndarray]:
    """The fork pockets a pallet's boards and blocks leave open, for faces with exactly two openings.

    An opening is a rectangle of the face, free of material through the whole depth of the pallet, with
    material above it and on both sides; where openings overlap (a notch over a gap between bottom boards), the
    widest one.

    :param boxes_m: (k, 2, 3) min/max corners of the parts, pallet frame, metres.
    :return: face -> (2, 2, 3) min/max corners of its two openings, left then right seen from outside the
        face (on +x: -y first; on -x: +y first; on +y: +x first; on -y: -x first).
    """
    boxes_m = np.asarray(boxes_m, dtype=np.float64)
    if boxes_m.ndim != 3 or boxes_m.shape[1:] != (2, 3) or len(boxes_m) == 0:
        raise ValueError(f"boxes_m must be (k, 2, 3), got shape {boxes_m.shape}")
    lo, hi = boxes_m[:, 0].min(0), boxes_m[:, 1].max(0)
    pockets: dict[str, np.ndarray] = {}
    for axis, (plus, minus) in enumerate((("+x", "-x"), ("+y", "-y"))):
        rects = _openings(boxes_m, axis)
        if len(rects) != 2:
            continue
        corners = []
        for u0, u1, z0, z1 in rects:
            box = np.array([lo, hi])
            box[:, 1 - axis] = u0, u1
            box[:, 2] = z0, z1
            corners.append(box)
        ascending = np.stack(corners)                    # ordered by u
        # seen from outside +x, left is -y; from outside +y, left is +x
        pockets[plus] = ascending if axis == 0 else ascending[::-1]
        pockets[minus] = ascending[::-1] if axis == 0 else ascending
    return {face: pockets[face] for face in FACES if face in pockets}
