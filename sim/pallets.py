"""The pallet catalogue: every type built from its real boards, blocks, runners and legs.

Pallet frame (DESIGN.md): origin at the centre of the pallet's bounding box, x along its length,
y along its width, z up. Every part is an axis-aligned box given by its min/max corners in metres.

Wooden types (outer sizes, board and block counts from the EPAL product sheets at epal-pallets.org and
EN 13698-1 / -2; GMA from the GMA/NWPCA 48 x 40 specification):
- ``epal``: EUR/EPAL 1, 1200 x 800 x 144 mm (EN 13698-1): 5 top deck boards (22 mm thick; the two edge
  boards and the centre board 145 mm wide, the two others 100 mm) along the length, 3 stringer (cross)
  boards 800 x 145 x 22 mm along the width, 9 blocks 78 mm high (the 3 on the centre line 145 x 145 mm,
  the 6 others 145 x 100 mm), 3 bottom boards (edges 100 mm, centre 145 mm).
- ``eur3``: EUR/EPAL 3, 1000 x 1200 x 144 mm: 7 top deck boards along the 1200 mm side (edge boards
  145 mm, inner boards 100 mm), otherwise as ``epal`` (the FIN pallet has the same layout).
- ``eur2``: EUR/EPAL 2, 1200 x 1000 x 162 mm: 7 top boards along the 1200 mm side, 3 cross boards,
  9 blocks 96 mm high (the taller blocks give the 162 mm height), 3 bottom boards along the length.
- ``eur6``: EUR/EPAL 6 half pallet, 800 x 600 x 144 mm: 21 mm boards (EPAL: seven top boards, three
  cross boards, three bottom skids), 9 blocks 81 mm high (100 x 90 mm, centre row 100 x 100 mm).
- ``gma``: GMA 48 x 40 in stringer pallet (1219 x 1016 x 121 mm): 3 stringers 38 x 89 mm (1.5 x 3.5 in)
  along the 48 in length, each with two 229 x 38 mm (9 x 1.5 in) fork notches; 7 top deck boards and
  5 bottom deck boards 16 mm (5/8 in) thick across them (edge boards 140 mm, inner 89 mm).
- ``block_1210``: 1200 x 1000 x 150 mm block pallet as pooled by CHEP (B1210: 1200 x 1000 x 150 mm,
  four-way, perimeter base): 7 top boards, 3 cross boards, 9 blocks 84 mm high, a perimeter base of
  3 bottom boards along the length and 2 across the ends (forks enter above the base on every side).
  Its blue paint is appearance, not geometry.

Plastic types (typical manufacturers' datasheets for EUR-footprint plastic pallets):
- ``plastic_9leg``: 1200 x 800 x 150 mm nestable pallet: a 30 mm deck on 9 legs 120 mm high
  (140 x 120 mm, centre row 140 x 140 mm), no bottom, so forks and pallet jacks enter from the floor.
- ``plastic_3runner`` (1200 x 800) and ``plastic_3runner_1210`` (1200 x 1000), 150 mm high: an open
  deck of 25 mm slats on 9 blocks 100 mm high, 3 runners 25 mm thick along the length.
- ``plastic_closed`` (1200 x 800) and ``plastic_closed_1210`` (1200 x 1000), 160 mm high: a closed 35 mm
  deck on 9 blocks 100 mm high and a perimeter base of 25 mm runners (hygienic pallets).

Symmetries: every type is unchanged by a 180 degree turn about z and by no other rotation (top and bottom
differ, and length differs from width), so each has {identity, Rz(180)}; `tests/test_sim_pallets.py`
checks this numerically. `pockets_m` and `refine_starts` follow INTERFACES.md section 1. Colour, wear,
dirt and missing boards are variants of a type, drawn by the scene builder: the ground-truth model of a
pallet with a missing board stays its type's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pallet6d.runtime.pallet_geometry import default_refine_starts

__all__ = ["PalletModel", "PALLET_MODELS", "FACES", "get_pallet_model", "box_corners", "face_normal",
           "refine_starts_for", "ROT_Z_180"]

ROT_Z_180 = np.diag([-1.0, -1.0, 1.0, 1.0])
FACES: tuple[str, ...] = ("+x", "-x", "+y", "-y")

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


def _layered_pallet(length: float, width: float, *, top: list[float] | None, t_top: float, t_cross: float,
                    block_h: float, block_x: float, block_y: tuple[float, float], bottom: str,
                    t_bottom: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A pallet on a 3 x 3 grid of blocks or legs (mm in, metres out), and its fork openings.

    Layers from the floor: the base (`bottom`: "boards" = 3 boards/runners along x under the block rows,
    "perimeter" = those plus end boards across the ends between them, "none" = legs on the floor), the
    blocks, 3 cross boards along y over the block columns (`t_cross` > 0), the top deck (`top`: board
    widths along x spread over the width, or None for a closed plate).

    :param block_x: block size along x. :param block_y: (outer rows, centre row) block sizes along y.
    :return: (k, 2, 3) boxes and {face: (2, 2, 3) pocket boxes} in metres.
    """
    if bottom not in ("boards", "perimeter", "none") or (bottom == "none") != (t_bottom == 0):
        raise ValueError(f"bottom must be 'boards' or 'perimeter' with t_bottom > 0, or 'none', got {bottom!r}")
    by_outer, by_centre = block_y
    height = t_bottom + block_h + t_cross + t_top
    z_bottom = -height / 2 + t_bottom / 2
    z_block = -height / 2 + t_bottom + block_h / 2
    z_cross = z_block + block_h / 2 + t_cross / 2
    z_top = height / 2 - t_top / 2
    xs = [-(length / 2 - block_x / 2), 0.0, length / 2 - block_x / 2]      # blocks flush with the ends
    ys = [-(width / 2 - by_outer / 2), 0.0, width / 2 - by_outer / 2]      # ... and with the sides
    parts = []
    if top is None:
        parts.append(_box((0, 0, z_top), (length, width, t_top)))
    else:
        for y, w in zip(_spread(width, top), top):
            parts.append(_box((0, y, z_top), (length, w, t_top)))
    if t_cross > 0:
        for x in xs:
            parts.append(_box((x, 0, z_cross), (block_x, width, t_cross)))
    for x in xs:
        for y in ys:
            parts.append(_box((x, y, z_block), (block_x, by_centre if y == 0 else by_outer, block_h)))
    if bottom != "none":
        for y in ys:
            parts.append(_box((0, y, z_bottom), (length, by_centre if y == 0 else by_outer, t_bottom)))
    if bottom == "perimeter":   # end boards between the long bottom boards
        gap = (width / 2 - by_outer) - by_centre / 2
        for x in (xs[0], xs[2]):
            for y in (-(by_centre / 2 + gap / 2), by_centre / 2 + gap / 2):
                parts.append(_box((x, y, z_bottom), (block_x, gap, t_bottom)))
    z_floor, z_base = -height / 2, -height / 2 + t_bottom
    z_block_top = z_base + block_h
    # Through the ends (+-x): between the block rows, from the floor (or the perimeter base) to the cross boards.
    z0 = z_base if bottom == "perimeter" else z_floor
    ends = [[-width / 2 + by_outer, -by_centre / 2], [by_centre / 2, width / 2 - by_outer]]
    # Through the sides (+-y): between the block columns, above the base, up to the top deck.
    sides = [[-length / 2 + block_x, -block_x / 2], [block_x / 2, length / 2 - block_x]]
    pockets = _pockets(length, width, ends, (z0, z_block_top), sides, (z_base, z_block_top + t_cross))
    return np.stack(parts) / 1000.0, pockets


