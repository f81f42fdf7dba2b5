"""Every input frame accounted for and no traceback: `pallet6d run` and `pallet6d record` on bad recordings,
bad --out, failed overlay writes, and SIGINT / SIGTERM (in a subprocess, on a slow endless fake source)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from pallet6d.runtime.cameras import ReplaySource, ReplayWriter
from pallet6d.runtime.cli import main

from camera_fixtures import box_frame

TESTS = Path(__file__).parent


@pytest.fixture
def replay_dir(tmp_path):
    out = tmp_path / "rec"
    with ReplayWriter(out) as w:
        for i in range(6):
            w.write(box_frame(i))
    return out


def _lines(text: str) -> list[dict]:
    return [json.loads(x) for x in text.splitlines()]


def _run(args, capsys):
    rc = main(["run", "--frame", "camera", *args])
    out = capsys.readouterr()
    return rc, _lines(out.out), out.err


def test_unreadable_replay_frames_get_error_lines_in_order(replay_dir, bundle_dir, capsys):
    (replay_dir / "depth" / "000001.png").unlink()                                      # missing
    p = replay_dir / "depth" / "000002.png"
    p.write_bytes(p.read_bytes()[:100])                                                  # truncated
    (replay_dir / "rgb" / "000003.png").write_bytes(b"garbage")                         # garbage
    cv2.imwrite(str(replay_dir / "depth" / "000004.png"), np.zeros((10, 10), np.uint16))  # another size
    rc, lines, _ = _run(["--source", f"replay:{replay_dir}", "--bundle", str(bundle_dir), "--threads", "1"], capsys)
    assert rc == 0
    assert [x["frame"] for x in lines[:-1]] == [100, 101, 102, 103, 104, 105]
    assert ["error" in x for x in lines[:-1]] == [False, True, True, True, True, False]
    assert lines[-1]["summary"] == {"frames": 6, "estimated": 2, "errors": 4,
                                    "poses": sum(len(x.get("poses", [])) for x in lines[:-1])}


def test_bad_camera_json_entries_are_frame_errors(replay_dir, bundle_dir, capsys):
    doc = json.loads((replay_dir / "camera.json").read_text())
    doc["frames"][1]["frame_number"] = None
    doc["frames"][2]["timestamp_s"] = "abc"
    doc["frames"][3]["rgb"] = "../../etc/passwd"
    doc["frames"][4] = 7
    (replay_dir / "camera.json").write_text(json.dumps(doc))
    rc, lines, err = _run(["--source", f"replay:{replay_dir}", "--bundle", str(bundle_dir), "--threads", "1"], capsys)
    assert rc == 0 and "Traceback" not in err
    assert [x["frame"] for x in lines[:-1]] == [100, 1, 102, 103, 4, 105]
    assert "frame_number" in lines[1]["error"] and "timestamp_s" in lines[2]["error"]
    assert "inside the recording" in lines[3]["error"] and "not an object" in lines[4]["error"]


def test_a_run_that_estimates_nothing_fails(replay_dir, bundle_dir, capsys):
    for p in (replay_dir / "depth").iterdir():
        p.write_bytes(b"x")
    rc, lines, err = _run(["--source", f"replay:{replay_dir}", "--bundle", str(bundle_dir)], capsys)
    assert rc == 1 and "no frame could be estimated" in err and len(lines) == 7
    rc, lines, err = _run(["--source", f"replay:{replay_dir}", "--bundle", str(bundle_dir), "--max-failures", "2"],
                          capsys)
    assert rc == 1 and "2 frames in a row failed" in err and [x["frame"] for x in lines[:-1]] == [100, 101]


def test_overlays_are_named_by_frame_number_and_write_failures_reported(replay_dir, bundle_dir, tmp_path, capsys,
                                                                        monkeypatch):
    (replay_dir / "depth" / "000001.png").unlink()
    ov = tmp_path / "ov"
    args = ["--source", f"replay:{replay_dir}", "--bundle", str(bundle_dir), "--threads", "1", "--out", str(ov),
            "--max-frames", "3"]
    rc, lines, _ = _run(args, capsys)
    assert rc == 0 and sorted(p.name for p in ov.iterdir()) == ["000100.png", "000102.png"]
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: False)
    rc, lines, _ = _run(args, capsys)
    assert rc == 0 and "cannot write overlay" in lines[0]["overlay_error"] and "poses" in lines[0]
    assert lines[-1]["summary"]["overlay_errors"] == 2


@pytest.mark.parametrize("out", ["file", "file/sub"])
def test_bad_out_is_one_line_and_status_2(replay_dir, bundle_dir, tmp_path, capsys, out):
    (tmp_path / "file").write_text("x")
    for cmd in (["run", "--bundle", str(bundle_dir)], ["record"]):
        rc = main([*cmd, "--source", f"replay:{replay_dir}", "--out", str(tmp_path / out)])
        err = capsys.readouterr().err
        assert rc == 2 and "--out" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args, status, message", [
    (["sim", "--frames", "1", "--seed", "-5", "--out", "{tmp}/s"], 2, "--seed >= 0"),
    (["sim", "--frames", "1", "--out", "{tmp}/file"], 2, "exists and is not a folder"),
    (["sim", "--frames", "1", "--size", "5000x5000", "--out", "{tmp}/s"], 2, "image must be at most 8.3 MP"),
    (["eval", "--bundle", "{bundle}", "--data", "{tmp}", "--json", "{tmp}"], 2, "is a folder; give a file name"),
    (["eval", "--bundle", "{bundle}", "--data", "{tmp}", "--max-frames", "-2"], 2, "--max-frames must be >= 0"),
    (["record", "--source", "replay:{rec}", "--out", "{tmp}/r", "--size", "0x0"], 2, "--size must be positive"),
    (["record", "--source", "replay:{rec}", "--out", "{tmp}/r", "--size", "big"], 2, "--size must look like"),
    (["record", "--source", "replay:{rec}", "--out", "{tmp}/r", "--fps", "-5"], 2, "--fps must be positive"),
    (["record", "--source", "replay:{rec}", "--out", "{rec}"], 2, "`pallet6d record --overwrite`"),
    (["calib", "floor", "--source", "replay:{tmp}/none", "--out", "{tmp}/c.toml"], 1, "does not exist"),
])
def test_other_commands_refuse_bad_options_in_one_line(replay_dir, bundle_dir, tmp_path, capsys, args, status,
                                                        message):
    (tmp_path / "file").write_text("x")
    fill = {"tmp": str(tmp_path), "bundle": str(bundle_dir), "rec": str(replay_dir)}
    rc = main([a.format(**fill) for a in args])
    err = [x for x in capsys.readouterr().err.splitlines() if x.startswith("pallet6d")]
    assert rc == status and len(err) == 1 and message in err[0], err


def test_an_unexpected_error_is_one_line_and_status_3(monkeypatch, capsys):
    from pallet6d.runtime import bundle_cli

    def boom(args):
        raise RuntimeError("onnxruntime: protobuf parsing failed")

    monkeypatch.setattr(bundle_cli, "main", boom)
    assert main(["bundle", "check", "x"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unexpected error: RuntimeError: onnxruntime" in err and "-v" in err


# A slow endless recording in a child process: the parent stops it with a signal.
_CHILD = r"""
import os, sys, time
sys.path.insert(0, {tests!r})
from camera_fixtures import K_SMALL, box_frame
from pallet6d.runtime import cameras
from pallet6d.runtime.cli import main

