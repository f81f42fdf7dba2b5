"""Randomised appearance: camera effects, textures, lamps and shadows, and frames drawn with it."""
import math
from dataclasses import replace

import numpy as np
import pytest

from pallet6d.runtime import geometry as g
from pallet6d.sim import camera_effects as fx
from pallet6d.sim.appearance import AppearanceConfig, draw_appearance
from pallet6d.sim.generate import generate_frame, render_scene
from pallet6d.sim.lighting import shadow_visibility
from pallet6d.sim.pallets import get_pallet_model
from pallet6d.sim.presets import PAPER_PRESETS, PRESETS, SimConfig, get_preset
from pallet6d.sim.scene import MATERIALS, Box, PalletPlacement, Scene, look_at_T_world_cam, pallet_boxes
from pallet6d.sim.textures import PLASTIC_PALLET_COLORS, STYLES, apply_style, dirt_overlay, wear_overlay
from pallet6d.sim.tof import ToFDepthModel

K_SMALL = np.array([[200.0, 0, 159.5], [0, 200.0, 89.5], [0, 0, 1]])


def linear_image(seed=0, h=40, w=60):
    return np.random.default_rng(seed).uniform(0, 1, (h, w, 3)).astype(np.float32)


# --- camera effects ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("op", [
    lambda img, rng: fx.white_balance(img, (1.1, 1.0, 0.9)),
    lambda img, rng: fx.vignette(img, 0.5),
    lambda img, rng: fx.defocus_blur(img, 1.5),
    lambda img, rng: fx.motion_blur(img, 9, 20.0),
    lambda img, rng: fx.chromatic_shift(img, 1.5),
    lambda img, rng: fx.sensor_noise(img, 0.02, 0.01, rng),
    lambda img, rng: fx.tone_curve(img, 0.8),
])
def test_linear_ops_keep_shape_and_dtype(op):
    img = linear_image()
    out = op(img, np.random.default_rng(0))
    assert out.shape == img.shape and out.dtype == np.float32 and np.isfinite(out).all()


def test_range_preserving_ops_stay_in_range():
    img = linear_image()
    for out in (fx.vignette(img, 0.8), fx.defocus_blur(img, 2.0), fx.motion_blur(img, 7, 45.0),
                fx.chromatic_shift(img, 2.0), fx.tone_curve(img * 3 - 1, 1.2)):
        assert out.min() >= 0 and out.max() <= 1 + 1e-6


def test_vignetting_darkens_corners_not_the_centre():
    out = fx.vignette(np.ones((41, 61, 3), np.float32), 0.4)
    assert out[20, 30].min() == pytest.approx(1.0) and out[0, 0].max() == pytest.approx(0.6, abs=1e-5)


def test_motion_blur_smears_along_its_direction_only():
    img = np.zeros((41, 41, 3), np.float32)
    img[20, 20] = 1.0
    out = fx.motion_blur(img, 9, 0.0)
    assert (out[20, 16:25, 0] > 0).all() and out[16, 20, 0] == 0 and out[24, 20, 0] == 0


def test_chromatic_shift_moves_red_and_blue_apart_at_the_border():
    img = np.zeros((61, 81, 3), np.float32)
    img[:, 70:] = 1.0                                        # an edge near the right border
    out = fx.chromatic_shift(img, 3.0)
    red_edge = np.argmax(out[30, :, 0] > 0.5)
    blue_edge = np.argmax(out[30, :, 2] > 0.5)
    assert blue_edge < 70 < red_edge and red_edge - blue_edge >= 3      # red magnified, blue shrunk


def test_sensor_noise_grows_with_signal_and_is_seeded():
    dark, bright = np.full((60, 60, 3), 0.05, np.float32), np.full((60, 60, 3), 0.8, np.float32)
    rng = np.random.default_rng(1)
    assert fx.sensor_noise(bright, 0.05, 0.0, rng).std() > 2 * fx.sensor_noise(dark, 0.05, 0.0, rng).std()
    a = fx.sensor_noise(bright, 0.05, 0.01, np.random.default_rng(7))
    b = fx.sensor_noise(bright, 0.05, 0.01, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)


def test_jpeg_keeps_uint8_rgb_and_loses_a_little():
    img = fx.to_uint8(linear_image(3, 64, 64))
    out = fx.jpeg(img, 40)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert 0 < np.abs(out.astype(int) - img).mean() < 60
    with pytest.raises(ValueError, match="uint8"):
        fx.jpeg(img.astype(np.float32), 50)


