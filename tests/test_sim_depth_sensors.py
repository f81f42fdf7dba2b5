"""ToF and OAK-D-like depth models, the sensor names, and the D435 model kept as it is."""
from dataclasses import replace

import numpy as np
import pytest

from pallet6d.sim.depth_sensors import apply_sensor, check_sensor_model, depth_model_for
from pallet6d.sim.oakd import OakdStereoModel, apply_oakd
from pallet6d.sim.raycast import pixel_rays, raycast_boxes
from pallet6d.sim.sensors import SENSORS, PixelInfo, StereoDepthModel, apply_depth_model
from pallet6d.sim.shading import surface_hits
from pallet6d.sim.tof import ToFDepthModel, apply_tof, multipath_bias_m, register_rgb_to_depth

F_PX = 400.0
QUIET_TOF = ToFDepthModel(sigma_ref_m=0.0, multipath_gain=0.0, flying_prob=0.0)


def wall_info(h, w, albedo=0.5, intensity=None):
    """A fronto-parallel wall: normals towards the camera."""
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = -1
    alb = np.broadcast_to(np.asarray(albedo, np.float32), (h, w)).copy()
    inten = np.full((h, w), 0.5, np.float32) if intensity is None else intensity
    return PixelInfo(normal_cam=normal, albedo=alb, box_index=np.zeros((h, w), np.int64), intensity=inten)


def textured(h, w, seed=0):
    return np.random.default_rng(seed).uniform(0.2, 0.8, (h, w)).astype(np.float32)


def step_depth(near=1.0, far=3.0, h=40, w=200):
    d = np.full((h, w), far, dtype=np.float32)
    d[:, 100:140] = near
    return d


# --- names and dispatch -------------------------------------------------------------------------------------------

def test_sensor_names_and_default_models():
    assert SENSORS == ("ideal", "d435", "oakd", "tof")
    assert depth_model_for("ideal") is None
    assert isinstance(depth_model_for("d435"), StereoDepthModel)
    assert isinstance(depth_model_for("oakd"), OakdStereoModel)
    assert isinstance(depth_model_for("tof"), ToFDepthModel)
    with pytest.raises(ValueError, match="tof"):
        depth_model_for("kinect")


@pytest.mark.parametrize("name, model", [("d435", ToFDepthModel()), ("ideal", StereoDepthModel()),
                                         ("tof", OakdStereoModel())])
def test_a_model_of_another_sensor_is_refused(name, model):
    with pytest.raises(ValueError, match=name):
        check_sensor_model(name, model)


