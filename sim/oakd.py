"""OAK-D-like passive stereo depth model (Luxonis OAK-D: two global-shutter mono imagers 7.5 cm apart).

What sets it apart from the D435-like model (`StereoDepthModel`), from Luxonis' documentation
(docs.luxonis.com "Configuring Stereo Depth", StereoDepth node "Depth Modes"):
- baseline 7.5 cm: depth = f * B / disparity; a wider baseline, so less depth noise at range;
- disparity search 0..95 px (0..190 with extended disparity): nothing nearer than f * B / 95 is measured;
- subpixel disparity with 3 fractional bits by default: disparity is quantised to 1/8 px, so depth comes in
  steps that grow with z^2 (visible terraces on far surfaces);
- left-right check: disparities matched right-to-left and left-to-right must agree, which removes the
  occluded band beside near objects and unreliable pixels at depth edges;
- passive matching (no dot projector on the plain OAK-D): surfaces without texture match badly: noisy
  disparity and holes where the local contrast is too low (confidence threshold);
- block matching fattens foreground objects into the background at depth edges;
- a median filter on the disparity (on by default on the device) smooths noise and fills isolated holes.
The depth error grows as sigma_z = z^2 * sigma_d / (f * B) (Luxonis quote below 2 % up to 4 m on textured
targets for the OAK-D family).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pallet6d.sim.sensors import PixelInfo, correlated_noise, stereo_shadow_mask

__all__ = ["OakdStereoModel", "local_contrast", "apply_oakd"]


@dataclass(frozen=True)
class OakdStereoModel:
    """Parameters of an OAK-D-like passive stereo depth sensor (disparities in pixels of the rendered image)."""

    baseline_m: float = 0.075
    subpixel_bits: int = 3            # disparity step 1 / 2^bits px
    sigma_disparity_px: float = 0.12  # disparity noise on well-textured surfaces
    max_disparity_px: float = 95.0    # search range; 190 with extended disparity
    max_m: float = 15.0
    contrast_threshold: float = 0.005  # local contrast (std / mean of intensity) below which matching fails
    lr_edge_px: int = 1               # band beside depth edges removed by the left-right check
    fatten_px: int = 2                # foreground spreads this far into the background at depth edges
    fatten_prob: float = 0.5
    edge_jump_m: float = 0.08
    dropout_prob: float = 0.0003
    median_px: int = 5                # median filter on the disparity (0 = off; the device's default is on)
    quantum_m: float = 0.001

    def __post_init__(self) -> None:
        if not (self.baseline_m > 0 and 0 <= self.subpixel_bits <= 5 and self.sigma_disparity_px >= 0
                and self.max_disparity_px > 0 and self.max_m > 0 and self.contrast_threshold >= 0
                and self.lr_edge_px >= 0 and self.fatten_px >= 0 and 0 <= self.fatten_prob <= 1
                and self.median_px in (0, 3, 5) and self.quantum_m >= 0):
            raise ValueError(f"invalid OAK-D stereo model parameters: {self}")

    def min_m(self, f_px: float) -> float:
        """Nearest measurable depth (metres): the largest disparity the matcher searches."""
        return f_px * self.baseline_m / self.max_disparity_px

    def sigma_m(self, z_m: np.ndarray, f_px: float) -> np.ndarray:
        """Depth noise sigma (metres) on a textured surface at depth z (metres)."""
        return np.asarray(z_m) ** 2 * self.sigma_disparity_px / (f_px * self.baseline_m)


def local_contrast(intensity: np.ndarray, window_px: int = 7) -> np.ndarray:
    """(H, W) float32 std / mean of the intensity in a window: the texture a block matcher can lock onto."""
    img = np.asarray(intensity, np.float32)
    k = (window_px, window_px)
    mean = cv2.blur(img, k)
    var = np.maximum(cv2.blur(img * img, k) - mean * mean, 0)
    return np.sqrt(var) / np.maximum(mean, 0.02)


def apply_oakd(depth_m: np.ndarray, f_px: float, model: OakdStereoModel, info: PixelInfo,
               rng: np.random.Generator) -> np.ndarray:
    """OAK-D-like sensor depth from ideal depth.

    :param depth_m: (H, W) ideal depth, metres (0 = no surface). :param f_px: focal length, pixels.
    :param info: per-pixel scene data; `info.intensity` is the texture the matcher sees.
    :return: (H, W) float32 metres, 0 = invalid.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    h, w = depth.shape
    valid = depth > 0
    fb = np.float32(f_px * model.baseline_m)
    disp = np.where(valid, fb / np.maximum(depth, 1e-3), 0).astype(np.float32)
    # Foreground fattening: near the edge of a nearer surface, the matching window is dominated by it.
    if model.fatten_px > 0:
        k = np.ones((2 * model.fatten_px + 1, 2 * model.fatten_px + 1), np.uint8)
        disp_max = cv2.dilate(disp, k)
        jump = valid & (disp_max > disp) & (fb / np.maximum(disp, 1e-3) - fb / np.maximum(disp_max, 1e-3)
                                            > model.edge_jump_m)
        fat = jump & (rng.random((h, w)) < model.fatten_prob)
        disp = np.where(fat, disp_max, disp)
    # Disparity noise, larger where the texture is weak; half of it correlated over the matching window.
    contrast = local_contrast(info.intensity)
    weak = np.float32(model.contrast_threshold) / np.maximum(contrast, 1e-4)
    sigma_px = np.float32(model.sigma_disparity_px) * (1 + np.minimum(weak, 8))
    noise = np.float32(np.sqrt(0.5)) * rng.standard_normal((h, w)).astype(np.float32) \
        + np.float32(np.sqrt(0.5)) * correlated_noise((h, w), 6, rng)
    disp = disp + sigma_px * noise
    step = np.float32(2.0 ** -model.subpixel_bits)
    disp = np.round(disp / step) * step
    # Invalid: left-right check failures (occlusion shadow, a band at depth edges), weak texture, range.
    invalid = ~valid | stereo_shadow_mask(depth, f_px, model.baseline_m)
    if model.lr_edge_px > 0:
        k = np.ones((3, 2 * model.lr_edge_px + 1), np.uint8)
        d_near = cv2.dilate(np.where(valid, depth, 0).astype(np.float32), k)
        d_far = cv2.erode(np.where(valid, depth, np.float32(1e4)), k)
        invalid |= (d_near - d_far > model.edge_jump_m) & (d_near < 1e3)
    confidence = contrast / np.float32(max(model.contrast_threshold, 1e-6))
    invalid |= rng.random((h, w)) > np.clip(confidence - 0.5, 0, 1)
    seeds = (rng.random((h, w)) < model.dropout_prob).astype(np.uint8)
    invalid |= cv2.dilate(seeds, np.ones((5, 5), np.uint8)).astype(bool)
    invalid |= (disp <= fb / model.max_m) | (disp > model.max_disparity_px)
    disp = np.where(invalid, 0, disp).astype(np.float32)
    if model.median_px:
        # The median smooths the noise and fills isolated holes; it keeps disparities on the 1/2^bits grid.
        disp = cv2.medianBlur(disp, model.median_px)
    out = np.where(disp > 0, fb / np.maximum(disp, step), 0).astype(np.float32)
    if model.quantum_m > 0:
        out = np.round(out / model.quantum_m) * np.float32(model.quantum_m)
    return out.astype(np.float32)
