"""Export side: network shapes per config, losses, ONNX export parity, int8, external detectors, FLOP count."""
import dataclasses

import numpy as np
import pytest
import torch

from pallet6d.export.bundle_export import ExportError, export_bundle
from pallet6d.export.calib_data import make_calibration_set
from pallet6d.export.config import CONFIGS, DetectorConfig, FusionConfig, PoseConfig, get_config
from pallet6d.export.detector import build_detector
from pallet6d.export.flops import count_gflops
from pallet6d.export.fusion import build_fusion
from pallet6d.export.pallet_types import class_ids_for_types
from pallet6d.export.losses import DetectorLoss, pose_loss
from pallet6d.export.onnx_io import export_graph
from pallet6d.export.pose import build_pose
from pallet6d.runtime.bundle import BundleError, check_bundle, load_bundle
from pallet6d.sim.pallets import get_pallet_model


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def shrink(cfg):
    """Same structure (attention on/off, strides, crop, N) at tiny widths."""
    f, p = cfg.fusion, cfg.pose
    return cfg.replace(
        detector=DetectorConfig(scale="custom", depth_multiple=0.33, width_multiple=0.0625, max_channels=64,
                                input_hw=(64, 96)),
        fusion=dataclasses.replace(f, resnet_widths=(8, 8, 16, 16), psp_out=16, up_channels=(8, 8, 8), branch_dim=4,
                                   attention_heads=2),
        pose=dataclasses.replace(p, point_dims=(8, 8), global_dims=(16, 16), head_dims=(16, 8, 8), attention_heads=2))


@pytest.mark.parametrize("name", ["paper", "edge", "densefusion"])
def test_forward_shapes_per_config(name):
    torch.manual_seed(0)
    cfg = shrink(get_config(name))
    det, fus, pose = build_detector(cfg.detector).eval(), build_fusion(cfg.fusion).eval(), \
        build_pose(cfg.pose, cfg.fusion.feature_dim).eval()
    h, w = cfg.fusion.crop_hw
    n = cfg.pose.num_points
    with torch.no_grad():
        out = det(torch.rand(1, 3, 64, 96))
        feats = fus(torch.randn(2, 3, h, w), torch.randn(2, 1, h, w))
        quat, trans, conf = pose(torch.randn(2, n, 3) * 0.3, torch.randn(2, n, cfg.fusion.feature_dim))
    assert out.shape == (1, 5, (8 * 12) + (4 * 6) + (2 * 3))
    assert (out[:, 4] >= 0).all() and (out[:, 4] <= 1).all() and (out[:, 2:4] > 0).all()
    assert feats.shape == (2, 2 * 4, h, w)
    assert quat.shape == (2, n, 4) and trans.shape == (2, n, 3) and conf.shape == (2, n)
    torch.testing.assert_close(quat.norm(dim=-1), torch.ones(2, n))
    assert ((conf > 0) & (conf < 1)).all()
    assert (fus.attention is not None) == (name != "densefusion") == (pose.attention is not None)


def test_configs_are_as_documented_and_validated():
    assert CONFIGS["paper"].fusion.crop_hw == (120, 120) and CONFIGS["paper"].pose.num_points == 500
    assert CONFIGS["paper"].fusion.resnet_widths == (64, 128, 256, 512)
    assert CONFIGS["densefusion"].fusion.attention is False and CONFIGS["densefusion"].pose.attention is False
    assert CONFIGS["edge"].pose.num_points == 256 and CONFIGS["edge"].detector.scale == "n"
    with pytest.raises(ValueError, match="multiples of 32"):
        DetectorConfig(input_hw=(100, 640))
    with pytest.raises(ValueError, match="multiples of 8"):
        FusionConfig(crop_hw=(100, 100))
    with pytest.raises(ValueError, match="attention_stride"):
        FusionConfig(crop_hw=(120, 120), attention_stride=16)
    with pytest.raises(ValueError, match="positive"):
        PoseConfig(num_points=0)
    with pytest.raises(ValueError, match="unknown config"):
        get_config("huge")


