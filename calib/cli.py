"""`pallet6d calib`: calibrate a forklift camera and write its calibration file (TOML, docs/forklift.md).

    pallet6d calib intrinsics --images DIR --board charuco:7x5:0.08:0.06 --out intr.json
    pallet6d calib extrinsics --image board.png --board charuco:7x5:0.08:0.06 --intrinsics intr.json \
        --board-pose 1.50,0.28,1.10,0 --out board.json
    pallet6d calib floor --source realsense --extrinsics board.json --out cam.toml
    pallet6d calib show cam.toml
    pallet6d calib check --source realsense --calibration cam.toml

`floor` fits the floor plane over a few frames (RANSAC, then least squares in inverse depth on the inliers, up to 8
m ahead) and takes the camera's pitch, roll and height from it; the yaw and the position over the floor come from
the board (`--extrinsics`) or from the mount drawing (`--yaw-deg --x-m --y-m`). Intrinsics come from `--intrinsics`
(a file from `calib intrinsics`) or else from the source itself (the camera's SDK, a recording's camera.json).
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path

import numpy as np

HELP = "calibrate a forklift camera: intrinsics, extrinsics from a board, floor; show or check a calibration"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="calib_command", metavar="STEP", required=True)
    p = sub.add_parser("intrinsics", help="intrinsics from images of a chessboard or ChArUco board")
    p.add_argument("--images", type=Path, required=True, help="folder of PNG/JPG images of the board")
    p.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE_M or charuco:COLSxROWS:SQUARE_M:MARKER_M")
    p.add_argument("--out", type=Path, required=True, help="intrinsics JSON to write")
    p = sub.add_parser("extrinsics", help="camera-to-vehicle transform from a ChArUco board at a measured place")
    p.add_argument("--image", type=Path, required=True, help="an image of the board from the mounted camera")
    p.add_argument("--board", required=True, help="charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]")
    p.add_argument("--intrinsics", type=Path, required=True, help="intrinsics JSON (calib intrinsics) or calibration")
    p.add_argument("--board-pose", required=True,
                   help="X,Y,Z,YAW_DEG: the board's top-left corner in the vehicle frame (metres) and its yaw; the "
                        "board stands upright facing the forks (yaw 0: its face looks back along -x)")
    p.add_argument("--out", type=Path, required=True, help="JSON with T_vehicle_cam to write")
    p = sub.add_parser("floor", help="fit the floor; write the calibration file")
    p.add_argument("--source", required=True, help="replay:DIR, bag:FILE, realsense[:SERIAL] or oakd[:MXID]")
    p.add_argument("--intrinsics", type=Path, help="intrinsics JSON (default: the source's own)")
    p.add_argument("--extrinsics", type=Path, help="JSON from calib extrinsics: yaw and position over the floor")
    p.add_argument("--yaw-deg", type=float, default=0.0,
                   help="camera yaw from the mount drawing (without --extrinsics)")
    p.add_argument("--x-m", type=float, default=0.0, help="camera x from the fork roots (without --extrinsics)")
    p.add_argument("--y-m", type=float, default=0.0, help="camera y, left positive (without --extrinsics)")
    p.add_argument("--frames", type=int, default=10, help="frames to fit the floor on (default 10)")
    p.add_argument("--serial", default=None, help="the camera's serial (default: from the source spec)")
    p.add_argument("--out", type=Path, required=True, help="calibration TOML to write")
    p = sub.add_parser("show", help="validate a calibration file and print it")
    p.add_argument("calibration", type=Path)
    p = sub.add_parser("check", help="does the floor still agree with the calibration?")
    p.add_argument("--source", required=True)
    p.add_argument("--calibration", type=Path, required=True)
    p.add_argument("--frames", type=int, default=5)


def _intrinsics(path: Path):
    from pallet6d.runtime.calibration import load_calibration

    from .intrinsics import CameraIntrinsics
    if path.suffix == ".toml":
        c = load_calibration(path)
        return CameraIntrinsics(c.width, c.height, c.K, c.dist)
    return CameraIntrinsics.load(path)


def _frames(spec: str, n: int):
    from pallet6d.runtime.cameras import open_source

    with open_source(spec) as source:
        for i, frame in enumerate(source):
            if i >= n:
                break
            yield frame


def _cmd_intrinsics(args) -> int:
    import cv2

    from .board import calibrate_intrinsics, parse_board
    files = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    intr, rms, used = calibrate_intrinsics([g for g in images if g is not None], parse_board(args.board))
    intr.save(args.out)
    print(f"intrinsics from {used} of {len(files)} images, RMS reprojection {rms:.3f} px -> {args.out}")
    return 0


def _cmd_extrinsics(args) -> int:
    import cv2

    from pallet6d.runtime.geometry import make_T

    from .board import T_vehicle_cam_from_board, board_pose, parse_board
    try:
        x, y, z, yaw = (float(v) for v in args.board_pose.split(","))
    except ValueError:
        raise ValueError(f"--board-pose must be X,Y,Z,YAW_DEG, got {args.board_pose!r}") from None
    gray = cv2.imread(str(args.image), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise ValueError(f"{args.image}: cannot read the image")
    intr = _intrinsics(args.intrinsics)
    T_cam_board, rms, n = board_pose(gray, parse_board(args.board), intr.K, intr.dist)
    T_vehicle_board = make_T(upright_board_R(yaw), [x, y, z])
    T = T_vehicle_cam_from_board(T_vehicle_board, T_cam_board)
    args.out.write_text(json.dumps({"T_vehicle_cam": T.tolist(), "rms_px": rms, "corners": n,
                                    "source": f"board {args.board} in {args.image.name}"}, indent=1))
    print(f"board found ({n} corners, RMS {rms:.2f} px); camera at {np.round(T[:3, 3], 3).tolist()} m -> {args.out}")
    return 0


def upright_board_R(yaw_deg: float) -> np.ndarray:
    """(3, 3) R_vehicle_board of an upright board facing the forks, turned by `yaw_deg` about z: board x (its
    columns) points right as seen from the forklift (-y), board y (its rows) down (-z), board z into it (+x)."""
    a = np.radians(yaw_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return Rz @ np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])


def heading_and_position(T_vehicle_cam: np.ndarray) -> tuple[float, float, float]:
    """The optical axis' heading (degrees, anticlockwise from x, seen from above) and the camera's x, y."""
    axis = np.asarray(T_vehicle_cam)[:3, 2]
    return float(np.degrees(np.arctan2(axis[1], axis[0]))), float(T_vehicle_cam[0, 3]), float(T_vehicle_cam[1, 3])


def _cmd_floor(args) -> int:
    from pallet6d.runtime.calibration import Calibration, save_calibration
    from .floor import T_vehicle_cam_from_floor, fit_floor_for_calibration, pitch_roll_deg
    frames = list(_frames(args.source, args.frames))
    if not frames:
        raise ValueError(f"{args.source}: no frames")
    intr = _intrinsics(args.intrinsics) if args.intrinsics else None
    K = intr.K if intr is not None else frames[0].K
    plane = fit_floor_for_calibration([f.depth_m for f in frames], K)
    yaw, x, y = args.yaw_deg, args.x_m, args.y_m
    ext_source = "floor+mount drawing"
    if args.extrinsics:
        yaw, x, y = heading_and_position(np.asarray(json.loads(args.extrinsics.read_text())["T_vehicle_cam"]))
        ext_source = f"floor+{args.extrinsics.name}"
    T = T_vehicle_cam_from_floor(plane, yaw, x, y)
    serial = args.serial if args.serial is not None else (args.source.split(":", 1)[1] if ":" in args.source else "")
    cal = Calibration(serial=serial, date=dt.date.today().isoformat(), width=frames[0].width,
                      height=frames[0].height, K=K, dist=intr.dist if intr is not None else np.zeros(5),
                      T_vehicle_cam=T, floor=plane, camera=args.source.split(":", 1)[0],
                      intrinsics_source=str(args.intrinsics) if args.intrinsics else "sdk",
                      extrinsics_source=ext_source)
    save_calibration(cal, args.out)
    pitch, roll = pitch_roll_deg(T[:3, :3])
    print(f"floor: {plane.inlier_ratio:.0%} inliers, RMS {1000 * plane.rms_m:.1f} mm; camera height "
          f"{plane.d:.3f} m, pitch {pitch:.2f} deg, roll {roll:.2f} deg, yaw {yaw:.2f} deg -> {args.out}")
    return 0


def _cmd_show(args) -> int:
    from pallet6d.runtime.calibration import load_calibration, to_toml

    from .floor import pitch_roll_deg
    cal = load_calibration(args.calibration)
    pitch, roll = pitch_roll_deg(cal.T_vehicle_cam[:3, :3])
    print(to_toml(cal.to_dict()), end="")
    print(f"# camera height {cal.T_vehicle_cam[2, 3]:.3f} m, pitch {pitch:.2f} deg, roll {roll:.2f} deg")
    return 0


def _cmd_check(args) -> int:
    from pallet6d.runtime.calibration import load_calibration
    from pallet6d.runtime.floor import check_floor

    cal = load_calibration(args.calibration)
    bad = 0
    for f in _frames(args.source, args.frames):
        cal.check_camera(f.K, (f.height, f.width))
        c = check_floor(cal.floor, f.depth_m, f.K)
        bad += c.agrees is False
        print(f"frame {f.frame_number}: {'agrees' if c.agrees else 'DISAGREES' if c.agrees is False else 'unseen'}: "
              f"{c.detail}")
    return 1 if bad else 0


def main(args: argparse.Namespace) -> int:
    run = {"intrinsics": _cmd_intrinsics, "extrinsics": _cmd_extrinsics, "floor": _cmd_floor, "show": _cmd_show,
           "check": _cmd_check}[args.calib_command]
    from pallet6d.runtime.cameras.errors import CameraError

    try:
        return run(args)
    except (ValueError, OSError, CameraError) as exc:   # a camera that is not there or a recording that cannot be read
        print(f"pallet6d calib {args.calib_command}: {exc}", file=sys.stderr)
        return 1
