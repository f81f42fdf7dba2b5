"""The frame-level registration test: registered depth passes, shifted or another frame's depth is refused, and
inputs that cannot judge give no evidence either way."""
import dataclasses

import numpy as np
import pytest

from pallet6d.runtime.candidates import Candidates
from pallet6d.runtime.detector import Detections
from pallet6d.runtime.registration import RegistrationScore, pair_auc, registration_region, registration_score
from pallet6d.runtime.structure import (StructureParams, StructureScore, frame_registration, frame_size_rule,
                                        registration_verdict)

H, W = 240, 320
WALL_M = 6.0


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cartons of random size, range and colour in front of a grey wall: (H, W) depth metres, (H, W, 3) uint8 RGB
    (shaded by range, sensor noise), (n, 4) the cartons' boxes."""
    rng = np.random.default_rng(seed)
    depth = np.full((H, W), WALL_M, np.float32)
    rgb = np.empty((H, W, 3))
    rgb[:] = (90.0, 95.0, 105.0)
    boxes = []
    for _ in range(6):
        w, h = rng.integers(40, 90, 2)
        x0, y0 = rng.integers(0, W - w), rng.integers(0, H - h)
        boxes.append([x0, y0, x0 + w, y0 + h, rng.uniform(1.5, 4.5)])
    for x0, y0, x1, y1, z in sorted(boxes, key=lambda b: -b[4]):      # nearer cartons hide farther ones
        depth[y0:y1, x0:x1] = z
        rgb[y0:y1, x0:x1] = rng.uniform(30, 230, 3)
    rgb = rgb * (1.0 - 0.03 * depth)[..., None] + rng.normal(0, 3.0, rgb.shape)
    return depth, np.clip(rgb, 0, 255).astype(np.uint8), np.array(boxes)[:, :4].astype(float)


DEPTH, RGB, BOXES = _frame(0)
OTHER_DEPTH, _, _ = _frame(1)
P = StructureParams()


def _score(depth=DEPTH, rgb=RGB, boxes=BOXES) -> RegistrationScore:
    return frame_registration(depth, rgb, boxes, P)[0]


def test_registered_frame_has_a_clear_peak_at_zero_shift():
    s, refused = frame_registration(DEPTH, RGB, BOXES, P)
    assert s.judged and not refused and registration_verdict(s, P) == "", s
    assert s.auc_0 > 0.85 and s.peak > 0.2, s
    assert s.jump_pairs >= P.registration_min_pairs and s.other_pairs >= P.registration_min_pairs


@pytest.mark.parametrize("name,depth", [
    ("another frame's depth", OTHER_DEPTH),
    ("depth shifted 24 px right", np.roll(DEPTH, 24, axis=1)),
    ("depth shifted 24 px down", np.roll(DEPTH, 24, axis=0)),
    ("depth shifted 12 px left", np.roll(DEPTH, -12, axis=1)),
])
def test_depth_that_is_not_this_images_is_refused(name, depth):
    s, refused = frame_registration(depth, RGB, BOXES, P)
    assert s.judged and refused and registration_verdict(s, P) == "mismatch", (name, s)
    assert s.peak < P.min_registration_peak and s.auc_0 < P.registered_edge_auc, (name, s)


def test_zero_peak_threshold_turns_it_off_and_a_high_auc_is_registered_whatever_its_peak():
    s = _score(depth=OTHER_DEPTH)
    assert s.mismatch(0.03, 0.85) and not s.mismatch(0.0, 0.85) and not s.mismatch(0.03, s.auc_0)
    assert not frame_registration(OTHER_DEPTH, RGB, BOXES, dataclasses.replace(P, min_registration_peak=0.0))[1]


def _nan_holes() -> np.ndarray:
    d = DEPTH.copy()
    d[::7] = np.nan
    d[:, ::11] = np.inf
    return d