def _rz(deg):
    a = np.deg2rad(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def test_pose_loss_symmetry_aware():
    pallet = get_pallet_model("epal")
    pm = torch.from_numpy(pallet.surface_points(300, seed=0)).double()
    T_gt = torch.from_numpy(_rz(30.0) @ np.diag([1.0, -1.0, -1.0, 1.0])).double()  # some rotation
    T_gt[:3, 3] = torch.tensor([0.1, -0.2, 0.05])
    T_flip = T_gt @ torch.from_numpy(_rz(180.0))                                     # same pallet, turned 180 deg about z
    n = 8
    points = torch.randn(1, n, 3, dtype=torch.float64) * 0.2
    from pallet6d.runtime.geometry import rot_to_quat
    q = torch.from_numpy(rot_to_quat(T_flip[:3, :3].numpy())).expand(1, n, 4)
    trans = T_flip[:3, 3].expand(1, n, 3) - points
    conf = torch.full((1, n), 0.9, dtype=torch.float64)
    sym = torch.from_numpy(np.array(pallet.symmetries))
    loss_sym, d_sym = pose_loss(q, trans, conf, points, pm, T_gt[None], sym)
    loss_plain, d_plain = pose_loss(q, trans, conf, points, pm, T_gt[None], None)
    assert d_sym.max() < 1e-6
    assert d_plain.min() > 0.3          # the flipped pallet's points are ~0.5 m off on average
    # eq. 4: exactly d*c - w log c averaged
    assert abs(float(loss_sym) - (-0.015 * np.log(0.9))) < 1e-6
    assert float(loss_plain) == pytest.approx(float((d_plain * 0.9).mean()) - 0.015 * np.log(0.9), rel=1e-6)
    # a translation error of 5 cm gives d = 5 cm with or without symmetries
    _, d_off = pose_loss(q, trans + torch.tensor([0.05, 0, 0], dtype=torch.float64), conf, points, pm, T_gt[None], sym)
    torch.testing.assert_close(d_off, torch.full((1, n), 0.05, dtype=torch.float64))


def test_pose_loss_trains_confidence_and_rejects_bad_shapes():
    q = torch.tensor([[[1.0, 0, 0, 0]]])
    with pytest.raises(ValueError, match="do not agree"):
        pose_loss(q, torch.zeros(1, 1, 3), torch.ones(1, 2), torch.zeros(1, 1, 3), torch.zeros(5, 3), torch.eye(4)[None])


def test_detector_loss_decreases_when_overfitting():
    torch.manual_seed(0)
    cfg = DetectorConfig(scale="custom", depth_multiple=0.33, width_multiple=0.0625, max_channels=64, input_hw=(64, 128))
    model = build_detector(cfg)
    model.train()
    crit = DetectorLoss(model)
    imgs = torch.rand(2, 3, 64, 128) * 0.2
    imgs[0, :, 10:40, 20:80] = 0.9
    imgs[1, :, 30:60, 60:120] = 0.9
    targets = [torch.tensor([[0, 20.0, 10.0, 80.0, 40.0]]), torch.tensor([[0, 60.0, 30.0, 120.0, 60.0]])]
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(20):
        loss, parts = crit(model(imgs), targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert parts["fg"] > 0
    assert np.isfinite(losses).all() and losses[-1] < 0.5 * losses[0], losses
    # no targets at all is a valid batch (background only)
    loss, parts = crit(model(imgs), [torch.zeros(0, 5), torch.zeros(0, 5)])
    assert parts["fg"] == 0 and np.isfinite(float(loss.detach()))


def test_flop_count_matches_hand_count(tmp_path):
    conv = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, padding=1), torch.nn.Flatten(), torch.nn.Linear(8 * 16 * 16, 10))
    path = export_graph(conv, (torch.zeros(1, 3, 16, 16),), tmp_path / "m.onnx", ["x"], ["y"], {"x": {0: "b"}})
    expected = 2 * (8 * 16 * 16 * 3 * 9 + 8 * 16 * 16 * 10) / 1e9
    assert count_gflops(path) == pytest.approx(expected, rel=1e-9)


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory):
    cfg = get_config("tiny")
    out = tmp_path_factory.mktemp("b") / "tiny"
    calib = make_calibration_set(cfg, frames=4, max_crops=16, seed=0, synthetic=True)
    exported = export_bundle(cfg, out, seed=0, random_init=True, int8=True, calib=calib, command="test")
    return out, exported.report, calib


