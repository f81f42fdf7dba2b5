"""The daemon's TOML configuration: defaults, paths, and a clear error for each kind of mistake."""
from __future__ import annotations

from pathlib import Path

import pytest

from pallet6d.runtime.serve.config import ConfigError, ServeConfig

REPO = Path(__file__).resolve().parents[1]
TOKEN = "0123456789abcdef-token"
CAMERA_FRAME = '[output]\nframe = "camera"\n'


def load(tmp_path: Path, text: str, environ: dict | None = None) -> ServeConfig:
    path = tmp_path / "serve.toml"
    path.write_text(text)
    return ServeConfig.load(path, environ=environ or {})


def test_the_example_config_is_valid_and_uses_the_defaults():
    cfg = ServeConfig.load(REPO / "deploy" / "serve.toml", environ={})
    assert cfg.camera.source == "realsense" and cfg.camera.mode == "continuous"
    assert cfg.api.host == "127.0.0.1" and cfg.api.token == "" and cfg.model.precision == "int8"
    assert cfg.estimator.score_threshold == 0.25 and cfg.snapshot.frames == 30


def test_empty_config_means_defaults_and_relative_paths_follow_the_file(tmp_path):
    assert load(tmp_path, CAMERA_FRAME).camera.source == "realsense"
    cfg = load(tmp_path, '[camera]\nsource = "replay:rec"\n[model]\nbundle = "b"\n[snapshot]\ndir = "snaps"\n'
                         '[estimator]\ndepth_range_m = [0.3, 6]\nmax_pallets = 4\n' + CAMERA_FRAME)
    assert cfg.camera.source == f"replay:{tmp_path / 'rec'}"
    assert cfg.model.bundle == str(tmp_path / "b") and cfg.snapshot.dir == str(tmp_path / "snaps")
    assert cfg.estimator.depth_range_m == (0.3, 6.0) and cfg.estimator.max_pallets == 4
    assert load(tmp_path, '[estimator]\npallet_types = ["epal"]\n' + CAMERA_FRAME).estimator.pallet_types == ("epal",)
    assert load(tmp_path, "[estimator]\nlevel = false\n" + CAMERA_FRAME).estimator.level is None
    level = load(tmp_path, "[estimator]\nlevel = {refine_iterations = 3}\n" + CAMERA_FRAME).estimator.level
    assert level.refine_iterations == 3 and level.refine_points == 600
    assert load(tmp_path, "[estimator]\nstructure = false\n" + CAMERA_FRAME).estimator.structure is None
    relaxed = load(tmp_path, "[estimator]\nstructure = {min_agreement = 0.5}\n" + CAMERA_FRAME).estimator.structure
    assert relaxed.min_agreement == 0.5 and relaxed.grid == 32
    assert load(tmp_path, "[estimator]\nweak_boxes = false\n" + CAMERA_FRAME).estimator.weak_boxes is None
    weak = load(tmp_path, "[estimator]\nweak_boxes = {score_threshold = 0.15}\n" + CAMERA_FRAME).estimator.weak_boxes
    assert weak.score_threshold == 0.15 and weak.min_open_fraction == 0.7 and weak.min_open_fraction_cut == 0.85
    assert load(tmp_path, "[estimator]\ndepth_proposals = false\n" + CAMERA_FRAME).estimator.depth_proposals is None
    near = load(tmp_path, "[estimator]\ndepth_proposals = {max_range_m = 4.0}\n" + CAMERA_FRAME).estimator
    assert near.depth_proposals.max_range_m == 4.0 and near.depth_proposals.band_m == (0.05, 0.19)
    assert load(tmp_path, '[camera]\nsource = "realsense:123"\n' + CAMERA_FRAME).camera.source == "realsense:123"


