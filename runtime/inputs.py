"""Checking what an integrator hands to `PalletEstimator` (numpy only).

Every check raises `TypeError` (wrong kind of thing) or `ValueError` (right kind, wrong content) with a
message that says what was expected and what came, so the fix is obvious on the forklift.
"""
from __future__ import annotations

import numpy as np

from .geometry import check_K

__all__ = ["check_rgb", "check_rgbd", "check_image_size", "check_nonfinite_mode", "native_depth",
           "MAX_IMAGE_PIXELS", "NONFINITE_MODES"]

NONFINITE_MODES = ("raise", "as_missing")
# The largest colour stream of the supported cameras (OAK-D 4K, 3840 x 2160). The pipeline's memory and time
# grow with the pixel count (8000 x 6000 took 1.1 GB and 2.4 s), and the detector sees a downscaled image anyway:
# a larger frame is refused rather than slowly exhausting a forklift computer.
MAX_IMAGE_PIXELS = 3840 * 2160
MIN_IMAGE_SIDE = 8


def check_nonfinite_mode(mode) -> str:
    """Validate a `nonfinite_depth` choice: "raise" or "as_missing"."""
    if mode not in NONFINITE_MODES:
        raise ValueError(f"nonfinite_depth must be one of {NONFINITE_MODES}, got {mode!r}")
    return mode


def check_image_size(height: int, width: int) -> None:
    """Refuse images smaller than 8 px a side or larger than `MAX_IMAGE_PIXELS` (ValueError)."""
    if height < MIN_IMAGE_SIDE or width < MIN_IMAGE_SIDE:
        raise ValueError(f"image too small: {width}x{height} (at least {MIN_IMAGE_SIDE} px a side)")
    if height * width > MAX_IMAGE_PIXELS:
        raise ValueError(f"image too large: {width}x{height} = {height * width / 1e6:.1f} MP, the limit is "
                         f"{MAX_IMAGE_PIXELS / 1e6:.1f} MP (3840x2160); downscale it and its K")


def native_depth(depth: np.ndarray) -> np.ndarray:
    """Depth in the machine's byte order: big-endian uint16 / float (from some PNG or network readers) is
    converted, everything else returned as is."""
    if not depth.dtype.isnative:
        return depth.astype(depth.dtype.newbyteorder("="))
    return depth


def check_rgb(rgb) -> np.ndarray:
    """Validate an (H, W, 3) uint8 RGB image and return it."""
    if not isinstance(rgb, np.ndarray):
        raise TypeError(f"rgb must be a numpy array (H, W, 3) uint8, got {type(rgb).__name__}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise TypeError(f"rgb must be uint8 (0-255), got dtype {rgb.dtype}")
    return rgb


def check_rgbd(rgb, depth, K, depth_scale_m: float | None = None,
               nonfinite_depth: str = "raise") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate one RGB-D frame and return (rgb uint8 (H, W, 3), depth float32 metres (H, W), K float64 (3, 3)).

    :param rgb: (H, W, 3) uint8 RGB.
    :param depth: (H, W) registered to `rgb`: uint16 in units of `depth_scale_m` metres (default 0.001, mm)
        or float32/float64 metres, in either byte order. 0 = no data. At most `MAX_IMAGE_PIXELS`.
    :param K: (3, 3) intrinsics of the colour image (`geometry.check_K` with the image size).
    :param depth_scale_m: metres per unit of integer depth; must be None for float depth.
    :param nonfinite_depth: "raise" on NaN/inf in float depth, or "as_missing" to read them as no data
        (drivers that follow ROS REP 118 mark missing depth with NaN/inf).
    """
    check_nonfinite_mode(nonfinite_depth)
    check_rgb(rgb)
    if not isinstance(depth, np.ndarray):
        raise TypeError(f"depth must be a numpy array (H, W), got {type(depth).__name__}")
    if depth.ndim != 2:
        raise ValueError(f"depth must be a single-channel (H, W) image, got shape {depth.shape}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth {depth.shape} and rgb {rgb.shape[:2]} differ in size: depth must be aligned "
                         "(registered) to the colour image")
    check_image_size(*rgb.shape[:2])
    if K is None:
        raise ValueError("camera intrinsics K are missing: pass K=(3, 3) or an RGBDFrame that carries them")
    K = check_K(K, rgb.shape[:2])
    depth = native_depth(depth)

    if np.issubdtype(depth.dtype, np.integer):
        if depth.dtype != np.uint16:
            raise TypeError(f"integer depth must be uint16, got {depth.dtype}")
        scale = 0.001 if depth_scale_m is None else float(depth_scale_m)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"depth_scale_m must be a positive number of metres per unit, got {depth_scale_m}")
        depth_m = depth.astype(np.float32) * np.float32(scale)
        hi = float(depth.max())
    elif np.issubdtype(depth.dtype, np.floating):
        if depth_scale_m not in (None, 1, 1.0):
            raise ValueError(f"float depth is read as metres; depth_scale_m={depth_scale_m} applies to uint16 only")
        depth_m = depth.astype(np.float32, copy=True)
        # two reductions instead of a pass per test: NaN propagates through min/max, inf shows in them
        lo, hi = float(depth_m.min()), float(depth_m.max())
        if not (np.isfinite(lo) and np.isfinite(hi)):
            bad = ~np.isfinite(depth_m)
            if nonfinite_depth == "raise":
                raise ValueError(f"depth has {int(bad.sum())} NaN/inf pixels; mark missing depth with 0, or pass "
                                 "nonfinite_depth='as_missing'")
            depth_m[bad] = 0.0
            lo, hi = float(depth_m.min()), float(depth_m.max())
        if lo < 0:
            raise ValueError(f"depth has negative values (min {lo:.3f}); expected metres >= 0")
        if hi > 1000.0:
            raise ValueError(f"float depth must be metres, but values reach {hi:.0f}: "
                             "millimetres? pass uint16 or divide by 1000")
    else:
        raise TypeError(f"depth must be uint16 (units of depth_scale_m) or float metres, got dtype {depth.dtype}")
    if not hi > 0:
        raise ValueError("depth is all zero (no valid pixel): is the depth stream running and aligned to colour?")
    return rgb, depth_m, K
