"""What stands on and around pallets in a real warehouse: loads (cartons, shrink-wrapped stacks, sacks,
drums), pallet colours and wear, stacks of empty pallets, truck beds, distractor objects and obstacles in
fork pockets. All boxes, world frame (z up, floor z = 0), metres.

Every function draws from the given `rng` only, so a scene is reproducible from its seed.
"""
from __future__ import annotations

import math

import numpy as np

from pallet6d.sim.pallets import face_normal, get_pallet_model
from pallet6d.sim.scene import Box, PalletPlacement, box_at

__all__ = ["WOOD_COLORS", "PLASTIC_COLORS", "CHEP_BLUE", "pallet_look", "load_boxes", "drum_boxes",
           "pocket_obstacle", "distractor_boxes", "truck_bed_boxes"]

WOOD_COLORS = np.array([[0.82, 0.66, 0.45], [0.72, 0.58, 0.40], [0.62, 0.57, 0.49], [0.58, 0.44, 0.30],
                        [0.86, 0.74, 0.55]])
# Plastic pallets come in blue, black, grey, white and red.
PLASTIC_COLORS = np.array([[0.10, 0.25, 0.65], [0.07, 0.07, 0.08], [0.45, 0.46, 0.48], [0.88, 0.88, 0.86],
                           [0.70, 0.10, 0.10]])
CHEP_BLUE = np.array([0.12, 0.32, 0.66])
_CARTON = np.array([0.66, 0.50, 0.33])


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2 ** 20))


def pallet_look(rng: np.random.Generator, model_name: str, missing_board_prob: float):
    """A pallet's appearance variant: (base colour (3,), per-part colours (k, 3), missing part indices).

    Wood is new (light), weathered (grey) or dirty (dark patches on some parts); the 1200 x 1000 block
    pallet is CHEP blue most of the time; plastic is one of PLASTIC_COLORS. A missing board is one inner top
    deck board left out (the ground-truth model stays the type's).
    """
    model = get_pallet_model(model_name)
    k = len(model.boxes_m)
    if model.material == "plastic":
        base = PLASTIC_COLORS[rng.integers(len(PLASTIC_COLORS))] * rng.uniform(0.9, 1.1, 3)
        parts = np.repeat(base[None], k, 0) * rng.uniform(0.97, 1.03, (k, 1))
        return np.clip(base, 0, 1), np.clip(parts, 0, 1), ()
    if model_name == "block_1210" and rng.random() < 0.8:
        base = CHEP_BLUE * rng.uniform(0.85, 1.1, 3)
    else:
        base = WOOD_COLORS[rng.integers(len(WOOD_COLORS))] * rng.uniform(0.9, 1.08, 3)
        weathered = rng.uniform(0.0, 0.7) if rng.random() < 0.4 else 0.0
        base = (1 - weathered) * base + weathered * np.array([0.5, 0.5, 0.5])
    dirt = rng.random(k) < rng.uniform(0.0, 0.5)
    parts = np.repeat(base[None], k, 0) * np.where(dirt, rng.uniform(0.45, 0.8, k), rng.uniform(0.92, 1.06, k))[:, None]
    missing: tuple[int, ...] = ()
    if rng.random() < missing_board_prob:
        top = np.flatnonzero(np.isclose(model.boxes_m[:, 1, 2], model.size_m[2] / 2))
        inner = top[1:-1] if len(top) > 2 else np.array([], dtype=np.int64)
        if inner.size:
            missing = (int(inner[rng.integers(inner.size)]),)
    return np.clip(base, 0, 1), np.clip(parts, 0, 1), missing


