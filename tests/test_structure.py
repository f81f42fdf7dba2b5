"""The structure check on depth rendered from the pallet's own boxes: true poses pass, mismatches do not."""
from dataclasses import replace

import numpy as np
import pytest

from pallet6d.runtime.geometry import make_T, quat_to_rot
from pallet6d.runtime.structure import (StructureParams, box_metric_size, cast_rays_boxes, edge_agreement,
                                        structure_agreement, structure_check)
from pallet6d.sim.pallets import get_pallet_model

EPAL = get_pallet_model("epal")
H, W = 240, 320
K = np.array([[260.0, 0, (W - 1) / 2], [0, 260.0, (H - 1) / 2], [0, 0, 1]])
BACK_WALL_M = 7.0


def _rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg) / 2
    return quat_to_rot(np.array([np.cos(a), np.sin(a), 0, 0]))


# the pallet 3 m ahead, its -x face (the 800 mm side with fork pockets) towards the camera, seen a little from above:
# pallet z (up) = camera -y, pallet x (length) = camera z
R_CAM_PALLET = _rot_x(-10.0) @ np.array([[0.0, 1, 0], [0, 0, -1], [1, 0, 0]])
T_TRUE = make_T(R_CAM_PALLET, np.array([0.1, 0.45, 3.0]))


def _render(T_cam_pallet: np.ndarray, K_: np.ndarray = K) -> np.ndarray:
    """Ideal depth of the posed pallet in front of a flat back wall, metres."""
    v, u = np.mgrid[0:H, 0:W]
    d_cam = np.stack([(u - K_[0, 2]) / K_[0, 0], (v - K_[1, 2]) / K_[1, 1], np.ones((H, W))], -1).reshape(1, -1, 3)
    R, t = T_cam_pallet[:3, :3], T_cam_pallet[:3, 3]
    t_box, _ = cast_rays_boxes((-R.T @ t)[None], d_cam @ R, EPAL.boxes_m)
    return np.minimum(t_box[0], BACK_WALL_M).reshape(H, W).astype(np.float32)


def _box(T: np.ndarray) -> np.ndarray:
    """The posed pallet's visible box in the image, as a detector would give it."""
    depth = _render(T)
    v, u = np.nonzero(depth < BACK_WALL_M)
    return np.array([[u.min(), v.min(), u.max() + 1, v.max() + 1]], float)


DEPTH = _render(T_TRUE)
BOX = _box(T_TRUE)


def _colour(depth: np.ndarray, seed: int = 0) -> np.ndarray:
    """An image of a depth rendering: wood where the pallet is, a grey wall behind, shading by range, sensor noise."""
    rng = np.random.default_rng(seed)
    wood = depth < BACK_WALL_M
    rgb = np.where(wood[..., None], np.array([170.0, 125.0, 80.0]), np.array([90.0, 95.0, 105.0]))
    rgb = rgb * (1.0 - 0.03 * np.minimum(depth, BACK_WALL_M))[..., None] + rng.normal(0, 3.0, rgb.shape)
    return np.clip(rgb, 0, 255).astype(np.uint8)


RGB = _colour(DEPTH)


def _check(T=T_TRUE, depth=DEPTH, K_=K, box=BOX, **kw):
    return structure_check(T[None], EPAL.boxes_m, depth, K_, box, **kw)[0]


def test_true_pose_passes_with_open_pockets():
    s = _check()
    assert s.ok, s
    assert s.agreement > 0.95 and s.open_fraction > 0.9
    assert s.open > 20 and s.solid > 100


