"""`pallet6d eval` on a random-init tiny bundle and the 3-frame sim fixture: the JSON has the protocol's keys
and sane values; bad inputs give exit codes, not tracebacks. Runtime only (the bundle comes from the exporter)."""
from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def tiny_bundle(bundle_dir):
    return bundle_dir


def _counted_gt(root) -> int:
    from pallet6d.runtime.bop import BopDataset

    ds = BopDataset(root)
    return sum(1 for i in range(len(ds)) for g in ds[i].gts
               if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1)


@pytest.mark.parametrize("extra", [[], ["--gt-boxes", "--min-fit", "0", "--no-structure-check"]])
def test_eval_writes_a_summary_with_the_protocol_keys(tiny_bundle, sim_bop_dataset, tmp_path, capsys, extra):
    from pallet6d.runtime.cli import main

    out = tmp_path / "eval.json"
    rc = main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--json", str(out),
               "--threads", "1", *extra])
    assert rc == 0
    doc = json.loads(out.read_text())
    n_gt = _counted_gt(sim_bop_dataset)
    assert n_gt > 0 and doc["n_gt"] == n_gt and doc["frames"] == 3
    assert 0.0 <= doc["recall"] <= 1.0 and 0.0 <= doc["precision"] <= 1.0
    for key in ("add_acc", "add_sym_acc"):
        assert set(doc[key]) == {"0.02", "0.05", "0.1"}
        vals = [doc[key][k] for k in ("0.02", "0.05", "0.1")]
        assert all(0.0 <= v <= 1.0 for v in vals) and vals == sorted(vals)
    assert len(doc["records"]) == n_gt
    assert sum(r["detected"] for r in doc["records"]) == doc["n_detected"]
    for r in doc["records"]:
        assert r["visib_fract"] >= 0.1 and r["distance_m"] > 0
        assert (r["add_sym_m"] is None) == (not r["detected"])
        if r["detected"]:
            assert r["add_sym_m"] <= r["add_m"] + 1e-9
    if extra:   # ground-truth boxes: every pallet with enough depth reaches the pose stage, none is a false positive
        assert doc["n_detected"] >= 1 and doc["precision"] == 1.0
    assert "precision" in capsys.readouterr().out


def test_eval_max_frames(tiny_bundle, sim_bop_dataset, tmp_path):
    from pallet6d.runtime.cli import main

    out = tmp_path / "e.json"
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--json", str(out),
                 "--max-frames", "1", "--threads", "1"]) == 0
    doc = json.loads(out.read_text())
    assert doc["frames"] == 1 and all(r["frame"] == 0 for r in doc["records"])


def test_eval_max_pallets_caps_the_pallets_posed_per_frame(tiny_bundle, sim_bop_dataset, tmp_path):
    from pallet6d.runtime.cli import main

    out = tmp_path / "e.json"
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--json", str(out),
                 "--gt-boxes", "--min-fit", "0", "--no-structure-check", "--max-pallets", "1", "--threads", "1"]) == 0
    doc = json.loads(out.read_text())
    per_frame = [sum(r["detected"] for r in doc["records"] if r["frame"] == f) for f in range(doc["frames"])]
    assert max(per_frame) == 1 and doc["n_detected"] < doc["n_gt"]


def test_eval_bad_inputs(tiny_bundle, sim_bop_dataset, tmp_path, capsys):
    from pallet6d.runtime.cli import main

    assert main(["eval", "--bundle", str(tmp_path / "nope"), "--data", str(sim_bop_dataset)]) == 2
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "cannot load bundle" in err and str(tmp_path) in err
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--refine-starts", "15"]) == 2
    assert "refine_starts must be in [0, 14]" in capsys.readouterr().err
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--max-pallets", "0"]) == 2
    assert "max_pallets must be >= 1" in capsys.readouterr().err
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--type-first-enough", "0"]) == 2
    assert "type_first_enough must be in (0, 1]" in capsys.readouterr().err


def test_eval_cli_does_not_import_torch():
    import subprocess
    import sys

    code = ("import sys, pallet6d.runtime.eval_cli as m, pallet6d.runtime.evaluation, pallet6d.runtime.estimator; "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_eval_calibrated_passes_each_frames_vehicle_calibration(tiny_bundle, sim_bop_dataset, tmp_path, caplog):
    from pallet6d.runtime.cli import main
    from pallet6d.sim.dataset import write_dataset
    from pallet6d.sim.presets import get_preset

    forklift = tmp_path / "forklift"
    write_dataset(get_preset("forklift-approach").with_image_size(212, 120), 2, 5, forklift)
    out = tmp_path / "e.json"
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(forklift), "--json", str(out),
                 "--threads", "1", "--calibrated"]) == 0
    assert json.loads(out.read_text())["calibrated_frames"] == 2
    # the paper presets have no vehicle: estimated without one, and said so
    assert main(["eval", "--bundle", str(tiny_bundle), "--data", str(sim_bop_dataset), "--json", str(out),
                 "--threads", "1", "--calibrated"]) == 0
    assert json.loads(out.read_text())["calibrated_frames"] == 0
    assert "no vehicle calibration" in caplog.text
