import numpy as np
import pytest

from forklift_fixtures import EPAL, K, camera, pallet_pose, render
from pallet6d.runtime import kernels
from pallet6d.runtime.forklift import (ForkliftInfo, ForkliftParams, Pocket, attach_forklift, forklift_info,
                                       pocket_free_fraction, pocket_occupied_fraction, vehicle_pose)
from pallet6d.runtime.geometry import invert_T
from pallet6d.runtime.level import LevelParams
from pallet6d.runtime.results import FitScore, FrameResult, PalletPose


NO_REFINE = ForkliftParams(level=LevelParams(refine_points=0))


def _info(T_vc, T_vp, depth, params=ForkliftParams(), pockets=None):
    T_cp = invert_T(T_vc) @ T_vp
    return forklift_info(T_cp, T_vc, EPAL.size_m, EPAL.pockets_m if pockets is None else pockets, EPAL.boxes_m,
                         depth, K, params)


def test_straight_ahead_face_pockets_and_clear_depth():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    info = _info(T_vc, T_vp, render(T_vc, T_vp))
    assert info.face == "-x" and info.pick_safe and info.reason == ""
    np.testing.assert_allclose(info.face_centre_vehicle_m, [2.0, 0.0, 0.072], atol=1e-9)
    assert info.distance_m == pytest.approx(2.0) and info.lateral_offset_m == pytest.approx(0.0, abs=1e-9)
    assert info.face_yaw_deg == pytest.approx(0.0, abs=1e-9)
    left, right = info.pockets
    assert left.centre_vehicle_m[1] > 0 > right.centre_vehicle_m[1]          # left is +y seen from the forks
    np.testing.assert_allclose(left.centre_vehicle_m, [2.0, 0.18625, 0.05], atol=1e-9)   # opening 0..0.1 m up
    assert (left.width_m, left.height_m) == pytest.approx((0.2275, 0.1))
    assert all(p.state == "clear" and p.open_rays >= 8 and p.blocked_rays == 0 for p in info.pockets)


@pytest.mark.parametrize("yaw", [-20.0, 12.5, 30.0])
def test_face_yaw_is_anticlockwise_positive_and_lateral_offset_is_y(yaw):
    T_vc, T_vp = camera(), pallet_pose(2.5, yaw, lateral_m=0.3)
    info = _info(T_vc, T_vp, None)
    assert info.face_yaw_deg == pytest.approx(yaw, abs=1e-6)
    assert info.lateral_offset_m == pytest.approx(info.face_centre_vehicle_m[1])
    assert all(p.state == "hidden" for p in info.pockets) and info.reason == "pocket_hidden"


def test_the_face_towards_the_vehicle_is_chosen_whichever_way_the_pallet_lies():
    T_vc = camera()
    assert _info(T_vc, pallet_pose(2.0, 180.0), None).face == "+x"
    assert _info(T_vc, pallet_pose(2.0, 90.0), None).face == "+y"      # its +y axis points back at the forks
    assert _info(T_vc, pallet_pose(2.0, 0.0), None, pockets={"+y": EPAL.pockets_m["+y"]}).face == "+y"
    assert _info(T_vc, pallet_pose(2.0), None, pockets={}) is None


def test_an_obstacle_in_a_pocket_makes_it_blocked_and_the_pick_unsafe():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    lo, hi = EPAL.pockets_m["-x"][0]                 # left pocket of the -x face, pallet frame
    carton = np.array([[[-0.6, lo[1] + 0.02, lo[2]], [-0.45, hi[1] - 0.02, hi[2] - 0.01]]])   # 15 cm in
    info = _info(T_vc, T_vp, render(T_vc, T_vp, carton))
    assert [p.state for p in info.pockets] == ["blocked", "clear"]
    assert not info.pick_safe and info.reason == "pocket_blocked" and "left pocket blocked" in info.detail


def test_an_obstacle_sticking_out_of_a_pocket_mouth_blocks_it():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    lo, hi = EPAL.pockets_m["-x"][1]
    crate = np.array([[[-0.65, lo[1], lo[2]], [-0.3, hi[1], hi[2]]]])       # 5 cm out of the face
    info = _info(T_vc, T_vp, render(T_vc, T_vp, crate))
    assert info.pockets[1].state == "blocked" and info.reason == "pocket_blocked"


def test_a_wall_in_front_of_the_face_hides_the_pockets():
    T_vc, T_vp = camera(), pallet_pose(2.5)
    wall = np.array([[[-1.4, -0.6, -0.07], [-1.3, 0.6, 0.5]]])            # 0.7 m in front of the face
    info = _info(T_vc, T_vp, render(T_vc, T_vp, wall))
    assert all(p.state == "hidden" for p in info.pockets) and info.reason == "pocket_hidden"