def _render_boxes(boxes_m: np.ndarray, T_cam_pallet: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(1, -1, 3)
    R, t = T_cam_pallet[:3, :3], T_cam_pallet[:3, 3]
    t_box, _ = cast_rays_boxes((-R.T @ t)[None], d_cam @ R, boxes_m)
    return np.minimum(t_box[0], BACK_WALL_M).reshape(H, W).astype(np.float32)


def test_a_carton_where_a_pallet_seen_from_below_should_be_closes_its_pockets_mouths():
    # seen 8 degrees from below, the rays that enter the pockets meet the blocks and bottom boards inside: a carton
    # face where the pallet's front is shows no pocket, a pallet shows open mouths
    T_below = make_T(_rot_x(8.0) @ np.array([[0.0, 1, 0], [0, 0, -1], [1, 0, 0]]), np.array([0.1, -0.45, 3.0]))
    lo, hi = EPAL.boxes_m[:, 0].min(0), EPAL.boxes_m[:, 1].max(0)
    carton = _render_boxes(np.array([[lo, hi]]), T_below)           # a solid block the pallet's size
    pallet = _render_boxes(EPAL.boxes_m, T_below)
    v, u = np.nonzero(pallet < BACK_WALL_M)
    box = np.array([[u.min(), v.min(), u.max() + 1, v.max() + 1]], float)
    on_pallet = _check(T=T_below, depth=pallet, box=box)
    assert on_pallet.ok and on_pallet.mouth_open > 8 and on_pallet.mouth_closed == 0, on_pallet
    on_carton = _check(T=T_below, depth=carton, box=box)
    assert on_carton.reason == "openings_closed" and on_carton.mouth_closed > 8, on_carton


def test_a_pallet_needs_one_open_pocket():
    # seen 30 degrees from above, the top deck's gaps are open whatever fills the pockets: a carton stack's bottom
    # posed as a pallet passes the overall open fraction; an obstacle in one pocket is a pallet still
    T_above = make_T(_rot_x(-30.0) @ np.array([[0.0, 1, 0], [0, 0, -1], [1, 0, 0]]), np.array([0.1, 0.45, 3.0]))

    def plugged(*y_ranges):
        plugs = [[[-0.6, y0, -0.05], [-0.455, y1, 0.028]] for y0, y1 in y_ranges]   # the -x face's pockets
        depth = _render_boxes(np.concatenate([EPAL.boxes_m, np.reshape(plugs, (-1, 2, 3))]), T_above)
        v, u = np.nonzero(depth < BACK_WALL_M)
        return _check(T=T_above, depth=depth, box=np.array([[u.min(), v.min(), u.max() + 1, v.max() + 1]], float))

    none = plugged()
    assert none.ok and none.pocket_open == 1.0
    one = plugged((-0.3, -0.072))
    assert one.ok and one.pocket_open == 1.0, one
    both = plugged((-0.3, -0.072), (0.072, 0.3))
    assert both.open_fraction > 0.5 and both.pocket_open < 0.2 and both.reason == "pockets_closed", both
    unjudged = _check(T=T_above, depth=_render_boxes(EPAL.boxes_m, T_above), box=BOX,
                      params=StructureParams(min_pocket_evidence=10**6))
    assert np.isnan(unjudged.pocket_open) and unjudged.reason != "pockets_closed"


def test_cast_rays_boxes_hits_the_face_at_its_depth():
    # a ray along the camera axis from 3 m in front of the -x face at a block's height and centre
    origin = np.array([[-3.6, 0.0, 0.0]])
    dirs = np.array([[[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]])
    t_box, t_bbox = cast_rays_boxes(origin, dirs, EPAL.boxes_m)
    assert t_box[0, 0] == pytest.approx(3.0, abs=1e-9) and t_bbox[0, 0] == pytest.approx(3.0, abs=1e-9)
    assert np.isinf(t_box[0, 1]) and np.isinf(t_bbox[0, 1])


@pytest.mark.parametrize("name, make_input, reasons", [
    ("flat wall at the face", lambda: (np.full((H, W), 3.0, np.float32) - 0.4, K),
     {"openings_closed", "structure_mismatch", "box_mismatch"}),
    ("depth 10x too near", lambda: (DEPTH * np.float32(0.1), K), {"size_mismatch"}),
    ("depth 10x too far", lambda: (DEPTH * np.float32(10.0), K), {"size_mismatch"}),
    ("focal length 2x too long", lambda: (DEPTH, K * np.array([[2.0], [2.0], [1.0]])),
     {"box_mismatch", "structure_mismatch"}),
    ("another frame's depth", lambda: (_render(make_T(R_CAM_PALLET, np.array([-1.2, 0.6, 4.5]))), K),
     {"structure_mismatch", "openings_closed", "box_mismatch"}),
    ("no depth at all", lambda: (np.zeros((H, W), np.float32), K), {"structure_unseen"}),
])
def test_mismatched_inputs_fail(name, make_input, reasons):
    depth, K_ = make_input()
    s = _check(depth=depth, K_=K_)
    assert not s.ok and s.reason in reasons, (name, s)


@pytest.mark.parametrize("name, T_wrong", [
    ("slid 30 cm sideways", make_T(R_CAM_PALLET, T_TRUE[:3, 3] + np.array([0.3, 0, 0]))),
    ("turned 90 degrees about z", T_TRUE @ make_T(quat_to_rot(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])),
                                                  np.zeros(3))),
    ("40 cm too near", make_T(R_CAM_PALLET, T_TRUE[:3, 3] * (2.6 / 3.0))),
])
def test_wrong_poses_fail(name, T_wrong):
    assert not _check(T=T_wrong).ok, name


