"""pose_inputs: crops, depth encoding, sampling, back-projection and feature indices, on edge cases."""
import numpy as np
import pytest

from pallet6d.runtime import geometry
from pallet6d.runtime.pose_inputs import PoseBatch, PoseInputSpec, encode_depth, gather_features, prepare_pose_inputs

K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
SPEC = PoseInputSpec(crop_hw=(16, 16), rgb_mean=(0.5, 0.5, 0.5), rgb_std=(0.25, 0.25, 0.25), depth_clip_m=1.0,
                     num_points=20, depth_range_m=(0.1, 10.0))


def frame(depth_value=2.0, hw=(48, 64)):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, hw + (3,), dtype=np.uint8)
    depth = np.full(hw, depth_value, np.float32)
    return rgb, depth


def test_shapes_and_backprojection_consistent():
    rgb, depth = frame()
    depth[10:20, 10:30] = 3.0
    b = prepare_pose_inputs(rgb, depth, K, [[8, 8, 40, 30]], SPEC, np.random.default_rng(1))
    assert b.rgb_crops.shape == (1, 3, 16, 16) and b.depth_crops.shape == (1, 1, 16, 16)
    assert b.points.shape == (1, 20, 3) and b.choose.shape == (1, 20)
    assert b.has_depth.tolist() == [True] and b.n_valid[0] == 32 * 22
    pts = b.points[0] + b.centres[0]
    # every sampled point lies on its pixel's ray at that pixel's depth, inside the box
    uv = geometry.project_points(pts, K)
    assert np.all((uv[:, 0] >= 7.5) & (uv[:, 0] <= 39.5) & (uv[:, 1] >= 7.5) & (uv[:, 1] <= 29.5))
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    np.testing.assert_allclose(pts[:, 2], depth[v, u], atol=1e-5)
    np.testing.assert_allclose(b.points[0].mean(0), 0, atol=1e-5)
    # choose points at the crop pixel the sampled image pixel was resized to
    cu, cv = b.choose[0] % 16, b.choose[0] // 16
    np.testing.assert_array_equal(cu, np.floor((u - 8 + 0.5) * 16 / 32).astype(int))
    np.testing.assert_array_equal(cv, np.floor((v - 8 + 0.5) * 16 / 22).astype(int))
    # depth encoding: the near patch is at median + 1 m -> clipped to +1, the rest at the median -> 0
    assert set(np.unique(b.depth_crops)) <= {0.0, 1.0}
    # rgb normalisation
    crop = rgb[8:30, 8:40]
    assert abs(b.rgb_crops[0].mean() - ((crop.mean() / 255 - 0.5) / 0.25)) < 0.05


@pytest.mark.parametrize("box, in_image, has_depth", [
    ([100, 100, 120, 120], False, False),     # outside the image
    ([-50, -50, -1, -1], False, False),
    ([np.nan, 0, 10, 10], False, False),
    ([60, 40, 200, 200], True, True),         # partly outside: clamped
])
def test_box_outside_or_partial(box, in_image, has_depth):
    rgb, depth = frame()
    b = prepare_pose_inputs(rgb, depth, K, [box], SPEC, np.random.default_rng(0))
    assert b.box_in_image.tolist() == [in_image] and b.usable.tolist() == [has_depth]
    if not in_image:
        assert b.boxes_xyxy[0].tolist() == [-1, -1, -1, -1] and not b.points.any()
    else:
        assert b.boxes_xyxy[0].tolist() == [60, 40, 64, 48]


def test_zero_valid_depth_is_flagged_not_invented():
    rgb, depth = frame(depth_value=0.0)
    depth[0, 0] = np.nan
    b = prepare_pose_inputs(rgb, depth, K, [[0, 0, 20, 20], [30, 30, 50, 45]], SPEC, np.random.default_rng(0))
    assert b.box_in_image.all() and not b.has_depth.any() and b.n_valid.tolist() == [0, 0]
    assert not b.points.any() and not b.depth_crops.any()
    assert len(b.take(np.flatnonzero(b.usable))) == 0


