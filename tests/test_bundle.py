"""Bundle contract: one validation shared by load_bundle and check_bundle (`pallet6d bundle check`), on good
bundles (format 2 with several pallet types, the shipped format 1 bundle) and on broken ones."""
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime import cli
from pallet6d.runtime.bundle import (REPORT, BundleError, Manifest, check_bundle, load_bundle, sha256_file,
                                     update_report)
from pallet6d.runtime.refine import MAX_STARTS, start_offsets

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: one thread is faster, and far faster on a busy 2-core machine (no spin-waiting)."""
    torch_ = pytest.importorskip("torch")
    n = torch_.get_num_threads()
    torch_.set_num_threads(1)
    yield
    torch_.set_num_threads(n)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A random-init tiny bundle with two pallet types (EPAL and the GMA stringer pallet)."""
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config

    cfg = get_config("tiny")
    out = tmp_path_factory.mktemp("bundles") / "good"
    return export_bundle(cfg, out, seed=0, random_init=True, pallet_types=("epal", "gma"),
                         calib=make_calibration_set(cfg, frames=2, max_crops=8, seed=0, synthetic=True))


@pytest.fixture(scope="module")
def good(exported):
    return exported.root


@pytest.fixture
def bundle(good, tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(good, dst)
    return dst


def edit_manifest(path, fn):
    m = json.loads((path / "manifest.json").read_text())
    fn(m)
    (path / "manifest.json").write_text(json.dumps(m))


def rehash(path, rel):
    """Record `rel`'s current sha256 in the manifest (a file replaced by someone who also fixed the manifest)."""
    edit_manifest(path, lambda m: m["files"].__setitem__(rel, sha256_file(path / rel)))


def same_error_from_both(path, message):
    """load_bundle raises BundleError matching `message`, and check_bundle reports exactly that one problem."""
    with pytest.raises(BundleError, match=message) as info:
        load_bundle(path)
    assert check_bundle(path) == [str(info.value)]
    return str(info.value)


# -- good bundles --------------------------------------------------------------------------------------

def test_v2_bundle_has_its_pallet_types_and_report(good):
    b = load_bundle(good)
    assert check_bundle(good) == []
    assert b.manifest.format_version == 2 and b.classes == ("epal", "gma") and b.precision == ("fp32",)
    assert [(t.name, t.class_id) for t in b.pallet_types] == [("epal", 0), ("gma", 1)]
    assert b.pallet is b.pallet_types[0] and b.pallet_type_for_class(1).name == "gma"
    assert b.pallet_class_ids == (0, 1)
    with pytest.raises(BundleError, match="detector class 2 is no pallet type"):
        b.pallet_type_for_class(2)
    gma = b.pallet_type_for_class(1)
    assert gma.points().shape == (2000, 3) and gma.points().dtype == np.float32
    np.testing.assert_allclose(gma.size_m, (1.219, 1.016, 0.121), atol=1e-9)
    assert set(gma.pockets_m) == {"+x", "-x", "+y", "-y"} and gma.pockets_m["+y"].shape == (2, 2, 3)
    # the default ICP starts, their slides scaled to the GMA pallet's length and width
    np.testing.assert_allclose(gma.refine_starts[2], (0.0, 0.1 * 1.219 / 1.2, 0.0))
    np.testing.assert_allclose(gma.refine_starts[4], (0.0, 0.0, 0.1 * 1.016 / 0.8))
    assert b.fusion.choose_input is None and b.detector.layout == "yolov8" and b.graph("detector").is_absolute()
    assert b.fusion.crop_hw == (32, 32) and b.fusion.feature_dim == 16 and b.pose_input_spec().num_points == 32
    # the contract carries no provenance; the report beside it does
    raw = json.loads((good / "manifest.json").read_text())
    assert not {"provenance", "checks", "scores"} & set(raw)
    assert b.provenance["random_init"] is True and "parity" in b.checks and b.scores == {}
    with pytest.raises(BundleError, match="no int8 fusion graph"):
        b.graph("fusion", "int8")
    with pytest.raises(ValueError, match="precision"):
        b.graph("fusion", "fp16")


def test_v2_round_trip_gives_the_same_dataclasses(exported, good):
    raw = json.loads((good / "manifest.json").read_text())
    assert Manifest.from_dict(raw) == exported.manifest
    assert load_bundle(good).manifest == exported.manifest
    assert Manifest.from_dict(raw).to_dict() == raw
    assert load_bundle(good).pallet_types == exported.manifest.pallet_types


def test_shipped_bundle_reads_as_every_trained_type_epal_first():
    b = load_bundle(SHIPPED)
    assert b.classes == ("pallet",)
    epal = b.pallet_types[0]                      # a detection's first type: the type margin's common one
    trained = b.report["provenance"]["training"]["pose"]["pallet_types"]
    assert [t.name for t in b.pallet_types] == [trained[k] for k in sorted(trained, key=int)]
    assert {t.class_id for t in b.pallet_types} == {0}      # one detector class; the depth picks the type
    assert epal.name == "epal" and epal.class_id == 0 and epal.points().shape == (2000, 3)
    # today's ICP starts, in today's order
    np.testing.assert_allclose(epal.start_offsets(), start_offsets(MAX_STARTS), atol=1e-12)
    np.testing.assert_allclose(epal.start_offsets(6), start_offsets(6), atol=1e-12)
    # fork pockets derived from its boards and blocks: 227.5 mm wide and 100 mm high on the short faces,
    # 382.5 mm wide and 100 mm high on the long ones
    width = lambda p: p[:, 1] - p[:, 0]  # noqa: E731
    np.testing.assert_allclose(width(epal.pockets_m["+x"])[:, 1:], [[0.2275, 0.1]] * 2, atol=1e-9)
    np.testing.assert_allclose(width(epal.pockets_m["-y"])[:, [0, 2]], [[0.3825, 0.1]] * 2, atol=1e-9)
    assert epal.pockets_m["+x"][0, 0, 1] < 0 < epal.pockets_m["-x"][0, 0, 1]   # left first, seen from outside
    assert set(b.report) == {"provenance", "checks", "scores"} and "fp32" in b.scores


def test_shipped_bundle_passes_bundle_check(capsys):
    assert cli.main(["bundle", "check", str(SHIPPED)]) == 0
    assert "OK" in capsys.readouterr().out


def test_v1_manifest_of_an_export_still_loads(good, bundle):
    """A version 1 manifest (one pallet_model, classes at the top, provenance inside) reads as one type, the
    detector's "pallet" class (here an external detector that also knows boxes)."""
    v2 = json.loads((good / "manifest.json").read_text())
    epal = v2["pallet_types"][0]
    det = {k: v for k, v in v2["detector"].items() if k != "classes"}
    v1 = {"format": "pallet6d-bundle", "format_version": 1, "name": "old", "config": "tiny", "classes": ["pallet", "box"],
          "depth_units": "metres", "precision": ["fp32"],
          "detector": {**det, "num_classes": 2, "scale": "custom", "source": "external"},
          "fusion": {**v2["fusion"], "attention": True, "attention_stride": 8},
          "pose": {**v2["pose"], "selection": "max_confidence", "attention": True},
          "pallet_model": {k: epal[k] for k in ("name", "size_m", "diameter_m", "points_file", "boxes_m",
                                                "symmetries")},
          "files": {k: h for k, h in v2["files"].items() if "gma" not in k},
          "provenance": {"command": "x"}, "checks": {}, "scores": {}}
    (bundle / "manifest.json").write_text(json.dumps(v1))
    (bundle / REPORT).unlink()
    b = load_bundle(bundle)
    assert check_bundle(bundle) == []
    assert b.pallet.name == "epal" and b.pallet.class_id == 0 and len(b.pallet.refine_starts) == MAX_STARTS
    assert b.provenance == {"command": "x"} and b.pallet_class_ids == (0,)
    v1["pose"]["wobble"] = 1
    (bundle / "manifest.json").write_text(json.dumps(v1))
    same_error_from_both(bundle, r"field 'pose.wobble' is not a field of format version 1")
    v1["pose"].pop("wobble")
    v1["pose"]["selection"] = "mean"
    (bundle / "manifest.json").write_text(json.dumps(v1))
    same_error_from_both(bundle, r"field 'pose.selection' must be 'max_confidence'")


def test_report_updates_leave_the_contract_alone(bundle, caplog):
    digest = sha256_file(bundle / "manifest.json")
    update_report(bundle, "scores", {"fp32": {"virtual-clean": {"add_sym_acc": {"0.05": 0.9}}}})
    b = load_bundle(bundle)
    assert b.scores["fp32"]["virtual-clean"]["add_sym_acc"]["0.05"] == 0.9 and b.provenance["random_init"] is True
    assert sha256_file(bundle / "manifest.json") == digest
    # a damaged report holds nothing the runtime needs: both readers warn and go on
    (bundle / REPORT).write_text("{not json")
    with caplog.at_level(logging.WARNING):
        assert load_bundle(bundle).report == {} and check_bundle(bundle) == []
    assert "ignoring the bundle's report" in caplog.text


# -- broken bundles: one message from load_bundle and check_bundle --------------------------------------

def _set(section, key, value):
    def edit(m):
        target = m
        for part in section:
            target = target[part]
        target[key] = value
    return edit


def _drop_type(index):
    def edit(m):
        t = m["pallet_types"].pop(index)
        m["files"].pop(t["points_file"])
    return edit


def _file_field(value, section=("pallet_types", 0), key="points_file"):
    """Point a file field (and its files entry) at `value`."""
    def edit(m):
        target = m
        for part in section:
            target = target[part]
        old = target[key]
        target[key] = value
        m["files"][value] = m["files"].pop(old)
    return edit


SYM_SCALED = [np.eye(4).tolist(), np.diag([2.0, 2.0, 1.0, 1.0]).tolist()]
SYM_MIRROR = [np.eye(4).tolist(), np.diag([-1.0, 1.0, 1.0, 1.0]).tolist()]
SYM_TURN_90 = [np.eye(4).tolist(), [[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1.0]]]
SYM_FLIP = [np.eye(4).tolist(), np.diag([1.0, -1.0, -1.0, 1.0]).tolist()]   # upside down: the decks differ
POCKET = [[[-0.6, -0.3, -0.07], [0.6, -0.1, 0.02]], [[-0.6, 0.1, -0.07], [0.6, 0.3, 0.02]]]


@pytest.mark.parametrize("edit, message", [
    # meaning, not only type
    (_set(("fusion", "depth_encoding"), "clip_m", 0), r"'fusion.depth_encoding.clip_m' must be a finite number > 0"),
    (_set(("fusion", "depth_encoding"), "clip_m", "1"), r"'fusion.depth_encoding.clip_m' must be a number"),
    (_set(("fusion",), "rgb_std", [0.2, 0.0, 0.2]), r"'fusion.rgb_std' must be a finite number > 0"),
    (_set(("detector",), "rgb_std", [1, 1, -1]), r"'detector.rgb_std' must be a finite number > 0"),
    (_set(("detector",), "pixel_scale", 0), r"'detector.pixel_scale' must be a finite number > 0"),
    (_set(("pose",), "depth_range_m", [10.0, 0.1]), r"'pose.depth_range_m' must be \[min, max\] with 0 <= min < max"),
    (_set(("pose",), "depth_range_m", [-1.0, 5.0]), r"'pose.depth_range_m' must be \[min, max\]"),
    (_set(("pose",), "num_points", 0), r"'pose.num_points' must be a positive integer"),
    (_set(("pose",), "num_points", True), r"'pose.num_points' must be an integer"),
    (_set(("detector",), "input_hw", [100, 640]), r"'detector.input_hw' must be positive multiples of 32"),
    (_set(("detector",), "letterbox_pad_value", 300), r"'detector.letterbox_pad_value' must be in \[0, 255\]"),
    (_set(("detector",), "channel_order", "RGBA"), r"'detector.channel_order' must be 'RGB' or 'BGR'"),
    (_set(("detector",), "classes", ["epal", "epal"]), r"'detector.classes' must be a non-empty list of distinct"),
    (_set(("fusion",), "choose_input", "rgb"), r"'fusion.rgb_input' the graph's inputs need distinct names"),
    (_set(("fusion",), "crop_resize", "letterbox"), r"'fusion.crop_resize' must be 'stretch'"),
    (_set(("fusion", "depth_encoding"), "interpolation", "linear"), r"'fusion.depth_encoding.interpolation' must be"),
    (_set(("pose",), "quaternion_order", "xyzw"), r"'pose.quaternion_order' must be 'wxyz'"),
    (_set(("pose",), "hypotheses", "top_3"), r"'pose.hypotheses' must be one of per_point, most_confident"),
    (_set((), "precision", ["fp32", "int8"]), r"'precision' lists 'int8' but not every graph has a file_int8"),
    # pallet types
    (_drop_type(1), r"'pallet_types' has no type for detector class 1 \('gma'\)"),
    (_set(("pallet_types", 1), "class_id", 5), r"'pallet_types\[1\].class_id' is 5, but the detector has 2"),
    (_set(("pallet_types", 1), "name", "epal"), r"'pallet_types' has two types with name 'epal'"),
    (_set(("pallet_types", 0), "size_m", [1.2, 0.0, 0.144]), r"'pallet_types\[0\].size_m' must be a finite number > 0"),
    (_set(("pallet_types", 0), "diameter_m", 0.5), r"'pallet_types\[0\].diameter_m' 0.5 does not fit size_m"),
    (_set(("pallet_types", 0), "symmetries", [[[2]]]), r"'pallet_types\[0\].symmetries' must be \(S, 4, 4\)"),
    (_set(("pallet_types", 0), "symmetries", SYM_SCALED[::-1]), r"'pallet_types\[0\].symmetries' must start with"),
    (_set(("pallet_types", 0), "symmetries", SYM_SCALED), r"'pallet_types\[0\].symmetries' \[1\] is not a rigid"),
    (_set(("pallet_types", 0), "symmetries", SYM_MIRROR), r"'pallet_types\[0\].symmetries' \[1\] is not a rigid"),
    (_set(("pallet_types", 0), "symmetries", SYM_TURN_90), r"symmetries' \[1\] does not map the pallet's boxes_m"),
    (_set(("pallet_types", 1), "symmetries", SYM_FLIP), r"'pallet_types\[1\].symmetries' \[1\] does not map"),
    (_set(("pallet_types", 0), "boxes_m", [[0, 0, 0]]), r"'pallet_types\[0\].boxes_m' must be \(k, 2, 3\)"),
    (_set(("pallet_types", 0), "boxes_m", [[[0, 0, 0], [1, -1, 1]]]), r"max > min"),
    (_set(("pallet_types", 0), "boxes_m", [[[0, 0, 0], [2, 0.1, 0.01]]]), r"boxes_m' reach outside size_m"),
    (_set(("pallet_types", 0), "pockets_m", {"+z": POCKET}), r"'pallet_types\[0\].pockets_m' has face '\+z'"),
    (_set(("pallet_types", 0), "pockets_m", {"+x": POCKET[:1]}), r"'pallet_types\[0\].pockets_m.\+x' must be \(2, 2, 3\)"),
    (_set(("pallet_types", 0), "refine_starts", [[15.0, 0.0]]), r"'pallet_types\[0\].refine_starts' must be \(S, 3\)"),
    (_set(("pallet_types", 0), "refine_starts", [[400.0, 0, 0]]), r"refine_starts' must turn by at most 180"),
    (_set(("pallet_types", 0), "refine_starts", [[float("nan"), 0, 0]]), r"refine_starts' must hold finite numbers"),
    # files
    (_file_field("../../../../etc/passwd"), r"'pallet_types\[0\].points_file' must be a relative file name"),
    (_file_field("/proc/self/mem"), r"'pallet_types\[0\].points_file' must be a relative file name"),
    (_file_field("/proc/self/mem.onnx", ("fusion",), "file"), r"'fusion.file' must be a relative file name"),
    (_file_field("pallets/./epal.npy"), r"must be a relative file name"),
    (_set(("files",), "extra.bin", "0" * 64), r"'files' lists 'extra.bin', which no field of the manifest names"),
    (lambda m: m["files"].pop("pose.onnx"), r"'files' lacks the sha256 of 'pose.onnx'"),
    (_set(("files",), "pose.onnx", "abc"), r"'files.pose.onnx' must be a sha256 in lowercase hex"),
    (_file_field("pose.npy", ("pose",), "file"), r"'pose.file' must name an .onnx file"),
    # structure
    (_set((), "format_version", 3), r"format_version 3 is not supported"),
    (_set((), "format", "other"), r"field 'format' must be"),
    (lambda m: m["detector"].pop("input_hw"), r"'detector.input_hw' is missing"),
    (_set((), "provenance", {}), r"field 'provenance' is not a field of format version 2"),
    (_set(("detector",), "scale", "n"), r"field 'detector.scale' is not a field"),
    (_set(("fusion", "depth_encoding"), "gamma", 1), r"'fusion.depth_encoding.gamma' is not a field"),
    (_set(("pallet_types", 1), "colour", "blue"), r"'pallet_types\[1\].colour' is not a field"),
    (_set((), "pallet_types", []), r"'pallet_types' must list at least one pallet type"),
])
def test_bad_manifest_gives_one_error_from_both(bundle, edit, message):
    edit_manifest(bundle, edit)
    same_error_from_both(bundle, message)


def _write_points(path, pts):
    np.save(path / "pallets" / "epal.npy", np.asarray(pts, dtype=np.float32))
    rehash(path, "pallets/epal.npy")


@pytest.mark.parametrize("make, message", [
    (lambda p: _write_points(p, [[0.0, 0.0, np.nan]] * 10), r"points_file' \(pallets/epal.npy\) holds model points "
                                                             r"that are not finite"),
    (lambda p: _write_points(p, [[0.0, 0.0, 1.0]] * 10), r"holds model points outside size_m"),
    (lambda p: _write_points(p, np.zeros((10, 2))), r"must hold \(n, 3\) model points"),
    (lambda p: (np.save(p / "pallets" / "epal.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True),
                rehash(p, "pallets/epal.npy")), r"points_file' \(pallets/epal.npy\): not a .npy array"),
    (lambda p: ((p / "detector.onnx").write_bytes(b"garbage"), rehash(p, "detector.onnx")),
     r"detector graph 'detector.onnx': not a valid ONNX model"),
    (lambda p: ((p / "pose.onnx").write_bytes((p / "pose.onnx").read_bytes()[:-100]), rehash(p, "pose.onnx")),
     r"pose graph 'pose.onnx': not a valid ONNX model \(field \d+ runs past the end"),
    (lambda p: ((p / "fusion.onnx").write_bytes(b"\x08\x07"), rehash(p, "fusion.onnx")), r"no graph"),
    (lambda p: open(p / "fusion.onnx", "ab").write(b"\x28\x01"), r"sha256 of 'fusion.onnx' is .* changed or damaged"),
    (lambda p: (p / "pose.onnx").unlink(), r"'pose.file' names 'pose.onnx', which is not in the bundle"),
    (lambda p: ((p / "pallets" / "epal.npy").unlink(), os.symlink("/etc/passwd", p / "pallets" / "epal.npy")),
     r"'pallet_types\[0\].points_file' names 'pallets/epal.npy', which leads outside the bundle folder"),
    (lambda p: ((p / "pallets" / "epal.npy").unlink(), os.symlink("../../b2", p / "pallets" / "epal.npy")),
     r"which leads outside the bundle folder"),
    (lambda p: ((p / "pallets" / "epal.npy").unlink(), (p / "pallets" / "epal.npy").mkdir()),
     r"names 'pallets/epal.npy', which is not a regular file"),
])
def test_bad_files_give_one_error_from_both(bundle, make, message):
    make(bundle)
    same_error_from_both(bundle, message)


def test_file_size_limit(bundle, monkeypatch):
    from pallet6d.runtime import bundle_files

    monkeypatch.setattr(bundle_files, "MAX_FILE_BYTES", 1000)
    same_error_from_both(bundle, r"'detector.file' names 'detector.onnx', \d+ bytes: more than the limit of 1000")


def test_symlink_inside_the_bundle_is_fine(bundle):
    (bundle / "pallets" / "epal.npy").rename(bundle / "epal-points.npy")
    os.symlink("../epal-points.npy", bundle / "pallets" / "epal.npy")
    assert load_bundle(bundle).pallet.points().shape == (2000, 3) and check_bundle(bundle) == []


def test_sha256_check_can_be_skipped(bundle):
    with open(bundle / "fusion.onnx", "ab") as fh:
        fh.write(b"\x28\x01")   # a well-formed protobuf field (model_version = 1): still an ONNX model
    load_bundle(bundle, verify_sha256=False)


def test_graph_onnxruntime_cannot_load_is_a_bundle_error(bundle, capsys):
    """Well-formed protobuf that is no runnable model: the session wrapper names the graph, and `pallet6d run`
    says so in one line."""
    from pallet6d.runtime.sessions import OnnxModel

    (bundle / "fusion.onnx").write_bytes(b"\x08\x07\x3a\x02\x0a\x00")   # ir_version 7, a graph with an empty node
    rehash(bundle, "fusion.onnx")
    load_bundle(bundle)   # the structure is sound; onnxruntime is the judge of the rest
    with pytest.raises(BundleError, match=r"fusion.onnx: onnxruntime cannot load it"):
        OnnxModel(bundle / "fusion.onnx", threads=1)
    problems = check_bundle(bundle)
    assert len(problems) == 1 and "fusion (fusion.onnx): ONNX graph" in problems[0], problems
    assert cli.main(["run", "--source", f"replay:{bundle / 'none'}", "--bundle", str(bundle), "--threads", "1",
                     "--frame", "camera"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot load bundle" in err[0] and "fusion.onnx: onnxruntime cannot load it" in err[0]


# -- graphs against the manifest (check_bundle only: it opens them) -------------------------------------

def test_wrong_input_shape_named(bundle):
    edit_manifest(bundle, _set(("fusion",), "crop_hw", [40, 40]))
    problems = check_bundle(bundle)
    assert any("fusion (fusion.onnx): input 'rgb' has shape" in p and "40" in p for p in problems), problems


def test_wrong_points_and_names(bundle):
    edit_manifest(bundle, lambda m: (m["pose"].__setitem__("num_points", 64),
                                     m["detector"].__setitem__("output_name", "boxes")))
    problems = check_bundle(bundle)
    assert any("detector (detector.onnx): has no output named 'boxes'" in p for p in problems), problems
    assert any("pose (pose.onnx): input 'points' has shape" in p for p in problems), problems


def test_swapped_graph_is_caught(bundle):
    shutil.copyfile(bundle / "fusion.onnx", bundle / "pose.onnx")
    rehash(bundle, "pose.onnx")
    problems = check_bundle(bundle)
    assert any("pose (pose.onnx): has no input named 'points'" in p for p in problems), problems


def test_choose_input_the_graph_lacks(bundle):
    edit_manifest(bundle, _set(("fusion",), "choose_input", "choose"))
    assert load_bundle(bundle).fusion.choose_input == "choose"
    problems = check_bundle(bundle, run=False)
    assert any("fusion (fusion.onnx): has no input named 'choose'" in p for p in problems), problems
    assert any("output 'features' has shape" in p and "['*', 32, 16]" in p for p in problems), problems


def test_not_a_bundle(tmp_path):
    with pytest.raises(BundleError, match="not a folder"):
        load_bundle(tmp_path / "nope")
    with pytest.raises(BundleError, match="has no manifest.json"):
        load_bundle(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(BundleError, match="not valid JSON"):
        load_bundle(tmp_path)
    (tmp_path / "manifest.json").write_text("[1, 2]")
    with pytest.raises(BundleError, match="must hold a JSON object"):
        load_bundle(tmp_path)


def test_bundle_cli(good, bundle, capsys):
    assert cli.main(["bundle", "check", str(good)]) == 0
    assert "OK" in capsys.readouterr().out
    (bundle / "detector.onnx").write_bytes(b"garbage")
    rehash(bundle, "detector.onnx")
    assert cli.main(["bundle", "check", str(bundle)]) == 1
    assert "detector graph 'detector.onnx': not a valid ONNX model" in capsys.readouterr().err
    assert cli.main(["bundle", "info", str(good)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_points"] == 32 and [t["name"] for t in info["pallet_types"]] == ["epal", "gma"]


def test_boxes_are_optional_and_refinement_follows_them(good, bundle, caplog):
    from pallet6d.runtime.estimator import PalletEstimator

    assert load_bundle(good).pallet.boxes_m.shape[1:] == (2, 3)
    assert PalletEstimator.from_bundle(good, threads=1).refines
    edit_manifest(bundle, lambda m: [t.__setitem__("boxes_m", None) for t in m["pallet_types"]])
    assert load_bundle(bundle).pallet.boxes_m is None
    with caplog.at_level("WARNING"):
        est = PalletEstimator.from_bundle(bundle, threads=1)
    assert not est.refines and "no pallet boxes_m" in caplog.text
    assert not PalletEstimator.from_bundle(good, threads=1, refine=False).refines


def _leaves(node, path=()):
    """Every path to a value in a JSON tree."""
    yield path
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:3]):
            yield from _leaves(v, (*path, i))


JUNK = (None, -1, 0, 0.5, 1e12, float("nan"), float("inf"), True, "", "x", "../x.onnx", [], [1, 2], {}, {"a": 1})


def test_random_manifest_damage_gives_bundle_errors_only(good, bundle):
    """Seeded random edits of the manifest: load_bundle either loads or raises BundleError (never another
    exception), and check_bundle reports exactly load_bundle's error."""
    rng = np.random.default_rng(0)
    original = json.loads((good / "manifest.json").read_text())
    paths = [p for p in _leaves(original) if p and p[0] != "files"]
    outcomes = {"loaded": 0, "refused": 0}
    for _ in range(150):
        m = json.loads(json.dumps(original))
        path = paths[rng.integers(len(paths))]
        parent = m
        for k in path[:-1]:
            parent = parent[k]
        if rng.random() < 0.15 and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = JUNK[rng.integers(len(JUNK))]
        (bundle / "manifest.json").write_text(json.dumps(m))
        try:
            load_bundle(bundle)
            outcomes["loaded"] += 1
        except BundleError as exc:
            outcomes["refused"] += 1
            assert check_bundle(bundle, run=False) == [str(exc)], path
    assert outcomes["refused"] > 100, outcomes
