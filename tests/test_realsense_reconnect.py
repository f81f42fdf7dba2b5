"""RealSense unplug/replug handling, with the SDK calls stood in for (no hardware, no pyrealsense2 needed)."""
from __future__ import annotations

import logging

import pytest

from pallet6d.runtime.cameras import CameraDisconnected, CameraTimeout
from pallet6d.runtime.cameras.realsense import RealSenseCamera
from camera_fixtures import K_SMALL, box_frame


class ScriptedRealSense(RealSenseCamera):
    """`wait` script items: a frame index (frame arrives) or None (nothing within timeout_s).
    `present` script: answers to "is the serial on USB?" in order (last answer repeats)."""

    def __init__(self, wait, present, **kw):
        super().__init__(serial="123", timeout_s=0.01, **kw)
        self.wait_script, self.present_script = list(wait), list(present)
        self.opens = self.closes = 0

    def _open(self):
        self.opens += 1
        self.device_serial = "123"
        self._K, self._depth_scale_m = K_SMALL, 0.001

    def _close(self):
        self.closes += 1

    def _wait_frames(self):
        return self.wait_script.pop(0)

    def _device_present(self):
        return self.present_script.pop(0) if len(self.present_script) > 1 else self.present_script[0]

    def _to_frame(self, i):
        return box_frame(i)


def test_unplug_and_replug_resumes_and_reports_gap(caplog):
    cam = ScriptedRealSense(wait=[0, None, 1, 2], present=[False, False, True], reconnect_timeout_s=5.0)
    with caplog.at_level(logging.WARNING), cam:
        numbers = [cam.read().frame_number for _ in range(3)]
    assert numbers == [100, 101, 102]
    assert cam.reconnects == 1 and cam.last_gap_s > 0
    assert cam.opens == 2 and cam.closes >= 2
    text = " ".join(r.getMessage() for r in caplog.records)
    assert "disconnected" in text and "back after" in text


def test_not_back_in_time_raises_disconnected():
    cam = ScriptedRealSense(wait=[0, None], present=[False], reconnect_timeout_s=0.0)
    with cam:
        cam.read()
        with pytest.raises(CameraDisconnected, match="not back within"):
            cam.read()


def test_present_but_silent_is_timeout():
    cam = ScriptedRealSense(wait=[None], present=[True])
    with cam, pytest.raises(CameraTimeout, match="although the camera is connected"):
        cam.read()