@pytest.mark.parametrize("n_valid", [1, 20, 21, 200])
def test_oversampling_and_subsampling(n_valid):
    rgb, depth = frame(depth_value=0.0)
    ys, xs = np.unravel_index(np.arange(n_valid), (20, 20))
    depth[ys + 5, xs + 5] = 1.0 + 0.01 * np.arange(n_valid)
    b = prepare_pose_inputs(rgb, depth, K, [[5, 5, 25, 25]], SPEC, np.random.default_rng(0))
    assert b.n_valid[0] == n_valid
    z = b.points[0, :, 2] + b.centres[0, 2]
    distinct = len(np.unique(np.round(z, 4)))
    assert distinct == min(n_valid, 20)          # every candidate used when fewer than N, none repeated when more


def test_mask_restricts_points():
    rgb, depth = frame()
    mask = np.zeros((1,) + depth.shape, bool)
    mask[0, 10:14, 10:14] = True
    b = prepare_pose_inputs(rgb, depth, K, [[0, 0, 40, 40]], SPEC, np.random.default_rng(0), masks=mask)
    assert b.n_valid[0] == 16
    uv = geometry.project_points(b.points[0] + b.centres[0], K)
    assert np.all((uv >= 9.5) & (uv <= 13.5))


def test_deterministic_per_seed_and_empty_boxes():
    rgb, depth = frame()
    depth += np.random.default_rng(3).uniform(0, 1, depth.shape).astype(np.float32)
    a = prepare_pose_inputs(rgb, depth, K, [[0, 0, 30, 30]], SPEC, np.random.default_rng(7))
    b = prepare_pose_inputs(rgb, depth, K, [[0, 0, 30, 30]], SPEC, np.random.default_rng(7))
    c = prepare_pose_inputs(rgb, depth, K, [[0, 0, 30, 30]], SPEC, np.random.default_rng(8))
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.choose, c.choose)
    empty = prepare_pose_inputs(rgb, depth, K, np.zeros((0, 4)), SPEC, np.random.default_rng(0))
    assert len(empty) == 0 and empty.points.shape == (0, 20, 3)


@pytest.mark.parametrize("kwargs, exc", [
    (dict(rgb=np.zeros((48, 64), np.uint8)), ValueError),
    (dict(rgb=np.zeros((48, 64, 3), np.float32)), ValueError),
    (dict(depth=np.zeros((48, 63), np.float32)), ValueError),
    (dict(depth=np.zeros((48, 64), np.uint16)), ValueError),
    (dict(boxes=[[0, 0, 10]]), ValueError),
    (dict(K=np.eye(2)), ValueError),
    (dict(rng=0), TypeError),
])
def test_bad_input_raises(kwargs, exc):
    rgb, depth = frame()
    args = dict(rgb=rgb, depth=depth, K=K, boxes=[[0, 0, 10, 10]], rng=np.random.default_rng(0))
    args.update(kwargs)
    with pytest.raises(exc):
        prepare_pose_inputs(args["rgb"], args["depth"], args["K"], args["boxes"], SPEC, args["rng"])


def test_encode_depth_and_gather():
    d = np.array([[0.0, 1.0], [2.0, 5.0]], np.float32)
    enc, med = encode_depth(d, clip_m=1.0)
    assert med == 2.0 and enc.tolist() == [[0.0, -1.0], [0.0, 1.0]]
    feats = np.arange(2 * 3 * 2 * 2, dtype=np.float32).reshape(2, 3, 2, 2)
    out = gather_features(feats, np.array([[0, 3], [1, 1]]))
    assert out.shape == (2, 2, 3)
    np.testing.assert_array_equal(out[0, 1], feats[0, :, 1, 1])
    np.testing.assert_array_equal(out[1, 0], feats[1, :, 0, 1])
    with pytest.raises(ValueError, match="choose"):
        gather_features(feats, np.array([[0, 4], [0, 0]]))


def test_batch_validates_shapes():
    with pytest.raises(ValueError, match="points"):
        PoseBatch(np.zeros((1, 3, 4, 4), np.float32), np.zeros((1, 1, 4, 4), np.float32), np.zeros((1, 5, 2), np.float32),
                  np.zeros((1, 5), np.int64), np.zeros((1, 3)), np.zeros(1, np.int64), np.zeros((1, 4), np.int64),
                  np.ones(1, bool), np.ones(1, bool))
