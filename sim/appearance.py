"""Randomised appearance (domain randomisation) for rendered frames.

`AppearanceConfig` holds the ranges; `draw_appearance(config, scene, rng)` draws one frame's `Appearance`
(surface styles and colours per box, lamps, ambient light, camera effects); `shade_appearance` lights the
surface with it. A frame rendered without an appearance is the plain look of `shading.shade`.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from pallet6d.sim.camera_effects import CameraEffects
from pallet6d.sim.lighting import PointLight, ambient_occlusion, light_hits, shadow_visibility
from pallet6d.sim.scene import MATERIALS, Scene
from pallet6d.sim.shading import BACKGROUND_RGB, SurfaceHits, albedo
from pallet6d.sim.textures import CHEP_BLUE, PLASTIC_PALLET_COLORS, STYLE_IDS, apply_style, dirt_overlay, wear_overlay

__all__ = ["AppearanceConfig", "Appearance", "draw_appearance", "surface_albedo", "shade_appearance"]

_Range = tuple[float, float]
_WOOD, _PLASTIC, _CONCRETE = MATERIALS.index("wood"), MATERIALS.index("plastic"), MATERIALS.index("concrete")
_PLASTIC_STYLES = (STYLE_IDS["plastic-smooth"], STYLE_IDS["plastic-ribbed"], STYLE_IDS["plastic-moulded"])
_PATTERN_STYLES = (STYLE_IDS["noise"], STYLE_IDS["stripes"], STYLE_IDS["pattern"])


@dataclass(frozen=True)
class AppearanceConfig:
    """Ranges of the randomised appearance. Ranges are (min, max), drawn uniformly per frame (or per box)."""

    # Surfaces.
    chep_prob: float = 0.15               # a wooden pallet painted CHEP blue
    wood_tint: _Range = (0.75, 1.15)      # brightness of wooden pallets (fresh to weathered)
    board_variation: _Range = (0.0, 0.6)  # per-pallet strength of board-to-board darkening and greying (stains)
    plastic_colors: tuple[str, ...] = tuple(PLASTIC_PALLET_COLORS)   # plastic pallets draw one of these
    pattern_prob: float = 0.25            # a non-pallet box gets a random pattern (noise, stripes, checker...)
    recolor_prob: float = 0.3             # a non-pallet box gets a random colour
    dirt: _Range = (0.0, 0.7)             # dirt strength per box
    wear: _Range = (0.0, 0.8)             # worn edges and scratches per box
    specular: _Range = (0.0, 0.25)        # highlight strength on plastic, metal and film
    # Lights.
    lamps: tuple[int, int] = (1, 3)       # ceiling lamps (point lights with a cone); each costs a shadow pass
    lamp_height_m: _Range = (2.5, 8.0)    # capped below the ceiling
    lamp_spread_m: _Range = (0.0, 6.0)    # horizontal distance of a lamp from the point the camera looks at
    lamp_intensity: _Range = (0.2, 1.0)
    light_tint: _Range = (0.0, 0.25)      # random colour of each light (0 = white)
    key_intensity: _Range = (0.0, 0.8)    # a wide lamp from the scene's light direction
    ambient: _Range = (0.05, 0.35)
    headlight: _Range = (0.0, 0.4)        # lamp at the camera (the forklift's light)
    occlusion: _Range = (0.5, 1.0)        # strength of ambient occlusion (dark pockets and corners)
    shadows: bool = True
    # Camera.
    exposure: _Range = (0.55, 1.6)        # times the auto-exposure gain
    white_balance: _Range = (0.85, 1.15)  # per-channel gain
    vignetting: _Range = (0.0, 0.5)
    defocus_prob: float = 0.2
    defocus_sigma_px: _Range = (0.5, 1.8)
    motion_blur_prob: float = 0.25
    motion_blur_px: _Range = (2.0, 12.0)
    chromatic_px: _Range = (0.0, 1.5)
    shot_noise: _Range = (0.003, 0.03)
    read_noise: _Range = (0.002, 0.02)
    gamma: _Range = (0.8, 1.2)
    jpeg_prob: float = 0.5
    jpeg_quality: tuple[int, int] = (35, 95)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.endswith("_prob") and not 0.0 <= v <= 1.0:
                raise ValueError(f"AppearanceConfig.{f.name} must be in [0, 1], got {v}")
            if isinstance(v, tuple) and f.name != "plastic_colors":
                if len(v) != 2 or not 0 <= v[0] <= v[1]:
                    raise ValueError(f"AppearanceConfig.{f.name} must be a (min, max) pair, 0 <= min <= max, got {v}")
        unknown = set(self.plastic_colors) - set(PLASTIC_PALLET_COLORS)
        if not self.plastic_colors or unknown:
            raise ValueError(f"AppearanceConfig.plastic_colors must name some of {sorted(PLASTIC_PALLET_COLORS)}, "
                             f"got {self.plastic_colors}")
        if self.exposure[0] <= 0 or self.white_balance[0] <= 0 or self.gamma[0] <= 0 or self.jpeg_quality[1] > 100:
            raise ValueError("AppearanceConfig: exposure, white_balance and gamma must be > 0, jpeg_quality <= 100")


@dataclass(frozen=True)
class Appearance:
    """One frame's drawn appearance.

    style: (N,) per box, 0 = the material's own texture, else a `textures.STYLES` id.
    color: (N, 3) per-box base colours. dirt / wear: (N,) strengths. specular: highlight strength.
    lights: lamps and the key light. ambient: (3,) RGB. headlight: strength of the lamp at the camera.
    occlusion: how much ambient occlusion darkens the ambient and headlight terms (0..1).
    """

    style: np.ndarray
    color: np.ndarray
    dirt: np.ndarray
    wear: np.ndarray
    specular: float
    lights: tuple[PointLight, ...]
    ambient: np.ndarray
    headlight: float
    shadows: bool
    camera: CameraEffects
    occlusion: float = 0.0


def _u(rng: np.random.Generator, r) -> float:
    return float(rng.uniform(r[0], r[1]))


def _tint(rng: np.random.Generator, amount: float) -> np.ndarray:
    c = 1.0 + amount * rng.uniform(-1, 1, 3)
    return c / c.mean()


def _ceiling_z(scene: Scene, xy: np.ndarray, above_m: float) -> float:
    """Underside of the lowest wide box above `above_m` over `xy` (the ceiling or a roof), inf if none."""
    z = np.inf
    for b in scene.boxes:
        if b.half_size_m[0] < 1.5 or b.half_size_m[1] < 1.5:
            continue
        local = b.T_world_box[:3, :3].T @ (np.append(xy, b.T_world_box[2, 3]) - b.T_world_box[:3, 3])
        if np.all(np.abs(local[:2]) <= b.half_size_m[:2]):
            bottom = b.T_world_box[2, 3] - b.half_size_m[2]
            if bottom > above_m:
                z = min(z, bottom)
    return z


def _seen_from_camera(scene: Scene, boxes_world: tuple, position_world: np.ndarray) -> bool:
    """True when nothing stands between the camera and `position_world` (a lamp in the camera's room)."""
    cam = scene.T_world_cam[:3, 3]
    return bool(shadow_visibility(cam[None], position_world, cam - position_world, *boxes_world, max_tan=1.0)[0])


def draw_appearance(cfg: AppearanceConfig, scene: Scene, rng: np.random.Generator) -> Appearance:
    """Draw one frame's appearance for `scene` (box styles and colours, lights, camera effects)."""
    n = len(scene.boxes)
    material = np.array([b.material for b in scene.boxes], dtype=np.int64)
    inst = np.array([b.instance_id for b in scene.boxes], dtype=np.int64)
    color = np.array([b.color for b in scene.boxes], dtype=np.float64).reshape(n, 3)
    style = np.zeros(n, dtype=np.int64)
    # Pallets: one look per pallet instance.
    for i in np.unique(inst[inst > 0]):
        sel = inst == i
        if np.any(material[sel] == _PLASTIC):                      # moulded in one piece: one colour
            name = cfg.plastic_colors[int(rng.integers(len(cfg.plastic_colors)))]
            style[sel] = _PLASTIC_STYLES[int(rng.integers(3))]
            color[sel] = np.array(PLASTIC_PALLET_COLORS[name]) * rng.uniform(0.9, 1.1)
            continue
        if rng.random() < cfg.chep_prob:
            style[sel] = STYLE_IDS["painted-wood"]
            color[sel] = np.array(CHEP_BLUE) * rng.uniform(0.85, 1.1)
        else:
            color[sel] = np.clip(color[sel] * _u(rng, cfg.wood_tint), 0, 1)
        # Weathered boards: some darker and greyer than their neighbours, as on real wooden pallets.
        k = _u(rng, cfg.board_variation)
        rows = np.flatnonzero(sel)
        dark = 1 - k * rng.uniform(0, 1, rows.size) ** 2
        grey = k * rng.uniform(0, 1, rows.size)
        c = color[rows]
        color[rows] = (c + (c.mean(1, keepdims=True) - c) * grey[:, None]) * dark[:, None]
    # Everything else: random patterns and colours (the floor keeps its concrete look more often).
    others = np.flatnonzero(inst == 0)
    floor_like = np.where(material[others] == _CONCRETE, 0.3, 1.0)
    pattern = rng.random(others.size) < cfg.pattern_prob * floor_like
    style[others[pattern]] = np.array(_PATTERN_STYLES)[rng.integers(0, 3, int(pattern.sum()))]
    recolor = rng.random(others.size) < cfg.recolor_prob * floor_like
    new_color = rng.uniform(0.05, 0.95, (int(recolor.sum()), 3))
    saturation = rng.uniform(0.2, 1.0, (int(recolor.sum()), 1))
    grey = new_color.mean(1, keepdims=True)
    color[others[recolor]] = grey + (new_color - grey) * saturation
    dirt = rng.uniform(*cfg.dirt, n)
    wear = rng.uniform(*cfg.wear, n)
    # Lights: lamps under the ceiling around where the camera looks, in the camera's room; a key light
    # from the scene's light direction; ambient; the headlight.
    cam = scene.T_world_cam[:3, 3]
    look = cam + scene.T_world_cam[:3, 2] * rng.uniform(1.0, 5.0)
    boxes_world = (np.array([b.T_world_box[:3, :3] for b in scene.boxes]).reshape(n, 3, 3),
                   np.array([b.T_world_box[:3, 3] for b in scene.boxes]).reshape(n, 3),
                   np.array([b.half_size_m for b in scene.boxes]).reshape(n, 3))
    lights = []
    for _ in range(int(rng.integers(cfg.lamps[0], cfg.lamps[1] + 1))):
        for _try in range(8):
            ang, r = rng.uniform(0, 2 * np.pi), _u(rng, cfg.lamp_spread_m) * (1 - _try / 8)
            xy = look[:2] + r * np.array([np.cos(ang), np.sin(ang)])
            z = min(_u(rng, cfg.lamp_height_m), _ceiling_z(scene, xy, max(cam[2], 1.0) + 0.3) - 0.15)
            if _seen_from_camera(scene, boxes_world, np.append(xy, z)):
                break
        lights.append(PointLight(np.append(xy, z), _tint(rng, _u(rng, cfg.light_tint)), _u(rng, cfg.lamp_intensity),
                                 cone_deg=float(rng.uniform(45, 75))))
    key = _u(rng, cfg.key_intensity)
    if key > 0:
        d = scene.light.direction_world
        for dist in (8.0, 5.0, 3.0, 2.0):
            pos = look - d * dist
            if _seen_from_camera(scene, boxes_world, pos):
                break
        lights.append(PointLight(pos, _tint(rng, _u(rng, cfg.light_tint)), key, axis_world=d, cone_deg=80.0,
                                 ref_m=dist))
    ambient = _u(rng, cfg.ambient) * _tint(rng, _u(rng, cfg.light_tint))
    motion = rng.random() < cfg.motion_blur_prob
    defocus = rng.random() < cfg.defocus_prob
    jpeg_on = rng.random() < cfg.jpeg_prob
    camera = CameraEffects(
        exposure=_u(rng, cfg.exposure), wb_gains=tuple(float(g) for g in rng.uniform(*cfg.white_balance, 3)),
        vignetting=_u(rng, cfg.vignetting),
        defocus_sigma_px=_u(rng, cfg.defocus_sigma_px) if defocus else 0.0,
        motion_blur_px=_u(rng, cfg.motion_blur_px) if motion else 0.0, motion_blur_deg=float(rng.uniform(-30, 30)),
        chromatic_px=_u(rng, cfg.chromatic_px), shot_noise=_u(rng, cfg.shot_noise), read_noise=_u(rng, cfg.read_noise),
        gamma=_u(rng, cfg.gamma),
        jpeg_quality=int(rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1)) if jpeg_on else 0)
    return Appearance(style=style, color=np.clip(color, 0, 1).astype(np.float32), dirt=dirt.astype(np.float32),
                      wear=wear.astype(np.float32), specular=_u(rng, cfg.specular), lights=tuple(lights),
                      ambient=ambient.astype(np.float32), headlight=_u(rng, cfg.headlight), shadows=cfg.shadows,
                      camera=camera, occlusion=_u(rng, cfg.occlusion))


