"""What a colour camera does to the light reaching it: exposure, white balance, vignetting, blur, motion blur,
chromatic shift, shot and read noise, tone curve, 8-bit quantisation and JPEG compression.

Each effect is a pure function of an (H, W, 3) float32 linear image in [0, 1] (JPEG: uint8), returning the
same shape and dtype; `apply_camera_effects` chains them in the order a camera applies them.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["CameraEffects", "auto_exposure_gain", "white_balance", "vignette", "defocus_blur", "motion_blur",
           "chromatic_shift", "sensor_noise", "tone_curve", "to_uint8", "jpeg", "apply_camera_effects"]


@dataclass(frozen=True)
class CameraEffects:
    """One camera's drawn settings for one frame (see `pallet6d.sim.appearance.AppearanceConfig` for ranges)."""

    exposure: float = 1.0                    # multiplies the auto-exposure gain (< 1 under-, > 1 over-exposed)
    auto_exposure: bool = True               # scale the image so its mean grey is `ae_target`
    ae_target: float = 0.4
    wb_gains: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.0                  # brightness loss in the image corners (0..1)
    defocus_sigma_px: float = 0.0
    motion_blur_px: float = 0.0
    motion_blur_deg: float = 0.0             # direction of the motion blur in the image (0 = horizontal)
    chromatic_px: float = 0.0                # red/blue shift at the image corner (lateral chromatic aberration)
    shot_noise: float = 0.0                  # photon noise: sigma = shot_noise * sqrt(signal)
    read_noise: float = 0.0                  # gaussian read noise sigma, [0, 1] units
    gamma: float = 1.0                       # tone curve exponent applied to the [0, 1] image
    jpeg_quality: int = 0                    # 0 = no JPEG, else 1..100

    def __post_init__(self) -> None:
        if not (self.exposure > 0 and 0 < self.ae_target < 1 and len(self.wb_gains) == 3
                and min(self.wb_gains) > 0 and 0 <= self.vignetting <= 1 and self.defocus_sigma_px >= 0
                and self.motion_blur_px >= 0 and self.chromatic_px >= 0 and self.shot_noise >= 0
                and self.read_noise >= 0 and self.gamma > 0 and 0 <= self.jpeg_quality <= 100):
            raise ValueError(f"invalid camera effects: {self}")


def _f32(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {img.shape}")
    return img.astype(np.float32, copy=False)


def auto_exposure_gain(img: np.ndarray, target: float = 0.4) -> float:
    """Gain that brings the image's mean grey to `target` (a camera's auto exposure), in [1/16, 16]."""
    mean = float(_f32(img).mean())
    return float(np.clip(target / max(mean, 1e-4), 1 / 16, 16))


def white_balance(img: np.ndarray, gains) -> np.ndarray:
    """Per-channel gains (3,): an imperfect white balance gives a colour cast."""
    return _f32(img) * np.asarray(gains, np.float32)[None, None, :]


def vignette(img: np.ndarray, strength: float) -> np.ndarray:
    """Darken towards the corners: brightness 1 - strength * r^2, r = 1 at the corner."""
    img = _f32(img)
    h, w = img.shape[:2]
    y = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / max((h - 1) / 2, 1)
    x = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / max((w - 1) / 2, 1)
    r2 = (x[None, :] ** 2 + y[:, None] ** 2) / 2
    return img * (1 - np.float32(strength) * r2)[:, :, None]


def defocus_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur (out of focus)."""
    img = _f32(img)
    return cv2.GaussianBlur(img, (0, 0), float(sigma_px)) if sigma_px > 0.3 else img


def motion_blur(img: np.ndarray, length_px: float, angle_deg: float) -> np.ndarray:
    """Blur along a line of `length_px` pixels at `angle_deg` (camera moving during the exposure)."""
    img = _f32(img)
    n = int(round(length_px))
    if n < 2:
        return img
    k = np.zeros((n, n), np.float32)
    c = (n - 1) / 2
    t = np.linspace(-c, c, 4 * n)
    a = np.radians(angle_deg)
    xs = np.clip(np.round(c + t * np.cos(a)), 0, n - 1).astype(int)
    ys = np.clip(np.round(c + t * np.sin(a)), 0, n - 1).astype(int)
    k[ys, xs] = 1.0
    return cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)


def chromatic_shift(img: np.ndarray, corner_px: float) -> np.ndarray:
    """Lateral chromatic aberration: red magnified and blue shrunk about the centre, by `corner_px` at a corner."""
    img = _f32(img)
    h, w = img.shape[:2]
    if corner_px <= 0.05:
        return img
    r = float(np.hypot(w / 2, h / 2))
    out = img.copy()
    for ch, sign in ((0, 1.0), (2, -1.0)):
        s = 1 + sign * corner_px / r
        M = np.array([[s, 0, (1 - s) * (w - 1) / 2], [0, s, (1 - s) * (h - 1) / 2]], np.float32)
        out[:, :, ch] = cv2.warpAffine(img[:, :, ch], M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out


def sensor_noise(img: np.ndarray, shot: float, read: float, rng: np.random.Generator) -> np.ndarray:
    """Photon (shot) noise growing with sqrt(signal) plus gaussian read noise."""
    img = _f32(img)
    if shot <= 0 and read <= 0:
        return img
    sigma = np.sqrt(np.float32(read) ** 2 + np.float32(shot) ** 2 * np.clip(img, 0, None))
    return img + sigma * rng.standard_normal(img.shape, dtype=np.float32)


def tone_curve(img: np.ndarray, gamma: float) -> np.ndarray:
    """Clip to [0, 1] (sensor saturation) and apply the exponent."""
    img = np.clip(_f32(img), 0, 1)
    return img if gamma == 1.0 else img ** np.float32(gamma)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """[0, 1] float -> uint8 with rounding."""
    return (np.clip(_f32(img), 0, 1) * 255 + 0.5).astype(np.uint8)


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """Compress and decompress as JPEG at `quality` (1..100). (H, W, 3) uint8 RGB in and out."""
    if img.dtype != np.uint8 or img.ndim != 3:
        raise ValueError(f"jpeg needs an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy()


def apply_camera_effects(rgb_linear: np.ndarray, fx: CameraEffects, rng: np.random.Generator) -> np.ndarray:
    """Camera image (H, W, 3) uint8 from the lit linear image (H, W, 3) float."""
    img = _f32(rgb_linear)
    gain = fx.exposure * (auto_exposure_gain(img, fx.ae_target) if fx.auto_exposure else 1.0)
    img = img * np.float32(gain)
    img = white_balance(img, fx.wb_gains)
    if fx.vignetting > 0:
        img = vignette(img, fx.vignetting)
    img = defocus_blur(img, fx.defocus_sigma_px)
    img = motion_blur(img, fx.motion_blur_px, fx.motion_blur_deg)
    img = chromatic_shift(img, fx.chromatic_px)
    img = sensor_noise(img, fx.shot_noise, fx.read_noise, rng)
    out = to_uint8(tone_curve(img, fx.gamma))
    return jpeg(out, fx.jpeg_quality) if fx.jpeg_quality > 0 else out
