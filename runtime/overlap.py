"""Poses that occupy the same space: two pallets cannot, so of two accepted poses that overlap the one of the
higher-scoring detection stays (reason "duplicate" for the other). Pure numpy.

The detector's NMS keeps boxes that overlap less than its IoU threshold: a box around a pallet's front face and one
around the whole pallet, or a weak box on part of a pallet already found (`weak_boxes.py`), can both be posed on the
same pallet. Their boxes differ, their poses do not.
"""
from __future__ import annotations

import numpy as np

__all__ = ["GRID", "overlap_fractions", "duplicate_of"]

GRID = 8   # sample points per side of a pose's bounding box (GRID**3 in all)


def _cell_centres(size_m: np.ndarray, grid: int) -> np.ndarray:
    """(grid**3, 3) the centres of a grid of cells filling a box of `size_m` (3,) centred at the origin."""
    t = (np.arange(grid) + 0.5) / grid - 0.5
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    return g * np.asarray(size_m, dtype=np.float64)


def overlap_fractions(T_cam_pallet: np.ndarray, sizes_m: np.ndarray, grid: int = GRID) -> np.ndarray:
    """The share of each pose's bounding box that lies inside each other pose's.

    :param T_cam_pallet: (n, 4, 4) poses (pallet frame: origin at the bounding box's centre). :param sizes_m: (n, 3)
        each pose's length, width, height, metres. :return: (n, n) entry [i, j]: the fraction of pose i's box
        inside pose j's (the diagonal is 1)."""
    T = np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    sizes = np.asarray(sizes_m, dtype=np.float64).reshape(-1, 3)
    n = len(T)
    if len(sizes) != n:
        raise ValueError(f"overlap_fractions: {n} poses but {len(sizes)} sizes")
    frac = np.eye(n)
    # only boxes whose bounding spheres meet can overlap: most frames have no such pair
    reach = np.linalg.norm(sizes, axis=1) / 2
    centres = T[:, :3, 3]
    near = np.linalg.norm(centres[:, None] - centres[None], axis=-1) < reach[:, None] + reach[None]
    np.fill_diagonal(near, False)
    a, b = np.nonzero(near)                             # ordered pairs: a's points in b's box
    if len(a):
        R, half_b = T[:, :3, :3], sizes[b] / 2
        R_ba = np.transpose(R[b], (0, 2, 1)) @ R[a]                                # pose a's frame -> pose b's
        t_ba = np.einsum("pji,pj->pi", R[b], centres[a] - centres[b])
        # a's unit grid scaled to its box, into b's frame, in units of b's half sizes: inside where |coordinates| <= 1
        M = sizes[a, :, None] * np.transpose(R_ba, (0, 2, 1)) / half_b[:, None, :]
        rel = np.abs(_cell_centres(np.ones(3), grid) @ M + (t_ba / half_b)[:, None]) <= 1
        frac[a, b] = (rel[..., 0] & rel[..., 1] & rel[..., 2]).mean(axis=1)
    return frac


def duplicate_of(T_cam_pallet: np.ndarray, sizes_m: np.ndarray, max_overlap: float = 0.5) -> np.ndarray:
    """For poses in order of preference (the detector's score, highest first): the earlier kept pose each one
    duplicates, or -1.

    A pose duplicates an earlier kept one where more than `max_overlap` of either's bounding box lies inside the
    other's. :param T_cam_pallet: (n, 4, 4). :param sizes_m: (n, 3). :return: (n,) int64 row indexes."""
    frac = overlap_fractions(T_cam_pallet, sizes_m)
    n = len(frac)
    out = np.full(n, -1, dtype=np.int64)
    kept: list[int] = []
    for i in range(n):
        hit = [j for j in kept if max(frac[i, j], frac[j, i]) > max_overlap]
        if hit:
            out[i] = hit[0]
        else:
            kept.append(i)
    return out