def test_an_object_past_the_mouth_of_an_obliquely_seen_pocket_leaves_it_hidden_not_clear():
    # seen 25 degrees off, the left pocket's own block hides its far half: a carton there meets one ray in twelve
    T_vc, T_vp = camera(), pallet_pose(1.5, 25.0)
    lo, hi = EPAL.pockets_m["-x"][0]
    carton = np.array([[[-0.4, hi[1] - 0.12, lo[2]], [-0.15, hi[1], hi[2] - 0.02]]])    # 0.2-0.45 m in
    left = _info(T_vc, T_vp, render(T_vc, T_vp, carton)).pockets[0]
    assert left.blocked_rays <= ForkliftParams().max_blocked_fraction * (left.open_rays + left.blocked_rays)
    assert left.open_rays >= ForkliftParams().min_rays                      # the rays alone would call it clear
    assert left.state == "hidden" and left.free_fraction < ForkliftParams().min_free_fraction
    info = _info(T_vc, T_vp, render(T_vc, T_vp, carton), ForkliftParams(min_free_fraction=0.0))
    assert info.pockets[0].state == "clear"                                 # what the volume check prevents


def test_the_share_of_the_forks_path_seen_free_grows_as_the_face_turns_square():
    T_vc = camera()
    free = [_info(T_vc, pallet_pose(3.0, yaw), render(T_vc, pallet_pose(3.0, yaw))).pockets[1].free_fraction
            for yaw in (30.0, 20.0, 0.0)]
    assert 0.0 < free[0] < free[1] < free[2] <= 1.0
    info = _info(T_vc, pallet_pose(3.0), render(T_vc, pallet_pose(3.0)))
    assert info.pick_safe and all(p.free_fraction >= ForkliftParams().min_free_fraction for p in info.pockets)


def test_an_object_seen_past_the_middle_block_through_a_sliver_of_the_opening_blocks_the_pocket():
    # the pallet 0.7 m to the right: the right pocket's inner half, 0.2-0.35 m in, lies behind the middle block
    T_vc, T_vp = camera(), pallet_pose(3.0, lateral_m=-0.7)
    lo, hi = EPAL.pockets_m["-x"][1]
    carton = np.array([[[-0.4, hi[1] - 0.5 * (hi[1] - lo[1]), lo[2]], [-0.25, hi[1], lo[2] + 0.07]]])
    depth = render(T_vc, T_vp, carton)
    rays_only = _info(T_vc, T_vp, depth, ForkliftParams(max_occupied_fraction=1.0)).pockets[1]
    assert rays_only.state == "clear" and rays_only.free_fraction >= ForkliftParams().min_free_fraction
    info = _info(T_vc, T_vp, depth)
    right = info.pockets[1]
    assert right.state == "blocked" and right.occupied_fraction > ForkliftParams().max_occupied_fraction
    assert not info.pick_safe and "right pocket blocked (depth shows a surface in" in info.detail
    assert info.pockets[0].state == "clear" and info.pockets[0].occupied_fraction == 0.0


def test_surfaces_in_front_of_the_face_are_not_in_the_pocket():
    # the forklift's own fork tips, 0.3-0.5 m short of the face, in front of both pockets
    T_vc, T_vp = camera(), pallet_pose(2.0)
    T_cp = invert_T(T_vc) @ T_vp
    tips = np.array([[[-1.1, -0.35, -0.072], [-0.9, 0.35, -0.03]]])
    args = (T_cp, EPAL.boxes_m, EPAL.pockets_m["-x"], EPAL.size_m, "-x", render(T_vc, T_vp, tips), K)
    np.testing.assert_array_equal(pocket_occupied_fraction(*args), [0.0, 0.0])


@pytest.mark.parametrize("fill", [0.0, np.nan])
def test_pocket_occupied_fraction_is_zero_without_depth_or_a_volume_to_check(fill):
    T_vc, T_vp = camera(), pallet_pose(2.0)
    T_cp = invert_T(T_vc) @ T_vp
    args = (T_cp, EPAL.boxes_m, EPAL.pockets_m["-x"], EPAL.size_m, "-x", np.full((240, 424), fill, np.float32), K)
    np.testing.assert_array_equal(pocket_occupied_fraction(*args), [0.0, 0.0])
    np.testing.assert_array_equal(pocket_occupied_fraction(*args, ForkliftParams(clear_depth_m=0.0)), [0.0, 0.0])


@pytest.mark.parametrize("fill", [0.0, np.nan])
def test_pocket_free_fraction_is_zero_without_depth_and_one_without_a_volume_to_check(fill):
    T_vc, T_vp = camera(), pallet_pose(2.0)
    T_cp = invert_T(T_vc) @ T_vp
    depth = np.full((240, 424), fill, np.float32)
    args = (T_cp, EPAL.boxes_m, EPAL.pockets_m["-x"], EPAL.size_m, "-x", depth, K)
    np.testing.assert_array_equal(pocket_free_fraction(*args), [0.0, 0.0])
    np.testing.assert_array_equal(pocket_free_fraction(*args, ForkliftParams(min_open_depth_m=0.4)), [1.0, 1.0])
    with pytest.raises(ValueError, match="depth_m must be"):
        pocket_free_fraction(*args[:5], depth[0], K)


