"""Luxonis OAK-D (depthai v3): colour camera + on-device stereo depth aligned to the colour socket.

Pipeline on the device: CAM_A colour output at `size` -> Sync["rgb"]; CAM_B/CAM_C mono -> StereoDepth
(aligned to CAM_A, scaled to `size`, millimetres) -> Sync["depth"]; the host reads Sync's
MessageGroups. Intrinsics come from the device's factory calibration at the output size.
The host-side pieces (`oakd_intrinsics`, `frame_from_oakd`) are pure functions of depthai messages,
tested on a host-only pipeline without a device.
"""
from __future__ import annotations

import datetime
import faulthandler
import logging
import signal

import cv2
import numpy as np

from pallet6d.runtime.geometry import check_K

from .base import FrameSource
from .errors import CameraDisconnected, CameraError, CameraNotFound, CameraTimeout
from .frame import RGBDFrame

__all__ = ["OakDCamera", "oakd_intrinsics", "frame_from_oakd", "list_oakd_ids", "OAKD_DEPTH_SCALE_M"]

log = logging.getLogger(__name__)

OAKD_DEPTH_SCALE_M = 0.001  # StereoDepth.depth is always uint16 millimetres


_FATAL_SIGNALS = ("SIGSEGV", "SIGABRT", "SIGBUS", "SIGILL", "SIGFPE")


def _dai():
    try:
        import depthai as dai
    except ImportError as exc:
        raise CameraError(f"depthai is not usable ({exc}); install it with: pip install 'pallet6d[oakd]'") from None
    _restore_fatal_signal_handlers()
    return dai


def _restore_fatal_signal_handlers() -> None:
    """Undo the crash handler depthai installs on import, so a crash ends the process.

    Its handler writes a crash report, which allocates: after a heap corruption detected inside free() it
    deadlocks on the allocator's lock (seen here with pyrealsense2 in the same process), so a daemon
    would hang instead of dying and being restarted by its supervisor. faulthandler's own handler
    (async-signal-safe) is reinstalled when it was on.
    """
    try:
        for name in _FATAL_SIGNALS:
            signal.signal(getattr(signal, name), signal.SIG_DFL)
    except ValueError:  # not the main thread: leave the handlers as they are
        log.debug("depthai imported outside the main thread; its crash handler stays")
        return
    if faulthandler.is_enabled():
        faulthandler.enable()


def list_oakd_ids() -> list[str]:
    """Device ids (MXIDs) of the OAK devices found within DEPTHAI_SEARCH_TIMEOUT."""
    dai = _dai()
    return [d.getDeviceId() for d in dai.Device.getAllAvailableDevices()]


def oakd_intrinsics(calib, socket, size_wh: tuple[int, int]) -> np.ndarray:
    """(3, 3) intrinsics of `socket` at the output size, from a `dai.CalibrationHandler`.

    depthai rescales the factory calibration and, for another aspect ratio, accounts for the crop
    its ISP makes (keepAspectRatio), as the Camera node does.
    """
    w, h = (int(v) for v in size_wh)
    try:
        K = np.asarray(calib.getCameraIntrinsics(socket, w, h), dtype=np.float64)
    except RuntimeError as exc:
        raise CameraError(f"OAK-D calibration has no intrinsics for {socket}: {exc}") from None
    return check_K(K)


def frame_from_oakd(rgb_msg, depth_msg, K: np.ndarray, source: str) -> RGBDFrame:
    """One `RGBDFrame` from a colour `dai.ImgFrame` and its aligned depth `dai.ImgFrame`.

    :param rgb_msg: colour frame of any type `getCvFrame()` decodes (BGR888i/p, RGB888i, NV12...).
    :param depth_msg: StereoDepth.depth frame, uint16 millimetres, aligned to the colour socket.
    :param K: (3, 3) colour intrinsics at this size.
    """
    bgr = rgb_msg.getCvFrame()
    if bgr.ndim != 3 or bgr.shape[2] != 3:
        raise CameraError(f"{source}: colour frame decoded to shape {bgr.shape}, expected (H, W, 3)")
    depth = np.asarray(depth_msg.getFrame())
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise CameraError(f"{source}: depth frame must be uint16 (H, W) millimetres, got {depth.dtype} {depth.shape}")
    if depth.shape != bgr.shape[:2]:
        raise CameraError(f"{source}: depth {depth.shape[1]}x{depth.shape[0]} is not aligned to colour "
                          f"{bgr.shape[1]}x{bgr.shape[0]} (StereoDepth.setDepthAlign/setOutputSize)")
    return RGBDFrame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth.copy(), K, OAKD_DEPTH_SCALE_M,
                     rgb_msg.getTimestampDevice().total_seconds(), rgb_msg.getSequenceNum(), source)