def test_auto_exposure_brings_a_dark_image_up():
    dark = np.full((10, 10, 3), 0.05, np.float32)
    assert fx.auto_exposure_gain(dark, 0.4) == pytest.approx(8.0)


def test_apply_camera_effects_is_uint8_and_seeded():
    effects = fx.CameraEffects(exposure=1.2, wb_gains=(1.1, 1.0, 0.9), vignetting=0.3, defocus_sigma_px=1.0,
                               motion_blur_px=5, chromatic_px=1.0, shot_noise=0.02, read_noise=0.01, gamma=0.9,
                               jpeg_quality=60)
    img = linear_image(5)
    a = fx.apply_camera_effects(img, effects, np.random.default_rng(2))
    b = fx.apply_camera_effects(img, effects, np.random.default_rng(2))
    c = fx.apply_camera_effects(img, effects, np.random.default_rng(3))
    assert a.dtype == np.uint8 and a.shape == img.shape
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_bad_camera_effects_raise():
    with pytest.raises(ValueError):
        fx.CameraEffects(vignetting=2.0)
    with pytest.raises(ValueError, match="H, W, 3"):
        fx.vignette(np.zeros((4, 4), np.float32), 0.2)


# --- textures ---------------------------------------------------------------------------------------------------

def surface_points(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    half = np.tile([0.6, 0.05, 0.04], (n, 1)).astype(np.float32)
    p = (rng.uniform(-1, 1, (n, 3)) * half).astype(np.float32)
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = half[np.arange(n), axis]         # on the faces
    return p, half, axis, np.full(n, 17, np.int64), np.tile([0.2, 0.4, 0.7], (n, 1)).astype(np.float32)


@pytest.mark.parametrize("style", sorted(STYLES))
def test_every_style_gives_a_valid_colour_and_is_deterministic(style):
    p, half, axis, seed, color = surface_points()
    rgb = np.zeros_like(color)
    a = apply_style(rgb, np.full(len(p), style), p, half, axis, seed, color)
    b = apply_style(rgb, np.full(len(p), style), p, half, axis, seed, color)
    assert a.shape == color.shape and a.dtype == np.float32
    assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.005   # patterned, not flat
    np.testing.assert_array_equal(a, b)


def test_style_zero_keeps_the_material_texture():
    p, half, axis, seed, color = surface_points()
    rgb = np.random.default_rng(0).uniform(0, 1, color.shape).astype(np.float32)
    np.testing.assert_array_equal(apply_style(rgb, np.zeros(len(p), int), p, half, axis, seed, color), rgb)


def test_dirt_and_wear_are_off_at_zero_strength_and_change_colour_when_on():
    p, half, axis, seed, color = surface_points()
    zero, full = np.zeros(len(p), np.float32), np.ones(len(p), np.float32)
    np.testing.assert_allclose(dirt_overlay(color, p, axis, seed, zero), color)
    np.testing.assert_array_equal(wear_overlay(color, p, half, axis, seed, zero), color)
    dirty = dirt_overlay(color, p, axis, seed, full)
    worn = wear_overlay(color, p, half, axis, seed, full)
    assert np.abs(dirty - color).max(1).mean() > 0.02 and (np.abs(worn - color).max(1) > 0.01).mean() > 0.02
    assert dirty.min() >= 0 and worn.max() <= 1


# --- shadows ----------------------------------------------------------------------------------------------------

def test_a_box_between_a_lamp_and_the_floor_casts_a_shadow():
    # Camera frame as world: lamp at y = -3 (up), a box at y = -1, floor points at y = 0 around x = 0.
    xs = np.linspace(-2, 2, 41)
    pts = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 4.0)], 1)
    R, t, half = np.eye(3)[None], np.array([[0.0, -1.0, 4.0]]), np.array([[0.3, 0.1, 0.3]])
    lit = shadow_visibility(pts, np.array([0.0, -3.0, 4.0]), np.array([0.0, 1.0, 0.0]), R, t, half)
    # Shadow of a 0.6 m wide box 2 m below the lamp on a floor 3 m below it: 0.6 * 3 / 2.1 ~ 0.86 m wide.
    shadowed = xs[~lit]
    assert shadowed.size > 0 and abs(shadowed.mean()) < 1e-9 and 0.7 <= shadowed.max() - shadowed.min() <= 0.9


