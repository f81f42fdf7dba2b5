"""Weak detections: posed with or without a calibration, kept only with clear structure, never seen by `detect`."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime.detector import Detections
from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator
from pallet6d.runtime.weak_boxes import CUT_NOTE, WeakBoxes, inside_fraction, weak_box_failures

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"


@pytest.mark.parametrize("agreement, open_fraction, box_cut, expected", [
    ([0.9], [0.9], None, [""]),
    ([0.85], [0.7], None, [""]),                              # the thresholds themselves pass
    ([0.85], [0.85], [True], [""]),
    ([0.8], [0.9], None, ["agreement 0.80 < 0.85"]),
    ([0.9], [0.4], None, ["openings open 0.40 < 0.7"]),
    ([0.9], [0.75], [False], [""]),
    ([0.9], [0.75], [True], ["openings open 0.75 < 0.85" + CUT_NOTE]),   # a cut box shows more, or is refused
    ([0.5], [0.1], [False], ["agreement 0.50 < 0.85, openings open 0.10 < 0.7"]),
    ([np.nan], [0.9], None, ["agreement nan < 0.85"]),       # no evidence is no clear structure
    ([0.9], [np.nan], [True], ["openings open nan < 0.85" + CUT_NOTE]),
    ([0.9, 0.9], [0.8, 0.8], [False, True], ["", "openings open 0.80 < 0.85" + CUT_NOTE]),
    ([], [], None, []),
])
def test_weak_box_failures(agreement, open_fraction, box_cut, expected):
    assert weak_box_failures(agreement, open_fraction, WeakBoxes(), box_cut) == expected


@pytest.mark.parametrize("agreement, open_fraction, box_cut, match", [
    ([0.9, 0.9], [0.9], None, "2 agreements but 1 open"), ([0.9], [0.9], [True, False], "and 2 cut flags")])
def test_weak_box_failures_needs_one_value_of_each_per_pose(agreement, open_fraction, box_cut, match):
    with pytest.raises(ValueError, match=match):
        weak_box_failures(agreement, open_fraction, WeakBoxes(), box_cut)


@pytest.mark.parametrize("field, value", [("score_threshold", -0.1), ("min_agreement", 1.5),
                                          ("min_open_fraction", "0.8"), ("min_open_fraction_cut", 1.2),
                                          ("score_threshold", True),
                                          ("min_agreement", float("nan"))])
def test_weak_box_params_are_checked(field, value):
    with pytest.raises(ValueError, match=f"WeakBoxes.{field}"):
        WeakBoxes(**{field: value})


def test_the_option_takes_weak_box_params_only():
    assert EstimatorOptions().weak_boxes == WeakBoxes()          # on by default
    with pytest.raises(TypeError, match="weak_boxes must be a WeakBoxes"):
        EstimatorOptions(weak_boxes={"score_threshold": 0.1})


@pytest.fixture(scope="module")
def forklift_frame():
    """A calibrated forklift-approach frame of EPALs (exact depth) and the boxes of its most visible pallets."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(dataclasses.replace(get_preset("forklift-approach"), pallet_models=("epal",)), seed=3)
    f = dataclasses.replace(f, depth_m=f.depth_ideal_m)
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in
                      (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.5)], float)
    assert len(boxes) >= 2
    return f, boxes


def _estimator(boxes, scores, **options):
    """The shipped bundle whose detector reports `boxes` with `scores` (the decoding's threshold applied)."""
    est = PalletEstimator.from_bundle(SHIPPED, threads=1, pallet_types=("epal",), **options)
    threshold = est.detector.score_threshold
    keep = np.asarray(scores) >= threshold
    det = Detections(boxes[keep], np.asarray(scores, float)[keep], np.zeros(int(keep.sum()), np.int64))
    est.detector.postprocess = lambda raw, lb: det
    return est


def _outcome(res):
    return sorted([(tuple(p.box_xyxy.round(3)), "accepted") for p in res.poses] +
                  [(tuple(r.box_xyxy.round(3)), r.reason) for r in res.rejected])


