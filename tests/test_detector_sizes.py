"""One detector for every camera aspect: the manifest's `detector.input_sizes`, the detector stage choosing the
input size per frame, and the export of a detector graph that takes several sizes (fp32 and int8)."""
import json
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime import cli
from pallet6d.runtime.bundle import BundleError, check_bundle, load_bundle
from pallet6d.runtime.detector import decode_yolov8, letterbox, to_nchw, undo_letterbox
from pallet6d.runtime.manifest import Manifest, read_manifest
from pallet6d.runtime.sessions import OnnxModel
from pallet6d.runtime.stage_detector import DetectorStage

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"
SIZES = ((64, 128), (96, 96))          # the tiny config's reference size, and a squarer one of about its pixels


def _manifest_v2() -> dict:
    """The shipped bundle's manifest as a format_version 2 dict, its detector at one input, 192x640."""
    m, _ = read_manifest(json.loads((SHIPPED / "manifest.json").read_text()))
    d = m.to_dict()
    d["detector"].pop("input_sizes", None)
    d["detector"]["input_hw"] = [192, 640]
    return d


@pytest.fixture(scope="module")
def single(tmp_path_factory, one_torch_thread):
    """A tiny bundle whose detector graph is static at one input, 64x128."""
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config

    cfg = get_config("tiny")
    calib = make_calibration_set(cfg, frames=2, max_crops=4, seed=0, synthetic=True)
    return export_bundle(cfg, tmp_path_factory.mktemp("b") / "single", random_init=True, int8=True, calib=calib)


# -- the manifest -------------------------------------------------------------------------------------------

def test_manifest_without_input_sizes_takes_input_hw_alone_and_writes_no_field():
    d = _manifest_v2()
    assert "input_sizes" not in d["detector"]
    m = Manifest.from_dict(d)
    assert m.detector.input_sizes == ((192, 640),) and not m.detector.multi_size
    assert "input_sizes" not in m.to_dict()["detector"]
    d["detector"]["input_sizes"] = [[192, 640]]        # the default spelled out reads the same
    assert Manifest.from_dict(d).to_dict() == m.to_dict()


def test_manifest_input_sizes_round_trip():
    d = _manifest_v2()
    d["detector"]["input_sizes"] = [[256, 480], [192, 640], [224, 544]]
    m = Manifest.from_dict(d)
    assert m.detector.input_sizes == ((256, 480), (192, 640), (224, 544)) and m.detector.multi_size
    assert m.detector.input_hw == (192, 640)
    written = m.to_dict()
    assert written["detector"]["input_sizes"] == [[256, 480], [192, 640], [224, 544]]
    assert Manifest.from_dict(written) == m


@pytest.mark.parametrize("sizes, message", [
    ([[192, 640], [250, 480]], r"'detector.input_sizes\[1\]' must be positive multiples of 32"),
    ([[192, 640], [0, 480]], r"'detector.input_sizes\[1\]' must be positive multiples of 32"),
    ([[256, 480]], r"'detector.input_hw' \[192, 640\] must be one of input_sizes \[\[256, 480\]\]"),
    ([], r"'detector.input_sizes' must list at least one \[H, W\]"),
    ([[192, 640], [256, 480], [256, 480]], r"'detector.input_sizes' lists \[256, 480\] twice"),
    ([192, 640], r"'detector.input_sizes' must be a list of lists of 2 integers"),
    ([[192, 640, 3]], r"'detector.input_sizes' must be a list of lists of 2 integers"),
    ([[192.0, 640]], r"'detector.input_sizes' must be a list of lists of 2 integers"),
    ("192x640", r"'detector.input_sizes' must be a list"),
])
def test_manifest_refuses_bad_input_sizes(sizes, message):
    d = _manifest_v2()
    d["detector"]["input_sizes"] = sizes
    with pytest.raises(BundleError, match=message):
        Manifest.from_dict(d)


def test_single_size_bundle_letterboxes_every_frame_to_input_hw(single):
    stage = DetectorStage(single.bundle, "fp32", 1, (0,), 0.5, 0.5, 10)
    for hw in ((480, 640), (370, 1224), (400, 640)):
        x, lb = stage.preprocess(np.zeros((*hw, 3), np.uint8))
        assert x.shape == (1, 3, 64, 128) and lb.input_hw == (64, 128)


# -- a tiny bundle whose detector takes two sizes ---------------------------------------------------------

@pytest.fixture(scope="module")
def multi(tmp_path_factory, one_torch_thread):
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config

    cfg = get_config("tiny")
    calib = make_calibration_set(cfg, frames=4, max_crops=8, seed=0, synthetic=True, detector_sizes=SIZES)
    return export_bundle(cfg, tmp_path_factory.mktemp("b") / "multi", random_init=True, int8=True, calib=calib,
                         detector_input_sizes=SIZES)


