"""A ReLU detector (`DetectorConfig.activation`, `pallet6d train detector --detector-activation relu`): the same
layers as YOLOv8's SiLU detector, so it starts from a SiLU detector's weights (a checkpoint or a bundle's graph)
and can learn from it as a teacher (`--distill`); its int8 graph folds the ReLU into the convolutions; export
builds the activation the checkpoint was trained with."""
from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.bundle_weights import (bundle_checkpoint, detector_activation_of, graph_activation,  # noqa: E402
                                            load_bundle_weights)
from pallet6d.export.config import DetectorConfig, get_config  # noqa: E402
from pallet6d.export.detector import build_detector  # noqa: E402
from pallet6d.export.export_inputs import ExportError, trained_activation  # noqa: E402
from pallet6d.export.onnx_io import export_graph, ort_session, run_session  # noqa: E402
from pallet6d.export.quantize import INT8_RECIPES, quantize_graph  # noqa: E402
from pallet6d.export.losses import detector_distill_loss  # noqa: E402
from pallet6d.export.train_loop import CKPT_FORMAT, LoopSettings, load_checkpoint  # noqa: E402

CFG = get_config("tiny")


def _relu(cfg: DetectorConfig = CFG.detector) -> DetectorConfig:
    return dataclasses.replace(cfg, activation="relu")


@pytest.mark.parametrize("activation", ["gelu", "", "ReLU", None])
def test_an_unknown_activation_is_refused(activation):
    with pytest.raises(ValueError, match="activation"):
        DetectorConfig(activation=activation)


def test_relu_detector_has_silus_layers_and_no_silu():
    silu, relu = build_detector(CFG.detector), build_detector(_relu())
    assert not any(isinstance(m, torch.nn.SiLU) for m in relu.modules())
    assert sum(isinstance(m, torch.nn.ReLU) for m in relu.modules()) == sum(
        isinstance(m, torch.nn.SiLU) for m in silu.modules()) > 0
    relu.load_state_dict(silu.state_dict())     # every weight fits: it can start from a SiLU detector


def test_relu_int8_graph_folds_the_activation_and_follows_fp32(tmp_path):
    torch.manual_seed(0)
    net = build_detector(_relu()).eval()
    h, w = CFG.detector.input_hw
    rng = np.random.default_rng(0)
    images = [rng.random((1, 3, h, w), dtype=np.float32) for _ in range(4)]
    fp32 = export_graph(net, (torch.from_numpy(images[0]),), tmp_path / "det.onnx", ["images"], ["output0"])
    assert graph_activation(fp32) == "relu"
    int8 = quantize_graph(fp32, tmp_path / "det.int8.onnx", [{"images": x} for x in images],
                          **INT8_RECIPES["detector"])
    ops = [n.op_type for n in onnx.load(str(int8)).graph.node]
    assert "Relu" not in ops and "DequantizeLinear" in ops
    ref = run_session(ort_session(fp32), {"images": images[1]})["output0"]
    out = run_session(ort_session(int8), {"images": images[1]})["output0"]
    boxes_ref, boxes = ref[:, :4], out[:, :4]
    assert np.median(np.abs(boxes - boxes_ref)) < 0.05 * max(h, w)


def test_a_relu_detector_starts_from_a_silu_bundles_weights(bundle_dir):
    assert graph_activation(bundle_dir / "detector.onnx") == "silu"
    assert detector_activation_of(bundle_dir) == "silu" and detector_activation_of(None) == "silu"
    silu, relu = build_detector(CFG.detector), build_detector(_relu())
    load_bundle_weights(bundle_dir, {"detector": silu}, calib_frames=1)
    record = load_bundle_weights(bundle_dir, {"detector": relu}, calib_frames=1)
    assert record["activation"] == {"graph": "silu", "network": "relu"}
    ref = silu.state_dict()
    assert all(torch.equal(v, ref[k]) for k, v in relu.state_dict().items())
    # a bundle's detector as a checkpoint records the activation its graph has
    assert bundle_checkpoint(bundle_dir, "detector")["provenance"]["activation"] == "silu"


@pytest.mark.parametrize("provenance, expected", [
    ({"stage": "detector", "activation": "relu"}, "relu"),
    ({"stage": "detector"}, "silu"),                          # trained before the option: YOLOv8's
    ({"stage": "merged", "detector": {"activation": "relu"}}, "relu"),
])
def test_export_builds_the_activation_the_checkpoint_was_trained_with(provenance, expected):
    assert trained_activation({"provenance": provenance}) == expected


def test_a_checkpoint_with_an_unknown_activation_is_a_clear_error(tmp_path):
    with pytest.raises(ExportError, match="activation 'tanh'"):
        trained_activation({"provenance": {"stage": "detector", "activation": "tanh"}})
    # as an --init or --distill path too, before any weights are loaded into a network of a guessed activation
    torch.save({"format": CKPT_FORMAT, "provenance": {"stage": "detector", "activation": "tanh"}}, tmp_path / "d.pt")
    with pytest.raises(ExportError, match="activation 'tanh'"):
        detector_activation_of(tmp_path / "d.pt")
    with pytest.raises(ValueError, match="no checkpoint"):
        detector_activation_of(tmp_path / "missing.pt")


def test_distillation_is_zero_where_the_student_computes_what_the_teacher_does():
    torch.manual_seed(0)
    net = build_detector(CFG.detector).eval()
    h, w = CFG.detector.input_hw
    x = torch.rand(2, 3, h, w)
    with torch.no_grad():
        ref = net.forward_raw(x)
    cls, box = detector_distill_loss(ref, ref, net.head.reg_max)
    assert abs(float(cls)) < 1e-5 and abs(float(box)) < 1e-5
    student = build_detector(_relu())
    student.load_state_dict(net.state_dict())
    cls, box = detector_distill_loss(student.forward_raw(x), ref, net.head.reg_max)
    assert float(cls.detach()) > 0 and float(box.detach()) > 0
    (cls + box).backward()
    assert student.stem.conv.weight.grad.abs().sum() > 0


def test_a_relu_detector_trains_from_and_against_a_silu_bundle(bundle_dir, sim_bop_dataset, tmp_path):
    from pallet6d.export.train_detector import train_detector

    entry = train_detector(dataclasses.replace(CFG, detector=_relu()), [sim_bop_dataset], tmp_path / "det",
                           LoopSettings(epochs=1, batch=2, lr=1e-3), progress=False, init=bundle_dir,
                           distill=bundle_dir, distill_weight=2.0)
    assert entry["train_distill_cls"] >= 0 and entry["train_distill_box"] >= 0
    ckpt = load_checkpoint(tmp_path / "det" / "last.pt")
    prov = ckpt["provenance"]
    assert prov["activation"] == "relu" and trained_activation(ckpt) == "relu"
    assert prov["distill"]["weight"] == 2.0 and prov["distill"]["activation"] == "silu"
    assert prov["distill"]["weights"]["bundle"] == str(bundle_dir)
    assert detector_activation_of(tmp_path / "det" / "last.pt") == "relu"
    with pytest.raises(ValueError, match="distill_weight"):
        train_detector(CFG, [sim_bop_dataset], tmp_path / "bad", LoopSettings(epochs=1, batch=2, lr=1e-3),
                       progress=False, distill=bundle_dir, distill_weight=0.0)