@pytest.mark.parametrize("kwargs,match", [
    (dict(min_free_fraction=1.5), "min_free_fraction"), (dict(min_free_fraction=-0.1), "min_free_fraction"),
    (dict(slice_m=0.0), "slice_m"), (dict(grid=1), "grid"), (dict(max_blocked_fraction=2.0), "max_blocked"),
    (dict(max_occupied_fraction=-0.01), "max_occupied_fraction"),
])
def test_forklift_params_are_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ForkliftParams(**kwargs)


def test_a_face_seen_too_obliquely_is_not_safe():
    T_vc, T_vp = camera(), pallet_pose(2.0, 25.0)
    depth = render(T_vc, T_vp)
    assert _info(T_vc, T_vp, depth, ForkliftParams(max_view_angle_deg=10.0)).reason == "face_oblique"


def test_depth_that_is_all_missing_or_nan_hides_the_pockets():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    depth = np.full((240, 424), np.nan, np.float32)
    assert _info(T_vc, T_vp, depth).reason == "pocket_hidden"
    assert _info(T_vc, T_vp, np.zeros((240, 424), np.float32)).reason == "pocket_hidden"


@pytest.mark.parametrize("kwargs,match", [
    (dict(pick_safe=True, reason="pocket_blocked"), "empty exactly when"),
    (dict(pick_safe=False, reason=""), "empty exactly when"),
    (dict(pick_safe=False, reason="no_idea"), "must be one of"),
    (dict(face="front"), "face"),
    (dict(face_centre_vehicle_m=[1.0, np.nan, 0.0]), "face_centre_vehicle_m"),
])
def test_forklift_info_validates(kwargs, match):
    pk = (Pocket("left", [2, 0.2, 0.07], 0.2, 0.1, "clear"), Pocket("right", [2, -0.2, 0.07], 0.2, 0.1, "clear"))
    base = dict(face="-x", face_centre_vehicle_m=[2, 0, 0.07], face_normal_vehicle=[-1, 0, 0], face_yaw_deg=0,
                lateral_offset_m=0, distance_m=2, view_angle_deg=5, pockets=pk, pick_safe=True, reason="")
    with pytest.raises(ValueError, match=match):
        ForkliftInfo(**{**base, **kwargs})
    with pytest.raises(ValueError, match="state"):
        Pocket("left", [0, 0, 0], 0.2, 0.1, "open")
    with pytest.raises(ValueError, match="free_fraction"):
        Pocket("left", [0, 0, 0], 0.2, 0.1, "clear", 10, 0, 1.5)
    with pytest.raises(ValueError, match="occupied_fraction"):
        Pocket("left", [0, 0, 0], 0.2, 0.1, "clear", 10, 0, 0.5, -0.1)


def test_attach_forklift_adds_the_vehicle_pose_and_outputs_to_every_pose():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    T_cp = invert_T(T_vc) @ T_vp
    pose = PalletPose(T_cp, 0.9, 0.8, [100, 100, 200, 160], 500, FitScore(0.9, 0.0, 0.9), class_name="pallet")
    other = PalletPose(T_cp, 0.9, 0.8, [100, 100, 200, 160], 500, FitScore(0.9, 0.0, 0.9), class_name="drum")
    result = attach_forklift(FrameResult([pose, other]), T_vc, {"pallet": EPAL}, render(T_vc, T_vp), K, NO_REFINE)
    a, b = result.poses
    np.testing.assert_allclose(a.T_vehicle_pallet, T_vp, atol=1e-9)
    assert a.forklift.pick_safe and b.forklift is None and b.T_vehicle_pallet is not None
    d = a.to_dict()
    assert d["forklift"]["pick_safe"] and len(d["forklift"]["pockets"]) == 2 and "t_vehicle_m" in d
    assert "t_vehicle_m" not in pose.to_dict() and "forklift" not in pose.to_dict()


def _tilted(T_vp, deg, axis=(1.0, 0.0, 0.0)):
    """T_vp turned by `deg` about `axis` (vehicle frame) through its own origin."""
    import cv2

    R, _ = cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float))
    out = T_vp.copy()
    out[:3, :3] = R @ T_vp[:3, :3]
    return out


