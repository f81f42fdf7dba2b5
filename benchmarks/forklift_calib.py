"""Calibration accuracy on simulated views: the floor fit (pitch, roll, height; exact and D435-like depth of a
floor with boxes on it, one frame and `--floor-frames` frames of a still camera) and board extrinsics (a ChArUco
board rendered into a grey view, 1.2-2.2 m ahead).

    python benchmarks/forklift_calib.py --floors 60 --boards 60 --frames data/forklift-frames \
        --out benchmarks/results/forklift/calib.json

With `--frames` (cached forklift-approach frames, `benchmarks/forklift_frames.py`) it also counts how often the
running floor check agrees, disagrees or sees no floor, with the exact calibration and with a knocked camera.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pallet6d.calib.board import BoardSpec, T_vehicle_cam_from_board, board_pose, render_board
from pallet6d.calib.cli import upright_board_R
from pallet6d.calib.floor import T_vehicle_cam_from_floor, fit_floor_for_calibration, pitch_roll_deg
from pallet6d.runtime.geometry import invert_T, make_T

BOARD = BoardSpec("charuco", 9, 6, 0.10, 0.075)   # 0.9 x 0.6 m, printed on a panel
W, H, HFOV = 848, 480, 69.4


def _stats(a) -> dict:
    a = np.abs(np.asarray(a, dtype=np.float64))
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def _K() -> np.ndarray:
    f = W / 2 / np.tan(np.radians(HFOV) / 2)
    return np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])


def _camera(rng: np.random.Generator) -> np.ndarray:
    """A forklift camera's T_vehicle_cam: 0.3-2 m high, pitched 3-20 degrees down, small roll and yaw."""
    pitch, roll = np.radians(rng.uniform(3, 20)), np.radians(rng.uniform(-1.5, 1.5))
    yaw = np.radians(rng.uniform(-2, 2))
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)        # optical axis along x, image down = -z
    Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    return make_T(Rz @ Ry @ Rx @ R0, [rng.uniform(-0.05, 0.10), rng.uniform(-0.12, 0.12), rng.uniform(0.3, 2.0)])


def render_floor_view(rng: np.random.Generator, sensor: str,
                      frames: int = 1) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Depth of a calibration view: 3.5 m of free floor ahead of a forklift, then 1-4 boxes (a carton stack, a wall
    piece) on it, exact or through the simulator's D435 model, `frames` times from the still camera (each with its
    own sensor noise). :return: depth_m (H, W) per frame, K, T_vehicle_cam."""
    from pallet6d.runtime.structure import cast_rays_boxes
    from pallet6d.sim.depth_sensors import depth_model_for
    from pallet6d.sim.sensors import apply_depth_model

    K, T_vc = _K(), _camera(rng)
    v, u = np.mgrid[0:H, 0:W]
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(-1, 3)
    rays_v = rays_c @ T_vc[:3, :3].T
    o = T_vc[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(rays_v[:, 2] < -1e-9, -o[2] / rays_v[:, 2], np.inf)
    boxes = []
    for _ in range(rng.integers(1, 5)):
        half = rng.uniform(0.2, 0.8, 2)
        c = np.array([3.5 + half[0] + rng.uniform(0, 2.5), rng.uniform(-2.5, 2.5)])   # 3.5 m of free floor ahead
        boxes.append([[*(c - half), 0.0], [*(c + half), rng.uniform(0.3, 2.0)]])
    t_box, _ = cast_rays_boxes(o[None], rays_v[None], np.asarray(boxes))
    t = np.minimum(t_floor, t_box[0])
    depth = np.where(np.isfinite(t) & (t < 10.0), t, 0.0).reshape(H, W).astype(np.float32)
    return [apply_depth_model(depth, K[0, 0], depth_model_for(sensor), rng) for _ in range(frames)], K, T_vc


def floor_errors(n: int, seed: int, sensor: str, frames: int = 1) -> dict:
    """Pitch, roll and height of the camera from the floor fit (`calib floor` on `frames` frames of each view) vs
    the truth."""
    rng = np.random.default_rng(seed)
    dp, dr, dh, failed = [], [], [], 0
    for _ in range(n):
        depths, K, T_true = render_floor_view(rng, sensor, frames)
        try:
            plane = fit_floor_for_calibration(depths, K)
        except ValueError:
            failed += 1
            continue
        T = T_vehicle_cam_from_floor(plane)
        (p, r), (pt, rt) = pitch_roll_deg(T[:3, :3]), pitch_roll_deg(T_true[:3, :3])
        dp.append(p - pt)
        dr.append(r - rt)
        dh.append(T[2, 3] - T_true[2, 3])
    ok = [abs(a) <= 0.3 and abs(b) <= 0.3 and abs(c) <= 0.01 for a, b, c in zip(dp, dr, dh)] + [False] * failed
    return {"views": len(dp) + failed, "frames_per_view": frames, "failed": failed, "pitch_err_deg": _stats(dp),
            "roll_err_deg": _stats(dr), "height_err_m": _stats(dh), "within_target": float(np.mean(ok)) if ok else 0.0}


def render_board_view(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A grey 848x480 view of a ChArUco board standing 1.2-2.2 m ahead of a forklift camera.

    :return: image (H, W) uint8, K, T_vehicle_cam (truth), T_vehicle_board (the "measured" board place).
    """
    K, T_vc = _K(), _camera(rng)
    # the board's centre on the optical axis' line of sight, 1.2-2.2 m ahead, turned up to 10 degrees
    dist = rng.uniform(1.2, 2.2)
    centre = T_vc[:3, 3] + dist * T_vc[:3, 2] + rng.normal(0, 0.05, 3)
    R_vb = upright_board_R(rng.uniform(-10, 10))
    half = np.array([BOARD.cols * BOARD.square_m, BOARD.rows * BOARD.square_m, 0]) / 2
    T_vb = make_T(R_vb, centre - R_vb @ half)
    T_cb = invert_T(T_vc) @ T_vb
    view = render_board(BOARD, K, T_cb, (H, W), background=int(rng.integers(60, 200))).astype(np.float64)
    view = view * rng.uniform(0.6, 1.0) + rng.normal(0, 2.0, view.shape)
    return np.clip(view, 0, 255).astype(np.uint8), K, T_vc, T_vb


