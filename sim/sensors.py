"""Sensor models: what a real camera makes of the ideal rendered depth and colour.

The D435-like depth model follows active-stereo geometry (left imager is the depth reference, the
right imager sits `baseline_m` to its right):
- noise: sigma_z = z^2 * subpixel / (f * baseline), the depth error of a `subpixel` disparity error,
  half of it spatially correlated (stereo matching blurs over a window);
- occlusion shadow: background pixels the right imager cannot see (just left of near objects) get no depth;
- flying pixels: at depth edges some pixels take a depth between foreground and background;
- speckle dropouts, range limits (0.3 - 10 m), quantisation to millimetres.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["SENSORS", "StereoDepthModel", "RgbCameraModel", "PixelInfo", "stereo_shadow_mask", "apply_depth_model",
           "apply_rgb_model", "correlated_noise"]

# Depth sensors selectable by name (`SimConfig.sensor`); their models: `pallet6d.sim.depth_sensors.SENSOR_MODELS`.
SENSORS: tuple[str, ...] = ("ideal", "d435", "oakd", "tof")


@dataclass(frozen=True)
class StereoDepthModel:
    """Parameters of a D435-like active stereo depth sensor."""

    baseline_m: float = 0.050
    subpixel: float = 0.08
    min_m: float = 0.3
    max_m: float = 10.0
    flying_prob: float = 0.5       # probability that a depth-edge pixel becomes a flying pixel
    edge_jump_m: float = 0.08      # depth difference that makes an edge
    dropout_prob: float = 0.0004   # seeds of speckle holes
    quantum_m: float = 0.001

    def __post_init__(self) -> None:
        if not (self.baseline_m > 0 and self.subpixel >= 0 and 0 <= self.min_m < self.max_m and self.quantum_m >= 0):
            raise ValueError(f"invalid stereo depth model parameters: {self}")

    def sigma_m(self, z_m: np.ndarray, f_px: float) -> np.ndarray:
        """Depth noise standard deviation (metres) at depth z (metres) for focal length f (pixels)."""
        return np.asarray(z_m) ** 2 * self.subpixel / (f_px * self.baseline_m)


@dataclass(frozen=True)
class RgbCameraModel:
    """Colour camera effects, applied to a linear [0, 1] image."""

    exposure: float = 1.0          # multiplies the light; < 0.5 is a dim scene
    noise_sigma: float = 0.0       # read noise (gaussian), [0, 1] units
    shot_noise: float = 0.01       # photon noise grows with sqrt(signal)
    blur_px: float = 0.0           # horizontal motion blur length in pixels (0 = none)
    gamma: float = 1.0            # the shaded image is already display-referred; < 1 brightens shadows


@dataclass
class PixelInfo:
    """What a depth sensor model may know about each pixel besides its ideal depth.

    normal_cam: (H, W, 3) unit surface normal, camera frame (0 where nothing was hit).
    albedo: (H, W) surface reflectance in [0, 1] (grey level of the texture before lighting).
    box_index: (H, W) int index of the box hit, -1 = none.
    intensity: (H, W) linear grey level of the lit image (the texture a passive stereo matcher sees).
    """

    normal_cam: np.ndarray
    albedo: np.ndarray
    box_index: np.ndarray
    intensity: np.ndarray

    def __post_init__(self) -> None:
        h, w = self.box_index.shape
        if self.normal_cam.shape != (h, w, 3) or self.albedo.shape != (h, w) or self.intensity.shape != (h, w):
            raise ValueError(f"PixelInfo arrays must be ({h}, {w}[, 3]), got normal {self.normal_cam.shape}, "
                             f"albedo {self.albedo.shape}, intensity {self.intensity.shape}")


def correlated_noise(shape: tuple[int, int], cell_px: int, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 unit-variance noise, smooth over about `cell_px` pixels (bilinear upsampled cells)."""
    h, w = shape
    coarse = rng.standard_normal(((h + cell_px - 1) // cell_px, (w + cell_px - 1) // cell_px)).astype(np.float32)
    smooth = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
    return smooth / max(float(smooth.std()), 1e-6)


def stereo_shadow_mask(depth_m: np.ndarray, f_px: float, baseline_m: float) -> np.ndarray:
    """Pixels the right imager of a stereo pair cannot see (the left-camera occlusion shadow).

    Pixel u of the reference (left) image appears at u - d(u) in the right image, d = f * B / z.
    It is occluded when a pixel to its right lands at or left of it there (that pixel is nearer).

    :param depth_m: (H, W) metres, 0 = no data (treated as infinitely far).
    :return: (H, W) bool, True = occluded.
    """
    z = np.asarray(depth_m, dtype=np.float64)
    with np.errstate(divide="ignore"):
        disp = np.where(z > 0, f_px * baseline_m / z, 0.0)
    w = z.shape[1]
    x_right = np.arange(w)[None, :] - disp
    # Minimum over pixels strictly to the right, per row.
    suffix_min = np.minimum.accumulate(x_right[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([suffix_min[:, 1:], np.full((z.shape[0], 1), np.inf)], axis=1)
    return (right_min < x_right - 0.5) & (z > 0)


def apply_depth_model(depth_m: np.ndarray, f_px: float, model: StereoDepthModel | None,
                      rng: np.random.Generator) -> np.ndarray:
    """Sensor depth from ideal depth. `model` None = ideal sensor (returned unchanged, as float32).

    :param depth_m: (H, W) ideal depth in metres (0 = no surface).
    :return: (H, W) float32 metres, 0 = invalid.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if model is None:
        return depth.copy()
    h, w = depth.shape
    valid = depth > 0
    far = np.where(valid, depth, np.float32(1e4))
    # Flying pixels: mixes of the nearest and farthest depth in a 3x3 neighbourhood.
    kernel = np.ones((3, 3), np.uint8)
    near_n, far_n = cv2.erode(far, kernel), cv2.dilate(np.where(valid, depth, 0), kernel)
    edge = valid & (far_n - near_n > model.edge_jump_m) & (far_n < 1e3)
    flying = edge & (rng.random((h, w)) < model.flying_prob)
    out = depth.copy()
    mix = rng.random((h, w)).astype(np.float32)
    out[flying] = (near_n + mix * (far_n - near_n))[flying]
    # Noise: half white, half correlated over ~8 px windows.
    sigma = model.sigma_m(out, f_px).astype(np.float32)
    white = rng.standard_normal((h, w)).astype(np.float32)
    smooth = correlated_noise((h, w), 8, rng)
    out = out + sigma * (np.float32(np.sqrt(0.5)) * white + np.float32(np.sqrt(0.5)) * smooth)
    # Invalid pixels: stereo shadow, speckle holes, out of range, no surface.
    invalid = ~valid | stereo_shadow_mask(depth, f_px, model.baseline_m)
    seeds = (rng.random((h, w)) < model.dropout_prob).astype(np.uint8)
    invalid |= cv2.dilate(seeds, np.ones((3, 3), np.uint8)).astype(bool)
    invalid |= (out < model.min_m) | (out > model.max_m)
    out[invalid] = 0.0
    if model.quantum_m > 0:
        out = np.round(out / model.quantum_m) * np.float32(model.quantum_m)
    return out.astype(np.float32)


def apply_rgb_model(rgb_linear: np.ndarray, model: RgbCameraModel, rng: np.random.Generator) -> np.ndarray:
    """Camera image from the shaded linear image.

    :param rgb_linear: (H, W, 3) float, nominally [0, 1].
    :return: (H, W, 3) uint8 RGB.
    """
    img = np.asarray(rgb_linear, dtype=np.float32) * np.float32(model.exposure)
    if model.blur_px >= 1.0:
        n = int(round(model.blur_px))
        img = cv2.blur(img, (n, 1))
    if model.shot_noise > 0 or model.noise_sigma > 0:
        sigma = np.sqrt(model.noise_sigma ** 2 + model.shot_noise ** 2 * np.clip(img, 0, None))
        img = img + sigma * rng.standard_normal(img.shape).astype(np.float32)
    img = np.clip(img, 0, 1) ** np.float32(model.gamma)
    return (img * 255 + 0.5).astype(np.uint8)
