import json
import math
import shutil

import cv2
import numpy as np
import pytest
from conftest import SIM_BOP_FRAMES, SIM_BOP_PRESET, SIM_BOP_SEED, SIM_BOP_SIZE

from pallet6d.runtime.bop import BopDataset, BopFormatError, BopGT, BopWriter, symmetries_from_info
from pallet6d.sim.generate import generate_frame
from pallet6d.sim.pallets import ROT_Z_180, get_pallet_model
from pallet6d.sim.presets import get_preset


@pytest.fixture()
def bop_copy(sim_bop_dataset, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(sim_bop_dataset, root)
    return root


def test_round_trip_matches_the_generated_frames(sim_bop_dataset):
    ds = BopDataset(sim_bop_dataset)
    assert ds.split == "train" and len(ds) == SIM_BOP_FRAMES
    cfg = get_preset(SIM_BOP_PRESET).with_image_size(*SIM_BOP_SIZE)
    n_masks = 0
    for i in range(len(ds)):
        frame = ds[i]
        ref = generate_frame(cfg, SIM_BOP_SEED, i)
        assert (frame.scene_id, frame.im_id) == (0, i)
        np.testing.assert_array_equal(frame.rgb, ref.rgb)
        np.testing.assert_allclose(frame.K, ref.K)
        assert frame.depth_scale_mm == 1.0
        assert np.abs(frame.depth_m - ref.depth_m).max() <= 0.0005 + 1e-6
        np.testing.assert_array_equal(frame.depth_m > 0, ref.depth_m > 0)
        assert len(frame.gts) == len(ref.pallets) > 0
        for gt, p in zip(frame.gts, ref.pallets):
            assert gt.obj_id == p.obj_id == 1
            np.testing.assert_allclose(gt.T_cam_model, p.T_cam_pallet, atol=1e-9)
            np.testing.assert_array_equal(gt.bbox_visib_xywh, p.bbox_visib_xywh)
            np.testing.assert_array_equal(gt.bbox_obj_xywh, p.bbox_obj_xywh)
            assert gt.visib_fract == pytest.approx(p.visib_fract)
            if p.px_count_visib:
                np.testing.assert_array_equal(gt.mask_visib, p.mask_visib)
                n_masks += 1
            np.testing.assert_array_equal(gt.mask, p.mask_full)
        np.testing.assert_allclose(frame.T_cam_world @ ref.T_world_cam, np.eye(4), atol=1e-9)
    assert n_masks > 0


def test_models_info_and_symmetries(sim_bop_dataset):
    ds = BopDataset(sim_bop_dataset)
    epal = get_pallet_model("epal")
    info = ds.models_info[1]
    assert info["diameter"] == pytest.approx(epal.diameter_m * 1000)
    assert [info["size_x"], info["size_y"], info["size_z"]] == pytest.approx([1200, 800, 144])
    assert info["min_x"] == pytest.approx(-600)
    syms = ds.model_symmetries(1)
    assert syms.shape == (2, 4, 4)
    np.testing.assert_allclose(syms[0], np.eye(4))
    np.testing.assert_allclose(syms[1], ROT_Z_180, atol=1e-12)
    assert ds.model_path(1).exists()
    with pytest.raises(ValueError, match="obj_id 99"):
        ds.model_symmetries(99)


def test_continuous_symmetries_are_discretised():
    syms = symmetries_from_info({"diameter": 1, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                                 "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 100, 0, 0, 0, 1]]},
                                continuous_steps=4)
    assert syms.shape == (8, 4, 4)
    np.testing.assert_allclose(syms[0], np.eye(4))
    np.testing.assert_allclose(syms[1][2, 3], 0.1)         # translation from mm to m


def test_masks_missing_and_jpg_rgb_still_load(bop_copy):
    scene = bop_copy / "train" / "000000"
    shutil.rmtree(scene / "mask_visib")
    shutil.rmtree(scene / "mask")
    for png in (scene / "rgb").glob("*.png"):
        cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png)))
        png.unlink()
    (scene / "scene_gt_info.json").unlink()
    frame = BopDataset(bop_copy)[0]
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (SIM_BOP_SIZE[1], SIM_BOP_SIZE[0], 3)
    assert all(gt.mask_visib is None and gt.bbox_obj_xywh is None and math.isnan(gt.visib_fract)
               for gt in frame.gts)


def test_split_must_be_named_when_there_are_several(bop_copy):
    shutil.copytree(bop_copy / "train", bop_copy / "test")
    with pytest.raises(ValueError, match="test"):
        BopDataset(bop_copy)
    assert len(BopDataset(bop_copy, "test")) == SIM_BOP_FRAMES
    with pytest.raises(ValueError, match="val"):
        BopDataset(bop_copy, "val")


def _edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("fname, edit, field", [
    ("scene_gt.json", lambda d: d["0"][0].pop("cam_t_m2c"), "cam_t_m2c"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[1, 0, 0]), "cam_R_m2c"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[2, 0, 0, 0, 1, 0, 0, 0, 1]), "cam_R_m2c"),
    ("scene_gt.json", lambda d: d["0"][0].update(obj_id="pallet"), "obj_id"),
    ("scene_camera.json", lambda d: d["1"].pop("cam_K"), "cam_K"),
    ("scene_camera.json", lambda d: d["1"].update(depth_scale=-1), "depth_scale"),
    ("scene_gt_info.json", lambda d: d["0"][0].pop("bbox_visib"), "bbox_visib"),
])
def test_malformed_fields_name_file_and_field(bop_copy, fname, edit, field):
    _edit_json(bop_copy / "train" / "000000" / fname, edit)
    with pytest.raises(BopFormatError, match=rf"{fname}.*'{field}'"):
        BopDataset(bop_copy)


