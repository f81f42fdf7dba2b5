"""`CameraLoop`: the daemon's one camera thread: source -> estimator -> the latest result.

The source is read through `LatestFrame`, so the estimator always takes the newest frame and stale ones are
dropped, never queued. The loop publishes immutable `Published` records by replacing one reference: API workers
read it without waiting on the loop, and nothing an HTTP client does can slow the loop down.

Faults never end the loop: a frame the estimator rejects or an estimator error is counted and logged; a source
that fails, times out or ends is stopped and reopened with a growing wait (`reconnect_min_s` doubling up to
`reconnect_max_s`), and meanwhile `camera_up` is False (`GET /readyz` fails).

With a calibration, the loop hands a frame to its `FloorWatch` every few seconds (never waiting for the check)
and withholds vehicle-frame output while the watch says the camera moved: such a frame is published with no
pallets and the reason in `error` (counted as a `calibration` failure), and `detect()` refuses.

Modes: "continuous" estimates every frame it takes; "triggered" only keeps the newest frame, and `detect()`
estimates on it when asked. `detect()` works in both modes (the estimator is not thread-safe: a lock
serialises it with the loop).
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..calibration import CalibrationError
from ..cameras import CameraError, CameraTimeout, LatestFrame, RGBDFrame, open_source, parse_source_spec
from ..results import FrameResult
from .config import ServeConfig
from .metrics import Metrics
from .snapshots import FrameRing

__all__ = ["CameraLoop", "Published", "RegionHint", "NoFrameError"]

log = logging.getLogger(__name__)

# how often the loop proves it is alive (heartbeat) while waiting for a frame or before a reconnect
TICK_S = 0.5


class NoFrameError(LookupError):
    """No recent camera frame to estimate on (not started yet, or the camera is down)."""


@dataclass(frozen=True)
class RegionHint:
    """Where the wanted pallet is expected (either part may be None): a pose counts only when its detector box's
    centre lies in `box_xyxy` (image pixels) and its centre's camera depth (z) is within `distance_m +-
    tolerance_m`."""

    box_xyxy: tuple[float, float, float, float] | None = None
    distance_m: float | None = None
    tolerance_m: float = 0.5

    def keeps(self, box_xyxy: np.ndarray, t_cam_m: np.ndarray) -> bool:
        """:param box_xyxy: (4,) pixels. :param t_cam_m: (3,) pallet centre, camera frame, metres."""
        if self.box_xyxy is not None:
            x1, y1, x2, y2 = self.box_xyxy
            cx, cy = (box_xyxy[0] + box_xyxy[2]) / 2, (box_xyxy[1] + box_xyxy[3]) / 2
            if not (x1 <= cx <= x2 and y1 <= cy <= y2):
                return False
        if self.distance_m is not None and abs(float(t_cam_m[2]) - self.distance_m) > self.tolerance_m:
            return False
        return True


@dataclass(frozen=True)
class Published:
    """One frame and what was estimated on it (result None: a frame not estimated, triggered mode).

    :ivar seq: increases by one per published record.
    :ivar received_monotonic: `time.monotonic()` when the loop took the frame (ages are measured from it).
    :ivar received_unix_s: wall-clock time of the same moment.
    :ivar trigger: "continuous" or "detect".
    :ivar hint: the region hint of a `detect()`, else None.
    :ivar n_outside_hint: accepted poses that the hint dropped.
    :ivar error: why the frame has no result to give ("" when it has one), e.g. vehicle-frame output withheld.
    """

    seq: int
    frame: RGBDFrame
    result: FrameResult | None
    received_monotonic: float
    received_unix_s: float
    trigger: str = "continuous"
    hint: RegionHint | None = None
    n_outside_hint: int = 0
    error: str = ""


class _StampedSource:
    """A frame source that notes when it last delivered a frame (read on the grabber's thread), so the camera's
    health does not depend on how long the estimator takes."""

    def __init__(self, source) -> None:
        self._source = source
        self.last_read_monotonic = float("-inf")

    def read(self):
        frame = self._source.read()
        if frame is not None:
            self.last_read_monotonic = time.monotonic()
        return frame

    def __getattr__(self, name: str):
        return getattr(self._source, name)


class CameraLoop:
    """The camera thread. :param config: the daemon's configuration. :param estimator: anything with
    `estimate(frame) -> FrameResult` and `model_size_m` (`EstimatorProcess`, `PalletEstimator`; called only under
    this loop's lock). :param metrics: where counts go. :param ring: recent frames for snapshots.
    :param source_factory: spec -> `FrameSource` (default `open_source` with the config's replay options).
    :param floor_watch: the calibration's floor check (None without a calibration); started and stopped with the
        loop."""

    def __init__(self, config: ServeConfig, estimator, metrics: Metrics, ring: FrameRing,
                 source_factory: Callable[[str], object] | None = None, floor_watch=None) -> None:
        self.config = config
        self.floor_watch = floor_watch
        self._vehicle = config.output.frame == "vehicle" and floor_watch is not None
        self.estimator = estimator
        self.metrics = metrics
        self.ring = ring
        self._source_factory = source_factory or self._open_source
        self._est_lock = threading.Lock()
        self._pub_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._counted = [0, 0]
        self._source: _StampedSource | None = None
        self._log_counts: dict[str, int] = {}
        self._subscribers: list[Callable[[Published], None]] = []
        self.latest: Published | None = None        #: newest record with a result
        self.latest_frame: Published | None = None  #: newest frame taken (with or without a result)
        self.camera_up = False
        self.last_error = ""
        self.heartbeat = time.monotonic()            #: last moment the loop proved it is not stuck
        metrics.set_age_function(self.result_age_s)

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> "CameraLoop":
        if self._thread is None:
            if self.floor_watch is not None:
                self.floor_watch.start()
            self._thread = threading.Thread(target=self._run, name="camera-loop", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("camera loop did not stop within %.1f s", timeout_s)
        if self.floor_watch is not None:
            self.floor_watch.stop()

    def alive(self, max_silence_s: float) -> bool:
        """The thread runs and has ticked within `max_silence_s` (neither the estimator nor the source hangs)."""
        return self._thread is not None and self._thread.is_alive() and \
            time.monotonic() - self.heartbeat < max_silence_s

    def subscribe(self, callback: Callable[[Published], None]) -> None:
        """`callback(published)` after each new result, on the loop's thread: it must return at once."""
        self._subscribers.append(callback)

    # -- what the API reads ---------------------------------------------------------------------------
    def result_age_s(self) -> float:
        latest = self.latest
        return float("nan") if latest is None else time.monotonic() - latest.received_monotonic

    def camera_age_s(self) -> float:
        """Seconds since the camera last delivered a frame (inf: none from the current connection)."""
        source = self._source
        return float("inf") if source is None or not self.camera_up else time.monotonic() - source.last_read_monotonic

    def camera_fresh(self) -> bool:
        """The camera streams: it delivered a frame within the configured `frame_timeout_s`."""
        return self.camera_age_s() <= self.config.camera.frame_timeout_s

    def detect(self, hint: RegionHint | None = None) -> Published:
        """Estimate on the newest frame now (any mode), keeping only poses inside `hint`.

        :raises NoFrameError: no frame, or the newest is older than the camera's `frame_timeout_s`.
        :raises CalibrationError: vehicle-frame output is withheld (the camera moved since calibration).
        """
        frame_pub = self.latest_frame
        if frame_pub is None or not self.camera_fresh():
            raise NoFrameError("no recent camera frame" + (f" ({self.last_error})" if self.last_error else ""))
        blocked = self._blocked(frame_pub.frame)
        if blocked:
            raise CalibrationError(blocked)
        result = self._estimate(frame_pub.frame)
        if result is None:
            raise ValueError("estimation failed on the newest frame (see the daemon's log)")
        n_out = 0
        if hint is not None:
            kept = [p for p in result.poses if hint.keeps(p.box_xyxy, p.t_m)]
            n_out = len(result.poses) - len(kept)
            result = dataclasses.replace(result, poses=kept)
        pub = self._record(frame_pub, result, "detect", hint, n_out)
        if self.config.camera.mode == "triggered":
            self._publish(pub)
        return pub

    # -- the thread -----------------------------------------------------------------------------------
    def _open_source(self, spec: str):
        kind, _ = parse_source_spec(spec)
        if kind == "replay":
            return open_source(spec, realtime=self.config.camera.realtime, loop=True)
        if kind == "bop":
            return open_source(spec, loop=True)
        return open_source(spec)

    def _run(self) -> None:
        c = self.config.camera
        wait_s, failed_before = c.reconnect_min_s, False
        while not self._stop.is_set():
            self.heartbeat = time.monotonic()
            try:
                self._source = _StampedSource(self._source_factory(c.source))
                grab = LatestFrame(self._source).start()
                self._counted = [0, 0]   # the new grabber's dropped frames and its source's skipped ones
            except Exception as exc:  # noqa: BLE001 - a camera that cannot open is retried, never fatal
                self._camera_failed(f"cannot open {c.source}: {exc}")
                failed_before = True
                self._sleep(wait_s)
                wait_s = min(2 * wait_s, c.reconnect_max_s)
                continue
            if failed_before:
                self.metrics.reconnects.inc()
                log.info("%s: reopened", c.source)
            try:
                for frame in self._frames(grab):
                    wait_s, failed_before = c.reconnect_min_s, False
                    self._take(frame)
            except CameraError as exc:
                self._camera_failed(f"{c.source}: {exc}")
                failed_before = True
            except Exception as exc:  # noqa: BLE001 - the thread must outlive any one failure
                log.exception("camera loop: unexpected error")
                self._camera_failed(f"{c.source}: unexpected error: {exc!r}")
                failed_before = True
            finally:
                self._count_source(grab)
                grab.stop()
            if not self._stop.is_set():
                self._sleep(wait_s)
                wait_s = min(2 * wait_s, c.reconnect_max_s)
        self.camera_up = False

    def _frames(self, grab: LatestFrame):
        """Frames from the grabber until stop; raises `CameraError` on a failed, silent or ended source."""
        timeout_s = self.config.camera.frame_timeout_s
        period_s = 1.0 / self.config.camera.max_rate_hz if self.config.camera.max_rate_hz > 0 else 0.0
        last = next_s = time.monotonic()
        while not self._stop.is_set():
            self.heartbeat = time.monotonic()
            if period_s:
                # the grabber keeps only the newest frame: the frames of the wait are dropped (and counted)
                self._sleep(next_s - time.monotonic())
                if self._stop.is_set():
                    return
            try:
                frame = grab.get(timeout_s=TICK_S)
            except CameraTimeout:
                if time.monotonic() - last > timeout_s:
                    raise CameraTimeout(f"no frame for {timeout_s} s") from None
                continue
            if frame is None:
                if self._stop.is_set():
                    return
                raise CameraError("the source ended")
            last = time.monotonic()
            # the next slot one period on; after a stall (no frame for longer), the schedule restarts here rather
            # than catching up with a burst
            next_s = max(next_s + period_s, last) if period_s else last
            if not self.camera_up:
                log.info("%s: streaming", self.config.camera.source)
            self.camera_up, self.last_error = True, ""
            self.metrics.camera_up.set(1)
            yield frame
            self._count_source(grab)

    def _take(self, frame: RGBDFrame) -> None:
        self.metrics.frames_received.inc()
        self.ring.push(frame)
        now = time.monotonic()
        frame_pub = Published(0, frame, None, now, time.time())
        self.latest_frame = frame_pub
        if self.floor_watch is not None:
            self.floor_watch.offer(frame)
        if self.config.camera.mode != "continuous":
            return
        blocked = self._blocked(frame)
        if blocked:
            self._failed("calibration", f"frame {frame.frame_number}: no vehicle-frame output: {blocked}")
            empty = FrameResult.empty(frame.rgb.shape[:2])
            self._publish(self._record(frame_pub, empty, "continuous", error=f"CalibrationError: {blocked}"))
            return
        result = self._estimate(frame)
        if result is not None:
            self._publish(self._record(frame_pub, result, "continuous"))

    def _estimate(self, frame: RGBDFrame) -> FrameResult | None:
        """The estimator's result, or None after counting and logging its failure."""
        from .worker import EstimatorCrashed

        try:
            with self._est_lock:
                result = self.estimator.estimate(frame)
        except EstimatorCrashed as exc:
            self._failed("estimator", f"frame {frame.frame_number}: {exc}")
            return None
        except (ValueError, TypeError) as exc:
            self._failed("bad_frame", f"frame {frame.frame_number}: rejected by the estimator: {exc}")
            return None
        except Exception as exc:  # noqa: BLE001 - one frame's failure is never fatal
            self._failed("estimator", f"frame {frame.frame_number}: estimator error: {exc!r}", exc_info=True)
            return None
        self.metrics.observe_result(result.timings_ms, len(result.poses))
        return result

    def _blocked(self, frame: RGBDFrame) -> str:
        """Why vehicle-frame output must not be given for this frame ("" when it may, or in the camera frame)."""
        return self.floor_watch.blocked_reason(frame) if self._vehicle else ""

    def _record(self, frame_pub: Published, result: FrameResult, trigger: str, hint: RegionHint | None = None,
                n_out: int = 0, error: str = "") -> Published:
        with self._pub_lock:
            self._seq += 1
            return dataclasses.replace(frame_pub, seq=self._seq, result=result, trigger=trigger, hint=hint,
                                       n_outside_hint=n_out, error=error)

    def _publish(self, pub: Published) -> None:
        self.latest = pub
        for callback in self._subscribers:
            try:
                callback(pub)
            except Exception:  # noqa: BLE001 - a subscriber's bug must not stop the camera
                log.exception("result subscriber failed")

    # -- faults -----------------------------------------------------------------------------------------
    def _camera_failed(self, message: str) -> None:
        self.camera_up, self.last_error = False, message
        self.metrics.camera_up.set(0)
        self._failed("camera", message)

    def _failed(self, reason: str, message: str, exc_info: bool = False) -> None:
        """Count a failure; log the first 10 of each reason, then every 100th (a camera left unplugged
        overnight must not fill the disk)."""
        self.metrics.failures.labels(reason).inc()
        n = self._log_counts[reason] = self._log_counts.get(reason, 0) + 1
        if n <= 10 or n % 100 == 0:
            log.warning("%s (%s failure %d)", message, reason, n, exc_info=exc_info)

    def _count_source(self, grab: LatestFrame) -> None:
        """Frames the grabber dropped and recorded frames the source skipped, since the last call."""
        dropped, skipped = grab.dropped, int(getattr(grab.source, "skipped", 0))
        if dropped > self._counted[0]:
            self.metrics.frames_dropped.inc(dropped - self._counted[0])
        if skipped > self._counted[1]:
            self.metrics.failures.labels("read_error").inc(skipped - self._counted[1])
        self._counted = [dropped, skipped]

    def _sleep(self, seconds: float) -> None:
        """Wait (stop ends it early), ticking the heartbeat."""
        end = time.monotonic() + seconds
        while not self._stop.is_set() and (left := end - time.monotonic()) > 0:
            self.heartbeat = time.monotonic()
            self._stop.wait(min(TICK_S, left))
