"""Label previews: each pallet's ground-truth 3D box and axes drawn on the RGB image, depth beside it."""
from __future__ import annotations

import cv2
import numpy as np

from pallet6d.runtime.geometry import project_points, transform_points
from pallet6d.sim.generate import SimFrame

__all__ = ["colorize_depth", "draw_preview"]

# Edges of a box whose corners are ordered as in pallets.box_corners (index = 4x + 2y + z).
_BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def colorize_depth(depth_m: np.ndarray, max_m: float | None = None) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) uint8 RGB (turbo colour map, black = no data)."""
    valid = depth_m > 0
    top = max_m or (float(np.percentile(depth_m[valid], 99)) if valid.any() else 1.0)
    img = cv2.applyColorMap(np.clip(depth_m / top * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)[:, :, ::-1]
    img[~valid] = 0
    return img


def draw_preview(frame: SimFrame, axis_m: float = 0.3) -> np.ndarray:
    """RGB image with every pallet's 3D box (green: target, yellow: others), x/y/z axes (red/green/blue),
    instance id and visible fraction, front-face centre and fork pockets; the colourised depth under it
    (beside it for tall images).

    :return: (H2, W2, 3) uint8 RGB.
    """
    img = np.ascontiguousarray(frame.rgb.copy())
    h, w = img.shape[:2]
    for p in frame.pallets:
        uv = project_points(p.box3d_cam, frame.K)
        if not np.all(np.isfinite(uv)):
            continue
        color = (0, 255, 0) if p.instance_id == frame.target_instance else (255, 220, 0)
        pts = np.round(uv).astype(np.int32)
        for a, b in _BOX_EDGES:
            cv2.line(img, tuple(pts[a]), tuple(pts[b]), color, 1, cv2.LINE_AA)
        axes = transform_points(p.T_cam_pallet, np.array([[0, 0, 0], [axis_m, 0, 0], [0, axis_m, 0], [0, 0, axis_m]]))
        a_uv = project_points(axes, frame.K)
        if np.all(np.isfinite(a_uv)):
            o = tuple(np.round(a_uv[0]).astype(int))
            for k, c in ((1, (255, 0, 0)), (2, (0, 255, 0)), (3, (0, 0, 255))):
                cv2.line(img, o, tuple(np.round(a_uv[k]).astype(int)), c, 2, cv2.LINE_AA)
        x, y = int(np.clip(pts[:, 0].min(), 0, w - 60)), int(np.clip(pts[:, 1].min() - 4, 10, h - 2))
        cv2.putText(img, f"{p.instance_id}:{p.visib_fract:.2f}", (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1,
                    cv2.LINE_AA)
    for f in frame.faces:
        _draw_face(img, f, frame.pallet(f.instance_id).T_cam_pallet, frame.K)
    depth = colorize_depth(frame.depth_m)
    return np.vstack([img, depth]) if w >= h else np.hstack([img, depth])


def _draw_face(img: np.ndarray, f, T_cam_pallet: np.ndarray, K: np.ndarray) -> None:
    """A pallet's front-face centre (white dot) and its pocket openings (cyan; red where blocked; L/R)."""
    for k, corners in enumerate(f.pocket_corners_cam(T_cam_pallet)):
        uv = project_points(corners, K)
        if not np.all(np.isfinite(uv)):
            continue
        color = (255, 40, 40) if f.pocket_blocked[k] else (0, 230, 255)
        cv2.polylines(img, [np.round(uv).astype(np.int32)], True, color, 1, cv2.LINE_AA)
        o = np.round(uv.mean(0)).astype(int)
        cv2.putText(img, "LR"[k], (int(o[0]) - 3, int(o[1]) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.3, color, 1, cv2.LINE_AA)
    uv = project_points(f.face_centre_cam[None], K)
    if np.all(np.isfinite(uv)):
        cv2.circle(img, tuple(np.round(uv[0]).astype(int)), 3, (255, 255, 255), -1, cv2.LINE_AA)