def test_invalid_json_names_the_file(bop_copy):
    (bop_copy / "train" / "000000" / "scene_gt.json").write_text("{not json")
    with pytest.raises(BopFormatError, match="scene_gt.json"):
        BopDataset(bop_copy)


def test_malformed_models_info(bop_copy):
    _edit_json(bop_copy / "models" / "models_info.json", lambda d: d["1"].pop("diameter"))
    with pytest.raises(BopFormatError, match=r"models_info.json.*'diameter'"):
        BopDataset(bop_copy)


def test_writer_handles_depth_scale_and_far_depth(tmp_path):
    rgb = np.zeros((8, 10, 3), np.uint8)
    depth = np.full((8, 10), 1.23456, np.float32)
    depth[0, 0] = 70.0           # beyond uint16 millimetres: stored as no data
    depth[1, 1] = np.nan
    gt = BopGT(obj_id=2, T_cam_model=np.eye(4), mask_visib=np.ones((8, 10), bool))
    with BopWriter(tmp_path, "val", depth_scale_mm=0.1) as w:
        w.write_frame(3, 5, rgb, depth, np.diag([100.0, 100.0, 1.0]), [gt])
    frame = BopDataset(tmp_path)[0]
    assert (frame.scene_id, frame.im_id, frame.depth_scale_mm) == (3, 5, 0.1)
    assert frame.depth_m[0, 0] == 0 and frame.depth_m[1, 1] == 0
    assert frame.depth_m[2, 2] == pytest.approx(1.23456, abs=0.00005)
    assert frame.gts[0].obj_id == 2 and frame.gts[0].mask_visib.all()


def test_writer_rejects_bad_input(tmp_path):
    w = BopWriter(tmp_path)
    with pytest.raises(ValueError, match="rgb"):
        w.write_frame(0, 0, np.zeros((8, 10), np.uint8), np.zeros((8, 10)), np.eye(3), [])
    with pytest.raises(ValueError, match="depth_m"):
        w.write_frame(0, 0, np.zeros((8, 10, 3), np.uint8), np.zeros((8, 11)), np.eye(3), [])
    with pytest.raises(ValueError, match="depth_scale"):
        BopWriter(tmp_path, depth_scale_mm=0)
    with pytest.raises(ValueError, match="T_cam_model"):
        BopGT(obj_id=1, T_cam_model=np.eye(3))


def test_depth_units_as_stored_and_the_bop_source_hands_them_out_unchanged(tmp_path):
    from pallet6d.runtime.cameras import open_source

    rgb = np.zeros((8, 10, 3), np.uint8)
    depth = np.random.default_rng(0).uniform(0.2, 6.0, (8, 10)).astype(np.float32)
    K = np.diag([100.0, 100.0, 1.0])
    K[:2, 2] = (5.0, 4.0)
    with BopWriter(tmp_path, "val", depth_scale_mm=0.1) as w:
        w.write_frame(0, 0, rgb, depth, K, [])
    stored = cv2.imread(str(tmp_path / "val" / "000000" / "depth" / "000000.png"), cv2.IMREAD_ANYDEPTH)
    frame = BopDataset(tmp_path)[0]
    assert frame.depth_units.dtype == np.uint16
    np.testing.assert_array_equal(frame.depth_units, stored)
    np.testing.assert_array_equal(frame.depth_m, stored.astype(np.float32) * np.float32(0.0001))
    with open_source(f"bop:{tmp_path}") as src:
        f = src.read()
    np.testing.assert_array_equal(f.depth, stored)
    assert f.depth_scale_m == pytest.approx(1e-4) and np.array_equal(f.K, K)


def test_depth_missing_gives_zeros_and_a_float_depth_image_is_refused(bop_copy):
    scene = bop_copy / "train" / "000000"
    (scene / "depth" / "000000.png").unlink()
    frame = BopDataset(bop_copy)[0]
    assert frame.depth_units.dtype == np.uint16 and not frame.depth_units.any() and not frame.depth_m.any()
    cv2.imwrite(str(scene / "depth" / "000000.tif"), np.ones(frame.depth_m.shape, np.float32))
    with pytest.raises(BopFormatError, match="000000.tif.*integer"):
        BopDataset(bop_copy)[0]


def test_ply_mesh_ascii_and_surface_samples(tmp_path):
    from pallet6d.runtime.bop import read_ply_mesh, sample_surface

    path = tmp_path / "square.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n")
    verts, faces = read_ply_mesh(path)
    np.testing.assert_array_equal(verts, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3]])
    pts = sample_surface(verts, faces, 4000, seed=1)
    assert pts.shape == (4000, 3) and np.all(pts[:, 2] == 0) and pts[:, :2].min() >= 0 and pts[:, :2].max() <= 1
    assert abs(pts[:, 0].mean() - 0.5) < 0.03 and abs(pts[:, 1].mean() - 0.5) < 0.03   # uniform over the square


@pytest.mark.parametrize("text, match", [
    ("not a ply", "not a PLY file"),
    ("ply\nformat binary_big_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
     "element face 0\nproperty list uchar int vertex_indices\nend_header\n", "expected float x, y, z"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
     "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 1 2\n", "face index outside"),
])
def test_ply_mesh_refuses_other_layouts(tmp_path, text, match):
    from pallet6d.runtime.bop import read_ply_mesh

    (tmp_path / "m.ply").write_text(text)
    with pytest.raises(BopFormatError, match=match):
        read_ply_mesh(tmp_path / "m.ply")
