"""The frame's own floor near a calibrated one (`floor.refine_floor`) and the calibration moved onto it
(`floor.on_floor`), on a seeded simulated forklift view (D435-like depth)."""
from __future__ import annotations

import numpy as np
import pytest

from pallet6d.runtime.floor import FloorPlane, on_floor, plane_angle_deg, refine_floor

SEED = 4          # of the forklift-approach preset at 424x240: a camera 0.74 m up that sees the floor


@pytest.fixture(scope="module")
def view():
    """(depth_m, K, T_vehicle_cam) of one generated forklift view."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(get_preset("forklift-approach").with_image_size(424, 240), SEED, 0)
    return f.depth_m, f.K, f.T_vehicle_cam


def _off(T: np.ndarray, pitch_deg: float = 0.0, roll_deg: float = 0.0, height_m: float = 0.0) -> np.ndarray:
    """T turned about the camera's x (pitch) and z (roll) axes and raised by `height_m`."""
    a, b = np.radians(pitch_deg), np.radians(roll_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Rz = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ Rx @ Rz
    out[2, 3] += height_m
    return out


def _floor(T: np.ndarray) -> FloorPlane:
    return FloorPlane(T[2, :3].copy(), float(T[2, 3]))


@pytest.mark.parametrize("pitch, roll, height", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (-1.5, 0.0, 0.02),
                                                 (0.0, 1.0, -0.03), (0.5, -0.5, 0.04)])
def test_the_frame_floor_near_a_calibration_a_little_off_is_the_true_floor(view, pitch, roll, height):
    depth, K, T = view
    floor = refine_floor(_floor(_off(T, pitch, roll, height)), depth, K)
    assert floor is not None
    assert plane_angle_deg(floor.normal, T[2, :3]) < 0.15 and abs(floor.d - T[2, 3]) < 0.01


@pytest.mark.parametrize("pitch, height", [(5.0, 0.0), (0.0, 0.2), (0.0, -0.15)])
def test_a_calibration_far_off_is_left_to_the_floor_check(view, pitch, height):
    # a deck or a plane half a pallet away is never taken for the floor: that is the floor check's to report
    depth, K, T = view
    assert refine_floor(_floor(_off(T, pitch, 0.0, height)), depth, K) is None


@pytest.mark.parametrize("depth_of", [lambda d: np.zeros_like(d), lambda d: np.where(np.arange(d.shape[0])[:, None]
                                                                                      > 0.3 * d.shape[0], 0.0, d),
                                      lambda d: np.full_like(d, np.nan)])
def test_no_floor_in_the_depth_gives_none(view, depth_of):
    depth, K, T = view
    assert refine_floor(_floor(T), depth_of(depth), K) is None


def test_the_calibration_on_the_frame_floor_keeps_its_heading_and_place(view):
    _, _, T = view
    floor = _floor(_off(T, 1.0, 0.5, 0.02))
    moved = on_floor(T, floor)
    np.testing.assert_allclose(moved[2, :3], floor.normal, atol=1e-12)
    assert moved[2, 3] == pytest.approx(floor.d)
    np.testing.assert_allclose(moved[:3, :3] @ moved[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(moved[:2, 3], T[:2, 3])
    turn = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ moved[:3, :3]) - 1) / 2, -1, 1)))
    assert turn == pytest.approx(plane_angle_deg(T[2, :3], floor.normal), abs=1e-6)   # the least turn
    np.testing.assert_allclose(on_floor(T, _floor(T)), T, atol=1e-12)


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
