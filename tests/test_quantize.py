"""Static int8 quantization recipes: which nodes become int8, which stay float, outputs close to fp32."""
import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from pallet6d.export.quantize import CONV_OPS, DETECTOR_OPS, _downstream, quantize_graph  # noqa: E402


def _tiny_detector(path):
    """conv -> SiLU (Sigmoid, Mul) -> output conv "head" -> decoding (Softmax, Mul)."""
    rng = np.random.default_rng(0)
    inits = [numpy_helper.from_array(rng.normal(0, 0.3, (8, 3, 3, 3)).astype(np.float32), "w1"),
             numpy_helper.from_array(rng.normal(0, 0.3, (4, 8, 1, 1)).astype(np.float32), "w2")]
    nodes = [helper.make_node("Conv", ["x", "w1"], ["c1"], name="/stem/Conv", pads=[1, 1, 1, 1]),
             helper.make_node("Sigmoid", ["c1"], ["s1"], name="/stem/Sigmoid"),
             helper.make_node("Mul", ["c1", "s1"], ["a1"], name="/stem/Mul"),
             helper.make_node("Conv", ["a1", "w2"], ["logits"], name="/head/Conv"),
             helper.make_node("Softmax", ["logits"], ["probs"], name="/decode/Softmax", axis=1),
             helper.make_node("Mul", ["probs", "logits"], ["y"], name="/decode/Mul")]
    graph = helper.make_graph(nodes, "tiny", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 16, 16])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 16, 16])], inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    return path


def _feeds(n=6):
    rng = np.random.default_rng(1)
    return [{"x": rng.random((1, 3, 16, 16), dtype=np.float32)} for _ in range(n)]


def _quantized_outputs(path):
    """Tensor names that a QuantizeLinear node quantizes."""
    return {n.input[0] for n in onnx.load(str(path)).graph.node if n.op_type == "QuantizeLinear"}


def _run(path, x):
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]


def test_detector_recipe_quantizes_the_graph_up_to_the_heads(tmp_path):
    fp32 = _tiny_detector(tmp_path / "det.onnx")
    graph = onnx.load(str(fp32)).graph
    assert _downstream(graph, ("/head/Conv",)) == ["/decode/Softmax", "/decode/Mul"]
    assert _downstream(graph, ("/nothing",)) == []
    int8 = quantize_graph(fp32, tmp_path / "det.int8.onnx", _feeds(), op_types=DETECTOR_OPS,
                          float_after=("/head/Conv",))
    q = _quantized_outputs(int8)
    assert {"c1", "s1", "a1", "logits"} <= q            # conv, SiLU and the output conv run in int8
    assert not {"probs", "y"} & q                       # the decoding stays float
    x = _feeds(1)[0]["x"]
    ref, got = _run(fp32, x), _run(int8, x)
    assert np.corrcoef(ref.ravel(), got.ravel())[0, 1] > 0.98


def test_moving_average_keeps_one_unusual_calibration_batch_from_setting_the_ranges(tmp_path):
    """Plain MinMax takes each tensor's range from the most extreme calibration batch; with the moving average
    (the detector's recipe) an outlier frame among ordinary ones leaves ordinary inputs finely quantized."""
    fp32 = _tiny_detector(tmp_path / "det.onnx")
    feeds = _feeds(7)
    feeds[3] = {"x": feeds[3]["x"] * 20.0}                 # one frame far brighter than the rest
    kw = dict(op_types=DETECTOR_OPS, float_after=("/head/Conv",))
    extremes = quantize_graph(fp32, tmp_path / "minmax.onnx", feeds, **kw)
    mean = quantize_graph(fp32, tmp_path / "mean.onnx", feeds, moving_average=True, **kw)
    x = _feeds(9)[8]["x"]                                  # an ordinary input
    ref = _run(fp32, x)
    err_extremes, err_mean = (float(np.abs(_run(g, x) - ref).mean()) for g in (extremes, mean))
    assert err_mean < 0.5 * err_extremes, (err_mean, err_extremes)


def test_convs_only_and_fallback_when_the_heads_are_not_found(tmp_path):
    fp32 = _tiny_detector(tmp_path / "det.onnx")
    convs = _quantized_outputs(quantize_graph(fp32, tmp_path / "a.onnx", _feeds(), op_types=CONV_OPS))
    assert "s1" not in convs and not {"probs", "y"} & convs    # the Sigmoid and the decoding stay float
    # a graph named otherwise (another toolchain's detector): convs only, its decoding never int8
    other = _quantized_outputs(quantize_graph(fp32, tmp_path / "b.onnx", _feeds(), op_types=DETECTOR_OPS,
                                              float_after=("/model.22/*",)))
    assert other == convs
    with pytest.raises(ValueError, match="calibration"):
        quantize_graph(fp32, tmp_path / "c.onnx", [])


def test_detector_recipe_keeps_the_class_output_convs_float(bundle_dir, tmp_path):
    """uint8 class logits gave a handful of distinct scores (ties, thresholds that meant the same): the exporter's
    detector recipe keeps the class output convs float and the box output convs int8, on an exported detector."""
    from pallet6d.export.quantize import INT8_RECIPES
    from pallet6d.runtime.bundle import load_bundle

    det = load_bundle(bundle_dir).detector
    h, w = det.input_hw
    rng = np.random.default_rng(2)
    feeds = [{det.input_name: rng.random((1, 3, h, w), dtype=np.float32)} for _ in range(2)]
    path = quantize_graph(bundle_dir / det.file, tmp_path / "det.int8.onnx", feeds, **INT8_RECIPES["detector"])
    graph = onnx.load(str(path)).graph
    dequantized = {o for n in graph.node if n.op_type == "DequantizeLinear" for o in n.output}
    convs = {n.name: n for n in graph.node if n.op_type == "Conv"}
    cls = [c for name, c in convs.items() if name.startswith("/head/cls") and name.endswith(".2/Conv")]
    box = [c for name, c in convs.items() if name.startswith("/head/box") and name.endswith(".2/Conv")]
    assert cls and box, sorted(convs)
    assert all(c.input[1] not in dequantized for c in cls), "a class output conv has int8 weights"
    assert all(c.input[1] in dequantized for c in box), "a box output conv lost its int8 weights"
