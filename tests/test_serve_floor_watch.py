"""The daemon's floor check (`FloorWatch`) on exact rendered depth: agree, disagree, unseen, wrong camera; the
camera loop withholding vehicle-frame output while it fails."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from forklift_fixtures import H, K, W, camera
from pallet6d.runtime.calibration import Calibration, CalibrationError
from pallet6d.runtime.cameras import FrameSource, RGBDFrame
from pallet6d.runtime.floor import FloorPlane
from pallet6d.runtime.results import FrameResult
from pallet6d.runtime.serve.config import CameraConfig, FloorCheckConfig, OutputConfig, ServeConfig
from pallet6d.runtime.serve.floor_watch import FloorWatch
from pallet6d.runtime.serve.loop import CameraLoop
from pallet6d.runtime.serve.metrics import Metrics
from pallet6d.runtime.serve.snapshots import FrameRing

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


def floor_depth(T_vehicle_cam: np.ndarray) -> np.ndarray:
    """(H, W) exact depth of the bare floor (the vehicle's z = 0) within 20 m, metres."""
    v, u = np.mgrid[0:H, 0:W]
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    down = (rays_c @ T_vehicle_cam[:3, :3].T)[..., 2]
    with np.errstate(divide="ignore"):
        z = np.where(down < -1e-9, -T_vehicle_cam[2, 3] / down, 0.0)
    return np.where(z < 20, z, 0.0).astype(np.float32)


@pytest.fixture(scope="module")
def seen():
    """A frame of the bare floor."""
    return frame(floor_depth(T_VEHICLE_CAM))


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
    assert strict.status.state == "failed"
    assert strict.to_dict()["floor_tilt_deg"]["measured"] == pytest.approx(3, abs=0.3)
    lenient = checked(FloorWatch(cal, cfg(max_tilt_deg=5.0, max_height_diff_m=0.1), Metrics()), seen)
    assert lenient.status.state == "ok"


@pytest.mark.parametrize("height_error_m", [0.5, 1.0])
def test_a_calibration_far_too_high_fails_with_the_floor_found_elsewhere(seen, height_error_m):
    """The floor lies far outside the band around the calibrated one: found in the whole image, not unknown."""
    watch = checked(FloorWatch(calibration(height_error_m), cfg(when_unseen="ready"), Metrics()), seen)
    d = watch.to_dict()
    assert d["state"] == "failed" and not watch.ready() and "found in the whole image" in d["detail"]
    assert d["camera_height_m"]["measured"] == pytest.approx(0.5, abs=0.01)
    assert d["camera_height_m"]["expected"] == pytest.approx(0.5 + height_error_m)
    assert "camera moved since it was calibrated" in watch.blocked_reason(seen)


def test_a_calibration_tilted_20_degrees_fails_with_the_measured_tilt(seen):
    T = T_VEHICLE_CAM.copy()
    a = np.radians(20.0)
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    cal = Calibration("sim", "2026-11-23", W, H, K, T, FloorPlane(T[2, :3].copy(), float(T[2, 3])))
    watch = checked(FloorWatch(cal, cfg(), Metrics()), seen)
    assert watch.status.state == "failed"
    assert watch.to_dict()["floor_tilt_deg"]["measured"] == pytest.approx(20, abs=0.3)


def test_a_frame_without_depth_is_unknown_even_far_off():
    """No depth at all shows no floor anywhere: unknown, whatever the calibration says (NaN depth: the camera
    frame is uint16, see tests/test_floor_far.py for the floor check itself)."""
    watch = checked(FloorWatch(calibration(0.5), cfg(), Metrics()), frame(np.zeros((H, W), np.float32)))
    assert watch.status.state == "unknown" and "floor not seen" in watch.status.detail


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
    knocked = frame(floor_depth(camera(height_m=0.6, pitch_deg=8.0)))    # the camera 10 cm higher
    watch = checked(FloorWatch(calibration(), cfg(), Metrics()), seen)
    assert checked(watch, knocked).status.state == "ok"
    assert checked(watch, knocked).status.state == "failed"
    assert checked(watch, seen, 2).status.state == "failed"
    assert checked(watch, seen).status.state == "ok"


def test_offer_never_checks_on_the_callers_thread(seen):
    watch = FloorWatch(calibration(height_error_m=0.2), cfg(), Metrics())     # not started: nobody checks
    for _ in range(3):
        watch.offer(seen)
    assert watch.status.checks == 0 and watch.status.state == "unknown"


class _ViewSource(FrameSource):
    """The rendered view, again and again (a camera at 200 fps)."""

    live = True

    def __init__(self, view: RGBDFrame) -> None:
        super().__init__("view")
        self.view, self.n = view, 0

    def _start(self) -> None:
        self._K, self._depth_scale_m = self.view.K, self.view.depth_scale_m

    def _read(self):
        time.sleep(0.005)
        self.n += 1
        return dataclasses.replace(self.view, frame_number=self.n, timestamp_s=self.n / 200)

    def _stop(self) -> None:
        pass


class _CountingEstimator:
    model_size_m = np.array([1.2, 0.8, 0.144])

    def __init__(self) -> None:
        self.calls = 0

    def estimate(self, f):
        self.calls += 1
        return FrameResult.empty(f.rgb.shape[:2], {"total": 1.0})


def _loop(seen, frame_kind: str, estimator) -> CameraLoop:
    config = ServeConfig(camera=CameraConfig(source="realsense", frame_timeout_s=5.0),
                         output=OutputConfig(frame=frame_kind))
    metrics = Metrics()
    watch = FloorWatch(calibration(height_error_m=0.2), cfg(), metrics)
    return CameraLoop(config, estimator, metrics, FrameRing(2), source_factory=lambda _spec: _ViewSource(seen),
                      floor_watch=watch)


def _wait(predicate, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < end, "condition not reached"
        time.sleep(0.01)


def test_the_loop_withholds_vehicle_output_while_the_camera_counts_as_moved(seen):
    estimator = _CountingEstimator()
    loop = _loop(seen, "vehicle", estimator).start()
    try:
        _wait(lambda: loop.floor_watch.status.state == "failed" and loop.latest is not None
              and loop.latest.error != "")
        calls = estimator.calls
        seq = loop.latest.seq
        _wait(lambda: loop.latest.seq >= seq + 3)
        assert estimator.calls == calls                         # withheld frames are not estimated
        assert loop.latest.result.poses == [] and "camera moved since it was calibrated" in loop.latest.error
        assert loop.metrics.registry.get_sample_value("pallet6d_failures_total", {"reason": "calibration"}) >= 3
        with pytest.raises(CalibrationError, match="camera moved"):
            loop.detect()
    finally:
        loop.stop()


def test_camera_frame_output_is_not_withheld(seen):
    estimator = _CountingEstimator()
    loop = _loop(seen, "camera", estimator).start()
    try:
        _wait(lambda: loop.floor_watch.status.state == "failed")      # the check still runs (GET /readyz)
        calls = estimator.calls
        _wait(lambda: estimator.calls >= calls + 3)
        assert loop.latest.error == "" and loop.detect().error == ""
    finally:
        loop.stop()
