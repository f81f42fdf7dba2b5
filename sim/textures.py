"""Procedural surface styles and overlays for randomised appearance (numpy only, deterministic per seed).

Every function takes the hit points in their box's frame and returns a colour per hit, so patterns stick to
the surface: `p` (P, 3) metres, `half` (P, 3) the box's half size, `axis` (P,) the box axis of the face hit,
`seed` (P,) int per box, `color` (P, 3) base colour in [0, 1]. Styles replace a material's default texture;
overlays (dirt, wear) multiply into any texture.
"""
from __future__ import annotations

import numpy as np

from pallet6d.sim.shading import _hash01, _wood, value_noise_2d

__all__ = ["STYLES", "PLASTIC_PALLET_COLORS", "CHEP_BLUE", "apply_style", "dirt_overlay", "wear_overlay"]

# Plastic pallet colours (display-referred RGB): the common moulded-pallet colours.
PLASTIC_PALLET_COLORS: dict[str, tuple[float, float, float]] = {
    "blue": (0.06, 0.24, 0.58), "black": (0.05, 0.05, 0.055), "grey": (0.42, 0.44, 0.46),
    "white": (0.86, 0.87, 0.85), "red": (0.68, 0.08, 0.07)}
CHEP_BLUE = (0.02, 0.30, 0.62)   # CHEP's painted block pallets


