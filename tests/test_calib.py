import numpy as np
import pytest

from pallet6d.calib.floor import T_vehicle_cam_from_floor, fit_floor_plane
from pallet6d.calib.intrinsics import CameraIntrinsics
from pallet6d.runtime.geometry import backproject_pixels, invert_T, make_T, transform_points

K = np.array([[610.0, 0, 423.5], [0, 610.0, 239.5], [0, 0, 1]])


def test_intrinsics_round_trip_and_scaling(tmp_path):
    intr = CameraIntrinsics(848, 480, K)
    intr.save(tmp_path / "cam.json")
    back = CameraIntrinsics.load(tmp_path / "cam.json")
    np.testing.assert_allclose(back.K, K)
    half = intr.scaled(424, 240)
    assert half.K[0, 0] == pytest.approx(305.0)
    assert half.K[0, 2] == pytest.approx(211.5)   # centre of a 424-wide image


@pytest.mark.parametrize("kwargs,match", [
    (dict(width=0, height=480, K=K), "image size"),
    (dict(width=848, height=480, K=np.eye(2)), "3x3"),
    (dict(width=848, height=480, K=K, dist=np.zeros(3)), "dist"),
])
def test_intrinsics_rejects(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CameraIntrinsics(**kwargs)


def test_intrinsics_load_names_file_and_field(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{"width": 10, "K": [[1,0,0],[0,1,0],[0,0,1]]}')
    with pytest.raises(ValueError, match="bad.json.*height"):
        CameraIntrinsics.load(p)


def _floor_view(height_m, pitch_deg, roll_deg, rng):
    """Points of a floor seen by a camera at a height, pitched down and rolled; plus some clutter."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    # camera axes in the vehicle frame: start with optical axis = vehicle x, image down = -z, image right = -y
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])   # pitch down about y
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])  # roll about x
    R_vehicle_cam = Rx @ Ry @ R0
    T_vehicle_cam = make_T(R_vehicle_cam, [0, 0, height_m])
    floor_v = np.c_[rng.uniform(1.0, 6.0, 3000), rng.uniform(-2, 2, 3000), np.zeros(3000)]
    clutter_v = np.c_[rng.uniform(1.0, 6.0, 800), rng.uniform(-2, 2, 800), rng.uniform(0.1, 2.0, 800)]
    pts_cam = transform_points(invert_T(T_vehicle_cam), np.r_[floor_v, clutter_v])
    return pts_cam[pts_cam[:, 2] > 0.1], T_vehicle_cam


@pytest.mark.parametrize("inverse_depth", [False, True])
@pytest.mark.parametrize("height,pitch,roll", [(1.2, 10.0, 0.0), (0.4, 25.0, 3.0), (2.0, 5.0, -2.0)])
def test_floor_fit_recovers_height_pitch_roll(height, pitch, roll, inverse_depth):
    rng = np.random.default_rng(0)
    pts, T_true = _floor_view(height, pitch, roll, rng)
    pts = pts + rng.normal(0, 0.003, pts.shape)
    plane = fit_floor_plane(pts, np.random.default_rng(1), inverse_depth=inverse_depth)
    assert plane.camera_height_m == pytest.approx(height, abs=0.01)
    T = T_vehicle_cam_from_floor(plane)
    # The floor's normal, and so pitch and roll, must match; yaw is not observable and is fixed by convention.
    np.testing.assert_allclose(T[2, :3], T_true[2, :3], atol=5e-3)
    assert T[2, 3] == pytest.approx(height, abs=0.01)


def test_floor_fit_in_inverse_depth_weighs_far_stereo_depth_by_what_it_knows():
    """Stereo depth noise along each ray grows as z**2 (here 9 cm at 6 m): over seeded draws the fit in inverse
    depth tilts less than the 3D fit and stays within the calibration's 0.3 degrees and 1 cm."""
    tilt_deg, height_m = {False: [], True: []}, {False: [], True: []}
    for seed in range(12):
        rng = np.random.default_rng(seed)
        pts, T_true = _floor_view(1.8, 6.0, 0.0, rng)
        noisy = pts * (1 + 0.0026 * pts[:, 2:] * rng.normal(0, 1, (len(pts), 1)))
        for inverse_depth in (False, True):
            T = T_vehicle_cam_from_floor(fit_floor_plane(noisy, np.random.default_rng(1), inverse_depth=inverse_depth))
            tilt_deg[inverse_depth].append(np.degrees(np.arccos(np.clip(T[2, :3] @ T_true[2, :3], -1, 1))))
            height_m[inverse_depth].append(abs(T[2, 3] - T_true[2, 3]))
    assert np.mean(tilt_deg[True]) < 0.8 * np.mean(tilt_deg[False])
    assert max(tilt_deg[True]) < 0.3 and max(height_m[True]) < 0.01


def test_floor_fit_without_floor_fails_clearly():
    rng = np.random.default_rng(0)
    pts = backproject_pixels(rng.uniform(0, 848, 500), rng.uniform(0, 480, 500), rng.uniform(1, 5, 500), K)
    with pytest.raises(ValueError, match="no floor plane"):
        fit_floor_plane(pts, np.random.default_rng(0), min_inlier_ratio=0.5)
    with pytest.raises(ValueError, match="at least 3"):
        fit_floor_plane(np.zeros((2, 3)), np.random.default_rng(0))


# --- boards -------------------------------------------------------------------------------------------------

from pallet6d.calib.board import (BoardSpec, T_vehicle_cam_from_board, board_pose,  # noqa: E402
                                  calibrate_intrinsics, parse_board, render_board)
from pallet6d.calib.cli import upright_board_R  # noqa: E402

BOARD = BoardSpec("charuco", 9, 6, 0.10, 0.075)
HW = (480, 848)


def _board_in_view(distance_m, yaw_deg, rng):
    """T_cam_board of the board about `distance_m` ahead of a camera, turned by `yaw_deg` about its vertical."""
    a = np.radians(yaw_deg)
    R_cam_board = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), distance_m])
    half = np.array([BOARD.cols * BOARD.square_m, BOARD.rows * BOARD.square_m, 0]) / 2
    return make_T(R_cam_board, centre - R_cam_board @ half)


