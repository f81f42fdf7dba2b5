"""Every colour+depth frameset of a RealSense `.bag`, in order, with a stop that cannot deadlock.

Why not `rs.pipeline` or an `rs.syncer` as the sensors' sink:
- A pipeline started on a recording drops the first frameset now and then (measured: 1 run in 6
  here, more under load): its syncer emits the first depth and colour frames each alone and the
  pipeline discards incomplete sets.
- Without real-time pacing the playback blocks until the sink takes each frame. Stopping the sensors
  while a syncer's full queue holds the playback thread deadlocks (librealsense issues #3126, #2472;
  CI hung on it). Here the sink is our own callback, whose wait gives up as soon as `close()` starts.
- The playback status reads `stopped` right after the sensors start, before the first frame, and
  again when the file is read while frames are still on their way to the sink. The end of the
  recording is therefore the status `stopped` once frames came, and no frame for `_QUIET_S`.

Colour and depth frames taken together (timestamps within half a frame period) are joined into one
composite frameset, so `rs.align` and the depth filters see what a live camera gives.
"""
from __future__ import annotations

import collections
import threading
import time
from pathlib import Path

from .errors import CameraError

__all__ = ["BagPlayback"]

_QUEUE_FRAMES = 4   # frames held between the sensors' threads and the reader
_QUIET_S = 0.3      # after the file is read, this long without a frame means every frame came


class BagPlayback:
    """Frames of one recording. `wait()` gives the next colour+depth frameset, None at the end."""

    def __init__(self, rs, ctx, path: Path, realtime: bool) -> None:
        self._rs = rs
        try:
            self.device = ctx.load_device(str(path))
        except RuntimeError as exc:
            raise CameraError(f"bag:{path}: not a playable RealSense recording: {exc}") from None
        self._ctx, self._path, self._realtime = ctx, path, bool(realtime)
        self._playback = self.device.as_playback()
        self._playback.set_real_time(self._realtime)
        self._cond = threading.Condition()
        self._queue: collections.deque = collections.deque()  # single frames, as the sensors send them
        self._closing = False
        self._started = False
        self._frames_in = 0
        self._last_frame_t = 0.0
        self._lone: dict = {}
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
        # a processing block is the SDK's way to make a composite frameset from two frames
        self._pair_frames: list = []
        self._out = rs.frame_queue(1, keep_frames=True)
        self._composer = rs.processing_block(
            lambda _frame, source: source.frame_ready(source.allocate_composite_frame(self._pair_frames)))
        self._composer.start(self._out)

    def _start(self) -> None:
        for sensor, profiles in self._sensors:
            sensor.open(profiles)
        self._started = True
        self._last_frame_t = time.monotonic()
        # the playback reads from the first sensor's start on: paused, no frame of a later one is lost
        self._playback.pause()
        for sensor, _ in self._sensors:
            sensor.start(self._on_frame)
        self._playback.resume()

    def _on_frame(self, frame) -> None:
        """On a sensor's thread: hand the frame to the reader (waiting for room unless played in real time)."""
        frame.keep()
        with self._cond:
            while not self._realtime and len(self._queue) >= _QUEUE_FRAMES and not self._closing:
                self._cond.wait(0.05)
            if self._closing:
                return
            if len(self._queue) >= _QUEUE_FRAMES:  # real time: the oldest frame is dropped, as from a camera
                self._queue.popleft()
            self._queue.append(frame)
            self._frames_in += 1
            self._last_frame_t = time.monotonic()
            self._cond.notify_all()

    def _next_frame(self, timeout_s: float):
        with self._cond:
            if not self._queue:
                self._cond.wait(timeout_s)
            if not self._queue:
                return None
            frame = self._queue.popleft()
            self._cond.notify_all()
            return frame

    def ended(self) -> bool:
        if not self._started or self._playback.current_status() != self._rs.playback_status.stopped:
            return False
        with self._cond:
            return self._frames_in > 0 and not self._queue and time.monotonic() - self._last_frame_t >= _QUIET_S

    def wait(self, timeout_s: float):
        """The next colour+depth frameset, or None when the recording ended or none came in `timeout_s`."""
        if not self._started:  # started at the first read, so that opening reads no frame
            self._start()
        rs = self._rs
        deadline = time.monotonic() + timeout_s
        while True:
            frame = self._next_frame(0.05)  # short steps: the end of the file shows soon
            if frame is None:
                if self.ended() or time.monotonic() >= deadline:
                    return None
                continue
            self._lone[frame.get_profile().stream_type()] = frame
            color, depth = self._lone.get(rs.stream.color), self._lone.get(rs.stream.depth)
            if color is None or depth is None:
                continue
            if abs(color.get_timestamp() - depth.get_timestamp()) <= self._pair_tol_ms:
                self._lone.clear()
                return self._compose(depth, color)
            # the older one has no partner in the recording
            del self._lone[rs.stream.color if color.get_timestamp() < depth.get_timestamp() else rs.stream.depth]

    def _compose(self, depth, color):
        self._pair_frames = [depth, color]
        try:
            self._composer.invoke(depth)  # runs the block on this thread
            ok, fs = self._out.try_wait_for_frame(1000)
        finally:
            self._pair_frames = []
        if not ok:
            raise CameraError(f"bag:{self._path}: could not join a colour and a depth frame")
        return fs.as_frameset()

    def close(self) -> None:
        with self._cond:
            self._closing = True  # a sensor thread waiting in _on_frame returns now, so stop() can finish
            self._cond.notify_all()
        for sensor, _ in self._sensors if self._started else ():
            for call in (sensor.stop, sensor.close):
                try:
                    call()
                except RuntimeError:  # already stopped at the end of the file
                    pass
        self._started = False
        self._sensors = []
        self._lone.clear()
        with self._cond:
            self._queue.clear()
        try:
            self._ctx.unload_device(str(self._path))
        except RuntimeError:
            pass
