import numpy as np
import pytest

from pallet6d.runtime.evaluation import (Estimate, GroundTruth, box_iou, evaluate_frame, records_to_dicts,
                                         summarize)
from pallet6d.runtime.geometry import make_T

PTS = np.random.default_rng(0).uniform([-0.6, -0.4, -0.07], [0.6, 0.4, 0.07], size=(300, 3))
SYMS = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])


def gt(x, box, visib=1.0):
    return GroundTruth(make_T(np.eye(3), [x, 0, 3.0]), np.array(box, float), visib)


def est(x, box, score=0.9, R=np.eye(3)):
    return Estimate(make_T(R, [x, 0, 3.0]), np.array(box, float), score)


def test_box_iou():
    iou = box_iou(np.array([[0, 0, 10, 10], [5, 5, 15, 15]]), np.array([[0, 0, 10, 10], [20, 20, 30, 30]]))
    np.testing.assert_allclose(iou, [[1.0, 0.0], [25 / 175, 0.0]])
    assert box_iou(np.zeros((0, 4)), np.zeros((2, 4))).shape == (0, 2)


def test_perfect_and_missed_and_false_positive():
    gts = [gt(0.0, [0, 0, 100, 50]), gt(2.0, [200, 0, 300, 50])]
    ests = [est(0.03, [0, 0, 100, 50]), est(0.0, [500, 0, 600, 50], score=0.5)]   # 3 cm off; one FP
    records, tp, fp = evaluate_frame(0, ests, gts, PTS, SYMS)
    assert (tp, fp) == (1, 1)
    assert records[0].detected and records[0].add_m == pytest.approx(0.03)
    assert not records[1].detected and np.isinf(records[1].add_m)
    s = summarize(records, tp, fp)
    assert s["n_gt"] == 2 and s["precision"] == 0.5 and s["recall"] == 0.5
    assert s["add_acc"] == {"0.02": 0.0, "0.05": 0.5, "0.1": 0.5}
    assert records_to_dicts(records)[1]["add_m"] is None


def test_symmetric_flip_counts_for_add_sym_only():
    Rz180 = np.diag([-1.0, -1.0, 1.0])
    records, tp, fp = evaluate_frame(0, [est(0.0, [0, 0, 100, 50], R=Rz180)], [gt(0.0, [0, 0, 100, 50])], PTS, SYMS)
    s = summarize(records, tp, fp)
    assert s["add_acc"]["0.1"] == 0.0 and s["add_sym_acc"]["0.02"] == 1.0


def test_hidden_pallets_do_not_count_and_their_detections_are_ignored():
    gts = [gt(0.0, [0, 0, 100, 50], visib=0.05)]
    records, tp, fp = evaluate_frame(0, [est(0.0, [0, 0, 100, 50])], gts, PTS, SYMS)
    assert records == [] and (tp, fp) == (0, 0)
    s = summarize(records, tp, fp)
    assert s["n_gt"] == 0 and s["recall"] == 0.0 and s["by_distance"] == []


def test_outcomes_by_visibility():
    # boxes far apart so each estimate matches its own pallet; errors along x: 3 cm, 7 cm, 30 cm, missed
    gts = [gt(0.0, [0, 0, 100, 50], visib=0.2), gt(0.0, [200, 0, 300, 50], visib=0.2),
           gt(0.0, [400, 0, 500, 50], visib=1.0), gt(0.0, [600, 0, 700, 50], visib=0.7)]
    ests = [est(0.03, [0, 0, 100, 50]), est(0.07, [200, 0, 300, 50]), est(0.3, [400, 0, 500, 50])]
    records, tp, fp = evaluate_frame(0, ests, gts, PTS, SYMS)
    bins = summarize(records, tp, fp)["by_visibility"]
    assert [(b["from"], b["to"], b["n_gt"]) for b in bins] == [(0.1, 0.3, 2), (0.6, 1.0, 2)]   # empty bin left out
    low, high = bins
    assert (low["add_sym_lt_5cm"], low["add_sym_5_10cm"], low["add_sym_ge_10cm"], low["missed"]) == (0.5, 0.5, 0, 0)
    assert (high["add_sym_lt_5cm"], high["add_sym_5_10cm"], high["add_sym_ge_10cm"], high["missed"]) == (0, 0, .5, .5)
    assert summarize([], 0, 0)["by_visibility"] == []


def test_outcomes_in_view_and_cut_by_the_image_border():
    truncated = GroundTruth(make_T(np.eye(3), [2.0, 0, 3.0]), np.array([200, 0, 300, 50], float), 0.2, truncated=True)
    gts = [gt(0.0, [0, 0, 100, 50]), truncated, gt(4.0, [400, 0, 500, 50])]
    ests = [est(0.01, [0, 0, 100, 50]), est(2.3, [200, 0, 300, 50])]   # in view: 1 cm and missed; cut: 30 cm
    records, tp, fp = evaluate_frame(0, ests, gts, PTS, SYMS)
    assert [r.truncated for r in records] == [False, True, False]
    in_view, cut = summarize(records, tp, fp)["by_truncation"]
    assert (in_view["truncated"], in_view["n_gt"], in_view["add_sym_lt_5cm"], in_view["missed"]) == (False, 2, .5, .5)
    assert (cut["truncated"], cut["n_gt"], cut["add_sym_ge_10cm"], cut["missed"]) == (True, 1, 1.0, 0.0)
    assert summarize(records[:1], 1, 0)["by_truncation"] == [
        {"truncated": False, "n_gt": 1, "missed": 0.0, "add_sym_ge_10cm": 0.0, "add_sym_5_10cm": 0.0,
         "add_sym_lt_5cm": 1.0}]   # a group without pallets is left out


@pytest.mark.parametrize("bbox_obj, image_hw, truncated", [
    ([10, 10, 50, 20], (100, 200), False),
    ([150, 10, 50, 20], (100, 200), False),   # touches the right edge: still in view
    ([151, 10, 50, 20], (100, 200), True),
    ([-1, 10, 50, 20], (100, 200), True),
    ([10, 90, 50, 20], (100, 200), True),
    ([-1, 10, 50, 20], None, False),          # image size unknown
    (None, (100, 200), False),                # no bbox_obj in the annotations
])
def test_ground_truth_truncation_from_bop(bbox_obj, image_hw, truncated):
    from pallet6d.runtime.bop import BopGT
    from pallet6d.runtime.evaluation import ground_truths_from_bop

    g = BopGT(1, make_T(np.eye(3), [0, 0, 3.0]), bbox_obj_xywh=None if bbox_obj is None else np.array(bbox_obj),
              bbox_visib_xywh=np.array([20, 20, 10, 10]), visib_fract=0.5)
    gts, skipped = ground_truths_from_bop([g], image_hw)
    assert skipped == 0 and gts[0].truncated is truncated


def test_one_estimate_matches_one_pallet():
    gts = [gt(0.0, [0, 0, 100, 50]), gt(0.0, [0, 0, 100, 52])]
    records, tp, fp = evaluate_frame(0, [est(0.0, [0, 0, 100, 50])], gts, PTS, SYMS)
    assert tp == 1 and sum(r.detected for r in records) == 1
