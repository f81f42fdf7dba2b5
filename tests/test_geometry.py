import numpy as np
import pytest

from pallet6d.runtime import geometry as g

K = np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]])


def random_rotation(rng):
    q = rng.normal(size=4)
    return g.quat_to_rot(q)


def test_backproject_then_project_round_trip():
    rng = np.random.default_rng(0)
    u = rng.uniform(0, 640, 50)
    v = rng.uniform(0, 480, 50)
    z = rng.uniform(0.3, 8.0, 50)
    pts = g.backproject_pixels(u, v, z, K)
    assert pts.shape == (50, 3) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[:, 2], z, rtol=1e-6)
    uv = g.project_points(pts, K)
    np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-3)


def test_principal_point_maps_to_optical_axis():
    pts = g.backproject_pixels(np.array([320.0]), np.array([240.0]), np.array([2.0]), K)
    np.testing.assert_allclose(pts, [[0, 0, 2.0]])


def test_backproject_depth_image_shape_and_zero_depth():
    depth = np.zeros((4, 5), np.float32)
    depth[1, 2] = 1.5
    pts = g.backproject_depth(depth, K)
    assert pts.shape == (4, 5, 3)
    assert np.all(pts[0, 0] == 0) and pts[1, 2, 2] == pytest.approx(1.5)


def test_project_behind_camera_is_nan():
    uv = g.project_points(np.array([[0, 0, -1.0], [0, 0, 0.0], [0.1, 0, 1]]), K)
    assert np.isnan(uv[0]).all() and np.isnan(uv[1]).all() and np.isfinite(uv[2]).all()


@pytest.mark.parametrize("depth,scale,expected", [
    (np.array([[1000, 0]], np.uint16), None, [1.0, 0.0]),
    (np.array([[1000, 0]], np.uint16), 0.0001, [0.1, 0.0]),
    (np.array([[1.25, np.nan]], np.float32), None, [1.25, 0.0]),
    (np.array([[np.inf, -2.0]], np.float32), None, [0.0, 0.0]),
])
def test_depth_to_metres(depth, scale, expected):
    out = g.depth_to_metres(depth, scale)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[0], expected, rtol=1e-6)


@pytest.mark.parametrize("depth,scale,exc", [
    (np.zeros((2, 2, 1), np.uint16), None, ValueError),
    (np.zeros((2, 2), np.uint16), 0.0, ValueError),
    (np.zeros((2, 2), np.float32), 0.001, ValueError),
    (np.zeros((2, 2), bool), None, TypeError),
])
def test_depth_to_metres_rejects(depth, scale, exc):
    with pytest.raises(exc):
        g.depth_to_metres(depth, scale)


@pytest.mark.parametrize("bad", [np.eye(2), np.zeros((3, 3)), np.full((3, 3), np.nan)])
def test_bad_intrinsics(bad):
    with pytest.raises(ValueError, match="intrinsics"):
        g.backproject_pixels(np.zeros(1), np.zeros(1), np.ones(1), bad)


@pytest.mark.parametrize("box,expected", [
    ([10.2, 20.7, 30.1, 40.0], [10, 20, 31, 40]),
    ([-5, -5, 10, 10], [0, 0, 10, 10]),
    ([600, 400, 700, 500], [600, 400, 640, 480]),
    ([700, 10, 800, 20], None),          # entirely right of the image
    ([10, 10, 10, 20], None),            # zero width
    ([np.nan, 0, 10, 10], None),
])
def test_clamp_box(box, expected):
    out = g.clamp_box(np.array(box, float), (480, 640))
    if expected is None:
        assert out is None
    else:
        assert out.tolist() == expected


def test_crop_is_view_of_box():
    img = np.arange(48).reshape(6, 8)
    c = g.crop(img, np.array([2, 1, 5, 4]))
    assert c.shape == (3, 3) and c[0, 0] == img[1, 2]


def test_select_pixels_mask_and_range():
    depth = np.zeros((6, 8), np.float32)
    depth[2:4, 2:6] = 2.0
    depth[2, 2] = 20.0                       # out of range
    mask = np.zeros((6, 8), bool)
    mask[2:4, 2:4] = True
    box = np.array([0, 0, 8, 6])
    v, u = g.select_pixels(depth, box, max_depth_m=10.0)
    assert len(v) == 7
    v, u = g.select_pixels(depth, box, mask=mask, max_depth_m=10.0)
    assert sorted(zip(v.tolist(), u.tolist())) == [(2, 3), (3, 2), (3, 3)]
    v, u = g.select_pixels(depth, np.array([4, 0, 8, 6]))   # offsets are in full-image pixels
    assert u.min() == 4


def test_select_pixels_mask_shape_mismatch():
    with pytest.raises(ValueError, match="mask shape"):
        g.select_pixels(np.ones((4, 4)), np.array([0, 0, 4, 4]), mask=np.ones((3, 4), bool))


@pytest.mark.parametrize("n_available,n_points", [(0, 10), (1, 10), (7, 10), (10, 10), (11, 10), (5000, 500)])
def test_sample_indices_edge_cases(n_available, n_points):
    idx = g.sample_indices(n_available, n_points, np.random.default_rng(3))
    if n_available == 0:
        assert idx.shape == (0,)
        return
    assert idx.shape == (n_points,) and idx.dtype == np.int64
    assert idx.min() >= 0 and idx.max() < n_available
    if n_available >= n_points:
        assert len(np.unique(idx)) == n_points          # no repetition
    else:
        assert set(idx.tolist()) == set(range(n_available))  # oversampling keeps every point


def test_sample_indices_deterministic_per_seed():
    a = g.sample_indices(1000, 100, np.random.default_rng(5))
    b = g.sample_indices(1000, 100, np.random.default_rng(5))
    c = g.sample_indices(1000, 100, np.random.default_rng(6))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_sample_indices_rejects_bad_counts():
    with pytest.raises(ValueError):
        g.sample_indices(10, 0, np.random.default_rng(0))
    with pytest.raises(ValueError):
        g.sample_indices(-1, 5, np.random.default_rng(0))


def test_quaternion_round_trip_and_orthonormal():
    rng = np.random.default_rng(1)
    for _ in range(200):
        R = random_rotation(rng)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        q = g.rot_to_quat(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(g.quat_to_rot(q), R, atol=1e-9)


@pytest.mark.parametrize("R", [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
def test_rot_to_quat_special_rotations(R):
    np.testing.assert_allclose(g.quat_to_rot(g.rot_to_quat(R)), R, atol=1e-12)


def test_quat_to_rot_batched_and_bad():
    q = np.array([[1.0, 0, 0, 0], [0, 0, 0, 1]])
    R = g.quat_to_rot(q)
    assert R.shape == (2, 3, 3)
    np.testing.assert_allclose(R[1], np.diag([-1.0, -1, 1]), atol=1e-12)
    with pytest.raises(ValueError):
        g.quat_to_rot(np.zeros(4))
    with pytest.raises(ValueError):
        g.quat_to_rot(np.ones(3))


def test_rigid_transform_inverse_and_batch():
    rng = np.random.default_rng(2)
    T = g.make_T(random_rotation(rng), rng.normal(size=3))
    pts = rng.normal(size=(10, 3))
    back = g.transform_points(g.invert_T(T), g.transform_points(T, pts))
    np.testing.assert_allclose(back, pts, atol=1e-12)
    Tb = np.stack([T, np.eye(4)])
    out = g.transform_points(Tb, np.stack([pts, pts]))
    np.testing.assert_allclose(out[0], g.transform_points(T, pts))
    np.testing.assert_allclose(out[1], pts)
