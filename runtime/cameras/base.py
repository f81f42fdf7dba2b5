"""The one camera interface: a context manager that yields `RGBDFrame`s.

    with open_source("realsense") as cam:
        K = cam.K                      # known before the first frame
        for frame in cam:              # ends when a recording ends; live cameras run until stopped
            ...

Subclasses implement `_start()` (open the device or file, set `self._K` and `self._depth_scale_m`),
`_read()` (next frame, or None at the end of a recording) and `_stop()` (release everything; must be
safe to call twice and after a failed start).
"""
from __future__ import annotations

import abc
import logging
from typing import Iterator

import numpy as np

from .errors import CameraError
from .frame import RGBDFrame

__all__ = ["FrameSource"]

log = logging.getLogger(__name__)


class FrameSource(abc.ABC):
    """Base of all RGB-D frame sources. Not thread-safe: one consumer (or one `LatestFrame` grabber)."""

    #: True for cameras (frames arrive at their own pace and stale ones should be dropped).
    live: bool = False

    def __init__(self, name: str) -> None:
        self.name = name
        self._K: np.ndarray | None = None
        self._depth_scale_m: float | None = None
        self._running = False

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "FrameSource":
        if self._running:
            return self
        try:
            self._start()
        except BaseException:
            self._safe_stop()
            raise
        if self._K is None or self._depth_scale_m is None:
            self._safe_stop()
            raise CameraError(f"{self.name}: source started without intrinsics or depth scale")
        self._running = True
        log.info("%s: started (depth scale %.6g m)", self.name, self._depth_scale_m)
        return self

    def stop(self) -> None:
        if self._running:
            log.info("%s: stopping", self.name)
        self._running = False
        self._safe_stop()

    def _safe_stop(self) -> None:
        try:
            self._stop()
        except Exception:  # stopping must never mask the error that made us stop
            log.exception("%s: error while stopping", self.name)

    def __enter__(self) -> "FrameSource":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- frames ------------------------------------------------------------------------------
    def read(self) -> RGBDFrame | None:
        """Next frame, or None at the end of a recording. Raises `CameraError` subclasses on failure."""
        if not self._running:
            raise CameraError(f"{self.name}: read() before start() (use `with source:` or call start())")
        return self._read()

    def __iter__(self) -> Iterator[RGBDFrame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    # -- what is known before the first frame --------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics of the colour image (and of the aligned depth)."""
        if self._K is None:
            raise CameraError(f"{self.name}: intrinsics are known only after start()")
        return self._K.copy()

    @property
    def depth_scale_m(self) -> float:
        """Metres per depth unit of `RGBDFrame.depth`."""
        if self._depth_scale_m is None:
            raise CameraError(f"{self.name}: depth scale is known only after start()")
        return self._depth_scale_m

    @property
    def running(self) -> bool:
        return self._running

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    # -- to implement ------------------------------------------------------------------------
    @abc.abstractmethod
    def _start(self) -> None: ...

    @abc.abstractmethod
    def _read(self) -> RGBDFrame | None: ...

    @abc.abstractmethod
    def _stop(self) -> None: ...
