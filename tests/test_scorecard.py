"""benchmarks/scorecard.py: the table of several bundles' figures, kept results read back instead of measured again,
and what it refuses (the measures themselves are the benchmarks' own, tested with them)."""
import importlib.util
import json
import shutil
from pathlib import Path

import pytest

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "scorecard.py"


@pytest.fixture
def scorecard(monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))     # as `python benchmarks/scorecard.py` runs: its siblings import
    spec = importlib.util.spec_from_file_location("scorecard_benchmark", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_table_puts_each_bundles_figures_beside_the_target(scorecard):
    a = {"presets": {"virtual-clean": 97.5, "indoor-noisy": 91.0}, "mismatched": {"kept": 14}}
    b = {"presets": {"virtual-clean": 98.0}, "mismatched": {"kept": 9},
         "real": {"missing": "data/real/labels.json not found"}}
    text = scorecard.table(["shipped", "candidate"], [a, b])
    rows = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines()}
    assert rows["ADD-sym within 5 cm, virtual-clean (%)"].endswith("| 97.5 | 98 | >= 98.1 |")
    assert rows["ADD-sym within 5 cm, indoor-noisy (%)"].endswith("| 91 | - | >= 93.7 |")
    assert rows["mismatched inputs: poses kept"].endswith("| 14 | 9 |  |")
    assert not any("virtual-occluded" in r for r in rows)          # no bundle has it: no row
    assert "- `candidate`: data/real/labels.json not found" in text


def test_a_measures_own_figures_are_not_overwritten_by_its_run_record(scorecard, monkeypatch, tmp_path):
    from pallet6d.runtime.structure import StructureParams

    monkeypatch.setattr(scorecard, "measure_real", lambda *a: {"recall": 30.0, "precision": 56.0})
    res = scorecard.run_measure("real", tmp_path, "int8", {"structure": StructureParams(grid=24)}, False, tmp_path,
                                tmp_path)
    assert res["precision"] == 56.0 and res["graphs"] == "int8" and res["options"] == {"structure": {"grid": 24}}
    json.dumps(res)


def test_kept_results_are_read_back_not_measured_again(scorecard, tmp_path, monkeypatch, capsys):
    bundle = tmp_path / "cand"
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    kept = tmp_path / "out" / "cand"
    kept.mkdir(parents=True)
    (kept / "mismatched-int8.json").write_text(json.dumps({"kept": 3, "accepted": 40}))
    calls = []

    def fake(name, *args):
        calls.append(name)
        return {"exact": 90.0, "d435": 85.0, "blocked_safe": 0}

    monkeypatch.setattr(scorecard, "run_measure", fake)
    assert scorecard.main(["--bundle", str(bundle), "--measures", "mismatched,pockets", "--out",
                           str(tmp_path / "out")]) == 0
    assert calls == ["pockets"]
    assert json.loads((kept / "pockets-int8.json").read_text())["exact"] == 90.0
    md = (tmp_path / "out" / "scorecard.md").read_text()
    assert "| mismatched inputs: poses kept | 3 |  |" in md and "| blocked pockets called safe | 0 | 0 |" in md
    assert md == "\n".join(capsys.readouterr().out.splitlines()[:len(md.splitlines())]) + "\n"


def test_a_variant_is_measured_with_its_options_under_its_own_name(scorecard, tmp_path, monkeypatch, capsys):
    from pallet6d.runtime.structure import StructureParams

    bundle = tmp_path / "cand"
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    seen = []

    def fake(name, bundle, precision, options, *args):
        seen.append(options)
        return {"kept": len(options)}

    monkeypatch.setattr(scorecard, "run_measure", fake)
    assert scorecard.main(["--bundle", str(bundle), "--measures", "mismatched", "--out", str(tmp_path / "out"),
                           "--variant", 'g24={"structure": {"grid": 24}, "min_fit": 0.3}']) == 0
    assert seen[0] == {} and seen[1]["min_fit"] == 0.3 and seen[1]["structure"] == StructureParams(grid=24)
    assert (tmp_path / "out" / "cand+g24" / "mismatched-int8.json").is_file()
    md = capsys.readouterr().out
    assert "| `cand` | `cand+g24` | target |" in md and "| mismatched inputs: poses kept | 0 | 2 |  |" in md
    assert '- `+g24`: `{"structure": {"grid": 24}, "min_fit": 0.3}`' in md


