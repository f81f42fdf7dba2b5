"""Picking each pallet's pose from the pose network's per-point hypotheses (paper 3.1.5), batched.

The pose network predicts, for every sampled point i of pallet b, a quaternion q[b, i], a translation
offset dt[b, i] and a confidence c[b, i]. Points enter the network centred (the cloud's centre is
subtracted), so hypothesis i places the pallet at  points[b, i] + dt[b, i] + centre[b]  in the camera
frame, with rotation q[b, i]. The pose is the most confident hypothesis (DenseFusion's argmax).

A pose graph that picks that hypothesis itself (manifest `pose.hypotheses` "most_confident") gives each pallet's
quaternion, its chosen point plus offset (centred frame) and confidence: `chosen_poses` only adds the centre back.
"""
from __future__ import annotations

import numpy as np

from .geometry import quat_to_rot

__all__ = ["chosen_poses", "select_poses"]


def select_poses(quat: np.ndarray, offset_m: np.ndarray, conf: np.ndarray, points_m: np.ndarray,
                 centre_m: np.ndarray, quat_order: str = "wxyz") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Most confident hypothesis per pallet.

    :param quat: (B, N, 4) per-point quaternions (need not be normalised), order `quat_order`.
    :param offset_m: (B, N, 3) per-point translation offsets, metres.
    :param conf: (B, N) per-point confidences.
    :param points_m: (B, N, 3) the centred points the network saw, metres.
    :param centre_m: (B, 3) the centre subtracted from each pallet's points, camera frame, metres.
    :param quat_order: "wxyz" or "xyzw".
    :return: T_cam_pallet (B, 4, 4), confidence (B,), chosen point index (B,).
    """
    quat = np.asarray(quat, dtype=np.float64)
    offset_m = np.asarray(offset_m, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    points_m = np.asarray(points_m, dtype=np.float64)
    centre_m = np.asarray(centre_m, dtype=np.float64)
    if quat.ndim != 3 or quat.shape[2] != 4:
        raise ValueError(f"quat must be (B, N, 4), got {quat.shape}")
    B, N = quat.shape[:2]
    for name, arr, shape in (("offset_m", offset_m, (B, N, 3)), ("conf", conf, (B, N)),
                             ("points_m", points_m, (B, N, 3)), ("centre_m", centre_m, (B, 3))):
        if arr.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if quat_order not in ("wxyz", "xyzw"):
        raise ValueError(f"quat_order must be 'wxyz' or 'xyzw', got {quat_order!r}")
    if B == 0:
        return np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, dtype=np.int64)
    # NaN confidences never win
    idx = np.nan_to_num(conf, nan=-np.inf).argmax(axis=1)
    rows = np.arange(B)
    q = quat[rows, idx]
    if quat_order == "xyzw":
        q = q[:, [3, 0, 1, 2]]
    T = np.tile(np.eye(4), (B, 1, 1))
    T[:, :3, :3] = quat_to_rot(q)
    T[:, :3, 3] = points_m[rows, idx] + offset_m[rows, idx] + centre_m
    return T, conf[rows, idx], idx.astype(np.int64)


def chosen_poses(quat: np.ndarray, trans_centred_m: np.ndarray, conf: np.ndarray,
                 centre_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses from a graph that picked each pallet's most confident hypothesis itself.

    :param quat: (B, 4) wxyz quaternions (need not be normalised).
    :param trans_centred_m: (B, 3) the chosen point plus its offset, in the centred frame, metres.
    :param conf: (B,) the chosen hypotheses' confidences.
    :param centre_m: (B, 3) the centre subtracted from each pallet's points, camera frame, metres.
    :return: T_cam_pallet (B, 4, 4), confidence (B,).
    """
    quat = np.asarray(quat, dtype=np.float64)
    if quat.ndim != 2 or quat.shape[1] != 4:
        raise ValueError(f"quat must be (B, 4), got {quat.shape}")
    B = len(quat)
    trans_centred_m = np.asarray(trans_centred_m, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    centre_m = np.asarray(centre_m, dtype=np.float64)
    for name, arr, shape in (("trans_centred_m", trans_centred_m, (B, 3)), ("conf", conf, (B,)),
                             ("centre_m", centre_m, (B, 3))):
        if arr.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    T = np.tile(np.eye(4), (B, 1, 1))
    if B:
        T[:, :3, :3] = quat_to_rot(quat)
        T[:, :3, 3] = trans_centred_m + centre_m
    return T, conf
