"""Proposals from the depth alone: boxes around what stands a pallet's height on the floor, posed as weak detections."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime.depth_proposals import DepthProposals, framing_iou, propose_boxes
from pallet6d.runtime.detector import Detections
from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator
from pallet6d.runtime.evaluation import box_iou

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"
H, W = 240, 424
K = np.array([[300.0, 0, 211.5], [0, 300.0, 119.5], [0, 0, 1]])
CAM_HEIGHT_M = 0.6


def _T_vehicle_cam(pitch_deg: float = 10.0) -> np.ndarray:
    """A camera 0.6 m above the floor looking forward (vehicle x), pitched down: its axes in the vehicle frame."""
    p = np.radians(pitch_deg)
    z_cam = np.array([np.cos(p), 0.0, -np.sin(p)])                 # the optical axis
    x_cam = np.array([0.0, -1.0, 0.0])                             # image right: the vehicle's right
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x_cam, np.cross(z_cam, x_cam), z_cam
    T[:3, 3] = [0.0, 0.0, CAM_HEIGHT_M]
    return T


def _render(blocks, T_vc: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres of a floor (z = 0) and axis-aligned blocks [(x0, x1, y0, y1, z0, z1)] in the vehicle frame,
    by casting each pixel's ray."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    R, o = T_vc[:3, :3], T_vc[:3, 3]
    d = rays_cam @ R.T                                             # ray directions in the vehicle frame
    t_best = np.where(d[..., 2] < -1e-9, -o[2] / np.minimum(d[..., 2], -1e-9), np.inf)    # the floor
    for x0, x1, y0, y1, z0, z1 in blocks:
        lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo - o) / d, (hi - o) / d
        t_near = np.nanmax(np.minimum(ta, tb), axis=-1)
        t_far = np.nanmin(np.maximum(ta, tb), axis=-1)
        hit = (t_near <= t_far) & (t_far > 0)
        t_best = np.where(hit & (t_near < t_best), t_near, t_best)
    depth = t_best * rays_cam[..., 2]                              # z of the hit in the camera frame
    return np.where(np.isfinite(depth) & (depth < 20), depth, 0.0).astype(np.float32)


def _projected_box(block, T_vc: np.ndarray) -> np.ndarray:
    x0, x1, y0, y1, z0, z1 = block
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)])
    p_cam = (corners - T_vc[:3, 3]) @ T_vc[:3, :3]
    u = K[0, 0] * p_cam[:, 0] / p_cam[:, 2] + K[0, 2]
    v = K[1, 1] * p_cam[:, 1] / p_cam[:, 2] + K[1, 2]
    return np.array([[u.min(), v.min(), u.max(), v.max()]])


PALLET = (3.0, 3.8, -0.6, 0.6, 0.0, 0.144)                        # a EUR pallet's footprint 3 m ahead, long side on


def test_the_camera_used_by_these_tests_looks_forward_and_down():
    T = _T_vehicle_cam()
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    assert T[:3, 2] @ [1, 0, 0] > 0.9 and T[:3, 2][2] < 0                # the optical axis ahead, below level
    assert T[:3, 1][2] < 0                                                 # image down is vehicle down


def test_a_pallet_on_the_floor_is_proposed_around_where_it_is_seen():
    T = _T_vehicle_cam()
    boxes = propose_boxes(_render([PALLET], T), K, T)
    assert boxes.shape == (1, 4)
    assert box_iou(boxes, _projected_box(PALLET, T))[0, 0] > 0.7


@pytest.mark.parametrize("blocks, why", [
    ([], "a bare floor"),
    ([(2.0, 2.1, -3.0, 3.0, 0.0, 2.5)], "a wall across the view: far wider than a pallet"),
    ([(3.0, 3.8, -0.6, 0.6, 0.0, 0.04)], "a mat 4 cm high: under the band"),
    ([(3.0, 3.1, -0.1, 0.0, 0.0, 0.15)], "a post 10 cm across: narrower than any pallet"),
    ([(8.0, 8.8, -0.6, 0.6, 0.0, 0.144)], "a pallet beyond the range"),
])
def test_nothing_a_pallet_could_not_be_is_proposed(blocks, why):
    T = _T_vehicle_cam()
    assert propose_boxes(_render(blocks, T), K, T).shape == (0, 4), why


def test_two_pallets_a_hand_apart_are_two_proposals_nearest_first():
    T = _T_vehicle_cam()
    far = (3.0, 3.8, 0.1, 1.3, 0.0, 0.144)
    near = (2.5, 3.3, -1.4, -0.2, 0.0, 0.144)
    boxes = propose_boxes(_render([far, near], T), K, T)
    assert boxes.shape == (2, 4)
    assert box_iou(boxes[:1], _projected_box(near, T))[0, 0] > 0.6
    assert box_iou(boxes[1:], _projected_box(far, T))[0, 0] > 0.6


def test_what_stands_on_the_pallet_does_not_change_its_proposal():
    T = _T_vehicle_cam()
    load = (3.0, 3.8, -0.6, 0.6, 0.144, 1.2)
    boxes = propose_boxes(_render([PALLET, load], T), K, T)
    assert boxes.shape == (1, 4)
    assert box_iou(boxes, _projected_box(PALLET, T))[0, 0] > 0.6


@pytest.mark.parametrize("depth", [np.zeros((H, W), np.float32), np.full((H, W), np.nan, np.float32)])
def test_depth_without_data_proposes_nothing(depth):
    T = _T_vehicle_cam()
    assert propose_boxes(depth, K, T).shape == (0, 4)


@pytest.mark.parametrize("depth, K_, T, match", [
    (np.zeros((4, 4, 3)), K, None, r"depth_m must be \(H, W\)"),
    (np.zeros((H, W)), K[:2], None, r"intrinsics K must be 3x3"),
    (np.zeros((H, W)), K.T, None, r"transposed\?"),
    (np.zeros((H, W)), K, np.eye(3), r"T_vehicle_cam must be \(4, 4\)"),
])
def test_inputs_of_the_wrong_shape_are_refused(depth, K_, T, match):
    with pytest.raises(ValueError, match=match):
        propose_boxes(depth, K_, _T_vehicle_cam() if T is None else T)


@pytest.mark.parametrize("field, value", [
    ("band_m", (0.2, 0.1)), ("band_m", (-0.1, 0.2)), ("width_m", (1.0, 0.5)), ("max_range_m", 0.0),
    ("min_height_m", float("nan")), ("cell_m", True), ("stride", 0), ("stride", 1.5), ("min_points", 0),
    ("margin", 1.5), ("max_iou", -0.1), ("max_boxes", 0), ("max_boxes", 2.0),
])
def test_proposal_params_are_checked(field, value):
    with pytest.raises(ValueError, match=f"DepthProposals.{field}"):
        DepthProposals(**{field: value})


def test_the_option_takes_proposal_params_only():
    assert EstimatorOptions().depth_proposals == DepthProposals()     # on by default (it acts with a calibration only)
    with pytest.raises(TypeError, match="depth_proposals must be a DepthProposals"):
        EstimatorOptions(depth_proposals={"stride": 2})


def _pose_at(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def test_framing_iou_is_that_of_the_box_and_the_pallets_projection_inside_the_image():
    size = np.array([[1.2, 0.8, 0.2]])
    T = _pose_at(0.0, 0.0, 3.0)
    # the pallet frame as the camera's (its 0.2 m "height" along the optical axis): the near face at 2.9 m
    u = 300.0 * 0.6 / 2.9
    v = 300.0 * 0.4 / 2.9
    exact = np.array([[211.5 - u, 119.5 - v, 211.5 + u, 119.5 + v]])
    assert framing_iou(T[None], size, K, exact, (H, W))[0] == pytest.approx(1.0)
    left_half = exact.copy()
    left_half[0, 2] = 211.5
    assert framing_iou(T[None], size, K, left_half, (H, W))[0] == pytest.approx(0.5)
    elsewhere = np.array([[0.0, 0.0, 20.0, 20.0]])
    assert framing_iou(T[None], size, K, elsewhere, (H, W))[0] == 0.0
    behind = _pose_at(0.0, 0.0, -3.0)
    assert framing_iou(behind[None], size, K, exact, (H, W))[0] == 0.0
    # a pallet reaching past the image's edge is judged on its part inside the image, as the box is
    wide = np.array([[8.0, 0.8, 0.2]])
    assert framing_iou(T[None], wide, K, np.array([[0.0, 119.5 - v, W, 119.5 + v]]), (H, W))[0] == pytest.approx(1.0)
    assert framing_iou(np.zeros((0, 4, 4)), np.zeros((0, 3)), K, np.zeros((0, 4)), (H, W)).shape == (0,)


@pytest.fixture(scope="module")
def forklift_frame():
    """A calibrated forklift-approach frame of EPALs (exact depth)."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    f = generate_frame(dataclasses.replace(get_preset("forklift-approach"), pallet_models=("epal",)), seed=3)
    return dataclasses.replace(f, depth_m=f.depth_ideal_m)