def board_errors(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    dr, dt, failed = [], [], 0
    for _ in range(n):
        img, K, T_vc, T_vb = render_board_view(rng)
        try:
            T_cb, _, _ = board_pose(img, BOARD, K)
        except ValueError:
            failed += 1
            continue
        T = T_vehicle_cam_from_board(T_vb, T_cb)
        dR = T[:3, :3] @ T_vc[:3, :3].T
        dr.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        dt.append(np.linalg.norm(T[:3, 3] - T_vc[:3, 3]))
    ok = [a <= 0.3 and b <= 0.01 for a, b in zip(dr, dt)] + [False] * failed
    return {"views": n, "not_found": failed, "rotation_err_deg": _stats(dr), "translation_err_m": _stats(dt),
            "within_target": float(np.mean(ok)) if ok else 0.0}


def floor_check_rates(frames_dir: Path, depth_key: str) -> dict:
    """The running floor check on forklift-approach frames: with the exact calibration (false alarms) and with the
    camera knocked after calibration (2 or 20 degrees of pitch, 1.5 of roll, or 5 cm of height) or a calibration
    far off in height (0.5 or 1 m too high, 0.5 m too low)."""
    from pallet6d.runtime.floor import FloorPlane, check_floor

    knocks = {"exact": (0.0, 0.0, 0.0), "pitch_2deg": (2.0, 0.0, 0.0), "roll_1.5deg": (0.0, 1.5, 0.0),
              "height_5cm": (0.0, 0.0, 0.05), "pitch_20deg": (20.0, 0.0, 0.0), "height_+50cm": (0.0, 0.0, 0.5),
              "height_+1m": (0.0, 0.0, 1.0), "height_-50cm": (0.0, 0.0, -0.5)}
    counts = {k: {"agrees": 0, "disagrees": 0, "unseen": 0, "camera_too_low": 0} for k in knocks}
    errors: dict[str, list[tuple[float, float]]] = {k: [] for k in knocks}
    for path in sorted(frames_dir.glob("*.npz")):
        z = np.load(path)
        T = z["T_vehicle_cam"]
        for name, (dp, dr, dh) in knocks.items():
            p, r = np.radians(dp), np.radians(dr)
            Rp = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])   # about camera x
            Rr = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])   # about camera z
            R = T[:3, :3] @ Rp @ Rr                       # the calibration the camera had before the knock
            if T[2, 3] + dh <= 0.05:                      # no calibration puts the camera under the floor
                counts[name]["camera_too_low"] += 1
                continue
            c = check_floor(FloorPlane(R[2].copy(), float(T[2, 3] + dh)), z[depth_key], z["K"])
            counts[name]["unseen" if c.agrees is None else "agrees" if c.agrees else "disagrees"] += 1
            if c.agrees is not None and np.isfinite(c.height_diff_m):    # measured against the knock
                errors[name].append((abs(c.height_diff_m + dh), abs(c.tilt_deg - np.hypot(dp, dr))))
    for name, e in errors.items():
        if e:
            counts[name]["height_err_m_median_max"] = [float(np.median([a for a, _ in e])), max(a for a, _ in e)]
            counts[name]["tilt_err_deg_median_max"] = [float(np.median([b for _, b in e])), max(b for _, b in e)]
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--floors", type=int, default=60)
    ap.add_argument("--frames", type=Path, help="cached forklift-approach frames for the floor check")
    ap.add_argument("--floor-frames", type=int, default=10,
                    help="frames of each view the D435-like floor fit also runs on (`calib floor`'s default 10)")
    ap.add_argument("--boards", type=int, default=60)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    out = {"floor_clean": floor_errors(args.floors, args.seed, "ideal"),
           "floor_d435": floor_errors(args.floors, args.seed, "d435"),
           "floor_d435_frames": floor_errors(args.floors, args.seed, "d435", args.floor_frames),
           "board": board_errors(args.boards, args.seed)}
    if args.frames:
        out["floor_check_clean"] = floor_check_rates(args.frames, "depth_ideal_m")
        out["floor_check_d435"] = floor_check_rates(args.frames, "depth_m")
    print(json.dumps(out, indent=1))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
