import numpy as np
import pytest

from pallet6d.runtime.geometry import make_T, quat_to_rot
from pallet6d.runtime.results import FitScore, FrameResult, PalletPose, Rejection

FIT = FitScore(0.8, 0.1, 0.72)
T = make_T(quat_to_rot(np.array([0.9, 0.1, -0.2, 0.3])), [0.1, 0.2, 3.0])


def _pose(**kw):
    args = dict(T_cam_pallet=T, confidence=0.7, detector_score=0.9, box_xyxy=[1, 2, 30, 40], n_valid_points=123,
                fit=FIT)
    args.update(kw)
    return PalletPose(**args)


def test_pose_fields_and_quaternion_round_trip():
    p = _pose()
    np.testing.assert_allclose(quat_to_rot(p.quat_wxyz), p.R, atol=1e-12)
    np.testing.assert_allclose(p.t_m, [0.1, 0.2, 3.0])
    assert p.to_dict()["n_valid_points"] == 123 and not p.T_cam_pallet.flags.writeable
    assert p.pallet_type == "" and _pose(pallet_type="gma").to_dict()["pallet_type"] == "gma"


@pytest.mark.parametrize("kw, exc, match", [
    (dict(T_cam_pallet=np.eye(3)), ValueError, r"expected shape \(4, 4\)"),
    (dict(T_cam_pallet=np.diag([1.0, 1, -1, 1])), ValueError, "rigid"),
    (dict(T_cam_pallet=np.full((4, 4), np.nan)), ValueError, "finite"),
    (dict(box_xyxy=[1, 2, 3]), ValueError, r"box_xyxy: expected shape \(4,\)"),
    (dict(n_valid_points=-1), ValueError, "n_valid_points"),
    (dict(fit=0.5), TypeError, "FitScore"),
    (dict(confidence=np.nan), ValueError, "finite"),
    (dict(pallet_type=None), TypeError, "pallet_type must be str"),
])
def test_pose_validation(kw, exc, match):
    with pytest.raises(exc, match=match):
        _pose(**kw)


def test_fit_rejection_and_frame_result():
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        FitScore(1.2, 0.0, 0.5)
    with pytest.raises(ValueError, match="reason must be one of"):
        Rejection([0, 0, 1, 1], 0.5, "bad_luck")
    assert Rejection([0, 0, 1, 1], 0.5, "time_budget").to_dict()["reason"] == "time_budget"
    r = Rejection([0, 0, 1, 1], 0.5, "poor_fit", "fit 0.1", 10, _pose())
    fr = FrameResult([_pose()], [r], {"total": 1.0}, (10, 20))
    d = fr.to_dict()
    assert d["rejected"][0]["pose"]["fit"]["score"] == 0.72 and d["image_hw"] == [10, 20]
    empty = FrameResult.empty((10, 20))
    assert empty.poses == [] and empty.rejected == [] and empty.image_hw == (10, 20)
    with pytest.raises(TypeError, match="PalletPose"):
        FrameResult([r])
