import numpy as np
import pytest

from forklift_fixtures import H, K, W, camera, pallet_pose, render
from pallet6d.runtime.calibration import (Calibration, CalibrationError, CalibrationMonitor, load_calibration,
                                          save_calibration)
from pallet6d.runtime.floor import FloorPlane, check_floor
from pallet6d.runtime.roi import RegionOfInterest, roi_filter


def _calibration(T_vc=None, **kw) -> Calibration:
    T_vc = camera() if T_vc is None else T_vc
    floor = FloorPlane(T_vc[2, :3].copy(), float(T_vc[2, 3]))
    return Calibration(**{"serial": "815412070123", "date": "2026-11-23", "width": W, "height": H, "K": K,
                          "T_vehicle_cam": T_vc, "floor": floor, "camera": "realsense", **kw})


def test_calibration_file_round_trip_is_readable_toml(tmp_path):
    cal = _calibration(dist=[0.1, -0.05, 0.0, 0.0, 0.01])
    save_calibration(cal, tmp_path / "cam.toml")
    text = (tmp_path / "cam.toml").read_text()
    assert 'serial = "815412070123"' in text and "[extrinsics]" in text and "T_vehicle_cam" in text
    back = load_calibration(tmp_path / "cam.toml")
    np.testing.assert_allclose(back.T_vehicle_cam, cal.T_vehicle_cam, atol=1e-15)
    np.testing.assert_allclose(back.K, K)
    assert back.dist.tolist() == [0.1, -0.05, 0.0, 0.0, 0.01] and back.date == "2026-11-23"


def test_missing_calibration_file_says_what_to_run(tmp_path):
    with pytest.raises(CalibrationError, match="pallet6d calib floor.*--frame camera"):
        load_calibration(tmp_path / "none.toml")


@pytest.mark.parametrize("edit,match", [
    (lambda t: t.replace("format_version = 1", "format_version = 7"), "format_version"),
    (lambda t: t.replace('date = "2026-11-23"', 'date = "yesterday"'), "ISO date"),
    (lambda t: t.replace("[floor]", "[floor_]"), "missing field 'floor'"),
    (lambda t: t.replace("d_m = 0.5", "d_m = 0.6"), "floor disagrees"),
    (lambda t: t + "\n[broken", "not a TOML"),
])
def test_bad_calibration_files_are_refused(tmp_path, edit, match):
    path = tmp_path / "cam.toml"
    save_calibration(_calibration(), path)
    path.write_text(edit(path.read_text()))
    with pytest.raises(CalibrationError, match=match):
        load_calibration(path)


def test_frames_from_another_camera_or_resolution_are_refused():
    cal = _calibration()
    cal.check_camera(K, (H, W))
    with pytest.raises(CalibrationError, match="424x240 images"):
        cal.check_camera(K, (480, 848))
    with pytest.raises(CalibrationError, match="intrinsics differ"):
        cal.check_camera(K * [[1.1], [1.1], [1]], (H, W))


def test_floor_check_agrees_when_still_and_disagrees_when_knocked():
    T_vc = camera(0.8, 10.0)
    cal = _calibration(T_vc)
    depth = render(T_vc, pallet_pose(2.5))
    assert check_floor(cal.floor, depth, K).agrees is True
    knocked = render(camera(0.8, 12.5, roll_deg=1.0), pallet_pose(2.5))
    c = check_floor(cal.floor, knocked, K)
    assert c.agrees is False and c.tilt_deg == pytest.approx(np.hypot(2.5, 1.0), abs=0.1)
    assert check_floor(cal.floor, np.zeros((H, W), np.float32), K).agrees is None


def test_floor_check_disagrees_with_a_focal_length_off():
    """Depth read with the wrong intrinsics puts the floor elsewhere: a focal length 2x too long (which the
    structure check cannot always see in a box cut by the image's edge) stops vehicle-frame output at start."""
    T_vc = camera(0.8, 10.0)
    depth = render(T_vc, pallet_pose(2.5))
    long_K = np.array(K, dtype=float)
    long_K[0, 0] *= 2.0
    long_K[1, 1] *= 2.0
    assert check_floor(_calibration(T_vc).floor, depth, long_K).agrees is False
    mon = CalibrationMonitor(_calibration(T_vc))
    assert mon.update(depth, long_K).agrees is False and not mon.ok


@pytest.mark.parametrize("scale", [0.1, 0.5, 2.0])
def test_floor_check_disagrees_with_a_depth_scale_off(scale):
    """Depth read with the wrong scale (uint16 millimetres taken for 0.1 mm, a stereo baseline off) puts the floor
    at the wrong height: vehicle-frame output stops at start. The structure check's frame size rule leaves such
    frames to this check when a calibration is given."""
    T_vc = camera(0.8, 10.0)
    depth = render(T_vc, pallet_pose(2.5))
    cal = _calibration(T_vc)
    c = check_floor(cal.floor, depth * scale, K)
    assert c.agrees is False and c.height_diff_m == pytest.approx(0.8 * (scale - 1.0), abs=0.02)
    mon = CalibrationMonitor(cal)
    assert mon.update(depth * scale, K).agrees is False and not mon.ok


