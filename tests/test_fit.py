import numpy as np
import pytest

from pallet6d.runtime.fit import ModelPointIndex, distance_to_boxes, distance_to_points, fit_score, fit_scores
from pallet6d.runtime.geometry import (backproject_pixels, clamp_box, make_T, quat_to_rot, sample_indices,
                                       select_pixels)

sim_generate = pytest.importorskip("pallet6d.sim.generate")
from pallet6d.sim.pallets import get_pallet_model  # noqa: E402
from pallet6d.sim.presets import get_preset  # noqa: E402

EPAL = get_pallet_model("epal")
MODEL_PTS = EPAL.surface_points(1000, seed=0)
RZ90 = make_T(quat_to_rot(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])), np.zeros(3))


def _observed(frame, n=500):
    """The target pallet's box as a detector would give it: 500 sampled back-projected points."""
    gt = frame.pallet(frame.target_instance)
    x, y, w, h = gt.bbox_visib_xywh
    box = clamp_box(np.array([x, y, x + w, y + h], float), frame.depth_m.shape)
    v, u = select_pixels(frame.depth_m, box)
    idx = sample_indices(len(v), n, np.random.default_rng(0))
    return gt.T_cam_pallet, backproject_pixels(u[idx], v[idx], frame.depth_m[v[idx], u[idx]], frame.K)


@pytest.fixture(scope="module", params=[("virtual-clean", 0), ("indoor-noisy", 1)], ids=lambda p: p[0])
def scene(request):
    name, seed = request.param
    frame = sim_generate.generate_frame(get_preset(name), seed=seed)
    T_gt, obs = _observed(frame)
    return frame, T_gt, obs


def _score(scene, T, boxes=EPAL.boxes_m):
    frame, _, obs = scene
    return fit_score(T, obs, MODEL_PTS, frame.depth_m, frame.K, tol_m=0.04, model_boxes_m=boxes)


def test_ground_truth_scores_high(scene):
    _, T_gt, _ = scene
    s = _score(scene, T_gt)
    assert s.score > 0.5 and s.free_space_violation < 0.06
    # the symmetric twin is just as good; surface points give the same verdict as boxes
    assert _score(scene, T_gt @ np.diag([-1.0, -1.0, 1.0, 1.0])).score > 0.5
    assert _score(scene, T_gt, boxes=None).score > 0.45


@pytest.mark.parametrize("shift", [(0.2, 0, 0), (0, 0.2, 0), (0, 0, 0.2), (0, 0, -0.2)], ids=str)
def test_shifted_20cm_scores_low(scene, shift):
    _, T_gt, _ = scene
    good = _score(scene, T_gt).score
    bad = _score(scene, make_T(T_gt[:3, :3], T_gt[:3, 3] + np.array(shift)))
    assert bad.score < 0.75 * good and bad.score < 0.5


def test_turned_90deg_scores_low(scene):
    _, T_gt, _ = scene
    bad = _score(scene, T_gt @ RZ90)
    assert bad.score < 0.3 and bad.free_space_violation > 0.1


def test_no_observed_points_gives_zero_inliers():
    K = np.array([[500.0, 0, 32], [0, 500, 24], [0, 0, 1]])
    s = fit_score(make_T(np.eye(3), [0, 0, 3.0]), np.zeros((0, 3)), MODEL_PTS, np.zeros((48, 64), np.float32), K)
    assert s.inlier_fraction == 0.0 and s.free_space_violation == 0.0 and s.score == 0.0


def test_wall_in_front_of_camera_is_a_violation():
    # the observed depth is a wall at 5 m; a pallet posed at 3 m would have blocked it everywhere
    K = np.array([[300.0, 0, 32], [0, 300, 24], [0, 0, 1]])
    depth = np.full((48, 64), 5.0, np.float32)
    s = fit_score(make_T(np.eye(3), [0, 0, 3.0]), np.array([[0, 0, 5.0]]), MODEL_PTS, depth, K)
    assert s.free_space_violation == 1.0 and s.score == 0.0


