import numpy as np
import pytest

from pallet6d.runtime.evaluation import (NO_DETECTION, Estimate, GroundTruth, Refused, box_iou, evaluate_frame,
                                         records_to_dicts, summarize)
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


def test_missed_pallets_are_told_why_from_the_refused_detections_over_them():
    gts = [gt(0.0, [0, 0, 100, 50]), gt(1.5, [200, 0, 300, 50]), gt(3.0, [400, 0, 500, 50]),
           gt(4.5, [600, 0, 700, 50]), gt(6.0, [800, 0, 900, 50])]
    refused = [Refused(np.array([200, 0, 300, 50.0]), "poor_fit", make_T(np.eye(3), [1.52, 0, 3.0])),   # 2 cm off
               Refused(np.array([400, 0, 500, 48.0]), "no_pallet_structure", make_T(np.eye(3), [3.3, 0, 3.0])),
               Refused(np.array([600, 0, 700, 50.0]), "low_confidence"),          # refused before a pose
               Refused(np.array([860, 0, 960, 50.0]), "poor_fit")]                 # IoU 0.25 with the last: no match
    records, tp, fp = evaluate_frame(0, [est(0.0, [0, 0, 100, 50])], gts, PTS, SYMS, refused=refused)
    assert [r.missed_reason for r in records] == [None, "poor_fit", "no_pallet_structure", "low_confidence",
                                                  NO_DETECTION]
    assert records[1].refused_add_sym_m == pytest.approx(0.02) and records[2].refused_add_sym_m == pytest.approx(0.3)
    assert np.isinf(records[3].refused_add_sym_m) and np.isinf(records[0].refused_add_sym_m)
    assert summarize(records, tp, fp)["missed_by_reason"] == {
        "low_confidence": {"n_gt": 1, "refused_within_5cm": 0}, NO_DETECTION: {"n_gt": 1, "refused_within_5cm": 0},
        "no_pallet_structure": {"n_gt": 1, "refused_within_5cm": 0}, "poor_fit": {"n_gt": 1, "refused_within_5cm": 1}}
    assert records_to_dicts(records)[3]["refused_add_sym_m"] is None
    no_refusals = evaluate_frame(0, [], gts[:1], PTS, SYMS).records
    assert no_refusals[0].missed_reason == NO_DETECTION


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


def test_outcomes_per_pallet_type_when_there_are_several():
    def typed(x, box, obj_id):
        return GroundTruth(make_T(np.eye(3), [x, 0, 3.0]), np.array(box, float), 1.0, obj_id=obj_id)

    gts = [typed(0.0, [0, 0, 100, 50], 1), typed(2.0, [200, 0, 300, 50], 10), typed(4.0, [400, 0, 500, 50], 10)]
    records, tp, fp = evaluate_frame(0, [est(0.01, [0, 0, 100, 50]), est(2.0, [200, 0, 300, 50])], gts, PTS, SYMS)
    assert [r.obj_id for r in records] == [1, 10, 10] and records_to_dicts(records)[1]["obj_id"] == 10
    one, ten = summarize(records, tp, fp)["by_object"]
    assert (one["obj_id"], one["n_gt"], one["add_sym_lt_5cm"]) == (1, 1, 1.0)
    assert (ten["obj_id"], ten["n_gt"], ten["add_sym_lt_5cm"], ten["missed"]) == (10, 2, 0.5, 0.5)
    assert "by_object" not in summarize(records[1:], 1, 0)      # one type: nothing to split


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


# -- which ground-truth pallets count ------------------------------------------------------------------------
def _ann(visib, box):
    from pallet6d.runtime.bop import BopGT

    return BopGT(1, np.eye(4), bbox_visib_xywh=None if box is None else np.array(box), visib_fract=visib)


@pytest.mark.parametrize("visib, box, rule, counts", [
    (0.1, [0, 0, 5, 5], {}, True),                                   # exactly the threshold counts
    (0.0999, [0, 0, 5, 5], {}, False),
    (0.5, None, {}, False),                                          # no visible box: nothing to match or crop
    (np.nan, [0, 0, 5, 5], {}, True),                                # evaluation: unknown visibility counts
    (np.nan, [0, 0, 5, 5], {"unknown_visib_counts": False}, False),  # training: it may be hidden entirely
    (0.5, [0, 0, 0, 5], {}, True),                                   # box size not checked by default
    (0.5, [0, 0, 1, 5], {"min_box_side_px": 2}, False),
    (0.5, [0, 0, 2, 1], {"min_box_side_px": 2}, False),
    (0.5, [0, 0, 2, 2], {"min_box_side_px": 2}, True),
    (0.2, [0, 0, 9, 9], {"min_visib_fract": 0.25}, False),
])
def test_counted_pallets_rule(visib, box, rule, counts):
    from pallet6d.runtime.evaluation import counted_pallets

    mask = counted_pallets([_ann(visib, box)], **rule)
    assert mask.dtype == bool and mask.tolist() == [counts]


def test_counted_pallets_of_none_and_of_evaluation_ground_truth():
    from pallet6d.runtime.evaluation import counted_pallets

    assert counted_pallets([]).shape == (0,)
    gts = [gt(0.0, [10, 20, 40, 30], visib=0.05), gt(0.0, [10, 20, 40, 30], visib=0.5)]
    assert counted_pallets(gts).tolist() == [False, True]
    np.testing.assert_array_equal(gts[0].bbox_visib_xywh, [10, 20, 30, 10])


