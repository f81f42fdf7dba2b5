"""The estimator's stages on their own, the pipeline they make, time budgets and pallet types per detection."""
import copy
import dataclasses
import functools
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime.bundle import PalletType, load_bundle
from pallet6d.runtime.candidates import Candidates
from pallet6d.runtime.level import LevelParams
from pallet6d.runtime.detector import Detections
from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator
from pallet6d.runtime.fit import fit_score
from pallet6d.runtime.pallet_geometry import default_refine_starts
from pallet6d.runtime.structure import StructureParams
from pallet6d.sim.pallets import get_pallet_model

from estimator_fixtures import scene, visible_boxes

KW = dict(threads=1, score_threshold=0.0, min_fit=0.0, structure=None)


@pytest.fixture(scope="module")
def frame():
    return scene()


@pytest.fixture(scope="module")
def boxes(frame):
    """The visible boxes of three pallets, most visible first."""
    return visible_boxes(frame, 3)


@pytest.fixture(scope="module")
def est(bundle_dir):
    return PalletEstimator.from_bundle(bundle_dir, **KW)


def _cands(est, boxes, scores=None):
    n = len(boxes)
    scores = np.linspace(0.9, 0.5, n) if scores is None else scores
    return Candidates.new(boxes, scores, np.zeros(n, np.int64), np.zeros(n, np.int64), est.spec.num_points)


def _inputs(est, frame):
    return est.check_inputs(frame.rgb, frame.depth_m, frame.K)


# -- the stages on their own ------------------------------------------------------------------------------
def test_pose_inputs_with_one_generator_per_box_and_the_selected_pixels(est, frame, boxes):
    from pallet6d.runtime.geometry import clamp_box, select_pixels
    from pallet6d.runtime.pose_inputs import prepare_pose_inputs

    rgb, depth_m, K = _inputs(est, frame)
    lo, hi = est.spec.depth_range_m
    batch, pixels = prepare_pose_inputs(rgb, depth_m, K, boxes, est.spec,
                                        [np.random.default_rng(i) for i in range(len(boxes))], return_pixels=True)
    for i, box in enumerate(boxes):                   # each box as if alone, with its own generator
        alone = prepare_pose_inputs(rgb, depth_m, K, box[None], est.spec, np.random.default_rng(i))
        np.testing.assert_array_equal(alone.points[0], batch.points[i])
        v, u = select_pixels(depth_m, clamp_box(box, depth_m.shape), None, lo, hi)
        np.testing.assert_array_equal(pixels[i][0], v)
        np.testing.assert_array_equal(pixels[i][1], u)
    with pytest.raises(TypeError, match="one per box"):
        prepare_pose_inputs(rgb, depth_m, K, boxes, est.spec, [np.random.default_rng(0)])


def test_detector_stage_steps_make_detect(est, frame):
    x, lb = est.detector.preprocess(frame.rgb)
    assert x.shape == (1, 3, *est.bundle.detector.input_hw) and x.dtype == np.float32
    raw = est.detector.infer(x)
    det = est.detector.postprocess(raw, lb)
    ref = est.detect(frame.rgb)
    np.testing.assert_array_equal(det.boxes_xyxy, ref.boxes_xyxy)
    np.testing.assert_array_equal(det.scores, ref.scores)
    # an output with no score above the threshold gives no detection
    assert len(est.detector.postprocess(np.zeros_like(raw), lb)) == 0


def test_the_mirrored_detector_scores_a_mirrored_frame_as_the_frame_and_keeps_its_own_boxes(bundle_dir, frame):
    from pallet6d.runtime.detector import unmirror_yolov8

    x, _ = PalletEstimator.from_bundle(bundle_dir, **KW).detector.preprocess(frame.rgb)
    x_mirrored = np.ascontiguousarray(x[..., ::-1])
    hw = x.shape[-2:]
    plain = PalletEstimator.from_bundle(bundle_dir, **KW).detector
    mirrored = PalletEstimator.from_bundle(bundle_dir, **KW, detector_mirror=True).detector
    for det, symmetric in ((plain, False), (mirrored, True)):
        raw, raw_mirrored = det.infer(x), det.infer(x_mirrored)
        assert np.allclose(unmirror_yolov8(raw_mirrored, hw)[:, 4:], raw[:, 4:], atol=1e-5) == symmetric
    np.testing.assert_array_equal(mirrored.infer(x)[:, :4], plain.infer(x)[:, :4])
    with pytest.raises(TypeError):
        EstimatorOptions(detector_mirror="yes")


def test_stages_on_no_candidates(est, frame):
    rgb, depth_m, K = _inputs(est, frame)
    c, timings = _cands(est, np.zeros((0, 4))), {}
    est.pose_network(rgb, depth_m, K, c, timings)
    est.refiner(c, depth_m, K, timings)
    est.fit_check(c, depth_m, K, timings)
    assert len(c) == 0
    T, fit = est.refiner.refine(np.zeros((0, 4, 4)), np.zeros((0, 5, 3)), [], np.zeros(0, np.int64), depth_m, K)
    assert T.shape == (0, 4, 4) and fit.shape == (0, 3)
    fit = est.fit_check.score(np.zeros((0, 4, 4)), np.zeros((0, 5, 3)), np.zeros(0, np.int64), depth_m, K)
    assert fit.shape == (0, 3)


def test_one_candidate_through_the_stages_equals_estimate_boxes(est, frame, boxes):
    rgb, depth_m, K = _inputs(est, frame)
    c, timings = _cands(est, boxes[:1], [0.8]), {}
    est.pose_network(rgb, depth_m, K, c, timings)
    assert c.alive.all() and c.n_valid[0] > 0 and len(c.pixels[0][0]) == c.n_valid[0]
    np.testing.assert_array_equal(c.T_cam_pallet, c.T_net)              # not refined yet
    est.refiner(c, depth_m, K, timings)
    assert not np.isnan(c.fit).any()                                     # refine_batch scores what it returns
    est.fit_check(c, depth_m, K, timings)
    assert set(timings) >= {"pose_inputs", "fusion", "pose", "selection", "refine", "fit"}
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:1], scores=[0.8])
    assert len(r.poses) == 1
    np.testing.assert_array_equal(r.poses[0].T_cam_pallet, c.T_cam_pallet[0])
    assert r.poses[0].fit.score == c.fit[0, 2] and r.poses[0].pallet_type == est.pallet_types[0].name


