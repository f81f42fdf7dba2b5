"""Time-of-flight depth sensor model (forklift ToF cameras such as ifm O3R or Basler blaze).

An indirect (phase) ToF camera lights the scene with modulated near-infrared light and measures, per pixel,
the phase of the returning light. What that does to the depth:
- amplitude: the returned signal is A ~ albedo * cos(incidence) / z^2. Pixels whose amplitude falls below
  the camera's confidence threshold are invalid: dark (low-albedo) surfaces, far surfaces and grazing
  surfaces drop out first (black plastic pallets are the classic case); bright surfaces very near the
  camera saturate the pixel and drop out too.
- noise: depth noise is inversely proportional to the signal-to-noise ratio of the phase measurement
  (sigma_d = c / (4 pi f) * sigma_phi, sigma_phi ~ 1 / SNR); in the shot-noise-limited regime SNR ~ sqrt(A),
  so sigma grows about linearly with range on a given surface and with 1 / sqrt(albedo). Basler's blaze-101
  data sheet gives < 1 mm temporal noise up to 5.5 m and +-5 mm accuracy over 0.5-5.5 m on its reference
  target, range 0.3-10 m (docs.baslerweb.com, "Fast Mode" / "Operating Mode"); forklift-grade heads are
  noisier on dark targets, which is what `sigma_ref_m` at `ref_albedo` sets.
- flying (mixed) pixels: a pixel that straddles a depth edge receives light from both surfaces and reports
  a depth between them (pmdtec.com FAQ "flying pixel").
- multipath: in a concave corner (floor meeting a pallet face, a load standing on a pallet) light reaches
  a point also via the other surface; the longer path adds to the direct one and the measured depth is too
  long (overestimation near corners: Nuvoton ToF manual, "Multipath Interference"; Chronoptics, "Multipath
  Interference in Indirect Time-of-Flight Depth Sensors"). Modelled as a one-bounce sum over neighbouring
  surface patches: the measured round trip is the amplitude-weighted mean of the direct and indirect paths.
- the colour image is registered onto the depth, and pixels without depth are black in it.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pallet6d.sim.sensors import PixelInfo, correlated_noise

__all__ = ["ToFDepthModel", "tof_amplitude", "multipath_bias_m", "apply_tof", "register_rgb_to_depth"]


@dataclass(frozen=True)
class ToFDepthModel:
    """Parameters of an indirect ToF depth camera. Amplitudes are albedo * cos(incidence) / z^2 (1/m^2)."""

    min_m: float = 0.3
    max_m: float = 10.0
    min_amplitude: float = 0.01      # confidence threshold: albedo 0.1 facing the camera is lost beyond 3.2 m
    max_amplitude: float = 6.0       # saturation: white (0.9) surfaces facing the camera nearer than 0.39 m
    sigma_ref_m: float = 0.004       # noise sigma of a surface of ref_albedo facing the camera at ref_m
    ref_m: float = 2.0
    ref_albedo: float = 0.5
    flying_prob: float = 0.7         # probability that a pixel on a depth edge is a mixed pixel
    edge_jump_m: float = 0.05
    multipath_gain: float = 1.0      # scales the one-bounce multipath bias (0 = off)
    multipath_radius_px: int = 24    # how far (pixels) the neighbouring surfaces that add light are sampled
    quantum_m: float = 0.001
    register_rgb: bool = True        # the colour image is black where depth is invalid

    def __post_init__(self) -> None:
        if not (0 <= self.min_m < self.max_m and 0 <= self.min_amplitude < self.max_amplitude and self.sigma_ref_m >= 0
                and self.ref_m > 0 and 0 < self.ref_albedo <= 1 and 0 <= self.flying_prob <= 1
                and self.edge_jump_m > 0 and self.multipath_gain >= 0 and self.multipath_radius_px >= 2
                and self.quantum_m >= 0):
            raise ValueError(f"invalid ToF depth model parameters: {self}")

    def sigma_m(self, z_m: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
        """Depth noise sigma (metres) of pixels with the given amplitude: sigma ~ 1 / sqrt(amplitude)."""
        ref = self.ref_albedo / self.ref_m ** 2
        return self.sigma_ref_m * np.sqrt(ref / np.maximum(np.asarray(amplitude, np.float32), 1e-6))


def _points_cam(depth_m: np.ndarray, f_px: float) -> np.ndarray:
    """(H, W, 3) back-projected points with the principal point at the image centre (only differences matter)."""
    h, w = depth_m.shape
    u = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / np.float32(f_px)
    v = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / np.float32(f_px)
    return np.stack([u[None, :] * depth_m, v[:, None] * depth_m, depth_m], axis=-1)


def tof_amplitude(depth_m: np.ndarray, f_px: float, info: PixelInfo) -> np.ndarray:
    """(H, W) float32 returned amplitude albedo * cos(incidence) / z^2 (0 where nothing was hit)."""
    z = np.asarray(depth_m, np.float32)
    p = _points_cam(z, f_px)
    view = -p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-6)
    cos = np.clip((info.normal_cam * view).sum(-1), 0, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        amp = np.where(z > 0, info.albedo * cos / np.maximum(z, 1e-3) ** 2, 0.0)
    return amp.astype(np.float32)


def multipath_bias_m(depth_m: np.ndarray, f_px: float, info: PixelInfo, radius_px: int = 24,
                     step: int = 4) -> np.ndarray:
    """(H, W) float32 depth overestimation from one-bounce multipath (metres, >= 0).

    For each pixel p (on a grid `step` pixels apart) neighbouring patches q on rings up to `radius_px` add
    light that went camera -> q -> p -> camera. Relative to the direct return, a patch adds
    rho_q = albedo_q * (cos_q,cam / d_q^2) * F_pq / (cos_p,cam / d_p^2), F_pq = cos_p cos_q area_q / (pi r^2),
    and the measured depth is the amplitude-weighted mean: bias = sum rho_q (L_q - 2 d_p) / (2 (1 + sum rho_q)),
    L_q = d_q + r + d_p the indirect path. Surfaces facing away from each other (convex) add nothing.
    """
    z_full = np.asarray(depth_m, np.float32)
    h, w = z_full.shape
    z = np.ascontiguousarray(z_full[::step, ::step])
    hs, ws = z.shape
    P = _points_cam(z_full, f_px)[::step, ::step]
    N = info.normal_cam[::step, ::step]
    px, py, pz = (np.ascontiguousarray(P[..., k]) for k in range(3))
    nx, ny, nz = (np.ascontiguousarray(N[..., k]) for k in range(3))
    alb = np.ascontiguousarray(info.albedo[::step, ::step])
    valid = z > 0
    d = np.sqrt(px * px + py * py + pz * pz)
    cos_cam = np.clip(-(nx * px + ny * py + nz * pz) / np.maximum(d, 1e-6), 0, 1)
    # What a patch q sends towards p, less the geometry at p: albedo_q * cos_q,cam / d_q^2 * area_q / pi.
    area_px = (z / np.float32(f_px)) ** 2 / np.maximum(cos_cam, 0.2)
    send = np.where(valid, alb * cos_cam / np.maximum(d, 1e-3) ** 2 * area_px / np.float32(np.pi), 0).astype(np.float32)
    rho = np.zeros((hs, ws), np.float32)
    extra = np.zeros((hs, ws), np.float32)
    rings = [r for r in (1, 2, 3, 4, 6, 8, 12, 16) if r * step <= radius_px] or [1]
    n_dir = 12
    for k, r in enumerate(rings):
        r_in = 0.5 * (r + (rings[k - 1] if k else 0))
        r_out = 0.5 * (r + rings[k + 1]) if k + 1 < len(rings) else r + 0.5 * (r - (rings[k - 1] if k else 0))
        ring_px = np.float32(np.pi * (r_out ** 2 - r_in ** 2) * step * step / n_dir)   # full-res pixels per sample
        for a in range(n_dir):
            ang = 2 * np.pi * (a + 0.5 * (k % 2)) / n_dir
            dy, dx = int(round(r * np.sin(ang))), int(round(r * np.cos(ang)))
            if abs(dy) >= hs or abs(dx) >= ws:
                continue
            ys, yd = (slice(dy, hs), slice(0, hs - dy)) if dy >= 0 else (slice(0, hs + dy), slice(-dy, hs))
            xs, xd = (slice(dx, ws), slice(0, ws - dx)) if dx >= 0 else (slice(0, ws + dx), slice(-dx, ws))
            ex, ey, ez = px[ys, xs] - px[yd, xd], py[ys, xs] - py[yd, xd], pz[ys, xs] - pz[yd, xd]
            r2 = np.maximum(ex * ex + ey * ey + ez * ez, np.float32(1e-6))
            rr = np.sqrt(r2)
            cos_p = np.clip((nx[yd, xd] * ex + ny[yd, xd] * ey + nz[yd, xd] * ez) / rr, 0, 1)
            cos_q = np.clip(-(nx[ys, xs] * ex + ny[ys, xs] * ey + nz[ys, xs] * ez) / rr, 0, 1)
            contrib = send[ys, xs] * ring_px * cos_p * cos_q / r2
            contrib *= valid[yd, xd]
            rho[yd, xd] += contrib
            extra[yd, xd] += contrib * (d[ys, xs] + rr - d[yd, xd])
    direct = np.maximum(cos_cam / np.maximum(d, 1e-3) ** 2, 1e-6)
    rho_rel, extra_rel = rho / direct, extra / direct
    bias = np.where(valid, extra_rel / (2 * (1 + rho_rel)), 0.0).astype(np.float32)
    return cv2.resize(bias, (w, h), interpolation=cv2.INTER_LINEAR)[:h, :w] * (z_full > 0)


def apply_tof(depth_m: np.ndarray, f_px: float, model: ToFDepthModel, info: PixelInfo,
              rng: np.random.Generator) -> np.ndarray:
    """ToF sensor depth from ideal depth.

    :param depth_m: (H, W) ideal depth, metres (0 = no surface). :param f_px: focal length, pixels.
    :param info: per-pixel normals and albedo of the scene.
    :return: (H, W) float32 metres, 0 = invalid.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    h, w = depth.shape
    valid = depth > 0
    amp = tof_amplitude(depth, f_px, info)
    out = depth.copy()
    if model.multipath_gain > 0:
        out = out + np.float32(model.multipath_gain) * multipath_bias_m(depth, f_px, info, model.multipath_radius_px)
    # Mixed pixels: a pixel on a depth edge reports a depth between the nearest and farthest of its neighbours
    # (both sides of the edge, unlike stereo's foreground fattening).
    kernel = np.ones((3, 3), np.uint8)
    far = np.where(valid, depth, np.float32(1e4))
    near_n, far_n = cv2.erode(far, kernel), cv2.dilate(np.where(valid, depth, 0).astype(np.float32), kernel)
    edge = valid & (far_n - near_n > model.edge_jump_m) & (far_n < 1e3)
    flying = edge & (rng.random((h, w)) < model.flying_prob)
    mix = rng.random((h, w)).astype(np.float32)
    out[flying] = (near_n + mix * (far_n - near_n))[flying]
    sigma = model.sigma_m(depth, amp).astype(np.float32)
    noise = np.float32(np.sqrt(0.8)) * rng.standard_normal((h, w)).astype(np.float32) \
        + np.float32(np.sqrt(0.2)) * correlated_noise((h, w), 4, rng)
    out = out + sigma * noise
    invalid = ~valid | (amp < model.min_amplitude) | (amp > model.max_amplitude) | (out < model.min_m) \
        | (out > model.max_m)
    out[invalid] = 0.0
    if model.quantum_m > 0:
        out = np.round(out / model.quantum_m) * np.float32(model.quantum_m)
    return out.astype(np.float32)


def register_rgb_to_depth(rgb: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Colour registered onto depth as ToF cameras deliver it: black where the depth is invalid.

    :param rgb: (H, W, 3) uint8, already in the depth camera's pixel grid. :param depth_m: (H, W), 0 = invalid.
    """
    if rgb.shape[:2] != depth_m.shape:
        raise ValueError(f"rgb {rgb.shape[:2]} and depth {depth_m.shape} must have the same size")
    out = rgb.copy()
    out[depth_m <= 0] = 0
    return out
