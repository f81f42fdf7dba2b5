"""The sampled fusion graph (`sample_stride`: features at the chosen pixels inside the graph), per-type pose
losses for mixed pallet types, warm starts across configs, and the export of a sampled graph."""
from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch")
import torch.nn.functional as F  # noqa: E402

from pallet6d.export.bundle_export import export_bundle  # noqa: E402
from pallet6d.export.calib_data import make_calibration_set  # noqa: E402
from pallet6d.export.config import CONFIGS, FusionConfig, get_config  # noqa: E402
from pallet6d.export.fusion import FusionNet, SampledFusionNet, build_fusion, sample_bilinear  # noqa: E402
from pallet6d.export.losses import pad_symmetries, pose_loss, quat_to_rot, stack_model_points  # noqa: E402
from pallet6d.export.onnx_io import check_parity, export_graph, ort_session  # noqa: E402
from pallet6d.export.train_data import NO_AUGMENT  # noqa: E402
from pallet6d.export.train_pose import PoseTrainer, gather_points, load_pose_data  # noqa: E402
from pallet6d.export.warm_start import transfer_state  # noqa: E402
from pallet6d.runtime.bundle import load_bundle  # noqa: E402
from pallet6d.runtime.geometry import rot_to_quat  # noqa: E402
from pallet6d.sim.pallets import ROT_Z_180, get_pallet_model  # noqa: E402