def test_board_pose_recovers_the_board_and_the_camera_to_vehicle_transform():
    rng = np.random.default_rng(0)
    T_cam_board = _board_in_view(1.6, 12.0, rng)
    img = render_board(BOARD, K, T_cam_board, HW)
    T_est, rms, n = board_pose(img, BOARD, K)
    assert n >= 30 and rms < 0.5
    np.testing.assert_allclose(T_est[:3, 3], T_cam_board[:3, 3], atol=0.005)
    dR = T_est[:3, :3] @ T_cam_board[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3
    # the board measured 1.5 m ahead of the fork roots: the camera comes out where the two poses put it
    T_vehicle_board = make_T(upright_board_R(0.0), [1.5, 0.45, 1.2])
    T_vc = T_vehicle_cam_from_board(T_vehicle_board, T_est)
    np.testing.assert_allclose(T_vc @ T_est, T_vehicle_board, atol=1e-9)


def test_intrinsics_from_rendered_board_views():
    rng = np.random.default_rng(1)
    views = [render_board(BOARD, K, _board_in_view(rng.uniform(1.2, 2.0), rng.uniform(-30, 30), rng), HW)
             for _ in range(6)]
    intr, rms, used = calibrate_intrinsics(views, BOARD)
    assert used == 6 and rms < 0.5
    np.testing.assert_allclose(intr.K[[0, 1], [0, 1]], K[[0, 1], [0, 1]], rtol=0.02)
    with pytest.raises(ValueError, match="found in 0 of 2"):
        calibrate_intrinsics([np.full(HW, 128, np.uint8)] * 2, BOARD)


def test_board_errors_are_clear():
    assert parse_board("charuco:9x6:0.1:0.075") == BOARD
    assert parse_board("chessboard:8x6:0.05").kind == "chessboard"
    for bad in ("charuco:9x6:0.1", "board:9x6:0.1", "chessboard:9by6:0.1"):
        with pytest.raises(ValueError, match="COLSxROWS"):
            parse_board(bad)
    with pytest.raises(ValueError, match="smaller than its square"):
        BoardSpec("charuco", 9, 6, 0.1, 0.2)
    with pytest.raises(ValueError, match="ChArUco"):
        board_pose(np.zeros(HW, np.uint8), parse_board("chessboard:8x6:0.05"), K)
    with pytest.raises(ValueError, match="board not found"):
        board_pose(np.full(HW, 128, np.uint8), BOARD, K)


def test_calib_cli_extrinsics_floor_and_show(tmp_path, capsys):
    import cv2

    from pallet6d.runtime.cli import main

    rng = np.random.default_rng(2)
    T_cam_board = _board_in_view(1.5, 0.0, rng)
    cv2.imwrite(str(tmp_path / "board.png"), render_board(BOARD, K, T_cam_board, HW))
    CameraIntrinsics(848, 480, K).save(tmp_path / "intr.json")
    assert main(["calib", "extrinsics", "--image", str(tmp_path / "board.png"), "--board", "charuco:9x6:0.1:0.075",
                 "--intrinsics", str(tmp_path / "intr.json"), "--board-pose", "1.5,0.45,1.2,0",
                 "--out", str(tmp_path / "board.json")]) == 0
    T_vc = np.asarray(__import__("json").loads((tmp_path / "board.json").read_text())["T_vehicle_cam"])
    expected = make_T(upright_board_R(0.0), [1.5, 0.45, 1.2]) @ invert_T(T_cam_board)
    np.testing.assert_allclose(T_vc[:3, 3], expected[:3, 3], atol=0.01)
    assert main(["calib", "show", str(tmp_path / "missing.toml")]) == 1
    assert "cannot read the calibration" in capsys.readouterr().err

    # the floor seen by the mounted camera gives pitch, roll and height; the board's file gives yaw and x, y
    from forklift_fixtures import K as K_SMALL
    from forklift_fixtures import camera, pallet_pose, render

    from pallet6d.runtime.calibration import load_calibration
    from pallet6d.runtime.cameras import RGBDFrame
    from pallet6d.runtime.cameras.replay import ReplayWriter
    T_true = camera(0.9, 12.0, roll_deg=1.0)
    depth = render(T_true, pallet_pose(3.5))
    with ReplayWriter(tmp_path / "rec") as w:
        for i in range(2):
            w.write(RGBDFrame.from_depth_m(np.zeros(depth.shape + (3,), np.uint8), depth, K_SMALL, timestamp_s=i,
                                           frame_number=i, source="test"))
    assert main(["calib", "floor", "--source", f"replay:{tmp_path / 'rec'}", "--extrinsics",
                 str(tmp_path / "board.json"), "--serial", "123", "--out", str(tmp_path / "cam.toml")]) == 0
    cal = load_calibration(tmp_path / "cam.toml")
    np.testing.assert_allclose(cal.T_vehicle_cam[2], T_true[2], atol=2e-3)      # pitch, roll, height
    np.testing.assert_allclose(cal.T_vehicle_cam[:2, 3], T_vc[:2, 3], atol=1e-9)  # x, y from the board
    assert cal.serial == "123" and cal.width == depth.shape[1]
    assert main(["calib", "show", str(tmp_path / "cam.toml")]) == 0
    assert 'serial = "123"' in capsys.readouterr().out
    assert main(["calib", "check", "--source", f"replay:{tmp_path / 'rec'}", "--calibration",
                 str(tmp_path / "cam.toml")]) == 0