def test_vehicle_pose_levels_a_slightly_tilted_pallet_and_sets_it_on_the_floor():
    T_vc, T_vp = camera(), pallet_pose(2.0, 20.0, lateral_m=0.3)
    est = _tilted(T_vp, 3.0, (1.0, 1.0, 0.0))
    est[2, 3] += 0.025                                     # 2.5 cm above the floor
    T_cp = invert_T(T_vc) @ est
    np.testing.assert_allclose(vehicle_pose(T_cp, T_vc, EPAL.size_m), T_vp, atol=0.02)
    levelled = vehicle_pose(T_cp, T_vc, EPAL.size_m)
    np.testing.assert_allclose(levelled[:3, 2], [0, 0, 1], atol=1e-12)
    assert levelled[2, 3] == pytest.approx(EPAL.size_m[2] / 2)
    assert np.degrees(np.arctan2(levelled[1, 0], levelled[0, 0])) == pytest.approx(20.0, abs=0.2)
    np.testing.assert_allclose(levelled[:2, 3], est[:2, 3], atol=1e-12)          # the centre stays (but for z)
    exact = invert_T(T_vc) @ T_vp
    np.testing.assert_allclose(vehicle_pose(exact, T_vc, EPAL.size_m), T_vp, atol=1e-12)


def test_vehicle_pose_leaves_high_or_steeply_tilted_pallets_and_can_be_turned_off():
    T_vc = camera()
    on_rack = pallet_pose(2.0)
    on_rack[2, 3] += 1.2
    out = vehicle_pose(invert_T(T_vc) @ on_rack, T_vc, EPAL.size_m)
    assert out[2, 3] == pytest.approx(on_rack[2, 3])                              # levelled, not moved down
    steep = _tilted(pallet_pose(2.0), 30.0)                   # beyond the structure check's 25 degrees: left as is
    np.testing.assert_allclose(vehicle_pose(invert_T(T_vc) @ steep, T_vc, EPAL.size_m), steep, atol=1e-12)
    within = vehicle_pose(invert_T(T_vc) @ _tilted(pallet_pose(2.0), 20.0), T_vc, EPAL.size_m)
    np.testing.assert_allclose(within[:3, 2], [0, 0, 1], atol=1e-12)           # a pose the check accepts is levelled
    slight = _tilted(pallet_pose(2.0), 2.0)
    off = ForkliftParams(level=LevelParams(max_tilt_deg=0, floor_snap_m=0))
    np.testing.assert_allclose(vehicle_pose(invert_T(T_vc) @ slight, T_vc, EPAL.size_m, off), slight, atol=1e-12)
    np.testing.assert_allclose(vehicle_pose(invert_T(T_vc) @ slight, T_vc, EPAL.size_m, ForkliftParams(level=None)),
                               slight, atol=1e-12)
    for kwargs, match in ((dict(max_tilt_deg=95), "max_tilt_deg"), (dict(floor_snap_m=-0.01), "floor_snap_m"),
                          (dict(refine_points=-1), "refine_points"), (dict(refine_iterations=0), "refine_iterations")):
        with pytest.raises(ValueError, match=match):
            LevelParams(**kwargs)


def test_attach_forklift_reports_the_levelled_pose_its_pockets_come_from():
    T_vc, T_vp = camera(), pallet_pose(2.0)
    T_cp = invert_T(T_vc) @ _tilted(T_vp, 2.0, (0.0, 1.0, 0.0))
    pose = PalletPose(T_cp, 0.9, 0.8, [100, 100, 200, 160], 500, FitScore(0.9, 0.0, 0.9), class_name="pallet")
    (a,) = attach_forklift(FrameResult([pose]), T_vc, {"pallet": EPAL}, render(T_vc, T_vp), K, NO_REFINE).poses
    np.testing.assert_allclose(a.T_vehicle_pallet, T_vp, atol=1e-9)
    np.testing.assert_allclose(a.forklift.pockets[0].centre_vehicle_m, [2.0, 0.18625, 0.05], atol=1e-9)
    np.testing.assert_allclose(a.T_cam_pallet, T_cp)                               # the camera-frame pose as estimated


def _box_of(T_vc, T_vp):
    """The pallet's image box (pixels) under `camera()`'s intrinsics."""
    corners = np.array(np.meshgrid(*[[-v / 2, v / 2] for v in EPAL.size_m])).reshape(3, -1).T
    T_cp = invert_T(T_vc) @ T_vp
    c = corners @ T_cp[:3, :3].T + T_cp[:3, 3]
    uv = c[:, :2] / c[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return np.concatenate([uv.min(0), uv.max(0)])


@pytest.mark.parametrize("yaw_err_deg, shift_m", [(1.5, (0.015, -0.01)), (-1.0, (-0.01, 0.02))])
def test_the_levelled_pose_is_refined_on_the_depth_in_yaw_and_position(yaw_err_deg, shift_m):
    T_vc, T_vp = camera(), pallet_pose(2.0, 10.0, lateral_m=0.2)
    est = _tilted(T_vp, yaw_err_deg, (0.0, 0.0, 1.0))
    est = _tilted(est, 1.5, (1.0, 0.0, 0.0))
    est[:3, 3] += [shift_m[0], shift_m[1], 0.01]
    T_cp, depth, box = invert_T(T_vc) @ est, render(T_vc, T_vp), _box_of(T_vc, T_vp)
    out = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, depth, K, box)
    np.testing.assert_allclose(out[:3, 2], [0, 0, 1], atol=1e-12)
    assert out[2, 3] == pytest.approx(EPAL.size_m[2] / 2)
    assert np.linalg.norm(out[:2, 3] - T_vp[:2, 3]) < 0.01
    assert np.degrees(np.arccos(np.clip(out[:3, 0] @ T_vp[:3, 0], -1, 1))) < 0.5
    levelled_only = vehicle_pose(T_cp, T_vc, EPAL.size_m, NO_REFINE, EPAL.boxes_m, depth, K, box)
    assert np.linalg.norm(levelled_only[:2, 3] - T_vp[:2, 3]) > 0.015            # the refinement did the work
    no_depth = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, np.zeros_like(depth), K, box)
    np.testing.assert_allclose(no_depth, levelled_only, atol=1e-12)


