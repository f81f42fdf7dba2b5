import json
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pallet6d.runtime.bundle import BundleError
from pallet6d.runtime.cameras import RGBDFrame
from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator
from pallet6d.runtime.metrics import add_sym
from pallet6d.runtime.results import FrameResult, PalletPose

from estimator_fixtures import scene, visible_boxes


@pytest.fixture(scope="module")
def frame():
    return scene()


@pytest.fixture(scope="module")
def boxes(frame):
    """The visible boxes of four pallets, as a detector would give them."""
    return visible_boxes(frame, 4)


@pytest.fixture(scope="module")
def est(bundle_dir):
    # min_fit=0, no structure check: random weights never fit, and these tests are about the plumbing
    return PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None)


def _key(result: FrameResult):
    """Everything of a result except the timings."""
    d = result.to_dict()
    d.pop("timings_ms")
    return json.dumps(d, sort_keys=True)


def test_end_to_end_types_shapes_and_determinism(est, frame):
    r1 = est.estimate(frame.rgb, frame.depth_m, frame.K)
    r2 = est.estimate(frame.rgb, frame.depth_m, frame.K)
    assert isinstance(r1, FrameResult) and r1.image_hw == frame.depth_m.shape
    assert len(r1.poses) + len(r1.rejected) >= 1, "a random detector at threshold 0 finds something"
    assert len(r1.poses) + len(r1.rejected) <= est.options.max_pallets
    for p in r1.poses:
        assert isinstance(p, PalletPose) and p.T_cam_pallet.shape == (4, 4) and p.quat_wxyz.shape == (4,)
        np.testing.assert_allclose(p.R @ p.R.T, np.eye(3), atol=1e-6)
        assert 0 <= p.confidence <= 1 and 0 <= p.fit.score <= 1
    assert set(r1.timings_ms) >= {"preprocess", "detector", "decode_nms", "pose_inputs", "fusion", "pose",
                                  "selection", "fit", "total"}
    assert _key(r1) == _key(r2)
    json.dumps(r1.to_dict())  # serialisable as one JSON line


def test_detect_is_the_detector_stage_of_estimate(est, frame):
    det = est.detect(frame.rgb)
    r = est.estimate(frame.rgb, frame.depth_m, frame.K)
    h, w = frame.depth_m.shape
    assert 1 <= len(det) <= est.options.max_pallets and np.all(np.diff(det.scores) <= 0)
    assert np.all(det.boxes_xyxy[:, [0, 2]] >= -1) and np.all(det.boxes_xyxy[:, [0, 2]] <= w + 1)
    assert np.all(det.boxes_xyxy[:, [1, 3]] >= -1) and np.all(det.boxes_xyxy[:, [1, 3]] <= h + 1)
    posed = sorted([*(p.box_xyxy for p in r.poses), *(x.box_xyxy for x in r.rejected)], key=lambda b: tuple(b))
    np.testing.assert_allclose(posed, sorted(det.boxes_xyxy.tolist(), key=tuple))
    # the same checks and messages as estimate's
    for bad, error, match in ((frame.rgb[..., 0], ValueError, "rgb must be \\(H, W, 3\\)"),
                              (frame.rgb.astype(np.float32), TypeError, "rgb must be uint8"),
                              (None, TypeError, "rgb must be a numpy array")):
        with pytest.raises(error, match=match):
            est.detect(bad)


def test_predict_returns_the_accepted_poses(est, frame):
    poses = est.predict(frame.rgb, frame.depth_m, frame.K)
    assert [p.to_dict() for p in poses] == [p.to_dict() for p in est.estimate(frame.rgb, frame.depth_m, frame.K).poses]


def test_rgbd_frame_input_equals_arrays(est, frame):
    rgbd = RGBDFrame.from_depth_m(frame.rgb, frame.depth_m, frame.K, 0.0, 0, "test")
    a = est.estimate(rgbd)
    b = est.estimate(frame.rgb, rgbd.depth, frame.K, depth_scale=rgbd.depth_scale_m)
    assert _key(a) == _key(b)


def test_no_detections_gives_empty_list(bundle_dir, frame):
    strict = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=1.0, weak_boxes=None)
    assert strict.predict(frame.rgb, frame.depth_m, frame.K) == []
    r = strict.estimate(frame.rgb, frame.depth_m, frame.K)
    assert r.poses == [] and r.rejected == []


