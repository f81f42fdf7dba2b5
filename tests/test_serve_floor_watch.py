"""The daemon's floor check (`FloorWatch`) on exact rendered depth: agree, disagree, unseen, wrong camera."""
from __future__ import annotations

import time

import numpy as np
import pytest

from forklift_fixtures import H, K, W, camera, pallet_pose, render
from pallet6d.runtime.calibration import Calibration
from pallet6d.runtime.cameras import RGBDFrame
from pallet6d.runtime.floor import FloorPlane
from pallet6d.runtime.serve.config import FloorCheckConfig
from pallet6d.runtime.serve.floor_watch import FloorWatch
from pallet6d.runtime.serve.metrics import Metrics

T_VEHICLE_CAM = camera(height_m=0.5, pitch_deg=8.0)


def cfg(**kw) -> FloorCheckConfig:
    return FloorCheckConfig(interval_s=0.1, **kw)


def calibration(height_error_m: float = 0.0) -> Calibration:
    """The camera's calibration, its height `height_error_m` off the truth (stored floor consistent with it)."""
    T = T_VEHICLE_CAM.copy()
    T[2, 3] += height_error_m
    return Calibration("sim", "2026-11-23", W, H, K, T, FloorPlane(T[2, :3].copy(), float(T[2, 3])))


def frame(depth_m: np.ndarray, K_: np.ndarray = K, number: int = 0) -> RGBDFrame:
    depth = np.round(depth_m / 0.001).astype(np.uint16)
    return RGBDFrame(np.zeros((*depth.shape, 3), np.uint8), depth, K_, 0.001, number / 30, number, "test")


@pytest.fixture(scope="module")
def seen():
    """A frame of the pallet 2 m ahead on the floor."""
    return frame(render(T_VEHICLE_CAM, pallet_pose(2.0)))


def checked(watch: FloorWatch, f: RGBDFrame, n: int = 1) -> FloorWatch:
    """`watch` after `n` more checks of `f` (handed over as the camera loop does)."""
    watch.start()
    try:
        target = watch.status.checks + n
        end = time.monotonic() + 30
        while watch.status.checks < target and time.monotonic() < end:
            watch.offer(f)
            time.sleep(0.02)
    finally:
        watch.stop()
    assert watch.status.checks >= target
    return watch


def test_a_matching_calibration_agrees(seen):
    metrics = Metrics()
    watch = checked(FloorWatch(calibration(), cfg(), metrics), seen)
    d = watch.to_dict()
    assert d["state"] == "ok" and watch.ready() and watch.blocked_reason(seen) == ""
    assert abs(d["camera_height_m"]["measured"] - 0.5) < 0.01 and d["camera_height_m"]["expected"] == 0.5
    assert d["floor_tilt_deg"]["measured"] < 0.5 and d["floor_tilt_deg"]["tolerance"] == 2.0
    text = metrics.exposition().decode()
    assert 'pallet6d_floor_checks_total{result="agrees"} 1.0' in text and "pallet6d_calibration_ok 1.0" in text


def test_a_camera_height_off_by_20cm_fails_with_measured_and_expected(seen):
    metrics = Metrics()
    watch = checked(FloorWatch(calibration(height_error_m=0.2), cfg(), metrics), seen)
    d = watch.to_dict()
    assert d["state"] == "failed" and not watch.ready()
    assert d["camera_height_m"]["expected"] == pytest.approx(0.7)
    assert d["camera_height_m"]["measured"] == pytest.approx(0.5, abs=0.01)
    assert "camera height off by -20.0 cm" in d["detail"]
    assert "camera moved since it was calibrated" in watch.blocked_reason(seen)
    text = metrics.exposition().decode()
    assert 'pallet6d_floor_checks_total{result="disagrees"} 1.0' in text and "pallet6d_calibration_ok 0.0" in text
    diff = next(line for line in text.splitlines() if line.startswith("pallet6d_floor_height_diff_meters "))
    assert float(diff.split()[1]) == pytest.approx(-0.2, abs=0.01)


def test_a_tilted_camera_fails_and_the_tolerance_is_the_configs(seen):
    T = T_VEHICLE_CAM.copy()
    a = np.radians(3.0)        # the camera knocked 3 degrees about its own x axis since it was calibrated
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    cal = Calibration("sim", "2026-11-23", W, H, K, T, FloorPlane(T[2, :3].copy(), float(T[2, 3])))
    strict = checked(FloorWatch(cal, cfg(), Metrics()), seen)
    assert strict.status.state == "failed" and strict.to_dict()["floor_tilt_deg"]["measured"] == pytest.approx(3, abs=0.3)
    lenient = checked(FloorWatch(cal, cfg(max_tilt_deg=5.0, max_height_diff_m=0.1), Metrics()), seen)
    assert lenient.status.state == "ok"


@pytest.mark.parametrize("when_unseen, ready", [("ready", True), ("not_ready", False)])
def test_no_floor_in_view_is_unknown_and_readiness_follows_the_config(when_unseen, ready):
    wall = frame(np.full((H, W), 1.5, np.float32))     # a wall 1.5 m ahead, no floor
    metrics = Metrics()
    watch = checked(FloorWatch(calibration(), cfg(when_unseen=when_unseen), metrics), wall)
    d = watch.to_dict()
    assert d["state"] == "unknown" and "floor not seen" in d["detail"] and d["camera_height_m"]["measured"] is None
    assert watch.ready() is ready and watch.blocked_reason(wall) == ""      # unknown withholds nothing
    assert 'pallet6d_floor_checks_total{result="unseen"} 1.0' in metrics.exposition().decode()


def test_not_checked_yet_is_unknown():
    watch = FloorWatch(calibration(), cfg(when_unseen="not_ready"), Metrics())
    assert watch.to_dict()["state"] == "unknown" and watch.to_dict()["checked_age_s"] is None and not watch.ready()


def test_frames_of_another_camera_fail(seen):
    other_K = K.copy()
    other_K[0, 0] *= 1.2
    other = frame(seen.depth_m, other_K)
    watch = checked(FloorWatch(calibration(), cfg(), Metrics()), other)
    assert watch.status.state == "failed" and "intrinsics differ" in watch.status.detail
    assert "intrinsics differ" in watch.blocked_reason(other)


def test_a_moved_camera_needs_agreeing_checks_in_a_row_to_recover(seen):
    """After agreeing once, one disagreement is not enough (a ramp edge); two are; three agreeing end it."""
    knocked = frame(render(camera(height_m=0.6, pitch_deg=8.0), pallet_pose(2.0)))   # the camera 10 cm higher
    watch = checked(FloorWatch(calibration(), cfg(), Metrics()), seen)
    assert checked(watch, knocked).status.state == "ok"
    assert checked(watch, knocked).status.state == "failed"
    assert checked(watch, seen, 2).status.state == "failed"
    assert checked(watch, seen).status.state == "ok"
