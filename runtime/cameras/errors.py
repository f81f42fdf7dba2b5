"""Typed camera errors: an integrator catches `CameraError` and decides whether to retry."""
from __future__ import annotations

__all__ = ["CameraError", "CameraNotFound", "CameraDisconnected", "CameraTimeout", "FrameReadError",
           "SourceSpecError"]


class CameraError(RuntimeError):
    """Any failure of a frame source (device, SDK, recording)."""


class CameraNotFound(CameraError):
    """No device matches the request (nothing plugged in, wrong serial/MXID, missing recording)."""


class CameraDisconnected(CameraError):
    """The device went away while streaming and did not come back in time."""


class CameraTimeout(CameraError):
    """No frame arrived within the allowed time although the device is still present."""


class FrameReadError(CameraError):
    """A recorded frame is missing, truncated or corrupt (raised in `on_error="raise"` mode).

    :ivar frame_number: the frame number the unreadable frame would have had, so that a consumer can report
        it in place of the frame and read on; None when the failure is not one frame's (nothing readable at all).
    """

    def __init__(self, message: str, frame_number: int | None = None) -> None:
        super().__init__(message)
        self.frame_number = frame_number


class SourceSpecError(ValueError):
    """A source spec string (`realsense:SERIAL`, `bag:FILE`, ...) cannot be parsed."""