def test_four_pallets_batched_equal_one_at_a_time(est, frame, boxes):
    batched = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert len(batched.poses) == 4
    for box, pose in zip(boxes, batched.poses):
        single = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=box[None])
        assert len(single.poses) == 1
        np.testing.assert_allclose(single.poses[0].T_cam_pallet, pose.T_cam_pallet, atol=1e-5)
        np.testing.assert_allclose(single.poses[0].box_xyxy, box)
        assert single.poses[0].n_valid_points == pose.n_valid_points


def test_graphs_run_in_chunks_of_graph_batch_with_the_same_poses(est, frame, boxes, monkeypatch):
    whole = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    calls = []
    fusion = est.pose_network.fusion
    fusion_run = fusion.run
    monkeypatch.setattr(fusion, "run", lambda feeds, out: calls.append(len(next(iter(feeds.values()))))
                        or fusion_run(feeds, out))
    monkeypatch.setattr(est.pose_network, "graph_batch", 3)
    chunked = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert calls == [3, 1]
    assert len(chunked.poses) == len(whole.poses) == 4
    for a, b in zip(whole.poses, chunked.poses):
        np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet, atol=1e-5)
        assert a.confidence == pytest.approx(b.confidence, abs=1e-5)


@pytest.fixture(scope="module")
def lanes_est(bundle_dir):
    est = PalletEstimator.from_bundle(bundle_dir, threads=2, score_threshold=0.0, min_fit=0.0, structure=None,
                                      pallet_lanes=None)
    yield est
    est.close()


def test_pallet_lanes_give_the_same_poses_as_one_after_the_other(lanes_est, frame, boxes):
    assert lanes_est.pose_network.lanes == 2                      # None: as many as threads
    one = PalletEstimator.from_bundle(lanes_est.bundle.root, threads=2, score_threshold=0.0, min_fit=0.0,
                                      structure=None)
    assert one.pose_network.lanes == 1                            # the default
    a = one.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    b = lanes_est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    assert one.pose_network._lane_graphs is None                  # one lane: no one-thread copy of the graphs
    assert lanes_est.pose_network._lane_graphs is not None        # several pallets went side by side
    assert len(a.poses) == len(b.poses) == len(boxes) and a.rejected == b.rejected == []
    for pa, pb in zip(a.poses, b.poses):
        np.testing.assert_allclose(pb.T_cam_pallet, pa.T_cam_pallet, atol=1e-6)
        assert pb.confidence == pytest.approx(pa.confidence, abs=1e-6)
    assert b.timings_ms["fusion"] > 0 and b.timings_ms["pose"] > 0


def test_pallet_lanes_keep_one_pallet_on_all_threads(bundle_dir, frame, boxes):
    est = PalletEstimator.from_bundle(bundle_dir, threads=2, score_threshold=0.0, min_fit=0.0, structure=None,
                                      pallet_lanes=2)
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:1])
    assert len(r.poses) == 1 and est.pose_network._lane_graphs is None
    est.close()
    est.close()                                                   # twice is fine


def test_pallet_lanes_stop_taking_pallets_once_the_budget_is_spent(lanes_est, frame, boxes):
    """Chunks are taken in order: whatever the lanes did when the budget ran out, the rows run are the first."""
    pn = lanes_est.pose_network
    batch, _ = pn.preprocess(frame.rgb, frame.depth_m, frame.K, boxes)

    class AfterReads:          # a deadline that expires after its first `n` reads
        def __init__(self, n):
            self.left, self.budget_ms = n, 1.0

        def expired(self):
            self.left -= 1
            return self.left < 0

    full = pn.infer(batch)
    for n in range(0, 6):
        quat, trans, conf = pn.infer(batch, {}, AfterReads(n))
        assert len(quat) == min(n, len(boxes))
        np.testing.assert_array_equal(conf, full[2][:len(conf)])


@pytest.mark.parametrize("lanes", [0, -1])
def test_pallet_lanes_option_is_checked(lanes):
    with pytest.raises(ValueError, match="pallet_lanes"):
        EstimatorOptions(pallet_lanes=lanes)