def test_symmetric_pose_passes():
    T_sym = T_TRUE @ EPAL.symmetries[1]
    assert _check(T=T_sym).ok


def test_occluder_in_front_is_no_evidence():
    depth = np.minimum(DEPTH, np.float32(1.0))     # a sheet 1 m from the camera hides everything
    s = _check(depth=depth)
    assert s.solid + s.see_through + s.open + s.closed == 0
    assert np.isnan(s.box_solid) and s.reason == "structure_unseen"     # no pallet seen: no pose


def test_partly_hidden_pallet_passes():
    depth = DEPTH.copy()
    depth[:, : int(BOX[0, 0] + 0.4 * (BOX[0, 2] - BOX[0, 0]))] = 1.0   # a post hides the left 40 % of the pallet
    v, u = np.nonzero((depth < BACK_WALL_M) & (depth > 1.0))
    s = _check(depth=depth, box=np.array([[u.min(), v.min(), u.max() + 1, v.max() + 1]], float))
    assert s.ok, s


LOOSE = StructureParams(min_agreement=0.0, min_box_cover=0.0, min_box_solid=0.0, min_seen_iou=0.0,
                        min_open_fraction=0.0, min_pocket_open_fraction=0.0, min_box_height_of_type=0.0,
                        min_whole_box_height_of_type=0.0)


def test_a_pose_standing_in_free_space_beyond_a_whole_box_is_refused():
    """A box the image's edge does not cut holds the whole pallet: a pose that reaches past it where the depth shows
    the wall behind (a pose too large for the pallet seen, as with a focal length 2x too long) is refused, whatever
    the other tests say; where an occluder in front hides the pallet beyond its box, the pose stands."""
    assert _check(params=LOOSE).ok
    T_past = T_TRUE.copy()
    T_past[0, 3] += 0.25                            # a third of the pallet's width past the box's right side
    s = _check(T=T_past, params=LOOSE)
    assert s.reason == "see_through_beyond_box", s
    assert s.see_through_beyond > LOOSE.max_see_through_beyond_box * (s.solid + s.see_through)
    assert _check(T=T_past, params=replace(LOOSE, max_see_through_beyond_box=1.0)).ok
    hidden = DEPTH.copy()                           # a post in front of the pallet's right third
    hidden[:, int(BOX[0, 0] + 0.67 * (BOX[0, 2] - BOX[0, 0])):] = 1.0
    v, u = np.nonzero((hidden < BACK_WALL_M) & (hidden > 1.0))
    seen = np.array([[u.min(), v.min(), u.max() + 1, v.max() + 1]], float)
    s = _check(depth=hidden, box=seen)
    assert s.ok and s.see_through_beyond == 0, s


def test_a_pose_past_a_box_cut_by_the_image_edge_is_judged_by_its_boards_instead():
    """A cut box does not hold the whole pallet: the rule leaves it to `see_through_cut`."""
    T_cut = make_T(R_CAM_PALLET, np.array([1.6, 0.45, 3.0]))
    depth = _render(T_cut)
    box = _box(T_cut)
    assert box[0, 2] == W
    T_past = T_cut.copy()
    T_past[0, 3] -= 0.25                            # past the box's left side, into free space
    s = _check(T=T_past, depth=depth, box=box, params=LOOSE)
    assert s.see_through_beyond > LOOSE.max_see_through_beyond_box * (s.solid + s.see_through), s
    assert s.reason != "see_through_beyond_box", s


def test_box_far_from_the_pose_is_a_mismatch():
    s = _check(box=BOX + np.array([[150.0, 0, 150.0, 0]]))
    assert s.reason == "box_mismatch"