@pytest.mark.parametrize("text, where", [
    ("[camera\n", "not valid TOML"),
    ("[cameras]\n", "unknown section"),
    ("[camera]\nsorce = 'replay:x'\n", "unknown key(s) ['sorce']"),
    ("[camera]\nsource = 'webcam'\n", "camera.source"),
    ("[camera]\nsource = 'replay:'\n", "camera.source"),
    ("[camera]\nmode = 'sometimes'\n", "camera.mode"),
    ("[camera]\nframe_timeout_s = 0\n", "camera.frame_timeout_s"),
    ("[camera]\nframe_timeout_s = '5'\n", "expected float, got str"),
    ("[camera]\nrealtime = 1\n", "camera.realtime: expected bool"),
    ("[camera]\nreconnect_min_s = 20.0\n", "camera.reconnect_min_s"),
    ("[camera]\nmax_rate_hz = -1.0\n", "camera.max_rate_hz"),
    ("[camera]\nmax_rate_hz = 0.01\n", "camera.max_rate_hz"),
    ("[model]\nprecision = 'fp16'\n", "model.precision"),
    ("[model]\nthreads = 0\n", "model.threads"),
    ("[model]\nthreads = true\n", "model.threads: expected int"),
    ("[model]\nthreads = 100000\n", "model.threads: must be in 1..64, got 100000"),
    ("[estimator]\nseed = -1\n", "seed must be an integer >= 0, got -1"),
    ("[estimator]\nscore_threshold = 2.0\n", "score_threshold must be in [0, 1]"),
    ("[estimator]\nthreshold = 0.5\n", "[estimator] unknown key(s) ['threshold']"),
    ("[estimator]\ndepth_range_m = [1]\n", "estimator.depth_range_m"),
    ("[estimator]\npallet_types = 'epal'\n", "estimator.pallet_types: expected a list of pallet type names"),
    ("[estimator]\npallet_types = []\n", "estimator.pallet_types"),
    ("[estimator]\nstructure = 3\n", "estimator.structure: expected true, false or a table"),
    ("[estimator]\nstructure = {grid = 'x'}\n", "estimator.structure.grid: expected int"),
    ("[estimator]\nstructure = {gird = 32}\n", "estimator.structure: unknown key(s) ['gird']"),
    ("[output]\nframe = 'world'\n", "output.frame: must be one of ('vehicle', 'camera')"),
    ("[output]\n", "output.frame: vehicle-frame output (the default) needs output.calibration"),
    ("[output]\nframe = 'vehicle'\n", "output.calibration: frame = \"vehicle\" needs the camera's calibration"),
    ("[output]\ncalibration = 'missing.toml'\n", "output.calibration: "),
    ("[floor_check]\ninterval_s = 0\n", "floor_check.interval_s"),
    ("[floor_check]\nmax_tilt_deg = 0\n", "floor_check.max_tilt_deg"),
    ("[floor_check]\nmax_height_diff_m = 2.0\n", "floor_check.max_height_diff_m"),
    ("[floor_check]\nwhen_unseen = 'maybe'\n", "floor_check.when_unseen"),
    ("[floor_check]\nmax_tilt_deg = '2'\n", "floor_check.max_tilt_deg: expected float"),
    ("[api]\nhost = 'localhost'\n", "must be an IP address"),
    ("[api]\nport = 70000\n", "api.port"),
    ("[api]\nmax_body_bytes = 10\n", "api.max_body_bytes"),
    ("[api]\nhost = '0.0.0.0'\n", "set a bearer token"),
    ("[api]\ntoken_file = 'nope'\n", "api.token_file: cannot read"),
    ("[api]\ntoken = 'inline'\n", "unknown key(s) ['token']"),
    ("[snapshot]\nframes = 0\n", "snapshot.frames"),
    ("[snapshot]\nframes = 100000\n", "snapshot.frames"),
    ("camera = 3\n", "[camera] must be a table"),
])
def test_config_errors_name_the_key(tmp_path, text, where):
    with pytest.raises(ConfigError) as err:
        load(tmp_path, text if "[output]" in text else text + CAMERA_FRAME)
    assert where in str(err.value) and str(tmp_path / "serve.toml") in str(err.value)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        ServeConfig.load(tmp_path / "none.toml")


def test_public_address_needs_a_token_from_a_file_or_the_environment(tmp_path):
    (tmp_path / "token").write_text(TOKEN + "\n")
    cfg = load(tmp_path, '[api]\nhost = "0.0.0.0"\ntoken_file = "token"\n' + CAMERA_FRAME)
    assert cfg.api.token == TOKEN and TOKEN not in repr(cfg)
    env = {"PALLET6D_API_TOKEN": TOKEN}
    assert load(tmp_path, '[api]\nhost = "::"\n' + CAMERA_FRAME, environ=env).api.token == TOKEN
    with pytest.raises(ConfigError, match="at least 16"):
        load(tmp_path, '[api]\nhost = "0.0.0.0"\n' + CAMERA_FRAME, environ={"PALLET6D_API_TOKEN": "short"})
    # a loopback address may have a token too (then every endpoint but the health checks needs it)
    assert load(tmp_path, CAMERA_FRAME, environ=env).api.token == TOKEN


