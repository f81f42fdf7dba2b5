"""`pallet6d serve` in the vehicle frame: the real daemon on a replay of a simulated forklift view, with the
simulator's exact calibration and with ones whose camera height is 20 cm and 50 cm off."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from serve_fixtures import Daemon, free_port, write_config
from pallet6d.runtime.calibration import Calibration, save_calibration
from pallet6d.runtime.floor import FloorPlane
from pallet6d.runtime.serve.schema import ReadyResponse

FRAME = 2          # of the generated views, the one (camera 0.4 m up) that shows enough floor at 424x240


@pytest.fixture(scope="module")
def forklift_view(tmp_path_factory):
    """A replay of one simulated forklift view (4 copies, 1/30 s apart) and its exact T_vehicle_cam."""
    from pallet6d.runtime.cameras import ReplayWriter, open_source
    from pallet6d.runtime.cli import main

    work = tmp_path_factory.mktemp("forklift_view")
    assert main(["sim", "--preset", "forklift-approach", "--frames", "3", "--seed", "5", "--size", "424x240",
                 "--out", str(work / "bop")]) == 0
    fk = json.loads(next((work / "bop").rglob("scene_forklift.json")).read_text())[str(FRAME)]
    T = np.eye(4)
    T[:3, :3] = np.asarray(fk["cam_R_c2v"]).reshape(3, 3)
    T[:3, 3] = np.asarray(fk["cam_t_c2v"]) / 1000
    with open_source(f"bop:{work / 'bop'}") as src:
        frame = [f for f in src][FRAME]
    with ReplayWriter(work / "rec") as writer:
        for k in range(4):
            writer.write(dataclasses.replace(frame, timestamp_s=k / 30, frame_number=k))
    return work / "rec", T, frame


def calibration_file(path, T_vehicle_cam, frame, height_error_m=0.0):
    T = T_vehicle_cam.copy()
    T[2, 3] += height_error_m
    save_calibration(Calibration("sim", "2026-11-23", frame.width, frame.height, frame.K, T,
                                 FloorPlane(T[2, :3].copy(), float(T[2, 3]))), path)
    return path


def start(tmp_path, forklift_view, bundle_dir, height_error_m):
    rec, T, frame = forklift_view
    cal = calibration_file(tmp_path / "cam.toml", T, frame, height_error_m)
    port = free_port()
    cfg = write_config(tmp_path / "serve.toml", f"replay:{rec}", bundle_dir, port,
                       output=f'calibration = "{cal}"\n\n[floor_check]\ninterval_s = 0.5')
    # the random-weight test bundle's poses are not pallet-shaped: no structure check, so that some are accepted
    cfg.write_text(cfg.read_text().replace("refine = false", "refine = false\nstructure = false"))
    return Daemon(cfg, port), cfg


@pytest.fixture(scope="module")
def daemons(forklift_view, bundle_dir, tmp_path_factory):
    """Two daemons started side by side: the exact calibration, and one 20 cm too high."""
    good = start(tmp_path_factory.mktemp("good"), forklift_view, bundle_dir, 0.0)
    off = start(tmp_path_factory.mktemp("off"), forklift_view, bundle_dir, 0.2)
    try:
        for d, _ in (good, off):
            d.wait_healthy()
            d.wait(lambda d=d: d.client.get("/readyz").json()["calibration"]["checks"] >= 1, "a floor check")
        yield good, off
    finally:
        for d, _ in (good, off):
            assert d.stop() == 0, d.log()


def test_vehicle_frame_response_equals_the_forklift_module(daemons, forklift_view):
    from pallet6d.runtime.cameras import open_source
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.forklift import vehicle_frame_result
    from pallet6d.runtime.serve.cli import _options
    from pallet6d.runtime.serve.config import ServeConfig
    from pallet6d.runtime.serve.schema import PalletsResponse

    (d, cfg_path), _ = daemons
    rec, T, _ = forklift_view
    d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz")
    body = d.client.post("/v1/detect").json()
    PalletsResponse.model_validate(body)            # the OpenAPI description is what is sent
    assert body["output_frame"] == "vehicle" and body["error"] is None

    cfg = ServeConfig.load(cfg_path)
    est = PalletEstimator.from_bundle(cfg.model.bundle, threads=1, precision="fp32", **_options(cfg.estimator))
    with open_source(f"replay:{rec}") as src:
        frame = next(iter(src))         # every frame of the recording is the same view
    expected = vehicle_frame_result(est.estimate(frame, T_vehicle_cam=T), T, est.bundle, frame).to_dict()["poses"]
    assert any("forklift" in p and len(p["forklift"]["pockets"]) == 2 for p in expected), "nothing to compare"
    assert len(body["pallets"]) == len(expected)
    for got, want in zip(body["pallets"], expected):
        assert _same(got, want), (got, want)
    latest = d.client.get("/v1/pallets").json()
    PalletsResponse.model_validate(latest)
    assert latest["output_frame"] == "vehicle" and all("t_vehicle_m" in p for p in latest["pallets"])
    with d.client.stream("GET", "/v1/stream", params={"max_events": 1}) as r:
        event = next(json.loads(line[6:]) for line in r.iter_lines() if line.startswith("data: "))
    assert event["output_frame"] == "vehicle" and event["pallets"] and "forklift" in event["pallets"][0]


def test_openapi_describes_the_vehicle_frame_response(daemons):
    (d, _), _ = daemons
    schemas = d.client.get("/openapi.json").json()["components"]["schemas"]
    assert {"PalletsResponse", "Pallet", "Forklift", "Pocket", "ReadyResponse"} <= set(schemas)
    assert {"t_vehicle_m", "forklift"} <= set(schemas["Pallet"]["properties"])
    assert {"centre_m", "state"} <= set(schemas["Pocket"]["properties"])
    assert "pick_safe" in schemas["Forklift"]["properties"]


def test_a_matching_calibration_is_ready(daemons):
    (d, _), _ = daemons
    d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz")
    ready = d.client.get("/readyz").json()
    floor = ready["calibration"]
    assert ready["checks"]["calibration"] and ready["reasons"] == [] and floor["state"] == "ok"
    assert abs(floor["camera_height_m"]["measured"] - floor["camera_height_m"]["expected"]) < 0.03
    assert floor["floor_tilt_deg"]["measured"] < 2.0 and ready["output_frame"] == "vehicle"
    ReadyResponse.model_validate(ready)
    assert d.metric('pallet6d_floor_checks_total{result="agrees"}') >= 1
    assert d.metric("pallet6d_calibration_ok") == 1


def test_a_calibration_20cm_off_fails_readyz_and_withholds_vehicle_output(daemons):
    _, (d, _) = daemons
    r = d.client.get("/readyz")
    ready = r.json()
    floor = ready["calibration"]
    assert r.status_code == 503 and not ready["ready"] and ready["checks"]["calibration"] is False
    assert ready["checks"]["camera"] and ready["checks"]["model"]            # only the calibration fails
    ReadyResponse.model_validate(ready)
    assert floor["state"] == "failed" and "camera height off by -20.0 cm" in floor["detail"]
    assert floor["camera_height_m"]["expected"] - floor["camera_height_m"]["measured"] == pytest.approx(0.2, abs=0.02)
    assert floor["camera_height_m"]["tolerance"] == 0.03 and floor["floor_tilt_deg"]["tolerance"] == 2.0
    assert len(ready["reasons"]) == 1 and ready["reasons"][0].startswith("calibration failed: floor tilted")
    # frames estimated before the first check may carry pallets; every frame after it is withheld
    d.wait(lambda: (d.client.get("/v1/pallets").json().get("error") or "") != "", "a withheld frame")
    latest = d.client.get("/v1/pallets").json()
    assert latest["pallets"] == [] and "camera moved since it was calibrated" in latest["error"]
    detect = d.client.post("/v1/detect")
    assert detect.status_code == 503 and "camera moved since it was calibrated" in detect.json()["detail"]
    assert d.metric('pallet6d_floor_checks_total{result="disagrees"}') >= 1
    assert d.metric("pallet6d_calibration_ok") == 0
    assert d.metric('pallet6d_failures_total{reason="calibration"}') >= 1


@pytest.fixture(scope="module")
def far_daemon(forklift_view, bundle_dir, tmp_path_factory):
    """A daemon whose calibration puts the camera 0.5 m too high: no floor near the calibrated one."""
    d, _ = start(tmp_path_factory.mktemp("far"), forklift_view, bundle_dir, 0.5)
    try:
        d.wait_healthy()
        d.wait(lambda: d.client.get("/readyz").json()["calibration"]["checks"] >= 1, "a floor check")
        yield d
    finally:
        assert d.stop() == 0, d.log()


def test_a_calibration_half_a_metre_too_high_fails_readyz_with_the_floor_found_elsewhere(far_daemon):
    d = far_daemon
    r = d.client.get("/readyz")
    ready = r.json()
    floor = ready["calibration"]
    assert r.status_code == 503 and ready["checks"]["calibration"] is False and floor["state"] == "failed"
    ReadyResponse.model_validate(ready)
    assert floor["camera_height_m"]["expected"] - floor["camera_height_m"]["measured"] == pytest.approx(0.5, abs=0.02)
    assert floor["floor_tilt_deg"]["measured"] < 1.0
    reason = next(r for r in ready["reasons"] if r.startswith("calibration failed: floor tilted"))
    assert "camera height off by -50.0 cm" in reason and "found in the whole image" in reason
    assert d.metric('pallet6d_floor_checks_total{result="disagrees"}') >= 1
    assert d.metric("pallet6d_calibration_ok") == 0


def test_check_names_the_calibration_and_refuses_vehicle_output_without_one(daemons, tmp_path, forklift_view,
                                                                            bundle_dir, capsys):
    from pallet6d.runtime.cli import main

    (_, good_cfg), _ = daemons
    assert main(["serve", "--config", str(good_cfg), "--check"]) == 0
    out = capsys.readouterr().out
    assert "vehicle-frame output, calibration" in out and "camera sim" in out
    rec, _, _ = forklift_view
    bare = write_config(tmp_path / "serve.toml", f"replay:{rec}", bundle_dir, free_port(), output="")
    assert main(["serve", "--config", str(bare), "--check"]) == 2
    err = capsys.readouterr().err
    assert "needs output.calibration" in err and 'frame = "camera"' in err


def _same(got, want) -> bool:
    """Equal JSON, numbers within 1e-3 (both sides rounded to 4 decimals from the same computation)."""
    if isinstance(want, dict):
        return isinstance(got, dict) and got.keys() == want.keys() and all(_same(got[k], want[k]) for k in want)
    if isinstance(want, list):
        return isinstance(got, list) and len(got) == len(want) and all(_same(g, w) for g, w in zip(got, want))
    if isinstance(want, float) and not isinstance(want, bool):
        return isinstance(got, (int, float)) and abs(got - want) <= 1e-3
    return got == want