def test_tilt_against_an_up_vector():
    up_cam = R_CAM_PALLET[:, 2]                     # the pallet's own up: upright
    assert _check(up_cam=up_cam).ok
    up_tilted = _rot_x(40.0) @ up_cam
    assert _check(up_cam=up_tilted).reason == "tilted"
    assert np.isnan(_check().tilt_deg)


def test_a_levelled_pose_must_agree_as_the_calibrated_threshold_says():
    # with a calibration (up_cam) the poses are levelled and searched: min_agreement_levelled applies instead
    up_cam = R_CAM_PALLET[:, 2]
    slid = make_T(R_CAM_PALLET, T_TRUE[:3, 3] + R_CAM_PALLET @ np.array([0.06, 0.0, 0.0]))
    agreement = _check(T=slid).agreement
    assert 0.0 < agreement < 1.0
    between = (StructureParams(min_agreement=agreement - 0.01, min_agreement_levelled=agreement + 0.01),
               StructureParams(min_agreement=agreement + 0.01, min_agreement_levelled=agreement - 0.01))
    assert _check(T=slid, params=between[0]).reason != "structure_mismatch"
    assert _check(T=slid, params=between[0], up_cam=up_cam).reason == "structure_mismatch"
    assert _check(T=slid, params=between[1]).reason == "structure_mismatch"
    assert _check(T=slid, params=between[1], up_cam=up_cam).reason != "structure_mismatch"


def test_empty_and_batched():
    assert structure_check(np.zeros((0, 4, 4)), EPAL.boxes_m, DEPTH, K, np.zeros((0, 4))) == []
    T2 = np.stack([T_TRUE, make_T(R_CAM_PALLET, T_TRUE[:3, 3] + np.array([0.3, 0, 0]))])
    s = structure_check(T2, EPAL.boxes_m, DEPTH, K, np.repeat(BOX, 2, 0))
    assert [x.ok for x in s] == [True, False]
    one = _check()                                 # batching does not change a pose's score
    assert (s[0].solid, s[0].see_through, s[0].open, s[0].closed) == (one.solid, one.see_through, one.open, one.closed)