@pytest.mark.parametrize("yaw_err_deg, shift_m", [(90.0, (0.0, 0.0)), (-60.0, (0.1, 0.05)), (135.0, (-0.15, 0.0))])
def test_the_levelled_search_finds_a_pose_whose_yaw_is_far_off(yaw_err_deg, shift_m):
    # the network's yaw 60-135 degrees off, outside ICP's reach: the search over turns and slides finds the pallet
    T_vc, T_vp = camera(), pallet_pose(2.5, 10.0, lateral_m=0.2)
    est = _tilted(T_vp, yaw_err_deg, (0.0, 0.0, 1.0))
    est[:3, 3] += [shift_m[0], shift_m[1], 0.0]
    T_cp, depth, box = invert_T(T_vc) @ _tilted(est, 1.0), render(T_vc, T_vp), _box_of(T_vc, T_vp)

    def yaw_err(T):                                     # the EPAL looks the same turned by 180 degrees
        return np.degrees(np.arccos(np.clip(abs(T[:3, 0] @ T_vp[:3, 0]), -1, 1)))

    out = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, depth, K, box)
    assert yaw_err(out) < 0.5 and np.linalg.norm(out[:2, 3] - T_vp[:2, 3]) < 0.01
    no_search = ForkliftParams(level=LevelParams(search_yaw_step_deg=0))
    alone = vehicle_pose(T_cp, T_vc, EPAL.size_m, no_search, EPAL.boxes_m, depth, K, box)
    assert yaw_err(alone) > 10.0                                                 # ICP alone stays far off


@pytest.mark.parametrize("yaw_err_deg, shift_m", [(3.0, (0.03, -0.02)), (-2.0, (-0.04, 0.0)), (0.0, (0.0, 0.035))])
def test_the_climb_brings_a_pose_a_few_degrees_and_centimetres_off_onto_the_pallet(yaw_err_deg, shift_m):
    # a start where ICP may stop on the pallet's repeated boards: the soft ray score's climb ends on the pallet
    from pallet6d.runtime.level import _climb_one, climb_poses
    from pallet6d.runtime.refine import box_points

    T_vc, T_vp = camera(), pallet_pose(1.8, 15.0, lateral_m=0.1)
    depth, box = render(T_vc, T_vp), _box_of(T_vc, T_vp)
    est = _tilted(T_vp, yaw_err_deg, (0.0, 0.0, 1.0))
    est[:3, 3] += [shift_m[0], shift_m[1], 0.0]
    pts = box_points(depth, K, box, 600, (0.1, 20.0))
    out = T_vc @ _climb_one(invert_T(T_vc) @ est, pts, EPAL.boxes_m, LevelParams())
    err_deg = np.degrees(np.arccos(np.clip(abs(out[:3, 0] @ T_vp[:3, 0]), -1, 1)))
    assert err_deg < 0.3 and np.linalg.norm(out[:2, 3] - T_vp[:2, 3]) < 0.006
    np.testing.assert_allclose(out[2], T_vp[2], atol=1e-9)                      # level, on the floor: untouched
    tethered = LevelParams(climb_max_shift_m=0.01, climb_max_turn_deg=0.5)     # never far from the judged pose
    near = _climb_one(invert_T(T_vc) @ est, pts, EPAL.boxes_m, tethered)
    assert np.linalg.norm(near[:3, 3] - (invert_T(T_vc) @ est)[:3, 3]) <= 0.01 + 1e-9
    assert np.degrees(np.arccos(np.clip((np.trace(near[:3, :3].T @ (invert_T(T_vc) @ est)[:3, :3]) - 1) / 2,
                                        -1, 1))) <= 0.5 + 1e-6
    T_est = invert_T(T_vc) @ est
    climbed = climb_poses(T_est[None], [pts], [EPAL.boxes_m])[0]
    np.testing.assert_allclose(climbed, _climb_one(T_est, pts, EPAL.boxes_m, LevelParams()))
    beyond = LevelParams(climb_max_range_m=1.0)                                 # farther: depth noise rules there
    np.testing.assert_allclose(climb_poses(T_est[None], [pts], [EPAL.boxes_m], beyond)[0], T_est)
    stuck = LevelParams(climb_max_moves=0)                                     # no move allowed: the pose stays
    np.testing.assert_allclose(_climb_one(invert_T(T_vc) @ est, pts, EPAL.boxes_m, stuck), invert_T(T_vc) @ est)
    np.testing.assert_allclose(_climb_one(invert_T(T_vc) @ est, np.zeros((0, 3)), EPAL.boxes_m, LevelParams()),
                               invert_T(T_vc) @ est)                            # no points: nothing to climb