def _face_uv(p: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-face coordinates of each hit (the box coordinates other than the face's axis)."""
    rows = np.arange(len(p))
    return p[rows, (axis + 1) % 3], p[rows, (axis + 2) % 3]


def _plastic_smooth(p, half, axis, seed, color):
    a, b = _face_uv(p, axis)
    return color * (0.95 + 0.06 * value_noise_2d(a * 10.0, b * 10.0, seed))[:, None]


def _plastic_ribbed(p, half, axis, seed, color):
    """Ribs 1-2.5 cm apart across the box's longest axis, shaded like grooves."""
    rows = np.arange(len(p))
    along = np.argmax(half, axis=1)
    s = p[rows, along]
    period = 0.01 + 0.015 * _hash01(seed, 21, 4)
    phase = np.mod(s / period, 1.0)
    groove = np.where(phase < 0.25, 0.72, 1.0) * (0.97 + 0.05 * np.sin(phase * 2 * np.pi))
    on_rib_face = axis != along
    return color * np.where(on_rib_face, groove, 0.95).astype(np.float32)[:, None]


def _plastic_moulded(p, half, axis, seed, color):
    """Recessed moulded panels with a fine stipple, as on injection-moulded pallets."""
    a, b = _face_uv(p, axis)
    cell = 0.08 + 0.08 * _hash01(seed, 13, 9)
    fa, fb = np.mod(a / cell, 1.0), np.mod(b / cell, 1.0)
    recess = (np.abs(fa - 0.5) < 0.38) & (np.abs(fb - 0.5) < 0.38)
    rim = (np.abs(fa - 0.5) > 0.34) & (np.abs(fa - 0.5) < 0.38) | (np.abs(fb - 0.5) > 0.34) & (np.abs(fb - 0.5) < 0.38)
    stipple = value_noise_2d(a * 300.0, b * 300.0, seed + 7)
    shade = np.where(recess, 0.88, 1.0) * np.where(rim, 0.75, 1.0) * (0.95 + 0.08 * stipple)
    return color * shade.astype(np.float32)[:, None]


def _noise(p, half, axis, seed, color):
    """Multi-scale value noise between the base colour and a second random colour."""
    a, b = _face_uv(p, axis)
    scale = 2.0 + 30.0 * _hash01(seed, 31, 2)
    n = 0.6 * value_noise_2d(a * scale, b * scale, seed) + 0.4 * value_noise_2d(a * scale * 4, b * scale * 4, seed + 1)
    other = np.stack([_hash01(seed, 40 + k, 6) for k in range(3)], 1)
    return color + (other - color) * n[:, None].astype(np.float32)


def _stripes(p, half, axis, seed, color):
    """Straight stripes of random width, direction and second colour (hazard tape, lane markings, labels)."""
    a, b = _face_uv(p, axis)
    ang = np.pi * _hash01(seed, 51, 3)
    width = 0.02 + 0.2 * _hash01(seed, 52, 3)
    s = a * np.cos(ang) + b * np.sin(ang)
    on = np.mod(s / width, 2.0) < 1.0
    other = np.stack([_hash01(seed, 55 + k, 6) for k in range(3)], 1)
    return np.where(on[:, None], color, other).astype(np.float32)


def _pattern(p, half, axis, seed, color):
    """Checker or blob patterns with random colours: distractor textures that look like nothing in particular."""
    a, b = _face_uv(p, axis)
    scale = 3.0 + 25.0 * _hash01(seed, 61, 8)
    checker = (np.floor(a * scale) + np.floor(b * scale)).astype(np.int64) % 2 == 0
    blobs = value_noise_2d(a * scale, b * scale, seed + 3) > 0.55
    use_checker = _hash01(seed, 62, 8) < 0.5
    on = np.where(use_checker, checker, blobs)
    other = np.stack([_hash01(seed, 65 + k, 6) for k in range(3)], 1)
    return np.where(on[:, None], color, other).astype(np.float32)


def _painted_wood(p, half, axis, seed, color):
    """Painted boards (CHEP): the paint evens out the grain."""
    grain = _wood(p, half, axis, seed, np.ones_like(color))
    return color * (0.55 + 0.45 * grain)


# Style id -> texture; 0 keeps the material's own texture.
STYLES = {1: ("plastic-smooth", _plastic_smooth), 2: ("plastic-ribbed", _plastic_ribbed),
          3: ("plastic-moulded", _plastic_moulded), 4: ("noise", _noise), 5: ("stripes", _stripes),
          6: ("pattern", _pattern), 7: ("painted-wood", _painted_wood)}
STYLE_IDS = {name: k for k, (name, _) in STYLES.items()}


def apply_style(rgb: np.ndarray, style: np.ndarray, p, half, axis, seed, color) -> np.ndarray:
    """Replace the colour of hits whose style is not 0 by that style's texture. rgb: (P, 3), style: (P,)."""
    out = rgb.copy()
    for k, (_, fn) in STYLES.items():
        sel = np.flatnonzero(style == k)
        if sel.size:
            out[sel] = fn(p[sel], half[sel], axis[sel], seed[sel], color[sel])
    return out


def dirt_overlay(rgb: np.ndarray, p: np.ndarray, axis: np.ndarray, seed: np.ndarray,
                 strength: np.ndarray) -> np.ndarray:
    """Darken blotches towards a dirt brown. strength: (P,) in [0, 1]; 0 leaves the colour unchanged."""
    a, b = _face_uv(p, axis)
    coarse = value_noise_2d(a * 6.0, b * 6.0, seed + 101)
    # amount > 0 needs 0.7 coarse + 0.3 fine > 1 - 0.6 strength: the fine noise only where that can hold.
    sel = np.flatnonzero(0.7 * coarse + 0.3 > 1.0 - 0.6 * strength)
    out = rgb.copy()
    if sel.size:
        n = 0.7 * coarse[sel] + 0.3 * value_noise_2d(a[sel] * 40.0, b[sel] * 40.0, seed[sel] + 102)
        s = strength[sel]
        amount = (np.clip((n - (1.0 - 0.6 * s)) * 3.0, 0, 1) * s).astype(np.float32)
        dirt = np.array([0.22, 0.18, 0.13], np.float32)
        out[sel] = rgb[sel] + (dirt - rgb[sel]) * amount[:, None]
    return out


def wear_overlay(rgb: np.ndarray, p: np.ndarray, half: np.ndarray, axis: np.ndarray, seed: np.ndarray,
                 strength: np.ndarray) -> np.ndarray:
    """Scuffed edges and scratches: paint and surface wear off near box edges, lighter and greyer there."""
    a_idx, b_idx = (axis + 1) % 3, (axis + 2) % 3
    rows = np.arange(len(p))
    edge_dist = np.minimum(half[rows, a_idx] - np.abs(p[rows, a_idx]), half[rows, b_idx] - np.abs(p[rows, b_idx]))
    a, b = _face_uv(p, axis)
    worn = np.zeros(len(p), dtype=bool)
    near = np.flatnonzero((edge_dist < 0.004 + 0.03 * strength) & (strength > 0))
    if near.size:
        ragged = value_noise_2d(a[near] * 30.0, b[near] * 30.0, seed[near] + 201)
        worn[near] = (edge_dist[near] < 0.004 + 0.03 * strength[near] * ragged) & (ragged > 0.35)
    line = np.flatnonzero((np.abs(np.sin(a * 37.0 + b * 23.0 + seed)) < 0.02 * strength) & (strength > 0))
    if line.size:
        worn[line] |= value_noise_2d(a[line] * 5, b[line] * 5, seed[line]) > 0.6
    out = rgb.copy()
    if worn.any():
        c = rgb[worn]
        faded = 0.5 * (c + c.mean(1, keepdims=True)) * np.float32(1.15) + np.float32(0.04)
        out[worn] = np.clip(faded, 0, 1)
    return out.astype(np.float32)