@pytest.mark.parametrize("kwargs, exc, match", [
    (dict(T=np.full((4, 4), np.nan)), ValueError, "finite"),
    (dict(box=np.zeros((2, 4))), ValueError, "1 poses but 2 boxes"),
    (dict(depth=np.zeros((3, 4, 5))), ValueError, r"depth_m must be \(H, W\)"),
    (dict(K_=np.eye(2)), ValueError, "3x3"),
    (dict(up_cam=np.zeros(3)), ValueError, "non-zero"),
])
def test_bad_input_raises(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        _check(**kwargs)


def test_bad_boxes_raise():
    with pytest.raises(ValueError, match="boxes_m"):
        structure_check(T_TRUE[None], np.zeros((0, 2, 3)), DEPTH, K, BOX)


@pytest.mark.parametrize("kwargs", [dict(grid=2), dict(tol_m=0.0), dict(min_agreement=1.5), dict(max_tilt_deg=0.0),
                                    dict(min_evidence=0), dict(min_edge_auc=1.2), dict(min_box_height_of_type=-0.1),
                                    dict(max_box_size_of_diameter=0.0), dict(min_edge_pairs=0),
                                    dict(min_whole_box_height_of_type=1.5), dict(border_px=-1.0),
                                    dict(whole_box_edge_px=-1.0), dict(whole_box_edge_px=float("nan"))])
def test_bad_params_raise(kwargs):
    with pytest.raises(ValueError):
        StructureParams(**kwargs)


def test_true_pose_passes_with_its_image():
    s = _check(rgb=RGB)
    assert s.ok, s
    assert s.edge_auc > 0.7
    assert _check(rgb=RGB, params=StructureParams(grid=16)).ok
    width_m, height_m = s.box_size_m
    assert 0.6 < width_m < 1.0 and 0.1 < height_m < 0.3       # the 800 mm face, 144 mm tall, seen a little from above


def test_depth_of_another_scene_under_the_image_is_refused():
    """The image shows a bare wall (another frame's image, or depth not registered to it): its colour does not
    change where the depth jumps."""
    wall = _colour(np.full((H, W), BACK_WALL_M, np.float32), seed=1)
    # a grid no finer than the pallet's pixels (rays reading the same pixel lift the AUC above chance)
    s = _check(rgb=wall, params=StructureParams(grid=16, min_edge_auc=0.58))
    assert s.reason == "depth_image_mismatch", s
    assert abs(s.edge_auc - 0.5) < 0.15


def test_image_of_a_pallet_elsewhere_is_refused():
    elsewhere = _colour(_render(make_T(R_CAM_PALLET, np.array([-0.6, 0.3, 4.0]))), seed=2)
    assert _check(rgb=elsewhere, params=StructureParams(grid=16, min_edge_auc=0.58)).reason == "depth_image_mismatch"
    assert _check(rgb=elsewhere, params=StructureParams(grid=16)).ok       # the edge test is off by default


def test_edge_test_needs_pairs_and_can_be_off():
    flat = np.full((H, W), 3.0, np.float32)        # no depth jump at all: no evidence either way
    s = structure_check(T_TRUE[None], EPAL.boxes_m, flat, K, BOX, rgb=RGB,
                        params=StructureParams(min_edge_auc=0.58))[0]
    assert np.isnan(s.edge_auc) and s.reason != "depth_image_mismatch"
    wall = _colour(np.full((H, W), BACK_WALL_M, np.float32), seed=1)
    assert _check(rgb=wall, params=StructureParams(grid=16, min_edge_auc=0.0)).ok
    assert np.isnan(_check().edge_auc)              # without a colour image the test is skipped


def test_focal_length_far_too_long_is_a_size_mismatch():
    s = _check(K_=K * np.array([[4.0], [4.0], [1.0]]))
    assert s.reason == "size_mismatch", s


def test_size_bounds_can_be_off():
    shrunk = DEPTH * np.float32(0.1)
    s = _check(depth=shrunk, params=StructureParams(min_box_height_of_type=0.0, min_whole_box_height_of_type=0.0,
                                                    whole_box_edge_px=float("inf")))
    assert s.reason != "size_mismatch"


def test_box_metric_size():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:10] = 0.0                                # missing depth is ignored
    size = box_metric_size(np.array([[10.0, 20.0, 140.0, 46.0], [0.0, 0.0, 20.0, 5.0]]), depth, K)
    assert size[0] == pytest.approx([130 * 2.0 / 260.0, 26 * 2.0 / 260.0])
    assert np.all(np.isnan(size[1]))                # no valid depth in the box


def test_edge_agreement_ranks_colour_steps_at_depth_jumps():
    z = np.full((1, 8, 8), 3.0)
    z[:, :, 4:] = 5.0                               # a depth jump between columns 3 and 4
    colour = np.zeros((1, 8, 8, 3))
    tol = np.full((1, 8, 8), 0.05)
    colour[:, :, 4:] = 100.0                        # ... where the colour steps too
    assert edge_agreement(z, colour, tol, min_pairs=5)[0] == pytest.approx(1.0)
    colour_elsewhere = np.zeros((1, 8, 8, 3))
    colour_elsewhere[:, 4:] = 100.0                 # a colour step across the rows instead
    assert edge_agreement(z, colour_elsewhere, tol, min_pairs=5)[0] < 0.6
    assert np.isnan(edge_agreement(z, colour, tol, min_pairs=9)[0])    # 8 jumping pairs only


def test_rgb_of_another_size_raises():
    with pytest.raises(ValueError, match="rgb"):
        _check(rgb=RGB[:-1])


def _render_type(boxes_m: np.ndarray, T_cam_pallet: np.ndarray, K_: np.ndarray = K) -> tuple[np.ndarray, np.ndarray]:
    """Ideal depth of a posed pallet of any type before the back wall, and its visible box in the image."""
    v, u = np.mgrid[0:H, 0:W]
    d_cam = np.stack([(u - K_[0, 2]) / K_[0, 0], (v - K_[1, 2]) / K_[1, 1], np.ones((H, W))], -1).reshape(1, -1, 3)
    R, t = T_cam_pallet[:3, :3], T_cam_pallet[:3, 3]
    t_box, _ = cast_rays_boxes((-R.T @ t)[None], d_cam @ R, boxes_m)
    depth = np.minimum(t_box[0], BACK_WALL_M).reshape(H, W).astype(np.float32)
    rows, cols = np.nonzero(depth < BACK_WALL_M)
    return depth, np.array([[cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]], float)