def test_multi_size_export_passes_bundle_check(multi):
    m = multi.manifest
    assert m.detector.input_sizes == SIZES and m.detector.input_hw == SIZES[0]
    assert json.loads((multi.root / "manifest.json").read_text())["detector"]["input_sizes"] == [[64, 128], [96, 96]]
    assert check_bundle(multi.root) == []
    assert cli.main(["bundle", "check", str(multi.root)]) == 0
    for precision in ("fp32", "int8"):         # height and width are dynamic: one graph for every size
        shape = OnnxModel(multi.bundle.graph("detector", precision), 1).input_shape(m.detector.input_name)
        assert shape[:2] == [1, 3] and not any(isinstance(v, int) for v in shape[2:]), (precision, shape)
    checks = multi.report["checks"]
    for name in ("64x128", "96x96"):           # torch-vs-onnx parity and int8-vs-fp32 at every size
        par = checks["parity"]["detector"][name]["output0"]
        assert par["max_abs"] <= 1e-4 * max(1.0, par["ref_max_abs"])
        assert checks["int8"]["detector_by_size"][name]["output0"]["corr"] > 0.99
        assert checks["gflops"][f"detector_per_frame_{name}"] > 0


def test_a_static_graph_that_misses_a_listed_size_is_refused(single, tmp_path):
    """A detector graph static at 64x128: a manifest that lists 96x96 too is refused by `bundle check` (at that
    size) and by the estimator."""
    import shutil

    from pallet6d.runtime.estimator import PalletEstimator

    root = tmp_path / "b"
    shutil.copytree(single.root, root)
    d = json.loads((root / "manifest.json").read_text())
    d["detector"]["input_sizes"] = [[64, 128], [96, 96]]
    (root / "manifest.json").write_text(json.dumps(d))
    problems = check_bundle(root)
    assert len(problems) == 2 and all("at 96x96" in p for p in problems), problems   # fp32 and int8
    with pytest.raises(BundleError, match=r"detector.input_sizes\[1\]\[0\] is 96"):
        PalletEstimator.from_bundle(root, threads=1)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_stage_letterboxes_each_frame_to_the_size_that_fits_it(multi, precision):
    stage = DetectorStage(multi.bundle, precision, 1, (0,), 0.0, 0.5, 20)
    rng = np.random.default_rng(0)
    inputs = {}
    for image_hw, input_hw in (((480, 640), (96, 96)), ((370, 1224), (64, 128))):
        rgb = rng.integers(0, 255, (*image_hw, 3), dtype=np.uint8)
        x, lb = stage.preprocess(rgb)
        assert x.shape == (1, 3, *input_hw) and lb.input_hw == input_hw and lb.image_hw == image_hw
        inputs[input_hw] = x
        det = stage.postprocess(stage.infer(x), lb)
        assert len(det) > 0
        # the same graph run by hand on the frame letterboxed at that size, boxes mapped back to the image
        img, lb_ref = letterbox(rgb, input_hw, 114)
        raw = OnnxModel(multi.bundle.graph("detector", precision), 1).session.run(None, {
            "images": to_nchw(img, (0, 0, 0), (1, 1, 1), 1 / 255)})[0]
        ref = decode_yolov8(raw, 0.0, 0.5, (0,), 20)
        np.testing.assert_allclose(det.boxes_xyxy, undo_letterbox(ref.boxes_xyxy, lb_ref))
        assert np.all(det.boxes_xyxy >= 0) and np.all(det.boxes_xyxy[:, [0, 2]] <= image_hw[1]) \
            and np.all(det.boxes_xyxy[:, [1, 3]] <= image_hw[0])
    # a camera of fixed size reuses its input buffer; each size has its own
    x_again, _ = stage.preprocess(np.zeros((480, 640, 3), np.uint8))
    assert x_again is inputs[(96, 96)] and inputs[(96, 96)] is not inputs[(64, 128)]