@pytest.mark.parametrize("name,depth,rgb,boxes", [
    ("empty frame", np.zeros((0, 0), np.float32), np.zeros((0, 0, 3), np.uint8), BOXES),
    ("no candidates", DEPTH, RGB, np.zeros((0, 4))),
    ("all-invalid depth", np.zeros_like(DEPTH), RGB, BOXES),
    ("all-NaN depth", np.full_like(DEPTH, np.nan), RGB, BOXES),
    ("flat depth under a constant image", np.full_like(DEPTH, 3.0), np.full_like(RGB, 128), BOXES),
    ("flat depth of few pixels", np.where(np.arange(W) < 2, 3.0, 0.0).astype(np.float32)[None].repeat(H, 0), RGB,
     BOXES),
    ("constant image", DEPTH, np.full_like(RGB, 128), BOXES),
    ("tiny boxes", DEPTH, RGB, BOXES[:, :2][:, [0, 1, 0, 1]] + [0.0, 0.0, 2.0, 2.0]),
    ("boxes outside the image", DEPTH, RGB, BOXES + [W + 100, 0, W + 100, 0]),
    ("non-finite boxes", DEPTH, RGB, np.full((2, 4), np.nan)),
])
def test_inputs_that_cannot_judge_give_no_evidence_either_way(name, depth, rgb, boxes):
    s, refused = frame_registration(depth, rgb, boxes, P)
    assert not s.judged and not refused and np.isnan(s.peak), (name, s)


@pytest.mark.parametrize("name,depth", [
    ("a flat wall", np.full_like(DEPTH, 3.0)),
    ("a wall seen obliquely", np.linspace(2.0, 4.0, W, dtype=np.float32)[None].repeat(H, 0)),
    ("a flat wall with holes", np.where(np.arange(H)[:, None] % 9 == 0, 0.0, np.full_like(DEPTH, 3.0))),
])
def test_flat_depth_under_an_image_with_edges_is_refused(name, depth):
    s, refused = frame_registration(depth.astype(np.float32), RGB, BOXES, P)
    assert refused and not s.judged and s.jump_pairs == 0, (name, s)
    assert s.flat(P.registration_min_pairs, P.registration_min_jump_fraction), (name, s)
    assert registration_verdict(s, P) == "flat"
    assert registration_verdict(s, dataclasses.replace(P, min_registration_peak=0.0)) == ""     # the test off
    assert not frame_registration(depth.astype(np.float32), RGB, BOXES,
                                  dataclasses.replace(P, registration_min_jump_fraction=0.0))[1], name


def test_a_frame_whose_depth_steps_in_few_pairs_is_flat_only_below_the_fraction():
    s = RegistrationScore(float("nan"), float("nan"), 3, 9997, 500)
    assert s.flat(50, 0.001) and not s.flat(50, 0.0003) and not s.flat(50, 0.0)
    assert not RegistrationScore(float("nan"), float("nan"), 0, 40, 500).flat(50, 0.001)     # too few pairs
    assert not RegistrationScore(float("nan"), float("nan"), 0, 9000, 40).flat(50, 0.001)    # too few colour edges
    assert not RegistrationScore.unjudged(500).flat(50, 0.001)


@pytest.mark.parametrize("auc_0,auc_shifted,refused", [
    (0.60, 0.55, True),      # near chance: a peak of 0.05 is not enough
    (0.60, 0.53, False),     # twice the peak
    (0.70, 0.66, False),     # above the weak AUC, the plain peak rule
    (0.70, 0.68, True),
    (0.90, 0.89, False),     # registered whatever its peak
])
def test_a_frame_whose_edges_barely_follow_the_images_needs_twice_the_peak(auc_0, auc_shifted, refused):
    s = RegistrationScore(auc_0, auc_shifted, 500, 9000, 500)
    assert s.mismatch(0.03, 0.85, 0.65) == refused, s
    assert not s.mismatch(0.0, 0.85, 0.65)


def test_nan_and_inf_depth_read_as_missing():
    s = _score(depth=_nan_holes())
    assert s.judged and s.auc_0 > 0.85 and s.peak > 0.1, s


def test_deterministic_and_independent_of_the_depths_dtype():
    a, b = _score(), _score()
    assert a == b
    c = _score(depth=DEPTH.astype(np.float64))
    assert c == a