def drum_boxes(centre_xy, z0: float, radius: float, height: float, color, seed: int, yaw: float = 0.0,
               sides: int = 8) -> list[Box]:
    """A drum (upright cylinder) as a regular `sides`-gon prism: the union of sides / 2 boxes turned by
    360 / sides degrees, each spanning two opposite flats with its corners on the drum's circle."""
    if sides < 4 or sides % 2:
        raise ValueError(f"sides must be an even number >= 4, got {sides}")
    half = math.pi / sides
    size = [2 * radius * math.cos(half), 2 * radius * math.sin(half), height]
    centre = [centre_xy[0], centre_xy[1], z0 + height / 2]
    return [box_at(centre, size, "metal", color, seed, _rz(yaw + 2 * half * k)) for k in range(sides // 2)]


def load_boxes(rng: np.random.Generator, p: PalletPlacement, clearance_m: float) -> list[Box]:
    """A random load on a pallet: carton layers, a shrink-wrapped stack, sacks or drums."""
    model = get_pallet_model(p.model_name)
    L, W, H = model.size_m
    R = p.T_world_pallet[:3, :3]
    top = p.T_world_pallet[:3, 3] + R[:, 2] * (H / 2)
    max_h = min(clearance_m - 0.05, 1.8)
    kind = rng.choice(["cartons", "wrapped", "sacks", "drums"], p=[0.45, 0.25, 0.15, 0.15])
    out: list[Box] = []
    if kind == "wrapped":   # a block of cartons in stretch film, sometimes with a cap sheet
        h = rng.uniform(0.3, max_h)
        over = rng.uniform(-0.04, 0.03, 2)
        color = np.array([0.82, 0.84, 0.86]) * rng.uniform(0.8, 1.05) if rng.random() < 0.8 else \
            np.array([0.15, 0.15, 0.16])
        out.append(box_at(top + R[:, 2] * h / 2, [L + over[0], W + over[1], h], "film", color, _seed(rng), R))
    elif kind == "cartons":
        bx, by, bz = rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.4), rng.uniform(0.15, 0.4)
        nx, ny = max(int(L // bx), 1), max(int(W // by), 1)
        layers = int(rng.integers(1, max(int(max_h // bz), 1) + 1))
        base = _CARTON * rng.uniform(0.8, 1.15, 3) if rng.random() < 0.85 else np.array([0.9, 0.9, 0.88])
        for k in range(layers):
            for i in range(nx):
                for j in range(ny):
                    if k > 0 and rng.random() < (0.4 if k == layers - 1 else 0.05):   # the first layer is whole
                        continue
                    c = np.array([(i + 0.5) * L / nx - L / 2, (j + 0.5) * W / ny - W / 2, (k + 0.5) * bz])
                    c[:2] += rng.uniform(-0.015, 0.015, 2)
                    out.append(box_at(top + R @ c, [L / nx - 0.01, W / ny - 0.01, bz - 0.002], "cardboard",
                                      base * rng.uniform(0.93, 1.07, 3), _seed(rng), R))
    elif kind == "sacks":   # paper or woven plastic sacks in a brick pattern
        plastic = rng.random() < 0.5
        color = (np.array([0.92, 0.92, 0.9]) if plastic else np.array([0.78, 0.68, 0.5])) * rng.uniform(0.85, 1.05)
        sz = rng.uniform(0.1, 0.16)
        for k in range(int(rng.integers(2, max(int(max_h // sz), 2) + 1))):
            rot = k % 2
            sx, sy = (L / 2, W / 3) if not rot else (L / 3, W / 2)
            for i in range(round(L / sx)):
                for j in range(round(W / sy)):
                    c = np.array([(i + 0.5) * sx - L / 2, (j + 0.5) * sy - W / 2, (k + 0.5) * sz])
                    c[:2] += rng.uniform(-0.02, 0.02, 2)
                    Rk = R @ _rz(rng.uniform(-0.06, 0.06))
                    out.append(box_at(top + R @ c, [sx * 0.96, sy * 0.93, sz * 0.98], "plastic" if plastic else
                                      "cardboard", color * rng.uniform(0.95, 1.05, 3), _seed(rng), Rk))
    else:                   # drums standing on the pallet
        radius = rng.uniform(0.12, min(L, W) / 4 - 0.005)
        h = min(rng.uniform(0.5, 0.95), max_h)
        nx, ny = max(int(L // (2 * radius + 0.01)), 1), max(int(W // (2 * radius + 0.01)), 1)
        color = np.array([[0.1, 0.25, 0.6], [0.7, 0.1, 0.08], [0.15, 0.15, 0.15], [0.2, 0.45, 0.2],
                          [0.75, 0.75, 0.78]])[rng.integers(5)]
        for i in range(nx):
            for j in range(ny):
                c = top + R @ np.array([(i + 0.5) * L / nx - L / 2, (j + 0.5) * W / ny - W / 2, 0.0])
                out.extend(drum_boxes(c[:2], c[2], radius, h, color * rng.uniform(0.9, 1.1), _seed(rng)))
    return out


def pocket_obstacle(rng: np.random.Generator, p: PalletPlacement, face: str) -> list[Box]:
    """Something left in one fork pocket of `face` (a carton, a block of wood, a bin, a drum lid stack...):
    a box inside the opening, from the face plane inwards (sometimes sticking out a little)."""
    model = get_pallet_model(p.model_name)
    pk = model.pockets_m[face][int(rng.integers(2))]
    depth_axis = 0 if face[1] == "x" else 1
    n = face_normal(face)
    lo, hi = pk[0].copy(), pk[1].copy()
    size = hi - lo
    ext = np.empty(3)
    lat = 1 - depth_axis
    ext[lat] = size[lat] * rng.uniform(0.4, 0.9)
    ext[2] = size[2] * rng.uniform(0.5, 0.9)
    ext[depth_axis] = rng.uniform(0.1, 0.4)
    centre = (lo + hi) / 2
    centre[lat] += rng.uniform(-1, 1) * (size[lat] - ext[lat]) / 2
    centre[2] = lo[2] + ext[2] / 2 + 0.003
    face_pos = model.size_m[depth_axis] / 2 * n[depth_axis]
    inset = rng.uniform(-0.05, 0.25)                      # < 0: sticks out of the face
    centre[depth_axis] = face_pos - n[depth_axis] * (inset + ext[depth_axis] / 2)
    material, color = [("cardboard", _CARTON), ("wood", WOOD_COLORS[0]), ("plastic", PLASTIC_COLORS[0]),
                       ("metal", np.array([0.5, 0.5, 0.52]))][int(rng.integers(4))]
    T = p.T_world_pallet
    return [box_at(T[:3, :3] @ centre + T[:3, 3], ext, material, color * rng.uniform(0.85, 1.1, 3), _seed(rng),
                   T[:3, :3])]


def distractor_boxes(rng: np.random.Generator, xy, yaw: float) -> list[Box]:
    """A non-pallet object standing on the floor: a bin, a drum, a post, a wall piece, a carton stack, a
    crate, a safety barrier."""
    kind = int(rng.integers(6))
    out: list[Box] = []
    if kind == 0:       # drum or barrel
        r, h = rng.uniform(0.2, 0.3), rng.uniform(0.6, 0.95)
        color = np.array([[0.1, 0.25, 0.6], [0.7, 0.1, 0.08], [0.2, 0.45, 0.2]])[rng.integers(3)]
        out.extend(drum_boxes(xy, 0.0, r, h, color, _seed(rng), yaw))
    elif kind == 1:     # steel post with a yellow guard
        out.append(box_at([xy[0], xy[1], 2.5], [0.2, 0.2, 5.0], "metal", np.array([0.35, 0.36, 0.38]), _seed(rng),
                          _rz(yaw)))
        out.append(box_at([xy[0], xy[1], 0.5], [0.3, 0.3, 1.0], "plastic", np.array([0.9, 0.75, 0.1]), _seed(rng),
                          _rz(yaw)))
    elif kind == 2:     # a piece of wall or a partition
        length, h = rng.uniform(1.0, 3.0), rng.uniform(1.0, 3.0)
        out.append(box_at([xy[0], xy[1], h / 2], [length, 0.12, h], "wall",
                          np.array([0.85, 0.85, 0.82]) * rng.uniform(0.6, 1.05, 3), _seed(rng), _rz(yaw)))
    elif kind == 3:     # stack of cartons
        z = 0.0
        base = _CARTON * rng.uniform(0.85, 1.1, 3)
        for _ in range(int(rng.integers(1, 5))):
            s = rng.uniform([0.3, 0.3, 0.2], [0.7, 0.6, 0.5])
            out.append(box_at([xy[0], xy[1], z + s[2] / 2], s, "cardboard", base * rng.uniform(0.93, 1.07, 3),
                              _seed(rng), _rz(yaw + rng.uniform(-0.2, 0.2))))
            z += s[2]
    elif kind == 4:     # plastic crate or bin
        s = rng.uniform([0.4, 0.3, 0.3], [1.2, 1.0, 1.1])
        color = PLASTIC_COLORS[rng.integers(len(PLASTIC_COLORS))]
        out.append(box_at([xy[0], xy[1], s[2] / 2], s, "plastic", color, _seed(rng), _rz(yaw)))
    else:               # safety barrier: two posts and a rail
        length = rng.uniform(1.0, 2.5)
        R = _rz(yaw)
        for sx in (-1, 1):
            c = np.array([xy[0], xy[1], 0.0]) + R @ [sx * length / 2, 0, 0]
            out.append(box_at(c + [0, 0, 0.5], [0.1, 0.1, 1.0], "metal", np.array([0.9, 0.75, 0.1]), _seed(rng), R))
        out.append(box_at([xy[0], xy[1], 0.85], [length, 0.08, 0.12], "metal", np.array([0.9, 0.75, 0.1]),
                          _seed(rng), R))
    return out


def truck_bed_boxes(rng: np.random.Generator, centre_xy, yaw: float, length: float, height: float) -> list[Box]:
    """A truck's or trailer's load bed seen from the side: the floor deck, the chassis and wheels under it."""
    R = _rz(yaw)
    c = np.array([centre_xy[0], centre_xy[1], 0.0])
    color = np.array([[0.8, 0.8, 0.82], [0.15, 0.3, 0.6], [0.7, 0.12, 0.1], [0.2, 0.2, 0.22]])[rng.integers(4)]
    out = [box_at(c + [0, 0, height - 0.08], [length, 2.45, 0.16], "metal", color * rng.uniform(0.9, 1.1),
                  _seed(rng), R),
           box_at(c + [0, 0, height - 0.4], [length * 0.95, 1.0, 0.5], "metal", np.array([0.12, 0.12, 0.13]),
                  _seed(rng), R)]
    for x in (-length / 2 + 1.0, -length / 2 + 2.4, length / 2 - 1.2):
        for y in (-0.95, 0.95):
            out.append(box_at(c + R @ [x, y, 0.5], [1.0, 0.35, 1.0], "plastic", np.array([0.06, 0.06, 0.06]),
                              _seed(rng), R))
    return out