@pytest.mark.parametrize("name", ["epal", "eur6", "plastic_3runner_1210", "gma"])
def test_whole_box_height_uses_the_types_own_geometry(name):
    """Every type's true pose passes; with the focal length 2x too long its whole box spans half its height."""
    boxes = get_pallet_model(name).boxes_m
    T = make_T(R_CAM_PALLET, np.array([0.1, 0.45, 2.5]))
    depth, box = _render_type(boxes, T)
    s = structure_check(T[None], boxes, depth, K, box)[0]
    assert s.ok and not s.box_cut, s
    height_m = (boxes[:, 1].max(0) - boxes[:, 0].min(0)).min()
    assert s.box_size_m[1] > StructureParams().min_whole_box_height_of_type * height_m
    # with fx, fy doubled the depth back-projects to a pallet half the size laterally, at the same range: the
    # pose network puts the full-size model there (half the lateral offset), larger than the box
    T_focal = make_T(R_CAM_PALLET, T[:3, 3] * np.array([0.5, 0.5, 1.0]))
    K_focal = K.copy()
    K_focal[0, 0] *= 2.0
    K_focal[1, 1] *= 2.0
    wrong = structure_check(T_focal[None], boxes, depth, K_focal, box)[0]
    assert wrong.reason == "size_mismatch" and not wrong.box_cut, wrong
    assert wrong.whole_height_m == pytest.approx(s.whole_height_m / 2.0, rel=0.15)
    assert s.whole_height_m == pytest.approx(s.box_size_m[1], rel=0.15)


def test_a_whole_box_is_held_to_its_height_less_a_few_pixels():
    """Seen 18 degrees from above, a pallet's whole box is 1.8 times its height tall: with the focal length 2x too
    long it spans 0.89 of the height, over the 0.8 bound and under the height less 3 of the box's 34 pixels."""
    T = make_T(_rot_x(-18.0) @ np.array([[0.0, 1, 0], [0, 0, -1], [1, 0, 0]]), np.array([0.1, 0.45, 2.5]))
    depth, box = _render_type(EPAL.boxes_m, T)
    edge = StructureParams()
    assert edge.whole_box_edge_px == 3.0 and structure_check(T[None], EPAL.boxes_m, depth, K, box, edge)[0].ok
    T_focal = make_T(T[:3, :3], T[:3, 3] * np.array([0.5, 0.5, 1.0]))
    K_focal = K.copy()
    K_focal[0, 0] *= 2.0
    K_focal[1, 1] *= 2.0
    loose = structure_check(T_focal[None], EPAL.boxes_m, depth, K_focal, box,
                            StructureParams(whole_box_edge_px=float("inf")))[0]
    box_h_px = box[0, 3] - box[0, 1]
    assert loose.reason != "size_mismatch" and not loose.box_cut, loose
    assert 0.8 < loose.whole_height_m / EPAL.size_m.min() < 1.0 - 3.0 / box_h_px
    assert structure_check(T_focal[None], EPAL.boxes_m, depth, K_focal, box, edge)[0].reason == "size_mismatch"


def test_box_cut_by_the_image_edge_keeps_the_looser_bound():
    """A pallet half below the image's bottom edge shows less than its height: a cut box, not a size mismatch."""
    T = make_T(R_CAM_PALLET, np.array([0.1, 1.55, 3.0]))
    depth, box = _render_type(EPAL.boxes_m, T)
    assert box[0, 3] == H                           # the box ends at the image's bottom edge
    s = _check(T=T, depth=depth, box=box)
    assert s.box_cut and s.ok, s
    assert s.box_size_m[1] < StructureParams().min_whole_box_height_of_type * EPAL.size_m.min()


def test_a_cut_box_whose_pose_sees_through_its_boards_is_refused():
    """A box the image's edge cuts cannot show a wrong scale by its size: its pose must not overhang the depth."""
    T_cut = make_T(R_CAM_PALLET, np.array([1.6, 0.45, 3.0]))
    depth, box = _render_type(EPAL.boxes_m, T_cut)
    assert box[0, 2] == W                           # the box ends at the image's right edge
    assert _check(T=T_cut, depth=depth, box=box).ok
    T_aside = T_cut.copy()
    T_aside[0, 3] += 0.05                           # its boards now overhang the wall behind
    s = _check(T=T_aside, depth=depth, box=box)
    assert s.reason == "see_through_cut" and s.see_through > 0.2 * (s.solid + s.see_through), s
    assert _check(T=T_aside, depth=depth, box=box, params=StructureParams(max_see_through_cut=1.0)).ok
    whole = T_TRUE.copy()
    whole[0, 3] += 0.05                             # the same error on a whole box: its size is judged instead
    assert _check(T=whole).reason != "see_through_cut"