def _pockets(length: float, width: float, y_spans, z_ends: tuple[float, float], x_spans,
             z_sides: tuple[float, float]) -> dict[str, np.ndarray]:
    """{face: (2, 2, 3)} pocket boxes in metres (mm in), each through the whole pallet, left then right as
    seen from outside the face. `y_spans`/`z_ends`: the openings of the +-x faces; `x_spans`/`z_sides`: of
    the +-y faces (None: that face has none)."""
    out = {}
    for face, spans, zz, depth_axis in (("+x", y_spans, z_ends, 0), ("-x", y_spans, z_ends, 0),
                                         ("+y", x_spans, z_sides, 1), ("-y", x_spans, z_sides, 1)):
        if spans is None:
            continue
        boxes = []
        for lo, hi in spans:
            box = np.zeros((2, 3))
            box[:, depth_axis] = [-length / 2, length / 2] if depth_axis == 0 else [-width / 2, width / 2]
            box[:, 1 - depth_axis] = [lo, hi]
            box[:, 2] = zz
            boxes.append(box)
        # Left as seen from outside: larger coordinate along (outward normal x z).
        left_axis = np.cross(_FACE_NORMALS[face], [0.0, 0.0, 1.0])
        key = [float(left_axis @ bx.mean(0)) for bx in boxes]
        order = np.argsort(key)[::-1]
        out[face] = np.stack([boxes[i] for i in order]) / 1000.0
    return out