def test_d435_through_the_dispatch_is_the_d435_model_itself():
    d = step_depth()
    a = apply_sensor(d, F_PX, StereoDepthModel(), None, np.random.default_rng(3))
    b = apply_depth_model(d, F_PX, StereoDepthModel(), np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("model", [OakdStereoModel(), ToFDepthModel()])
def test_models_that_need_scene_data_say_so(model):
    with pytest.raises(ValueError, match="PixelInfo"):
        apply_sensor(step_depth(), F_PX, model, None, np.random.default_rng(0))


@pytest.mark.parametrize("cls, kwargs", [(ToFDepthModel, dict(min_m=5.0, max_m=1.0)),
                                         (ToFDepthModel, dict(flying_prob=2.0)),
                                         (OakdStereoModel, dict(baseline_m=0.0)),
                                         (OakdStereoModel, dict(subpixel_bits=9))])
def test_bad_model_parameters_raise(cls, kwargs):
    with pytest.raises(ValueError):
        cls(**kwargs)


# --- ToF --------------------------------------------------------------------------------------------------------

def test_tof_holes_on_dark_surfaces():
    alb = np.full((40, 80), 0.6, np.float32)
    alb[:, :40] = 0.04                                        # black plastic
    out = apply_tof(np.full((40, 80), 2.5, np.float32), F_PX, QUIET_TOF, wall_info(40, 80, alb),
                    np.random.default_rng(0))
    assert (out[:, :40] == 0).all() and (out[:, 40:] > 0).all()


def test_tof_holes_on_far_surfaces():
    info = wall_info(30, 30, 0.3)
    near = apply_tof(np.full((30, 30), 1.5, np.float32), F_PX, QUIET_TOF, info, np.random.default_rng(0))
    far = apply_tof(np.full((30, 30), 6.0, np.float32), F_PX, QUIET_TOF, info, np.random.default_rng(0))
    assert (near > 0).all() and (far == 0).all()


def test_tof_holes_on_grazing_surfaces():
    info = wall_info(20, 20, 0.3)
    info.normal_cam[:] = np.array([np.sin(np.radians(85)), 0, -np.cos(np.radians(85))], np.float32)
    out = apply_tof(np.full((20, 20), 2.0, np.float32), F_PX, QUIET_TOF, info, np.random.default_rng(0))
    assert (out == 0).all()


def test_tof_flying_pixels_only_at_depth_edges():
    d = step_depth(1.0, 2.0)
    model = replace(QUIET_TOF, flying_prob=1.0)
    out = apply_tof(d, F_PX, model, wall_info(*d.shape, 0.8), np.random.default_rng(1))
    moved = (out > 0) & (np.abs(out - d) > 0.01)
    cols = np.nonzero(moved)[1]
    assert moved.sum() > 40                                   # the edges have mixed pixels ...
    assert set(np.unique(cols)) <= {99, 100, 139, 140}        # ... and only the edges
    assert np.all((out[moved] >= 1.0) & (out[moved] <= 2.0))  # between the two surfaces


def test_tof_noise_grows_with_range():
    model = replace(QUIET_TOF, sigma_ref_m=0.004, min_amplitude=0.0)
    stds = []
    for z in (1.0, 2.0, 4.0):
        out = apply_tof(np.full((100, 120), z, np.float32), F_PX, model, wall_info(100, 120, 0.5),
                        np.random.default_rng(2))
        stds.append(out.std())
        assert abs(out.mean() - z) < 0.002
    assert stds[0] < stds[1] < stds[2]
    assert 0.6 * 0.004 < stds[1] < 1.4 * 0.004                # sigma_ref at ref_m = 2 m on albedo 0.5


def corner_scene(h=60, w=80):
    """Floor (y = +0.5 m below the camera) meeting a wall at z = 3 m: a concave corner at the image centre row."""
    R = np.stack([np.eye(3)] * 2)
    t = np.array([[0.0, 0.55, 2.0], [0.0, -0.5, 3.05]])       # floor slab (top at y = 0.5), wall (front z = 3)
    half = np.array([[5.0, 0.05, 1.0], [5.0, 1.0, 0.05]])
    K = np.array([[F_PX / 4, 0, (w - 1) / 2], [0, F_PX / 4, (h - 1) / 2], [0, 0, 1]])
    rc = raycast_boxes(R, t, half, K, (h, w))
    hits = surface_hits(rc.depth_m, rc.box_index, pixel_rays(K, (h, w)), R, t, half)
    info = PixelInfo(hits.to_image(hits.normal_cam), hits.to_image(np.full(hits.pix.size, 0.7)), rc.box_index,
                     np.full((h, w), 0.5, np.float32))
    return rc.depth_m, K[0, 0], info, rc.box_index


def test_tof_multipath_lengthens_depth_near_a_concave_corner():
    depth, f, info, box = corner_scene()
    bias = multipath_bias_m(depth, f, info, radius_px=24)
    corner_row = int(np.nonzero(box[:, 40] == 0)[0].min())  # first floor row under the wall
    near_corner = bias[corner_row - 3:corner_row, 30:50].mean()
    far_up = bias[2:5, 30:50].mean()
    assert (bias >= 0).all()
    assert near_corner > 0.003 and near_corner > 3 * far_up


def test_tof_no_multipath_on_a_flat_wall():
    bias = multipath_bias_m(np.full((40, 60), 2.0, np.float32), F_PX, wall_info(40, 60, 0.9))
    assert np.abs(bias).max() < 1e-6


def test_tof_registered_rgb_is_black_exactly_where_depth_is_invalid():
    alb = np.full((20, 30), 0.6, np.float32)
    alb[:, :10] = 0.02
    depth = apply_tof(np.full((20, 30), 2.0, np.float32), F_PX, ToFDepthModel(), wall_info(20, 30, alb),
                      np.random.default_rng(0))
    rgb = register_rgb_to_depth(np.full((20, 30, 3), 200, np.uint8), depth)
    assert (rgb[depth == 0] == 0).all() and (rgb[depth > 0] == 200).all() and (depth == 0).any()


def test_tof_is_seeded():
    d = step_depth()
    info = wall_info(*d.shape)
    a = apply_tof(d, F_PX, ToFDepthModel(), info, np.random.default_rng(4))
    b = apply_tof(d, F_PX, ToFDepthModel(), info, np.random.default_rng(4))
    c = apply_tof(d, F_PX, ToFDepthModel(), info, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


# --- OAK-D ------------------------------------------------------------------------------------------------------

def test_oakd_nothing_nearer_than_the_disparity_search_range():
    model = OakdStereoModel(contrast_threshold=0.0, dropout_prob=0.0)
    z_min = model.min_m(F_PX)                                  # 400 * 0.075 / 95 = 0.316 m
    info = wall_info(30, 40, intensity=textured(30, 40))
    near = apply_oakd(np.full((30, 40), 0.9 * z_min, np.float32), F_PX, model, info, np.random.default_rng(0))
    ok = apply_oakd(np.full((30, 40), 1.5 * z_min, np.float32), F_PX, model, info, np.random.default_rng(0))
    assert (near == 0).all() and (ok > 0).mean() > 0.95


def test_oakd_disparity_is_quantised_to_eighth_pixels():
    model = OakdStereoModel(sigma_disparity_px=0.0, contrast_threshold=0.0, dropout_prob=0.0)
    out = apply_oakd(np.full((20, 20), 5.0, np.float32), F_PX, model, wall_info(20, 20, intensity=textured(20, 20)),
                     np.random.default_rng(0))
    disp = F_PX * 0.075 / out[out > 0].astype(np.float64)
    np.testing.assert_allclose(disp * 8, np.round(disp * 8), atol=0.02)


def test_oakd_left_right_check_removes_the_occluded_band():
    d = step_depth()
    model = OakdStereoModel(contrast_threshold=0.0, dropout_prob=0.0, fatten_px=0)
    out = apply_oakd(d, F_PX, model, wall_info(*d.shape, intensity=textured(*d.shape)), np.random.default_rng(0))
    # Disparity jump f * B * (1 / 1 - 1 / 3) = 20 px of background left of the near object.
    assert (out[:, 81:99] == 0).all()
    assert (out[:, 10:70] > 0).mean() > 0.95


def test_oakd_holes_where_there_is_no_texture():
    model = OakdStereoModel(dropout_prob=0.0)
    d = np.full((40, 60), 2.0, np.float32)
    flat = apply_oakd(d, F_PX, model, wall_info(40, 60, intensity=np.full((40, 60), 0.5, np.float32)),
                      np.random.default_rng(0))
    rich = apply_oakd(d, F_PX, model, wall_info(40, 60, intensity=textured(40, 60)), np.random.default_rng(0))
    assert (flat > 0).mean() < 0.05 and (rich > 0).mean() > 0.95


def test_oakd_noise_grows_with_range():
    model = OakdStereoModel(contrast_threshold=0.0, dropout_prob=0.0)
    stds = []
    for z in (1.0, 2.0, 4.0):
        out = apply_oakd(np.full((100, 120), z, np.float32), F_PX, model,
                         wall_info(100, 120, intensity=textured(100, 120)), np.random.default_rng(1))
        stds.append(out[out > 0].std())
    assert stds[0] < stds[1] < stds[2] and stds[2] / stds[0] > 8      # ~z^2


@pytest.mark.parametrize("model", [OakdStereoModel(), ToFDepthModel(), StereoDepthModel()])
def test_no_surface_gives_no_depth(model):
    d = np.zeros((24, 32), np.float32)
    info = wall_info(24, 32)
    info.normal_cam[:] = 0
    out = apply_sensor(d, F_PX, model, info, np.random.default_rng(0))
    assert out.dtype == np.float32 and out.shape == d.shape and (out == 0).all()


def test_pixel_info_checks_shapes():
    with pytest.raises(ValueError, match="PixelInfo"):
        PixelInfo(np.zeros((4, 5, 3)), np.zeros((4, 4)), np.zeros((4, 5), np.int64), np.zeros((4, 5)))


def test_tof_saturates_on_bright_surfaces_very_near():
    info = wall_info(10, 10, 0.9)
    near = apply_tof(np.full((10, 10), 0.35, np.float32), F_PX, QUIET_TOF, info, np.random.default_rng(0))
    ok = apply_tof(np.full((10, 10), 0.5, np.float32), F_PX, QUIET_TOF, info, np.random.default_rng(0))
    assert (near == 0).all() and (ok > 0).all()


def test_oakd_median_fills_scattered_holes_and_smooths():
    d = np.full((60, 80), 2.0, np.float32)
    rng_img = np.random.default_rng(3)
    weak = (0.5 + 0.0033 * rng_img.standard_normal((60, 80))).astype(np.float32)  # barely textured wall
    info = wall_info(60, 80, intensity=weak)
    raw = apply_oakd(d, F_PX, OakdStereoModel(median_px=0, dropout_prob=0.0), info, np.random.default_rng(1))
    med = apply_oakd(d, F_PX, OakdStereoModel(median_px=5, dropout_prob=0.0), info, np.random.default_rng(1))
    assert 0.6 < (raw > 0).mean() < 0.9 and (med > 0).mean() > (raw > 0).mean() + 0.1
    assert med[med > 0].std() < raw[raw > 0].std()
    with pytest.raises(ValueError):
        OakdStereoModel(median_px=4)