def test_export_parity_and_manifest(tiny_bundle):
    out, report, _ = tiny_bundle
    assert check_bundle(out) == []
    par = report["checks"]["parity"]
    for stage, outputs in (("detector", ["output0"]), ("fusion", ["features"]), ("pose", ["quat", "trans", "conf"])):
        for o in outputs:
            assert par[stage][o]["max_abs"] <= 1e-4 * max(1.0, par[stage][o]["ref_max_abs"])
    b = load_bundle(out)
    assert b.precision == ("fp32", "int8") and b.provenance["random_init"] is True
    assert "synthetic" in b.provenance["calibration"]
    assert b.pose_input_spec().num_points == 32 and b.fusion.crop_hw == (32, 32)
    assert all(v > 0 for v in report["checks"]["gflops"].values())
    # by default the float graphs keep int8 weights on disk (stored after int8 quantization, checked against float32)
    small = report["checks"]["weights_int8"]
    for stage in ("detector", "fusion", "pose"):
        assert small[stage]["converted"] > 0 and small[stage]["bytes_after"] < small[stage]["bytes_before"]
        assert all(d["rel_rms"] <= small[stage]["limit_rel_rms"] for d in small[stage]["vs_fp32_weights"].values())
        assert small[stage]["bytes_after"] == (out / f"{stage}.onnx").stat().st_size
    assert not list(out.glob("*-weights.onnx"))


def test_int8_graphs_run_and_correlate(tiny_bundle):
    out, report, calib = tiny_bundle
    from pallet6d.export.onnx_io import ort_session, run_session
    b = load_bundle(out)
    feeds = {"rgb": calib.rgb_crops[:4], "depth": calib.depth_crops[:4]}
    f32 = run_session(ort_session(b.graph("fusion")), feeds)["features"]
    f8 = run_session(ort_session(b.graph("fusion", "int8")), feeds)["features"]
    assert f8.shape == f32.shape and np.corrcoef(f32.ravel(), f8.ravel())[0, 1] > 0.9
    for stage, o in (("detector", "output0"), ("fusion", "features")):
        assert report["checks"]["int8"][stage][o]["corr"] > 0.9, (stage, report["checks"]["int8"][stage])
    # by default the pose net is not quantized: precision int8 runs its float graph
    assert b.graph("pose", "int8") == b.graph("pose") and not (out / "pose.int8.onnx").exists()
    assert report["checks"]["int8"]["pose"] == "float graph (not quantized)"


def test_int8_stages_choose_what_is_quantized(tmp_path, tiny_bundle):
    calib = tiny_bundle[2]
    report = export_bundle(get_config("tiny"), tmp_path / "all", random_init=True, int8=True, calib=calib,
                           int8_stages=("detector", "fusion", "pose")).report
    b = load_bundle(tmp_path / "all")
    assert b.graph("pose", "int8").name == "pose.int8.onnx"
    for o in ("quat", "trans"):
        assert report["checks"]["int8"]["pose"][o]["corr"] > 0.9, report["checks"]["int8"]["pose"]
    with pytest.raises(ExportError, match="int8 stages"):
        export_bundle(get_config("tiny"), tmp_path / "bad", random_init=True, int8=True, calib=calib,
                      int8_stages=("pose", "refine"))


def test_export_refuses_bad_arguments(tmp_path, tiny_bundle):
    cfg = get_config("tiny")
    with pytest.raises(ExportError, match="exactly one"):
        export_bundle(cfg, tmp_path / "x", random_init=False)
    with pytest.raises(ExportError, match="not empty"):
        export_bundle(cfg, tiny_bundle[0], random_init=True)
    bad = tmp_path / "ckpt.pt"
    torch.save({"config": "tiny", "fusion": {}}, bad)
    with pytest.raises(ExportError, match="no 'detector' weights"):
        export_bundle(cfg, tmp_path / "y", checkpoint=bad, calib=tiny_bundle[2])