def test_systemd_unit_and_docker_image_run_the_daemon_supervised():
    """CI cannot run systemd or Docker: the recipes are checked for what the daemon relies on."""
    unit = (REPO / "deploy" / "pallet6d.service").read_text()
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "RestartPreventExitStatus=2",
                 "ExecStart=/opt/pallet6d/venv/bin/pallet6d serve --config /etc/pallet6d/serve.toml", "User=pallet6d"):
        assert line in unit, line
    docker = (REPO / "Dockerfile").read_text()
    daemon_stage = docker.split("FROM edge AS daemon", 1)[1]
    assert "COPY deploy/serve.toml /etc/pallet6d/serve.toml" in daemon_stage
    assert "serve --config /etc/pallet6d/serve.toml --check" in daemon_stage
    assert "HEALTHCHECK" in daemon_stage and "/healthz" in daemon_stage and "FROM" not in daemon_stage
    assert "[serve" in docker   # the runtime image installs the serve extra
    smoke = (REPO / ".ci" / "smoke-installed").read_text()
    assert "pallet6d serve --config" in smoke and "kill -TERM" in smoke


def _calibration(path: Path, height_error_m: float = 0.0, serial: str = "815412070123") -> Path:
    """A calibration file of a camera 0.5 m above the floor; its stored floor `height_error_m` off its extrinsics."""
    from forklift_fixtures import K, H, W, camera

    from pallet6d.runtime.calibration import Calibration, save_calibration
    from pallet6d.runtime.floor import FloorPlane

    T = camera(height_m=0.5, pitch_deg=8.0)
    floor = FloorPlane(T[2, :3].copy(), float(T[2, 3]) + height_error_m)
    if height_error_m:   # written as text: a Calibration object refuses a disagreeing floor
        good = Calibration(serial, "2026-11-23", W, H, K, T, FloorPlane(T[2, :3].copy(), float(T[2, 3])))
        save_calibration(good, path)
        path.write_text(path.read_text().replace(f"d_m = {float(T[2, 3])!r}", f"d_m = {floor.d!r}"))
    else:
        save_calibration(Calibration(serial, "2026-11-23", W, H, K, T, floor), path)
    return path


def test_a_calibration_makes_the_vehicle_frame_the_default(tmp_path):
    _calibration(tmp_path / "cam.toml")
    cfg = load(tmp_path, '[output]\ncalibration = "cam.toml"\n')
    assert cfg.output.frame == "vehicle" and cfg.output.calibration == str(tmp_path / "cam.toml")
    assert cfg.output.loaded is not None and cfg.output.loaded.serial == "815412070123"
    assert cfg.floor_check.max_tilt_deg == 2.0 and cfg.floor_check.max_height_diff_m == 0.03
    assert cfg.floor_check.when_unseen == "ready"
    camera = load(tmp_path, '[output]\ncalibration = "cam.toml"\nframe = "camera"\n')
    assert camera.output.frame == "camera" and camera.output.loaded is not None
    cfg = load(tmp_path, '[output]\ncalibration = "cam.toml"\n[floor_check]\nmax_tilt_deg = 1\n'
                         'when_unseen = "not_ready"\n')
    assert cfg.floor_check.max_tilt_deg == 1.0 and cfg.floor_check.when_unseen == "not_ready"


@pytest.mark.parametrize("make, where", [
    (lambda p: p.write_text("format_version = 1\n"), "missing field 'intrinsics'"),
    (lambda p: p.write_text("[intrinsics\n"), "not a TOML calibration file"),
    (lambda p: _calibration(p, height_error_m=0.2), "the stored floor disagrees with T_vehicle_cam"),
    (lambda p: _calibration(p).write_text(p.read_text().replace("format_version = 1", "format_version = 7")),
     "format_version 7"),
])
def test_an_unusable_calibration_is_a_config_error(tmp_path, make, where):
    make(tmp_path / "cam.toml")
    with pytest.raises(ConfigError) as err:
        load(tmp_path, '[output]\ncalibration = "cam.toml"\n')
    assert "output.calibration" in str(err.value) and where in str(err.value), str(err.value)


def test_a_calibration_of_another_camera_is_refused(tmp_path):
    _calibration(tmp_path / "cam.toml", serial="111")
    with pytest.raises(ConfigError, match="output.calibration: is of camera '111', camera.source names '222'"):
        load(tmp_path, '[camera]\nsource = "realsense:222"\n[output]\ncalibration = "cam.toml"\n')
    assert load(tmp_path, '[camera]\nsource = "realsense:111"\n[output]\ncalibration = "cam.toml"\n').output.loaded
