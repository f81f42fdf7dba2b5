"""`pallet6d run` in the vehicle frame on a simulated forklift view, with the simulator's exact calibration."""
import json

import numpy as np
import pytest

from pallet6d.runtime.calibration import Calibration, save_calibration
from pallet6d.runtime.cli import main
from pallet6d.runtime.floor import FloorPlane


@pytest.fixture(scope="module")
def forklift_bop(tmp_path_factory):
    out = tmp_path_factory.mktemp("fa")
    assert main(["sim", "--preset", "forklift-approach", "--frames", "1", "--seed", "5", "--out", str(out)]) == 0
    return out


def _calibration_file(bop, path, extra_pitch_deg=0.0):
    scene = next(p for p in bop.rglob("scene_forklift.json"))
    cam = json.loads((scene.parent / "scene_camera.json").read_text())["0"]
    fk = json.loads(scene.read_text())["0"]
    T = np.eye(4)
    T[:3, :3] = np.asarray(fk["cam_R_c2v"]).reshape(3, 3)
    T[:3, 3] = np.asarray(fk["cam_t_c2v"]) / 1000
    a = np.radians(extra_pitch_deg)                      # a camera knocked about its own x axis
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    from pallet6d.runtime.cameras import open_source
    with open_source(f"bop:{bop}") as src:
        frame = next(iter(src))
    cal = Calibration(serial="sim", date="2026-11-23", width=frame.width, height=frame.height,
                      K=np.asarray(cam["cam_K"]).reshape(3, 3), T_vehicle_cam=T,
                      floor=FloorPlane(T[2, :3].copy(), float(T[2, 3])))
    save_calibration(cal, path)
    return path


def test_vehicle_frame_run_gives_vehicle_poses_and_pockets(bundle_dir, forklift_bop, tmp_path, capsys):
    cal = _calibration_file(forklift_bop, tmp_path / "cam.toml")
    # the random-init test bundle's poses lie any way up: with the calibration the structure check's tilt test
    # refuses them all, so it is off here (this test is about the output's fields)
    rc = main(["run", "--source", f"bop:{forklift_bop}", "--bundle", str(bundle_dir), "--threads", "1",
               "--score-threshold", "0", "--min-fit", "0", "--no-structure-check", "--calibration", str(cal)])
    assert rc == 0
    line = json.loads(capsys.readouterr().out.splitlines()[0])
    assert "error" not in line, line.get("error")
    assert line["poses"] and all("t_vehicle_m" in p for p in line["poses"])
    assert any("forklift" in p and len(p["forklift"]["pockets"]) == 2 for p in line["poses"])


def test_a_knocked_camera_stops_vehicle_output(bundle_dir, forklift_bop, tmp_path, capsys):
    cal = _calibration_file(forklift_bop, tmp_path / "cam.toml", extra_pitch_deg=2.0)
    rc = main(["run", "--source", f"bop:{forklift_bop}", "--bundle", str(bundle_dir), "--threads", "1",
               "--calibration", str(cal)])
    assert rc == 1                                  # every frame refused: a run that estimated nothing fails
    line = json.loads(capsys.readouterr().out.splitlines()[0])
    assert "poses" not in line and "camera moved since it was calibrated" in line["error"]


def test_roi_drops_detections_before_posing(bundle_dir, forklift_bop, capsys):
    rc = main(["run", "--source", f"bop:{forklift_bop}", "--bundle", str(bundle_dir), "--threads", "1",
               "--frame", "camera", "--score-threshold", "0", "--min-fit", "0", "--roi", "0,0,2,2"])
    assert rc == 0
    line = json.loads(capsys.readouterr().out.splitlines()[0])
    assert not line["poses"] and line["rejected"] and {r["reason"] for r in line["rejected"]} == {"outside_roi"}