def test_refiner_and_fit_check_leave_rejected_candidates_alone(est, frame, boxes):
    rgb, depth_m, K = _inputs(est, frame)
    c = _cands(est, boxes)
    est.pose_network(rgb, depth_m, K, c, {})
    T_net = c.T_cam_pallet.copy()
    c.reject(np.arange(len(c)), "low_confidence", "rejected by the test")
    est.refiner(c, depth_m, K, {})
    est.fit_check(c, depth_m, K, {})
    np.testing.assert_array_equal(c.T_cam_pallet, T_net)
    assert np.isnan(c.fit).all() and set(c.reason) == {"low_confidence"}


def test_pose_network_rejects_boxes_off_the_image_and_without_depth(est, frame, boxes):
    rgb, depth_m, K = _inputs(est, frame)
    depth = depth_m.copy()
    x1, y1, x2, y2 = boxes[1].astype(int)
    depth[y1:y2, x1:x2] = 0.0
    c = _cands(est, np.vstack([[5000.0, 5000.0, 5100.0, 5100.0], boxes[1]]))
    est.pose_network(rgb, depth, K, c, {})
    assert c.reason.tolist() == ["box_outside_image", "too_few_points"] and not c.alive.any()
    assert "valid depth pixels" in c.detail[1]


def test_nan_depth_pixels_are_never_points(bundle_dir, frame, boxes):
    depth = frame.depth_m.copy()
    x1, y1, x2, y2 = boxes[0].astype(int)
    depth[y1:(y1 + y2) // 2, x1:x2] = np.nan                         # the top half of the first box
    lenient = PalletEstimator.from_bundle(bundle_dir, nonfinite_depth="as_missing", **KW)
    rgb, depth_m, K = lenient.check_inputs(frame.rgb, depth, frame.K)
    c = _cands(lenient, boxes)
    lenient.pose_network(rgb, depth_m, K, c, {})
    v, u = c.pixels[0]
    assert len(v) == c.n_valid[0] > 0 and np.all(v >= (y1 + y2) // 2) and np.all(depth_m[v, u] > 0)
    assert np.all(np.isfinite(c.points_cam[0]))
    # the same frame whole: every candidate either posed with finite numbers or rejected with a reason
    r = lenient.estimate_boxes(frame.rgb, depth, frame.K, boxes_xyxy=boxes)
    assert len(r.poses) + len(r.rejected) == len(boxes)
    assert all(np.all(np.isfinite(p.T_cam_pallet)) for p in r.poses)


def test_estimate_reads_as_the_stages_in_order(est, frame):
    """The record `candidates` returns is what `estimate` reports: accepted rows in order, the rest rejected."""
    cands = est.candidates(frame.rgb, frame.depth_m, frame.K)
    r = est.estimate(frame.rgb, frame.depth_m, frame.K)
    assert np.all(np.diff(cands.scores) <= 0)
    alive = cands[cands.alive]
    assert len(r.poses) == len(alive) and len(r.rejected) == len(cands) - len(alive)
    for p, T, s in zip(r.poses, alive.T_cam_pallet, alive.scores):
        np.testing.assert_array_equal(p.T_cam_pallet, T)
        assert p.detector_score == s


# -- time budget ----------------------------------------------------------------------------------------
def test_zero_time_budget_poses_nothing_and_reports_every_detection(bundle_dir, frame, boxes):
    est = PalletEstimator.from_bundle(bundle_dir, time_budget_ms=0.0, **KW)
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert r.poses == [] and [x.reason for x in r.rejected] == ["time_budget"] * len(boxes)
    assert all(x.pose is None for x in r.rejected)
    json.dumps(r.to_dict())


def test_time_budget_poses_the_best_scores_first_and_skips_the_rest(bundle_dir, frame, boxes):
    """A fake clock that moves 1 ms each time it is read: the budget runs out part way through the frame."""
    ticks = itertools.count()
    est = PalletEstimator(load_bundle(bundle_dir), threads=1, options=EstimatorOptions(time_budget_ms=3.5, **{
        k: v for k, v in KW.items() if k != "threads"}), clock=lambda: next(ticks) / 1000.0)
    est.refiner.budget_chunk = 1
    est.pose_network.graph_batch = len(boxes)                           # one network chunk: the budget ends in ICP
    scores = [0.6, 0.9, 0.7]                                            # not in score order on purpose
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes, scores=scores)
    assert 1 <= len(r.poses) < len(boxes)
    assert [p.detector_score for p in r.poses] == sorted(scores, reverse=True)[:len(r.poses)]
    assert [x.reason for x in r.rejected] == ["time_budget"] * (len(boxes) - len(r.poses))
    assert all(x.pose is None for x in r.rejected)
    assert max(x.detector_score for x in r.rejected) < min(p.detector_score for p in r.poses)
    # without a budget the same clock changes nothing
    free = PalletEstimator(load_bundle(bundle_dir), threads=1, options=EstimatorOptions(**{
        k: v for k, v in KW.items() if k != "threads"}), clock=lambda: next(ticks) / 1000.0)
    assert len(free.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes, scores=scores).poses) == 3


def test_time_budget_option_is_checked():
    with pytest.raises(ValueError, match="time_budget_ms"):
        EstimatorOptions(time_budget_ms=-1.0)


# -- pallet types per detection ---------------------------------------------------------------------------
def _gma_type(class_id: int) -> PalletType:
    m = get_pallet_model("gma")
    return PalletType(name="gma", class_id=class_id, size_m=tuple(m.size_m), diameter_m=m.diameter_m,
                      points_file="gma_points.npy", symmetries=m.symmetries, boxes_m=m.boxes_m,
                      refine_starts=default_refine_starts(m.size_m), points_m=m.surface_points(500, seed=0))


