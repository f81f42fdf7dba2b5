"""Pallet models built from their boards and blocks, with real dimensions.

Pallet frame (DESIGN.md): origin at the centre of the pallet's bounding box, x along its length,
y along its width, z up. Every part is an axis-aligned box given by its min/max corners in metres.

- ``epal``: EUR/EPAL 1 block pallet, 1200 x 800 x 144 mm (EN 13698-1): 5 top deck boards (22 mm thick;
  the two edge boards and the centre board 145 mm wide, the two others 100 mm) along the length,
  3 stringer (cross) boards 800 x 145 x 22 mm along the width, 9 blocks 78 mm high (the 3 on the
  centre line 145 x 145 mm, the 6 others 145 x 100 mm), 3 bottom boards (edges 100 mm, centre 145 mm).
- ``eur3``: 1200 x 1000 x 144 mm block pallet (EPAL 3 layout): 7 top deck boards along the 1200 mm
  side (edge boards 145 mm, inner boards 100 mm), otherwise as ``epal``.
- ``gma``: GMA 48 x 40 in stringer pallet (1219 x 1016 x 121 mm): 3 stringers 38 x 89 mm (1.5 x 3.5 in)
  along the 48 in length, each with two 229 x 38 mm (9 x 1.5 in) fork notches; 7 top deck boards and
  5 bottom deck boards 16 mm (5/8 in) thick across them (edge boards 140 mm, inner 89 mm).

Symmetries: all three are unchanged by a 180 degree turn about z (and by nothing else that is a
rotation: top and bottom decks differ, and length differs from width), so each has
{identity, Rz(180)}. `tests/test_sim_pallets.py` checks this numerically.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["PalletModel", "PALLET_MODELS", "get_pallet_model", "box_corners", "ROT_Z_180"]

ROT_Z_180 = np.diag([-1.0, -1.0, 1.0, 1.0])

# (8, 3) sign pattern of a box's corners, and the 12 triangles of its 6 faces (outward, CCW).
_CORNER_SIGNS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
_BOX_TRIANGLES = np.array([
    [0, 1, 3], [0, 3, 2],  # x = min
    [4, 6, 7], [4, 7, 5],  # x = max
    [0, 4, 5], [0, 5, 1],  # y = min
    [2, 3, 7], [2, 7, 6],  # y = max
    [0, 2, 6], [0, 6, 4],  # z = min
    [1, 5, 7], [1, 7, 3],  # z = max
], dtype=np.int64)


def box_corners(boxes_m: np.ndarray) -> np.ndarray:
    """Corners of axis-aligned boxes.

    :param boxes_m: (k, 2, 3) min/max corners.
    :return: (k, 8, 3) corners, ordered by (x, y, z) in {min, max} with z fastest.
    """
    boxes_m = np.asarray(boxes_m, dtype=np.float64)
    lo, hi = boxes_m[:, None, 0, :], boxes_m[:, None, 1, :]
    return lo + _CORNER_SIGNS[None] * (hi - lo)


def _box(center_xyz, size_xyz) -> np.ndarray:
    c = np.asarray(center_xyz, dtype=np.float64)
    h = np.asarray(size_xyz, dtype=np.float64) / 2
    return np.stack([c - h, c + h])


def _spread(total: float, widths: list[float]) -> list[float]:
    """Centres of boards of the given widths spread edge to edge over `total` with equal gaps."""
    gap = (total - sum(widths)) / (len(widths) - 1)
    centres, pos = [], -total / 2
    for w in widths:
        centres.append(pos + w / 2)
        pos += w + gap
    return centres


def _block_pallet(length: float, width: float, top_widths: list[float]) -> np.ndarray:
    """EPAL-style block pallet (mm in, metres out): top boards along x, stringer boards along y."""
    height = 144.0
    deck, block_h = 22.0, 78.0
    z_bottom = -height / 2 + deck / 2
    z_block = -height / 2 + deck + block_h / 2
    z_stringer = z_block + block_h / 2 + deck / 2
    z_top = height / 2 - deck / 2
    xs = [-(length / 2 - 72.5), 0.0, length / 2 - 72.5]          # 145 mm blocks flush with the ends
    ys = [-(width / 2 - 50.0), 0.0, width / 2 - 50.0]            # 100 mm blocks flush with the sides
    parts = []
    for y, w in zip(_spread(width, top_widths), top_widths):
        parts.append(_box((0, y, z_top), (length, w, deck)))
    for x in xs:
        parts.append(_box((x, 0, z_stringer), (145.0, width, deck)))
    for x in xs:
        for y in ys:
            parts.append(_box((x, y, z_block), (145.0, 145.0 if y == 0 else 100.0, block_h)))
    for y in ys:
        parts.append(_box((0, y, z_bottom), (length, 145.0 if y == 0 else 100.0, deck)))
    return np.stack(parts) / 1000.0


def _gma_pallet() -> np.ndarray:
    """GMA 48 x 40 in stringer pallet (mm in, metres out): stringers along x, deck boards along y."""
    length, width = 1219.0, 1016.0
    deck, s_w, s_h = 16.0, 38.0, 89.0
    notch_len, notch_h = 229.0, 38.0
    height = deck + s_h + deck
    z_top = height / 2 - deck / 2
    z_bottom = -height / 2 + deck / 2
    s_z0 = -height / 2 + deck                        # stringer bottom
    parts = []
    top = [140.0] + [89.0] * 5 + [140.0]
    bottom = [140.0] + [89.0] * 3 + [140.0]
    for x, w in zip(_spread(length, top), top):
        parts.append(_box((x, 0, z_top), (w, width, deck)))
    for x, w in zip(_spread(length, bottom), bottom):
        parts.append(_box((x, 0, z_bottom), (w, width, deck)))
    # Notch centres at +-length/4: the stringer is a full-length upper part plus three lower feet.
    notch_x = [-length / 4, length / 4]
    feet = [(-length / 2, notch_x[0] - notch_len / 2), (notch_x[0] + notch_len / 2, notch_x[1] - notch_len / 2),
            (notch_x[1] + notch_len / 2, length / 2)]
    for y in (-(width / 2 - s_w / 2), 0.0, width / 2 - s_w / 2):
        parts.append(np.array([[-length / 2, y - s_w / 2, s_z0 + notch_h], [length / 2, y + s_w / 2, s_z0 + s_h]]))
        for x0, x1 in feet:
            parts.append(np.array([[x0, y - s_w / 2, s_z0], [x1, y + s_w / 2, s_z0 + notch_h]]))
    return np.stack(parts) / 1000.0


@dataclass(frozen=True)
class PalletModel:
    """A pallet as a union of axis-aligned boxes in its own frame (metres)."""

    name: str
    boxes_m: np.ndarray                        # (k, 2, 3) min/max corners of each board/block
    size_m: np.ndarray = field(init=False)     # (3,) length (x), width (y), height (z)
    symmetries: np.ndarray = field(default_factory=lambda: np.eye(4)[None])  # (S, 4, 4), identity first
    diameter_m: float = field(init=False)

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes_m, dtype=np.float64)
        if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0:
            raise ValueError(f"pallet {self.name!r}: boxes_m must be (k, 2, 3) with k >= 1, got {boxes.shape}")
        if np.any(boxes[:, 1] <= boxes[:, 0]):
            raise ValueError(f"pallet {self.name!r}: every box needs max > min on each axis")
        sym = np.asarray(self.symmetries, dtype=np.float64)
        if sym.ndim != 3 or sym.shape[1:] != (4, 4) or not np.allclose(sym[0], np.eye(4)):
            raise ValueError(f"pallet {self.name!r}: symmetries must be (S, 4, 4) with the identity first")
        lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
        if not np.allclose((lo + hi) / 2, 0, atol=1e-9):
            raise ValueError(f"pallet {self.name!r}: the origin must be the bounding-box centre, got {(lo + hi) / 2}")
        corners = box_corners(boxes).reshape(-1, 3)
        # The convex hull of a union of boxes has box corners as vertices: max pairwise corner distance is exact.
        d = np.sqrt(((corners[:, None] - corners[None]) ** 2).sum(-1)).max()
        for name, value in (("boxes_m", boxes), ("symmetries", sym), ("size_m", hi - lo)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "diameter_m", float(d))

    def distance_m(self, pts: np.ndarray) -> np.ndarray:
        """Unsigned distance from points to the solid pallet (0 inside or on it).

        :param pts: (n, 3) pallet-frame points, metres.
        :return: (n,) distances in metres.
        """
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        lo, hi = self.boxes_m[None, :, 0], self.boxes_m[None, :, 1]
        gap = np.maximum(np.maximum(lo - pts[:, None], pts[:, None] - hi), 0.0)   # (n, k, 3)
        return np.sqrt((gap ** 2).sum(-1)).min(1)

    def surface_distance_m(self, pts: np.ndarray) -> np.ndarray:
        """Unsigned distance from points to the pallet's surface, from outside or inside the wood.

        :param pts: (n, 3) pallet-frame points, metres.
        :return: (n,) distances in metres (0 on the surface).
        """
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        lo, hi = self.boxes_m[None, :, 0], self.boxes_m[None, :, 1]
        depth_in = np.minimum(pts[:, None] - lo, hi - pts[:, None]).min(-1).max(1)   # > 0: inside some part
        return np.where(depth_in > 0, depth_in, self.distance_m(pts))

    def surface_points(self, n: int = 2000, seed: int = 0) -> np.ndarray:
        """Points spread uniformly (by area) over the pallet's outer surface.

        Faces where two parts touch (a block under a board) are not surface: samples inside another
        part are rejected.

        :return: (n, 3) float32 pallet-frame points, metres.
        """
        if n <= 0:
            raise ValueError(f"n must be positive, got {n}")
        rng = np.random.default_rng(seed)
        boxes = self.boxes_m
        ext = boxes[:, 1] - boxes[:, 0]                       # (k, 3)
        # 6 faces per box: face f has normal axis f // 2 at min (even) or max (odd).
        face_area = np.repeat(np.stack([ext[:, 1] * ext[:, 2], ext[:, 0] * ext[:, 2], ext[:, 0] * ext[:, 1]], 1), 2, 1)
        prob = (face_area / face_area.sum()).ravel()
        out: list[np.ndarray] = []
        have = 0
        while have < n:
            m = 2 * (n - have) + 64
            pick = rng.choice(prob.size, size=m, p=prob)
            b, f = pick // 6, pick % 6
            axis, side = f // 2, f % 2
            pts = boxes[b, 0] + rng.random((m, 3)) * ext[b]
            pts[np.arange(m), axis] = boxes[b, side, axis]
            inside = np.zeros(m, dtype=bool)
            for j in range(len(boxes)):
                strictly = np.all((pts > boxes[j, 0] - 1e-9) & (pts < boxes[j, 1] + 1e-9), axis=1) & (b != j)
                inside |= strictly
            keep = pts[~inside]
            out.append(keep)
            have += len(keep)
        return np.concatenate(out)[:n].astype(np.float32)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of all parts: (8k, 3) vertices in metres and (12k, 3) int faces."""
        verts = box_corners(self.boxes_m).reshape(-1, 3)
        faces = (_BOX_TRIANGLES[None] + 8 * np.arange(len(self.boxes_m))[:, None, None]).reshape(-1, 3)
        return verts, faces

    def write_ply(self, path) -> None:
        """Write the triangle mesh as a binary little-endian PLY in millimetres (BOP convention)."""
        verts, faces = self.mesh()
        header = ("ply\nformat binary_little_endian 1.0\n"
                  f"comment pallet6d pallet model {self.name}, millimetres\n"
                  f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
                  f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
        body = bytearray((verts * 1000.0).astype("<f4").tobytes())
        face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        face_rec["n"] = 3
        face_rec["i"] = faces
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(bytes(body))
            fh.write(face_rec.tobytes())


_SYM_Z180 = np.stack([np.eye(4), ROT_Z_180])

_BUILDERS = {
    "epal": lambda: _block_pallet(1200.0, 800.0, [145.0, 100.0, 145.0, 100.0, 145.0]),
    "gma": _gma_pallet,
    "eur3": lambda: _block_pallet(1200.0, 1000.0, [145.0] + [100.0] * 5 + [145.0]),
}

PALLET_MODELS: tuple[str, ...] = tuple(_BUILDERS)
_CACHE: dict[str, PalletModel] = {}


def get_pallet_model(name: str = "epal") -> PalletModel:
    """The pallet model called `name` (one of PALLET_MODELS)."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown pallet model {name!r}; known models: {', '.join(PALLET_MODELS)}")
    if name not in _CACHE:  # immutable, so sharing one instance is safe
        _CACHE[name] = PalletModel(name=name, boxes_m=_BUILDERS[name](), symmetries=_SYM_Z180)
    return _CACHE[name]