class Slow(cameras.FrameSource):
    def __init__(self, *a, **k):
        super().__init__("slow")
        self.i = 0
    def _start(self):
        os.write(1, b"[warning] a native library writes to stdout\n")   # as depthai does on import
        self._K, self._depth_scale_m = K_SMALL, 0.001
    def _read(self):
        time.sleep(0.02)
        self.i += 1
        return box_frame(self.i)
    def _stop(self):
        pass

cameras.open_source = lambda spec, **k: Slow()
sys.exit(main(sys.argv[1:]))
"""


def _start_child(args: list[str]) -> subprocess.Popen:
    code = _CHILD.format(tests=str(TESTS))
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _wait_for(cond, timeout_s: float = 60.0) -> None:
    t_end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < t_end, "timed out"
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_record_stops_on_a_signal_with_every_frame_on_disk_in_the_index(tmp_path, sig):
    out = tmp_path / "rec"
    child = _start_child(["record", "--source", "replay:x", "--out", str(out)])
    _wait_for(lambda: (out / "depth").is_dir() and len(os.listdir(out / "depth")) >= 40)  # past one index flush
    child.send_signal(sig)
    stdout, stderr = child.communicate(timeout=60)
    assert child.returncode == 0, stderr
    assert f"stopped by {signal.Signals(sig).name}" in stdout and "Traceback" not in stderr
    on_disk = sorted(p.name for p in (out / "depth").iterdir())
    listed = [Path(f["depth"]).name for f in json.loads((out / "camera.json").read_text())["frames"]]
    assert listed == on_disk and len(listed) >= 40
    assert not (out / "camera.json.tmp").exists()
    assert len(list(ReplaySource(out).start())) == len(listed)


def test_run_stops_on_sigterm_with_the_summary_and_only_json_on_stdout(bundle_dir):
    child = _start_child(["run", "--frame", "camera", "--source", "replay:x", "--bundle", str(bundle_dir), "--threads", "1"])
    first = child.stdout.readline()
    assert json.loads(first)["frame"] == 101   # box_frame(i) is frame 100 + i
    child.send_signal(signal.SIGTERM)
    stdout, stderr = child.communicate(timeout=60)
    lines = [json.loads(first)] + _lines(stdout)
    assert child.returncode == 0 and "Traceback" not in stderr
    assert "a native library writes to stdout" in stderr   # not in the JSON stream: every stdout line parsed
    summary = lines[-1]["summary"]
    assert summary["stopped_by"] == "SIGTERM" and summary["frames"] == len(lines) - 1
    assert [x["frame"] for x in lines[:-1]] == list(range(101, 100 + len(lines)))
