"""`CameraLoop` in-process with a fake estimator and sources: faults are counted, never fatal."""
from __future__ import annotations

import time

import numpy as np
import pytest

from pallet6d.runtime.cameras import CameraDisconnected, FrameSource, RGBDFrame
from pallet6d.runtime.results import FrameResult
from pallet6d.runtime.serve.config import ServeConfig
from pallet6d.runtime.serve.loop import CameraLoop, NoFrameError, RegionHint
from pallet6d.runtime.serve.metrics import Metrics
from pallet6d.runtime.serve.snapshots import FrameRing

K = np.array([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]])


class FakeSource(FrameSource):
    """Numbered 32x24 frames every 5 ms; fails with CameraDisconnected at frame `fail_at` (once)."""

    live = True

    def __init__(self, fail_at: int | None = None) -> None:
        super().__init__("fake")
        self.fail_at, self.n = fail_at, 0

    def _start(self) -> None:
        self._K, self._depth_scale_m = K, 0.001

    def _read(self):
        time.sleep(0.005)
        self.n += 1
        if self.fail_at is not None and self.n == self.fail_at:
            raise CameraDisconnected("unplugged")
        return RGBDFrame(np.zeros((24, 32, 3), np.uint8), np.full((24, 32), 1000, np.uint16), K, 0.001,
                         self.n / 30, self.n, "fake")

    def _stop(self) -> None:
        pass


class FakeEstimator:
    """Fails on every `bad_every`-th call with ValueError and every `error_every`-th with RuntimeError."""

    model_size_m = np.array([1.2, 0.8, 0.144])

    def __init__(self, bad_every: int = 0, error_every: int = 0) -> None:
        self.calls, self.bad_every, self.error_every = 0, bad_every, error_every

    def estimate(self, frame):
        self.calls += 1
        if self.bad_every and self.calls % self.bad_every == 0:
            raise ValueError("depth has NaN")
        if self.error_every and self.calls % self.error_every == 0:
            raise RuntimeError("onnxruntime failed")
        return FrameResult.empty(frame.rgb.shape[:2], {"detector": 1.0, "total": 2.0})


def make_loop(estimator, sources, mode="continuous", max_rate_hz=0.0):
    cfg = ServeConfig.from_dict({"camera": {"source": "realsense", "mode": mode, "reconnect_min_s": 0.05,
                                            "reconnect_max_s": 0.1, "frame_timeout_s": 1.0,
                                            "max_rate_hz": max_rate_hz},
                                 "output": {"frame": "camera"}}, environ={})
    it = iter(sources)
    return CameraLoop(cfg, estimator, Metrics(), FrameRing(3), source_factory=lambda _spec: next(it))


def wait_for(predicate, timeout_s=20.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError("condition not reached")


def sample(loop, name, **labels):
    return loop.metrics.registry.get_sample_value(name, labels or None) or 0.0


def test_estimator_failures_are_counted_and_the_loop_goes_on():
    loop = make_loop(FakeEstimator(bad_every=3, error_every=5), [FakeSource()]).start()
    try:
        wait_for(lambda: sample(loop, "pallet6d_frames_total") >= 10)
        assert sample(loop, "pallet6d_failures_total", reason="bad_frame") >= 1
        assert sample(loop, "pallet6d_failures_total", reason="estimator") >= 1
        assert loop.latest is not None and loop.latest.result.poses == [] and loop.camera_fresh()
        assert len(loop.ring) == 3   # the ring keeps only the newest frames
    finally:
        loop.stop()
    assert not loop.alive(60.0)


def test_max_rate_hz_bounds_the_frames_taken():
    # the source makes about 200 frames a second; the loop may take at most 20
    loop = make_loop(FakeEstimator(), [FakeSource()], max_rate_hz=20.0).start()
    try:
        wait_for(lambda: sample(loop, "pallet6d_frames_total") >= 1)
        t0, n0 = time.monotonic(), sample(loop, "pallet6d_frames_total")
        wait_for(lambda: sample(loop, "pallet6d_frames_total") >= n0 + 5)
        n, elapsed_s = sample(loop, "pallet6d_frames_total") - n0, time.monotonic() - t0
        assert n <= 20.0 * elapsed_s + 1
        assert sample(loop, "pallet6d_frames_dropped_total") >= 1   # the frames of the waits were replaced
    finally:
        loop.stop()


def test_a_disconnect_is_followed_by_a_reconnect():
    loop = make_loop(FakeEstimator(), [FakeSource(fail_at=4), FakeSource()]).start()
    try:
        wait_for(lambda: sample(loop, "pallet6d_camera_reconnects_total") == 1 and loop.camera_up)
        assert sample(loop, "pallet6d_failures_total", reason="camera") == 1
        seq = loop.latest.seq
        wait_for(lambda: loop.latest.seq > seq)
    finally:
        loop.stop()


def test_a_source_that_cannot_open_is_retried():
    class Broken(FakeSource):
        def _start(self):
            raise CameraDisconnected("no device")

    loop = make_loop(FakeEstimator(), [Broken(), Broken(), FakeSource()]).start()
    try:
        wait_for(lambda: loop.camera_up)
        assert sample(loop, "pallet6d_failures_total", reason="camera") == 2
        assert sample(loop, "pallet6d_camera_reconnects_total") == 1
    finally:
        loop.stop()


def test_triggered_mode_estimates_only_on_detect():
    est = FakeEstimator()
    loop = make_loop(est, [FakeSource()], mode="triggered")
    with pytest.raises(NoFrameError):
        loop.detect()
    loop.start()
    try:
        wait_for(lambda: loop.latest_frame is not None and loop.camera_fresh())
        time.sleep(0.05)
        assert est.calls == 0 and loop.latest is None
        pub = loop.detect(RegionHint(box_xyxy=(0, 0, 10, 10)))
        assert est.calls == 1 and loop.latest is pub and pub.trigger == "detect" and pub.hint is not None
    finally:
        loop.stop()


@pytest.mark.parametrize("hint, keeps", [
    (RegionHint(), True),
    (RegionHint(box_xyxy=(0, 0, 100, 100)), True),
    (RegionHint(box_xyxy=(60, 0, 100, 100)), False),      # box centre x = 50
    (RegionHint(distance_m=3.0, tolerance_m=0.5), True),   # z = 2.7
    (RegionHint(distance_m=2.0, tolerance_m=0.5), False),
])
def test_region_hint(hint, keeps):
    assert hint.keeps(np.array([40.0, 40, 60, 60]), np.array([0.1, 0.2, 2.7])) is keeps