def test_each_detection_uses_its_own_types_geometry(bundle_dir, frame, boxes):
    bundle = load_bundle(bundle_dir)
    epal = bundle.pallet_types[0]
    two = dataclasses.replace(bundle, pallet_types=(epal, _gma_type(epal.class_id + 1)))
    only_gma = dataclasses.replace(bundle, pallet_types=(_gma_type(epal.class_id),))
    opts = EstimatorOptions(**{k: v for k, v in KW.items() if k != "threads"})
    mixed = PalletEstimator(two, threads=1, options=opts)
    classes = [epal.class_id, epal.class_id + 1, epal.class_id + 1]
    r = mixed.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes, class_ids=classes)
    assert [p.pallet_type for p in r.poses] == ["epal", "gma", "gma"]
    # the same detections with a bundle of one type each: a row's pose is that of its own type
    as_epal = PalletEstimator(bundle, threads=1, options=opts).estimate_boxes(
        frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:1])
    as_gma = PalletEstimator(only_gma, threads=1, options=opts).estimate_boxes(
        frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[1:])
    for p, q in zip(r.poses, as_epal.poses + as_gma.poses):
        np.testing.assert_allclose(p.T_cam_pallet, q.T_cam_pallet, atol=1e-9)
        assert p.fit.score == pytest.approx(q.fit.score, abs=1e-12)
    # the fit of a gma row is the fit of the gma model, not the epal one
    rgb, depth_m, K = mixed.check_inputs(frame.rgb, frame.depth_m, frame.K)
    c = mixed.candidates(rgb, depth_m, K, detections=Detections(boxes, np.linspace(0.9, 0.5, 3), classes))
    gma_pts = mixed.pallet_types[1].points_m
    expect = fit_score(c.T_cam_pallet[1], c.points_cam[1], gma_pts, depth_m, K, opts.fit_tol_m)
    assert c.type_index.tolist() == [0, 1, 1] and c.fit[1, 2] == pytest.approx(expect.score, abs=1e-12)
    with pytest.raises(ValueError, match="not pallet classes"):
        mixed.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:1], class_ids=[7])


# -- the reference-pose comparison (benchmarks/reference_poses.py) ------------------------------------------
def test_reference_poses_record_then_compare(bundle_dir, sim_bop_dataset, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parents[1] / "benchmarks" / "reference_poses.py"
    ref = tmp_path / "ref.json"
    common = ["--bundle", str(bundle_dir), "--precision", "fp32"]

    def run(*args):
        return subprocess.run([sys.executable, str(script), *args, *common], capture_output=True, text=True,
                              timeout=300)

    done = run("record", "--data", str(sim_bop_dataset), "--out", str(ref))
    assert done.returncode == 0, done.stderr
    same = run("compare", "--ref", str(ref))
    assert same.returncode == 0 and "largest pose difference 0," in same.stdout, same.stdout + same.stderr
    # a recorded pose moved by 1 micrometre is reported
    doc = json.loads(ref.read_text())
    frames = next(iter(doc["runs"]["fp32"].values()))
    pose = next(r for f in frames for r in f["accepted"] + [x["pose"] for x in f["rejected"] if x["pose"]])
    pose["T_cam_pallet"][0][3] += 1e-6
    ref.write_text(json.dumps(doc))
    moved = run("compare", "--ref", str(ref))
    assert moved.returncode == 1 and "pose differs by 1e-06" in moved.stdout, moved.stdout + moved.stderr


def test_roi_option_rejects_detections_outside_before_posing(bundle_dir, frame, boxes):
    from pallet6d.runtime.roi import RegionOfInterest

    roi = RegionOfInterest(box_xyxy=(0.0, 0.0, 1.0, 1.0))          # a 1-pixel corner: no box centre lies in it
    est = PalletEstimator.from_bundle(bundle_dir, roi=roi, **KW)
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert r.poses == [] and len(r.rejected) == len(boxes)
    assert all(x.reason == "outside_roi" and x.pose is None for x in r.rejected)


def test_depth_that_does_not_belong_to_the_image_gets_its_own_reason(bundle_dir, frame, boxes):
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, min_confidence=0.0)
    shrunk = est.estimate_boxes(frame.rgb, frame.depth_m * np.float32(0.1), frame.K, boxes_xyxy=boxes)
    assert shrunk.poses == [] and {r.reason for r in shrunk.rejected} == {"size_mismatch"}
    assert all("depth scale or focal length" in r.detail for r in shrunk.rejected)
    c = est.candidates(frame.rgb, frame.depth_m, frame.K, detections=Detections(boxes, np.ones(len(boxes)),
                                                                                  np.zeros(len(boxes), np.int64)))
    assert "size_mismatch" not in set(c.reason) and "depth_image_mismatch" not in set(c.reason)


# -- one detector class for several pallet types: the depth picks the type ---------------------------------
def _catalogue_type(name: str, class_id: int) -> PalletType:
    m = get_pallet_model(name)
    return PalletType(name=name, class_id=class_id, size_m=tuple(m.size_m), diameter_m=m.diameter_m,
                      points_file=f"{name}_points.npy", symmetries=m.symmetries, boxes_m=m.boxes_m,
                      refine_starts=default_refine_starts(m.size_m), points_m=m.surface_points(1000, seed=0))


