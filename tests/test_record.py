"""`pallet6d record`: bop -> replay round trip, bag output, errors."""
from __future__ import annotations

import numpy as np
import pytest

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.cameras import ReplaySource, open_source
from pallet6d.runtime.cli import main as cli_main


@pytest.fixture(scope="module")
def bop_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("bop")
    assert cli_main(["sim", "--preset", "virtual-occluded", "--frames", "3", "--seed", "11", "--size", "160x120",
                     "--out", str(root)]) == 0
    return root


def test_record_bop_to_replay_round_trip(bop_root, tmp_path, capsys):
    out = tmp_path / "rec"
    assert cli_main(["record", "--source", f"bop:{bop_root}", "--out", str(out)]) == 0
    assert "recorded 3 frames" in capsys.readouterr().out
    ds = BopDataset(bop_root)
    with ReplaySource(out) as rep:
        np.testing.assert_allclose(rep.K, ds[0].K)
        frames = list(rep)
    assert len(frames) == len(ds) == 3
    for i, f in enumerate(frames):
        ref = ds[i]
        np.testing.assert_array_equal(f.rgb, ref.rgb)
        np.testing.assert_allclose(f.depth_m, ref.depth_m, atol=1e-6)  # same stored units, no loss
        np.testing.assert_allclose(f.K, ref.K)
        assert f.frame_number == i
    assert rep.recorded_source == f"bop:{bop_root}"


def test_bop_source_matches_dataset(bop_root):
    ds = BopDataset(bop_root)
    with open_source(f"bop:{bop_root}", loop=True) as src:
        assert src.depth_scale_m == pytest.approx(ds[0].depth_scale_mm * 1e-3)
        frames = [src.read() for _ in range(4)]
    assert [f.frame_number for f in frames] == [0, 1, 2, 3]
    np.testing.assert_array_equal(frames[3].rgb, ds[0].rgb)  # looped


def test_record_frames_limit_and_jpeg(bop_root, tmp_path):
    out = tmp_path / "rec"
    assert cli_main(["record", "--source", f"bop:{bop_root}", "--out", str(out), "--frames", "2",
                     "--rgb-format", "jpg"]) == 0
    assert len(list(ReplaySource(out).start())) == 2
    # an existing recording is not overwritten by accident
    assert cli_main(["record", "--source", f"bop:{bop_root}", "--out", str(out)]) == 2
    assert cli_main(["record", "--source", f"bop:{bop_root}", "--out", str(out), "--overwrite"]) == 0
    assert len(list(ReplaySource(out).start())) == 3


def test_record_to_bag_plays_back(bop_root, tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("pyrealsense2")
    bag = tmp_path / "rec.bag"
    assert cli_main(["record", "--source", f"bop:{bop_root}", "--out", str(bag), "--format", "bag"]) == 0
    ds = BopDataset(bop_root)
    with open_source(f"bag:{bag}") as cam:
        np.testing.assert_allclose(cam.K, ds[0].K, rtol=1e-6)
        frames = list(cam)
    assert len(frames) == 3
    for f, i in zip(frames, range(3)):
        np.testing.assert_array_equal(f.rgb, ds[i].rgb)
        written = f.depth > 0  # identity extrinsics: rs.align writes (almost) every value where it was
        assert np.mean(np.abs(f.depth_m[written] - ds[i].depth_m[written]) < 1e-6) >= 0.95  # rest: a neighbour


@pytest.mark.parametrize("argv, code, words", [
    (["--source", "webcam", "--out", "x"], 2, "unknown source"),
    (["--source", "replay:/nonexistent/pallet6d", "--out", "x"], 1, "does not exist"),
    (["--source", "bop:/tmp", "--out", "x", "--frames", "0"], 2, "must be positive"),
])
def test_record_errors(argv, code, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["record", *argv]) == code
    assert words in capsys.readouterr().err
