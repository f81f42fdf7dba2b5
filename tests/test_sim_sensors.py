import numpy as np
import pytest

from pallet6d.sim.sensors import (RgbCameraModel, StereoDepthModel, apply_depth_model, apply_rgb_model,
                                  stereo_shadow_mask)

F_PX = 400.0


def step_depth(near=1.0, far=3.0):
    d = np.full((40, 200), far, dtype=np.float32)
    d[:, 100:140] = near
    return d


def test_shadow_is_left_of_the_near_object_with_the_stereo_width():
    d = step_depth()
    shadow = stereo_shadow_mask(d, F_PX, 0.05)
    cols = np.nonzero(shadow[20])[0]
    # Disparity jump f*B*(1/near - 1/far) = 400*0.05*(1 - 1/3) = 13.3 px of background left of column 100.
    assert cols.min() >= 86 and cols.max() == 99 and 12 <= cols.size <= 14
    assert not shadow[:, 140:].any()


def test_no_shadow_on_a_flat_wall():
    assert not stereo_shadow_mask(np.full((10, 50), 2.0, np.float32), F_PX, 0.05).any()


def test_d435_invalid_pixels_near_edges_and_flying_pixels():
    d = step_depth()
    out = apply_depth_model(d, F_PX, StereoDepthModel(dropout_prob=0.0), np.random.default_rng(0))
    assert (out[:, 88:100] == 0).all()                     # occlusion shadow (13 px)
    mid = (out > 1.2) & (out < 2.7)                        # flying pixels between the two depths
    assert mid.any() and np.all(np.nonzero(mid)[1] >= 98) and np.all(np.nonzero(mid)[1] <= 141)
    assert (out[:, :80] > 0).all()                         # far from edges everything is valid


@pytest.mark.parametrize("z", [0.1, 12.0])
def test_out_of_range_is_invalid(z):
    out = apply_depth_model(np.full((20, 20), z, np.float32), F_PX, StereoDepthModel(), np.random.default_rng(0))
    assert (out == 0).all()


def test_noise_std_grows_with_distance_squared():
    model = StereoDepthModel(dropout_prob=0.0)
    stds = []
    for z in (1.0, 2.0, 4.0):
        out = apply_depth_model(np.full((120, 160), z, np.float32), F_PX, model, np.random.default_rng(1))
        stds.append(out[out > 0].std())
        assert abs(out[out > 0].mean() - z) < 0.01 * z
    assert stds[0] < stds[1] < stds[2]
    expected = model.sigma_m(4.0, F_PX)                    # 16 * 0.08 / 20 = 0.064 m
    assert 0.6 * expected < stds[2] < 1.4 * expected
    assert stds[2] / stds[0] > 8                           # ~16 for z^2


def test_depth_is_quantised_to_millimetres():
    out = apply_depth_model(np.full((30, 30), 1.5, np.float32), F_PX, StereoDepthModel(), np.random.default_rng(2))
    v = out[out > 0].astype(np.float64) * 1000
    np.testing.assert_allclose(v, np.round(v), atol=1e-3)


def test_ideal_sensor_keeps_depth():
    d = step_depth()
    np.testing.assert_array_equal(apply_depth_model(d, F_PX, None, np.random.default_rng(0)), d)


def test_sensor_noise_is_seeded():
    d = step_depth()
    a = apply_depth_model(d, F_PX, StereoDepthModel(), np.random.default_rng(5))
    b = apply_depth_model(d, F_PX, StereoDepthModel(), np.random.default_rng(5))
    c = apply_depth_model(d, F_PX, StereoDepthModel(), np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_low_light_is_darker_and_noisier():
    rng = np.random.default_rng(0)
    img = np.full((50, 60, 3), 0.6, np.float32)
    bright = apply_rgb_model(img, RgbCameraModel(exposure=1.0, noise_sigma=0.0, shot_noise=0.0), rng)
    dim = apply_rgb_model(img, RgbCameraModel(exposure=0.3, noise_sigma=0.03), rng)
    assert bright.dtype == np.uint8 and bright.shape == (50, 60, 3)
    assert (bright == 153).all()
    assert dim.mean() < 0.4 * bright.mean() and dim.std() > 3


def test_blur_smooths_edges():
    img = np.zeros((20, 40, 3), np.float32)
    img[:, 20:] = 1.0
    sharp = apply_rgb_model(img, RgbCameraModel(shot_noise=0.0), np.random.default_rng(0))
    blurred = apply_rgb_model(img, RgbCameraModel(shot_noise=0.0, blur_px=7), np.random.default_rng(0))
    assert len(np.unique(sharp[10, :, 0])) == 2 and len(np.unique(blurred[10, :, 0])) > 4


def test_bad_sensor_parameters_raise():
    with pytest.raises(ValueError):
        StereoDepthModel(baseline_m=0.0)
    with pytest.raises(ValueError):
        StereoDepthModel(min_m=5.0, max_m=1.0)