def surface_albedo(hits: SurfaceHits, material: np.ndarray, texture_seed: np.ndarray, app: Appearance) -> np.ndarray:
    """(P, 3) float32 surface colour of every hit with the appearance's styles, colours, dirt and wear."""
    rgb = albedo(hits, material, app.color, texture_seed)
    b = hits.box
    seeds = texture_seed[b].astype(np.int64)
    rgb = apply_style(rgb, app.style[b], hits.p_box, hits.half_m, hits.axis, seeds, app.color[b])
    rgb = dirt_overlay(rgb, hits.p_box, hits.axis, seeds, app.dirt[b])
    rgb = wear_overlay(rgb, hits.p_box, hits.half_m, hits.axis, seeds, app.wear[b])
    return np.clip(rgb, 0, 1).astype(np.float32)


def shade_appearance(hits: SurfaceHits, surface_rgb: np.ndarray, material: np.ndarray, app: Appearance,
                     T_cam_world: np.ndarray, boxes: tuple) -> np.ndarray:
    """(H, W, 3) float32 linear image: the surface lit by the appearance's lights (shadows included).

    :param surface_rgb: (P, 3) from `surface_albedo`. :param boxes: (R_cam_box, t_cam_box, half_m) arrays.
    """
    h, w = hits.image_hw
    out = np.empty((h, w, 3), dtype=np.float32)
    out[:] = BACKGROUND_RGB * (app.ambient / max(float(app.ambient.mean()), 1e-3))    # tinted like the ambient
    if hits.pix.size == 0:
        return out
    irradiance = np.repeat(app.ambient[None], hits.pix.size, 0)
    lamp = np.maximum((hits.normal_cam * hits.view_cam).sum(1), 0)
    irradiance += (app.headlight * lamp)[:, None]
    if app.occlusion > 0:
        irradiance *= (1 - app.occlusion * ambient_occlusion(hits))[:, None]
    shiny = np.isin(material[hits.box], [MATERIALS.index(m) for m in ("plastic", "metal", "film")])
    spec = np.zeros(hits.pix.size, np.float32)
    for light in app.lights:
        e = light_hits(hits, light, T_cam_world, boxes, app.shadows)
        irradiance += e[:, None] * light.color[None].astype(np.float32)
        if app.specular > 0 and shiny.any():
            R_cw = T_cam_world[:3, :3]
            to = (R_cw @ light.position_world + T_cam_world[:3, 3])[None] - hits.p_cam
            l_dir = to / np.maximum(np.linalg.norm(to, axis=1, keepdims=True), 1e-6)
            half_v = l_dir + hits.view_cam
            half_v = half_v / np.maximum(np.linalg.norm(half_v, axis=1, keepdims=True), 1e-6)
            spec += np.where(shiny & (e > 0), e * np.maximum((hits.normal_cam * half_v).sum(1), 0) ** 40, 0)
    rgb = surface_rgb * irradiance + (app.specular * spec)[:, None]
    out.reshape(-1, 3)[hits.pix] = rgb
    return out
