"""`pallet6d serve`: the real daemon process on 127.0.0.1 with a generated replay, talked to over HTTP."""
from __future__ import annotations

import json
import shutil
import socket
import time

import cv2
import httpx
import numpy as np
import pytest

from serve_fixtures import Daemon, free_port, make_replay, write_config
from pallet6d.runtime.serve.schema import PalletsResponse, ReadyResponse


@pytest.fixture(scope="module")
def replay_dir(sim_bop_dataset, tmp_path_factory):
    return make_replay(sim_bop_dataset, tmp_path_factory.mktemp("replay") / "rec")


@pytest.fixture(scope="module")
def daemon(replay_dir, bundle_dir, tmp_path_factory):
    """A continuous-mode daemon, ready (results flowing)."""
    work = tmp_path_factory.mktemp("serve")
    port = free_port()
    d = Daemon(write_config(work / "serve.toml", f"replay:{replay_dir}", bundle_dir, port), port).wait_healthy()
    d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz")
    yield d
    assert d.stop() == 0, d.log()


def test_latest_result_health_and_metrics(daemon):
    c = daemon.client
    assert c.get("/healthz").json() == {"status": "ok"}
    ready = c.get("/readyz").json()
    assert ready["ready"] and all(ready["checks"].values()) and ready["camera_error"] is None
    assert ready["calibration"]["state"] == "not_configured" and ready["reasons"] == []
    first = c.get("/v1/pallets").json()
    ReadyResponse.model_validate(ready)      # what is sent is what the OpenAPI description says
    PalletsResponse.model_validate(first)
    assert {"seq", "frame", "capture_timestamp_s", "age_s", "latency_ms", "pallets", "rejected", "image_hw",
            "output_frame"} <= set(first)
    assert first["output_frame"] == "camera" and first["image_hw"] == [120, 320] and first["age_s"] >= 0
    assert "total" in first["latency_ms"] and "detector" in first["latency_ms"]
    daemon.wait(lambda: c.get("/v1/pallets").json()["seq"] > first["seq"], "a newer result")
    text = c.get("/metrics").text
    for name in ("pallet6d_frames_total", "pallet6d_stage_latency_seconds_bucket{", "pallet6d_camera_up 1.0",
                 'pallet6d_failures_total{reason="camera"}', "pallet6d_camera_reconnects_total",
                 "pallet6d_pallets_per_frame_bucket{"):
        assert name in text, name
    assert daemon.metric("pallet6d_frames_total") >= 2


def test_openapi_describes_the_endpoints(daemon):
    paths = daemon.client.get("/openapi.json").json()["paths"]
    for path in ("/v1/pallets", "/v1/detect", "/v1/stream", "/v1/overlay.jpg", "/v1/overlay.mjpg", "/healthz",
                 "/readyz", "/metrics", "/v1/snapshot"):
        assert path in paths, path


def test_stream_pushes_new_results_in_order(daemon):
    seqs = []
    with daemon.client.stream("GET", "/v1/stream", params={"max_events": 3}) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("data: "):
                seqs.append(json.loads(line[6:])["seq"])
    assert len(seqs) == 3 and seqs == sorted(set(seqs))


def test_overlay_jpeg_and_mjpeg_stream(daemon):
    r = daemon.client.get("/v1/overlay.jpg")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (120, 320, 3)
    r = daemon.client.get("/v1/overlay.mjpg", params={"max_frames": 2, "max_fps": 30})
    assert r.headers["content-type"].startswith("multipart/x-mixed-replace")
    parts = r.content.split(b"--pallet6d-frame\r\n")[1:]
    assert len(parts) == 2
    jpeg = parts[0].split(b"\r\n\r\n", 1)[1]
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (120, 320, 3)


def test_detect_with_and_without_a_region_hint(daemon):
    c = daemon.client
    everything = c.post("/v1/detect").json()
    assert everything["trigger"] == "detect" and everything["n_outside_hint"] == 0
    # a region off the image keeps nothing; one covering the whole image drops nothing
    off = c.post("/v1/detect", json={"box_xyxy": [5000, 5000, 5001, 5001]}).json()
    assert off["pallets"] == [] and off["n_outside_hint"] >= 0
    whole = c.post("/v1/detect", json={"box_xyxy": [-1, -1, 321, 121]}).json()
    assert whole["n_outside_hint"] == 0
    near = c.post("/v1/detect", json={"distance_m": 3.0, "tolerance_m": 0.5})
    assert near.status_code == 200 and all(abs(p["t_m"][2] - 3.0) <= 0.5 for p in near.json()["pallets"])


@pytest.mark.parametrize("body, status", [
    ({"box_xyxy": [10, 10, 5, 20]}, 422),           # x2 < x1
    ({"box_xyxy": [1, 2, 3]}, 422),
    ({"distance_m": -1}, 422),
    ({"distance_m": 1e9}, 422),
    ({"tolerance_m": 0}, 422),
    ({"unknown": 1}, 422),
    ("not json", 422),
    ('{"box_xyxy": [NaN, 0, 10, 10]}', 422),          # Python's JSON reads NaN; the answer must not carry it
    ('{"distance_m": Infinity}', 422),
])
def test_detect_rejects_invalid_bodies(daemon, body, status):
    if isinstance(body, str):
        r = daemon.client.post("/v1/detect", content=body, headers={"content-type": "application/json"})
    else:
        r = daemon.client.post("/v1/detect", json=body)
    assert r.status_code == status and "detail" in r.json()


