"""Vectorised ray caster over oriented boxes (numpy).

Rays go through pixel centres (pixel (u, v) is the ray (u - cx) / fx, (v - cy) / fy, 1 in the camera
frame), so the ray parameter of a hit is its depth z along the optical axis. Each box is tested only
against the pixels of its screen rectangle: the projection of the box clipped to the near plane,
which culls boxes behind the camera or outside the frustum at no cost.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RayCast", "box_screen_rects", "raycast_boxes", "pixel_rays"]

_CORNER_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
# The 12 edges of a box as pairs of corner indices (corners differing in one sign).
_EDGES = np.array([(i, i | bit) for bit in (4, 2, 1) for i in range(8) if not i & bit], dtype=np.int64)


@dataclass
class RayCast:
    """Result of casting every pixel's ray.

    depth_m: (H, W) float32 z of the nearest hit, 0 where nothing was hit.
    box_index: (H, W) int32 index of the box hit, -1 where nothing was hit.
    full_masks: {group id: (H, W) bool} silhouette of each requested group of boxes, ignoring occlusion.
    """

    depth_m: np.ndarray
    box_index: np.ndarray
    full_masks: dict[int, np.ndarray]


def pixel_rays(K: np.ndarray, image_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """x/z and y/z of each pixel's ray: two (H, W) float32 arrays."""
    h, w = image_hw
    rx = ((np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]).astype(np.float32)
    ry = ((np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]).astype(np.float32)
    return np.broadcast_to(rx[None, :], (h, w)), np.broadcast_to(ry[:, None], (h, w))


def box_screen_rects(R_cam_box: np.ndarray, t_cam_box: np.ndarray, half_m: np.ndarray, K: np.ndarray,
                     image_hw: tuple[int, int], near_m: float) -> np.ndarray:
    """Integer screen rectangles of boxes clipped to the near plane.

    :param R_cam_box: (N, 3, 3), :param t_cam_box: (N, 3) box poses in the camera frame.
    :param half_m: (N, 3) half sizes.
    :return: (N, 4) int64 u0, v0, u1, v1 (exclusive); u1 <= u0 for boxes that cannot be seen.
    """
    h, w = image_hw
    corners = t_cam_box[:, None, :] + np.einsum("nij,knj->nki", R_cam_box, _CORNER_SIGNS[:, None, :] * half_m[None])
    a, b = corners[:, _EDGES[:, 0]], corners[:, _EDGES[:, 1]]               # (N, 12, 3)
    za, zb = a[..., 2], b[..., 2]
    crosses = (za - near_m) * (zb - near_m) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crosses, (near_m - za) / (zb - za), 0.0)
    clip_pts = a + s[..., None] * (b - a)                                     # on the near plane where crosses
    pts = np.concatenate([corners, clip_pts], axis=1)
    ok = np.concatenate([corners[..., 2] >= near_m, crosses], axis=1)
    z = np.where(ok, pts[..., 2], 1.0)
    u = K[0, 0] * pts[..., 0] / z + K[0, 2]
    v = K[1, 1] * pts[..., 1] / z + K[1, 2]
    big = 1e9
    u_lo = np.where(ok, u, big).min(1)
    u_hi = np.where(ok, u, -big).max(1)
    v_lo = np.where(ok, v, big).min(1)
    v_hi = np.where(ok, v, -big).max(1)
    # Pixel centres at integers: a pixel can be hit if its centre lies in [lo, hi].
    rect = np.stack([np.ceil(u_lo), np.ceil(v_lo), np.floor(u_hi) + 1, np.floor(v_hi) + 1], 1)
    rect = np.clip(rect, 0, [w, h, w, h]).astype(np.int64)
    rect[~ok.any(1)] = 0
    return rect


def raycast_boxes(R_cam_box: np.ndarray, t_cam_box: np.ndarray, half_m: np.ndarray, K: np.ndarray,
                  image_hw: tuple[int, int], group: np.ndarray | None = None, near_m: float = 0.05) -> RayCast:
    """Cast one ray per pixel against oriented boxes and keep the nearest hit.

    :param R_cam_box: (N, 3, 3) rotations box -> camera.
    :param t_cam_box: (N, 3) box centres in the camera frame, metres.
    :param half_m: (N, 3) half sizes, metres.
    :param K: (3, 3) intrinsics.
    :param image_hw: (H, W).
    :param group: optional (N,) int group id per box; groups > 0 get a full (occlusion-free) silhouette.
    :param near_m: hits closer than this are ignored (the camera must not be inside a box).
    """
    h, w = image_hw
    n = len(half_m)
    R = np.asarray(R_cam_box, dtype=np.float32)
    t = np.asarray(t_cam_box, dtype=np.float32)
    half = np.asarray(half_m, dtype=np.float32)
    group = np.zeros(n, dtype=np.int64) if group is None else np.asarray(group)
    rx, ry = pixel_rays(K, image_hw)
    depth = np.full((h, w), np.inf, dtype=np.float32)
    index = np.full((h, w), -1, dtype=np.int32)
    full: dict[int, np.ndarray] = {}
    rects = box_screen_rects(R.astype(np.float64), t.astype(np.float64), half.astype(np.float64), K, image_hw, near_m)
    origin_local = -np.einsum("nji,nj->ni", R, t)                            # camera centre in each box frame
    for i in np.nonzero((rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1]))[0]:
        u0, v0, u1, v1 = rects[i]
        x, y = rx[v0:v1, u0:u1], ry[v0:v1, u0:u1]
        t_near = np.full(x.shape, -np.inf, dtype=np.float32)
        t_far = np.full(x.shape, np.inf, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in range(3):
                d = x * R[i, 0, a] + y * R[i, 1, a] + R[i, 2, a]           # ray direction in the box frame
                inv = np.float32(1.0) / d
                t1 = (-half[i, a] - origin_local[i, a]) * inv
                t2 = (half[i, a] - origin_local[i, a]) * inv
                np.maximum(t_near, np.minimum(t1, t2), out=t_near)
                np.minimum(t_far, np.maximum(t1, t2), out=t_far)
        hit = (t_near <= t_far) & (t_near > near_m)                          # NaN (ray in a face plane) -> miss
        if group[i] > 0:
            g = int(group[i])
            if g not in full:
                full[g] = np.zeros((h, w), dtype=bool)
            full[g][v0:v1, u0:u1] |= hit
        zb = depth[v0:v1, u0:u1]
        closer = hit & (t_near < zb)
        zb[closer] = t_near[closer]
        index[v0:v1, u0:u1][closer] = i
    depth[~np.isfinite(depth)] = 0.0
    return RayCast(depth_m=depth, box_index=index, full_masks=full)