@pytest.mark.parametrize("calibrated", [True, False])
def test_weak_boxes_count_with_or_without_a_calibration_and_never_in_detect(forklift_frame, calibrated):
    f, boxes = forklift_frame
    T_vc = f.T_vehicle_cam if calibrated else None
    scores = np.full(len(boxes), 0.15)
    est = _estimator(boxes, scores, weak_boxes=WeakBoxes(min_agreement=0.0, min_open_fraction=0.0,
                                                         min_open_fraction_cut=0.0))
    assert est.detector.score_threshold == pytest.approx(0.1)     # the boxes are decoded down to the weak threshold
    assert len(est.detect(f.rgb)) == 0                           # `detect` keeps the detector's own threshold
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    assert len(res.poses) + len(res.rejected) == len(boxes)
    assert res.poses                                             # what the structure check accepts is kept
    off = _estimator(boxes, scores, weak_boxes=None)             # the option off: under the threshold is nothing
    assert off.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc).poses == []


@pytest.mark.parametrize("calibrated", [True, False])
def test_weak_boxes_are_judged_as_strong_ones_and_must_also_show_clear_structure(forklift_frame, calibrated):
    f, boxes = forklift_frame
    T_vc = f.T_vehicle_cam if calibrated else None
    strong = _estimator(boxes, np.full(len(boxes), 0.6), weak_boxes=WeakBoxes())
    ref = strong.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    assert ref.poses
    # weak boxes without demands beyond the structure check: the same poses and rejections
    lax = _estimator(boxes, np.full(len(boxes), 0.15), weak_boxes=WeakBoxes(min_agreement=0.0, min_open_fraction=0.0,
                                                                            min_open_fraction_cut=0.0))
    res = lax.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    assert _outcome(res) == _outcome(ref)
    for a, b in zip(res.poses, ref.poses):
        np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet)
    # demands no pose meets: every pose the structure check accepted is refused, and says why
    strict = _estimator(boxes, np.full(len(boxes), 0.15), weak_boxes=WeakBoxes(min_agreement=1.0,
                                                                                 min_open_fraction=1.0,
                                                                                 min_open_fraction_cut=1.0))
    res = strict.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    accepted = {tuple(p.box_xyxy.round(3)) for p in ref.poses}
    refused_weak = [r for r in res.rejected if "weak detection (score 0.15)" in r.detail]
    assert {tuple(r.box_xyxy.round(3)) for r in res.poses} <= accepted
    assert len(res.poses) + len(refused_weak) == len(accepted)
    assert refused_weak and all(r.reason == "no_pallet_structure" and r.pose is not None for r in refused_weak)
    # a strong box beside weak ones is judged as before
    mixed_scores = np.full(len(boxes), 0.15)
    mixed_scores[0] = 0.6
    res = _estimator(boxes, mixed_scores, weak_boxes=WeakBoxes(min_agreement=1.0, min_open_fraction=1.0,
                                                                           min_open_fraction_cut=1.0)).estimate(
        f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    first = tuple(boxes[0].round(3))
    assert dict(_outcome(res))[first] == dict(_outcome(ref))[first]


@pytest.mark.parametrize("calibrated", [True, False])
def test_weak_boxes_without_a_structure_check_are_refused(forklift_frame, calibrated):
    f, boxes = forklift_frame
    est = _estimator(boxes, np.full(len(boxes), 0.15), weak_boxes=WeakBoxes(), structure=None)
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam if calibrated else None)
    assert res.poses == []
    assert any("the structure check is off" in r.detail for r in res.rejected)


@pytest.mark.parametrize("flags, expected", [([], WeakBoxes()), (["--no-weak-boxes"], None)])
def test_the_command_line_turns_weak_boxes_off(flags, expected):
    import argparse

    from pallet6d.runtime.estimator_cli import add_estimator_arguments, load_estimator

    parser = argparse.ArgumentParser()
    add_estimator_arguments(parser)
    est = load_estimator(parser.parse_args(["--bundle", str(SHIPPED), "--threads", "1", *flags]), "run")
    assert est.options.weak_boxes == expected