def test_a_tall_box_cut_aside_shows_its_size_and_may_see_through():
    """Seen 30 degrees from above, a pallet cut by the image's side is over twice its height tall in the box: a focal
    length 2x too long would leave it over the whole-height bound, so its size, not its see-through rays, judges."""
    T = make_T(_rot_x(-30.0) @ np.array([[0.0, 1, 0], [0, 0, -1], [1, 0, 0]]), np.array([1.4, 0.6, 2.5]))
    depth, box = _render_type(EPAL.boxes_m, T)
    T_aside = T.copy()
    T_aside[0, 3] += 0.05
    s = _check(T=T_aside, depth=depth, box=box)
    assert box[0, 2] == W and not s.box_cut
    assert s.whole_height_m > 2 * StructureParams().min_whole_box_height_of_type * EPAL.size_m.min()
    assert s.see_through > 0.2 * (s.solid + s.see_through) and s.ok, s


def test_whole_box_height_is_measured_at_the_pallets_depth():
    """Posts 1.5 m from the camera hide 60 % of the pallet's columns: the median depth in the box is theirs, the
    pallet's height is measured where the rays found its surface."""
    depth = DEPTH.copy()
    cols = np.arange(int(BOX[0, 0]), int(BOX[0, 2]))
    depth[:, cols[(cols - cols[0]) % 10 < 6]] = 1.5
    s = _check(depth=depth)
    assert s.ok and not s.box_cut, s
    assert s.box_size_m[1] < StructureParams().min_whole_box_height_of_type * EPAL.size_m.min()   # at the posts
    assert s.whole_height_m == pytest.approx(_check().whole_height_m, rel=0.05)


def test_fit_check_stage_names_the_whole_box_height_in_its_rejection():
    from pallet6d.runtime.candidates import Candidates
    from pallet6d.runtime.stage_fit import FitCheckStage
    from pallet6d.runtime.stage_geometry import PalletGeometry

    geoms = tuple(PalletGeometry(name=n, points_m=m.boxes_m.reshape(-1, 3), boxes_m=m.boxes_m, symmetries=m.symmetries,
                                 size_m=m.size_m, refine_starts=np.zeros((0, 3)))
                  for n, m in (("epal", EPAL), ("eur6", get_pallet_model("eur6"))))
    T = make_T(R_CAM_PALLET, np.array([0.1, 0.45, 2.5]))
    depth, box = _render_type(geoms[1].boxes_m, T)
    K_focal = K.copy()
    K_focal[0, 0] *= 2.0
    K_focal[1, 1] *= 2.0
    stage = FitCheckStage(geoms, tol_m=0.04, min_fit=0.0, min_confidence=0.0)
    right, wrong = (Candidates.new(box, [0.9], [0], [1], num_points=8) for _ in range(2))
    right.assign(np.arange(1), T_cam_pallet=T[None])
    wrong.assign(np.arange(1), T_cam_pallet=make_T(R_CAM_PALLET, T[:3, 3] * np.array([0.5, 0.5, 1.0]))[None])
    stage.check_structure(right, np.arange(1), depth, K)
    stage.check_structure(wrong, np.arange(1), depth, K_focal)
    assert right.reason[0] == "", right.detail[0]          # the eur6 at its true pose passes
    assert wrong.reason[0] == "size_mismatch" and "tall at the pallet's depth" in wrong.detail[0], wrong.detail[0]


