"""`export/retype.py`: a bundle given another set of pallet types keeps its graphs byte for byte, carries exactly
the named types (model points, hashes), refuses types its pose stage was not trained on, and loads in the runtime."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("torch")

from pallet6d.export.export_inputs import ExportError  # noqa: E402
from pallet6d.export.retype import main, retype_bundle  # noqa: E402
from pallet6d.runtime.bundle import check_bundle, load_bundle  # noqa: E402
from pallet6d.runtime.estimator import PalletEstimator  # noqa: E402
from pallet6d.sim.pallets import get_pallet_model  # noqa: E402

GRAPHS = ("detector.onnx", "fusion.onnx", "pose.onnx")


@pytest.fixture
def trained_bundle(bundle_dir, tmp_path):
    """The tiny bundle with a report saying its pose stage was trained on the EPAL and the EUR 3."""
    b = tmp_path / "trained"
    shutil.copytree(bundle_dir, b)
    report = json.loads((b / "report.json").read_text())
    report["provenance"]["training"] = {"pose": {"pallet_types": {"1": "epal", "2": "eur3"}}}
    (b / "report.json").write_text(json.dumps(report))
    return b


def test_the_new_types_are_carried_and_the_graphs_kept(trained_bundle, tmp_path):
    out = retype_bundle(trained_bundle, tmp_path / "two", ("epal", "eur3"), command="test")
    before = json.loads((trained_bundle / "manifest.json").read_text())
    after = json.loads((out / "manifest.json").read_text())
    for f in (g for g in GRAPHS if g in before["files"]):
        assert after["files"][f] == before["files"][f]
        assert (out / f).read_bytes() == (trained_bundle / f).read_bytes()
    assert [t["name"] for t in after["pallet_types"]] == ["epal", "eur3"]
    assert {t["class_id"] for t in after["pallet_types"]} == {0}        # one detector class for every type
    eur3 = next(t for t in after["pallet_types"] if t["name"] == "eur3")
    assert eur3["size_m"] == pytest.approx(list(get_pallet_model("eur3").size_m))
    assert set(after["files"]) >= {"pallets/epal.npy", "pallets/eur3.npy"}
    assert check_bundle(out) == []
    est = PalletEstimator.from_bundle(out)
    assert [g.name for g in est.pallet_types] == ["epal", "eur3"]
    record = json.loads((out / "report.json").read_text())["provenance"]["pallet_types"]
    assert record["pallet_types"] == ["epal", "eur3"] and record["trained_on"] == ["epal", "eur3"]
    assert record["command"] == "test"


def test_a_type_left_out_leaves_the_bundle(trained_bundle, tmp_path):
    two = retype_bundle(trained_bundle, tmp_path / "two", ("epal", "eur3"))
    one = retype_bundle(two, tmp_path / "one", ("eur3",))
    manifest = json.loads((one / "manifest.json").read_text())
    assert [t["name"] for t in manifest["pallet_types"]] == ["eur3"]
    assert "pallets/epal.npy" not in manifest["files"] and not (one / "pallets" / "epal.npy").exists()
    assert np.load(one / "pallets" / "eur3.npy").shape[1] == 3
    assert load_bundle(one).pallet_types[0].name == "eur3"


@pytest.mark.parametrize("names, allow, match", [
    (("epal", "plastic_closed"), False, "not trained on plastic_closed"),
    (("epal", "eur3"), False, None),
    (("epal", "plastic_closed"), True, None),
])
def test_types_the_pose_stage_was_not_trained_on(trained_bundle, tmp_path, names, allow, match):
    out = tmp_path / "b"
    if match:
        with pytest.raises(ExportError, match=match):
            retype_bundle(trained_bundle, out, names, allow_untrained=allow)
        assert not out.exists() or not any(out.iterdir())
    else:
        assert load_bundle(retype_bundle(trained_bundle, out, names, allow_untrained=allow)).pallet_types


def test_a_bundle_that_records_no_training_needs_allow_untrained(bundle_dir, tmp_path):
    with pytest.raises(ExportError, match="records none"):
        retype_bundle(bundle_dir, tmp_path / "b", ("epal",))


def test_the_output_folder_must_be_new(trained_bundle, tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ExportError, match="not empty"):
        retype_bundle(trained_bundle, tmp_path / "full", ("epal",))


def test_the_command_line(trained_bundle, tmp_path, capsys):
    assert main(["--bundle", str(trained_bundle), "--pallet-types", "trained", "--out", str(tmp_path / "t")]) == 0
    assert [t.name for t in load_bundle(tmp_path / "t").pallet_types] == ["epal", "eur3"]
    assert main(["--bundle", str(trained_bundle), "--pallet-types", "epal,nonsense", "--out", str(tmp_path / "u")]) == 2
    assert "unknown pallet type" in capsys.readouterr().err