class OakDCamera(FrameSource):
    """An OAK-D (or OAK-D Pro/Lite/S2) through depthai v3.

    :param mxid: device id to open (None: the first found).
    :param size: (width, height) of colour and aligned depth, e.g. (640, 360) or (1280, 720).
    :param fps: camera rate.
    :param preset: StereoDepth preset name (DEFAULT, ROBOTICS, HIGH_DETAIL, FAST_DENSITY, ...).
    :param mono_size: stereo pair resolution, (640, 400) or (1280, 800).
    :param timeout_s: longest wait for one frame.
    """

    live = True

    def __init__(self, mxid: str | None = None, size: tuple[int, int] = (640, 360), fps: float = 30.0,
                 preset: str = "DEFAULT", mono_size: tuple[int, int] = (640, 400), timeout_s: float = 2.0) -> None:
        if len(size) != 2 or min(size) <= 0 or not fps > 0 or not timeout_s > 0:
            raise ValueError("size must be (width, height) > 0; fps and timeout_s positive")
        super().__init__(f"oakd:{mxid or 'any'}")
        self.mxid, self.size, self.fps = mxid, (int(size[0]), int(size[1])), float(fps)
        self.preset, self.mono_size, self.timeout_s = preset.upper(), tuple(mono_size), float(timeout_s)
        self.device_id = ""
        self._device = self._pipeline = self._queue = None

    def _start(self) -> None:
        dai = _dai()
        ids = list_oakd_ids()
        if not ids:
            raise CameraNotFound("no OAK device found (USB cable, udev rules, or raise DEPTHAI_SEARCH_TIMEOUT)")
        if self.mxid is not None and self.mxid not in ids:
            raise CameraNotFound(f"no OAK device {self.mxid}; found: {', '.join(ids)}")
        preset = getattr(dai.node.StereoDepth.PresetMode, self.preset, None)
        if preset is None:
            raise ValueError(f"unknown StereoDepth preset {self.preset!r}")
        try:
            self._device = dai.Device(dai.DeviceInfo(self.mxid or ids[0]))
            self.device_id = self._device.getDeviceId()
            p = self._pipeline = dai.Pipeline(self._device)
            A, B, C = dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
            color = p.create(dai.node.Camera).build(A)
            rgb_out = color.requestOutput(self.size, dai.ImgFrame.Type.BGR888i, fps=self.fps)
            left = p.create(dai.node.Camera).build(B).requestOutput(self.mono_size, fps=self.fps)
            right = p.create(dai.node.Camera).build(C).requestOutput(self.mono_size, fps=self.fps)
            stereo = p.create(dai.node.StereoDepth).build(left, right, presetMode=preset)
            stereo.setDepthAlign(A)
            stereo.setOutputSize(*self.size)
            stereo.setLeftRightCheck(True)
            sync = p.create(dai.node.Sync)
            rgb_out.link(sync.inputs["rgb"])
            stereo.depth.link(sync.inputs["depth"])
            self._queue = sync.out.createOutputQueue(maxSize=4, blocking=False)
            self._K = oakd_intrinsics(self._device.readCalibration(), A, self.size)
            self._depth_scale_m = OAKD_DEPTH_SCALE_M
            p.start()
        except RuntimeError as exc:
            raise CameraError(f"{self.name}: cannot start the OAK pipeline: {exc}") from None
        self.name = f"oakd:{self.device_id}"
        log.info("%s: colour+depth %dx%d at %.0f fps, preset %s", self.name, *self.size, self.fps, self.preset)

    def _read(self) -> RGBDFrame | None:
        try:
            group = self._queue.get(datetime.timedelta(seconds=self.timeout_s))
        except RuntimeError as exc:  # queue closed: the device went away
            raise CameraDisconnected(f"{self.name}: device connection lost: {exc}") from None
        if group is None:
            if self._device is not None and self._device.isClosed():
                raise CameraDisconnected(f"{self.name}: device connection lost")
            raise CameraTimeout(f"{self.name}: no frame within {self.timeout_s} s")
        return frame_from_oakd(group["rgb"], group["depth"], self._K, self.name)

    def _stop(self) -> None:
        p, self._pipeline = self._pipeline, None
        if p is not None:
            try:
                p.stop()
                p.wait()  # without it the interpreter may hang at exit
            except RuntimeError as exc:
                log.debug("%s: pipeline stop: %s", self.name, exc)
        dev, self._device = self._device, None
        if dev is not None:
            try:
                dev.close()
            except RuntimeError as exc:
                log.debug("%s: device close: %s", self.name, exc)
        self._queue = None
