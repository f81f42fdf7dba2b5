import numpy as np
import pytest

from pallet6d.runtime.geometry import quat_to_rot, rot_to_quat
from pallet6d.runtime.selection import chosen_poses, select_poses


def _hypotheses(B=2, N=5, seed=0):
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(B, N, 4))
    offset = rng.normal(scale=0.1, size=(B, N, 3))
    conf = rng.uniform(0, 0.5, size=(B, N))
    points = rng.normal(scale=0.3, size=(B, N, 3))
    centre = rng.uniform([-1, -1, 2], [1, 1, 5], size=(B, 3))
    return quat, offset, conf, points, centre


def test_picks_the_most_confident_hypothesis_and_adds_point_offset_centre():
    quat, offset, conf, points, centre = _hypotheses()
    conf[0, 3] = 0.9
    conf[1, 1] = 0.8
    q_true = np.array([0.8, 0.2, -0.4, 0.4])
    quat[0, 3] = 2.5 * q_true                     # unnormalised on purpose
    T, c, idx = select_poses(quat, offset, conf, points, centre)
    assert list(idx) == [3, 1]
    np.testing.assert_allclose(c, [0.9, 0.8])
    np.testing.assert_allclose(T[0, :3, 3], points[0, 3] + offset[0, 3] + centre[0])
    np.testing.assert_allclose(T[1, :3, 3], points[1, 1] + offset[1, 1] + centre[1])
    np.testing.assert_allclose(T[0, :3, :3], quat_to_rot(q_true), atol=1e-12)
    np.testing.assert_allclose(T[:, 3], [[0, 0, 0, 1]] * 2)


def test_known_pose_round_trip():
    # every hypothesis of one pallet agrees: the result is that pose whatever wins
    R = quat_to_rot(np.array([0.9, 0.1, 0.3, -0.2]))
    t = np.array([0.4, -0.2, 3.0])
    centre = np.array([[0.35, -0.1, 2.9]])
    points = np.random.default_rng(1).normal(scale=0.2, size=(1, 7, 3))
    offset = t - centre[0] - points                 # so that point + offset + centre = t
    quat = np.tile(rot_to_quat(R), (1, 7, 1))
    T, _, _ = select_poses(quat, offset, np.linspace(0, 1, 7)[None], points, centre)
    np.testing.assert_allclose(T[0, :3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[0, :3, 3], t, atol=1e-12)


def test_xyzw_order_and_nan_confidence():
    quat, offset, conf, points, centre = _hypotheses(B=1, N=3)
    conf[0] = [np.nan, 0.2, 0.1]
    quat[0, 1] = [0.0, 0.0, 1.0, 0.0]                # xyzw: 180 deg about z
    T, c, idx = select_poses(quat, offset, conf, points, centre, quat_order="xyzw")
    assert idx[0] == 1 and c[0] == pytest.approx(0.2)
    np.testing.assert_allclose(T[0, :3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_empty_batch_and_shape_errors():
    T, c, idx = select_poses(np.zeros((0, 5, 4)), np.zeros((0, 5, 3)), np.zeros((0, 5)),
                             np.zeros((0, 5, 3)), np.zeros((0, 3)))
    assert T.shape == (0, 4, 4) and c.shape == (0,) and idx.shape == (0,)
    quat, offset, conf, points, centre = _hypotheses()
    with pytest.raises(ValueError, match=r"conf: expected shape \(2, 5\)"):
        select_poses(quat, offset, conf[:, :4], points, centre)
    with pytest.raises(ValueError, match="quat_order"):
        select_poses(quat, offset, conf, points, centre, quat_order="zyxw")


def test_a_graphs_own_choice_gives_the_same_pose_as_the_choice_here():
    quat, offset, conf, points, centre = _hypotheses(B=3, N=6, seed=2)
    T, c, idx = select_poses(quat, offset, conf, points, centre)
    rows = np.arange(3)
    T2, c2 = chosen_poses(quat[rows, idx], points[rows, idx] + offset[rows, idx], conf[rows, idx], centre)
    np.testing.assert_allclose(T2, T, atol=1e-12)
    np.testing.assert_allclose(c2, c)


def test_a_graphs_own_choice_empty_and_shape_errors():
    T, c = chosen_poses(np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    assert T.shape == (0, 4, 4) and c.shape == (0,)
    with pytest.raises(ValueError, match=r"quat must be \(B, 4\)"):
        chosen_poses(np.zeros((2, 5, 4)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"conf: expected shape \(2,\)"):
        chosen_poses(np.ones((2, 4)), np.zeros((2, 3)), np.zeros((2, 1)), np.zeros((2, 3)))