@functools.lru_cache(maxsize=4)
def _scene_of(name: str, exact: bool = True):
    """A forklift-approach frame whose pallets are all of one type, with exact depth (or the preset's stereo)."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    cfg = dataclasses.replace(get_preset("forklift-approach"), pallet_models=(name,))
    f = generate_frame(cfg, seed=3)
    return dataclasses.replace(f, depth_m=f.depth_ideal_m) if exact else f


@pytest.mark.parametrize("truth, refine", [("epal", True), ("eur6", True), ("plastic_9leg", True),
                                           # unrefined, the fit at the network's pose tells sizes apart
                                           ("epal", False), ("eur6", False)])
def test_the_depth_picks_the_type_among_a_classes_types(bundle_dir, truth, refine):
    types = tuple(_catalogue_type(n, 0) for n in ("epal", "eur6", "gma", "plastic_9leg"))
    multi = dataclasses.replace(load_bundle(bundle_dir), pallet_types=types)
    est = PalletEstimator(multi, threads=1, options=EstimatorOptions(**{
        k: v for k, v in KW.items() if k != "threads"}, refine=refine, type_candidates=2))
    assert est.type_choice.needed and est._types_of_class == {0: (0, 1, 2, 3)}
    f = _scene_of(truth)
    p = max(f.pallets, key=lambda p: p.visib_fract)
    assert p.model_name == truth and p.visib_fract > 0.5
    x, y, w, h = p.bbox_visib_xywh
    rgb, depth_m, K = est.check_inputs(f.rgb, f.depth_m, f.K)
    box = np.array([[x, y, x + w, y + h]], float)
    options = est._type_options(Detections(box, [0.9], [0]))
    assert options == [(0, 1, 2, 3)]                 # the class's types
    c = Candidates.new(box, [0.9], [0], [0], est.spec.num_points, type_options=options)
    est.pose_network(rgb, depth_m, K, c, {})
    T = p.T_cam_pallet.copy()
    T[:3, 3] += [0.01, -0.01, 0.01]                   # a network pose near the truth
    c.assign([0], T_net=T[None], T_cam_pallet=T[None])
    est.type_choice(c, depth_m, K, {})
    assert est.pallet_types[int(c.type_index[0])].name == truth
    assert np.isnan(c.fit[0, 2]) != refine          # refined: the winner's fit is set and the refiner leaves it
    if refine:
        assert np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3]) < 0.02


def _epal_first_candidate(bundle_dir, truth: str, exact: bool, T_net_of_truth: np.ndarray, more: tuple = (),
                          **options):
    """An estimator of an EPAL-first, `truth` bundle (one detector class; `more` types after them) with `options`,
    the `truth` scene's most visible pallet as its one candidate with the network pose `T_net_of_truth` in its true
    pallet frame, and the frame's depth, K, calibration and that pallet."""
    types = tuple(_catalogue_type(n, 0) for n in ("epal", truth, *more))
    multi = dataclasses.replace(load_bundle(bundle_dir), pallet_types=types)
    est = PalletEstimator(multi, threads=1, options=EstimatorOptions(**{
        k: v for k, v in KW.items() if k not in ("threads", *options)}, **options))
    f = _scene_of(truth, exact)
    p = max(f.pallets, key=lambda p: p.visib_fract)
    x, y, w, h = p.bbox_visib_xywh
    rgb, depth_m, K = est.check_inputs(f.rgb, f.depth_m, f.K)
    box = np.array([[x, y, x + w, y + h]], float)
    c = Candidates.new(box, [0.9], [0], [0], est.spec.num_points, type_options=est._type_options(
        Detections(box, [0.9], [0])))
    est.pose_network(rgb, depth_m, K, c, {})
    T_net = p.T_cam_pallet @ T_net_of_truth
    c.assign([0], T_net=T_net[None], T_cam_pallet=T_net[None])
    return est, c, depth_m, K, f.T_vehicle_cam, p


def _eur6_at_its_pose(bundle_dir, **options):
    """`_epal_first_candidate` of the EUR 6 scene with exact depth and the true pose as the network's."""
    est, c, depth_m, K, _, _ = _epal_first_candidate(bundle_dir, "eur6", True, np.eye(4), **options)
    return est, c, depth_m, K


@pytest.mark.parametrize("margin, expected", [(0.0, "eur6"), (0.9, "epal")])
def test_type_margin_keeps_the_first_type_unless_another_fits_clearly_better(bundle_dir, margin, expected):
    est, c, depth_m, K = _eur6_at_its_pose(bundle_dir, type_candidates=2, type_margin=margin)
    est.type_choice(c, depth_m, K, {})
    assert est.pallet_types[int(c.type_index[0])].name == expected   # an EUR 6 fits far better than an EPAL,
    for bad in (-0.1, 1.0, float("nan")):                               # but not by 0.9 of the 0-1 score
        with pytest.raises(ValueError, match="type_margin"):
            EstimatorOptions(type_margin=bad)


@pytest.mark.parametrize("structure, expected, refined", [
    (StructureParams(), "eur6", True),                                  # clear structure: the EUR 6 replaces it
    (StructureParams(replace_min_agreement=1.0), "epal", False),        # not clear enough: the first type stays,
    (StructureParams(replace_min_open_fraction=1.0, replace_min_agreement=0.0), "epal", False),   # for the refiner
])
def test_another_type_replaces_the_first_only_with_clear_structure(bundle_dir, structure, expected, refined):
    est, c, depth_m, K = _eur6_at_its_pose(bundle_dir, type_candidates=1, type_margin=0.0, structure=structure)
    est.type_choice(c, depth_m, K, {})       # one type refined: the EUR 6, which fits far better
    assert est.pallet_types[int(c.type_index[0])].name == expected
    assert np.isnan(c.fit[0, 2]) != refined
    if not refined:
        est.refiner(c, depth_m, K, {})        # the first type, refined as if it had been the only one
        assert np.isfinite(c.fit[0, 2]) and est.pallet_types[int(c.type_index[0])].name == "epal"


@pytest.mark.parametrize("truth", ["eur6", "epal"])
def test_a_first_type_that_fits_well_enough_is_kept_without_trying_the_others(bundle_dir, monkeypatch, truth):
    """`type_first_enough`: the first type (the EPAL) refined first; at or above the score it is kept and no other
    type is ranked; below, the types are compared as without the option, to the same pose and fit."""
    def choice(first_enough, spy=None):
        est, c, depth_m, K, _, _ = _epal_first_candidate(bundle_dir, truth, True, np.eye(4), type_candidates=2,
                                                         type_margin=0.0, type_first_enough=first_enough)
        if spy is not None:
            monkeypatch.setattr(est.type_choice, "rank", spy)
        est.type_choice(c, depth_m, K, {})
        return est.pallet_types[int(c.type_index[0])].name, c.T_cam_pallet[0].copy(), c.fit[0].copy()

    compared = choice(None)
    assert compared[0] == truth                       # compared, the depth picks the pallet's own type
    np.testing.assert_array_equal(choice(1.0)[1], compared[1])   # a score never reached: compared as before
    np.testing.assert_array_equal(choice(1.0)[2], compared[2])
    ranked = []
    settled = choice(1e-6, spy=lambda *a, **k: ranked.append(1))  # any refined EPAL is enough: kept, nothing ranked
    assert settled[0] == "epal" and np.isfinite(settled[2][2]) and not ranked
    if truth == "epal":                               # the EPAL's own refined pose, as when the types are compared
        np.testing.assert_array_equal(settled[1], compared[1])
    for bad in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="type_first_enough"):
            EstimatorOptions(type_first_enough=bad)