def test_grid_is_bounded_by_the_sample_budget():
    small = registration_score(DEPTH, RGB, BOXES, max_samples=2000, min_pairs=20)
    assert small.jump_pairs + small.other_pairs <= 2 * 2000 * 1.2, small
    assert small.judged and small.peak > 0.1, small


@pytest.mark.parametrize("kw,match", [
    (dict(depth_m=np.zeros((4, 4, 1))), "depth_m must be"),
    (dict(rgb=np.zeros((H, W), np.uint8)), "rgb must be"),
    (dict(rgb=np.zeros((H + 1, W, 3), np.uint8)), "rgb must be"),
    (dict(shift_px=0), ">= 1"),
    (dict(blur_px=0), ">= 1"),
])
def test_bad_input_raises(kw, match):
    args = dict(depth_m=DEPTH, rgb=RGB, boxes_xyxy=BOXES) | kw
    with pytest.raises(ValueError, match=match):
        registration_score(**args)


def test_colour_must_be_uint8():
    with pytest.raises(TypeError, match="uint8"):
        registration_score(DEPTH, RGB.astype(np.float32), BOXES)


@pytest.mark.parametrize("kw", [dict(min_registration_peak=-0.1), dict(registered_edge_auc=1.5),
                                dict(registration_shift_px=0), dict(registration_samples=0),
                                dict(registration_colour_edge=800), dict(frame_size_veto=-1)])
def test_params_are_validated(kw):
    with pytest.raises(ValueError):
        StructureParams(**kw)


@pytest.mark.parametrize("diff,jump,expected", [
    ([0, 0, 5, 5], [False, False, True, True], 1.0),          # every jump has the larger colour difference
    ([5, 5, 0, 0], [False, False, True, True], 0.0),
    ([3, 3, 3, 3], [False, False, True, True], 0.5),          # ties count half
    ([1, 2, 3, 4], [False, True, False, True], 0.75),
])
def test_pair_auc(diff, jump, expected):
    assert pair_auc(np.array(diff), np.array(jump), 1) == pytest.approx(expected)
    assert np.isnan(pair_auc(np.array(diff), np.array(jump), 3))


def test_region_is_the_dilated_boxes_clipped_to_the_image():
    dil, (x0, y0, x1, y1) = registration_region(np.array([[100.0, 50, 140, 70]]), (H, W), 0.5, 3)
    np.testing.assert_allclose(dil, [[80, 40, 160, 80]])
    assert (x0, y0, x1, y1) == (80, 40, 160, 80)
    _, (x0, y0, x1, y1) = registration_region(np.array([[0.0, 0, W, H]]), (H, W), 0.5, 3)
    assert (x0, y0, x1, y1) == (0, 0, W - 3, H - 3)


# -- the fit-check stage: the reason reaches the result -------------------------------------------------------
def test_estimator_rejects_every_pose_on_another_frames_depth(bundle_dir):
    from estimator_fixtures import scene, visible_boxes
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    frame = scene()
    boxes = visible_boxes(frame, 3)
    other = generate_frame(get_preset("virtual-clean"), seed=3)
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, min_confidence=0.0)
    r = est.estimate_boxes(frame.rgb, other.depth_m, frame.K, boxes_xyxy=boxes)
    assert r.poses == [] and len(r.rejected) == len(boxes)
    assert {x.reason for x in r.rejected} == {"depth_image_mismatch"}
    assert all("shifted 24 px" in x.detail for x in r.rejected), r.rejected[0].detail
    # the frame's own depth: no candidate is refused as not belonging to the image
    c = est.candidates(frame.rgb, frame.depth_m, frame.K,
                       detections=Detections(boxes, np.ones(len(boxes)), np.zeros(len(boxes), np.int64)))
    assert "depth_image_mismatch" not in set(c.reason)


def test_estimator_rejects_every_pose_on_a_flat_walls_depth(bundle_dir):
    from estimator_fixtures import scene, visible_boxes
    from pallet6d.runtime.estimator import PalletEstimator

    frame = scene()
    boxes = visible_boxes(frame, 3)
    wall = np.full_like(frame.depth_m, float(np.median(frame.depth_m[frame.depth_m > 0])))
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, min_confidence=0.0)
    r = est.estimate_boxes(frame.rgb, wall, frame.K, boxes_xyxy=boxes)
    assert r.poses == [] and len(r.rejected) == len(boxes)
    assert {x.reason for x in r.rejected} == {"depth_image_mismatch"}
    assert all("flat around its candidates" in x.detail for x in r.rejected), r.rejected[0].detail


