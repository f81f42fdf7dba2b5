"""Every colour+depth frameset of a RealSense `.bag`, in order, without the pipeline's start-up loss.

A pipeline started on a recording drops the first frameset now and then (measured: 1 run in 6 here,
more under load): its syncer has not yet seen both streams, emits the first depth and colour frames
each alone, and the pipeline discards incomplete sets. Here the recorded sensors stream straight into
a syncer, and lone frames are paired again by timestamp into one composite frameset, so `rs.align`
and the depth filters see the same kind of frameset as from a live camera.

With `realtime=False` the playback waits for the reader, so no frame is lost however slow it is.
"""
from __future__ import annotations

import time
from pathlib import Path

from .errors import CameraError

__all__ = ["BagPlayback"]


class BagPlayback:
    """Frames of one recording. `wait()` gives the next colour+depth frameset, None at the end."""

    def __init__(self, rs, ctx, path: Path, realtime: bool) -> None:
        self._rs = rs
        try:
            self.device = ctx.load_device(str(path))
        except RuntimeError as exc:
            raise CameraError(f"bag:{path}: not a playable RealSense recording: {exc}") from None
        self._ctx, self._path = ctx, path
        self._playback = self.device.as_playback()
        self._playback.set_real_time(bool(realtime))
        self._lone: dict = {}
        self._started = False
        self.color_profile = self.depth_profile = None
        self._sensors = []
        for sensor in self.device.query_sensors():
            wanted = []
            for prof in sensor.get_stream_profiles():
                st = prof.stream_type()
                if st == rs.stream.color and self.color_profile is None:
                    self.color_profile = prof.as_video_stream_profile()
                    wanted.append(prof)
                elif st == rs.stream.depth and self.depth_profile is None:
                    self.depth_profile = prof.as_video_stream_profile()
                    wanted.append(prof)
            if wanted:
                self._sensors.append((sensor, wanted))
        if self.color_profile is None or self.depth_profile is None:
            self.close()
            raise CameraError(f"bag:{path}: needs both a colour and a depth stream")
        # half a frame period: two lone frames closer than this were taken together
        self._pair_tol_ms = 500.0 / max(self.color_profile.fps(), self.depth_profile.fps(), 1)
        self._syncer = rs.syncer(2)
        self._out = rs.frame_queue(2, keep_frames=True)
        self._pairer = rs.processing_block(self._pair)
        self._pairer.start(self._out)

    def _start(self) -> None:
        for sensor, profiles in self._sensors:
            sensor.open(profiles)
        for sensor, _ in self._sensors:
            sensor.start(self._syncer)
        self._started = True

    def _pair(self, frame, source) -> None:
        """Pass complete framesets on; join a lone colour and a lone depth frame taken together."""
        rs = self._rs
        fs = frame.as_frameset()
        if fs.get_color_frame() and fs.get_depth_frame():
            source.frame_ready(fs)
            return
        for f in fs:
            f.keep()
            self._lone[f.get_profile().stream_type()] = f
        color, depth = self._lone.get(rs.stream.color), self._lone.get(rs.stream.depth)
        if color is None or depth is None:
            return
        if abs(color.get_timestamp() - depth.get_timestamp()) <= self._pair_tol_ms:
            source.frame_ready(source.allocate_composite_frame([depth, color]))
            self._lone.clear()
        else:  # the older one has no partner in the recording
            older = rs.stream.color if color.get_timestamp() < depth.get_timestamp() else rs.stream.depth
            del self._lone[older]

    def ended(self) -> bool:
        return self._started and self._playback.current_status() == self._rs.playback_status.stopped

    def wait(self, timeout_s: float):
        """The next colour+depth frameset, or None when the recording ended or none came in `timeout_s`."""
        if not self._started:  # started at the first read, so that opening reads no frame
            self._start()
        deadline = time.monotonic() + timeout_s
        while True:
            ok, fs = self._out.try_wait_for_frame(0)
            if ok:
                return fs.as_frameset()
            ok, fs = self._syncer.try_wait_for_frames(50)  # short steps: the end of the file shows at once
            if ok:
                self._pairer.invoke(fs)
                continue
            if self.ended() or time.monotonic() >= deadline:
                return None

    def close(self) -> None:
        for sensor, _ in self._sensors if self._started else ():
            for call in (sensor.stop, sensor.close):
                try:
                    call()
                except RuntimeError:  # already stopped at the end of the file
                    pass
        self._started = False
        self._sensors = []
        self._lone.clear()
        try:
            self._ctx.unload_device(str(self._path))
        except RuntimeError:
            pass