def test_face_starts_lay_a_smaller_type_flush_with_the_first_types_faces():
    from pallet6d.runtime.stage_type import face_starts

    epal, eur6, block = (get_pallet_model(n).size_m for n in ("epal", "eur6", "block_1210"))
    slides = face_starts(epal, eur6)
    assert slides.shape == (4, 4, 4)
    np.testing.assert_allclose(sorted(map(tuple, slides[:, :2, 3].round(6))),
                               [(-0.2, 0.0), (0.0, -0.1), (0.0, 0.1), (0.2, 0.0)])
    assert np.allclose(slides[:, :3, :3], np.eye(3))
    assert face_starts(epal, epal).shape == (0, 4, 4) and face_starts(epal, block).shape == (0, 4, 4)   # not smaller


@pytest.mark.parametrize("faces", [True, False])
@pytest.mark.parametrize("slide_m", [(0.2, 0.0), (0.0, 0.1)])
def test_a_smaller_pallet_posed_as_the_first_type_is_found_flush_with_its_face(bundle_dir, monkeypatch, faces,
                                                                              slide_m):
    from pallet6d.runtime import stage_type

    if not faces:
        monkeypatch.setattr(stage_type, "face_starts", lambda a, b: np.zeros((0, 4, 4)))
    off = np.eye(4)
    off[:2, 3] = slide_m                    # the network centred an EPAL's length or width behind the EUR 6's face
    alike = ("plastic_9leg", "plastic_3runner", "plastic_closed", "gma")     # EPAL-sized: they outrank it there
    est, c, depth_m, K, _, p = _epal_first_candidate(bundle_dir, "eur6", True, off, alike, type_candidates=2)
    est.type_choice(c, depth_m, K, {})
    found = est.pallet_types[int(c.type_index[0])].name == "eur6" and \
        np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3]) < 0.02
    assert found == faces


def _block_seen_by_a_calibrated_camera(bundle_dir, more: tuple = (), **options):
    """`_epal_first_candidate` of a 1200 x 1000 block pallet (alike an EPAL from the front) on the preset's stereo
    depth (too noisy to trust the six-degree ICP), the network's pose 15 degrees and 10 cm off and tilted 2 degrees
    (a network's pose is never exactly level)."""
    yaw, roll = np.radians(15.0), np.radians(2.0)
    off = np.eye(4)
    off[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]) @ \
        np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    off[0, 3] = 0.1
    est, c, depth_m, K, T_vc, p = _epal_first_candidate(bundle_dir, "block_1210", False, off, more, **options)
    return est, c, p, depth_m, K, T_vc


@pytest.mark.parametrize("structure, expected", [
    (StructureParams(), "block_1210"),                              # its own type, found at its levelled pose
    (StructureParams(replace_min_agreement=1.0), "epal"),          # no replacement: the first type, levelled
])
@pytest.mark.parametrize("first_enough", [None, 1e-6])    # levelled, every kept type is judged: never settled early
def test_with_the_calibration_the_types_are_judged_at_their_levelled_poses(bundle_dir, structure, expected,
                                                                           first_enough):
    est, c, p, depth_m, K, T_vc = _block_seen_by_a_calibrated_camera(
        bundle_dir, type_candidates=1, type_candidates_levelled=2, type_margin_levelled=0.0, structure=structure,
        type_first_enough=first_enough)
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=T_vc)
    assert est.pallet_types[int(c.type_index[0])].name == expected
    T_vp = T_vc @ c.T_cam_pallet[0]
    assert abs(T_vp[2, 2] - 1.0) < 1e-9                 # level on the vehicle's floor
    assert np.isfinite(c.fit[0, 2])                     # judged with its fit: the refiner stage leaves it
    T_before = c.T_cam_pallet.copy()
    est.refiner(c, depth_m, K, {})
    np.testing.assert_array_equal(c.T_cam_pallet, T_before)
    if expected == "block_1210":                         # the front face and the depth behind it
        assert np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3]) < 0.05


@pytest.mark.parametrize("margin, margin_levelled, expected", [
    (0.9, 0.0, "block_1210"),                       # the calibrated choice takes its own margin,
    (0.0, 0.9, "epal"),                             # not the one of the choice without a calibration
])
def test_with_the_calibration_the_type_choice_takes_the_levelled_margin(bundle_dir, margin, margin_levelled,
                                                                        expected):
    est, c, p, depth_m, K, T_vc = _block_seen_by_a_calibrated_camera(
        bundle_dir, type_candidates=1, type_candidates_levelled=2, type_margin=margin,
        type_margin_levelled=margin_levelled)
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=T_vc)
    assert est.pallet_types[int(c.type_index[0])].name == expected
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="type_margin_levelled"):
            EstimatorOptions(type_margin_levelled=bad)


@pytest.mark.parametrize("keep", [2, 4, 5])
def test_with_the_calibration_every_type_is_levelled_once_as_many_are_kept(bundle_dir, keep, monkeypatch):
    # five types: kept at least five, none is ranked and each is levelled, the others on fewer points than the first
    from pallet6d.runtime import stage_type

    est, c, p, depth_m, K, T_vc = _block_seen_by_a_calibrated_camera(
        bundle_dir, ("eur6", "gma", "plastic_closed"), type_candidates_levelled=keep, type_margin_levelled=0.0)
    levelled, ranked = [], []
    level_in_camera, rank = stage_type.level_in_camera, est.type_choice.rank

    def spy_level(T, T_vehicle_cam, geometries, params, *args):
        levelled.extend((g.name, params.search_points, params.refine_points) for g in geometries)
        return level_in_camera(T, T_vehicle_cam, geometries, params, *args)

    def spy_rank(*args):
        ranked.append(args[4])                          # how many others it ranks
        return rank(*args)

    monkeypatch.setattr(stage_type, "level_in_camera", spy_level)
    monkeypatch.setattr(est.type_choice, "rank", spy_rank)
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=T_vc)
    assert ranked == ([] if keep >= 5 else [stage_type.RANK_BY_FIT])
    names = [n for n, _, _ in levelled]
    assert len(names) == len(set(names)) and names[0] == "epal"     # the first type always, refined first
    assert len(names) == 5 if keep >= 5 else len(names) in (keep, keep + 1)
    full = est.options.level
    assert levelled[0][1:] == (full.search_points, full.refine_points)
    assert all((sp, rp) == (stage_type.OTHER_SEARCH_POINTS, full.refine_points) for _, sp, rp in levelled[1:])
    assert est.pallet_types[int(c.type_index[0])].name == "block_1210"
    assert np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3]) < 0.05


