"""Poses that occupy the same space: one pallet posed twice is reported once."""
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime.overlap import duplicate_of, overlap_fractions

EPAL = np.array([1.2, 0.8, 0.144])
SHIPPED = Path(__file__).resolve().parents[1] / "models" / "epal-default"


def _pose(x=0.0, y=0.0, z=3.0, yaw_deg=0.0):
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


@pytest.mark.parametrize("other, expected", [
    (_pose(), 1.0),                            # the same pose
    (_pose(x=0.6), 0.5),                       # half a length along: half of it inside
    (_pose(x=1.2), 0.0),                       # side by side
    (_pose(z=3.144), 0.0),                     # stacked (the stack's axis is the pallet's z here)
    (_pose(yaw_deg=180), 1.0),                 # its symmetric twin
    (_pose(yaw_deg=90), 0.8 * 0.8 / (1.2 * 0.8)),   # crossed: the middle 0.8 m of its length
])
def test_overlap_fractions_of_two_epals(other, expected):
    frac = overlap_fractions(np.stack([_pose(), other]), np.stack([EPAL, EPAL]))
    assert frac[0, 0] == frac[1, 1] == 1.0
    assert frac[0, 1] == pytest.approx(expected, abs=0.1)      # an 8 x 8 x 8 grid of cell centres


def test_overlap_fractions_edge_cases():
    assert overlap_fractions(np.zeros((0, 4, 4)), np.zeros((0, 3))).shape == (0, 0)
    assert overlap_fractions(_pose()[None], EPAL[None]).tolist() == [[1.0]]
    with pytest.raises(ValueError, match="2 poses but 1 sizes"):
        overlap_fractions(np.stack([_pose(), _pose()]), EPAL[None])
    # a small pallet inside a big one: all of the small one, part of the big one
    frac = overlap_fractions(np.stack([_pose(), _pose()]), np.stack([EPAL, EPAL / 2]))
    assert frac[1, 0] == 1.0 and frac[0, 1] < 0.2


def test_duplicate_of_keeps_the_first_of_each_place():
    poses = np.stack([_pose(), _pose(x=1.2), _pose(x=0.02), _pose(x=1.25, yaw_deg=180), _pose(x=0.6)])
    assert duplicate_of(poses, np.tile(EPAL, (5, 1))).tolist() == [-1, -1, 0, 1, -1]   # half inside is not more
    assert duplicate_of(np.zeros((0, 4, 4)), np.zeros((0, 3))).tolist() == []
    stack = np.stack([_pose(z=3.0 + 0.144 * k) for k in range(16)])            # a stack of 16: 16 pallets
    assert duplicate_of(stack, np.tile(EPAL, (16, 1))).tolist() == [-1] * 16


def test_overlap_fractions_equal_a_point_by_point_count():
    rng = np.random.default_rng(0)
    poses = np.stack([_pose(*rng.uniform(-0.5, 0.5, 2), 3.0 + rng.uniform(-0.1, 0.1), rng.uniform(0, 360))
                      for _ in range(6)])
    frac = overlap_fractions(poses, np.tile(EPAL, (6, 1)), grid=4)
    t = (np.arange(4) + 0.5) / 4 - 0.5
    own = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * EPAL
    for i, j in np.ndindex(6, 6):
        cam = own @ poses[i][:3, :3].T + poses[i][:3, 3]
        rel = (cam - poses[j][:3, 3]) @ poses[j][:3, :3]
        assert frac[i, j] == pytest.approx(np.all(np.abs(rel) <= EPAL / 2 + 1e-12, axis=1).mean())


def test_the_estimator_reports_one_pallet_posed_twice_once():
    from pallet6d.runtime.estimator import PalletEstimator
    from test_estimator_stages import _scene_of

    f = _scene_of("epal")
    est = PalletEstimator.from_bundle(SHIPPED, threads=1, pallet_types=("epal",))
    p = max(f.pallets, key=lambda p: p.visib_fract)
    x, y, w, h = p.bbox_visib_xywh
    box = np.array([x, y, x + w, y + h], float)
    once = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=[box], T_vehicle_cam=f.T_vehicle_cam)
    assert len(once.poses) == 1
    inner = box + np.array([0.1 * w, 0, -0.1 * w, 0])          # the same pallet, a narrower box
    twice = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=[box, inner], scores=[0.9, 0.5],
                               T_vehicle_cam=f.T_vehicle_cam)
    assert len(twice.poses) == 1
    np.testing.assert_allclose(twice.poses[0].box_xyxy, box)
    (dup,) = twice.rejected
    assert dup.reason == "duplicate" and "score 0.90" in dup.detail and dup.pose is not None