def test_fit_check_stage_names_the_see_through_of_a_cut_box():
    from pallet6d.runtime.candidates import Candidates
    from pallet6d.runtime.stage_fit import FitCheckStage
    from pallet6d.runtime.stage_geometry import PalletGeometry

    geom = PalletGeometry(name="epal", points_m=EPAL.boxes_m.reshape(-1, 3), boxes_m=EPAL.boxes_m,
                          symmetries=EPAL.symmetries, size_m=EPAL.size_m, refine_starts=np.zeros((0, 3)))
    T_cut = make_T(R_CAM_PALLET, np.array([1.6, 0.45, 3.0]))
    depth, box = _render_type(EPAL.boxes_m, T_cut)
    T_aside = T_cut.copy()
    T_aside[0, 3] += 0.05
    cands = Candidates.new(box, [0.9], [0], [0], num_points=8)
    cands.assign(np.arange(1), T_cam_pallet=T_aside[None])
    FitCheckStage((geom,), tol_m=0.04, min_fit=0.0, min_confidence=0.0).check_structure(cands, np.arange(1), depth, K)
    assert cands.reason[0] == "no_pallet_structure", cands.detail[0]
    assert cands.detail[0].startswith("see_through_cut: the image's edge cuts the box"), cands.detail[0]


def test_fit_check_stage_names_the_see_through_beyond_a_whole_box():
    from pallet6d.runtime.candidates import Candidates
    from pallet6d.runtime.stage_fit import FitCheckStage
    from pallet6d.runtime.stage_geometry import PalletGeometry

    geom = PalletGeometry(name="epal", points_m=EPAL.boxes_m.reshape(-1, 3), boxes_m=EPAL.boxes_m,
                          symmetries=EPAL.symmetries, size_m=EPAL.size_m, refine_starts=np.zeros((0, 3)))
    T_past = T_TRUE.copy()
    T_past[0, 3] += 0.25
    cands = Candidates.new(BOX, [0.9], [0], [0], num_points=8)
    cands.assign(np.arange(1), T_cam_pallet=T_past[None])
    FitCheckStage((geom,), tol_m=0.04, min_fit=0.0, min_confidence=0.0, structure=LOOSE).check_structure(
        cands, np.arange(1), DEPTH, K)
    assert cands.reason[0] == "no_pallet_structure", cands.detail[0]
    assert cands.detail[0].startswith("see_through_beyond_box: "), cands.detail[0]


@pytest.mark.parametrize("compiled", [True, False])
def test_structure_agreement_of_several_types_equals_the_structure_check(monkeypatch, compiled):
    """Poses of several types in one pass give each pose the agreement and open fraction that `structure_check`
    gives it with its own type's boxes, with the rays in the kernel or in numpy."""
    from pallet6d.runtime import kernels

    if not compiled:
        monkeypatch.setattr(kernels, "available", lambda: False)
    elif not kernels.available():
        pytest.skip("the compiled kernels are not built here")
    names = ["epal", "plastic_closed", "gma"]
    sets = [get_pallet_model(n).boxes_m for n in names]
    T = np.stack([T_TRUE, make_T(R_CAM_PALLET, np.array([0.2, 0.45, 3.0])), T_TRUE, make_T(_rot_x(20) @ R_CAM_PALLET,
                  np.array([0.1, 0.4, 3.2])), T_TRUE])
    which = np.array([0, 0, 1, 2, 2])
    agreement, open_fraction = structure_agreement(T, sets, which, DEPTH, K)
    for i, j in enumerate(which):
        s = structure_check(T[i:i + 1], sets[j], DEPTH, K, BOX)[0]
        assert agreement[i] == s.agreement and open_fraction[i] == s.open_fraction, (i, s)
    assert agreement[0] > 0.9 and agreement[2] < agreement[0]           # the EPAL's depth agrees with the EPAL best
    empty = structure_agreement(np.zeros((0, 4, 4)), sets, np.zeros(0, int), DEPTH, K)
    assert empty[0].shape == empty[1].shape == (0,)


@pytest.mark.parametrize("kwargs, match", [
    ({"which": np.array([3])}, "which"),
    ({"which": np.array([0, 0])}, "type indexes"),
    ({"box_sets": [np.zeros((0, 2, 3))]}, "box_sets"),
    ({"box_sets": []}, "at least one"),
    ({"depth_m": DEPTH[0]}, "depth_m"),
    ({"T_cam_pallet": np.full((1, 4, 4), np.nan)}, "finite"),
])
def test_structure_agreement_bad_input(kwargs, match):
    args = {"T_cam_pallet": T_TRUE[None], "box_sets": [EPAL.boxes_m], "which": np.array([0]), "depth_m": DEPTH,
            "K": K} | kwargs
    with pytest.raises(ValueError, match=match):
        structure_agreement(**args)