def test_with_the_calibration_a_refinement_gone_astray_leaves_the_network_pose_its_chance(bundle_dir, monkeypatch):
    # exact depth lets the six-degree refinement move the first type's pose; where it moved it off the pallet, beyond
    # the levelling's search, the network's pose levelled beside it finds the pallet
    types = tuple(_catalogue_type(n, 0) for n in ("epal", "eur6"))
    est = PalletEstimator(dataclasses.replace(load_bundle(bundle_dir), pallet_types=types), threads=1,
                          options=EstimatorOptions(**{k: v for k, v in KW.items() if k != "threads"},
                                                   type_candidates_levelled=2))
    f = _scene_of("epal")
    p = max(f.pallets, key=lambda p: p.visib_fract)
    x, y, w, h = p.bbox_visib_xywh
    rgb, depth_m, K = est.check_inputs(f.rgb, f.depth_m, f.K)
    box = np.array([[x, y, x + w, y + h]], float)
    c = Candidates.new(box, [0.9], [0], [0], est.spec.num_points,
                       type_options=est._type_options(Detections(box, [0.9], [0])))
    est.pose_network(rgb, depth_m, K, c, {})
    c.assign([0], T_net=p.T_cam_pallet[None], T_cam_pallet=p.T_cam_pallet[None])
    refine = est.type_choice.refiner.refine

    def astray(T, *args):                           # the refinement lands 0.6 m to the side
        T_out, fit = refine(T, *args)
        T_out = T_out.copy()
        T_out[:, 0, 3] += 0.6
        return T_out, fit

    monkeypatch.setattr(est.type_choice.refiner, "refine", astray)
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=f.T_vehicle_cam)
    assert est.pallet_types[int(c.type_index[0])].name == "epal"
    assert np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3]) < 0.03


def test_without_refinement_every_type_kept_is_still_ranked(bundle_dir, monkeypatch):
    # nothing is levelled without refinement: the ranking at the network's pose names the type
    est, c, p, depth_m, K, T_vc = _block_seen_by_a_calibrated_camera(
        bundle_dir, ("eur6",), type_candidates_levelled=5, refine=False)
    scores = []
    rank = est.type_choice.rank
    monkeypatch.setattr(est.type_choice, "rank", lambda *a: scores.append(rank(*a)) or scores[-1])
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=T_vc)
    assert len(scores) == 1 and int(c.type_index[0]) == int(np.argmax(scores[0][0]))


def test_with_the_calibration_the_type_choice_finds_what_it_misses_without(bundle_dir):
    est, c, p, depth_m, K, T_vc = _block_seen_by_a_calibrated_camera(bundle_dir, type_candidates=2,
                                                                      type_candidates_levelled=2, type_margin=0.0,
                                                                      type_margin_levelled=0.0)
    free = copy.deepcopy(c)
    est.type_choice(free, depth_m, K, {})            # the six-degree refinement alone, on stereo depth
    est.type_choice(c, depth_m, K, {}, T_vehicle_cam=T_vc)
    assert est.pallet_types[int(c.type_index[0])].name == "block_1210"
    err_free = np.linalg.norm(free.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3])
    err_level = np.linalg.norm(c.T_cam_pallet[0, :3, 3] - p.T_cam_pallet[:3, 3])
    assert err_level < 0.05 < err_free


@pytest.mark.parametrize("name", ["replace_min_agreement", "replace_min_open_fraction"])
def test_replacement_thresholds_are_checked(name):
    with pytest.raises(ValueError, match=name):
        StructureParams(**{name: 1.5})


@pytest.fixture
def typed(bundle_dir):
    """Makes an estimator whose detector has a class per type (epal 0, eur6 1, gma 2) with the given options."""
    bundle = dataclasses.replace(load_bundle(bundle_dir), pallet_types=tuple(
        _catalogue_type(n, c) for c, n in enumerate(("epal", "eur6", "gma"))))
    return lambda options: PalletEstimator(bundle, threads=1, options=EstimatorOptions(
        **{k: v for k, v in KW.items() if k != "threads"}, **options))


@pytest.mark.parametrize("class_scores, ratio, expected", [
    ([0.9, 0.1, 0.0], 0.5, (0,)),                    # sure: its class's type alone
    ([0.9, 0.5, 0.0], 0.5, (0, 1)),                  # a runner-up at >= half its score
    ([0.6, 0.4, 0.5], 0.5, (0, 2, 1)),               # runner-ups by score
    ([0.6, 0.4, 0.5], 1.0, (0,)),                    # ratio 1: the best class only
    (None, 0.5, (0,)),                               # boxes from elsewhere: no class scores
])
def test_a_typed_detectors_runner_up_classes_offer_their_types(typed, class_scores, ratio, expected):
    est = typed(dict(type_score_ratio=ratio))
    assert not est.type_choice.needed                # every class reports one type
    det = Detections([[10, 10, 60, 40]], [0.9], [0], None if class_scores is None else [class_scores])
    assert est._type_options(det) == [expected]


def test_the_depth_overrules_a_typed_detectors_wrong_class(typed):
    est = typed(dict(type_score_ratio=0.5))
    f = _scene_of("epal")
    p = max(f.pallets, key=lambda p: p.visib_fract)
    x, y, w, h = p.bbox_visib_xywh
    rgb, depth_m, K = est.check_inputs(f.rgb, f.depth_m, f.K)
    box = np.array([[x, y, x + w, y + h]], float)
    # the detector calls the EPAL an EUR 6 (class 1), with the EPAL (class 0) a close second
    options = est._type_options(Detections(box, [0.8], [1], [[0.7, 0.8, 0.1]]))
    assert options == [(1, 0)]
    c = Candidates.new(box, [0.8], [1], [1], est.spec.num_points, type_options=options)
    est.pose_network(rgb, depth_m, K, c, {})
    T = p.T_cam_pallet.copy()
    T[:3, 3] += [0.01, -0.01, 0.01]                  # a network pose near the truth
    c.assign([0], T_net=T[None], T_cam_pallet=T[None])
    est.type_choice(c, depth_m, K, {})
    assert est.pallet_types[int(c.type_index[0])].name == "epal"
    # sure of its wrong class, nothing is left to choose: the row stays an EUR 6
    sure = Candidates.new(box, [0.8], [1], [1], est.spec.num_points,
                          type_options=est._type_options(Detections(box, [0.8], [1], [[0.1, 0.8, 0.1]])))
    sure.assign([0], T_net=T[None], T_cam_pallet=T[None])
    est.type_choice(sure, depth_m, K, {})
    assert est.pallet_types[int(sure.type_index[0])].name == "eur6"