def test_rejections_are_reported_with_reasons(bundle_dir, frame, boxes):
    depth = frame.depth_m.copy()
    x1, y1, x2, y2 = boxes[1].astype(int)
    depth[y1:y2, x1:x2] = 0.0                                   # no depth in the second box
    outside = [5000.0, 5000.0, 5100.0, 5100.0]
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, min_fit=1.0)   # nothing random fits perfectly
    r = est.estimate_boxes(frame.rgb, depth, frame.K, boxes_xyxy=np.vstack([boxes[:2], outside]),
                           scores=[0.9, 0.8, 0.7])
    assert r.poses == []
    reasons = [x.reason for x in r.rejected]
    assert reasons == ["poor_fit", "too_few_points", "box_outside_image"]
    assert r.rejected[0].pose is not None and r.rejected[1].pose is None
    assert "valid depth pixels" in r.rejected[1].detail
    for bad in (dict(boxes_xyxy=[[np.nan, 0.0, 10.0, 10.0]]), dict(boxes_xyxy=boxes[:1], scores=[np.inf])):
        with pytest.raises(ValueError, match="boxes_xyxy and scores must be finite"):
            est.estimate_boxes(frame.rgb, depth, frame.K, **bad)


def _bad(frame):
    rgb, d, K = frame.rgb, frame.depth_m, frame.K
    nan = d.copy()
    nan[0, 0] = np.nan
    return [
        ("rgb_list", dict(rgb=rgb.tolist(), depth=d, K=K), TypeError, "numpy array"),
        ("rgb_float", dict(rgb=rgb.astype(np.float32), depth=d, K=K), TypeError, "uint8"),
        ("rgb_gray", dict(rgb=rgb[..., 0], depth=d, K=K), ValueError, r"\(H, W, 3\)"),
        ("depth_3ch", dict(rgb=rgb, depth=np.dstack([d] * 3), K=K), ValueError, "single-channel"),
        ("size_mismatch", dict(rgb=rgb, depth=d[:-10], K=K), ValueError, "aligned"),
        ("depth_int32", dict(rgb=rgb, depth=d.astype(np.int32), K=K), TypeError, "uint16"),
        ("all_zero", dict(rgb=rgb, depth=np.zeros_like(d), K=K), ValueError, "all zero"),
        ("nan", dict(rgb=rgb, depth=nan, K=K), ValueError, "NaN/inf"),
        ("inf", dict(rgb=rgb, depth=np.where(d > 3, np.inf, d).astype(np.float32), K=K), ValueError, "NaN/inf"),
        ("negative", dict(rgb=rgb, depth=d - 100.0, K=K), ValueError, "negative"),
        ("millimetres_as_float", dict(rgb=rgb, depth=d * 1000, K=K), ValueError, "millimetres"),
        ("missing_K", dict(rgb=rgb, depth=d, K=None), ValueError, "intrinsics K are missing"),
        ("bad_K", dict(rgb=rgb, depth=d, K=np.eye(4)), ValueError, "3x3"),
        ("scale_with_float", dict(rgb=rgb, depth=d, K=K, depth_scale=0.001), ValueError, "uint16 only"),
        ("missing_depth", dict(rgb=rgb, depth=None, K=K), ValueError, "depth is missing"),
    ]


BAD_IDS = [c[0] for c in _bad(type("F", (), dict(rgb=np.zeros((4, 4, 3), np.uint8), depth_m=np.ones((4, 4)),
                                                  K=np.eye(3)))())]


@pytest.mark.parametrize("case", BAD_IDS)
def test_bad_inputs_raise_clear_errors(est, frame, case):
    _, kwargs, exc, match = next(c for c in _bad(frame) if c[0] == case)
    with pytest.raises(exc, match=match):
        est.predict(**kwargs)


def test_nan_depth_as_missing_option(bundle_dir, frame):
    depth = frame.depth_m.copy()
    depth[depth == 0] = np.nan
    lenient = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None,
                                          nonfinite_depth="as_missing")
    strict_zero = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None)
    assert _key(lenient.estimate(frame.rgb, depth, frame.K)) == _key(strict_zero.estimate(frame.rgb, frame.depth_m,
                                                                                          frame.K))