def test_monitor_stops_vehicle_output_after_a_knock_and_resumes_when_the_floor_agrees_again():
    T_vc = camera(0.8, 10.0)
    mon = CalibrationMonitor(_calibration(T_vc), every_n=5, n_bad=2, n_good=2)
    good = render(T_vc, pallet_pose(2.5))
    bad = render(camera(0.8, 14.0), pallet_pose(2.5))
    assert mon.update(good, K).agrees and mon.ok
    assert mon.update(bad, K) is None and mon.ok                     # not due: checked every 5 frames
    for _ in range(3):
        mon.update(good, K)
    assert mon.update(bad, K).agrees is False and mon.ok             # one bad check is not yet a knock ...
    assert mon.update(bad, K).agrees is False and not mon.ok         # ... two in a row are (checked at once)
    with pytest.raises(CalibrationError, match="moved since it was calibrated"):
        mon.require_ok()
    mon.update(np.zeros((H, W), np.float32), K)                       # no floor in view: no change
    assert not mon.ok
    mon.update(good, K)
    assert not mon.ok
    mon.update(good, K)
    assert mon.ok
    mon.require_ok()


def test_roi_drops_boxes_outside_the_image_box_and_the_depth_window():
    depth = render(camera(), pallet_pose(2.0))
    boxes = np.array([[150, 120, 270, 170], [0, 0, 40, 40], [150, 120, 270, 170]], float)
    keep, why = roi_filter(boxes, depth, RegionOfInterest(box_xyxy=(100, 60, 330, 240)))
    assert keep.tolist() == [True, False, True] and "outside the region of interest" in why[1] and why[0] == ""
    keep, why = roi_filter(boxes[:1], depth, RegionOfInterest(distance_m=4.0, tolerance_m=0.5))
    assert keep.tolist() == [False] and "outside the hint 4.00" in why[0]
    assert roi_filter(boxes[:1], depth, RegionOfInterest(distance_m=2.2, tolerance_m=0.5))[0].tolist() == [True]
    empty = np.zeros((H, W), np.float32)                               # no depth: the pose stage judges it
    assert roi_filter(boxes[:1], empty, RegionOfInterest(distance_m=9.0))[0].tolist() == [True]
    assert roi_filter(np.zeros((0, 4)), depth, RegionOfInterest(distance_m=2.0))[0].shape == (0,)
    assert roi_filter(boxes, None, None)[0].all()


@pytest.mark.parametrize("kwargs,match", [
    (dict(box_xyxy=(10, 10, 5, 20)), "x2 > x1"),
    (dict(distance_m=-1.0), "distance_m"),
    (dict(distance_m=2.0, tolerance_m=0.0), "tolerance_m"),
])
def test_roi_validates(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RegionOfInterest(**kwargs)


def test_run_refuses_vehicle_frame_without_calibration(tmp_path, capsys):
    from pallet6d.runtime.cli import main

    rc = main(["run", "--source", f"bop:{tmp_path}", "--bundle", str(tmp_path / "nope")])
    err = capsys.readouterr().err
    assert rc == 2 and "needs a calibration" in err and "pallet6d calib floor" in err and "--frame camera" in err
    rc = main(["run", "--source", f"bop:{tmp_path}", "--calibration", str(tmp_path / "none.toml")])
    assert rc == 2 and "cannot read the calibration" in capsys.readouterr().err


def test_toml_writer_round_trips_through_tomllib_and_refuses_what_toml_cannot_hold():
    import tomllib

    from pallet6d.runtime.calibration import to_toml
    data = {"s": 'a "quoted" \\ path\nnext', "i": 3, "b": True, "m": [[1.5, -2.0], [0.0, 1e-12]],
            "t": {"x": 0.1, "l": ["a", "b"]}}
    assert tomllib.loads(to_toml(data)) == data
    with pytest.raises(ValueError, match="TOML cannot hold"):
        to_toml({"x": float("nan")})
    with pytest.raises(TypeError, match="cannot write"):
        to_toml({"x": object()})


def test_floor_fit_with_an_up_hint_never_takes_a_wall():
    from pallet6d.runtime.floor import fit_floor_plane

    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(-2, 2, 3000), rng.uniform(-1, 1, 3000), np.full(3000, 3.0)]    # facing the camera
    floor = np.c_[rng.uniform(-2, 2, 800), np.full(800, 1.0), rng.uniform(1, 4, 800)]      # 1 m below it
    pts = np.r_[wall, floor]
    assert abs(fit_floor_plane(pts, np.random.default_rng(1), min_inlier_ratio=0.1).normal[2]) > 0.99
    plane = fit_floor_plane(pts, np.random.default_rng(1), min_inlier_ratio=0.1,
                            up_hint=np.array([0.0, -1.0, 0.0]), max_tilt_deg=30)
    np.testing.assert_allclose(plane.normal, [0, -1, 0], atol=1e-3)
    assert plane.camera_height_m == pytest.approx(1.0, abs=0.005)


def test_floor_check_takes_nan_depth_as_missing():
    T_vc = camera(0.8, 10.0)
    depth = render(T_vc, pallet_pose(2.5))
    depth[np.random.default_rng(0).random(depth.shape) < 0.3] = np.nan
    assert check_floor(_calibration(T_vc).floor, depth, K).agrees is True