def test_types_may_share_a_detector_class(bundle_dir):
    bundle = load_bundle(bundle_dir)
    shared = dataclasses.replace(bundle.manifest, pallet_types=(bundle.pallet_types[0], _catalogue_type("eur6", 0)),
                                 files={**bundle.manifest.files, "eur6_points.npy": "0" * 64})
    assert [t.class_id for t in shared.pallet_types] == [0, 0]
    with pytest.raises(ValueError, match="type_candidates"):
        EstimatorOptions(type_candidates=0)
    with pytest.raises(ValueError, match="type_candidates_levelled"):
        EstimatorOptions(type_candidates_levelled=0)
    for ratio in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="type_score_ratio"):
            EstimatorOptions(type_score_ratio=ratio)


def test_site_pallet_types_narrow_the_type_choice(bundle_dir):
    types = tuple(_catalogue_type(n, 0) for n in ("epal", "eur6", "gma"))
    multi = dataclasses.replace(load_bundle(bundle_dir), pallet_types=types)
    opts = {k: v for k, v in KW.items() if k != "threads"}
    est = PalletEstimator(multi, threads=1, options=EstimatorOptions(**opts, pallet_types=("eur6", "gma")))
    assert est._types_of_class == {0: (1, 2)} and est.type_choice.needed
    one = PalletEstimator(multi, threads=1, options=EstimatorOptions(**opts, pallet_types=["epal"]))
    assert one._types_of_class == {0: (0,)} and not one.type_choice.needed
    assert one.options.pallet_types == ("epal",)
    f = _scene_of("epal")
    p = max(f.pallets, key=lambda p: p.visib_fract)
    x, y, w, h = p.bbox_visib_xywh
    res = one.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=[[x, y, x + w, y + h]])
    assert len(res.poses) + len(res.rejected) == 1 and all(q.pallet_type == "epal" for q in res.poses)


def test_a_detector_class_outside_the_site_types_is_dropped(bundle_dir):
    types = (_catalogue_type("epal", 0), _catalogue_type("gma", 1))
    multi = dataclasses.replace(load_bundle(bundle_dir), pallet_types=types)
    opts = {k: v for k, v in KW.items() if k != "threads"}
    est = PalletEstimator(multi, threads=1, options=EstimatorOptions(**opts, pallet_types=("gma",)))
    assert est._types_of_class == {1: (1,)} and est.detector.class_ids == (1,)
    with pytest.raises(ValueError, match="not pallet classes"):
        est.estimate_boxes(*_inputs(est, scene()), boxes_xyxy=[[10, 10, 60, 40]], class_ids=[0])


@pytest.mark.parametrize("value, match", [(("epal", "nope"), "not in bundle"), ((), "non-empty"),
                                          ("epal", "non-empty"), (("epal", ""), "non-empty")])
def test_site_pallet_types_are_checked(bundle_dir, value, match):
    with pytest.raises(ValueError, match=match):
        PalletEstimator(load_bundle(bundle_dir), threads=1, options=EstimatorOptions(pallet_types=value))


SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"


def test_with_the_calibration_poses_stand_level_on_the_floor():
    f = _scene_of("epal")
    T_vc = f.T_vehicle_cam
    # the scene's pallets are EPALs: the levelling snaps to the EPAL's half height
    est = PalletEstimator.from_bundle(SHIPPED, threads=1, structure=None, pallet_types=("epal",))
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.5)]
    free = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes)
    level = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
    assert len(level.poses) + len(level.rejected) == len(boxes)
    cos_z = np.array([(T_vc @ p.T_cam_pallet)[2, 2] for p in level.poses])
    # level in the vehicle frame, or (a pose on its side or upside down) left as estimated
    assert len(cos_z) and np.all(np.abs(cos_z - 1.0) < 1e-9)
    # on the floor where the scene's pallet stands on it (snapped to the pallet's half height), else at its height
    heights_gt = np.array([(T_vc @ g.T_cam_pallet)[2, 3] for g in f.pallets if g.visib_fract > 0.5])
    assert np.any(np.abs(heights_gt - 0.072) < 1e-6)
    for p in level.poses:
        z = (T_vc @ p.T_cam_pallet)[2, 3]
        nearest = heights_gt[np.argmin(np.abs(heights_gt - z))]
        assert z == pytest.approx(0.072) if abs(nearest - 0.072) < 1e-6 else abs(z - nearest) < 0.02
    tilts = [np.degrees(np.arccos(np.clip((T_vc @ p.T_cam_pallet)[2, 2], -1, 1))) for p in free.poses]
    assert max(tilts) > 1e-3                                          # without it the estimate keeps its tilt
    off = PalletEstimator.from_bundle(SHIPPED, threads=1, structure=None, level=None, pallet_types=("epal",))
    same = off.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
    for a, b in zip(same.poses, free.poses):
        np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet)