def test_bad_options_and_precision(bundle_dir):
    with pytest.raises(ValueError, match="max_pallets"):
        EstimatorOptions(max_pallets=0)
    with pytest.raises(ValueError, match="refine_margin"):
        EstimatorOptions(refine_margin=-1.1)
    with pytest.raises(ValueError, match="refine_max_rms_m"):
        EstimatorOptions(refine_max_rms_m=0.0)
    for bad in ({"refine_starts": -1}, {"refine_starts": 15}):
        with pytest.raises(ValueError, match="refine_starts"):
            EstimatorOptions(**bad)
    with pytest.raises(ValueError, match="refine_select_tol_m"):
        EstimatorOptions(refine_select_tol_m=0.0)
    with pytest.raises(ValueError, match="refine_start_max_rms_m"):
        EstimatorOptions(refine_start_max_rms_m=-0.001)
    with pytest.raises(ValueError, match="precision"):
        PalletEstimator.from_bundle(bundle_dir, precision="fp16")
    for seed in (-1, 1.5, True, "0"):          # numpy's sampler would refuse a negative seed at every frame
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            EstimatorOptions(seed=seed)
    assert EstimatorOptions(seed=np.int64(3)).seed == 3
    for threads in (0, 65, 100000, 2.5, True):  # onnxruntime would make 100000 threads, or refuse 0 mid-load
        with pytest.raises(ValueError, match="threads must be an integer in 1..64"):
            PalletEstimator.from_bundle(bundle_dir, threads=threads)


