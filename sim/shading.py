"""Procedural textures and lighting for ray-cast box scenes.

Textures are functions of the hit point in the box's own frame, so they stick to the box: wood grain
along each board's longest axis, cardboard with tape and labels, perforated rack uprights, concrete,
painted walls. Lighting is ambient + Lambert (directional light) + a lamp at the camera.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pallet6d.sim.scene import MATERIALS

__all__ = ["BACKGROUND_RGB", "SurfaceHits", "value_noise_2d", "surface_hits", "albedo", "shade"]

_WOOD, _CARD, _METAL, _CONCRETE, _WALL, _PLASTIC, _FILM = (MATERIALS.index(m) for m in MATERIALS)
BACKGROUND_RGB = np.array([0.08, 0.08, 0.09], dtype=np.float32)


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray | int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point (and seed)."""
    h = (np.asarray(ix, np.int64) * 73856093) ^ (np.asarray(iy, np.int64) * 19349663) ^ (np.asarray(seed, np.int64) * 83492791)
    h = (h & 0xFFFFFFFF).astype(np.uint32)
    h ^= h >> np.uint32(13)
    h *= np.uint32(0x5BD1E995)
    h ^= h >> np.uint32(15)
    return (h & np.uint32(0xFFFFFF)).astype(np.float32) / np.float32(2 ** 24)


