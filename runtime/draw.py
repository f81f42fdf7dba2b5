"""Overlays: each pallet's 3D bounding box and axes drawn on the RGB image (OpenCV)."""
from __future__ import annotations

import cv2
import numpy as np

from .geometry import project_points, transform_points
from .results import FrameResult, PalletPose

__all__ = ["box_corners_m", "draw_pose", "draw_result"]

# corner pairs of a box whose corners are ordered by (x, y, z) in {min, max}, z fastest
_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def box_corners_m(size_m: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a box of size (3,) centred at the origin, ordered by (x, y, z) in {-, +}, z fastest."""
    h = np.asarray(size_m, dtype=np.float64).reshape(3) / 2
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    return signs * h


def _pt(uv: np.ndarray) -> tuple[int, int]:
    return int(round(uv[0])), int(round(uv[1]))


def draw_pose(image_rgb: np.ndarray, T_cam_pallet: np.ndarray, K: np.ndarray, size_m: np.ndarray,
              color=(0, 255, 0), label: str | None = None, thickness: int = 2) -> np.ndarray:
    """Draw one posed 3D box (edges) and its axes (x red, y green, z blue) in place.

    :param image_rgb: (H, W, 3) uint8 RGB, modified in place and returned.
    :param T_cam_pallet: (4, 4); :param K: (3, 3); :param size_m: (3,) box size (length, width, height).
    """
    corners = transform_points(T_cam_pallet, box_corners_m(size_m))
    if np.any(corners[:, 2] <= 0.05):
        return image_rgb  # behind or at the camera: nothing sensible to draw
    uv = project_points(corners, K)
    for a, b in _EDGES:
        cv2.line(image_rgb, _pt(uv[a]), _pt(uv[b]), color, thickness, cv2.LINE_AA)
    axis_len = 0.5 * float(np.min(size_m[:2]))
    axes = transform_points(T_cam_pallet, np.array([[0, 0, 0], [axis_len, 0, 0], [0, axis_len, 0], [0, 0, axis_len]]))
    auv = project_points(axes, K)
    for i, c in enumerate([(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
        cv2.line(image_rgb, _pt(auv[0]), _pt(auv[i + 1]), c, thickness, cv2.LINE_AA)
    if label:
        top = uv[np.argmin(uv[:, 1])]
        cv2.putText(image_rgb, label, (_pt(top)[0], max(12, _pt(top)[1] - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    color, 1, cv2.LINE_AA)
    return image_rgb


def draw_result(image_rgb: np.ndarray, result: FrameResult, K: np.ndarray, size_m: np.ndarray,
                gt_T_cam_pallet: list[np.ndarray] | None = None) -> np.ndarray:
    """Copy of the image with accepted poses (green), rejected detections (red box + reason) and
    optional ground-truth poses (white) drawn.

    :return: (H, W, 3) uint8 RGB.
    """
    out = np.ascontiguousarray(image_rgb).copy()
    for T in gt_T_cam_pallet or []:
        draw_pose(out, T, K, size_m, color=(255, 255, 255), thickness=1)
    for r in result.rejected:
        x1, y1, x2, y2 = (int(round(v)) for v in r.box_xyxy)
        cv2.rectangle(out, (x1, y1), (x2, y2), (255, 0, 0), 1)
        cv2.putText(out, r.reason, (x1, max(12, y1 - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 0, 0), 1, cv2.LINE_AA)
    for p in result.poses:
        draw_pose(out, p.T_cam_pallet, K, size_m, label=f"{p.detector_score:.2f} fit {p.fit.score:.2f}")
    return out