def test_bundle_that_disagrees_with_its_graphs(bundle_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(bundle_dir, bad)
    man = json.loads((bad / "manifest.json").read_text())
    man["pose"]["num_points"] += 1
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(BundleError, match="disagrees with its own graphs.*num_points"):
        PalletEstimator.from_bundle(bad)


def test_rgb_detector_graph_under_a_manifest_that_says_depth(bundle_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(bundle_dir, bad)
    man = json.loads((bad / "manifest.json").read_text())
    man["detector"]["depth_max_m"] = 10.0
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(BundleError, match="disagrees with its own graphs.*input channels"):
        PalletEstimator.from_bundle(bad)


def test_runtime_prediction_never_imports_torch(bundle_dir):
    code = textwrap.dedent(f"""
        import sys
        import numpy as np
        from pallet6d.runtime.estimator import PalletEstimator
        est = PalletEstimator.from_bundle({str(bundle_dir)!r}, threads=1, score_threshold=0.0, min_fit=0.0, structure=None)
        rng = np.random.default_rng(0)
        rgb = rng.integers(0, 255, (120, 200, 3), dtype=np.uint8)
        depth = rng.uniform(1.0, 4.0, (120, 200)).astype(np.float32)
        K = np.array([[150.0, 0, 100], [0, 150, 60], [0, 0, 1]])
        r = est.estimate(rgb, depth, K)
        print(len(r.poses) + len(r.rejected), "torch" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    n, has_torch = out.stdout.split()
    assert int(n) >= 1 and has_torch == "False"


@pytest.mark.parametrize("margin, max_rms_m", [(0.0, 1.0), (0.02, 1.0), (1.0, 1.0), (0.0, 1e-9)])
def test_refined_pose_is_kept_only_when_it_fits_the_depth_better_by_the_margin(bundle_dir, frame, boxes, margin,
                                                                               max_rms_m):
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None, refine_margin=margin,
                                      refine_max_rms_m=max_rms_m, refine_starts=0)
    plain = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None, refine=False)
    assert est.refines and not plain.refines
    r, r0 = (e.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes) for e in (est, plain))
    assert len(r.poses) == len(r0.poses) == len(boxes)
    kept = 0
    for p, p0 in zip(r.poses, r0.poses):
        if np.allclose(p.T_cam_pallet, p0.T_cam_pallet):   # the network's pose stayed
            assert p.fit.score == pytest.approx(p0.fit.score)
        else:                                              # the refined pose won by the margin
            assert p.fit.score >= p0.fit.score + margin - 1e-12
            kept += 1
    if margin >= 1.0 or max_rms_m < 1e-6:  # no ICP result has a residual that small
        assert kept == 0
    elif margin == 0.0:
        assert kept >= 1   # on this rendered frame ICP does improve some network poses


def test_extra_starts_bring_back_a_network_pose_turned_out_of_icps_basin(bundle_dir, frame, boxes, monkeypatch):
    from pallet6d.runtime.geometry import make_T
    from pallet6d.sim.pallets import get_pallet_model

    # the network says: each pallet's true pose turned 20 degrees about its vertical axis
    T_gt = np.stack([p.T_cam_pallet for p in sorted(frame.pallets, key=lambda p: -p.visib_fract)[:len(boxes)]])
    a = np.deg2rad(20.0)
    turn = make_T(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]), np.zeros(3))

    def network_pose(quat, trans, conf, batch):
        return T_gt @ turn, np.ones(len(T_gt))

    pallet = get_pallet_model("epal")
    pts = pallet.surface_points(500, seed=0)

    def errors(est):
        monkeypatch.setattr(est.pose_network, "postprocess", network_pose)
        r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
        assert len(r.poses) == len(boxes)
        return np.array([add_sym(p.T_cam_pallet[:3, :3], p.T_cam_pallet[:3, 3], T[:3, :3], T[:3, 3], pts,
                                 pallet.symmetries) for p, T in zip(r.poses, T_gt)])

    kw = dict(threads=1, score_threshold=0.0, min_fit=0.0, structure=None)
    e_off = errors(PalletEstimator.from_bundle(bundle_dir, refine=False, **kw))
    e_icp = errors(PalletEstimator.from_bundle(bundle_dir, refine_starts=0, **kw))
    e_starts = errors(PalletEstimator.from_bundle(bundle_dir, **kw))
    assert np.all(e_off > 0.1)
    assert np.sum(e_icp < 0.05) <= 1                 # ICP alone keeps most where the network put them
    assert np.sum(e_starts < 0.01) >= len(boxes) - 1, e_starts


def test_noisy_depth_keeps_the_network_pose(bundle_dir, frame, boxes):
    # stereo-like noise (2 cm) pulls ICP off; its residual stays above refine_max_rms_m, so the network's pose stays
    rng = np.random.default_rng(3)
    depth = np.where(frame.depth_m > 0, frame.depth_m + rng.normal(0, 0.02, frame.depth_m.shape), 0).astype(np.float32)
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None)
    plain = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, structure=None, refine=False)
    r, r0 = (e.estimate_boxes(frame.rgb, depth, frame.K, boxes_xyxy=boxes) for e in (est, plain))
    assert len(r.poses) == len(r0.poses) == len(boxes) >= 1
    for p, p0 in zip(r.poses, r0.poses):
        np.testing.assert_allclose(p.T_cam_pallet, p0.T_cam_pallet)


def test_the_confidence_floor_is_on_by_default(bundle_dir, frame, boxes, monkeypatch):
    """Without being asked, a pose whose network confidence is under 0.1 is refused ("low_confidence"), one at or
    over it is not."""
    from pallet6d.runtime.stage_pose import PoseNetworkStage

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, min_fit=0.0, structure=None)
    assert est.options.min_confidence == 0.1
    post = PoseNetworkStage.postprocess

    def fixed_confidences(self, quat, trans, conf, batch):
        T, confidence = post(self, quat, trans, conf, batch)
        return T, np.resize([0.05, 0.1], len(confidence))

    monkeypatch.setattr(PoseNetworkStage, "postprocess", fixed_confidences)
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:2], scores=[0.9, 0.8])
    assert [x.reason for x in r.rejected] == ["low_confidence"]
    assert [p.confidence for p in r.poses] == [pytest.approx(0.1)]


def test_a_pose_under_the_confidence_floor_costs_no_type_choice_or_refinement(bundle_dir, frame, boxes, monkeypatch):
    """The confidence is the network's: no later stage changes it, so it is judged first and the candidate
    never reaches the type choice and refinement (with a calibration the most costly work of a frame)."""
    from pallet6d.runtime.stage_pose import PoseNetworkStage
    from pallet6d.runtime.stage_refine import RefinerStage

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, min_fit=0.0, structure=None)
    post, refine = PoseNetworkStage.postprocess, RefinerStage.__call__
    seen = []

    def fixed_confidences(self, quat, trans, conf, batch):
        T, confidence = post(self, quat, trans, conf, batch)
        return T, np.resize([0.05, 0.1], len(confidence))

    def watched(self, cands, *args, **kwargs):
        seen.append(cands.alive.copy())
        return refine(self, cands, *args, **kwargs)

    monkeypatch.setattr(PoseNetworkStage, "postprocess", fixed_confidences)
    monkeypatch.setattr(RefinerStage, "__call__", watched)
    r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:2], scores=[0.9, 0.8])
    assert [s.tolist() for s in seen] == [[False, True]]
    assert [(x.reason, x.pose) for x in r.rejected] == [("low_confidence", None)]
    assert len(r.poses) == 1
