"""Inputs that do not belong together: a frame's image with a depth or intrinsics from elsewhere, as a wrongly wired
or wrongly configured camera delivers them. A pose estimator must refuse them (no pose is right there); training and
benchmarks build them from simulated frames."""
from __future__ import annotations

import numpy as np

__all__ = ["MISMATCHES", "mismatched"]

MISMATCHES = ("other_frame", "depth_x0.1", "focal_x2", "flat_wall")


def mismatched(kind: str, depth_m: np.ndarray, K: np.ndarray,
               other_depth_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m, K) that do not belong to the image they come with.

    :param kind: "other_frame" (`other_depth_m` instead), "depth_x0.1" (depth 10x too near: a wrong depth scale),
        "focal_x2" (focal lengths 2x too long), "flat_wall" (a wall at the frame's median depth, 3 m without any).
    :param depth_m: (H, W) float metres. :param K: (3, 3); a new array is returned, the caller's is not changed.
    :raises ValueError: unknown kind, or "other_frame" without another depth.
    """
    K = np.array(K, np.float64)
    if kind == "other_frame":
        if other_depth_m is None:
            raise ValueError("other_frame needs another frame's depth")
        return other_depth_m, K
    if kind == "depth_x0.1":
        return depth_m * np.float32(0.1), K
    if kind == "focal_x2":
        K[0, 0] *= 2.0
        K[1, 1] *= 2.0
        return depth_m, K
    if kind == "flat_wall":
        valid = depth_m[depth_m > 0]
        return np.full_like(depth_m, float(np.median(valid)) if len(valid) else 3.0), K
    raise ValueError(f"unknown mismatch {kind!r}; known: {', '.join(MISMATCHES)}")
