"""Bundle contract: load_bundle / check_bundle / `pallet6d bundle check` on good and broken bundles."""
import json
import shutil

import numpy as np
import pytest

from pallet6d.runtime import cli
from pallet6d.runtime.bundle import BundleError, check_bundle, load_bundle, sha256_file


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: one thread is faster, and far faster on a busy 2-core machine (no spin-waiting)."""
    torch_ = pytest.importorskip("torch")
    n = torch_.get_num_threads()
    torch_.set_num_threads(1)
    yield
    torch_.set_num_threads(n)


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config

    cfg = get_config("tiny")
    out = tmp_path_factory.mktemp("bundles") / "good"
    export_bundle(cfg, out, seed=0, random_init=True,
                  calib=make_calibration_set(cfg, frames=2, max_crops=8, seed=0, synthetic=True))
    return out


@pytest.fixture
def bundle(good, tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(good, dst)
    return dst


def edit_manifest(path, fn):
    m = json.loads((path / "manifest.json").read_text())
    fn(m)
    (path / "manifest.json").write_text(json.dumps(m))


def test_good_bundle_loads_with_typed_sections(good):
    b = load_bundle(good)
    assert check_bundle(good) == []
    assert b.classes == ("pallet",) and b.precision == ("fp32",)
    assert b.detector.input_hw == (64, 128) and b.detector.layout == "yolov8" and b.graph("detector").is_absolute()
    assert b.fusion.crop_hw == (32, 32) and b.fusion.feature_dim == 16
    spec = b.pose_input_spec()
    assert spec.num_points == b.pose.num_points == 32 and spec.crop_hw == (32, 32)
    assert b.pallet.symmetries.shape == (2, 4, 4) and b.pallet.points().shape == (2000, 3)
    np.testing.assert_allclose(b.pallet.size_m, (1.2, 0.8, 0.144), atol=1e-9)
    with pytest.raises(BundleError, match="no int8 fusion graph"):
        b.graph("fusion", "int8")
    with pytest.raises(ValueError, match="precision"):
        b.graph("fusion", "fp16")


def test_missing_file(bundle):
    (bundle / "pose.onnx").unlink()
    with pytest.raises(BundleError, match=r"pose\.file.*'pose\.onnx'.*not in the bundle"):
        load_bundle(bundle)
    problems = check_bundle(bundle)
    assert len(problems) == 1 and "pose.onnx" in problems[0]


def test_wrong_sha256(bundle):
    with open(bundle / "fusion.onnx", "ab") as fh:
        fh.write(b"\x28\x01")   # a well-formed protobuf field (model_version = 1): still an ONNX model
    with pytest.raises(BundleError, match=r"sha256 of 'fusion\.onnx'.*changed or damaged"):
        load_bundle(bundle)
    load_bundle(bundle, verify_sha256=False)  # explicitly skipped


def test_wrong_input_shape_named(bundle):
    edit_manifest(bundle, lambda m: m["fusion"].__setitem__("crop_hw", [40, 40]))
    problems = check_bundle(bundle)
    assert any("fusion (fusion.onnx): input 'rgb' has shape" in p and "40" in p for p in problems), problems
    assert any("pose" not in p for p in problems)


def test_wrong_points_and_names(bundle):
    edit_manifest(bundle, lambda m: (m["pose"].__setitem__("num_points", 64),
                                     m["detector"].__setitem__("output_name", "boxes")))
    problems = check_bundle(bundle)
    assert any("detector (detector.onnx): has no output named 'boxes'" in p for p in problems), problems
    assert any("pose (pose.onnx): input 'points' has shape" in p for p in problems), problems


def test_swapped_graph_is_caught(bundle):
    shutil.copyfile(bundle / "fusion.onnx", bundle / "pose.onnx")
    edit_manifest(bundle, lambda m: m["files"].__setitem__("pose.onnx", sha256_file(bundle / "pose.onnx")))
    problems = check_bundle(bundle)
    assert any("pose (pose.onnx): has no input named 'points'" in p for p in problems), problems


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.__setitem__("format_version", 3), "format_version 3 is not supported"),
    (lambda m: m.__setitem__("format", "other"), "field 'format' must be"),
    (lambda m: m["detector"].pop("input_hw"), "'detector.input_hw' is missing"),
    (lambda m: m["detector"].__setitem__("input_hw", [100, 640]), "multiples of 32"),
    (lambda m: m["detector"].__setitem__("num_classes", 2), "'detector.num_classes' is 2 but 'classes' names 1"),
    (lambda m: m["pose"].__setitem__("quaternion_order", "xyzw"), "'pose.quaternion_order' must be 'wxyz'"),
    (lambda m: m["pallet_model"].__setitem__("symmetries", [[[2]]]), "symmetries"),
    (lambda m: m["pallet_model"].__setitem__("boxes_m", [[0, 0, 0]]), "'pallet_types\\[0\\].boxes_m' must be \\(k, 2, 3\\)"),
    (lambda m: m["pallet_model"].__setitem__("boxes_m", [[[0, 0, 0], [1, -1, 1]]]), "max > min"),
    (lambda m: m["files"].pop("pose.onnx"), "lacks the sha256 of 'pose.onnx'"),
    (lambda m: m["fusion"].__setitem__("file", "../outside.onnx"), "relative file name inside the bundle folder"),
    (lambda m: m.__setitem__("precision", ["fp32", "int8"]), "not every graph has a file_int8"),
    (lambda m: m["fusion"]["depth_encoding"].__setitem__("clip_m", "1"), "'fusion.depth_encoding.clip_m' must be"),
])
def test_manifest_errors_name_the_field(bundle, edit, message):
    edit_manifest(bundle, edit)
    with pytest.raises(BundleError, match=message):
        load_bundle(bundle)


def test_not_a_bundle(tmp_path):
    with pytest.raises(BundleError, match="not a folder"):
        load_bundle(tmp_path / "nope")
    with pytest.raises(BundleError, match="has no manifest.json"):
        load_bundle(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(BundleError, match="not valid JSON"):
        load_bundle(tmp_path)


def test_bundle_check_cli(good, bundle, capsys):
    assert cli.main(["bundle", "check", str(good)]) == 0
    assert "OK" in capsys.readouterr().out
    (bundle / "detector.onnx").write_bytes(b"garbage")
    edit_manifest(bundle, lambda m: m["files"].__setitem__("detector.onnx", sha256_file(bundle / "detector.onnx")))
    assert cli.main(["bundle", "check", str(bundle)]) == 1
    err = capsys.readouterr().err
    assert "detector graph 'detector.onnx': not a valid ONNX model" in err
    assert cli.main(["bundle", "info", str(good)]) == 0
    assert json.loads(capsys.readouterr().out)["num_points"] == 32


def test_boxes_are_optional_and_refinement_follows_them(good, bundle, caplog):
    from pallet6d.runtime.estimator import PalletEstimator

    assert load_bundle(good).pallet.boxes_m.shape[1:] == (2, 3)
    assert PalletEstimator.from_bundle(good, threads=1).refines
    edit_manifest(bundle, lambda m: m["pallet_model"].pop("boxes_m"))
    assert load_bundle(bundle).pallet.boxes_m is None
    with caplog.at_level("WARNING"):
        est = PalletEstimator.from_bundle(bundle, threads=1)
    assert not est.refines and "no pallet boxes_m" in caplog.text
    assert not PalletEstimator.from_bundle(good, threads=1, refine=False).refines
