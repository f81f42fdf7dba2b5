"""The shipped bundle: it passes `bundle check`, and its poses on a fixed generated frame stay where they were
recorded (`tests/fixtures/golden_epal_default.json`: every pose within 5 mm and 0.5 degrees, fp32 and int8)."""
import json
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime.bundle import check_bundle
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.geometry import quat_to_rot
from pallet6d.runtime.metrics import add_sym

from estimator_fixtures import scene

ROOT = Path(__file__).resolve().parents[1]
BUNDLE = ROOT / "models" / "epal-default"
GOLDEN = json.loads((Path(__file__).parent / "fixtures" / "golden_epal_default.json").read_text())


def test_shipped_bundle_passes_bundle_check():
    assert check_bundle(BUNDLE) == []


@pytest.fixture(scope="module")
def frame():
    return scene()


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_shipped_bundle_poses_match_the_recorded_ones(frame, precision):
    est = PalletEstimator.from_bundle(BUNDLE, threads=2, precision=precision)
    poses = est.estimate(frame.rgb, frame.depth_m, frame.K).poses
    golden = GOLDEN[precision]
    assert len(poses) == len(golden)
    for p, g in zip(poses, golden):
        assert p.pallet_type == g["pallet_type"]
        assert np.linalg.norm(p.t_m - np.array(g["t_m"])) < 0.005, (p.t_m, g["t_m"])
        R_g = quat_to_rot(np.array(g["quat_wxyz"]))
        cos = (np.trace(p.R.T @ R_g) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.5


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_recorded_poses_are_right(frame, precision):
    """The recorded poses are not just stable but correct: each is within 5 cm (ADD-sym) of a ground-truth pallet
    at least half visible, within 10 cm (the paper's looser threshold) of a mostly hidden one."""
    est = PalletEstimator.from_bundle(BUNDLE, threads=1, precision=precision)
    geom = est.pallet_types[0]
    for g in GOLDEN[precision]:
        R, t = quat_to_rot(np.array(g["quat_wxyz"])), np.array(g["t_m"])
        err, nearest = min((add_sym(R, t, p.T_cam_pallet[:3, :3], p.T_cam_pallet[:3, 3], geom.points_m,
                                    geom.symmetries), i) for i, p in enumerate(frame.pallets))
        assert err < (0.05 if frame.pallets[nearest].visib_fract >= 0.5 else 0.10), (err, nearest)