def test_points_on_the_lit_face_of_the_blocking_box_itself_are_lit():
    R, t, half = np.eye(3)[None], np.array([[0.0, -1.0, 4.0]]), np.array([[0.3, 0.1, 0.3]])
    top = np.array([[0.0, -1.1, 4.0], [0.2, -1.1, 4.1]])      # on the face towards the lamp
    lit = shadow_visibility(top, np.array([0.0, -3.0, 4.0]), np.array([0.0, 1.0, 0.0]), R, t, half)
    assert lit.all()


# --- frames with an appearance ----------------------------------------------------------------------------------

def plastic_pallet_scene():
    model = get_pallet_model("epal")
    T = g.make_T(np.eye(3), [0.0, 0.0, model.size_m[2] / 2])
    placement = PalletPlacement(1, "epal", T)
    floor = Box(g.make_T(np.eye(3), [0, 0, -0.05]), [20, 20, 0.05], MATERIALS.index("concrete"), [0.6, 0.6, 0.6])
    boxes = [floor, *[Box(b.T_world_box, b.half_size_m, MATERIALS.index("plastic"), b.color, 1, b.texture_seed)
                      for b in pallet_boxes(placement, np.array([0.5, 0.5, 0.5]), 3)]]
    T_world_cam = look_at_T_world_cam(np.array([-2.5, -1.0, 1.0]), np.array([0.0, 0.0, 0.07]))
    return Scene(boxes, [placement], T_world_cam, K_SMALL, (180, 320), target_instance=1)


def test_plastic_pallets_get_one_palette_colour_per_pallet():
    scene = plastic_pallet_scene()
    palette = np.array(list(PLASTIC_PALLET_COLORS.values()))
    for seed in range(5):
        app = draw_appearance(AppearanceConfig(), scene, np.random.default_rng(seed))
        pallet_colors = app.color[1:]
        assert np.allclose(pallet_colors, pallet_colors[0])
        ratio = pallet_colors[0] / np.maximum(palette, 1e-3)
        assert np.any(np.all(np.abs(ratio - ratio.mean(1, keepdims=True)) < 0.02, axis=1) &
                      (ratio.mean(1) > 0.85) & (ratio.mean(1) < 1.15))


def test_appearance_frame_is_seeded_and_keeps_the_ground_truth():
    cfg = replace(get_preset("virtual-occluded").with_image_size(160, 64), appearance=AppearanceConfig())
    a, b, c = generate_frame(cfg, 3, 0), generate_frame(cfg, 3, 0), generate_frame(cfg, 4, 0)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.rgb, c.rgb)
    plain = generate_frame(replace(cfg, appearance=None), 3, 0)
    np.testing.assert_array_equal(a.depth_ideal_m, plain.depth_ideal_m)    # same scene, other look
    assert [p.instance_id for p in a.pallets] == [p.instance_id for p in plain.pallets]
    assert a.rgb.dtype == np.uint8 and not np.array_equal(a.rgb, plain.rgb)


@pytest.mark.parametrize("sensor", ["ideal", "d435", "oakd", "tof"])
def test_every_sensor_renders_a_preset_frame(sensor):
    cfg = replace(get_preset("indoor-noisy").with_image_size(160, 96), sensor=sensor, appearance=AppearanceConfig())
    frame = generate_frame(cfg, 0, 1)
    assert frame.depth_m.dtype == np.float32 and frame.depth_m.shape == (96, 160)
    assert (frame.depth_m > 0).mean() > 0.2
    if sensor == "tof":                                       # colour registered onto depth, black = no depth
        assert (frame.rgb[frame.depth_m == 0] == 0).all()
        assert ((frame.rgb.max(2) == 0) & (frame.depth_m > 0)).mean() < 0.01
    if sensor == "ideal":
        np.testing.assert_array_equal(frame.depth_m, frame.depth_ideal_m)


def test_render_scene_needs_rng_and_a_matching_appearance():
    scene = plastic_pallet_scene()
    app = draw_appearance(AppearanceConfig(), scene, np.random.default_rng(0))
    with pytest.raises(ValueError, match="rng"):
        render_scene(scene, appearance=app)
    scene.boxes = scene.boxes[:-1]
    with pytest.raises(ValueError, match="boxes"):
        render_scene(scene, rng=np.random.default_rng(0), appearance=app)


