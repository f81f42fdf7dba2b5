"""Render scenes into frames with exact ground truth, and draw random frames from a preset.

`render_scene` turns a `Scene` into a `SimFrame` (RGB, depth, intrinsics, one `PalletGT` per pallet in
view); `generate_frame(config, seed, index)` draws the scene for frame `index` of a dataset with seed
`seed` (its own `np.random.default_rng((seed, index))`, so frames are reproducible one by one).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from pallet6d.runtime.geometry import project_points, transform_points
from pallet6d.sim.appearance import Appearance, draw_appearance, shade_appearance, surface_albedo
from pallet6d.sim.camera_effects import apply_camera_effects
from pallet6d.sim.depth_sensors import DepthModel, apply_sensor, depth_model_for
from pallet6d.sim.forklift_view import PalletFaceGT, face_gts, pocket_visibility
from pallet6d.sim.pallets import box_corners, get_pallet_model
from pallet6d.sim.presets import SimConfig
from pallet6d.sim.raycast import pixel_rays, raycast_boxes
from pallet6d.sim.scene import ForkliftVehicle, Scene, SceneError
from pallet6d.sim.sensors import PixelInfo, RgbCameraModel, StereoDepthModel, apply_rgb_model
from pallet6d.sim.shading import SurfaceHits, albedo, shade, surface_hits
from pallet6d.sim.tof import ToFDepthModel, register_rgb_to_depth
from pallet6d.sim.warehouse import build_scene

__all__ = ["PalletGT", "SimFrame", "obj_id_of", "render_scene", "render_with_sensors", "with_forklift_gt",
           "generate_frame", "mask_bbox_xywh"]

log = logging.getLogger(__name__)


def obj_id_of(model_name: str) -> int:
    """BOP object id of a pallet model: the catalogue's stable id (epal = 1)."""
    return get_pallet_model(model_name).obj_id


def mask_bbox_xywh(mask: np.ndarray) -> np.ndarray:
    """(4,) int x, y, w, h of a mask's pixels; (-1, -1, 0, 0) when empty (BOP convention)."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return np.array([-1, -1, 0, 0], dtype=np.int64)
    return np.array([xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], dtype=np.int64)


@dataclass
class PalletGT:
    """Ground truth of one pallet in a frame.

    T_cam_pallet: (4, 4) metres. mask_visib / mask_full: (H, W) bool (full = the pallet rendered alone).
    px_count_all counts the whole silhouette, outside the image too (BOP), so visib_fract drops when the
    image border cuts the pallet.
    bbox_*_xywh: (4,) int pixels; bbox_obj is the whole projected pallet and may extend past the image.
    box3d_cam: (8, 3) corners of the pallet's bounding box in the camera frame (order of `box_corners`).
    px_count_valid: visible pixels with sensor depth.
    """

    instance_id: int
    model_name: str
    obj_id: int
    T_cam_pallet: np.ndarray
    mask_visib: np.ndarray
    mask_full: np.ndarray
    bbox_obj_xywh: np.ndarray
    bbox_visib_xywh: np.ndarray
    box3d_cam: np.ndarray
    px_count_all: int
    px_count_visib: int
    px_count_valid: int
    visib_fract: float

    def __post_init__(self) -> None:
        if self.T_cam_pallet.shape != (4, 4):
            raise ValueError(f"T_cam_pallet must be (4, 4), got {self.T_cam_pallet.shape}")
        if self.mask_visib.shape != self.mask_full.shape or self.mask_visib.ndim != 2:
            raise ValueError(f"masks must be equal (H, W), got {self.mask_visib.shape} and {self.mask_full.shape}")
        if self.box3d_cam.shape != (8, 3):
            raise ValueError(f"box3d_cam must be (8, 3), got {self.box3d_cam.shape}")


@dataclass
class SimFrame:
    """One rendered frame.

    rgb: (H, W, 3) uint8 RGB. depth_m: (H, W) float32 sensor depth, 0 = none. depth_ideal_m: exact depth.
    K: (3, 3). T_world_cam: (4, 4). pallets: GT of every pallet whose silhouette is in the image.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    depth_ideal_m: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    pallets: list[PalletGT]
    target_instance: int | None = None
    vehicle: ForkliftVehicle | None = None            # the forklift carrying the camera, forklift views only
    faces: list[PalletFaceGT] = field(default_factory=list)   # front face and pockets of pallets in view

    def __post_init__(self) -> None:
        h, w = self.depth_m.shape
        if self.rgb.shape != (h, w, 3) or self.rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be ({h}, {w}, 3) uint8, got {self.rgb.shape} {self.rgb.dtype}")
        if self.depth_ideal_m.shape != (h, w):
            raise ValueError(f"depth_ideal_m must be ({h}, {w}), got {self.depth_ideal_m.shape}")

    @property
    def T_vehicle_cam(self) -> np.ndarray | None:
        """(4, 4) camera-to-vehicle transform (forklift views), else None."""
        return None if self.vehicle is None else self.vehicle.T_vehicle_cam

    def pallet(self, instance_id: int) -> PalletGT:
        for p in self.pallets:
            if p.instance_id == instance_id:
                return p
        raise KeyError(f"pallet instance {instance_id} is not in view in this frame")