def _blind_estimator(det: Detections, **options) -> PalletEstimator:
    """The shipped bundle whose detector reports `det`."""
    est = PalletEstimator.from_bundle(SHIPPED, threads=1, pallet_types=("epal",), **options)
    est.detector.postprocess = lambda raw, lb: det
    return est


def test_with_a_calibration_the_depth_finds_pallets_a_blind_detector_misses(forklift_frame):
    f = forklift_frame
    T_vc = f.T_vehicle_cam
    proposed = propose_boxes(f.depth_m, f.K, T_vc)
    assert len(proposed) >= 1
    est = _blind_estimator(Detections.empty(), depth_proposals=DepthProposals())
    assert est.estimate(f.rgb, f.depth_m, f.K).poses == []           # without a calibration: nothing to pose
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    posed = res.poses + res.rejected
    assert len(posed) == len(proposed)
    assert all(p.detector_score == 0.0 for p in posed)
    assert res.timings_ms["proposals"] > 0
    assert res.poses                                                   # the frame's clear pallets are kept
    gts = [p.T_cam_pallet for p in f.pallets]
    for p in res.poses:                                                # on pallets, not somewhere near them
        assert min(np.linalg.norm(p.T_cam_pallet[:3, 3] - g[:3, 3]) for g in gts) < 0.05
    off = _blind_estimator(Detections.empty(), depth_proposals=None)   # the option off
    assert off.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc).poses == []