def _structure_score(reason: str, cut: bool = False) -> StructureScore:
    return StructureScore(1, 0, 0, 0, 1.0, 1.0, 1.0, 1.0, 1.0, float("nan"), (1.0, 0.14), float("nan"), reason,
                          box_cut=cut)


SIZE, OK, BAD = "size_mismatch", "", "structure_mismatch"


@pytest.mark.parametrize("reasons, cut, params, calibrated, rule", [
    ([], [], {}, False, None),
    ([SIZE], [False], {}, False, "frame_size_vouched"),            # nothing vouches for the frame
    ([SIZE], [False], {}, True, None),                             # a calibration: left to the floor check
    ([SIZE, OK], [False, False], {}, False, "frame_size_vouched"),  # a tie refuses
    ([SIZE, OK, OK], [False, False, False], {}, False, None),
    # a structure failure vouches for nothing, nor does a box cut at the image's top or bottom
    ([SIZE, OK, BAD], [False, False, False], {}, False, "frame_size_vouched"),
    ([SIZE, OK, OK], [False, True, True], {}, False, "frame_size_vouched"),
    ([OK, BAD, BAD, BAD], [False] * 4, {}, False, None),           # no size failure: no frame rule
    ([SIZE], [False], {"frame_size_vouched": False}, False, None),
    ([SIZE, SIZE, OK], [False] * 3, {"frame_size_vouched": False, "frame_size_veto": 2}, False, "frame_size_veto"),
    ([SIZE, SIZE, BAD], [False] * 3, {"frame_size_vouched": False, "frame_size_majority": True}, False,
     "frame_size_majority"),
    ([SIZE, OK, BAD], [False] * 3, {"frame_size_vouched": False, "frame_size_majority": True}, False, None),
])
def test_frame_size_rule_table(reasons, cut, params, calibrated, rule):
    scores = [_structure_score(r, c) for r, c in zip(reasons, cut)]
    assert frame_size_rule(scores, StructureParams(**params), calibrated=calibrated) == rule


def test_frame_size_veto_rejects_every_candidate_when_enough_fail_the_metric_size(bundle_dir):
    from estimator_fixtures import scene
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.stage_fit import FitCheckStage

    frame = scene()
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, structure=None)
    pallets = sorted(frame.pallets, key=lambda p: -p.visib_fract)[:2]
    boxes = [[p.bbox_visib_xywh[0], p.bbox_visib_xywh[1], p.bbox_visib_xywh[0] + p.bbox_visib_xywh[2],
              p.bbox_visib_xywh[1] + p.bbox_visib_xywh[3]] for p in pallets]
    thin = list(boxes[0])
    thin[3] = thin[1] + 4                                           # 4 px tall: no pallet's metric height
    T = np.stack([p.T_cam_pallet for p in pallets] + [pallets[0].T_cam_pallet])

    def run(veto: int) -> Candidates:
        n = 3
        c = Candidates.new(np.array(boxes + [thin], float), np.ones(n), np.zeros(n, np.int64), np.zeros(n, np.int64),
                           est.spec.num_points)
        c.assign(np.arange(n), T_cam_pallet=T)
        stage = FitCheckStage(est.pallet_types, 0.04, 0.0, 0.0,
                              StructureParams(frame_size_veto=veto, frame_size_vouched=False))
        stage.check_structure(c, np.arange(n), frame.depth_m, frame.K, frame.rgb)
        return c

    off = run(0)
    assert off.reason[2] == "size_mismatch" and "size_mismatch" not in set(off.reason[:2]), off.reason
    on = run(1)
    assert list(on.reason) == ["size_mismatch"] * 3, on.reason
    assert "frame_size_veto" in on.detail[0] and "frame_size_veto" not in on.detail[2]


@pytest.mark.parametrize("n_thin, majority, vetoed", [(1, True, False), (2, True, False), (3, True, True),
                                                     (3, False, False)])
