"""The depthwise "yolox-nano" detector (`export.detector_dw`): the YOLOv8 detector's outputs and loss from a network
laid out as YOLOX-Nano, and the published network's weights read into it (`export.pretrained_dw`): a graph in the
published layout (BGR 0-255 input, BatchNorm folded, COCO output convs named as published) gives the same maps as
the detector reading RGB in [0, 1]."""
from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.bundle_weights import graph_architecture  # noqa: E402
from pallet6d.export.quantize import INT8_RECIPES, int8_recipe, quantize_graph  # noqa: E402
from pallet6d.export.config import DetectorConfig, get_config  # noqa: E402
from pallet6d.export.detector import YoloDetector, build_detector  # noqa: E402
from pallet6d.export.detector_dw import DW_HEAD_WIDTH, DepthwiseDetector  # noqa: E402
from pallet6d.export.export_inputs import ExportError, trained_architecture  # noqa: E402
from pallet6d.export.losses import DetectorLoss  # noqa: E402
from pallet6d.export.onnx_io import export_graph  # noqa: E402
from pallet6d.export.pretrained_dw import PretrainedError, load_yolox_onnx, stem_for_rgb01  # noqa: E402

DW = dataclasses.replace(get_config("tiny").detector, architecture="yolox-nano", input_hw=(96, 160))


class Published(torch.nn.Module):
    """A network in the published layout: reads BGR 0-255, runs `net`'s convolutions (its stem's kernels taken as
    the published BGR 0-255 ones) and COCO's output convs in the published order, level by level."""

    def __init__(self, net: DepthwiseDetector) -> None:
        super().__init__()
        self.net = net
        self.head = torch.nn.Module()
        for name, c in (("cls_preds", 80), ("reg_preds", 4), ("obj_preds", 1)):
            setattr(self.head, name, torch.nn.ModuleList(torch.nn.Conv2d(DW_HEAD_WIDTH, c, 1) for _ in range(3)))

    def forward(self, bgr255: torch.Tensor) -> torch.Tensor:
        outs = []
        h = self.net.head
        for k, f in enumerate(self.net.neck_outputs(bgr255)):
            x = h.stems[k](f)
            cls = self.head.cls_preds[k](h.cls[k][1](h.cls[k][0](x)))
            r = h.box[k][1](h.box[k][0](x))
            outs.append(torch.cat((self.head.reg_preds[k](r), self.head.obj_preds[k](r), cls), 1).flatten(2))
        return torch.cat(outs, 2)


def _published_graph(tmp_path, seed: int = 0):
    torch.manual_seed(seed)
    source = DepthwiseDetector(DW).eval()
    for p in source.parameters():                  # published-like magnitudes: not the output-bias prior
        p.data.normal_(0.0, 0.1)
    pub = Published(source).eval()
    x = torch.rand(1, 3, *DW.input_hw) * 255
    path = export_graph(pub, (x,), tmp_path / "published.onnx", ["images"], ["output"])
    return source, path


@pytest.mark.parametrize("architecture", ["yolox", "", "YOLOX-nano", None])
def test_an_unknown_architecture_is_refused(architecture):
    with pytest.raises(ValueError, match="architecture"):
        DetectorConfig(architecture=architecture)


@pytest.mark.parametrize("change", [{"activation": "relu"}, {"depth_max_m": 8.0}])
def test_the_depthwise_detector_is_rgb_with_silu_only(change):
    with pytest.raises(ValueError, match="RGB with SiLU only"):
        build_detector(dataclasses.replace(DW, **change))