@pytest.mark.parametrize("image_hw, box_image, box_input", [
    # 640x480 -> 96x96: scale 0.15 both ways, the image 96x72 at pad (0, 12)
    ((480, 640), [100.0, 200.0, 300.0, 400.0], [15.0, 42.0, 45.0, 72.0]),
    # 1224x370 -> 64x128: 128x39 at pad (0, 12), scales 128/1224 and 39/370
    ((370, 1224), [306.0, 37.0, 918.0, 333.0], [32.0, 12 + 37 * 39 / 370, 96.0, 12 + 333 * 39 / 370]),
])
def test_stage_boxes_come_back_in_image_pixels(multi, image_hw, box_image, box_input):
    """A detection at known detector-input pixels of the chosen size comes back at the image pixels it covers."""
    stage = DetectorStage(multi.bundle, "fp32", 1, (0,), 0.5, 0.5, 20)
    x, lb = stage.preprocess(np.zeros((*image_hw, 3), np.uint8))
    raw = np.zeros((1, 4 + multi.manifest.detector.num_classes, 10), np.float32)
    x1, y1, x2, y2 = box_input
    raw[0, :4, 3] = [(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1]
    raw[0, 4, 3] = 0.9
    det = stage.postprocess(raw, lb)
    np.testing.assert_allclose(det.boxes_xyxy, [box_image], atol=1e-6)


# -- export choices ---------------------------------------------------------------------------------------

def test_export_takes_the_sizes_the_checkpoint_was_trained_on(multi, single, tmp_path):
    import torch

    from pallet6d.export.bundle_export import build_networks, export_bundle
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config
    from pallet6d.export.export_inputs import ExportError, trained_input_sizes

    cfg = get_config("tiny")
    nets = build_networks(cfg, random_init=True, calib=make_calibration_set(
        cfg, frames=2, max_crops=4, seed=0, synthetic=True, detector_sizes=SIZES), detector_input_sizes=SIZES).nets
    prov = {"stage": "detector", "input_hw": [96, 96], "input_sizes": [[64, 128], [96, 96]]}
    ckpt = {"config": "tiny", "provenance": prov, **{k: v.state_dict() for k, v in nets.items()}}
    torch.save(ckpt, tmp_path / "ckpt.pt")
    assert trained_input_sizes(ckpt) == SIZES
    assert trained_input_sizes({"provenance": {"detector": prov}}) == SIZES     # a merged checkpoint
    assert trained_input_sizes({"provenance": {"stage": "detector", "input_hw": [64, 128]}}) is None
    calib = make_calibration_set(cfg, frames=2, max_crops=4, seed=0, synthetic=True, detector_sizes=SIZES)
    b = export_bundle(cfg, tmp_path / "b", checkpoint=tmp_path / "ckpt.pt", calib=calib).bundle
    assert b.detector.input_sizes == SIZES and b.detector.input_hw == (96, 96)   # the trained reference size
    with pytest.raises(ExportError, match="multiples of 32"):
        export_bundle(cfg, tmp_path / "c", random_init=True, detector_input_sizes=((64, 128), (100, 96)))
    with pytest.raises(ExportError, match="takes one input size"):
        export_bundle(cfg, tmp_path / "e", random_init=True, detector_onnx=single.root / "detector.onnx",
                      classes=("epal",), detector_input_sizes=((64, 128), (96, 96)))


def test_calibration_set_made_for_one_size_letterboxes_its_inputs_to_another(caplog):
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config

    cfg = get_config("tiny")
    both = make_calibration_set(cfg, frames=2, max_crops=4, seed=0, detector_sizes=SIZES)
    assert both.images_at((96, 96)).shape == (2, 3, 96, 96) and both.images_at((64, 128)) is both.images
    # each size letterboxes the frame itself: the sim's frames are wider than 96x96, so grey bands above and below
    assert np.all(both.images_at((96, 96))[:, :, 0] == np.float32(114 / 255))
    one = make_calibration_set(cfg, frames=2, max_crops=4, seed=0)
    with caplog.at_level("WARNING"):
        again = one.images_at((96, 96))
    assert again.shape == (2, 3, 96, 96) and "no detector inputs at 96x96" in caplog.text
    assert np.abs(again - both.images_at((96, 96))).mean() < 0.05     # the same frames, resampled twice


def test_export_cli_parses_input_sizes(capsys):
    from pallet6d.export.cli import _sizes

    assert _sizes("192x640,256x480") == ((192, 640), (256, 480))
    with pytest.raises(SystemExit):
        cli.main(["export", "--config", "tiny", "--random-init", "--detector-input-sizes", "192x640,256", "--out",
                  "unused"])
    assert "expected HxW" in capsys.readouterr().err


def test_weights_read_back_from_a_multi_size_bundle_keep_its_sizes(multi):
    """Training can start from a multi-size bundle (`--init`, `train merge`): its detector graph gives the weights
    back, and the checkpoint records the sizes, so a re-export takes them again."""
    from pallet6d.export.bundle_weights import bundle_checkpoint
    from pallet6d.export.export_inputs import trained_input_sizes

    ckpt = bundle_checkpoint(multi.root, "detector")
    assert ckpt["provenance"]["input_sizes"] == [[64, 128], [96, 96]] and trained_input_sizes(ckpt) == SIZES
    assert ckpt["provenance"]["read_back_from_bundle"]["parity"]["detector"]
