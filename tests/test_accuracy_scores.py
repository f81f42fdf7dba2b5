"""export/accuracy_report.py (benchmarks/accuracy.py): --write-scores puts the summary in the report and leaves
the manifest untouched; the markdown page; the test sets made again when annotated by an older generator."""
import json
import shutil

from pallet6d.export import accuracy_report as accuracy
from pallet6d.runtime.bundle import check_bundle, load_bundle, sha256_file


def test_write_scores_records_each_preset_per_precision(bundle_dir, tmp_path, capsys):
    bundle = tmp_path / "b"
    shutil.copytree(bundle_dir, bundle)
    summary = {"test_seed": 9001, "n_gt": 10, "frames": 5, "precision": 0.9, "recall": 0.8,
               "add_acc": {"0.02": 0.1, "0.05": 0.5, "0.1": 0.7}, "add_sym_acc": {"0.02": 0.2, "0.05": 0.6, "0.1": 0.8},
               "records": [{"add_m": 0.01}]}
    contract = sha256_file(bundle / "manifest.json")
    accuracy.write_scores(bundle, "fp32", {"virtual-clean": summary}, "python benchmarks/accuracy.py --bundle b")
    accuracy.write_scores(bundle, "int8", {"virtual-clean": dict(summary, recall=0.7)}, "cmd int8")
    scores = json.loads((bundle / "report.json").read_text())["scores"]
    assert load_bundle(bundle).scores == scores and sha256_file(bundle / "manifest.json") == contract
    assert set(scores) == {"fp32", "int8"}
    clean = scores["fp32"]["virtual-clean"]
    assert clean["add_sym_acc"]["0.05"] == 0.6 and clean["recall"] == 0.8 and clean["test_seed"] == 9001
    assert "records" not in clean and scores["int8"]["virtual-clean"]["recall"] == 0.7
    assert scores["fp32"]["command"].startswith("python benchmarks/accuracy.py")
    assert check_bundle(bundle) == []


def test_markdown_reports_pallets_cut_by_the_image_border():
    import numpy as np

    from pallet6d.runtime.evaluation import PalletRecord, summarize

    def rec(err_m, truncated):
        return PalletRecord(frame=0, distance_m=3.0, visib_fract=0.2 if truncated else 0.9, detected=err_m is not None,
                            add_m=np.inf if err_m is None else err_m, add_sym_m=np.inf if err_m is None else err_m,
                            adds_m=np.inf, rot_err_sym_deg=0.0, trans_err_m=0.0, truncated=truncated)

    summary = summarize([rec(0.01, False), rec(0.02, False), rec(None, True), rec(0.3, True)], 3, 0)
    table = accuracy.markdown({"virtual-clean": summary}, "b", "fp32", 1)
    assert "| virtual-clean | in view | 2 | 100% | 0% | 0% | 0% |" in table
    assert "| virtual-clean | cut by the border | 2 | 0% | 0% | 50% | 50% |" in table


def test_test_sets_annotated_by_an_older_generator_are_made_again(tmp_path):
    from pallet6d.sim.dataset import GT_INFO_VERSION

    out = accuracy.ensure_test_set("indoor-noisy", 1, tmp_path)
    meta_path = out / "test" / "sim_config_000000.json"
    assert json.loads(meta_path.read_text())["gt_info_version"] == GT_INFO_VERSION
    stamp = (out / "test" / "000000" / "scene_gt_info.json").stat().st_mtime_ns
    assert accuracy.ensure_test_set("indoor-noisy", 1, tmp_path) == out          # current: reused
    assert (out / "test" / "000000" / "scene_gt_info.json").stat().st_mtime_ns == stamp
    meta = json.loads(meta_path.read_text())
    del meta["gt_info_version"]                                                  # as written before version 2
    meta_path.write_text(json.dumps(meta))
    accuracy.ensure_test_set("indoor-noisy", 1, tmp_path)
    assert json.loads(meta_path.read_text())["gt_info_version"] == GT_INFO_VERSION


def test_a_test_set_of_another_seed_is_made_beside_the_presets_own(tmp_path):
    own = accuracy.ensure_test_set("indoor-noisy", 1, tmp_path)
    other = accuracy.ensure_test_set("indoor-noisy", 1, tmp_path, seed=8013)
    assert own.name == f"indoor-noisy-seed{accuracy.TEST_SEEDS['indoor-noisy']}-1"
    assert other.name == "indoor-noisy-seed8013-1"
    assert json.loads((other / "test" / "sim_config_000000.json").read_text())["seed"] == 8013