@pytest.mark.parametrize("name, split, frames, seed, models, folder", [
    ("pockets", "test", 60, 8, "epal", "forklift-frames-epal"),
    ("pockets", "val", 200, 8031, "epal", "forklift-frames-epal-val"),
    ("pockets-all", "test", 100, 7, None, "forklift-frames"),
    ("pockets-all", "val", 100, 819, None, "forklift-frames-val"),
])
def test_each_split_poses_its_own_forklift_targets(scorecard, monkeypatch, tmp_path, name, split, frames, seed, models,
                                                   folder):
    seen = []
    monkeypatch.setattr(scorecard, "measure_pockets", lambda *a: seen.append(a[3:]) or {"exact": 90.0})
    res = scorecard.run_measure(name, tmp_path, "int8", {}, False, tmp_path / "test-sets", tmp_path / "data", split)
    assert seen == [(frames, tmp_path / "data" / folder, seed, models)]
    assert res["split"] == split and res["frames"] == frames


@pytest.mark.parametrize("name", ["presets", "forklift"])
def test_the_validation_split_measures_the_presets_on_validation_seeds_under_data(scorecard, monkeypatch, tmp_path,
                                                                                   name):
    seen = {}
    for split in scorecard.SPLITS:
        monkeypatch.setattr(scorecard, f"measure_{name}", lambda *a: seen.setdefault(a[-1], a[-2]) and {})
        scorecard.run_measure(name, tmp_path, "int8", {}, False, tmp_path / "test-sets", tmp_path / "data", split)
    assert seen == {"test": tmp_path / "test-sets", "val": tmp_path / "data"}
    with pytest.raises(ValueError, match="unknown split"):
        scorecard.run_measure(name, tmp_path, "int8", {}, False, tmp_path, tmp_path, "train")


@pytest.mark.parametrize("split", ["val", "test"])
def test_validation_presets_pool_their_seeds_and_the_test_sets_keep_one(scorecard, monkeypatch, tmp_path, split):
    import pallet6d.export.accuracy_report as accuracy_report
    import pallet6d.runtime.eval_cli as eval_cli

    # (seed, frames) -> (pallets, share within 5 cm, missed)
    sets = {(8011, 100): (400, 0.95, {"no_detection": {"n_gt": 4, "refused_within_5cm": 0}}),
            (8021, 60): (240, 0.90, {"no_detection": {"n_gt": 2, "refused_within_5cm": 0},
                                     "poor_fit": {"n_gt": 3, "refused_within_5cm": 1}}),
            (9001, 100): (410, 0.97, {})}
    seen = []

    def ensure(preset, frames, root, seed):
        seen.append((preset, seed, frames))
        return (seed, frames)

    def evaluate(est, key, split_name):
        n, share, missed = sets.get(key, (100, 0.5, {}))
        return {"summary": {"n_gt": n, "add_sym_acc": {"0.05": share}, "missed_by_reason": missed}}

    monkeypatch.setattr(accuracy_report, "ensure_test_set", ensure)
    monkeypatch.setattr(eval_cli, "evaluate_dataset", evaluate)
    monkeypatch.setattr(scorecard, "_estimator", lambda *a, **k: None)
    res = scorecard.measure_presets(tmp_path, "int8", {}, 100, tmp_path, split)
    if split == "val":
        assert ("virtual-clean", 8011, 100) in seen and ("virtual-clean", 8021, 60) in seen and len(seen) == 7
        assert res["virtual-clean"] == pytest.approx(100 * (400 * 0.95 + 240 * 0.90) / 640, abs=0.01)
        assert res["virtual-clean-pallets"] == 640
        assert res["virtual-clean-missed"] == {"no_detection": {"n_gt": 6, "refused_within_5cm": 0},
                                               "poor_fit": {"n_gt": 3, "refused_within_5cm": 1}}
        assert res["virtual-clean-by_seed"] == {8011: 95.0, 8021: 90.0}
        assert res["seeds"]["indoor-noisy"] == [8013, 8023, 8033]
        assert ("indoor-noisy", 8033, 300) in seen
    else:
        assert seen == [("virtual-clean", 9001, 100), ("virtual-occluded", 9002, 100), ("indoor-noisy", 9003, 100)]
        assert res["virtual-clean"] == 97.0 and res["virtual-clean-pallets"] == 410
        assert res["seeds"]["virtual-clean"] == 9001


