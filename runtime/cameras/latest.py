"""`LatestFrame`: read a live source on a background thread and keep only the newest frame.

The pose estimator is slower than the camera (30 fps vs a few Hz on two cores). Queuing frames would
make every pose later than the one before; instead the grabber overwrites the unconsumed frame and
counts it as dropped, so each `get()` returns the freshest frame there is.

    with LatestFrame(open_source("realsense")) as grab:
        while True:
            frame = grab.get(timeout_s=2.0)    # None at the end of a recording
            if frame is None:
                break
            ...

Errors of the source (e.g. `CameraDisconnected`) are re-raised in the consumer by `get()`, after the
last good frame was handed out.
"""
from __future__ import annotations

import logging
import threading
from typing import Iterator

from .base import FrameSource
from .errors import CameraError, CameraTimeout
from .frame import RGBDFrame

__all__ = ["LatestFrame"]

log = logging.getLogger(__name__)


class LatestFrame:
    """Background grabber keeping only the newest frame of `source`.

    :param source: any `FrameSource`; started here if not yet running, stopped by `stop()`.
    :param join_timeout_s: how long `stop()` waits for the reader thread (a blocked SDK call).
    """

    def __init__(self, source: FrameSource, join_timeout_s: float = 5.0) -> None:
        self.source = source
        self.join_timeout_s = float(join_timeout_s)
        self._cond = threading.Condition()
        self._frame: RGBDFrame | None = None
        self._error: BaseException | None = None
        self._ended = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.received = 0  #: frames read from the source
        self.dropped = 0   #: frames overwritten before anyone took them

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "LatestFrame":
        if self._thread is not None:
            return self
        self.source.start()
        self._thread = threading.Thread(target=self._run, name=f"grab-{self.source.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop reading and the source, join the thread. Safe to call twice."""
        self._stop.set()
        self.source.stop()  # first: this is what unblocks a reader waiting inside the SDK
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(self.join_timeout_s)
            if thread.is_alive():
                log.warning("%s: reader thread did not stop within %.1f s", self.source.name, self.join_timeout_s)
        with self._cond:
            self._cond.notify_all()

    def __enter__(self) -> "LatestFrame":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def K(self):
        return self.source.K

    # -- reader thread -----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                with self._cond:
                    if frame is None:
                        self._ended = True
                        self._cond.notify_all()
                        return
                    self.received += 1
                    if self._frame is not None:
                        self.dropped += 1
                    self._frame = frame
                    self._cond.notify_all()
        except BaseException as exc:  # handed to the consumer, never lost in a thread
            if self._stop.is_set():  # the source was stopped under the reader's feet: not an error
                log.debug("%s: reader ended by stop(): %r", self.source.name, exc)
                return
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    # -- consumer ----------------------------------------------------------------------------
    def get(self, timeout_s: float | None = None) -> RGBDFrame | None:
        """The newest frame not yet returned; waits for one if needed.

        :return: the frame, or None when the source ended (recordings) or the grabber was stopped.
        :raises CameraError: the source failed (re-raised from the reader thread).
        :raises CameraTimeout: no new frame within `timeout_s`.
        """
        if self._thread is None and self._frame is None and self._error is None and not self._ended:
            raise CameraError("LatestFrame.get() before start() (use `with LatestFrame(source):`)")
        with self._cond:
            ok = self._cond.wait_for(lambda: self._frame is not None or self._error is not None
                                     or self._ended or self._stop.is_set(), timeout_s)
            if not ok:
                raise CameraTimeout(f"{self.source.name}: no frame within {timeout_s} s")
            if self._frame is not None:
                frame, self._frame = self._frame, None
                return frame
            if self._error is not None:
                err = self._error
                if isinstance(err, CameraError):
                    raise err
                raise CameraError(f"{self.source.name}: frame reader failed: {err!r}") from err
            return None

    def __iter__(self) -> Iterator[RGBDFrame]:
        while True:
            frame = self.get()
            if frame is None:
                return
            yield frame