@pytest.mark.parametrize("kwargs, match", [
    (dict(chep_prob=1.5), "chep_prob"),
    (dict(lamps=(3, 1)), "lamps"),
    (dict(plastic_colors=("purple",)), "plastic_colors"),
    (dict(exposure=(0.0, 1.0)), "exposure"),
])
def test_bad_appearance_configs_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AppearanceConfig(**kwargs)


def test_sim_config_takes_the_sensor_names_and_checks_models():
    base = dict(name="t", width=160, height=80, hfov_deg=80.0)
    for name in ("ideal", "d435", "oakd", "tof"):
        assert SimConfig(**base, sensor=name).sensor == name
    with pytest.raises(ValueError, match="ToFDepthModel"):
        SimConfig(**base, sensor="d435", sensor_model=ToFDepthModel())
    with pytest.raises(TypeError, match="AppearanceConfig"):
        SimConfig(**base, appearance={"shadows": True})
    assert all(PRESETS[n].appearance is None and PRESETS[n].sensor_model is None for n in PAPER_PRESETS)
    assert math.isfinite(PRESETS["indoor-noisy"].K[0, 0])


def test_lamp_shadows_on_a_rendered_frame_match_exact_shadow_rays():
    from pallet6d.sim.generate import _raycast
    from pallet6d.sim.lighting import PointLight, light_hits
    from pallet6d.sim.raycast import pixel_rays
    from pallet6d.sim.shading import surface_hits

    scene = plastic_pallet_scene()
    rc, _, (R, t, half, *_) = _raycast(scene)
    hits = surface_hits(rc.depth_m, rc.box_index, pixel_rays(scene.K, scene.image_hw), R, t, half)
    lamp = PointLight(np.array([0.3, 0.4, 2.5]), np.ones(3), 1.0, cone_deg=75.0)
    lit = light_hits(hits, lamp, scene.T_cam_world, (R, t, half), shadows=False)
    shaded = light_hits(hits, lamp, scene.T_cam_world, (R, t, half), shadows=True)
    need = lit > 1e-4
    exact = np.zeros_like(need)
    exact[need] = shadow_visibility(hits.p_cam[need], scene.T_cam_world[:3, :3] @ lamp.position_world
                                    + scene.T_cam_world[:3, 3], scene.T_cam_world[:3, :3] @ lamp.axis_world,
                                    R, t, half, max_tan=10.0)
    on_floor = hits.box == 0
    assert (~exact & need & on_floor).sum() > 200                  # the pallet shadows the floor
    agree = (shaded[need] > 0) == exact[need]
    assert agree.mean() > 0.98                                     # 2x2 sampling changes only shadow edges
    assert np.all(shaded <= lit + 1e-6)


def test_camera_effects_on_a_black_frame_stay_finite_and_dark():
    effects = fx.CameraEffects(shot_noise=0.02, read_noise=0.0, jpeg_quality=50)
    out = fx.apply_camera_effects(np.zeros((16, 16, 3), np.float32), effects, np.random.default_rng(0))
    assert out.dtype == np.uint8 and out.max() <= 2


def test_ambient_occlusion_darkens_a_concave_corner_not_an_open_floor():
    from pallet6d.sim.lighting import ambient_occlusion
    from pallet6d.sim.raycast import pixel_rays, raycast_boxes
    from pallet6d.sim.shading import surface_hits

    # Floor slab (top at y = 0.5 m below the camera) meeting a wall at z = 3 m.
    R = np.stack([np.eye(3)] * 2)
    t, half = np.array([[0.0, 0.55, 2.0], [0.0, -0.5, 3.05]]), np.array([[5.0, 0.05, 1.0], [5.0, 1.0, 0.05]])
    K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
    rc = raycast_boxes(R, t, half, K, (240, 320))
    hits = surface_hits(rc.depth_m, rc.box_index, pixel_rays(K, (240, 320)), R, t, half)
    ao = hits.to_image(ambient_occlusion(hits))
    corner = int(np.nonzero(rc.box_index[:, 160] == 0)[0].min())       # first floor row under the wall
    assert ao[corner - 3:corner + 1, 80:240].mean() > 0.15
    assert ao[-20:, 80:240].max() < 0.02 and ao[:40, 80:240].max() < 0.02
    assert ao.min() >= 0 and ao.max() <= 1