def _pack(scene: Scene):
    T_cam_world = scene.T_cam_world
    T = np.stack([b.T_world_box for b in scene.boxes]) if scene.boxes else np.zeros((0, 4, 4))
    T_cam_box = T_cam_world[None] @ T
    half = np.array([b.half_size_m for b in scene.boxes]).reshape(-1, 3)
    material = np.array([b.material for b in scene.boxes], dtype=np.int64)
    color = np.array([b.color for b in scene.boxes]).reshape(-1, 3)
    seed = np.array([b.texture_seed for b in scene.boxes], dtype=np.int64)
    inst = np.array([b.instance_id for b in scene.boxes], dtype=np.int64)
    return T_cam_box[:, :3, :3], T_cam_box[:, :3, 3], half, material, color, seed, inst


def _touches_border(mask: np.ndarray) -> bool:
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def _silhouette_px_count(boxes_m: np.ndarray, T_cam_pallet: np.ndarray, K: np.ndarray,
                         image_hw: tuple[int, int]) -> int:
    """Pixels of a pallet's whole silhouette, the part outside the image included: as BOP's calc_gt_info,
    on a canvas 3x the image with the image in its centre. So a pallet cut by the image border is that much
    less visible (`px_count_all`, `visib_fract`), not fully visible.

    :param boxes_m: (k, 2, 3) the pallet's boards and blocks, pallet frame.
    """
    h, w = image_hw
    K_canvas = K.astype(np.float64).copy()
    K_canvas[0, 2] += w
    K_canvas[1, 2] += h
    lo, hi = boxes_m[:, 0], boxes_m[:, 1]
    R = np.repeat(T_cam_pallet[None, :3, :3], len(lo), axis=0)
    rc = raycast_boxes(R, transform_points(T_cam_pallet, (lo + hi) / 2), (hi - lo) / 2, K_canvas, (3 * h, 3 * w),
                       group=np.ones(len(lo), dtype=np.int64))
    return int(rc.full_masks[1].sum()) if 1 in rc.full_masks else 0


def _pallet_gts(scene: Scene, depth_sensor: np.ndarray, inst_img: np.ndarray,
                full_masks: dict[int, np.ndarray]) -> list[PalletGT]:
    h, w = scene.image_hw
    out = []
    for p in scene.pallets:
        full = full_masks.get(p.instance_id)
        if full is None or not full.any():
            continue
        model = get_pallet_model(p.model_name)
        T_cam_pallet = scene.T_cam_world @ p.T_world_pallet
        visib = inst_img == p.instance_id
        corners = transform_points(T_cam_pallet, box_corners(model.boxes_m).reshape(-1, 3))
        if np.all(corners[:, 2] > 1e-3):   # projected silhouette bbox, may reach past the image
            uv = project_points(corners, scene.K)
            lo, hi = np.floor(uv.min(0) + 0.5), np.floor(uv.max(0) + 0.5)
            bbox_obj = np.array([lo[0], lo[1], hi[0] - lo[0] + 1, hi[1] - lo[1] + 1], dtype=np.int64)
        else:
            bbox_obj = mask_bbox_xywh(full)
        half = model.size_m / 2
        box3d = transform_points(T_cam_pallet, box_corners(np.stack([-half, half])[None])[0])
        n_all, n_vis = int(full.sum()), int(visib.sum())
        if _touches_border(full):
            n_all = max(n_all, _silhouette_px_count(model.boxes_m, T_cam_pallet, scene.K, (h, w)))
        out.append(PalletGT(
            instance_id=p.instance_id, model_name=p.model_name, obj_id=obj_id_of(p.model_name),
            T_cam_pallet=T_cam_pallet, mask_visib=visib, mask_full=full, bbox_obj_xywh=bbox_obj,
            bbox_visib_xywh=mask_bbox_xywh(visib), box3d_cam=box3d, px_count_all=n_all, px_count_visib=n_vis,
            px_count_valid=int((visib & (depth_sensor > 0)).sum()), visib_fract=n_vis / n_all))
    return out