TINY = get_config("tiny")
# the tiny widths with edge2's fusion structure: no upsampling, no dilation, sampled at stride 8
TINY_SAMPLED = TINY.replace(name="tiny-sampled", fusion=dataclasses.replace(
    TINY.fusion, up_channels=(), dilated=False, sample_stride=8, attention_stride=8))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _inputs(cfg, b: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    h, w = cfg.fusion.crop_hw
    return (torch.randn(b, 3, h, w, generator=g), torch.randn(b, 1, h, w, generator=g),
            torch.randint(0, h * w, (b, cfg.pose.num_points), generator=g))


@pytest.mark.parametrize("stride", [8, 4])
def test_sampling_equals_upsampling_then_gathering(stride):
    torch.manual_seed(0)
    fmap = torch.randn(2, 5, 40 // stride, 48 // stride)
    corners = torch.tensor([[0, 47, 39 * 48, 40 * 48 - 1]] * 2)
    choose = torch.cat((torch.randint(0, 40 * 48, (2, 60)), corners), 1)
    dense = F.interpolate(fmap, scale_factor=float(stride), mode="bilinear", align_corners=False)
    torch.testing.assert_close(sample_bilinear(fmap, choose, (40, 48), stride), gather_points(dense, choose))


def test_configs_pick_the_graph_and_validate_the_sampled_structure():
    assert isinstance(build_fusion(TINY.fusion), FusionNet)
    assert isinstance(build_fusion(TINY_SAMPLED.fusion), SampledFusionNet)
    e2 = CONFIGS["edge2"]
    assert e2.fusion.sampled and not e2.fusion.dilated and e2.fusion.up_channels == ()
    assert e2.pose == CONFIGS["edge"].pose and e2.fusion.resnet_widths == CONFIGS["edge"].fusion.resnet_widths
    assert not any(CONFIGS[n].fusion.sampled for n in ("paper", "edge", "densefusion", "edge-densefusion"))
    e2d, e = CONFIGS["edge2-dilated"].fusion, CONFIGS["edge"].fusion
    assert e2d.sampled and e2d.dilated and e2d.crop_hw == e.crop_hw and e2d.psp_out == e.psp_out
    for plain, verified in (("edge2-dilated", "edge2-verified"), ("edge2-pruned", "edge2-pruned-verified")):
        v, p = CONFIGS[verified], CONFIGS[plain]      # the plain config with a verifier head
        assert v.fusion == p.fusion and v.pose.verifier and not p.pose.verifier
    with pytest.raises(ValueError, match="up_channels must be empty"):
        FusionConfig(crop_hw=(80, 80), sample_stride=8)
    with pytest.raises(ValueError, match="sample_stride must be"):
        FusionConfig(crop_hw=(80, 80), up_channels=(), sample_stride=2)
    with pytest.raises(ValueError, match="three upsampling stages"):
        FusionConfig(crop_hw=(80, 80), up_channels=())
    with pytest.raises(ValueError, match="attention_stride must be 8"):
        FusionConfig(crop_hw=(80, 80), up_channels=(), sample_stride=8, attention_stride=4)


@pytest.mark.parametrize("stride", [8, 4])
def test_sampled_fusion_exports_with_choose_and_matches_torch(tmp_path, stride):
    torch.manual_seed(0)
    cfg = TINY_SAMPLED.replace(fusion=dataclasses.replace(TINY_SAMPLED.fusion, sample_stride=stride))
    net = build_fusion(cfg.fusion).eval()
    names = ["rgb", "depth", "choose"]
    path = export_graph(net, _inputs(cfg, 2), tmp_path / "fusion.onnx", names, ["features"],
                        {n: {0: "batch"} for n in [*names, "features"]})
    model = onnx.load(str(path))
    assert [i.name for i in model.graph.input] == names
    assert model.graph.input[2].type.tensor_type.elem_type == onnx.TensorProto.INT64
    check_parity(net, _inputs(cfg, 3, seed=1), path, names, ["features"])
    sess = ort_session(path, threads=1)
    c, n = cfg.fusion.feature_dim, cfg.pose.num_points
    for b in (0, 1, 5):
        args = _inputs(cfg, b, seed=b)
        with torch.no_grad():
            ref = net(*args).numpy()
        got = sess.run(None, {k: a.numpy() for k, a in zip(names, args)})[0]
        assert ref.shape == got.shape == (b, n, c)
        np.testing.assert_allclose(got, ref, atol=1e-4, rtol=1e-4)


def test_per_type_loss_uses_each_samples_own_symmetries():
    """Two samples predicted 180 degrees off about z: zero loss for the type with that symmetry only."""
    epal = get_pallet_model("epal")
    pm_epal = torch.from_numpy(epal.surface_points(200, seed=0)).double()
    pm_other = pm_epal[:150] * torch.tensor([1.0, 1.2, 1.0], dtype=torch.float64)   # another size, fewer points
    sym_epal = torch.tensor(np.array(epal.symmetries), dtype=torch.float64)    # identity, z 180
    sym_none = torch.eye(4, dtype=torch.float64)[None]                            # no symmetry
    T_gt = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T_gt[:, :3, :3] = quat_to_rot(torch.tensor([[0.9, 0.1, -0.2, 0.3], [0.5, -0.4, 0.1, 0.6]], dtype=torch.float64))
    T_gt[:, :3, 3] = torch.tensor([[0.1, 0.0, 0.0], [-0.2, 0.1, 0.05]], dtype=torch.float64)
    T_pred = T_gt @ torch.from_numpy(ROT_Z_180)
    n = 6
    points = torch.randn(2, n, 3, dtype=torch.float64) * 0.2
    quat = torch.from_numpy(np.stack([rot_to_quat(T[:3, :3]) for T in T_pred.numpy()]))[:, None].expand(2, n, 4)
    trans = T_pred[:, None, :3, 3] - points
    conf = torch.full((2, n), 0.5, dtype=torch.float64)
    model_points = stack_model_points([pm_epal, pm_other])
    symmetries = pad_symmetries([sym_epal, sym_none])
    assert model_points.shape == (2, 200, 3) and symmetries.shape == (2, 2, 4, 4)
    torch.testing.assert_close(symmetries[1, 1], torch.eye(4, dtype=torch.float64))   # padded with identity
    _, d = pose_loss(quat, trans, conf, points, model_points, T_gt, symmetries)
    assert d[0].max() < 1e-6
    assert d[1].min() > 0.3
    # swapping the sets swaps the verdicts
    _, d_swapped = pose_loss(quat, trans, conf, points, stack_model_points([pm_other, pm_epal]), T_gt,
                             pad_symmetries([sym_none, sym_epal]))
    assert d_swapped[0].min() > 0.3 and d_swapped[1].max() < 1e-6
    with pytest.raises(ValueError, match="symmetries must be"):
        pose_loss(quat, trans, conf, points, model_points, T_gt, symmetries[:, :, :3])
    with pytest.raises(ValueError, match="pad_symmetries"):
        pad_symmetries([torch.zeros(0, 4, 4)])


@pytest.fixture(scope="module")
def mixed_dataset(tmp_path_factory):
    """Four small frames whose pallets are of three types (epal, gma, eur3)."""
    from pallet6d.sim.dataset import write_dataset
    from pallet6d.sim.presets import get_preset

    root = tmp_path_factory.mktemp("mixed")
    config = dataclasses.replace(get_preset("virtual-occluded").with_image_size(320, 120),
                                 pallet_models=("epal", "gma", "eur3"))
    write_dataset(config, 4, 3, root, split="train")
    return root


def test_a_mixed_type_batch_trains_the_sampled_network(mixed_dataset, tmp_path):
    data = load_pose_data(TINY_SAMPLED, [mixed_dataset], variants=1, seed=0, aug=NO_AUGMENT,
                          cache_dir=tmp_path, progress=False)
    assert len(set(data.type_names.values())) >= 2
    assert set(np.unique(data.samples.obj_id)) == set(data.type_names)
    torch.manual_seed(0)
    trainer = PoseTrainer(TINY_SAMPLED, data)
    assert trainer.type_points.shape[0] == len(data.type_names)
    idx = np.arange(min(len(data.samples), 8))
    before = [p.detach().clone() for p in trainer.fusion.parameters()]
    opt = torch.optim.Adam([p for net in trainer.nets.values() for p in net.parameters()], lr=1e-3)
    loss, parts = trainer.step(idx, np.random.default_rng(0))
    assert torch.isfinite(loss) and parts["dis"] > 0
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert any(not torch.equal(a, b) for a, b in zip(before, trainer.fusion.parameters()))
    for net in trainer.nets.values():
        net.eval()
    with torch.no_grad():
        val = trainer.validate(batch=4)
    assert val["n"] == len(data.val_idx) and np.isfinite(val["metric"])


def test_warm_start_copies_what_fits_and_resizes_the_position_grid():
    torch.manual_seed(0)
    dense = build_fusion(TINY.fusion)
    wide = TINY_SAMPLED.replace(fusion=dataclasses.replace(TINY_SAMPLED.fusion, crop_hw=(48, 48)))
    sampled = build_fusion(wide.fusion)
    record = transfer_state(dense.state_dict(), sampled)
    src, dst = dense.state_dict(), sampled.state_dict()
    torch.testing.assert_close(dst["rgb.backbone.layer4.1.conv2.weight"], src["rgb.backbone.layer4.1.conv2.weight"])
    torch.testing.assert_close(dst["attention.qkv.weight"], src["attention.qkv.weight"])
    assert record["resized"] == ["pos"] and dst["pos"].shape == (1, 36, TINY.fusion.feature_dim)
    assert set(record["new"]) == {"rgb.final.weight", "depth.final.weight"}   # psp_out inputs now, not up_channels
    assert record["copied"] == len(dst) - 3


def test_export_writes_the_sampled_graph_and_its_choose_input(tmp_path):
    calib = make_calibration_set(TINY_SAMPLED, frames=2, max_crops=8, seed=0, synthetic=True)
    exported = export_bundle(TINY_SAMPLED, tmp_path / "b", random_init=True, int8=True, calib=calib, command="test")
    assert exported.manifest.fusion.choose_input == "choose"
    assert load_bundle(tmp_path / "b").fusion.feature_dim == TINY_SAMPLED.fusion.feature_dim
    n, c = TINY_SAMPLED.pose.num_points, TINY_SAMPLED.fusion.feature_dim
    for name in ("fusion.onnx", "fusion.int8.onnx"):
        sess = ort_session(tmp_path / "b" / name, threads=1)
        assert [i.name for i in sess.get_inputs()] == ["rgb", "depth", "choose"]
        feeds = {"rgb": calib.rgb_crops[:3], "depth": calib.depth_crops[:3], "choose": calib.choose[:3]}
        out = sess.run(None, feeds)[0]
        assert out.shape == (3, n, c) and np.isfinite(out).all()
    dense = export_bundle(TINY, tmp_path / "d", random_init=True, calib=make_calibration_set(
        TINY, frames=2, max_crops=8, seed=0, synthetic=True), command="test")
    assert dense.manifest.fusion.choose_input is None


def test_trained_pallet_types_come_from_the_pose_provenance():
    from pallet6d.export.pallet_types import trained_pallet_models, trained_pallet_types

    pose = {"stage": "pose", "pallet_types": {"3": "eur3", "1": "epal", "2": "gma"}}
    assert trained_pallet_types(pose, "epal") == ("epal", "gma", "eur3")
    assert trained_pallet_types({"detector": {}, "pose": pose}, "epal") == ("epal", "gma", "eur3")
    assert trained_pallet_types(None, "epal") == ("epal",)
    assert trained_pallet_types({"stage": "pose"}, "gma") == ("gma",)
    assert [m.name for m in trained_pallet_models(pose, "epal")] == ["epal", "gma", "eur3"]
    with pytest.raises(ValueError, match="unknown pallet model"):
        trained_pallet_types({"pallet_types": {"1": "crate"}}, "epal")


def test_a_sampled_bundle_reads_back_into_torch(tmp_path, monkeypatch):
    from pallet6d.export.bundle_weights import load_bundle_weights
    from pallet6d.export.pose import build_pose

    monkeypatch.setitem(CONFIGS, TINY_SAMPLED.name, TINY_SAMPLED)
    calib = make_calibration_set(TINY_SAMPLED, frames=2, max_crops=8, seed=0, synthetic=True)
    export_bundle(TINY_SAMPLED, tmp_path / "b", random_init=True, calib=calib, command="test")
    torch.manual_seed(1)
    nets = {"fusion": build_fusion(TINY_SAMPLED.fusion), "pose": build_pose(TINY_SAMPLED.pose, 16)}
    record = load_bundle_weights(tmp_path / "b", nets, calib_frames=2)
    assert set(record["parity"]) == {"fusion", "pose"}


def test_the_estimator_runs_a_sampled_bundle(tmp_path):
    """The runtime feeds `choose` to a fusion graph that samples its own features (`fusion.choose_input`)."""
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    calib = make_calibration_set(TINY_SAMPLED, frames=2, max_crops=8, seed=0, synthetic=True)
    export_bundle(TINY_SAMPLED, tmp_path / "b", random_init=True, calib=calib, command="test")
    frame = generate_frame(get_preset("virtual-clean").with_image_size(320, 120), seed=0)
    est = PalletEstimator.from_bundle(tmp_path / "b", threads=1, score_threshold=0.0, min_fit=0.0, structure=None)
    x, y, w, h = frame.pallet(frame.target_instance).bbox_visib_xywh
    result = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=[[x, y, x + w, y + h]])
    assert len(result.poses) + len(result.rejected) == 1
    assert all(np.all(np.isfinite(p.T_cam_pallet)) for p in result.poses)
