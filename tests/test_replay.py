"""Replay folder: writer/reader round trip, corrupt files, looping, pacing."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pallet6d.runtime.cameras import (CameraError, CameraNotFound, FrameReadError, ReplaySource, ReplayWriter,
                                      open_source)
from camera_fixtures import K_SMALL, box_frame


def _record(tmp_path, n=4, **kw):
    out = tmp_path / "rec"
    with ReplayWriter(out, **kw) as w:
        for i in range(n):
            w.write(box_frame(i))
    return out


def test_round_trip_png_is_exact(tmp_path):
    out = _record(tmp_path)
    with open_source(f"replay:{out}") as src:
        np.testing.assert_array_equal(src.K, K_SMALL)  # before the first frame
        assert src.depth_scale_m == 0.001 and len(src) == 4
        frames = list(src)
    assert len(frames) == 4
    for i, f in enumerate(frames):
        ref = box_frame(i)
        np.testing.assert_array_equal(f.rgb, ref.rgb)
        np.testing.assert_array_equal(f.depth, ref.depth)
        np.testing.assert_array_equal(f.K, ref.K)
        assert f.timestamp_s == ref.timestamp_s and f.frame_number == ref.frame_number
        assert f.source == f"replay:{out}"
    assert src.recorded_source == "test"


def test_round_trip_jpeg_depth_exact_rgb_close(tmp_path):
    out = _record(tmp_path, n=2, rgb_format="jpg", jpeg_quality=95)
    frames = list(ReplaySource(out).start())
    assert sorted(p.suffix for p in (out / "rgb").iterdir()) == [".jpg", ".jpg"]
    np.testing.assert_array_equal(frames[1].depth, box_frame(1).depth)
    # the flat pallet face survives JPEG almost unchanged
    assert np.abs(frames[1].rgb[25:35, 20:30].astype(int) - (200, 150, 60)).max() < 12


def test_writer_refuses_changing_camera(tmp_path):
    with ReplayWriter(tmp_path / "r") as w:
        w.write(box_frame(0))
        f = box_frame(1)
        K2 = K_SMALL.copy()
        K2[0, 0] = 70
        with pytest.raises(ValueError, match="changes image size, K or depth scale"):
            w.write(type(f)(f.rgb, f.depth, K2, f.depth_scale_m, f.timestamp_s, f.frame_number))
    with pytest.raises(FileExistsError):
        ReplayWriter(tmp_path / "r")


def test_flush_makes_partial_recording_playable(tmp_path):
    w = ReplayWriter(tmp_path / "r", flush_every=2)
    for i in range(3):
        w.write(box_frame(i))
    # no close(): as after a crash, the index holds the frames up to the last flush
    assert len(list(ReplaySource(tmp_path / "r").start())) == 2


def _damage(out, how):
    target = out / "depth" / "000001.png"
    if how == "missing":
        target.unlink()
    elif how == "truncated":
        target.write_bytes(target.read_bytes()[:60])
    elif how == "garbage":
        target.write_bytes(b"\x89PNG not really")
    elif how == "empty":
        target.write_bytes(b"")
    elif how == "rgb_as_depth":  # 8-bit 3-channel image where 16-bit depth belongs
        target.write_bytes((out / "rgb" / "000001.png").read_bytes())


@pytest.mark.parametrize("how", ["missing", "truncated", "garbage", "empty", "rgb_as_depth"])
def test_damaged_frame_skipped_with_warning(tmp_path, caplog, how):
    out = _record(tmp_path)
    _damage(out, how)
    src = ReplaySource(out, on_error="skip")
    with caplog.at_level(logging.WARNING), src:
        numbers = [f.frame_number for f in src]
    assert numbers == [100, 102, 103]
    assert src.skipped == 1
    assert any("skipping frame 1" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("how", ["missing", "truncated", "garbage", "rgb_as_depth"])
def test_damaged_frame_raises_in_raise_mode(tmp_path, how):
    out = _record(tmp_path)
    _damage(out, how)
    with ReplaySource(out, on_error="raise") as src:
        assert src.read().frame_number == 100
        with pytest.raises(FrameReadError, match="000001.png"):
            src.read()
        assert src.read().frame_number == 102  # the stream goes on if the caller wants it to


def test_truncated_rgb_png(tmp_path):
    out = _record(tmp_path)
    p = out / "rgb" / "000002.png"
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(FrameReadError):
        list(ReplaySource(out, on_error="raise").start())
    assert [f.frame_number for f in ReplaySource(out).start()] == [100, 101, 103]


@pytest.mark.parametrize("content, exc, words", [
    (None, CameraNotFound, "no camera.json"),
    ("{not json", CameraError, "cannot read"),
    (json.dumps({"format": "other"}), CameraError, "not a pallet6d-replay"),
    (json.dumps({"format": "pallet6d-replay", "version": 99}), CameraError, "unsupported replay version"),
    (json.dumps({"format": "pallet6d-replay", "version": 1, "K": [[60, 0, 32], [0, 60, 24], [0, 0, 1]],
                 "width": 64, "height": 48, "depth_scale_m": 0.001}), CameraError, "missing 'frames'"),
    (json.dumps({"format": "pallet6d-replay", "version": 1, "K": [[0, 0, 0], [0, 1, 0], [0, 0, 1]],
                 "width": 64, "height": 48, "depth_scale_m": 0.001, "frames": []}), CameraError, "focal"),
    (json.dumps({"format": "pallet6d-replay", "version": 1, "K": [[60, 0, 0], [0, 60, 0], [32, 24, 1]],
                 "width": 64, "height": 48, "depth_scale_m": 0.001, "frames": []}), CameraError, "transposed"),
    (json.dumps({"format": "pallet6d-replay", "version": 1, "K": [[60, 0, 32], [0, 60, 24], [0, 0, 1]],
                 "width": 8000, "height": 6000, "depth_scale_m": 0.001, "frames": []}), CameraError, "too large"),
    (json.dumps({"format": "pallet6d-replay", "version": 1, "K": [[60, 0, 32], [0, 60, 24], [0, 0, 1]],
                 "width": 64, "height": 48, "depth_scale_m": "abc", "frames": []}), CameraError, "depth_scale_m"),
])
def test_bad_index(tmp_path, content, exc, words):
    if content is not None:
        (tmp_path / "camera.json").write_text(content)
    with pytest.raises(exc, match=words):
        ReplaySource(tmp_path).start()


def test_missing_folder():
    with pytest.raises(CameraNotFound, match="does not exist"):
        open_source("replay:/nonexistent/pallet6d").start()


def test_loop_keeps_numbers_and_time_increasing(tmp_path):
    out = _record(tmp_path, n=3)
    with ReplaySource(out, loop=True) as src:
        frames = [src.read() for _ in range(7)]
    numbers = [f.frame_number for f in frames]
    times = [f.timestamp_s for f in frames]
    assert numbers == [100, 101, 102, 203, 204, 205, 306]
    assert all(b > a for a, b in zip(times, times[1:]))
    np.testing.assert_array_equal(frames[3].depth, frames[0].depth)


def test_loop_with_nothing_readable_raises(tmp_path):
    out = _record(tmp_path, n=2)
    for p in (out / "depth").iterdir():
        p.write_bytes(b"")
    with ReplaySource(out, loop=True) as src, pytest.raises(FrameReadError, match="no readable frame"):
        src.read()


def test_realtime_pacing_uses_recorded_timestamps(tmp_path):
    out = _record(tmp_path, n=3)  # timestamps 1/30 s apart
    now = [100.0]
    sleeps = []

    def sleep(dt):
        sleeps.append(dt)
        now[0] += dt

    with ReplaySource(out, realtime=True, speed=2.0, _clock=lambda: now[0], _sleep=sleep) as src:
        list(src)
    assert sleeps == pytest.approx([1 / 60, 1 / 60])


def test_bad_options(tmp_path):
    with pytest.raises(ValueError, match="on_error"):
        ReplaySource(tmp_path, on_error="ignore")
    with pytest.raises(ValueError, match="speed"):
        ReplaySource(tmp_path, speed=0)
    with pytest.raises(CameraError, match="before start"):
        ReplaySource(tmp_path).read()
