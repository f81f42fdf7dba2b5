import math

import numpy as np
import pytest

from pallet6d.runtime import geometry as g
from pallet6d.sim.generate import generate_frame, mask_bbox_xywh, render_scene
from pallet6d.sim.pallets import get_pallet_model
from pallet6d.sim.presets import PRESETS, SimConfig, get_preset
from pallet6d.sim.raycast import raycast_boxes
from pallet6d.sim.scene import MATERIALS, Box, PalletPlacement, Scene, SceneError, look_at_T_world_cam, pallet_boxes
from pallet6d.sim.sensors import StereoDepthModel

K_SMALL = np.array([[200.0, 0, 159.5], [0, 200.0, 89.5], [0, 0, 1]])


def floor_box():
    T = np.eye(4)
    T[2, 3] = -0.05
    return Box(T, [20, 20, 0.05], MATERIALS.index("concrete"), [0.6, 0.6, 0.6])


def pallet_scene(yaw=0.3, eye=(-2.5, -1.0, 1.0), extra=()):
    model = get_pallet_model("epal")
    c, s = math.cos(yaw), math.sin(yaw)
    T = g.make_T(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [0.1, 0.2, model.size_m[2] / 2])
    placement = PalletPlacement(1, "epal", T)
    boxes = [floor_box(), *pallet_boxes(placement, np.array([0.8, 0.65, 0.45]), 3), *extra]
    T_world_cam = look_at_T_world_cam(np.array(eye), np.array([0.1, 0.2, 0.07]))
    return Scene(boxes, [placement], T_world_cam, K_SMALL, (180, 320), target_instance=1)


def test_single_box_depth_is_exact():
    # A 1 m cube 3 m in front of the camera: its front face at z = 2.5 m, centred on the principal point.
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    rc = raycast_boxes(np.eye(3)[None], np.array([[0, 0, 3.0]]), np.array([[0.5, 0.5, 0.5]]), K, (48, 64),
                       group=np.array([1]))
    hit = rc.box_index == 0
    np.testing.assert_allclose(rc.depth_m[hit], 2.5, atol=1e-6)
    assert np.all(rc.depth_m[~hit] == 0)
    # Pixels whose rays pass within the face: |u - cx| <= 100 * 0.5 / 2.5 = 20.
    u = np.arange(64)
    np.testing.assert_array_equal(hit[24], np.abs(u - 31.5) <= 20)
    np.testing.assert_array_equal(rc.full_masks[1], hit)


def test_boxes_behind_the_camera_are_not_seen():
    rc = raycast_boxes(np.eye(3)[None], np.array([[0, 0, -3.0]]), np.array([[0.5, 0.5, 0.5]]), K_SMALL, (180, 320))
    assert (rc.box_index < 0).all()


def test_nearer_box_occludes_and_full_mask_ignores_occlusion():
    R = np.stack([np.eye(3)] * 2)
    t = np.array([[0, 0, 4.0], [0.0, 0, 2.0]])
    half = np.array([[0.5, 0.5, 0.5], [0.2, 0.2, 0.2]])
    rc = raycast_boxes(R, t, half, K_SMALL, (180, 320), group=np.array([1, 0]))
    assert (rc.box_index == 1).sum() > 0
    assert np.all(rc.full_masks[1][rc.box_index == 1])          # hidden pixels still in the full mask
    np.testing.assert_allclose(rc.depth_m[rc.box_index == 1], 1.8, atol=1e-5)


@pytest.mark.parametrize("yaw", [0.0, 0.3, 2.0])
def test_backprojected_depth_lies_on_the_pallet_surface(yaw):
    frame = render_scene(pallet_scene(yaw))
    (gt,) = frame.pallets
    assert gt.px_count_visib > 500
    v, u = np.nonzero(gt.mask_visib)
    pts_cam = g.backproject_pixels(u, v, frame.depth_m[v, u], frame.K)
    pts = g.transform_points(g.invert_T(gt.T_cam_pallet), pts_cam.astype(np.float64))
    err = get_pallet_model("epal").surface_distance_m(pts)
    assert np.percentile(err, 99) < 0.002 and err.max() < 0.005


def test_gt_fields_are_consistent():
    frame = render_scene(pallet_scene())
    (gt,) = frame.pallets
    assert gt.visib_fract == pytest.approx(1.0)
    np.testing.assert_array_equal(gt.mask_full, gt.mask_visib)
    bx, by, bw, bh = gt.bbox_obj_xywh
    vx, vy, vw, vh = mask_bbox_xywh(gt.mask_full)
    assert abs(bx - vx) <= 1 and abs(by - vy) <= 1 and abs(bw - vw) <= 2 and abs(bh - vh) <= 2
    uv = g.project_points(gt.box3d_cam, frame.K)
    assert np.all(uv.min(0) >= [bx - 1, by - 1]) and np.all(uv.max(0) <= [bx + bw + 1, by + bh + 1])
    # T_cam_pallet is the scene's placement seen from the camera.
    np.testing.assert_allclose(frame.T_world_cam @ gt.T_cam_pallet, pallet_scene().pallets[0].T_world_pallet,
                               atol=1e-9)


def test_image_border_cuts_the_visible_fraction_as_bop_counts_it():
    whole = render_scene(pallet_scene()).pallets[0]
    scene = pallet_scene()
    scene.K = K_SMALL.copy()
    scene.K[0, 2] -= 150.0          # the same view shifted 150 px left: the border cuts the pallet
    (cut,) = render_scene(scene).pallets
    assert cut.px_count_all == whole.px_count_all      # the whole silhouette, the part out of view included
    assert cut.mask_full.sum() < 0.8 * whole.mask_full.sum()
    assert cut.visib_fract == pytest.approx(cut.mask_full.sum() / whole.px_count_all)
    assert cut.bbox_obj_xywh[0] < 0 and whole.visib_fract == pytest.approx(1.0)