@pytest.mark.parametrize("height_err_m", [0.022, -0.015])
def test_a_pallet_off_the_floor_climbs_to_its_height(height_err_m):
    # on a rack beam 0.5 m up nothing holds the pallet's height: lifted, the climb finds it; not lifted, it stays
    from pallet6d.runtime.level import climb_poses
    from pallet6d.runtime.refine import box_points

    T_vc, T_vp = camera(), pallet_pose(2.0, 10.0)
    T_vp[2, 3] += 0.5
    depth, box = render(T_vc, T_vp, floor=False), _box_of(T_vc, T_vp)
    est = T_vp.copy()
    est[2, 3] += height_err_m
    pts = box_points(depth, K, box, 600, (0.1, 20.0))
    T_est = invert_T(T_vc) @ est
    lifted = T_vc @ climb_poses(T_est[None], [pts], [EPAL.boxes_m], lift=np.array([True]))[0]
    assert abs(lifted[2, 3] - T_vp[2, 3]) < 0.004 and np.linalg.norm(lifted[:2, 3] - T_vp[:2, 3]) < 0.006
    held = T_vc @ climb_poses(T_est[None], [pts], [EPAL.boxes_m])[0]
    assert held[2, 3] == pytest.approx(est[2, 3], abs=1e-9)


@pytest.mark.parametrize("kwargs, match", [({"search_yaw_step_deg": -1}, "search_yaw_step_deg"),
                                           ({"search_yaw_step_deg": 200}, "search_yaw_step_deg"),
                                           ({"search_shifts_m": ()}, "search_shifts_m"),
                                           ({"search_shifts_m": (0.0, 2.0)}, "search_shifts_m"),
                                           ({"search_keep": 0}, "search_keep"),
                                           ({"search_window_m": 0.0}, "search_window_m"),
                                           ({"climb_step_deg": -1.0}, "climb_step_deg"),
                                           ({"climb_min_step_deg": 0.0}, "climb_min_step_deg"),
                                           ({"climb_window_m": 0.0}, "climb_window_m"),
                                           ({"climb_max_moves": -1}, "climb_max_moves"),
                                           ({"climb_max_turn_deg": -1.0}, "climb_max_turn_deg"),
                                           ({"climb_max_shift_m": -0.1}, "climb_max_shift_m"),
                                           ({"climb_max_range_m": -1.0}, "climb_max_range_m"),
                                           ({"climb_points": -1}, "climb_points")])
def test_level_params_search_is_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LevelParams(**kwargs)


def test_level_poses_refines_a_frames_poses_together_as_one_by_one():
    from pallet6d.runtime.level import level_poses

    T_vc = camera()
    on_floor, on_rack = pallet_pose(2.0, 10.0, lateral_m=0.6), pallet_pose(2.4, -5.0, lateral_m=-0.7)
    on_rack[2, 3] += 0.5
    depth = np.minimum(render(T_vc, on_floor), np.where(render(T_vc, on_rack, floor=False) > 0,
                                                         render(T_vc, on_rack, floor=False), np.inf))
    depth[~np.isfinite(depth)] = 0
    est = [_tilted(T, 1.5, (1.0, 0.0, 0.0)) for T in (on_floor, on_rack)]
    for T in est:
        T[:3, 3] += [0.015, -0.01, 0.01]
    T_cp = np.stack([invert_T(T_vc) @ T for T in est])
    boxes = np.stack([_box_of(T_vc, T) for T in (on_floor, on_rack)])
    both = level_poses(T_cp, T_vc, [EPAL.size_m[2]] * 2, LevelParams(), [EPAL.boxes_m] * 2, depth, K, boxes)
    for i in range(2):
        one = level_poses(T_cp[i:i + 1], T_vc, [EPAL.size_m[2]], LevelParams(), [EPAL.boxes_m], depth, K,
                          boxes[i:i + 1])
        np.testing.assert_allclose(both[i], one[0], atol=1e-9)
    if kernels.available():                    # the ICP on the boxes' grid: fewer boxes per point, the same poses
        grid = kernels.box_grid(EPAL.boxes_m)
        gridded = level_poses(T_cp, T_vc, [EPAL.size_m[2]] * 2, LevelParams(), [EPAL.boxes_m] * 2, depth, K, boxes,
                              grids=[grid, grid])
        np.testing.assert_array_equal(gridded, both)
    assert both[0, 2, 3] == pytest.approx(EPAL.size_m[2] / 2)                     # the floor one is set on it
    assert abs(both[1, 2, 3] - on_rack[2, 3]) < 0.02                              # the rack one keeps its height
    np.testing.assert_allclose(both[:, 2, 2], 1.0, atol=1e-12)