def value_noise_2d(x: np.ndarray, y: np.ndarray, seed: np.ndarray | int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1) with unit lattice spacing.

    :param x: (n,) coordinates, :param y: (n,) coordinates, :param seed: scalar or (n,) ints.
    """
    fx, fy = np.floor(x), np.floor(y)
    tx, ty = (x - fx).astype(np.float32), (y - fy).astype(np.float32)
    tx, ty = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty)
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    a = _hash01(ix, iy, seed)
    b = _hash01(ix + 1, iy, seed)
    c = _hash01(ix, iy + 1, seed)
    d = _hash01(ix + 1, iy + 1, seed)
    return (a + (b - a) * tx) + ((c + (d - c) * tx) - (a + (b - a) * tx)) * ty


def _wood(p, half, axis, seed, color):
    """Board grain along the longest axis; concentric rings on end-grain faces."""
    n = len(p)
    along = np.argmax(half, axis=1)
    rows = np.arange(n)
    s = p[rows, along]
    c1 = p[rows, (along + 1) % 3]
    c2 = p[rows, (along + 2) % 3]
    rnd = _hash01(seed, seed * 7 + 1, 11)
    # A virtual log centre 5-15 cm off the board: rings appear as streaks on long faces.
    r = np.sqrt((c1 - 0.05 - 0.1 * rnd) ** 2 + (c2 + 0.04 - 0.08 * _hash01(seed, 3, 5)) ** 2)
    r = r + 0.006 * (value_noise_2d(s * 4.0, r * 30.0, seed) - 0.5) + 0.002 * np.sin(s * 9.0 + 6.28 * rnd)
    spacing = 0.006 + 0.006 * rnd
    ring = 0.5 + 0.5 * np.sin(r * (2 * np.pi) / spacing)
    streak = value_noise_2d(s * 1.5, (c1 + c2) * 60.0, seed + 1)
    shade = 0.80 + 0.14 * ring ** 2 + 0.12 * (streak - 0.5)
    # Knots: a few dark spots per board.
    knot = value_noise_2d(s * 6.0, (c1 + c2) * 25.0, seed + 2)
    shade = shade * np.where(knot > 0.93, 0.6, 1.0)
    end_grain = axis == along
    shade = np.where(end_grain, shade * 0.78, shade)
    tint = 0.9 + 0.2 * _hash01(seed, 17, 3)                          # board-to-board variation
    return color * (shade * tint)[:, None]


def _cardboard(p, half, axis, seed, color):
    fibre = value_noise_2d(p[:, 0] * 40.0 + p[:, 2] * 13.0, p[:, 1] * 40.0 + p[:, 2] * 29.0, seed)
    rgb = color * (0.9 + 0.12 * fibre)[:, None]
    # Tape over the top and down the sides along x = 0.
    tape = (np.abs(p[:, 0]) < 0.025) & ((axis == 2) | (p[:, 2] > half[:, 2] - 0.07)) & (axis != 0)
    rgb[tape] = rgb[tape] * np.float32(1.12) + np.float32(0.03)
    # A white shipping label with a barcode on one side face of some boxes.
    lx = (_hash01(seed, 5, 7) - 0.5) * np.maximum(half[:, 0] - 0.08, 0)
    label = (axis == 1) & (np.abs(p[:, 0] - lx) < 0.05) & (np.abs(p[:, 2] + 0.2 * half[:, 2]) < 0.035) \
        & (_hash01(seed, 9, 1) < 0.7)
    bars = label & (np.abs(p[:, 2] + 0.2 * half[:, 2]) < 0.015) & (np.sin(p[:, 0] * 900.0 + seed) > 0.2)
    rgb[label] = np.float32(0.92)
    rgb[bars] = np.float32(0.1)
    return rgb


def _metal(p, half, axis, seed, color):
    rgb = color * (0.95 + 0.05 * value_noise_2d(p[:, 0] * 20, p[:, 2] * 20, seed))[:, None]
    # Rack uprights (tall metal): punched slots every 5 cm on the faces, dark.
    upright = (half[:, 2] > 0.8) & (axis != 2)
    lateral = np.where(axis == 0, p[:, 1], p[:, 0])
    slot = upright & (np.mod(p[:, 2], 0.05) < 0.02) & (np.abs(lateral) < 0.008)
    rgb[slot] = np.float32(0.05)
    return rgb


def _concrete(p, half, axis, seed, color):
    coarse = value_noise_2d(p[:, 0] * 0.7, p[:, 1] * 0.7, seed)
    fine = value_noise_2d(p[:, 0] * 25.0, p[:, 1] * 25.0, seed + 3)
    stains = value_noise_2d(p[:, 0] * 3.0 + 10, p[:, 1] * 3.0, seed + 5)
    shade = 0.82 + 0.18 * coarse + 0.08 * (fine - 0.5) - 0.15 * np.maximum(stains - 0.7, 0)
    # Expansion joints every 6 m.
    joint = (np.abs(np.mod(p[:, 0] + 3.0, 6.0) - 3.0) > 2.99) | (np.abs(np.mod(p[:, 1] + 3.0, 6.0) - 3.0) > 2.99)
    shade = np.where(joint & (axis == 2), shade * 0.6, shade)
    return color * shade[:, None]


def _wall(p, half, axis, seed, color):
    z_floor = p[:, 2] + half[:, 2]                                  # walls stand on the floor
    panel = np.abs(np.mod(z_floor, 1.0) - 0.5) > 0.49
    rgb = color * (0.95 + 0.05 * value_noise_2d(p[:, 0] * 2 + p[:, 1] * 2, z_floor * 2, seed))[:, None]
    low = z_floor < 1.2                                              # painted dado band
    rgb[low] = rgb[low] * np.array([0.55, 0.65, 0.8], dtype=np.float32)
    rgb[panel] *= np.float32(0.7)
    return rgb


def _plastic(p, half, axis, seed, color):
    return color * (0.96 + 0.06 * value_noise_2d(p[:, 0] * 8, p[:, 1] * 8 + p[:, 2] * 8, seed))[:, None]


def _film(p, half, axis, seed, color):
    wrap = 0.5 + 0.5 * np.sin(p[:, 2] * 60.0 + 3.0 * value_noise_2d(p[:, 0] * 5, p[:, 1] * 5, seed))
    return color * (0.85 + 0.15 * wrap)[:, None]


_TEXTURES = {_WOOD: _wood, _CARD: _cardboard, _METAL: _metal, _CONCRETE: _concrete, _WALL: _wall,
             _PLASTIC: _plastic, _FILM: _film}


@dataclass
class SurfaceHits:
    """The ray-cast surface at every pixel that hit a box (P such pixels).

    pix: (P,) flat pixel indices; box: (P,) box index; p_box: (P, 3) hit point in its box's frame;
    half_m: (P, 3) that box's half size; axis: (P,) box axis of the face hit; normal_cam / view_cam: (P, 3) unit
    face normal and direction to the camera; p_cam: (P, 3) hit point, camera frame, metres.
    """

    image_hw: tuple[int, int]
    pix: np.ndarray
    box: np.ndarray
    p_box: np.ndarray
    half_m: np.ndarray
    axis: np.ndarray
    normal_cam: np.ndarray
    view_cam: np.ndarray
    p_cam: np.ndarray

    def to_image(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(P,) or (P, C) per-hit values -> (H, W) or (H, W, C) float32 image, `fill` where nothing was hit."""
        values = np.asarray(values, dtype=np.float32)
        out = np.full((self.image_hw[0] * self.image_hw[1],) + values.shape[1:], fill, dtype=np.float32)
        out[self.pix] = values
        return out.reshape(tuple(self.image_hw) + values.shape[1:])