def test_proposals_a_detection_covers_are_not_posed_again(forklift_frame):
    f = forklift_frame
    proposed = propose_boxes(f.depth_m, f.K, f.T_vehicle_cam)
    det = Detections(proposed, np.full(len(proposed), 0.9), np.zeros(len(proposed), np.int64))
    res = _blind_estimator(det, depth_proposals=DepthProposals()).estimate(f.rgb, f.depth_m, f.K,
                                                                           T_vehicle_cam=f.T_vehicle_cam)
    assert all(p.detector_score == 0.9 for p in res.poses + res.rejected)


def test_a_proposal_whose_detection_is_refused_is_posed_in_a_second_round(forklift_frame, monkeypatch):
    """A detection covering a proposal holds it back; where that detection's pose is refused, the proposal is
    posed after all, and its pose is kept where it shows a pallet."""
    f = forklift_frame
    proposed = propose_boxes(f.depth_m, f.K, f.T_vehicle_cam)
    first = _blind_estimator(Detections.empty()).estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    kept = [p for p in first.poses if np.allclose(p.box_xyxy, proposed[0])]
    assert kept                                    # the nearest proposal alone shows a pallet
    grown = proposed[:1] + np.array([[-3.0, -3.0, 3.0, 3.0]])            # the detector's box around the same pallet
    det = Detections(grown, np.array([0.9]), np.zeros(1, np.int64))
    est = _blind_estimator(det)
    real_check = est.fit_check

    def refuse_the_detection(cands, *args, **kwargs):
        real_check(cands, *args, **kwargs)
        cands.reject(np.flatnonzero(cands.alive & (cands.scores == 0.9)), "poor_fit", "refused by the test")

    monkeypatch.setattr(est, "fit_check", refuse_the_detection)
    res = est.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert [r.reason for r in res.rejected if r.detector_score == 0.9] == ["poor_fit"]
    again = [p for p in res.poses if np.allclose(p.box_xyxy, proposed[0])]
    assert len(again) == 1 and again[0].detector_score == 0.0
    np.testing.assert_allclose(again[0].T_cam_pallet, kept[0].T_cam_pallet, atol=1e-6)
    # accepted, the detection's pose takes the proposal: it is not posed
    res = _blind_estimator(det).estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert [p.detector_score for p in res.poses if np.allclose(p.box_xyxy, grown[0])] == [0.9]
    assert not [p for p in res.poses + res.rejected if np.allclose(p.box_xyxy, proposed[0])]


