"""`RGBDFrame`: one colour image with depth aligned to it, as every frame source yields it.

Depth is kept as the sensor delivers it, uint16 in units of `depth_scale_m` metres (RealSense D435:
0.001 by default; OAK-D: always millimetres), because that is lossless, half the size of float32 and
what the replay format stores. `frame.depth_m` gives float32 metres, 0 = no data.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pallet6d.runtime.geometry import check_K, depth_to_metres
from pallet6d.runtime.inputs import native_depth

__all__ = ["RGBDFrame"]


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """One RGB-D frame.

    :param rgb: (H, W, 3) uint8 RGB (not BGR).
    :param depth: (H, W) uint16 depth in units of `depth_scale_m`, registered to `rgb` pixel for pixel; 0 = no data.
    :param K: (3, 3) pinhole intrinsics of the colour image (and so of the aligned depth), `check_K` with
        the image size.
    :param depth_scale_m: metres per depth unit (> 0).
    :param timestamp_s: capture time in seconds (device clock for cameras, recording time for replays).
    :param frame_number: frame counter of the source (monotonic within one stream).
    :param source: which source produced it, e.g. "realsense:123456789012", "replay:/data/run1".
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    depth_scale_m: float
    timestamp_s: float
    frame_number: int
    source: str = ""

    def __post_init__(self) -> None:
        rgb = np.asarray(self.rgb)
        depth = native_depth(np.asarray(self.depth))   # big-endian uint16 (some PNG readers) is converted
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must be (H, W, 3), got shape {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise TypeError(f"rgb must be uint8, got {rgb.dtype}")
        if depth.shape != rgb.shape[:2]:
            raise ValueError(f"depth must be aligned to rgb: expected shape {rgb.shape[:2]}, got {depth.shape}")
        if depth.dtype != np.uint16:
            raise TypeError(f"depth must be uint16 in depth_scale_m units, got {depth.dtype}")
        scale = float(self.depth_scale_m)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"depth_scale_m must be a positive number, got {self.depth_scale_m}")
        ts = float(self.timestamp_s)
        if not np.isfinite(ts):
            raise ValueError(f"timestamp_s must be finite, got {self.timestamp_s}")
        object.__setattr__(self, "rgb", rgb)
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "K", check_K(self.K, rgb.shape[:2]))
        object.__setattr__(self, "depth_scale_m", scale)
        object.__setattr__(self, "timestamp_s", ts)
        object.__setattr__(self, "frame_number", int(self.frame_number))

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def depth_m(self) -> np.ndarray:
        """(H, W) float32 depth in metres, 0 where there is no data."""
        return depth_to_metres(self.depth, self.depth_scale_m)

    @classmethod
    def from_depth_m(cls, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, timestamp_s: float,
                     frame_number: int, source: str = "", depth_scale_m: float = 0.001) -> "RGBDFrame":
        """Build a frame from float metres (quantized to `depth_scale_m`; NaN, <= 0 and overflow -> 0)."""
        depth_m = np.asarray(depth_m, dtype=np.float64)
        if depth_m.ndim != 2:
            raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
        units = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m / depth_scale_m, 0.0)
        units = np.rint(units)
        units[units > np.iinfo(np.uint16).max] = 0  # out of range for the format: no data, not a wrong value
        return cls(rgb, units.astype(np.uint16), K, depth_scale_m, timestamp_s, frame_number, source)