def test_distances():
    boxes = np.array([[[0, 0, 0], [1, 1, 1]]], float)
    np.testing.assert_allclose(distance_to_boxes(np.array([[0.5, 0.5, 0.5], [2, 0.5, 0.5], [2, 2, 0.5]]), boxes),
                               [0, 1, np.sqrt(2)])
    np.testing.assert_allclose(distance_to_points(np.array([[0, 0, 0.3]]), np.array([[0, 0, 0], [0, 0, 1]])), [0.3],
                               atol=1e-6)
    with pytest.raises(ValueError, match="boxes_m"):
        distance_to_boxes(np.zeros((1, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="tol_m"):
        fit_score(np.eye(4), np.zeros((1, 3)), MODEL_PTS, np.zeros((4, 4)), np.eye(3), tol_m=0)


@pytest.mark.parametrize("boxes", [EPAL.boxes_m, None], ids=["boxes", "points"])
def test_fit_scores_equal_fit_score_pose_by_pose(scene, boxes):
    frame, T_gt, obs = scene
    rng = np.random.default_rng(4)
    Ts = np.stack([T_gt] + [make_T(T_gt[:3, :3], T_gt[:3, 3] + rng.uniform(-0.1, 0.1, 3)) for _ in range(3)]
                  + [T_gt @ RZ90])
    counts = np.array([len(obs), 300, 0, 1, 120])                # each pose its own first rows, one with none
    inlier, violation, score = fit_scores(Ts, np.broadcast_to(obs, (len(Ts),) + obs.shape), counts, MODEL_PTS,
                                          frame.depth_m, frame.K, 0.04, boxes)
    # with the boxes holding every model point, distances to points may skip points far from the boxes
    in_boxes = fit_scores(Ts, np.broadcast_to(obs, (len(Ts),) + obs.shape), counts, MODEL_PTS, frame.depth_m,
                          frame.K, 0.04, boxes, points_in_boxes_m=EPAL.boxes_m)
    for i, T in enumerate(Ts):
        ref = fit_score(T, obs[:counts[i]], MODEL_PTS, frame.depth_m, frame.K, 0.04, boxes)
        assert (inlier[i], violation[i], score[i]) == (ref.inlier_fraction, ref.free_space_violation, ref.score)
        assert (in_boxes[0][i], in_boxes[2][i]) == (ref.inlier_fraction, ref.score)
    assert inlier[2] == 0.0
    none = fit_scores(np.zeros((0, 4, 4)), np.zeros((0, 5, 3)), None, MODEL_PTS, frame.depth_m, frame.K)
    assert none[2].shape == (0,)
    with pytest.raises(ValueError, match="pts_obs_cam"):
        fit_scores(Ts, obs[None], None, MODEL_PTS, frame.depth_m, frame.K)
    with pytest.raises(ValueError, match="T_cam_model"):
        fit_scores(np.eye(4), obs[None], None, MODEL_PTS, frame.depth_m, frame.K)


@pytest.mark.parametrize("tol_m", [0.04, 0.015])
def test_model_point_index_finds_every_model_point_within_tol(tol_m):
    rng = np.random.default_rng(7)
    lo, hi = MODEL_PTS.min(0) - 0.1, MODEL_PTS.max(0) + 0.1
    pts = np.concatenate([rng.uniform(lo, hi, (3000, 3)),                         # around and inside the pallet
                          MODEL_PTS[:200] + rng.normal(0, tol_m / 2, (200, 3)),   # near the surface
                          [[50.0, 0.0, 0.0], [-3.0, -3.0, -3.0]]])                # far outside the grid
    ref = distance_to_points(pts, MODEL_PTS)
    index = ModelPointIndex(MODEL_PTS, 0.04)
    assert index.points.shape == MODEL_PTS.shape and index.offsets[-1] == len(MODEL_PTS)   # each point held once
    got = index.distances(pts)
    within = ref <= tol_m
    assert 100 < within.sum() < len(pts) - 100
    np.testing.assert_array_equal(got <= tol_m, within)
    np.testing.assert_allclose(got[within], ref[within], atol=1e-5)            # the search runs in float32
    assert np.all(got[-2:] > 0.04) and ModelPointIndex(MODEL_PTS[:1], 0.04).distances(np.zeros((0, 3))).shape == (0,)


def test_model_point_index_bad_input_and_one_point():
    with pytest.raises(ValueError, match="tol_m"):
        ModelPointIndex(MODEL_PTS, 0.0)
    with pytest.raises(ValueError, match="model points"):
        ModelPointIndex(np.zeros((0, 3)), 0.04)
    one = ModelPointIndex(np.array([[0.1, 0.2, 0.3]]), 0.04)
    np.testing.assert_allclose(one.distances(np.array([[0.1, 0.2, 0.33], [0.1, 0.2, 0.5]]))[0], 0.03)
    assert one.distances(np.array([[0.1, 0.2, 0.5]]))[0] > 0.04


def test_fit_scores_with_a_point_index_equal_the_search(scene):
    frame, T_gt, obs = scene
    rng = np.random.default_rng(5)
    Ts = np.stack([T_gt] + [make_T(T_gt[:3, :3], T_gt[:3, 3] + rng.uniform(-0.1, 0.1, 3)) for _ in range(4)])
    args = (Ts, np.broadcast_to(obs, (len(Ts),) + obs.shape), None, MODEL_PTS, frame.depth_m, frame.K, 0.04)
    ref = fit_scores(*args, points_in_boxes_m=EPAL.boxes_m)
    for index in (ModelPointIndex(MODEL_PTS, 0.04), ModelPointIndex(MODEL_PTS, 0.03)):   # 0.03: too small, unused
        got = fit_scores(*args, points_in_boxes_m=EPAL.boxes_m, point_index=index)
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
