import numpy as np
import pytest

from pallet6d.calib.floor import T_vehicle_cam_from_floor, fit_floor_plane
from pallet6d.calib.intrinsics import CameraIntrinsics
from pallet6d.runtime.geometry import backproject_pixels, make_T, invert_T, transform_points

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


@pytest.mark.parametrize("height,pitch,roll", [(1.2, 10.0, 0.0), (0.4, 25.0, 3.0), (2.0, 5.0, -2.0)])
def test_floor_fit_recovers_height_pitch_roll(height, pitch, roll):
    rng = np.random.default_rng(0)
    pts, T_true = _floor_view(height, pitch, roll, rng)
    pts = pts + rng.normal(0, 0.003, pts.shape)
    plane = fit_floor_plane(pts, np.random.default_rng(1))
    assert plane.camera_height_m == pytest.approx(height, abs=0.01)
    T = T_vehicle_cam_from_floor(plane)
    # The floor's normal, and so pitch and roll, must match; yaw is not observable and is fixed by convention.
    np.testing.assert_allclose(T[2, :3], T_true[2, :3], atol=5e-3)
    assert T[2, 3] == pytest.approx(height, abs=0.01)


def test_floor_fit_without_floor_fails_clearly():
    rng = np.random.default_rng(0)
    pts = backproject_pixels(rng.uniform(0, 848, 500), rng.uniform(0, 480, 500), rng.uniform(1, 5, 500), K)
    with pytest.raises(ValueError, match="no floor plane"):
        fit_floor_plane(pts, np.random.default_rng(0), min_inlier_ratio=0.5)
    with pytest.raises(ValueError, match="at least 3"):
        fit_floor_plane(np.zeros((2, 3)), np.random.default_rng(0))