def test_depthwise_detector_has_the_yolov8_detectors_outputs_and_trains_with_its_loss():
    torch.manual_seed(0)
    dw, v8 = build_detector(DW), build_detector(dataclasses.replace(DW, architecture="yolov8"))
    assert isinstance(dw, DepthwiseDetector) and isinstance(v8, YoloDetector)
    x = torch.rand(2, 3, 128, 224)                                   # not the config's size: fully convolutional
    raw_dw, raw_v8 = dw(x), v8(x)
    assert [r.shape for r in raw_dw] == [r.shape for r in raw_v8]
    dw.eval(), v8.eval()
    with torch.no_grad():
        out = dw(x)
    assert out.shape == v8(x).shape == (2, 4 + len(DW.classes), sum(128 * 224 // s ** 2 for s in (8, 16, 32)))
    assert ((out[:, 4:] >= 0) & (out[:, 4:] <= 1)).all()
    dw.train()
    targets = [torch.tensor([[0.0, 20, 30, 90, 80]]), torch.zeros((0, 5))]
    loss, _ = DetectorLoss(dw)(dw(x), targets)
    loss.backward()
    assert torch.isfinite(loss) and dw.stem.conv.weight.grad.abs().sum() > 0


def test_published_weights_give_the_published_maps_on_rgb_in_0_1(tmp_path):
    source, path = _published_graph(tmp_path)
    net = DepthwiseDetector(DW).eval()
    record = load_yolox_onnx(net, path)
    assert record["convolutions"] == len(net.pretrained_convs()) and len(record["sha256"]) == 64
    rgb01 = torch.rand(2, 3, *DW.input_hw)
    with torch.no_grad():
        ref = source.neck_outputs(rgb01.flip(1) * 255)
        out = net.neck_outputs(rgb01)
        for r, o in zip(ref, out):
            assert torch.allclose(o, r, rtol=1e-4, atol=1e-4 * float(r.abs().max()))
        # the head's branches too; its output convs keep their own initialisation (another box code, 80 classes)
        for k, f in enumerate(out):
            a, b = net.head.stems[k](f), source.head.stems[k](ref[k])
            assert torch.allclose(net.head.cls[k][1](net.head.cls[k][0](a)),
                                  source.head.cls[k][1](source.head.cls[k][0](b)), atol=1e-4)
            assert net.head.cls[k][2].weight.shape[0] == len(DW.classes)


def test_a_graph_of_another_layout_is_refused(tmp_path):
    _, path = _published_graph(tmp_path)
    model = onnx.load(str(path))
    convs = [n for n in model.graph.node if n.op_type == "Conv" and not n.input[1].startswith("head.")]
    model.graph.node.remove(convs[5])                                 # one convolution fewer
    short = tmp_path / "short.onnx"
    onnx.save(model, str(short))
    with pytest.raises(PretrainedError, match="convolutions"):
        load_yolox_onnx(DepthwiseDetector(DW), short)
    with pytest.raises(PretrainedError, match="12 channels"):
        stem_for_rgb01(np.zeros((16, 3, 3, 3), np.float32))


def test_graph_and_checkpoint_say_their_architecture(tmp_path):
    x = (torch.rand(1, 3, *DW.input_hw),)
    dw = export_graph(build_detector(DW).eval(), x, tmp_path / "dw.onnx", ["images"], ["output0"])
    v8 = export_graph(build_detector(dataclasses.replace(DW, architecture="yolov8")).eval(), x, tmp_path / "v8.onnx",
                      ["images"], ["output0"])
    assert graph_architecture(dw) == "yolox-nano" and graph_architecture(v8) == "yolov8"
    assert trained_architecture({"provenance": {"stage": "detector", "architecture": "yolox-nano"}}) == "yolox-nano"
    assert trained_architecture({"provenance": {"stage": "detector"}}) == "yolov8"
    with pytest.raises(ExportError, match="architecture"):
        trained_architecture({"provenance": {"stage": "detector", "architecture": "resnet"}})


def test_int8_keeps_the_depthwise_detectors_stem_and_first_downsampling_float(tmp_path):
    torch.manual_seed(0)
    x = torch.rand(1, 3, *DW.input_hw)
    dw = export_graph(build_detector(DW).eval(), (x,), tmp_path / "dw.onnx", ["images"], ["output0"])
    v8 = export_graph(build_detector(dataclasses.replace(DW, architecture="yolov8")).eval(), (x,),
                      tmp_path / "v8.onnx", ["images"], ["output0"])
    assert int8_recipe("detector", v8) is INT8_RECIPES["detector"]
    recipe = int8_recipe("detector", dw)
    assert recipe is INT8_RECIPES["detector-depthwise"] and int8_recipe("fusion", dw) is INT8_RECIPES["fusion"]
    rng = np.random.default_rng(0)
    feeds = [{"images": rng.random((1, 3, *DW.input_hw), dtype=np.float32)} for _ in range(2)]
    graph = onnx.load(str(quantize_graph(dw, tmp_path / "dw.int8.onnx", feeds, **recipe))).graph
    made_by = {o: n for n in graph.node for o in n.output}
    convs = {n.name: n for n in graph.node if n.op_type == "Conv"}

    def weight_dequantized(conv) -> bool:
        src = made_by.get(conv.input[1])
        return src is not None and src.op_type == "DequantizeLinear"

    assert not weight_dequantized(convs["/stem/conv/Conv"])
    assert not weight_dequantized(convs["/dark2/dark2.0/dconv/conv/Conv"])
    assert weight_dequantized(convs["/dark3/dark3.0/dconv/conv/Conv"])