def _raycast(scene: Scene):
    R, t, half, material, color, seed, inst = _pack(scene)
    rc = raycast_boxes(R, t, half, scene.K, scene.image_hw, group=inst)
    inst_img = np.where(rc.box_index >= 0, inst[np.maximum(rc.box_index, 0)], 0)
    return rc, inst_img, (R, t, half, material, color, seed)


def _pixel_info(hits: SurfaceHits, surface_rgb: np.ndarray, rgb_lin: np.ndarray, box_index: np.ndarray) -> PixelInfo:
    """Per-pixel normals, albedo (grey level of the surface colour) and lit intensity for the depth models."""
    return PixelInfo(normal_cam=hits.to_image(hits.normal_cam), albedo=hits.to_image(surface_rgb.mean(1)),
                     box_index=box_index, intensity=rgb_lin.mean(2).astype(np.float32))


def render_scene(scene: Scene, depth_model: DepthModel | None = None, rgb_model: RgbCameraModel | None = None,
                 rng: np.random.Generator | None = None, _cast=None, appearance: Appearance | None = None) -> SimFrame:
    """Render a scene with exact ground truth.

    :param depth_model: None = ideal depth sensor; else a model from `depth_sensors` (D435, OAK-D, ToF).
    :param rgb_model: None = noise-free camera. Not used with an appearance (its camera effects apply).
    :param rng: noise source for the sensor models (required when one is given, or an appearance).
    :param appearance: None = the plain look (`shading.shade`); else the drawn randomised appearance
        (`appearance.draw_appearance`): styles, colours, lamps with shadows, camera effects.
    """
    scene.validate()
    if (depth_model is not None or rgb_model is not None or appearance is not None) and rng is None:
        raise ValueError("render_scene: pass rng when a sensor model is given (noise must be seeded)")
    if appearance is not None and len(appearance.style) != len(scene.boxes):
        raise ValueError(f"render_scene: the appearance was drawn for {len(appearance.style)} boxes, the scene has "
                         f"{len(scene.boxes)}")
    rc, inst_img, packed = _raycast(scene) if _cast is None else _cast
    R, t, half, material, color, seed = packed
    rays = pixel_rays(scene.K, scene.image_hw)
    hits = surface_rgb = None
    if appearance is None:
        light_cam = scene.T_cam_world[:3, :3] @ scene.light.direction_world
        rgb_lin = shade(rc.depth_m, rc.box_index, rays, R, t, half, material, color, seed, light_cam,
                        scene.light.intensity, scene.light.ambient, scene.light.headlight)
    else:
        hits = surface_hits(rc.depth_m, rc.box_index, rays, R, t, half)
        surface_rgb = surface_albedo(hits, material, seed, appearance)
        rgb_lin = shade_appearance(hits, surface_rgb, material, appearance, scene.T_cam_world, (R, t, half))
    info = None
    if depth_model is not None and not isinstance(depth_model, StereoDepthModel):
        if hits is None:
            hits = surface_hits(rc.depth_m, rc.box_index, rays, R, t, half)
            surface_rgb = albedo(hits, material, color, seed)
        info = _pixel_info(hits, surface_rgb, rgb_lin, rc.box_index)
    depth = apply_sensor(rc.depth_m, float(scene.K[0, 0]), depth_model, info, rng)
    if appearance is None:
        rgb = apply_rgb_model(rgb_lin, rgb_model or RgbCameraModel(shot_noise=0.0), rng)
    else:
        rgb = apply_camera_effects(rgb_lin, appearance.camera, rng)
    if isinstance(depth_model, ToFDepthModel) and depth_model.register_rgb:
        rgb = register_rgb_to_depth(rgb, depth)
    gts = _pallet_gts(scene, depth, inst_img, rc.full_masks)
    return SimFrame(rgb=rgb, depth_m=depth, depth_ideal_m=rc.depth_m, K=scene.K.copy(),
                    T_world_cam=scene.T_world_cam.copy(), pallets=gts, target_instance=scene.target_instance)