def test_request_size_limits(daemon):
    big = b'{"frames": 1, "pad": "' + b"x" * 70000 + b'"}'
    r = daemon.client.post("/v1/snapshot", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413

    def chunks():
        yield big[:1000]
        yield big[1000:]
    r = daemon.client.post("/v1/detect", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert daemon.client.get("/v1/pallets", params={"q": "x" * 5000}).status_code == 414
    assert daemon.client.get("/v1/stream", params={"max_events": -1}).status_code == 422


def test_snapshot_is_a_replay_that_run_plays(daemon, bundle_dir, capsys):
    from pallet6d.runtime.cli import main

    r = daemon.client.post("/v1/snapshot", json={"frames": 2})
    assert r.status_code == 201, r.text
    snap = r.json()
    assert 1 <= snap["frames"] <= 2 and snap["source"] == f"replay:{snap['path']}"
    capsys.readouterr()
    assert main(["run", "--frame", "camera", "--source", snap["source"], "--bundle", str(bundle_dir), "--threads", "1"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    frames, summary = lines[:-1], lines[-1]          # one line per recorded frame, then the run's summary
    assert len(frames) == snap["frames"] and all("poses" in x for x in frames)
    assert summary["summary"]["frames"] == snap["frames"]


def test_a_client_that_never_reads_does_not_stall_the_loop(daemon):
    with socket.create_connection(("127.0.0.1", daemon.port)) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.sendall(b"GET /v1/overlay.mjpg?max_fps=30 HTTP/1.1\r\nHost: x\r\n\r\n")
        before = daemon.metric("pallet6d_frames_total")
        daemon.wait(lambda: daemon.metric("pallet6d_frames_total") >= before + 5, "frames while a client stalls")
        assert daemon.client.get("/v1/pallets").status_code == 200


def test_unplug_and_replug_recover_without_a_restart(replay_dir, bundle_dir, tmp_path):
    rec = tmp_path / "rec"
    shutil.copytree(replay_dir, rec)
    port = free_port()
    d = Daemon(write_config(tmp_path / "serve.toml", f"replay:{rec}", bundle_dir, port), port).wait_healthy()
    try:
        d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz")
        pid = d.proc.pid
        rec.rename(tmp_path / "unplugged")                 # the camera goes away
        # on a loaded machine the results may go stale first: wait for the camera check itself
        d.wait(lambda: d.client.get("/readyz").json()["checks"]["camera"] is False, "the camera check failing")
        r = d.client.get("/readyz")
        assert r.status_code == 503 and r.json()["camera_error"]
        assert d.client.post("/v1/detect").status_code == 503
        (tmp_path / "unplugged").rename(rec)               # and comes back
        d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz after replug")
        assert d.proc.pid == pid and d.proc.poll() is None
        assert d.metric("pallet6d_camera_reconnects_total") >= 1
        assert d.metric('pallet6d_failures_total{reason="camera"}') >= 1
    finally:
        # SIGTERM while a stream client is connected still stops cleanly
        with httpx.Client(base_url=d.url, timeout=30) as c, c.stream("GET", "/v1/stream") as r:
            assert r.status_code == 200
            t0 = time.monotonic()
            assert d.stop() == 0, d.log()
            assert time.monotonic() - t0 < 30


def test_triggered_mode_and_bearer_token(replay_dir, bundle_dir, tmp_path):
    token = "s3cret-token-for-tests-0123456789"
    (tmp_path / "token").write_text(token + "\n")
    port = free_port()
    cfg = write_config(tmp_path / "serve.toml", f"replay:{replay_dir}", bundle_dir, port, mode="triggered")
    cfg.write_text(cfg.read_text().replace("[api]\n", '[api]\ntoken_file = "token"\n'))
    d = Daemon(cfg, port).wait_healthy()
    auth = {"Authorization": f"Bearer {token}"}
    try:
        d.wait(lambda: d.client.get("/readyz").status_code == 200, "readyz")
        assert d.client.get("/v1/pallets").status_code == 401
        wrong = {"Authorization": "Bearer wrong-token-wrong-token"}
        assert d.client.get("/v1/pallets", headers=wrong).status_code == 401
        assert d.client.get("/metrics").status_code == 401
        assert d.client.get("/v1/pallets", headers=auth).status_code == 503   # nothing triggered yet
        assert d.metric("pallet6d_frames_total", auth) == 0                      # frames are not estimated
        r = d.client.post("/v1/detect", headers=auth)
        assert r.status_code == 200 and r.json()["trigger"] == "detect"
        latest = d.client.get("/v1/pallets", headers=auth).json()
        assert latest["seq"] == r.json()["seq"] and latest["trigger"] == "detect"
    finally:
        assert d.stop() == 0, d.log()


def test_refuses_a_public_address_without_a_token(replay_dir, bundle_dir, tmp_path, monkeypatch):
    import subprocess
    import sys

    monkeypatch.delenv("PALLET6D_API_TOKEN", raising=False)
    cfg = write_config(tmp_path / "serve.toml", f"replay:{replay_dir}", bundle_dir, free_port())
    cfg.write_text(cfg.read_text().replace("[api]\n", '[api]\nhost = "0.0.0.0"\n'))
    r = subprocess.run([sys.executable, "-m", "pallet6d.runtime.cli", "serve", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "bearer token" in r.stderr
