import json

import cv2
import pytest

from pallet6d.runtime.cli import main


@pytest.fixture(scope="module")
def bop_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("bop")
    assert main(["sim", "--preset", "virtual-clean", "--frames", "2", "--seed", "3", "--out", str(out)]) == 0
    return out


def test_run_on_bop_prints_json_lines_ground_truth_and_overlays(bundle_dir, bop_dir, tmp_path, capsys):
    rc = main(["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--threads", "1",
               "--frame", "camera", "--score-threshold", "0", "--min-fit", "0", "--no-structure-check", "--out", str(tmp_path / "ov"),
               "--max-frames", "2"])
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    frames, summary = lines[:-1], lines[-1]
    assert [f["frame"] for f in frames] == [0, 1]
    for f in frames:
        assert f["image_hw"] == [370, 1224] and "total" in f["timings_ms"] and len(f["poses"]) >= 1
        assert f["gt"] and all({"add_m", "add_sym_m", "detected"} <= set(g) for g in f["gt"])
    assert summary["summary"]["frames"] == 2 and summary["summary"]["n_gt"] == sum(len(f["gt"]) for f in frames)
    pngs = sorted((tmp_path / "ov").glob("*.png"))
    assert len(pngs) == 2 and cv2.imread(str(pngs[0])).shape == (370, 1224, 3)


def test_run_text_report_names_poses_errors_and_summary(bundle_dir, bop_dir, capsys):
    args = ["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--threads", "1",
            "--frame", "camera", "--score-threshold", "0", "--min-fit", "0", "--no-structure-check", "--max-frames", "1"]
    assert main(args) == 0
    frame = json.loads(capsys.readouterr().out.splitlines()[0])
    assert main(args + ["--format", "text"]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"frame 0: {len(frame['poses'])} pallet(s)")
    assert text.count("t_cam = (") == len(frame["poses"]) and text.count("ground truth at") == len(frame["gt"])
    assert "precision" in text and "ADD-sym" in text and "{" not in text


def test_run_with_a_missing_bundle_fails_clearly(tmp_path, capsys):
    rc = main(["run", "--source", f"bop:{tmp_path}", "--bundle", str(tmp_path / "nope"), "--frame", "camera"])
    assert rc == 2 and "cannot load bundle" in capsys.readouterr().err


@pytest.mark.parametrize("option, message", [
    (["--seed", "-1"], "invalid option: seed must be an integer >= 0, got -1"),
    (["--threads", "100000"], "invalid option: threads must be an integer in 1..64, got 100000"),
    (["--threads", "0"], "invalid option: threads must be an integer in 1..64, got 0"),
    (["--score-threshold", "2"], "invalid option: score_threshold must be in [0, 1], got 2.0"),
])
def test_run_refuses_a_bad_option_before_any_frame(bundle_dir, bop_dir, capsys, option, message):
    rc = main(["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--frame", "camera",
               *option])
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and err.strip().splitlines() == [f"pallet6d run: {message}"]


def _failing_estimate(monkeypatch, fail_frames):
    from pallet6d.runtime.estimator import PalletEstimator

    real = PalletEstimator.estimate

    def estimate(self, rgb, *args, **kwargs):
        if getattr(rgb, "frame_number", None) in fail_frames:
            raise RuntimeError("onnxruntime: simulated failure")
        return real(self, rgb, *args, **kwargs)

    monkeypatch.setattr(PalletEstimator, "estimate", estimate)


def test_one_failing_frame_is_reported_and_the_run_goes_on(bundle_dir, bop_dir, monkeypatch, capsys):
    _failing_estimate(monkeypatch, {0})
    rc = main(["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--threads", "1",
               "--frame", "camera", "--score-threshold", "0", "--min-fit", "0", "--no-structure-check"])
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert lines[0]["frame"] == 0 and "simulated failure" in lines[0]["error"] and "poses" not in lines[0]
    assert all(not g["detected"] for g in lines[0]["gt"])          # the failed frame's pallets count as missed
    assert lines[1]["frame"] == 1 and "poses" in lines[1]
    assert lines[-1]["summary"]["n_gt"] == len(lines[0]["gt"]) + len(lines[1]["gt"])


def test_failures_in_a_row_end_the_run(bundle_dir, bop_dir, monkeypatch, capsys):
    _failing_estimate(monkeypatch, {0, 1})
    rc = main(["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--threads", "1",
               "--frame", "camera", "--max-failures", "2"])
    out = capsys.readouterr()
    assert rc == 1 and "2 frames in a row failed" in out.err
    lines = [json.loads(x) for x in out.out.splitlines()]
    assert [x["frame"] for x in lines[:-1]] == [0, 1]
    assert lines[-1]["summary"]["errors"] == 2 and lines[-1]["summary"]["estimated"] == 0
    assert main(["run", "--source", f"bop:{bop_dir}", "--bundle", str(bundle_dir), "--max-failures", "0",
                 "--frame", "camera"]) == 2


def test_live_sources_go_through_latest_frame(monkeypatch):
    """A live camera is read by the newest-frame grabber: frames come out in order, the newest is never
    lost, and the camera is stopped at the end."""
    from camera_fixtures import K_SMALL, box_frame

    from pallet6d.runtime import cameras, run_cli

    class FakeLive(cameras.FrameSource):
        live = True

        def __init__(self):
            super().__init__("fake-live")
            self.frames = [box_frame(i) for i in range(5)]
            self.stopped = False

        def _start(self):
            self._K, self._depth_scale_m = K_SMALL, 0.001

        def _read(self):
            return self.frames.pop(0) if self.frames else None

        def _stop(self):
            self.stopped = True

    from pallet6d.runtime.cli_signals import StopSignals

    src = FakeLive()
    with src:
        got = [number for number, frame, error in run_cli._frames(src, StopSignals()) if error is None]
    assert got and got == sorted(got) and got[-1] == 104
    assert src.stopped


def test_ground_truths_from_bop_frame(bop_dir):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.evaluation import ground_truths_from_bop

    frame = BopDataset(bop_dir)[0]
    gts, skipped = ground_truths_from_bop(frame.gts)
    assert skipped == 0 and len(gts) == len(frame.gts)
    x, y, w, h = frame.gts[0].bbox_visib_xywh
    assert gts[0].box_visib_xyxy.tolist() == [x, y, x + w, y + h]


def test_an_unreadable_bop_file_is_an_error_line_and_the_run_goes_on(bundle_dir, bop_dir, tmp_path, capsys):
    """A damaged colour or depth file of a BOP dataset is that frame's error line, not the end of the run."""
    import shutil

    root = tmp_path / "bop"
    shutil.copytree(bop_dir, root)
    scene = next(p for p in root.rglob("rgb") if p.is_dir()).parent
    rgb = sorted((scene / "rgb").iterdir())[0]
    rgb.write_bytes(b"garbage")
    rc = main(["run", "--source", f"bop:{root}", "--bundle", str(bundle_dir), "--threads", "1",
               "--frame", "camera", "--score-threshold", "0", "--min-fit", "0", "--no-structure-check"])
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["frame"] for x in lines[:-1]] == [0, 1]
    assert "error" in lines[0] and rgb.name in lines[0]["error"] and "poses" in lines[1]
    assert lines[-1]["summary"]["frames"] == 2 and lines[-1]["summary"]["errors"] == 1