def test_occluder_reduces_visible_fraction():
    T = g.make_T(np.eye(3), [-1.37, -0.04, 0.4])   # covers about half of the pallet
    wall = Box(T, [0.3, 0.3, 0.4], MATERIALS.index("cardboard"), [0.6, 0.5, 0.3])
    frame = render_scene(pallet_scene(extra=[wall]))
    (gt,) = frame.pallets
    assert 0.0 < gt.visib_fract < 0.95
    assert not np.any(gt.mask_visib & ~gt.mask_full)


def test_same_seed_same_frame_and_different_seeds_differ():
    cfg = get_preset("virtual-occluded").with_image_size(160, 64)
    a, b, c = generate_frame(cfg, 3, 0), generate_frame(cfg, 3, 0), generate_frame(cfg, 4, 0)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert [p.instance_id for p in a.pallets] == [p.instance_id for p in b.pallets]
    assert not np.array_equal(a.rgb, c.rgb)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_give_a_visible_target(name):
    cfg = get_preset(name).with_image_size(160, 80)
    frame = generate_frame(cfg, 0, 1)
    target = frame.pallet(frame.target_instance)
    assert target.visib_fract >= cfg.min_target_visib
    assert frame.rgb.shape == (80, 160, 3) and frame.depth_m.dtype == np.float32
    assert frame.rgb.std() > 5     # textured, not a flat image


def test_clean_preset_has_the_camera_aligned_with_the_target():
    cfg = get_preset("virtual-clean").with_image_size(160, 64)
    frame = generate_frame(cfg, 1, 0)
    T = frame.pallet(frame.target_instance).T_cam_pallet
    x_axis_cam = T[:3, 0]
    # The pallet's length axis points along the optical axis (either way: 180 deg symmetric), no yaw.
    assert abs(x_axis_cam[0]) < 1e-6 and abs(abs(x_axis_cam[2]) / np.linalg.norm(x_axis_cam[[0, 2]]) - 1) < 1e-6


def test_unknown_preset_lists_known_ones():
    with pytest.raises(ValueError, match="virtual-clean"):
        get_preset("nope")


def test_scene_without_pallet_raises():
    s = pallet_scene()
    s.pallets = []
    with pytest.raises(SceneError, match="no pallet"):
        render_scene(s)


def test_camera_inside_geometry_raises():
    with pytest.raises(SceneError, match="inside"):
        render_scene(pallet_scene(eye=(0.3, 0.25, 0.05)))


@pytest.mark.parametrize("kwargs, match", [
    (dict(target_distance_m=(0.1, 0.2)), "target_distance_m"),
    (dict(target_distance_m=(3.0, 2.0)), "min <= max"),
    (dict(pallet_models=()), "pallet"),
    (dict(pallet_models=("nope",)), "unknown pallet"),
    (dict(min_target_visib=1.5), "min_target_visib"),
    (dict(sensor="kinect"), "sensor"),
    (dict(sensor="ideal", sensor_model=StereoDepthModel()), "ideal"),
    (dict(width=4), "16x16"),
])
def test_bad_configs_raise(kwargs, match):
    base = dict(name="t", width=160, height=80, hfov_deg=80.0)
    with pytest.raises(ValueError, match=match):
        SimConfig(**{**base, **kwargs})


def test_target_that_cannot_be_in_view_raises():
    # A 5 degree field of view cannot hold a whole pallet at 1.5 m.
    cfg = SimConfig(name="narrow", width=64, height=32, hfov_deg=10.0, target_distance_m=(1.0, 1.5),
                    max_attempts=3)
    with pytest.raises(SceneError, match="narrow"):
        generate_frame(cfg, 0, 0)


# sha256 (first 16 hex digits) of rgb + sensor depth + ideal depth of frames 0-2, seed 7, at 160x96: the paper
# presets' frames must stay exactly as they are (appearance None, their own sensors), so the paper comparison
# keeps its data. A change here changes the virtual-clean / virtual-occluded / indoor-noisy datasets. One frame has
# two digests: two of this project's machines (one an AMD EPYC) render it differently with the same numpy, OpenCV
# and Python (numpy 2.2-2.4 and OpenCV 4.14-5.0 give each machine its own digest); every other frame is the same.
PAPER_FRAME_HASHES = {
    ("indoor-noisy", 0): {"09903b6711d453a6"}, ("indoor-noisy", 1): {"5eaf2ba56b918510"},
    ("indoor-noisy", 2): {"5c82ef5d42beee57"}, ("virtual-clean", 0): {"0782d16f071d3434"},
    ("virtual-clean", 1): {"f58531baa31de907"}, ("virtual-clean", 2): {"eee67e9af3650b81"},
    ("virtual-occluded", 0): {"a1a63bfcfb15c5f7"}, ("virtual-occluded", 1): {"a87d42b614269132", "f9e6c2b7d1887fa1"},
    ("virtual-occluded", 2): {"d904ad4ba9537c6a"},
}


@pytest.mark.parametrize("name, index", sorted(PAPER_FRAME_HASHES))
def test_paper_preset_frames_are_bit_identical(name, index):
    import hashlib

    frame = generate_frame(get_preset(name).with_image_size(160, 96), 7, index)
    digest = hashlib.sha256(frame.rgb.tobytes() + frame.depth_m.tobytes() + frame.depth_ideal_m.tobytes())
    assert digest.hexdigest()[:16] in PAPER_FRAME_HASHES[(name, index)]