def test_proposals_keep_places_beside_a_full_list_of_detections(forklift_frame):
    """The detector's `max_pallets` boxes do not crowd out the depth's proposals (at most `max_boxes`, nearest
    first)."""
    f = forklift_frame
    proposed = propose_boxes(f.depth_m, f.K, f.T_vehicle_cam)
    far = np.array([[10.0 + 30 * i, 5.0, 30.0 + 30 * i, 15.0] for i in range(3)])     # boxes above the horizon
    det = Detections(far, np.full(3, 0.9), np.zeros(3, np.int64))
    for max_boxes in (1, 4):
        res = _blind_estimator(det, max_pallets=3, depth_proposals=DepthProposals(max_boxes=max_boxes)).estimate(
            f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
        rows = res.poses + res.rejected
        assert sum(r.detector_score == 0.9 for r in rows) == 3
        from_depth = [r.box_xyxy for r in rows if r.detector_score == 0.0]
        assert len(from_depth) == min(max_boxes, len(proposed))
        np.testing.assert_allclose(from_depth[0], proposed[0])


def test_proposals_are_judged_as_weak_detections(forklift_frame):
    """A proposal is posed and judged exactly as a weak detection on its box would be; without the weak boxes
    there are no proposals either."""
    f = forklift_frame
    T_vc = f.T_vehicle_cam
    proposed = propose_boxes(f.depth_m, f.K, T_vc)
    res = _blind_estimator(Detections.empty(), depth_proposals=DepthProposals()).estimate(
        f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    weak = Detections(proposed, np.full(len(proposed), 0.15), np.zeros(len(proposed), np.int64))
    as_weak = _blind_estimator(weak, depth_proposals=None).estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)

    def outcome(r):
        return sorted([(tuple(p.box_xyxy.round(3)), "accepted", tuple(p.T_cam_pallet.round(6).ravel()))
                       for p in r.poses] + [(tuple(q.box_xyxy.round(3)), q.reason, ()) for q in r.rejected])

    assert outcome(res) == outcome(as_weak) and res.poses
    no_weak = _blind_estimator(Detections.empty(), depth_proposals=DepthProposals(), weak_boxes=None)
    res = no_weak.estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=T_vc)
    assert res.poses == [] and res.rejected == []


@pytest.mark.parametrize("flags, expected", [([], DepthProposals()), (["--no-depth-proposals"], None)])
def test_the_command_line_turns_depth_proposals_off(flags, expected):
    import argparse

    from pallet6d.runtime.estimator_cli import add_estimator_arguments, load_estimator

    parser = argparse.ArgumentParser()
    add_estimator_arguments(parser)
    est = load_estimator(parser.parse_args(["--bundle", str(SHIPPED), "--threads", "1", *flags]), "run")
    assert est.options.depth_proposals == expected


