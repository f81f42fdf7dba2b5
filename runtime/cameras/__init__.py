"""Frame sources: RealSense D435 (live and .bag), OAK-D, replay folders, BOP datasets.

Camera SDKs (pyrealsense2, depthai) are imported only when such a source starts, so importing this
package costs numpy + OpenCV and works on the plain install.
"""
from .base import FrameSource
from .errors import (CameraDisconnected, CameraError, CameraNotFound, CameraTimeout, FrameReadError,
                     SourceSpecError)
from .frame import RGBDFrame
from .latest import LatestFrame
from .replay import ReplaySource, ReplayWriter
from .spec import open_source, parse_source_spec

__all__ = [
    "FrameSource", "RGBDFrame", "LatestFrame", "ReplaySource", "ReplayWriter", "open_source",
    "parse_source_spec", "CameraError", "CameraNotFound", "CameraDisconnected", "CameraTimeout",
    "FrameReadError", "SourceSpecError",
]
