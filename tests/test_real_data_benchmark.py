"""benchmarks/real_data.py: greedy matching at IoU 0.5 by score, and the report's tallies, on hand-made boxes."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("real_data_benchmark",
                                               Path(__file__).parents[1] / "benchmarks" / "real_data.py")
bench = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = bench        # its dataclasses look their module up
_spec.loader.exec_module(bench)

GT = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)


def test_the_higher_score_takes_the_box_and_the_duplicate_is_a_false_positive():
    pred = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10]], float)
    tp, matched = bench.match_greedy(pred, np.array([0.5, 0.9, 0.3]), GT)
    # the 0.9 box (IoU 0.82 with box 0) comes first and takes it; the exact 0.5 box finds it taken
    assert tp.tolist() == [False, True, True] and matched.tolist() == [True, True]


def test_iou_threshold_is_inclusive_and_below_it_nothing_matches():
    gt = np.array([[0, 0, 10, 10]], float)
    half = np.array([[0, 0, 10, 20]], float)          # IoU exactly 0.5
    assert bench.match_greedy(half, np.array([1.0]), gt)[0].tolist() == [True]
    loose = np.array([[0, 0, 10, 21]], float)         # IoU 0.476
    assert bench.match_greedy(loose, np.array([1.0]), gt)[0].tolist() == [False]


def test_a_detection_takes_its_best_overlap_not_the_first_box():
    gt = np.array([[0, 0, 10, 10], [2, 0, 12, 10]], float)
    tp, matched = bench.match_greedy(np.array([[2, 0, 12, 10]], float), np.array([0.8]), gt)
    assert tp.tolist() == [True] and matched.tolist() == [False, True]


@pytest.mark.parametrize("pred, gt", [(np.zeros((0, 4)), GT), (GT, np.zeros((0, 4))), (np.zeros((0, 4)),
                                                                                           np.zeros((0, 4)))])
def test_empty_inputs(pred, gt):
    tp, matched = bench.match_greedy(pred, np.ones(len(pred)), gt)
    assert tp.shape == (len(pred),) and matched.shape == (len(gt),) and not tp.any() and not matched.any()


def test_scores_must_match_boxes():
    with pytest.raises(ValueError, match="scores"):
        bench.match_greedy(GT, np.ones(3), GT)


def test_report_tallies_size_kind_convention_and_negatives():
    rep = bench.RealDataReport()
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
    assert d["negative_frames"] == 1 and d["false_positives_per_negative_frame"] == 3.0
    assert "overall" in bench.markdown("t", d, {"split": "heldout"})
