"""RGBDFrame validation and source-spec parsing."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pallet6d.runtime.cameras import (CameraError, RGBDFrame, ReplaySource, SourceSpecError, open_source,
                                      parse_source_spec)
from camera_fixtures import K_SMALL, box_frame


def test_frame_depth_m_and_fields():
    f = box_frame(0)
    d = f.depth_m
    assert d.dtype == np.float32 and d.shape == (60, 80)
    assert d[25, 15] == pytest.approx(2.0)
    assert np.all(d[f.depth == 0] == 0)
    assert (f.height, f.width, f.frame_number) == (60, 80, 100)


def _good():
    return dict(rgb=np.zeros((4, 5, 3), np.uint8), depth=np.zeros((4, 5), np.uint16), K=K_SMALL,
                depth_scale_m=0.001, timestamp_s=0.0, frame_number=0)


@pytest.mark.parametrize("change, exc, words", [
    ({"rgb": np.zeros((4, 5), np.uint8)}, ValueError, "(H, W, 3)"),
    ({"rgb": np.zeros((4, 5, 3), np.float32)}, TypeError, "uint8"),
    ({"depth": np.zeros((4, 6), np.uint16)}, ValueError, "aligned"),
    ({"depth": np.zeros((4, 5), np.float32)}, TypeError, "uint16"),
    ({"K": np.eye(2)}, ValueError, "3x3"),
    ({"depth_scale_m": 0.0}, ValueError, "positive"),
    ({"depth_scale_m": float("nan")}, ValueError, "positive"),
    ({"timestamp_s": float("inf")}, ValueError, "finite"),
])
def test_frame_rejects_bad_fields(change, exc, words):
    with pytest.raises(exc, match=words.replace("(", r"\(").replace(")", r"\)")):
        RGBDFrame(**{**_good(), **change})


def test_from_depth_m_quantizes_and_blanks_invalid():
    depth_m = np.array([[1.2344, np.nan], [-1.0, 70.0]])
    K = np.array([[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]])   # a 2x2 image needs a focal length of a few pixels
    f = RGBDFrame.from_depth_m(np.zeros((2, 2, 3), np.uint8), depth_m, K, 0.0, 0)
    assert f.depth.tolist() == [[1234, 0], [0, 0]]  # 70 m does not fit in uint16 mm: no data


@pytest.mark.parametrize("spec, expected", [
    ("realsense", ("realsense", None)),
    ("realsense:123456789012", ("realsense", "123456789012")),
    ("RealSense:1234", ("realsense", "1234")),
    ("oakd", ("oakd", None)),
    ("oakd:14442C10D13EABCE00", ("oakd", "14442C10D13EABCE00")),
    ("bag:/data/a.bag", ("bag", "/data/a.bag")),
    ("replay:rec/run1", ("replay", "rec/run1")),
    ("bop:C:/data", ("bop", "C:/data")),  # only the first colon separates
])
def test_parse_source_spec(spec, expected):
    assert parse_source_spec(spec) == expected


@pytest.mark.parametrize("spec, words", [
    ("", "unknown source"),
    ("webcam", "unknown source"),
    ("kinect:1", "unknown source"),
    ("bag", "needs a FILE"),
    ("replay:", "needs a DIR"),
    ("bop:  ", "needs a DIR"),
    ("realsense:", "empty SERIAL"),
])
def test_parse_source_spec_rejects(spec, words):
    with pytest.raises(SourceSpecError, match=words):
        parse_source_spec(spec)
    with pytest.raises(ValueError):  # SourceSpecError is a ValueError for callers that catch that
        open_source(spec)


def test_parse_source_spec_type():
    with pytest.raises(TypeError):
        parse_source_spec(3)


def test_open_source_replay_is_lazy_and_typed(tmp_path):
    src = open_source(f"replay:{tmp_path}", loop=True)
    assert isinstance(src, ReplaySource) and not src.running
    with pytest.raises(CameraError, match="after start"):
        src.K


def test_import_pulls_no_camera_sdk():
    code = ("import sys, pallet6d.runtime.cameras as c; "
            "bad = [m for m in ('pyrealsense2', 'depthai', 'rosbags', 'torch') if m in sys.modules]; "
            "sys.exit(1 if bad else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0