def test_validation_presets_kept_from_one_seed_are_measured_again(scorecard, tmp_path):
    old = tmp_path / "presets-val-int8.json"
    old.write_text(json.dumps({"virtual-clean": 96.0, "seeds": {"virtual-clean": 8011}}))
    assert scorecard._stale("presets", "val", old)
    now = tmp_path / "presets-val-now.json"
    now.write_text(json.dumps({"seeds": {p: scorecard.val_seeds(p) for p in scorecard.PAPER_PRESETS}}))
    assert not scorecard._stale("presets", "val", now)
    assert not scorecard._stale("presets", "test", old) and not scorecard._stale("forklift", "val", old)


def test_validation_results_are_kept_apart_from_the_test_results(scorecard, tmp_path, monkeypatch, capsys):
    bundle = tmp_path / "cand"
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    monkeypatch.setattr(scorecard, "run_measure", lambda name, *a: {"exact": 80.0 if a[-1] == "val" else 70.0})
    for split in ("val", "test"):
        assert scorecard.main(["--bundle", str(bundle), "--measures", "pockets-all,mismatched", "--split", split,
                               "--out", str(tmp_path / "out")]) == 0
    kept = tmp_path / "out" / "cand"
    assert json.loads((kept / "pockets-all-val-int8.json").read_text())["exact"] == 80.0
    assert json.loads((kept / "pockets-all-int8.json").read_text())["exact"] == 70.0
    assert sorted(p.name for p in kept.glob("mismatched*")) == ["mismatched-int8.json"]    # its frames either way
    assert "| every type's pockets within 2 cm and 1 degree, exact depth (%) | 70 | >= 95 |" in capsys.readouterr().out


@pytest.mark.parametrize("name, fields", [("weak_boxes", {"min_agreement": 0.9}),
                                          ("level", {"floor_from_depth": True})])
def test_a_variant_may_set_the_nested_options(scorecard, tmp_path, monkeypatch, name, fields):
    from pallet6d.runtime.level import LevelParams
    from pallet6d.runtime.weak_boxes import WeakBoxes

    bundle = tmp_path / "cand"
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    seen = []
    monkeypatch.setattr(scorecard, "run_measure", lambda name, bundle, precision, options, *a: seen.append(options)
                        or {"kept": 0})
    assert scorecard.main(["--bundle", str(bundle), "--measures", "mismatched", "--out", str(tmp_path / "out"),
                           "--variant", "v=" + json.dumps({name: fields})]) == 0
    assert seen[1][name] == {"weak_boxes": WeakBoxes, "level": LevelParams}[name](**fields)
    assert scorecard.options_json(seen[1]) == {name: fields}


@pytest.mark.parametrize("args, words", [
    (["--measures", "speed"], "unknown measures"),
    (["--variant", "x"], "give a label"),
    (["--variant", "a b={}"], "give a label"),
    (["--variant", "={}"], "give a label"),
    (["--variant", "v={not json"], "--variant v"),
    (["--variant", 'v={"speed": 1}'], "unknown estimator options"),
    (["--variant", 'v={"structure": {"speed": 1}}'], "unknown structure check fields"),
    (["--variant", 'v={"weak_boxes": {"speed": 1}}'], "unknown weak box fields"),
    (["--variant", 'v={"weak_boxes": {"min_agreement": 2}}'], "WeakBoxes.min_agreement"),
    (["--variant", 'v={"min_fit": 2}'], "min_fit"),
    (["--variant", "v={}", "--variant", "v={}"], "labels must differ"),
    (["--bundle", "NOT-A-BUNDLE"], "not a bundle folder"),
    (["--bundle", "SAME-NAME"], "different names"),
])
def test_bad_arguments_are_refused(scorecard, tmp_path, capsys, args, words):
    bundle = tmp_path / "a" / "b1"
    bundle.mkdir(parents=True)
    (bundle / "manifest.json").write_text("{}")
    argv = ["--bundle", str(bundle), "--out", str(tmp_path / "out")]
    if args[1] == "NOT-A-BUNDLE":
        args = ["--bundle", str(tmp_path / "nothing")]
    elif args[1] == "SAME-NAME":
        shutil.copytree(bundle, tmp_path / "b1")
        args = ["--bundle", str(tmp_path / "b1")]
    with pytest.raises(SystemExit):
        scorecard.main(argv + args)
    assert words in capsys.readouterr().err