def test_any_depth_gives_boxes_inside_the_image_and_nothing_else():
    """Property: whatever the depth (random planes and blocks, speckle, NaN, inf, huge values) and the camera's pose,
    the proposals are finite boxes inside the image, or none."""
    hypothesis = pytest.importorskip("hypothesis")
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=40, deadline=None, derandomize=True)
    @given(st.integers(0, 2**31 - 1), st.floats(-30, 60), st.floats(0.1, 3.0),
           st.sampled_from([0.0, np.nan, np.inf, 1e9, -1.0]))
    def check(seed, pitch_deg, height_m, odd):
        rng = np.random.default_rng(seed)
        T = _T_vehicle_cam(pitch_deg)
        T[2, 3] = height_m
        blocks = [(x, x + rng.uniform(0.1, 2.5), y, y + rng.uniform(0.1, 2.5), 0.0, rng.uniform(0.02, 1.5))
                  for x, y in rng.uniform([0.5, -3.0], [7.0, 3.0], size=(int(rng.integers(0, 6)), 2))]
        depth = _render(blocks, T)
        speckle = rng.random(depth.shape) < rng.uniform(0, 0.2)
        depth[speckle] = odd
        depth += rng.normal(0, rng.uniform(0, 0.05), depth.shape).astype(np.float32) * (depth > 0)
        boxes = propose_boxes(depth, K, T)
        assert boxes.ndim == 2 and boxes.shape[1] == 4 and np.all(np.isfinite(boxes))
        assert np.all(boxes[:, 0] >= 0) and np.all(boxes[:, 2] <= W) and np.all(boxes[:, 1] >= 0)
        assert np.all(boxes[:, 3] <= H) and np.all(boxes[:, 2] > boxes[:, 0]) and np.all(boxes[:, 3] > boxes[:, 1])

    check()


def test_the_registration_test_judges_the_detectors_boxes_only(forklift_frame, monkeypatch):
    """The frame-level registration test asks whether the image's edges lie on the depth's at the detector's boxes;
    a proposal's box is drawn from the depth, so it is left out of the test (and a frame of proposals alone is not
    tested)."""
    import pallet6d.runtime.stage_fit as stage_fit

    f = forklift_frame
    seen = []
    real = stage_fit.frame_registration

    def spy(depth_m, rgb, boxes, params):
        seen.append(np.array(boxes, copy=True))
        return real(depth_m, rgb, boxes, params)

    monkeypatch.setattr(stage_fit, "frame_registration", spy)
    proposed = propose_boxes(f.depth_m, f.K, f.T_vehicle_cam)
    assert len(proposed) >= 2
    det = Detections(proposed[:1], np.array([0.9]), np.zeros(1, np.int64))      # the detector found the first only
    res = _blind_estimator(det, depth_proposals=DepthProposals(max_iou=1.0)).estimate(
        f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert any(p.detector_score == 0.0 for p in res.poses + res.rejected)        # proposals were posed
    assert seen and all(np.array_equal(b, proposed[:1]) for b in seen)
    seen.clear()
    _blind_estimator(Detections.empty()).estimate(f.rgb, f.depth_m, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert seen == []


def test_a_detection_on_flat_depth_is_refused_and_the_depths_proposals_still_posed(forklift_frame):
    """Flat depth around the detector's boxes refuses those boxes (no pallet stands there, or the depth is a
    wall's); a proposal stands where the depth is not flat, so it is posed and judged as without that box."""
    f = forklift_frame
    depth = f.depth_m.copy()
    depth[:120, :320] = 4.0
    alone = _blind_estimator(Detections.empty()).estimate(f.rgb, depth, f.K, T_vehicle_cam=f.T_vehicle_cam)
    assert alone.poses                                # the proposals alone show pallets
    det = Detections(np.array([[20.0, 10.0, 180.0, 50.0]]), np.array([0.9]), np.zeros(1, np.int64))
    res = _blind_estimator(det).estimate(f.rgb, depth, f.K, T_vehicle_cam=f.T_vehicle_cam)
    refused = [r for r in res.rejected if r.detector_score == 0.9]
    assert [r.reason for r in refused] == ["depth_image_mismatch"] and "flat" in refused[0].detail
    posed = sorted(r.box_xyxy.tolist() for r in res.poses + res.rejected if r.detector_score == 0.0)
    assert posed == sorted(r.box_xyxy.tolist() for r in alone.poses + alone.rejected)
    assert not [r for r in res.rejected if r.detector_score == 0.0 and r.reason == "depth_image_mismatch"]
    assert res.poses and all(p.detector_score == 0.0 for p in res.poses)