def test_pallet_types_follow_the_pose_training(tmp_path, tiny_bundle):
    """Without --pallet-types a bundle carries the types its pose stage was trained on, where the detector has a
    class for each or one class for all (the runtime tells them apart by the depth)."""
    cfg = get_config("tiny")
    torch.manual_seed(2)
    nets = {"detector": build_detector(cfg.detector), "fusion": build_fusion(cfg.fusion),
            "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}
    prov = {"pose": {"stage": "pose", "pallet_types": {"2": "gma", "1": "epal"}}}
    torch.save({"config": "tiny", "provenance": prov, **{k: v.state_dict() for k, v in nets.items()}},
               tmp_path / "ckpt.pt")
    b = export_bundle(cfg, tmp_path / "one", checkpoint=tmp_path / "ckpt.pt", calib=tiny_bundle[2]).bundle
    assert [(t.name, t.class_id) for t in b.pallet_types] == [("epal", 0), ("gma", 0)]
    # types the pose stage was not trained on, asked for by name, share the checkpoint's one detector class
    b = export_bundle(cfg, tmp_path / "asked", checkpoint=tmp_path / "ckpt.pt", calib=tiny_bundle[2],
                      pallet_types=("gma", "eur6", "epal")).bundle
    assert [(t.name, t.class_id) for t in b.pallet_types] == [("gma", 0), ("eur6", 0), ("epal", 0)]
    with pytest.raises(ExportError, match="detector has 2 classes"):
        class_ids_for_types(("epal", "gma", "eur3"), ("epal", "gma"), external=False)
    assert class_ids_for_types(("epal", "gma"), ("epal", "gma"), external=False) == (0, 1)
    prov["pose"]["pallet_types"]["3"] = "crate"
    torch.save({"config": "tiny", "provenance": prov, **{k: v.state_dict() for k, v in nets.items()}},
               tmp_path / "ckpt.pt")
    with pytest.raises(ExportError, match="trained on a pallet type without a model.*crate"):
        export_bundle(cfg, tmp_path / "three", checkpoint=tmp_path / "ckpt.pt", calib=tiny_bundle[2])


def test_export_cli_refuses_unknown_pallet_types(tmp_path, capsys):
    from pallet6d.runtime import cli

    assert cli.main(["export", "--config", "tiny", "--random-init", "--pallet-types", "epal,chep",
                     "--out", str(tmp_path / "x")]) == 1
    assert "unknown pallet type(s) ['chep']" in capsys.readouterr().err and not (tmp_path / "x").exists()
    assert cli.main(["export", "--config", "tiny", "--random-init", "--pallet-types", "epal,epal",
                     "--out", str(tmp_path / "x")]) == 1
    assert "named twice" in capsys.readouterr().err


def test_export_cli_num_points_sets_the_graphs_and_manifest(tmp_path, capsys):
    import onnxruntime as ort

    from pallet6d.runtime import cli

    out = tmp_path / "n24"
    assert cli.main(["export", "--config", "tiny", "--random-init", "--torch-threads", "1", "--calib-frames", "2",
                     "--num-points", "24", "--out", str(out)]) == 0
    bundle = load_bundle(out)
    assert bundle.manifest.pose.num_points == 24 != get_config("tiny").pose.num_points
    shapes = {i.name: i.shape for i in ort.InferenceSession(str(out / "pose.onnx")).get_inputs()}
    assert shapes["points"][1:] == [24, 3]
    assert cli.main(["export", "--config", "tiny", "--random-init", "--num-points", "0",
                     "--out", str(tmp_path / "n0")]) == 1
    assert "--num-points must be a positive integer, got 0" in capsys.readouterr().err


def test_checkpoint_round_trip_and_external_detector(tmp_path, tiny_bundle):
    cfg = get_config("tiny")
    torch.manual_seed(1)
    nets = {"detector": build_detector(cfg.detector), "fusion": build_fusion(cfg.fusion),
            "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}
    torch.save({"config": "tiny", **{k: v.state_dict() for k, v in nets.items()}}, tmp_path / "ckpt.pt")
    calib = tiny_bundle[2]
    export_bundle(cfg, tmp_path / "from_ckpt", checkpoint=tmp_path / "ckpt.pt", calib=calib)
    assert check_bundle(tmp_path / "from_ckpt") == []
    # a YOLOv8-layout graph made elsewhere drops in as the detector (2 classes, named on the command line)
    ext_cfg = DetectorConfig(scale="custom", depth_multiple=0.33, width_multiple=0.0625, max_channels=64,
                             input_hw=(64, 96), classes=("pallet", "box"))
    ext = export_graph(build_detector(ext_cfg).eval(), (torch.rand(1, 3, 64, 96),), tmp_path / "yolo.onnx",
                       ["images"], ["output0"])
    m = export_bundle(cfg, tmp_path / "ext", random_init=True, detector_onnx=ext, classes=("pallet", "box"),
                      calib=calib).manifest
    assert m.detector.source == "external" and m.detector.input_hw == (64, 96)
    assert m.classes == ("pallet", "box") and check_bundle(tmp_path / "ext") == []
    # the one pallet type is the "pallet" class; "box" reports no type
    b = load_bundle(tmp_path / "ext")
    assert b.pallet_class_ids == (0,) and b.pallet.name == "epal"
    with pytest.raises(BundleError, match="class 1 \\('box'\\) is no pallet type"):
        b.pallet_type_for_class(1)
    with pytest.raises(ExportError, match="2 classes but 1 names"):
        export_bundle(cfg, tmp_path / "ext2", random_init=True, detector_onnx=ext, classes=("pallet",), calib=calib)
    with pytest.raises(ExportError, match="expected one input"):
        export_bundle(cfg, tmp_path / "ext3", random_init=True, detector_onnx=tiny_bundle[0] / "fusion.onnx",
                      classes=("pallet",), calib=calib)
    not_yolo = export_graph(torch.nn.Conv2d(3, 5, 3, stride=8), (torch.rand(1, 3, 64, 96),), tmp_path / "c.onnx",
                            ["images"], ["output0"])
    with pytest.raises(ExportError, match="not the YOLOv8 layout"):
        export_bundle(cfg, tmp_path / "ext4", random_init=True, detector_onnx=not_yolo, classes=("pallet",), calib=calib)


def test_quaternion_convention_matches_runtime_geometry():
    from pallet6d.export.losses import quat_to_rot
    from pallet6d.runtime.geometry import quat_to_rot as np_quat_to_rot
    q = np.random.default_rng(0).standard_normal((5, 4))
    np.testing.assert_allclose(quat_to_rot(torch.from_numpy(q)).numpy(), np_quat_to_rot(q), atol=1e-12)


def test_detector_output_is_cxcywh_pixels_of_each_anchor():
    """Force every side's DFL distribution onto bin k: each anchor's box is then centred on the anchor
    with width = height = 2 k stride, and scores = sigmoid(class bias), in the YOLOv8 layout."""
    torch.manual_seed(0)
    cfg = DetectorConfig(scale="custom", depth_multiple=0.33, width_multiple=0.0625, max_channels=64, input_hw=(64, 96))
    det = build_detector(cfg).eval()
    k = 3
    with torch.no_grad():
        for box, cls in zip(det.head.box, det.head.cls):
            box[-1].weight.zero_()
            bias = torch.full((4, cfg.reg_max), -50.0)
            bias[:, k] = 50.0
            box[-1].bias.copy_(bias.flatten())
            cls[-1].weight.zero_()
            cls[-1].bias.fill_(0.0)
        out = det(torch.rand(1, 3, 64, 96))[0]
    centres, sizes = [], []
    for s in (8, 16, 32):
        ys, xs = np.mgrid[0:64 // s, 0:96 // s]
        centres.append(np.stack([(xs.ravel() + 0.5) * s, (ys.ravel() + 0.5) * s]))
        sizes.append(np.full(xs.size, 2 * k * s, float))
    np.testing.assert_allclose(out[:2].numpy(), np.concatenate(centres, 1), atol=1e-4)
    np.testing.assert_allclose(out[2].numpy(), np.concatenate(sizes), atol=1e-4)
    np.testing.assert_allclose(out[3].numpy(), np.concatenate(sizes), atol=1e-4)
    np.testing.assert_allclose(out[4].numpy(), 0.5, atol=1e-6)


def test_parity_failure_stops_the_export(tmp_path):
    from pallet6d.export.onnx_io import ParityError, check_parity
    torch.manual_seed(0)
    a, b = torch.nn.Conv2d(3, 4, 3), torch.nn.Conv2d(3, 4, 3)
    x = (torch.rand(1, 3, 8, 8),)
    path = export_graph(a, x, tmp_path / "a.onnx", ["x"], ["y"])
    assert check_parity(a, x, path, ["x"], ["y"])["y"]["max_abs"] < 1e-5
    with pytest.raises(ParityError, match="does not reproduce"):
        check_parity(b, x, path, ["x"], ["y"])


def test_calibration_crops_come_from_the_presets_in_turn():
    # an indoor frame holds one pallet, a cluttered virtual one several: taking crops in turn gives each
    # preset its share, and the held-out last quarter (the int8 report) still mixes them
    presets = ("virtual-occluded", "indoor-noisy", "virtual-clean")
    calib = make_calibration_set(get_config("tiny"), frames=6, max_crops=5, seed=0, presets=presets)
    assert len(calib.rgb_crops) == len(calib.points) == len(calib.crop_sources) == 5
    assert set(calib.crop_sources[:3]) == set(presets)
    assert max(calib.crop_sources.count(p) for p in presets) - min(calib.crop_sources.count(p) for p in presets) <= 1
    assert calib.images.shape[0] == 6 and "5 ground-truth crops" in calib.source


def test_export_refuses_unknown_calibration_presets(tmp_path):
    with pytest.raises(ExportError, match=r"unknown calibration preset\(s\) \['attic'\]"):
        export_bundle(get_config("tiny"), tmp_path / "x", random_init=True, int8=True,
                      calib_presets=("indoor-noisy", "attic"))
    assert not (tmp_path / "x").exists()