def test_mismatched_inputs_are_measured_on_validation_seeds_and_held_out_on_test_seeds(scorecard, monkeypatch,
                                                                                        tmp_path):
    seen = {}
    monkeypatch.setattr(scorecard, "measure_mismatched", lambda *a: seen.setdefault(len(seen), a[3:]) and {})
    scorecard.run_measure("mismatched", tmp_path, "int8", {}, False, tmp_path / "test-sets", tmp_path / "data")
    scorecard.run_measure("mismatched-heldout", tmp_path, "int8", {}, False, tmp_path / "test-sets",
                          tmp_path / "data")
    assert seen[0] == (30, tmp_path / "data")                                       # VAL_SEEDS by default
    assert seen[1] == (30, tmp_path / "test-sets", {"virtual-clean": 9001, "virtual-occluded": 9002,
                                                    "indoor-noisy": 9003})


@pytest.mark.parametrize("gained, lost, p", [(0, 0, 1.0), (3, 3, 1.0), (5, 0, 2 / 32), (0, 5, 2 / 32),
                                             (10, 0, 2 / 1024), (7, 1, 2 * 9 / 256), (1, 2, 1.0),
                                             (600, 600, 1.0), (0, 1100, 0.0)])
def test_the_sign_test_on_the_pallets_two_bundles_disagree_on(scorecard, gained, lost, p):
    assert scorecard.sign_test(gained, lost) == pytest.approx(p)


def test_within_5cm_bits_keep_each_pallets_outcome_in_order(scorecard):
    records = [{"add_sym_m": 0.01}, {"add_sym_m": None}, {"add_sym_m": 0.05}, {"add_sym_m": 0.0499}]
    assert scorecard.within_5cm_bits(records) == "1001"
    assert scorecard.within_5cm_bits(None) == ""


def test_bundles_are_compared_pallet_by_pallet_with_the_first(scorecard):
    shipped = {"presets": {"virtual-clean-within5": "1111000011", "indoor-noisy-within5": "1110"},
               "forklift": {"mixed-within5": "10"}}
    cand = {"presets": {"virtual-clean-within5": "1011110001", "indoor-noisy-within5": "111"},
            "forklift": {"mixed-within5": "10"}}
    text = scorecard.paired_table(["shipped", "cand"], [shipped, cand])
    rows = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines() if line.startswith("|")}
    assert rows["virtual-clean within 5 cm (10)"].endswith("| +2 / -2 (p 1) |")
    assert rows["mixed within 5 cm, calibrated (2)"].endswith("| +0 / -0 (p 1) |")
    assert not any(k.startswith("indoor-noisy") for k in rows)     # measured on other frames: not compared
    assert scorecard.paired_table(["shipped"], [shipped]) == ""
    assert scorecard.paired_table(["a", "b"], [{"presets": {}}, {"presets": {}}]) == ""


def test_the_presets_keep_each_pallets_outcome_over_the_pooled_seeds(scorecard, monkeypatch, tmp_path):
    import pallet6d.export.accuracy_report as accuracy_report
    import pallet6d.runtime.eval_cli as eval_cli

    outcomes = {8011: [0.01, None], 8021: [0.2], 8012: [], 8022: [0.03], 8013: [None], 8023: [0.04, 0.06],
                8033: [0.01]}

    def evaluate(est, seed, split_name):
        errs = outcomes[seed]
        return {"summary": {"n_gt": len(errs), "add_sym_acc": {"0.05": 0.5}, "missed_by_reason": {}},
                "records": [{"add_sym_m": e} for e in errs]}

    monkeypatch.setattr(accuracy_report, "ensure_test_set", lambda preset, frames, root, seed: seed)
    monkeypatch.setattr(eval_cli, "evaluate_dataset", evaluate)
    monkeypatch.setattr(scorecard, "_estimator", lambda *a, **k: None)
    res = scorecard.measure_presets(tmp_path, "int8", {}, 100, tmp_path, "val")
    assert res["virtual-clean-within5"] == "100"
    assert res["virtual-occluded-within5"] == "1"
    assert res["indoor-noisy-within5"] == "0101"


