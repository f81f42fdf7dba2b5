"""OAK-D host side on a host-only depthai pipeline (no device); the device path is skipped with its reason."""
from __future__ import annotations

import datetime
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", "500")  # ms: a missing device is noticed fast
dai = pytest.importorskip("depthai", reason="depthai (extra 'oakd') is not installed")

from pallet6d.runtime.cameras import CameraError, CameraNotFound, open_source  # noqa: E402
from pallet6d.runtime.cameras.oakd import (OakDCamera, _dai, frame_from_oakd, list_oakd_ids,  # noqa: E402
                                           oakd_intrinsics)
from camera_fixtures import K_SMALL, box_frame  # noqa: E402

_dai()  # this module imported depthai at collection: undo its crash handler for the rest of the suite too


def _img(array: np.ndarray, kind, seq: int, t_s: float):
    msg = dai.ImgFrame()
    msg.setCvFrame(array, kind)
    ts = datetime.timedelta(seconds=t_s)
    msg.setTimestamp(ts)
    msg.setTimestampDevice(ts)
    msg.setSequenceNum(seq)
    return msg


@pytest.mark.parametrize("kind", ["BGR888i", "RGB888i", "BGR888p"])
def test_sync_group_to_frame_on_host_pipeline(kind):
    """The device's Sync -> MessageGroup -> RGBDFrame path, with Sync running on the host."""
    refs = [box_frame(i) for i in range(3)]
    got = []
    with dai.Pipeline(False) as p:
        sync = p.create(dai.node.Sync)
        sync.setRunOnHost(True)
        q_rgb = sync.inputs["rgb"].createInputQueue()
        q_depth = sync.inputs["depth"].createInputQueue()
        q_out = sync.out.createOutputQueue()
        p.start()
        for i, ref in enumerate(refs):
            bgr = np.ascontiguousarray(ref.rgb[..., ::-1])
            q_rgb.send(_img(bgr, getattr(dai.ImgFrame.Type, kind), 40 + i, 3.0 + i / 30))
            q_depth.send(_img(ref.depth, dai.ImgFrame.Type.RAW16, 40 + i, 3.0 + i / 30))
            group = q_out.get(datetime.timedelta(seconds=10))
            assert group is not None
            got.append(frame_from_oakd(group["rgb"], group["depth"], K_SMALL, "oakd:test"))
        p.stop()
        p.wait()
    for i, (f, ref) in enumerate(zip(got, refs)):
        np.testing.assert_array_equal(f.rgb, ref.rgb)  # RGB order, whatever the wire type
        np.testing.assert_array_equal(f.depth, ref.depth)
        assert f.depth_scale_m == 0.001
        np.testing.assert_array_equal(f.depth_m, ref.depth_m)
        assert f.frame_number == 40 + i and f.timestamp_s == pytest.approx(3.0 + i / 30)
        assert f.source == "oakd:test"


def test_unaligned_depth_is_refused():
    rgb = _img(np.zeros((60, 80, 3), np.uint8), dai.ImgFrame.Type.BGR888i, 0, 0.0)
    depth = _img(np.zeros((40, 64), np.uint16), dai.ImgFrame.Type.RAW16, 0, 0.0)
    with pytest.raises(CameraError, match="not aligned"):
        frame_from_oakd(rgb, depth, K_SMALL, "oakd:test")


def test_intrinsics_from_calibration_scale_with_output_size():
    calib = dai.CalibrationHandler()
    K_full = [[1500.0, 0.0, 960.0], [0.0, 1500.0, 540.0], [0.0, 0.0, 1.0]]
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K_full, 1920, 1080)
    K = oakd_intrinsics(calib, dai.CameraBoardSocket.CAM_A, (640, 360))
    assert K.shape == (3, 3)
    assert K[0, 0] == pytest.approx(500.0) and K[1, 1] == pytest.approx(500.0)
    assert K[0, 2] == pytest.approx(320.0, abs=0.6) and K[1, 2] == pytest.approx(180.0, abs=0.6)


def test_no_device_is_camera_not_found():
    if list_oakd_ids():
        pytest.skip("an OAK device is connected; this checks the no-device message")
    with pytest.raises(CameraNotFound, match="no OAK device"):
        open_source("oakd").start()
    with pytest.raises(CameraNotFound):
        OakDCamera(mxid="14442C10D13EABCE00").start()


def test_device_streams():
    if not list_oakd_ids():
        pytest.skip("no OAK-D connected: the device path (calibration read, on-device stereo aligned to CAM_A, "
                    "reconnect) needs hardware; run `pytest tests/test_oakd.py` with one plugged in")
    with OakDCamera(size=(640, 360)) as cam:
        K = cam.K
        frame = cam.read()
    assert frame.rgb.shape == (360, 640, 3) and frame.depth.shape == (360, 640)
    np.testing.assert_array_equal(frame.K, K)
    assert (frame.depth > 0).mean() > 0.2


def test_a_crash_after_importing_depthai_ends_the_process():
    # depthai's crash handler allocates, so a crash inside free() deadlocked it: the process must die instead
    code = "import os; from pallet6d.runtime.cameras.oakd import _dai; _dai(); os.abort()"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGABRT
    assert "Stack trace" not in out.stderr  # depthai's handler did not run