def test_evaluate_poses_scores_the_estimator_output_like_evaluate_frame():
    from types import SimpleNamespace

    from pallet6d.runtime.evaluation import ScoreTally, evaluate_poses

    gts = [gt(0.0, [0, 0, 100, 50]), gt(2.0, [200, 0, 300, 50], visib=0.05)]
    poses = [SimpleNamespace(T_cam_pallet=make_T(np.eye(3), [0.01, 0, 3.0]), box_xyxy=np.array([0, 0, 100, 50.]),
                             detector_score=0.9),
             SimpleNamespace(T_cam_pallet=make_T(np.eye(3), [2.0, 0, 3.0]), box_xyxy=np.array([200, 0, 300, 50.]),
                             detector_score=0.8)]
    score = evaluate_poses(3, poses, gts, PTS, SYMS)
    records, tp, fp = score                                     # a hidden pallet's detection is ignored
    assert (len(records), tp, fp) == (1, 1, 0) and records[0].frame == 3 and records[0].detected
    tally = ScoreTally()
    assert not tally
    tally.add(score)
    tally.add(evaluate_poses(4, [], gts, PTS, SYMS))            # a failed frame: its pallet is missed
    s = tally.summary()
    assert tally and s["n_gt"] == 2 and s["recall"] == 0.5 and s["precision"] == 1.0


def test_match_greedy_takes_the_best_free_overlap_by_score():
    from pallet6d.runtime.evaluation import match_greedy

    gt_boxes = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)
    pred = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10], [50, 50, 60, 60]], float)
    match, matched = match_greedy(pred, np.array([0.5, 0.9, 0.3, 0.99]), gt_boxes)
    # the 0.9 box comes first and takes box 0; the exact 0.5 box then finds it taken; the far one matches nothing
    assert match.tolist() == [-1, 0, 1, -1] and matched.tolist() == [True, True]
    overlap = np.array([[0, 0, 10, 10], [2, 0, 12, 10]], float)
    assert match_greedy(overlap[1:], [0.8], overlap)[0].tolist() == [1]   # its best overlap, not the first box
    half = np.array([[0, 0, 10, 20]], float)                   # IoU exactly 0.5: inclusive
    assert match_greedy(half, [1.0], gt_boxes[:1])[0].tolist() == [0]
    assert match_greedy(np.array([[0, 0, 10, 21]], float), [1.0], gt_boxes[:1])[0].tolist() == [-1]
    for p, g in ((np.zeros((0, 4)), gt_boxes), (gt_boxes, np.zeros((0, 4))), (np.zeros((0, 4)), np.zeros((0, 4)))):
        m, mm = match_greedy(p, np.ones(len(p)), g)
        assert m.shape == (len(p),) and mm.shape == (len(g),) and not mm.any() and (m < 0).all()
    with pytest.raises(ValueError, match="scores"):
        match_greedy(gt_boxes, np.ones(3), gt_boxes)


def test_each_ground_truth_is_scored_with_its_own_model():
    """A pallet turned 180 degrees about x: a model symmetric under that turn scores it 0; the default one does not."""
    Rx180 = np.diag([1.0, -1.0, -1.0])
    flat = PTS * [1, 1, 0]                              # a flat model, symmetric under the turn about x
    flat_syms = np.stack([np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])])
    g = GroundTruth(make_T(np.eye(3), [0, 0, 3.0]), np.array([0, 0, 100, 50], float), 1.0, obj_id=2)
    e = [est(0.0, [0, 0, 100, 50], R=Rx180)]
    default, _, _ = evaluate_frame(0, e, [g], PTS, SYMS)
    own, _, _ = evaluate_frame(0, e, [g], PTS, SYMS, models={2: (flat, flat_syms)})
    other, _, _ = evaluate_frame(0, e, [g], PTS, SYMS, models={3: (flat, flat_syms)})
    assert default[0].add_sym_m > 0.05 and own[0].add_sym_m == pytest.approx(0.0, abs=1e-12)
    assert other[0].add_sym_m == default[0].add_sym_m


def test_dataset_models_prefer_the_bundles_type_else_the_mesh(sim_bop_dataset):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.evaluation import dataset_models
    from pallet6d.runtime.fit import distance_to_boxes
    from pallet6d.runtime.stage_geometry import PalletGeometry
    from pallet6d.sim.pallets import get_pallet_model

    ds = BopDataset(sim_bop_dataset)
    from_mesh = dataset_models(ds)
    assert len(from_mesh) == len(ds.models_info) > 1
    for obj_id, info in ds.models_info.items():
        model = get_pallet_model(info["name"])
        assert from_mesh[obj_id][0].shape == (2000, 3)
        assert distance_to_boxes(from_mesh[obj_id][0], model.boxes_m).max() < 1e-6   # on its boards and blocks
        np.testing.assert_allclose(from_mesh[obj_id][1], model.symmetries, atol=1e-9)
    obj_id, info = next(iter(ds.models_info.items()))
    g = PalletGeometry(info["name"], PTS, None, SYMS, np.ones(3), np.zeros((0, 3)))
    assert dataset_models(ds, [g])[obj_id][0] is PTS
