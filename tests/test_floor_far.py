"""The floor check (`floor.check_floor`) on a seeded simulated forklift view (D435-like depth): a calibration a
little or far off, in height or tilt, fails with the measured numbers; the right one agrees; a view without
floor, or without depth, is "unknown". The frame's own floor near a calibrated one (`floor.refine_floor`) and the
calibration moved onto it (`floor.on_floor`) on the same view."""
from __future__ import annotations

import numpy as np
import pytest

from pallet6d.runtime.floor import (FloorPlane, check_floor, find_floor_anywhere, image_points, on_floor,
                                    plane_angle_deg, refine_floor)

SEED = 4          # of the forklift-approach preset at 424x240: a camera 0.74 m up that sees the floor


@pytest.fixture(scope="module")
def view():
    """(depth_m, K, T_vehicle_cam) of one generated forklift view."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(get_preset("forklift-approach").with_image_size(424, 240), SEED, 0)
    assert f.T_vehicle_cam[2, 3] > 0.6          # room for a calibration 0.5 m too low
    return f.depth_m, f.K, f.T_vehicle_cam


def calibrated_floor(T_vehicle_cam: np.ndarray, height_error_m: float = 0.0, tilt_deg: float = 0.0,
                     roll_deg: float = 0.0) -> FloorPlane:
    """The floor a calibration `height_error_m` too high, and tilted `tilt_deg` about the camera's x axis and
    `roll_deg` about its z axis, stores."""
    a, b = np.radians(tilt_deg), np.radians(roll_deg)
    R = T_vehicle_cam[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]) \
        @ np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    return FloorPlane(R[2].copy(), float(T_vehicle_cam[2, 3] + height_error_m))


def check(depth_m, K, floor):
    return check_floor(floor, depth_m, K, max_tilt_deg=2.0, max_height_diff_m=0.03)


def test_the_right_calibration_agrees(view):
    depth, K, T = view
    c = check(depth, K, calibrated_floor(T))
    assert c.agrees is True and c.tilt_deg < 0.5 and abs(c.height_diff_m) < 0.01


@pytest.mark.parametrize("height_error_m", [0.05, 0.5, 1.0, -0.5])
def test_a_camera_height_off_fails_with_the_measured_height(view, height_error_m):
    depth, K, T = view
    c = check(depth, K, calibrated_floor(T, height_error_m))
    assert c.agrees is False
    assert c.height_diff_m == pytest.approx(-height_error_m, abs=0.02) and c.tilt_deg < 1.0
    assert "camera height off by " + ("-" if height_error_m > 0 else "+") in c.detail


@pytest.mark.parametrize("tilt_deg", [5.0, 20.0])
def test_a_tilted_calibration_fails_with_the_measured_tilt(view, tilt_deg):
    depth, K, T = view
    c = check(depth, K, calibrated_floor(T, tilt_deg=tilt_deg))
    assert c.agrees is False
    assert c.tilt_deg == pytest.approx(tilt_deg, abs=1.0) and abs(c.height_diff_m) < 0.02


def test_far_off_floors_are_found_in_the_whole_image(view):
    depth, K, T = view
    c = check(depth, K, calibrated_floor(T, 0.5))
    assert "found in the whole image" in c.detail
    found = find_floor_anywhere(image_points(depth, K), calibrated_floor(T, 0.5).normal, np.random.default_rng(0))
    assert found.d == pytest.approx(T[2, 3], abs=0.03)


def test_a_wall_filling_the_view_is_unknown(view):
    _, K, T = view
    wall = np.full((240, 424), 1.5, np.float32)             # a wall 1.5 m ahead, square to the camera
    for floor in (calibrated_floor(T), calibrated_floor(T, 0.5), calibrated_floor(T, -0.5)):
        c = check(wall, K, floor)
        assert c.agrees is None and "floor not seen" in c.detail and np.isnan(c.height_diff_m)


@pytest.mark.parametrize("fill", [0.0, np.nan, np.inf, -1.0])
def test_no_depth_is_unknown(view, fill):
    _, K, T = view
    c = check(np.full((240, 424), fill, np.float32), K, calibrated_floor(T, 0.5))
    assert c.agrees is None and "floor not seen" in c.detail


def test_nan_holes_in_the_depth_change_nothing(view):
    depth, K, T = view
    holey = depth.copy()
    holey[np.random.default_rng(0).random(depth.shape) < 0.3] = np.nan
    assert check(holey, K, calibrated_floor(T)).agrees is True
    c = check(holey, K, calibrated_floor(T, 1.0))
    assert c.agrees is False and c.height_diff_m == pytest.approx(-1.0, abs=0.02)


def test_empty_or_malformed_depth_is_refused(view):
    _, K, T = view
    assert check(np.zeros((0, 0), np.float32), K, calibrated_floor(T)).agrees is None
    with pytest.raises(ValueError, match="depth_m must be"):
        check(np.zeros(10, np.float32), K, calibrated_floor(T))
    with pytest.raises(ValueError, match="up_hint"):
        find_floor_anywhere(np.zeros((10, 3)), np.zeros(3), np.random.default_rng(0))


@pytest.mark.parametrize("pitch, roll, height", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (-1.5, 0.0, 0.02),
                                                 (0.0, 1.0, -0.03), (0.5, -0.5, 0.04)])
def test_the_frame_floor_near_a_calibration_a_little_off_is_the_true_floor(view, pitch, roll, height):
    depth, K, T = view
    floor = refine_floor(calibrated_floor(T, height, pitch, roll), depth, K)
    assert floor is not None
    assert plane_angle_deg(floor.normal, T[2, :3]) < 0.15 and abs(floor.d - T[2, 3]) < 0.01


@pytest.mark.parametrize("pitch, height", [(5.0, 0.0), (0.0, 0.2), (0.0, -0.15)])
def test_a_calibration_far_off_is_left_to_the_floor_check(view, pitch, height):
    # a deck or a plane half a pallet away is never taken for the floor: that is the floor check's to report
    depth, K, T = view
    assert refine_floor(calibrated_floor(T, height, pitch), depth, K) is None


@pytest.mark.parametrize("depth_of", [lambda d: np.zeros_like(d), lambda d: np.where(np.arange(d.shape[0])[:, None]
                                                                                      > 0.3 * d.shape[0], 0.0, d),
                                      lambda d: np.full_like(d, np.nan)])
def test_no_floor_in_the_depth_gives_no_frame_floor(view, depth_of):
    depth, K, T = view
    assert refine_floor(calibrated_floor(T), depth_of(depth), K) is None


def test_a_narrow_patch_of_floor_gives_no_frame_floor(view):
    # the floor seen only in a strip of columns: its tilt across the strip is the depth's noise, not the floor's
    depth, K, T = view
    cols = np.arange(depth.shape[1])
    strip = np.where((cols > 0.45 * depth.shape[1]) & (cols < 0.55 * depth.shape[1]), depth, 0.0)
    assert refine_floor(calibrated_floor(T), depth, K) is not None
    assert refine_floor(calibrated_floor(T), strip, K, min_points=50) is None
    assert refine_floor(calibrated_floor(T), strip, K, min_points=50, min_spread_m=0.0) is not None


def test_the_calibration_on_the_frame_floor_keeps_its_heading_and_place(view):
    _, _, T = view
    floor = calibrated_floor(T, 0.02, 1.0, 0.5)
    moved = on_floor(T, floor)
    np.testing.assert_allclose(moved[2, :3], floor.normal, atol=1e-12)
    assert moved[2, 3] == pytest.approx(floor.d)
    np.testing.assert_allclose(moved[:3, :3] @ moved[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(moved[:2, 3], T[:2, 3])
    turn = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ moved[:3, :3]) - 1) / 2, -1, 1)))
    assert turn == pytest.approx(plane_angle_deg(T[2, :3], floor.normal), abs=1e-6)   # the least turn
    np.testing.assert_allclose(on_floor(T, calibrated_floor(T)), T, atol=1e-12)


@pytest.mark.parametrize("flags, expected", [([], False), (["--floor-from-depth"], True)])
def test_the_command_line_turns_the_frame_floor_on(flags, expected):
    import argparse
    from pathlib import Path

    from pallet6d.runtime.estimator_cli import add_estimator_arguments, load_estimator

    parser = argparse.ArgumentParser()
    add_estimator_arguments(parser)
    bundle = Path(__file__).resolve().parents[1] / "models" / "epal-default"
    est = load_estimator(parser.parse_args(["--bundle", str(bundle), "--threads", "1", *flags]), "run")
    assert est.options.level.floor_from_depth is expected