def test_pocket_targets_keep_each_targets_outcome_and_are_compared(scorecard, monkeypatch, tmp_path):
    import forklift_pockets

    rows = [{"pocket_err_m": 0.01, "yaw_err_deg": 0.5}, {"pocket_err_m": 0.03, "yaw_err_deg": 0.5},
            {"pocket_err_m": 0.01, "yaw_err_deg": 1.5}, {"missed": "no_box"}]
    summary = {"within_2cm_1deg": 0.25, "pallets": 4, "detected": 3, "pick_safe_table": {"blocked->safe": 0},
               "rows": rows}
    monkeypatch.setattr(scorecard, "_forklift_frames", lambda *a: tmp_path)
    monkeypatch.setattr(scorecard, "_estimator", lambda *a, **k: None)
    monkeypatch.setattr(forklift_pockets, "npz_frames", lambda root: iter(()))
    monkeypatch.setattr(forklift_pockets, "evaluate", lambda *a: {"clean": summary, "d435": summary})
    res = scorecard.measure_pockets(tmp_path, "int8", {}, 60, tmp_path)
    assert res["exact-ok"] == res["d435-ok"] == "1000"
    other = dict(res, **{"exact-ok": "0110"})
    text = scorecard.paired_table(["shipped", "cand"], [{"pockets": res}, {"pockets": other}])
    assert "| EPAL pocket targets, exact depth (4) | +2 / -1 (p 1) |" in text
    assert "| EPAL pocket targets, D435-like depth (4) | +0 / -0 (p 1) |" in text


def test_pallet_free_frames_keep_each_frames_outcome_and_are_compared(scorecard, monkeypatch, tmp_path):
    import real_data

    accepted = {("virtual-clean", 9300): [0, 2], ("forklift-approach", 9300): [1, 0],
                ("forklift-approach", 9400): [0, 0]}

    def sim_negatives(est, presets, frames, seed, calibrated, set_down, cache):
        runs = {p: accepted.get((p, seed), [0, 0]) for p in presets}
        return {p: {"frames": len(a), "accepted_by_frame": a} for p, a in runs.items()}

    monkeypatch.setattr(real_data, "sim_negatives", sim_negatives)
    monkeypatch.setattr(scorecard, "_estimator", lambda *a, **k: None)
    res = scorecard.measure_negatives(tmp_path, "int8", {}, 2, tmp_path, (9300, 9400))
    # five presets a seed, in order; the forklift views' calibrated run has two
    assert res["set_down"] == 3 and res["set_down-frames"] == 20
    assert res["set_down-clear"] == "10" + "11" * 2 + "01" + "11" + "11" * 5
    assert res["calibrated-clear"] == "01" + "11" + "11" + "11" and res["calibrated"] == 1
    assert res["hanging-clear"] == "10" + "11" * 2 + "01" + "11" and res["seeds"] == [9300, 9400]
    other = dict(res, **{"set_down-clear": "11" * 10})
    text = scorecard.paired_table(["shipped", "cand"], [{"negatives-heldout": res}, {"negatives-heldout": other}])
    assert ("| pallet-free frames of the held-out seeds, loads set down: without a pose (20) | +2 / -0 (p 0.5) |"
            in text)


@pytest.mark.parametrize("kept, stale", [
    ({"seeds": [9300], "set_down-clear": "1"}, True),             # fewer seeds than the measure now takes
    ({"seeds": [9300, 9400, 9500]}, True),                          # kept without each frame's outcome
    ({"seeds": [9300, 9400, 9500], "set_down-clear": "1"}, False),
])
def test_pallet_free_results_of_other_seeds_are_measured_again(scorecard, tmp_path, kept, stale):
    path = tmp_path / "negatives-heldout-int8.json"
    path.write_text(json.dumps(kept))
    assert scorecard._stale("negatives-heldout", "test", path) is stale