def test_points_handed_to_the_levelling_are_thinned_to_its_refine_points():
    # the caller's points (the estimator's box points) obey LevelParams.refine_points as the levelling's own do
    from pallet6d.runtime.level import level_poses
    from pallet6d.runtime.refine import box_points

    T_vc, T_vp = camera(), pallet_pose(2.2, 8.0, lateral_m=0.2)
    depth = render(T_vc, T_vp)
    T_cp = invert_T(T_vc) @ _tilted(T_vp, 1.5)
    pts = box_points(depth, K, _box_of(T_vc, T_vp), 100000, (0.1, 20.0))
    n = 200
    assert len(pts) > n
    params = LevelParams(refine_points=n)
    given = level_poses(T_cp[None], T_vc, [EPAL.size_m[2]], params, [EPAL.boxes_m], pts_cam=[pts])
    even = pts[np.linspace(0, len(pts) - 1, n).round().astype(np.int64)]
    thinned = level_poses(T_cp[None], T_vc, [EPAL.size_m[2]], params, [EPAL.boxes_m], pts_cam=[even])
    np.testing.assert_array_equal(given, thinned)
    every = level_poses(T_cp[None], T_vc, [EPAL.size_m[2]], LevelParams(refine_points=len(pts)), [EPAL.boxes_m],
                        pts_cam=[pts])
    assert not np.array_equal(given, every)


def test_a_pose_the_estimator_levelled_is_not_refined_again():
    T_vc, T_vp = camera(), pallet_pose(2.0, 5.0)
    off = T_vp.copy()
    off[:3, 3] += [0.015, -0.01, 0.0]                       # level and on the floor, but 1.8 cm off: refining moves it
    T_cp = invert_T(T_vc) @ off
    box, depth = _box_of(T_vc, T_vp), render(T_vc, T_vp)
    pose = PalletPose(T_cp, 0.9, 0.8, box, 500, FitScore(0.9, 0.0, 0.9), class_name="pallet")
    (a,) = attach_forklift(FrameResult([pose]), T_vc, {"pallet": EPAL}, depth, K).poses
    np.testing.assert_allclose(a.T_vehicle_pallet, off, atol=1e-9)
    tilted = invert_T(T_vc) @ _tilted(off, 1.0)
    moved = vehicle_pose(tilted, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, depth, K, box)
    assert np.linalg.norm(moved[:2, 3] - off[:2, 3]) > 0.005                 # an estimate that was not levelled is


@pytest.mark.parametrize("distance_m, sigma_m, seed", [(3.0, 0.03, 0), (4.0, 0.05, 1)])
def test_the_levelled_pose_is_not_pulled_towards_the_camera_by_depth_noise(distance_m, sigma_m, seed):
    # zero-mean depth noise of a stereo camera: closest-point ICP alone lands 2-3 cm nearer than the pallet; moved
    # along the rays by the points' ray residuals, the pose stays within about a centimetre
    T_vc, T_vp = camera(), pallet_pose(distance_m, 10.0, lateral_m=0.2)
    depth = render(T_vc, T_vp)
    noise = sigma_m * np.random.default_rng(seed).standard_normal(depth.shape)
    noisy = np.where(depth > 0, depth + noise, 0.0).astype(np.float32)
    T_cp, box = invert_T(T_vc) @ _tilted(T_vp, 1.0), _box_of(T_vc, T_vp)   # tilted: not level yet, so refined
    err = {}
    for window_m in (0.0, LevelParams().ray_window_m):
        # the ICP from the pose alone (no search, no climb): the search's choice among its landings and the climb
        # would blur the bias
        level = LevelParams(ray_window_m=window_m, search_yaw_step_deg=0, climb_step_deg=0)
        out = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(level=level), EPAL.boxes_m, noisy, K, box)
        err[window_m] = out[:2, 3] - T_vp[:2, 3]                  # x: along the forks, towards the pallet
    assert err[0.0][0] < -0.015
    assert np.all(np.abs(err[LevelParams().ray_window_m]) < 0.012)
    exact = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, depth, K, box)
    assert np.linalg.norm(exact[:2, 3] - T_vp[:2, 3]) < 0.002
    searched = vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(), EPAL.boxes_m, noisy, K, box)
    assert np.all(np.abs(searched[:2, 3] - T_vp[:2, 3]) < 0.012)                # the defaults, search included


