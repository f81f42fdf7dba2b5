"""export/real_data_report.py (benchmarks/real_data.py): the report's tallies on hand-made boxes (the matching
itself: tests/test_evaluation.py, `match_greedy`)."""
import numpy as np
import pytest

from pallet6d.export.real_data_report import RealDataReport, markdown


def test_report_tallies_size_kind_convention_and_negatives():
    rep = RealDataReport()
    # 100 px tall image: box 0 is 10 % (medium), box 1 is 5 % (small), box 2 is 50 % (large)
    rec = {"source": "a", "convention": "whole_pallet", "kinds": ["wood"], "height": 100, "negative": False,
           "boxes_xyxy": [[0, 0, 10, 10], [20, 0, 30, 5], [40, 0, 60, 50]]}
    pred = np.array([[0, 0, 10, 10], [40, 0, 60, 50], [70, 70, 80, 72]], float)
    rep.add_image(rec, pred, np.array([0.9, 0.8, 0.7]), 0.5)
    rep.add_image({**rec, "source": "b", "convention": "loaded_unit", "kinds": ["plastic"]}, pred[:1],
                  np.array([0.9]), 0.5)
    rep.add_image({**rec, "negative": True, "boxes_xyxy": []}, pred, np.ones(3), 0.5)
    d = rep.to_dict()
    assert d["overall"]["boxes"] == 3 and d["overall"]["recall"] == pytest.approx(2 / 3)
    assert d["overall"]["precision"] == pytest.approx(2 / 3)
    assert d["by_size"]["small"]["recall"] == 0.0 and d["by_size"]["small"]["precision"] == 0.0
    assert d["by_size"]["medium"]["recall"] == 1.0 and d["by_size"]["large"]["precision"] == 1.0
    assert "plastic" not in d["by_kind"] and d["by_kind"]["wood"]["boxes"] == 3
    assert d["other_convention"]["b"]["recall"] == pytest.approx(1 / 3)
    # a source with photos of both conventions: its row holds its whole-pallet photos only
    rep.add_image({**rec, "source": "b", "kinds": ["plastic"]}, pred, np.array([0.9, 0.8, 0.7]), 0.5)
    d = rep.to_dict()
    assert d["by_source"]["b"]["boxes"] == 3 and d["other_convention"]["b"]["boxes"] == 3
    assert d["by_kind"]["plastic"]["recall"] == pytest.approx(2 / 3)
    assert d["negative_frames"] == 1 and d["false_positives_per_negative_frame"] == 3.0
    assert "overall" in markdown("t", d, {"split": "heldout"})


def test_the_benchmark_without_imported_photographs_says_what_to_run(tmp_path, capsys):
    import importlib.util
    from pathlib import Path

    script = Path(__file__).parents[1] / "benchmarks" / "real_data.py"
    spec = importlib.util.spec_from_file_location("real_data_benchmark", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--bundle", str(tmp_path / "bundle"), "--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "labels.json not found" in err and "pallet6d.export.real_data import" in err


def test_pallet_free_frames_kept_in_a_cache_come_back_the_same(tmp_path):
    import importlib.util
    from pathlib import Path

    script = Path(__file__).parents[1] / "benchmarks" / "real_data.py"
    spec = importlib.util.spec_from_file_location("real_data_benchmark", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rendered = mod.pallet_free_frame("forklift-approach", 3, 0, True, tmp_path)
    assert [p.name for p in tmp_path.rglob("*.npz")] == ["forklift-approach-3-0.npz"]
    again = mod.pallet_free_frame("forklift-approach", 3, 0, True, tmp_path)
    for a, b in zip(rendered, again):
        np.testing.assert_array_equal(a, b)
    assert again[3].shape == (4, 4)                       # a forklift view keeps its calibration
    assert mod.pallet_free_frame("virtual-clean", 3, 0, False, tmp_path)[3] is None


def test_threshold_counts_recall_and_precision_while_ap_counts_every_detection():
    rep = RealDataReport()
    # 100 px tall image, two large boxes (50 % of the height)
    rec = {"source": "a", "convention": "whole_pallet", "kinds": ["wood"], "height": 100, "negative": False,
           "boxes_xyxy": [[0, 0, 50, 50], [60, 0, 110, 50]]}
    pred = np.array([[0, 0, 50, 50], [200, 0, 250, 50], [60, 0, 110, 50]], float)   # hit, miss, hit
    rep.add_image(rec, pred, np.array([0.9, 0.5, 0.1]), 0.5, score_threshold=0.25)
    rep.add_image({**rec, "negative": True, "boxes_xyxy": []}, pred, np.array([0.9, 0.5, 0.1]), 0.5,
                  score_threshold=0.25)
    d = rep.to_dict()
    o = d["overall"]
    assert (o["boxes"], o["detections"], o["recall"], o["precision"]) == (2, 2, 0.5, 0.5)
    # every detection, by score: hit (P 1, R 0.5), miss, hit (P 2/3, R 1): AP = 0.5 * 1 + 0.5 * 2/3
    assert o["average_precision"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    assert d["by_size"]["large"]["average_precision"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    assert d["false_positives_per_negative_frame"] == 2.0          # the pallet-free photo: above the threshold only
    assert "| 0.833 |" in markdown("t", d, {})


def test_ap_by_size_follows_the_matched_box():
    """A small detection matched to a medium box counts for the medium AP; an unmatched one for its own size."""
    rep = RealDataReport()
    rec = {"source": "a", "convention": "whole_pallet", "kinds": ["wood"], "height": 100, "negative": False,
           "boxes_xyxy": [[0, 0, 10, 10]]}                                     # medium (10 %)
    pred = np.array([[0, 1, 10, 8.5], [50, 0, 55, 5]], float)                 # 7.5 px: small, matched; small, wrong
    rep.add_image(rec, pred, np.array([0.9, 0.8]), 0.5)
    d = rep.to_dict()["by_size"]
    assert d["medium"]["average_precision"] == pytest.approx(1.0)
    assert d["small"]["boxes"] == 0 and d["small"]["average_precision"] is None
    assert d["small"]["detections"] == 2 and d["small"]["precision"] == 0.5