def surface_hits(depth_m: np.ndarray, box_index: np.ndarray, rays: tuple[np.ndarray, np.ndarray],
                 R_cam_box: np.ndarray, t_cam_box: np.ndarray, half_m: np.ndarray) -> SurfaceHits:
    """Hit points, faces and normals of a ray-cast frame (see `shade` for the parameters)."""
    h, w = depth_m.shape
    pix = np.flatnonzero(box_index >= 0)
    b = box_index.ravel()[pix]
    z = depth_m.ravel()[pix]
    ray = np.stack([rays[0].ravel()[pix], rays[1].ravel()[pix], np.ones(pix.size, np.float32)], 1)
    p_cam = ray * z[:, None]
    R = R_cam_box[b].astype(np.float32)                               # (P, 3, 3)
    p = np.einsum("pji,pj->pi", R, p_cam - t_cam_box[b].astype(np.float32))
    half = half_m[b].astype(np.float32)
    axis = np.argmax(np.abs(p) / half, axis=1)
    rows = np.arange(pix.size)
    sign = np.sign(p[rows, axis]).astype(np.float32)
    normal = R[rows, :, axis] * sign[:, None]
    view = -ray / np.linalg.norm(ray, axis=1, keepdims=True)
    return SurfaceHits((h, w), pix, b, p, half, axis, normal, view, p_cam)


def albedo(hits: SurfaceHits, material: np.ndarray, color: np.ndarray, texture_seed: np.ndarray) -> np.ndarray:
    """(P, 3) float32 textured surface colour (reflectance) of every hit, before lighting."""
    rgb = np.empty((hits.pix.size, 3), dtype=np.float32)
    mat = material[hits.box]
    seeds = texture_seed[hits.box].astype(np.int64)
    base = color[hits.box].astype(np.float32)
    for m, fn in _TEXTURES.items():
        sel = np.flatnonzero(mat == m)
        if sel.size:
            rgb[sel] = fn(hits.p_box[sel], hits.half_m[sel], hits.axis[sel], seeds[sel], base[sel])
    return rgb


def shade(depth_m: np.ndarray, box_index: np.ndarray, rays: tuple[np.ndarray, np.ndarray],
          R_cam_box: np.ndarray, t_cam_box: np.ndarray, half_m: np.ndarray, material: np.ndarray,
          color: np.ndarray, texture_seed: np.ndarray, light_dir_cam: np.ndarray, intensity: float,
          ambient: float, headlight: float) -> np.ndarray:
    """Shaded linear RGB image of a ray-cast frame.

    :param depth_m: (H, W) hit depth (0 = none); :param box_index: (H, W) box hit, -1 = none.
    :param rays: x/z and y/z per pixel, two (H, W) arrays.
    :param R_cam_box: (N, 3, 3), :param t_cam_box: (N, 3), :param half_m: (N, 3) the boxes.
    :param material: (N,) index into MATERIALS, :param color: (N, 3) base colours, :param texture_seed: (N,).
    :param light_dir_cam: (3,) unit direction the light travels, camera frame.
    :return: (H, W, 3) float32 RGB, nominally in [0, 1].
    """
    h, w = depth_m.shape
    out = np.empty((h, w, 3), dtype=np.float32)
    out[:] = BACKGROUND_RGB
    hits = surface_hits(depth_m, box_index, rays, R_cam_box, t_cam_box, half_m)
    if hits.pix.size == 0:
        return out
    lambert = np.maximum(hits.normal_cam @ (-np.asarray(light_dir_cam, np.float32)), 0)
    lamp = np.maximum((hits.normal_cam * hits.view_cam).sum(1), 0)
    light = ambient + intensity * lambert + headlight * lamp
    rgb = albedo(hits, material, color, texture_seed)
    out.reshape(-1, 3)[hits.pix] = rgb * light[:, None]
    return out