def _gma_pallet() -> tuple[np.ndarray, dict[str, np.ndarray]]:
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
    # Ends: between the stringers, deck to deck. Sides: only through the notches, the whole width.
    pockets = _pockets(length, width, [[-width / 2 + s_w, -s_w / 2], [s_w / 2, width / 2 - s_w]],
                       (s_z0, s_z0 + s_h), [[x - notch_len / 2, x + notch_len / 2] for x in notch_x],
                       (s_z0, s_z0 + notch_h))
    return np.stack(parts) / 1000.0, pockets


_FACE_NORMALS = {"+x": np.array([1.0, 0, 0]), "-x": np.array([-1.0, 0, 0]),
                 "+y": np.array([0, 1.0, 0]), "-y": np.array([0, -1.0, 0])}


@dataclass(frozen=True)
class PalletModel:
    """A pallet as a union of axis-aligned boxes in its own frame (metres)."""

    name: str
    boxes_m: np.ndarray                        # (k, 2, 3) min/max corners of each board/block
    size_m: np.ndarray = field(init=False)     # (3,) length (x), width (y), height (z)
    symmetries: np.ndarray = field(default_factory=lambda: np.eye(4)[None])  # (S, 4, 4), identity first
    diameter_m: float = field(init=False)
    # face ("+x", "-x", "+y", "-y") -> (2, 2, 3) min/max corners of its two fork openings, left then right
    # as seen from outside the face, each through the whole pallet; faces without openings are absent
    pockets_m: dict = field(default_factory=dict)
    refine_starts: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (S, 3) yaw_deg, dx_m, dy_m
    obj_id: int = 0                            # stable BOP object id (0: not in the catalogue)
    material: str = "wood"                     # "wood" or "plastic": what the scene builder dresses it in

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
        pockets = {}
        for face, pk in dict(self.pockets_m).items():
            pk = np.asarray(pk, dtype=np.float64)
            if face not in FACES or pk.shape != (2, 2, 3) or np.any(pk[:, 1] <= pk[:, 0]):
                raise ValueError(f"pallet {self.name!r}: pockets_m[{face!r}] must be a face of {FACES} with "
                                 f"(2, 2, 3) min/max boxes, got shape {pk.shape}")
            if np.any(pk[:, 0] < lo - 1e-9) or np.any(pk[:, 1] > hi + 1e-9):
                raise ValueError(f"pallet {self.name!r}: pockets_m[{face!r}] reaches outside the bounding box")
            pk.setflags(write=False)
            pockets[face] = pk
        starts = np.asarray(self.refine_starts, dtype=np.float64).reshape(-1, 3)
        for name, value in (("boxes_m", boxes), ("symmetries", sym), ("size_m", hi - lo), ("refine_starts", starts)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "pockets_m", pockets)
        object.__setattr__(self, "diameter_m", float(d))
        if self.material not in ("wood", "plastic"):
            raise ValueError(f"pallet {self.name!r}: material must be 'wood' or 'plastic', got {self.material!r}")

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

    def points(self, n: int = 2000) -> np.ndarray:
        """(n, 3) float32 model points (the surface points the pose network and ICP use), seed 0."""
        return self.surface_points(n, seed=0)

    def face_centre_m(self, face: str) -> np.ndarray:
        """(3,) centre of a face of the bounding box (pallet frame, metres)."""
        return _FACE_NORMALS[_check_face(face)] * self.size_m / 2

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