@pytest.mark.parametrize("window_m", [-0.1, 1.5, float("nan")])
def test_level_params_ray_window_is_validated(window_m):
    with pytest.raises(ValueError, match="ray_window_m"):
        LevelParams(ray_window_m=window_m)


def test_a_pallet_seen_steeply_from_above_is_not_moved_along_the_rays():
    # rays 60 degrees down see the deck, whose depth a horizontal move cannot explain: the pose keeps the ICP's place
    T_vc, T_vp = camera(height_m=2.5, pitch_deg=60.0), pallet_pose(0.8, 0.0)
    depth = render(T_vc, T_vp)
    noisy = np.where(depth > 0, depth + 0.03 * np.random.default_rng(0).standard_normal(depth.shape), 0.0)
    T_cp, box = invert_T(T_vc) @ _tilted(T_vp, 1.0), np.array([0.0, 0.0, depth.shape[1] - 1, depth.shape[0] - 1])
    out = [vehicle_pose(T_cp, T_vc, EPAL.size_m, ForkliftParams(level=LevelParams(ray_window_m=w)), EPAL.boxes_m,
                        noisy.astype(np.float32), K, box) for w in (0.0, 0.2)]
    np.testing.assert_allclose(out[1], out[0], atol=1e-12)


def _along_rays_one_by_one(T, pts, n_pts, boxes_m, window_m, T_vc, on_floor):
    """Step 4 of `level`'s docstring written pose by pose: the specification of the batched `_along_rays`."""
    from pallet6d.runtime.structure import cast_rays_boxes

    out = T.copy()
    up = T_vc[2, :3]
    for i in range(len(T)):
        p = pts[i, :n_pts[i]]
        R_pc = T[i, :3, :3].T
        s = cast_rays_boxes((-R_pc @ T[i, :3, 3])[None], (p @ R_pc.T)[None], boxes_m)[0][0]
        rng_m = np.linalg.norm(p, axis=1)
        with np.errstate(invalid="ignore"):
            res = (1.0 - s) * rng_m
        ok = np.isfinite(res) & (np.abs(res) < window_m)
        if ok.sum() < 30:
            continue
        ray = (p[ok] / rng_m[ok, None]).mean(0)
        ray /= np.linalg.norm(ray)
        move = np.median(res[ok]) * ray
        if on_floor[i]:
            flat = ray - (ray @ up) * up
            if flat @ flat < 0.5:
                continue
            move = np.median(res[ok]) * flat / (flat @ flat)
        out[i, :3, 3] += move
    return out


@pytest.mark.parametrize("compiled", [True, False])
def test_the_move_along_the_rays_is_the_same_for_every_pose_of_a_batch(compiled):
    # poses on the floor and off it, seen level and steeply from above, with too few points near the surface to move,
    # an odd and an even number of points within the window (the median of an even count is the mean of two)
    from pallet6d.runtime.level import _along_rays

    rng = np.random.default_rng(5)
    T_vc = camera(height_m=1.5, pitch_deg=20.0)
    T_vps = [pallet_pose(2.0), pallet_pose(3.0, 20.0, lateral_m=0.3), pallet_pose(2.5, -10.0), pallet_pose(0.6)]
    T = np.stack([invert_T(T_vc) @ T_vp for T_vp in T_vps])          # the last seen about 65 degrees down
    pts, n_pts = np.zeros((4, 301, 3)), np.array([301, 300, 20, 250])
    for i in range(4):
        surface = EPAL.surface_points(n_pts[i], seed=i) @ T[i, :3, :3].T + T[i, :3, 3]
        pts[i, :n_pts[i]] = surface + rng.normal(0.0, 0.02, surface.shape)
    T_moved = T @ _turn_z(3.0, 0.04)
    for on_floor in (np.zeros(4, bool), np.array([True, False, True, True])):
        got = _along_rays(T_moved, pts, n_pts, EPAL.boxes_m, 0.2, T_vc, on_floor, compiled=compiled)
        want = _along_rays_one_by_one(T_moved, pts, n_pts, EPAL.boxes_m, 0.2, T_vc, on_floor)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        if compiled:                                   # 12 poses: several chunks of 4 for the kernel's threads
            many = _along_rays(np.concatenate([T_moved] * 3), np.concatenate([pts] * 3), np.tile(n_pts, 3),
                               EPAL.boxes_m, 0.2, T_vc, np.tile(on_floor, 3), threads=3)
            np.testing.assert_allclose(many, np.concatenate([want] * 3), rtol=0, atol=1e-12)
        assert np.allclose(got[2], T_moved[2])                         # 20 points: too few to move
        assert not np.allclose(got[0], T_moved[0])
        assert np.allclose(got[3], T_moved[3]) == on_floor[3]          # steeply from above: not moved on the floor


def _turn_z(deg: float, shift_m: float) -> np.ndarray:
    a = np.deg2rad(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[0, 3] = shift_m
    return T