def test_frame_size_majority_rejects_every_candidate_when_failures_outnumber_whole_boxes(bundle_dir, n_thin, majority,
                                                                                        vetoed):
    """Two pallets with whole boxes of the right metric size and n_thin boxes of no pallet's size: the frame is
    refused only when the failures outnumber the right-sized whole boxes."""
    from estimator_fixtures import scene
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.stage_fit import FitCheckStage

    frame = scene()
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, structure=None)
    pallets = sorted(frame.pallets, key=lambda p: -p.visib_fract)[:2]
    boxes = [[p.bbox_visib_xywh[0], p.bbox_visib_xywh[1], p.bbox_visib_xywh[0] + p.bbox_visib_xywh[2],
              p.bbox_visib_xywh[1] + p.bbox_visib_xywh[3]] for p in pallets]
    assert all(b[1] > 5 and b[3] < frame.depth_m.shape[0] - 5 for b in boxes)     # whole boxes
    thin = [boxes[0][0], boxes[0][1], boxes[0][2], boxes[0][1] + 4]                # 4 px tall: no pallet's height
    n = 2 + n_thin
    c = Candidates.new(np.array(boxes + [thin] * n_thin, float), np.ones(n), np.zeros(n, np.int64),
                       np.zeros(n, np.int64), est.spec.num_points)
    c.assign(np.arange(n), T_cam_pallet=np.stack([p.T_cam_pallet for p in pallets]
                                                 + [pallets[0].T_cam_pallet] * n_thin))
    stage = FitCheckStage(est.pallet_types, 0.04, 0.0, 0.0,
                          StructureParams(frame_size_majority=majority, frame_size_vouched=False))
    stage.check_structure(c, np.arange(n), frame.depth_m, frame.K, frame.rgb)
    assert list(c.reason[2:]) == ["size_mismatch"] * n_thin
    if vetoed:
        assert list(c.reason[:2]) == ["size_mismatch"] * 2 and "frame_size_majority" in c.detail[0]
    else:
        assert "size_mismatch" not in set(c.reason[:2]), c.reason


@pytest.mark.parametrize("n_thin, n_misplaced, vouched, refused", [(1, 0, True, False), (2, 0, True, True),
                                                                   (1, 1, True, True), (2, 0, False, False)])
def test_frame_size_vouched_refuses_the_frame_unless_more_whole_pallets_pass_than_fail_the_size(
        bundle_dir, n_thin, n_misplaced, vouched, refused):
    """Two pallets with whole boxes, `n_misplaced` of them posed 0.5 m aside (they fail the structure check and vouch
    for nothing), and n_thin boxes of no pallet's metric size: the frame is refused when the thin boxes are at least
    as many as the whole boxes that pass the whole check."""
    from estimator_fixtures import scene
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.stage_fit import FitCheckStage

    frame = scene()
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, structure=None)
    pallets = sorted(frame.pallets, key=lambda p: -p.visib_fract)[:2]
    boxes = [[p.bbox_visib_xywh[0], p.bbox_visib_xywh[1], p.bbox_visib_xywh[0] + p.bbox_visib_xywh[2],
              p.bbox_visib_xywh[1] + p.bbox_visib_xywh[3]] for p in pallets]
    thin = [boxes[0][0], boxes[0][1], boxes[0][2], boxes[0][1] + 4]                # 4 px tall: no pallet's height
    T = [p.T_cam_pallet.copy() for p in pallets]
    for k in range(n_misplaced):
        T[k][0, 3] += 0.5
    n = 2 + n_thin
    c = Candidates.new(np.array(boxes + [thin] * n_thin, float), np.ones(n), np.zeros(n, np.int64),
                       np.zeros(n, np.int64), est.spec.num_points)
    c.assign(np.arange(n), T_cam_pallet=np.stack(T + [pallets[0].T_cam_pallet] * n_thin))
    stage = FitCheckStage(est.pallet_types, 0.04, 0.0, 0.0, StructureParams(frame_size_vouched=vouched))
    stage.check_structure(c, np.arange(n), frame.depth_m, frame.K, frame.rgb)
    assert list(c.reason[2:]) == ["size_mismatch"] * n_thin
    assert list(c.reason[:n_misplaced]) == ["no_pallet_structure"] * n_misplaced, c.reason
    if refused:
        assert list(c.reason[n_misplaced:2]) == ["size_mismatch"] * (2 - n_misplaced), c.reason
        assert all("frame_size_vouched" in d for d in c.detail[n_misplaced:2])
    else:
        assert "size_mismatch" not in set(c.reason[:2]), c.reason