@pytest.mark.parametrize("from_depth", [True, False])
def test_with_a_calibration_a_degree_off_the_poses_stand_on_the_floor_the_depth_shows(from_depth):
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(dataclasses.replace(get_preset("forklift-approach"), pallet_models=("epal",)), seed=3)
    a = np.radians(1.0)                                    # the calibration pitched a degree, 3 cm too high
    off = f.T_vehicle_cam @ np.array([[1, 0, 0, 0], [0, np.cos(a), -np.sin(a), 0], [0, np.sin(a), np.cos(a), 0],
                                      [0, 0, 0, 1.0]])
    off[2, 3] += 0.03
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.3)]
    est = PalletEstimator.from_bundle(SHIPPED, threads=1, structure=None, pallet_types=("epal",),
                                      level=LevelParams(floor_from_depth=from_depth))
    c = est.candidates(f.rgb, f.depth_m, f.K, detections=Detections(np.array(boxes, float), np.full(len(boxes), 0.9),
                                                                   np.zeros(len(boxes), int)), T_vehicle_cam=off)
    up_true, up_off = f.T_vehicle_cam[2, :3], off[2, :3]
    z_axes = c.T_cam_pallet[:, :3, 2]
    level = np.abs(z_axes @ up_true - 1) < 1e-4 if from_depth else np.abs(z_axes @ up_off - 1) < 1e-9
    assert level.sum() >= 2                                 # levelled poses (one tilted far may be left as it is)
    tilt_true = np.degrees(np.arccos(np.clip(z_axes[level] @ up_true, -1, 1)))
    if from_depth:        # the frame's floor: within a tenth of a degree of the true one
        assert tilt_true.max() < 0.1
    else:                 # the calibration's floor, a degree off
        assert tilt_true == pytest.approx(np.degrees(np.arccos(up_true @ up_off)), abs=1e-6)
        assert tilt_true.min() > 0.9


def test_the_climb_moves_accepted_poses_only_and_never_decides_acceptance():
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(dataclasses.replace(get_preset("forklift-approach"), pallet_models=("epal",)), seed=3)
    T_vc = f.T_vehicle_cam                                                      # D435-like depth
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.3)]
    runs = {}
    # these pallets stand 5-6 m away: the climb is let reach them
    for name, level in (("climb", LevelParams(climb_max_range_m=10.0)), ("no climb", LevelParams(climb_step_deg=0))):
        est = PalletEstimator.from_bundle(SHIPPED, threads=1, level=level)
        runs[name] = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=T_vc)
    climb, plain = runs["climb"], runs["no climb"]
    assert [p.box_xyxy.tolist() for p in climb.poses] == [p.box_xyxy.tolist() for p in plain.poses]
    assert [(r.box_xyxy.tolist(), r.reason) for r in climb.rejected] == \
        [(r.box_xyxy.tolist(), r.reason) for r in plain.rejected]
    for a, b in zip(climb.rejected, plain.rejected):                           # rejected poses are left as judged
        if b.pose is not None:
            np.testing.assert_allclose(a.pose.T_cam_pallet, b.pose.T_cam_pallet)
    assert len(climb.poses)
    moved = 0
    for a, b in zip(climb.poses, plain.poses):
        Ta, Tb = T_vc @ a.T_cam_pallet, T_vc @ b.T_cam_pallet
        np.testing.assert_allclose(Ta[2], Tb[2], atol=1e-9)                      # still level, at the same height
        assert np.linalg.norm(Ta[:2, 3] - Tb[:2, 3]) < 0.1
        if not np.allclose(Ta, Tb):                                              # a moved pose's fit is its own
            moved += 1
            assert a.fit.score != b.fit.score or a.fit.inlier_fraction != b.fit.inlier_fraction
    assert moved


def test_the_climb_scores_on_its_own_number_of_the_boxs_points(monkeypatch):
    from pallet6d.runtime import estimator as estimator_module
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(dataclasses.replace(get_preset("forklift-approach"), pallet_models=("epal",)), seed=3)
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.3)]
    seen = []
    real = estimator_module.climb_poses
    monkeypatch.setattr(estimator_module, "climb_poses",
                        lambda T, pts, *a, **k: seen.append([len(p) for p in pts]) or real(T, pts, *a, **k))
    counts = {}
    for n in (0, 1000):
        seen.clear()
        level = LevelParams(climb_max_range_m=10.0, climb_points=n)
        est = PalletEstimator.from_bundle(SHIPPED, threads=1, level=level)
        est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=f.T_vehicle_cam)
        assert len(seen) == 1 and seen[0]
        counts[n] = seen[0]
    assert max(counts[0]) <= est.options.refine_points                           # 0: the levelling's own points
    assert max(counts[1000]) <= 1000 and max(counts[1000]) > max(counts[0])


@pytest.mark.parametrize("T, match", [(np.eye(3), "rigid"), (np.diag([2.0, 1, 1, 1]), "rigid"),
                                      (np.full((4, 4), np.nan), "rigid"), (np.diag([1.0, 1, -1, 1]), "rigid")])
def test_a_bad_calibration_transform_is_refused(est, frame, T, match):
    with pytest.raises(ValueError, match=match):
        est.estimate(frame.rgb, frame.depth_m, frame.K, T_vehicle_cam=T)


def test_with_the_calibration_the_structure_check_tests_the_tilt(bundle_dir, monkeypatch):
    """The fit-check stage hands the vehicle's up (in the camera frame) to the structure check's tilt test."""
    import pallet6d.runtime.stage_fit as stage_fit

    seen = []
    real = stage_fit.structure_check

    def spy(*args, up_cam=None, **kwargs):
        seen.append(None if up_cam is None else np.array(up_cam))
        return real(*args, up_cam=up_cam, **kwargs)

    monkeypatch.setattr(stage_fit, "structure_check", spy)
    f = _scene_of("epal")
    est = PalletEstimator(load_bundle(bundle_dir), threads=1, options=EstimatorOptions(
        score_threshold=0.0, min_fit=0.0, min_confidence=0.0))
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (p.bbox_visib_xywh for p in f.pallets if p.visib_fract > 0.5)]
    est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes)
    est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=f.T_vehicle_cam)
    assert len(seen) == 2 and seen[0] is None
    np.testing.assert_allclose(seen[1], f.T_vehicle_cam[2, :3])
    np.testing.assert_allclose(f.T_vehicle_cam[:3, :3] @ seen[1], [0, 0, 1], atol=1e-12)   # the vehicle's up
    est = PalletEstimator(load_bundle(bundle_dir), threads=1, options=EstimatorOptions(      # the frame's floor
        score_threshold=0.0, min_fit=0.0, min_confidence=0.0, level=LevelParams(floor_from_depth=True)))
    est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes, T_vehicle_cam=f.T_vehicle_cam)
    assert np.degrees(np.arccos(np.clip(seen[2] @ f.T_vehicle_cam[2, :3], -1, 1))) < 0.2