def with_forklift_gt(scene: Scene, frame: SimFrame) -> SimFrame:
    """`frame` with the vehicle's camera mounting and the front face and pockets of every pallet in view
    (with the visible part of each pocket, measured on the exact depth)."""
    frame.vehicle = scene.vehicle
    faces = face_gts(scene, [p.instance_id for p in frame.pallets])
    frame.faces = [replace(f, pocket_visib_fract=pocket_visibility(f, frame.pallet(f.instance_id).T_cam_pallet,
                                                                   frame.depth_ideal_m, frame.K)) for f in faces]
    return frame


def render_with_sensors(config: SimConfig, scene: Scene, seed: int, index: int, cast=None) -> SimFrame:
    """Render `scene` through frame `index`'s draw of `config`'s sensors and appearance (seeded by (seed, index)).

    :param cast: `_raycast(scene)` when already computed, else None."""
    sensor_rng = np.random.default_rng((int(seed), int(index), 1))
    if config.sensor_mix:
        pick = np.random.default_rng((int(seed), int(index), 3)).integers(len(config.sensor_mix))
        depth_model = depth_model_for(config.sensor_mix[int(pick)])
    else:
        depth_model = config.sensor_model if config.sensor_model is not None else depth_model_for(config.sensor)
    if config.appearance is not None:
        app_rng = np.random.default_rng((int(seed), int(index), 2))
        appearance = draw_appearance(config.appearance, scene, app_rng)
        return render_scene(scene, depth_model, None, sensor_rng, _cast=cast, appearance=appearance)
    blur = sensor_rng.uniform(2, 9) if sensor_rng.random() < config.blur_prob else 0.0
    rgb_model = RgbCameraModel(exposure=sensor_rng.uniform(*config.exposure),
                               noise_sigma=sensor_rng.uniform(*config.rgb_noise_sigma),
                               shot_noise=0.004 if config.sensor == "ideal" else 0.01, blur_px=blur)
    return render_scene(scene, depth_model, rgb_model, sensor_rng, _cast=cast)


def generate_frame(config: SimConfig, seed: int, index: int = 0) -> SimFrame:
    """Frame `index` of the dataset drawn from `config` with `seed`.

    Scenes are redrawn (up to config.max_attempts) until the camera is clear of geometry and the target
    pallet's visible fraction reaches config.min_target_visib; SceneError otherwise.
    """
    rng = np.random.default_rng((int(seed), int(index)))
    best = 0.0
    for attempt in range(config.max_attempts):
        try:
            scene = build_scene(config, rng)
            scene.validate()
        except SceneError as exc:
            log.debug("frame %d attempt %d: %s", index, attempt, exc)
            continue
        cast = _raycast(scene)
        rc, inst_img, _ = cast
        full = rc.full_masks.get(scene.target_instance)
        n_all = 0 if full is None else int(full.sum())
        # The whole target must be inside the image (its silhouette does not touch the border) ...
        inside = n_all > 0 and (not config.target_inside or not _touches_border(full))
        if inside and _touches_border(full):   # ... or, where allowed, its visible fraction counts the part out of view
            target = next(p for p in scene.pallets if p.instance_id == scene.target_instance)
            n_all = max(n_all, _silhouette_px_count(get_pallet_model(target.model_name).boxes_m,
                                                    scene.T_cam_world @ target.T_world_pallet, scene.K, scene.image_hw))
        visib = int((inst_img == scene.target_instance).sum()) / n_all if n_all else 0.0
        best = max(best, visib if inside else 0.0)
        if inside and visib >= config.min_target_visib:
            return with_forklift_gt(scene, render_with_sensors(config, scene, seed, index, cast))
        log.debug("frame %d attempt %d: target visible fraction %.2f, inside image %s", index, attempt, visib,
                  inside)
    where = "fully in the image and " if config.target_inside else ""
    raise SceneError(f"preset {config.name!r}: no scene with the target pallet {where}at least "
                     f"{config.min_target_visib:.0%} visible after {config.max_attempts} attempts (best "
                     f"{best:.0%}); widen the field of view, move the camera back or lower min_target_visib")