def refine_starts_for(size_m) -> np.ndarray:
    """(14, 3) extra ICP starts (yaw_deg, dx_m, dy_m) for a pallet of this (3,) size: the runtime's EPAL starts,
    slides scaled with the length and width."""
    return default_refine_starts(size_m)


def _wood_block(length, width, top, block_h=78.0, t=22.0, block_x=145.0, block_y=(100.0, 145.0), bottom="boards",
                t_cross=None):
    return lambda: _layered_pallet(length, width, top=top, t_top=t, t_cross=t if t_cross is None else t_cross,
                                   block_h=block_h, block_x=block_x, block_y=block_y, bottom=bottom, t_bottom=t)


def _plastic(length, width, top, t_top, block_h, bottom, t_bottom):
    return lambda: _layered_pallet(length, width, top=top, t_top=t_top, t_cross=0.0, block_h=block_h,
                                   block_x=140.0, block_y=(120.0, 140.0), bottom=bottom, t_bottom=t_bottom)


_SLATS_800 = [90.0] * 7
_SLATS_1000 = [90.0] * 9
# name -> (obj_id, material, builder). The obj_id is the type's BOP id forever: never renumber, only append.
_CATALOGUE = {
    "epal": (1, "wood", _wood_block(1200.0, 800.0, [145.0, 100.0, 145.0, 100.0, 145.0])),
    "gma": (2, "wood", _gma_pallet),
    "eur3": (3, "wood", _wood_block(1200.0, 1000.0, [145.0] + [100.0] * 5 + [145.0])),
    "eur2": (4, "wood", _wood_block(1200.0, 1000.0, [145.0] + [100.0] * 5 + [145.0], block_h=96.0)),
    "eur6": (5, "wood", _wood_block(800.0, 600.0, [90.0, 60.0, 60.0, 90.0, 60.0, 60.0, 90.0], block_h=81.0, t=21.0,
                                    block_x=100.0, block_y=(90.0, 100.0))),
    "block_1210": (6, "wood", _wood_block(1200.0, 1000.0, [145.0, 100.0, 100.0, 145.0, 100.0, 100.0, 145.0],
                                          block_h=84.0, bottom="perimeter")),
    "plastic_9leg": (7, "plastic", _plastic(1200.0, 800.0, None, 30.0, 120.0, "none", 0.0)),
    "plastic_3runner": (8, "plastic", _plastic(1200.0, 800.0, _SLATS_800, 25.0, 100.0, "boards", 25.0)),
    "plastic_3runner_1210": (9, "plastic", _plastic(1200.0, 1000.0, _SLATS_1000, 25.0, 100.0, "boards", 25.0)),
    "plastic_closed": (10, "plastic", _plastic(1200.0, 800.0, None, 35.0, 100.0, "perimeter", 25.0)),
    "plastic_closed_1210": (11, "plastic", _plastic(1200.0, 1000.0, None, 35.0, 100.0, "perimeter", 25.0)),
}

PALLET_MODELS: tuple[str, ...] = tuple(_CATALOGUE)
_CACHE: dict[str, PalletModel] = {}


def _check_face(face: str) -> str:
    if face not in _FACE_NORMALS:
        raise ValueError(f"face must be one of {FACES}, got {face!r}")
    return face


def face_normal(face: str) -> np.ndarray:
    """(3,) outward unit normal of a pallet face ("+x", "-x", "+y", "-y"), pallet frame."""
    return _FACE_NORMALS[_check_face(face)].copy()


def get_pallet_model(name: str = "epal") -> PalletModel:
    """The pallet model called `name` (one of PALLET_MODELS)."""
    if name not in _CATALOGUE:
        raise ValueError(f"unknown pallet model {name!r}; known models: {', '.join(PALLET_MODELS)}")
    if name not in _CACHE:  # immutable, so sharing one instance is safe
        obj_id, material, build = _CATALOGUE[name]
        boxes, pockets = build()
        size = boxes[:, 1].max(0) - boxes[:, 0].min(0)
        _CACHE[name] = PalletModel(name=name, boxes_m=boxes, symmetries=_SYM_Z180, pockets_m=pockets,
                                   refine_starts=refine_starts_for(size), obj_id=obj_id, material=material)
    return _CACHE[name]
