"""Intel RealSense D435 (live, by serial) and RealSense `.bag` recordings, through pyrealsense2.

Depth is aligned to the colour image with `rs.align(rs.stream.color)` after the optional depth
post-processing (Intel's recommended order: decimation, depth->disparity, spatial, temporal,
disparity->depth, hole filling; filters work on the depth camera's own image, before alignment).

`rs.align` moves each depth value to the colour pixel its point projects to but keeps the value, the
point's z in the *depth* camera frame. With any rotation or z offset between the two cameras that is
not the colour camera's z, which back-projection with the colour K assumes; `_to_frame` converts it
exactly, per pixel (a few mm on a D435, whose cameras are nearly parallel).

When a live camera is unplugged, `read()` notices (no frame within `timeout_s` and the serial gone
from the USB device list), logs a warning, waits up to `reconnect_timeout_s` for the same serial to
come back, restarts streaming and goes on; `reconnects` and `last_gap_s` tell the gap. Without the
camera back in time it raises `CameraDisconnected`.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from .base import FrameSource
from .errors import CameraDisconnected, CameraError, CameraNotFound, CameraTimeout, FrameReadError
from .frame import RGBDFrame
from .rsbag_playback import BagPlayback

__all__ = ["RealSenseCamera", "FILTER_NAMES", "list_realsense_serials"]

log = logging.getLogger(__name__)

FILTER_NAMES = ("decimation", "spatial", "temporal", "hole_filling")


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:  # missing wheel or missing libusb-1.0-0
        raise CameraError(f"pyrealsense2 is not usable ({exc}); install it with: pip install 'pallet6d[realsense]' "
                          "(and the Debian package libusb-1.0-0)") from None
    return rs


def list_realsense_serials() -> list[str]:
    """Serial numbers of the RealSense devices on USB now."""
    rs = _rs()
    return [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]


class RealSenseCamera(FrameSource):
    """A RealSense D435 or a `.bag` recording of one.

    :param serial: pick this device (None: the only/first one). Ignored with `bag_path`.
    :param bag_path: play this recording instead of a camera (streams and sizes as recorded).
    :param color_size: (width, height) of colour, e.g. (848, 480) or (1280, 720).
    :param depth_size: (width, height) of depth, e.g. (848, 480); D435 depth is best at 848x480.
    :param fps: frame rate of both streams (6, 15, 30, 60 on a D435; 30 at 1280x720 needs USB 3).
    :param filters: depth post-processing, a subset of FILTER_NAMES, applied in Intel's order.
    :param decimation: decimation magnitude (2..8) when "decimation" is in `filters`.
    :param timeout_s: longest wait for one frame before checking whether the device is gone.
    :param reconnect_timeout_s: how long to wait for an unplugged camera to return (0: never wait).
    :param realtime: bag playback at recorded speed (True) or as fast as read (False, every frame).
    """

    live = True

    def __init__(self, serial: str | None = None, bag_path: str | Path | None = None,
                 color_size: tuple[int, int] = (848, 480), depth_size: tuple[int, int] = (848, 480), fps: int = 30,
                 filters: Sequence[str] = (), decimation: int = 2, timeout_s: float = 2.0,
                 reconnect_timeout_s: float = 30.0, realtime: bool = False) -> None:
        unknown = set(filters) - set(FILTER_NAMES)
        if unknown:
            raise ValueError(f"unknown depth filter(s) {sorted(unknown)}; choose from {FILTER_NAMES}")
        if not 2 <= int(decimation) <= 8:
            raise ValueError(f"decimation must be 2..8, got {decimation}")
        for name, size in (("color_size", color_size), ("depth_size", depth_size)):
            if len(size) != 2 or min(size) <= 0:
                raise ValueError(f"{name} must be (width, height) > 0, got {size}")
        if not timeout_s > 0 or reconnect_timeout_s < 0 or int(fps) <= 0:
            raise ValueError("timeout_s and fps must be positive, reconnect_timeout_s >= 0")
        self.bag_path = None if bag_path is None else Path(bag_path)
        self.serial = None if self.bag_path is not None else serial
        super().__init__(f"bag:{self.bag_path}" if self.bag_path is not None else f"realsense:{serial or 'any'}")
        self.live = self.bag_path is None
        self.color_size, self.depth_size, self.fps = tuple(color_size), tuple(depth_size), int(fps)
        self.filters, self.decimation = tuple(f for f in FILTER_NAMES if f in filters), int(decimation)
        self.timeout_s, self.reconnect_timeout_s, self.realtime = float(timeout_s), float(reconnect_timeout_s), bool(realtime)
        self.reconnects = 0      #: times the camera came back after being unplugged
        self.last_gap_s = 0.0    #: length of the last unplugged gap
        self.device_serial = ""  #: serial of the opened device (or recorded in the bag)
        self._pipe = None
        self._align = None
        self._blocks: list = []
        self._z_fix = None
        self._playback = None

    # -- SDK calls (one place each, so tests can stand in for the device) -------------------------
    def _device_present(self) -> bool:
        return self.device_serial in list_realsense_serials()

    def _open(self) -> None:
        rs = _rs()
        ctx = rs.context()
        self._playback = None
        if self.bag_path is not None:
            if not self.bag_path.is_file():
                what = "is a folder, not a .bag file" if self.bag_path.is_dir() else "does not exist"
                raise CameraNotFound(f"RealSense recording {self.bag_path} {what}")
            self._playback = BagPlayback(rs, ctx, self.bag_path, self.realtime)
            device, color, depth = self._playback.device, self._playback.color_profile, self._playback.depth_profile
        else:
            device, color, depth = self._start_pipeline(rs, ctx)
        self._ctx = ctx
        try:
            self.device_serial = device.get_info(rs.camera_info.serial_number)
        except RuntimeError:
            self.device_serial = ""
        intr = color.get_intrinsics()
        if any(abs(c) > 1e-6 for c in intr.coeffs):
            log.warning("%s: colour stream has distortion %s %s; K ignores it", self.name, intr.model, list(intr.coeffs))
        self._K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
        self._color_format = color.format()
        self._depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
        self._align = rs.align(rs.stream.color)
        self._blocks = self._make_filters(rs)
        ext = depth.get_extrinsics_to(color)
        self._z_fix = self._depth_z_to_color_z(np.array(ext.rotation).reshape(3, 3).T, np.array(ext.translation),
                                               intr.width, intr.height)
        log.info("%s: device %s, colour %dx%d, depth scale %.6g m, filters %s", self.name, self.device_serial,
                 intr.width, intr.height, self._depth_scale_m, list(self.filters) or "none")

    def _start_pipeline(self, rs, ctx):
        """Stream from a live camera; its device and colour and depth stream profiles."""
        serials = list_realsense_serials()
        if not serials:
            raise CameraNotFound("no RealSense camera connected (check the USB 3 cable and `rs-enumerate-devices`)")
        serial = self.device_serial or self.serial
        if serial is not None and serial not in serials:
            raise CameraNotFound(f"no RealSense with serial {serial}; connected: {', '.join(serials)}")
        cfg = rs.config()
        cfg.enable_device(serial or serials[0])
        cfg.enable_stream(rs.stream.color, self.color_size[0], self.color_size[1], rs.format.rgb8, self.fps)
        cfg.enable_stream(rs.stream.depth, self.depth_size[0], self.depth_size[1], rs.format.z16, self.fps)
        pipe = rs.pipeline(ctx)
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise CameraError(f"{self.name}: cannot start streaming: {exc}") from None
        self._pipe = pipe
        try:
            color = profile.get_stream(rs.stream.color).as_video_stream_profile()
            depth = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        except RuntimeError:
            self._close()
            raise CameraError(f"{self.name}: needs both a colour and a depth stream") from None
        return profile.get_device(), color, depth

    def _depth_z_to_color_z(self, R_color_depth: np.ndarray, t_color_depth: np.ndarray, width: int, height: int):
        """Per-pixel (a, b) with z_color = (z_depth + b) / a for an aligned depth image, or None for identity.

        A colour pixel's point is z_c * ray (ray = K^-1 [u, v, 1]); its depth-frame z is
        r3 . (z_c * ray - t) with r3 the third column of R_color_depth.
        """
        if np.allclose(R_color_depth[:, 2], [0, 0, 1], atol=1e-9) and abs(t_color_depth[2]) < 1e-9:
            return None
        u, v = np.meshgrid(np.arange(width), np.arange(height))
        r3 = R_color_depth[:, 2]
        a = (r3[0] * (u - self._K[0, 2]) / self._K[0, 0] + r3[1] * (v - self._K[1, 2]) / self._K[1, 1] + r3[2])
        return a.astype(np.float32), np.float32(r3 @ t_color_depth)

    def _fix_z(self, depth: np.ndarray) -> np.ndarray:
        if self._z_fix is None:
            return depth
        a, b = self._z_fix
        valid = depth > 0
        z_units = (depth.astype(np.float32) + b / np.float32(self._depth_scale_m)) / a
        out = np.where(valid, np.rint(z_units), 0)
        out[(out <= 0) | (out > np.iinfo(np.uint16).max)] = 0
        return out.astype(np.uint16)

    def _make_filters(self, rs) -> list:
        blocks = []
        if "decimation" in self.filters:
            dec = rs.decimation_filter()
            dec.set_option(rs.option.filter_magnitude, self.decimation)
            blocks.append(dec)
        if "spatial" in self.filters or "temporal" in self.filters:
            blocks.append(rs.disparity_transform(True))
            if "spatial" in self.filters:
                blocks.append(rs.spatial_filter())
            if "temporal" in self.filters:
                blocks.append(rs.temporal_filter())
            blocks.append(rs.disparity_transform(False))
        if "hole_filling" in self.filters:
            blocks.append(rs.hole_filling_filter())
        return blocks

    def _close(self) -> None:
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError as exc:  # already stopped, or the device is gone
                log.debug("%s: pipeline stop: %s", self.name, exc)
        playback, self._playback = self._playback, None
        if playback is not None:
            playback.close()

    def _wait_frames(self):
        """The next frameset, or None when none came within `timeout_s` (or a recording ended)."""
        if self.bag_path is None:
            ok, frames = self._pipe.try_wait_for_frames(int(self.timeout_s * 1000))
            return frames if ok else None
        return self._playback.wait(self.timeout_s)

    def _playback_ended(self) -> bool:
        return self._playback.ended()

    def _to_frame(self, frames) -> RGBDFrame:
        fs = frames
        for block in self._blocks:
            fs = block.process(fs).as_frameset()
        aligned = self._align.process(fs)
        color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        if not color or not depth:
            number = (color or depth).get_frame_number() if (color or depth) else None
            raise FrameReadError(f"{self.name}: frameset without colour or depth", number)
        rgb = np.asanyarray(color.get_data())
        rs = _rs()
        if self._color_format == rs.format.bgr8:
            rgb = cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB)
        elif self._color_format != rs.format.rgb8:
            raise CameraError(f"{self.name}: colour format {self._color_format} is not supported (use rgb8 or bgr8)")
        depth_img = self._fix_z(np.asanyarray(depth.get_data()).copy())
        return RGBDFrame(rgb.copy(), depth_img, self._K, self._depth_scale_m,
                         color.get_timestamp() / 1000.0, color.get_frame_number(), self.name)

    # -- FrameSource -----------------------------------------------------------------------------
    def _start(self) -> None:
        self._open()

    def _stop(self) -> None:
        self._close()

    def _read(self) -> RGBDFrame | None:
        while True:
            frames = self._wait_frames()
            if frames is not None:
                try:
                    return self._to_frame(frames)
                except FrameReadError as exc:
                    if self.bag_path is not None:   # a recording reports it in place of the frame
                        raise
                    log.warning("%s; waiting for the next one", exc)   # a live camera sends another at once
                    continue
            if self.bag_path is not None:
                if self._playback_ended():
                    return None
                raise CameraTimeout(f"{self.name}: no frame within {self.timeout_s} s while playing")
            if self._device_present():
                raise CameraTimeout(f"{self.name}: no frame within {self.timeout_s} s although the camera is connected")
            self._reconnect()

    def _reconnect(self) -> None:
        log.warning("%s: camera %s disconnected; waiting up to %.0f s for it to come back", self.name,
                    self.device_serial, self.reconnect_timeout_s)
        self._close()
        t0 = time.monotonic()
        while True:
            if self._device_present():
                try:
                    K_before = self._K
                    self._open()
                except CameraError as exc:  # enumerated but not ready yet
                    log.debug("%s: reopen failed: %s", self.name, exc)
                else:
                    self.last_gap_s = time.monotonic() - t0
                    self.reconnects += 1
                    if K_before is not None and not np.allclose(K_before, self._K):
                        log.warning("%s: intrinsics changed after reconnecting", self.name)
                    log.warning("%s: camera back after %.1f s; streaming again", self.name, self.last_gap_s)
                    return
            if time.monotonic() - t0 >= self.reconnect_timeout_s:
                raise CameraDisconnected(f"{self.name}: camera {self.device_serial} disconnected and not back "
                                         f"within {self.reconnect_timeout_s:.0f} s")
            time.sleep(min(0.5, self.reconnect_timeout_s))