# -- the test started while the networks run ---------------------------------------------------------------------
def _candidates_on(frame, n: int, est) -> Candidates:
    pallets = sorted(frame.pallets, key=lambda p: -p.visib_fract)[:n]
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in pallets)], float)
    c = Candidates.new(boxes, np.ones(n), np.zeros(n, np.int64), np.zeros(n, np.int64), est.spec.num_points)
    c.assign(np.arange(n), T_cam_pallet=np.stack([p.T_cam_pallet for p in pallets]))
    return c


def test_a_started_registration_is_taken_only_for_the_boxes_it_was_started_on(bundle_dir):
    """A started test that says "refused" rejects the frame when its boxes are the judged candidates' boxes, and is
    ignored (the test runs again on the frame's real depth) when they are not."""
    from concurrent.futures import Future

    from estimator_fixtures import scene
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.stage_fit import FitCheckStage

    frame = scene()
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, structure=None)
    stage = FitCheckStage(est.pallet_types, 0.04, 0.0, 0.0, StructureParams())
    refused: Future = Future()
    refused.set_result((RegistrationScore(0.5, 0.9, 100, 100, 500), True))
    c = _candidates_on(frame, 2, est)
    stage.check_structure(c, np.arange(2), frame.depth_m, frame.K, frame.rgb, registration=(c.boxes_xyxy[:1], refused))
    assert "depth_image_mismatch" not in set(c.reason), c.reason           # started on other boxes: not taken
    c = _candidates_on(frame, 2, est)
    stage.check_structure(c, np.arange(2), frame.depth_m, frame.K, frame.rgb, registration=(c.boxes_xyxy, refused))
    assert list(c.reason) == ["depth_image_mismatch"] * 2


def test_with_lanes_the_started_test_gives_the_same_result_and_stops_with_the_estimator(bundle_dir):
    from estimator_fixtures import scene, visible_boxes
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    frame = scene()
    boxes = visible_boxes(frame, 3)
    other = generate_frame(get_preset("virtual-clean"), seed=3)
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, min_confidence=0.0,
                                      pallet_lanes=2)
    started = est.fit_check.start_registration(boxes, frame.depth_m, frame.rgb)
    assert started is not None
    np.testing.assert_array_equal(started[0], boxes)
    assert started[1].result() == frame_registration(frame.depth_m, frame.rgb, boxes, est.options.structure)
    inline = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, min_confidence=0.0)
    # one lane (the default): the test runs in the fit check itself, no thread of its own
    inline.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert inline.fit_check._pool is None
    reasons = set()
    for depth in (frame.depth_m, other.depth_m):
        est.close()                                      # the worker thread stops; the next frame starts it again
        a = est.estimate_boxes(frame.rgb, depth, frame.K, boxes_xyxy=boxes)
        b = inline.estimate_boxes(frame.rgb, depth, frame.K, boxes_xyxy=boxes)
        assert [(x.reason, x.detail) for x in a.rejected] == [(x.reason, x.detail) for x in b.rejected]
        assert [p.T_cam_pallet.tolist() for p in a.poses] == [p.T_cam_pallet.tolist() for p in b.poses]
        reasons |= {x.reason for x in a.rejected}
    assert "depth_image_mismatch" in reasons                # another frame's depth: refused by the started test
    assert est.fit_check._pool is not None
    est.close()
    assert est.fit_check._pool is None
    # nothing to start without an image, without the test, or without boxes
    assert est.fit_check.start_registration(boxes, frame.depth_m, None) is None
    assert est.fit_check.start_registration(np.zeros((0, 4)), frame.depth_m, frame.rgb) is None