@pytest.mark.parametrize("boxes, others, expected", [
    ([[0, 0, 10, 10]], [[0, 0, 20, 20]], [1.0]),
    ([[0, 0, 10, 10]], [[5, 0, 20, 20], [0, 0, 2, 2]], [0.5]),      # the most of it inside one of them
    ([[0, 0, 10, 10]], [[20, 20, 30, 30]], [0.0]),
    ([[0, 0, 10, 10]], np.zeros((0, 4)), [0.0]),
    ([[5, 5, 5, 9]], [[0, 0, 20, 20]], [0.0]),                        # no area
    (np.zeros((0, 4)), [[0, 0, 1, 1]], []),
])
def test_inside_fraction(boxes, others, expected):
    np.testing.assert_allclose(inside_fraction(boxes, others), expected)


def test_a_weak_box_inside_a_stronger_one_is_not_posed(forklift_frame):
    f, boxes = forklift_frame
    part = boxes[0] + np.array([0.05, 0.05, -0.05, -0.05]) * (boxes[0][2] - boxes[0][0])
    est = _estimator(np.vstack([boxes[:1], part[None]]), np.array([0.6, 0.15]))
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    (dup,) = [r for r in res.rejected if r.detector_score == pytest.approx(0.15)]
    assert dup.reason == "duplicate" and "inside a stronger" in dup.detail and dup.pose is None


def test_weak_boxes_the_network_is_unsure_of_go_no_further(forklift_frame, monkeypatch):
    f, boxes = forklift_frame
    est = _estimator(boxes, np.full(len(boxes), 0.15),
                     weak_boxes=WeakBoxes(min_agreement=0, min_open_fraction=0, min_open_fraction_cut=0,
                                          min_confidence=1.0), min_confidence=1.0)
    refined = []
    real = est.refiner.__class__.__call__

    def spy(self, cands, *args, **kwargs):
        refined.append(int(cands.alive.sum()))
        return real(self, cands, *args, **kwargs)

    monkeypatch.setattr(est.refiner.__class__, "__call__", spy)
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert res.poses == [] and {r.reason for r in res.rejected} == {"low_confidence"}
    assert refined and not any(refined)          # none of them reached the refinement (nor the depth's proposals)


def test_a_box_at_the_threshold_itself_is_weak_as_the_decoding_says(forklift_frame):
    f, boxes = forklift_frame
    est = _estimator(boxes, np.full(len(boxes), 0.25), weak_boxes=WeakBoxes(min_agreement=1.0, min_open_fraction=1.0,
                                                                           min_open_fraction_cut=1.0))
    assert len(est.detect(f.rgb)) == 0                           # the decoding keeps scores above its threshold
    res = est.estimate(f.rgb, f.depth_m, f.K)
    assert any("weak detection (score 0.25)" in r.detail for r in res.rejected)


def test_poses_the_network_is_unsure_of_are_weak_with_a_calibration(forklift_frame):
    f, boxes = forklift_frame
    T_vc = f.T_vehicle_cam
    ref = _estimator(boxes, np.full(len(boxes), 0.6)).estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    assert ref.poses
    # every pose under `min_confidence` but above the weak floor: judged as before when weak poses need nothing more
    lax = _estimator(boxes, np.full(len(boxes), 0.6), min_confidence=1.0,
                     weak_boxes=WeakBoxes(min_agreement=0.0, min_open_fraction=0.0, min_open_fraction_cut=0.0,
                                          min_confidence=0.0))
    assert _outcome(lax.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)) == _outcome(ref)
    # ...and refused, saying why, where they must show more than any pose does
    strict = _estimator(boxes, np.full(len(boxes), 0.6), min_confidence=1.0,
                        weak_boxes=WeakBoxes(min_agreement=1.0, min_open_fraction=1.0, min_open_fraction_cut=1.0,
                                             min_confidence=0.0))
    res = strict.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    unsure = [r for r in res.rejected if "a pose of network confidence" in r.detail]
    accepted = {tuple(p.box_xyxy.round(3)) for p in ref.poses}
    assert {tuple(p.box_xyxy.round(3)) for p in res.poses} <= accepted      # a flawless pose passes even so
    assert unsure and len(res.poses) + len(unsure) == len(accepted)
    assert all(r.reason == "no_pallet_structure" and r.pose is not None for r in unsure)
    # without a calibration the confidence floor is `min_confidence` itself
    plain = strict.estimate(f.rgb, f.depth_m, f.K)
    assert plain.poses == [] and {r.reason for r in plain.rejected} == {"low_confidence"}
