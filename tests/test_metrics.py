import numpy as np
import pytest

from pallet6d.runtime import metrics as m
from pallet6d.runtime.geometry import quat_to_rot

# A EUR-pallet-sized box outline: 1.2 x 0.8 x 0.144 m, asymmetric point layout is not needed here
# because the box itself has the 180-degree-about-z symmetry the metrics must honour.
RNG = np.random.default_rng(0)
PTS = RNG.uniform([-0.6, -0.4, -0.072], [0.6, 0.4, 0.072], size=(500, 3))
I3 = np.eye(3)
Rz180 = np.diag([-1.0, -1.0, 1.0])
SYM_EUR = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])
T_GT = np.array([0.3, -0.1, 2.5])


def test_identity_is_zero():
    assert m.add(I3, T_GT, I3, T_GT, PTS) == 0.0
    assert m.add_sym(I3, T_GT, I3, T_GT, PTS, SYM_EUR) == 0.0
    assert m.adds(I3, T_GT, I3, T_GT, PTS) == pytest.approx(0.0, abs=1e-6)
    assert m.rotation_error_deg(I3, I3) == 0.0


@pytest.mark.parametrize("d", [0.01, 0.05, 0.3])
def test_pure_translation_gives_its_length(d):
    shift = np.array([0.6, 0.0, 0.8]) * d
    assert m.add(I3, T_GT + shift, I3, T_GT, PTS) == pytest.approx(d)
    assert m.add_sym(I3, T_GT + shift, I3, T_GT, PTS, SYM_EUR) == pytest.approx(d)
    assert m.translation_error_m(T_GT + shift, T_GT) == pytest.approx(d)
    assert m.adds(I3, T_GT + shift, I3, T_GT, PTS) <= d + 1e-9


def test_180_about_z_is_large_for_add_and_zero_for_symmetric_add():
    R_gt = quat_to_rot(np.array([0.9, 0.1, -0.3, 0.2]))
    R_est = R_gt @ Rz180
    assert m.add(R_est, T_GT, R_gt, T_GT, PTS) > 0.3
    assert m.add_sym(R_est, T_GT, R_gt, T_GT, PTS, SYM_EUR) == pytest.approx(0.0, abs=1e-9)
    assert m.rotation_error_deg(R_est, R_gt) == pytest.approx(180.0)
    assert m.rotation_error_sym_deg(R_est, R_gt, SYM_EUR) == pytest.approx(0.0, abs=1e-5)


def test_adds_is_not_larger_than_add():
    R_est = quat_to_rot(np.array([1.0, 0.05, 0.0, 0.02]))
    assert m.adds(R_est, T_GT, I3, T_GT, PTS) <= m.add(R_est, T_GT, I3, T_GT, PTS)


def test_rotation_error_known_angle():
    a = np.radians(30.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    assert m.rotation_error_deg(Rz, I3) == pytest.approx(30.0)


@pytest.mark.parametrize("args,match", [
    ((np.eye(2), T_GT, I3, T_GT, PTS), "rotation"),
    ((I3, np.zeros(2), I3, T_GT, PTS), "translation"),
    ((I3, T_GT, I3, T_GT, np.zeros((0, 3))), "model points"),
    ((I3, T_GT, I3, T_GT, np.zeros((5, 2))), "model points"),
])
def test_add_rejects_bad_shapes(args, match):
    with pytest.raises(ValueError, match=match):
        m.add(*args)


def test_add_sym_rejects_bad_symmetries():
    with pytest.raises(ValueError, match="symmetries"):
        m.add_sym(I3, T_GT, I3, T_GT, PTS, np.eye(4))


def test_accuracy_curve_counts_misses_as_failures():
    errors = np.array([0.01, 0.04, 0.09, np.nan, np.inf])
    acc = m.accuracy_curve(errors, [0.02, 0.05, 0.1, 10.0])
    np.testing.assert_allclose(acc, [0.2, 0.4, 0.6, 0.6])
    np.testing.assert_allclose(m.accuracy_curve([], [0.05]), [0.0])


def test_auc():
    assert m.auc(np.zeros(10)) == pytest.approx(1.0, abs=1e-3)
    assert m.auc(np.full(10, 1.0)) == 0.0
    # uniform errors on [0, 0.1] -> accuracy rises linearly -> area 0.5
    assert m.auc(np.linspace(0, 0.1, 10001)) == pytest.approx(0.5, abs=2e-3)
    with pytest.raises(ValueError):
        m.auc(np.zeros(3), max_threshold_m=0)


def test_eur_pallet_model_turned_180_about_z():
    """The real EPAL model and its own symmetry transforms: ADD sees a large error, symmetric ADD none."""
    from pallet6d.sim.pallets import get_pallet_model

    epal = get_pallet_model("epal")
    pts = epal.surface_points(1000, seed=0)
    R_gt = quat_to_rot(np.array([0.95, 0.05, 0.3, 0.0]))
    R_est = R_gt @ Rz180
    assert m.add(R_est, T_GT, R_gt, T_GT, pts) > 0.3
    assert m.add_sym(R_est, T_GT, R_gt, T_GT, pts, epal.symmetries) == pytest.approx(0.0, abs=1e-9)
