"""8-bit weight storage: int8 per output channel on disk, float32 arithmetic on the decoded weights, folded by
onnxruntime; odd tensors kept float16/float32; the export step records and limits the change."""
import collections

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from pallet6d.export.bundle_export import FLOAT_WEIGHTS, ExportError, Graphs, export_bundle, store_float_weights
from pallet6d.export.bundle_weights import _graph_values
from pallet6d.export.calib_data import make_calibration_set
from pallet6d.export.config import get_config
from pallet6d.export.onnx_io import compare_outputs, export_graph, ort_session, run_session
from pallet6d.export.weight_storage import Use
from pallet6d.export.weights_int8 import (INT8_LEVELS, output_channel_axis, quantize_per_channel,
                                          store_weights_int8)
from pallet6d.runtime.bundle import check_bundle, load_bundle
from pallet6d.runtime.sessions import session_options

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _net(seed=0):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Conv2d(3, 32, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(32, 16, 3),
                               torch.nn.Flatten(), torch.nn.Linear(16 * 6 * 6, 8)).eval()


def _inits(path):
    return {i.name: numpy_helper.to_array(i) for i in onnx.load(str(path)).graph.initializer}


def test_per_channel_scale_and_round_trip_bound():
    rng = np.random.default_rng(0)
    w = (rng.normal(size=(6, 4, 3, 3)) * np.array([1e-3, 0.1, 1, 10, 100, 1e4])[:, None, None, None]).astype(np.float32)
    q, scale = quantize_per_channel(w, axis=0)
    assert q.dtype == np.int8 and scale.dtype == np.float32 and scale.shape == (6, 1, 1, 1)
    peak = np.abs(w).reshape(6, -1).max(axis=1)
    np.testing.assert_allclose(scale.ravel(), peak / INT8_LEVELS, rtol=1e-6)
    # each channel's largest value maps to +-127, none beyond; the error is at most half a step per channel
    assert np.all(np.abs(q).reshape(6, -1).max(axis=1) == INT8_LEVELS) and q.min() >= -INT8_LEVELS
    err = np.abs(w - q.astype(np.float32) * scale)
    assert np.all(err <= scale / 2 * (1 + 1e-5)), (err / scale).max()
    # symmetric: -w stores exactly -q
    np.testing.assert_array_equal(quantize_per_channel(-w, axis=0)[0], -q)
    # along another axis (Gemm B, MatMul): one scale per column
    b = w.reshape(6, -1).T.copy()   # (36, 6): column c is channel c
    q1, s1 = quantize_per_channel(b, axis=1)
    assert s1.shape == (1, 6)
    np.testing.assert_allclose(s1.ravel(), scale.ravel(), rtol=1e-6)
    np.testing.assert_array_equal(q1, q.reshape(6, -1).T)


def test_zero_or_non_finite_channels_are_not_quantized():
    w = np.ones((4, 8), np.float32)
    w[2] = 0.0
    assert quantize_per_channel(w, axis=0) is None                       # scale would be 0
    assert quantize_per_channel(w, axis=1) is not None                    # every column has a 1
    w[2, 3] = np.inf
    assert quantize_per_channel(w, axis=1) is None
    tiny = np.full((2, 3), 1e-44, np.float32)                              # scale below float32's normal range
    assert quantize_per_channel(tiny, axis=0) is None


def test_output_channel_axis_by_reader():
    conv = helper.make_node("Conv", ["x", "w"], ["y"])
    gemm_t = helper.make_node("Gemm", ["x", "w"], ["y"], transB=1)
    gemm = helper.make_node("Gemm", ["x", "w"], ["y"])
    matmul = helper.make_node("MatMul", ["x", "w"], ["y"])
    add = helper.make_node("Add", ["x", "w"], ["y"])
    assert output_channel_axis((8, 4, 3, 3), [Use(conv, 1)]) == 0
    assert output_channel_axis((8, 4), [Use(gemm_t, 1)]) == 0
    assert output_channel_axis((4, 8), [Use(gemm, 1)]) == 1
    assert output_channel_axis((2, 4, 8), [Use(matmul, 1)]) == 2
    assert output_channel_axis((4, 8), [Use(matmul, 0)]) is None         # the weight on the left: not handled
    assert output_channel_axis((4, 8), [Use(add, 1)]) is None
    assert output_channel_axis((8, 8), [Use(gemm, 1), Use(gemm_t, 1)]) is None   # readers disagree
    assert output_channel_axis((8, 8), [Use(matmul, 1), Use(matmul, 1)]) == 1


def test_graph_runs_float32_on_the_decoded_weights(tmp_path):
    net = _net()
    x = torch.rand(2, 3, 8, 8)
    src = export_graph(net, (x,), tmp_path / "m.onnx", ["x"], ["y"])
    storage = store_weights_int8(src, tmp_path / "q.onnx", min_elements=256)
    assert (storage.converted, storage.kept_fp16, storage.kept_fp32) == (3, 0, 0)
    assert storage.bytes_after < 0.35 * storage.bytes_before
    inits = _inits(tmp_path / "q.onnx")
    assert sum(a.dtype == np.int8 for a in inits.values()) == 3
    assert all(a.dtype == np.float32 for n, a in inits.items() if not n.endswith("__int8"))   # scales, biases
    # expected: the same network with each large weight replaced by q * scale per output channel
    decoded = _net()
    with torch.no_grad():
        for m in (decoded[0], decoded[2], decoded[4]):
            q, s = quantize_per_channel(m.weight.numpy(), axis=0)
            m.weight.copy_(torch.from_numpy(q.astype(np.float32) * s))
        want, full = decoded(x).numpy(), net(x).numpy()
    got = run_session(ort_session(tmp_path / "q.onnx"), {"x": x.numpy()})["y"]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    d = compare_outputs(full, got)
    assert 0 < d.rel_rms < 0.02, d
    # the weights read back (fine-tuning from a bundle) are the decoded ones
    values = _graph_values(onnx.load(str(tmp_path / "q.onnx")))
    np.testing.assert_allclose(values["0.weight"], decoded[0].weight.detach().numpy(), rtol=1e-6)


def test_onnxruntime_folds_the_decoding_at_session_build(tmp_path):
    """The optimized graph is the float32 graph: no Cast, Mul or int8 tensor left to run per call."""
    net = _net()
    src = export_graph(net, (torch.rand(1, 3, 8, 8),), tmp_path / "m.onnx", ["x"], ["y"])
    store_weights_int8(src, tmp_path / "q.onnx", min_elements=256)

    def optimized(path):
        so = session_options(1)
        so.optimized_model_filepath = str(path.with_suffix(".opt.onnx"))
        ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        g = onnx.load(so.optimized_model_filepath).graph
        return (collections.Counter(n.op_type for n in g.node),
                collections.Counter(i.data_type for i in g.initializer))

    ops32, types32 = optimized(src)
    ops8, types8 = optimized(tmp_path / "q.onnx")
    assert ops8 == ops32 and types8 == types32 and TensorProto.INT8 not in types8


def test_tensors_kept_float16_or_float32(tmp_path):
    """An Add operand, a weight with a zero channel -> float16; small tensors and non-finite ones -> float32."""
    rng = np.random.default_rng(1)
    w_zero = rng.normal(size=(8, 4, 3, 3)).astype(np.float32)
    w_zero[5] = 0.0
    w_inf = rng.normal(size=(8, 8, 3, 3)).astype(np.float32)
    w_inf[0, 0, 0, 0] = np.inf
    w_ok = rng.normal(size=(4, 8, 3, 3)).astype(np.float32)
    emb = rng.normal(size=(1, 4, 6, 6)).astype(np.float32)
    bias = rng.normal(size=8).astype(np.float32)
    nodes = [helper.make_node("Conv", ["x", "w_zero", "bias"], ["a"], pads=[1, 1, 1, 1]),
             helper.make_node("Conv", ["a", "w_inf"], ["b"], pads=[1, 1, 1, 1]),
             helper.make_node("Conv", ["b", "w_ok"], ["c"], pads=[1, 1, 1, 1]),
             helper.make_node("Add", ["c", "emb"], ["y"])]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 6, 6])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 6, 6])],
                              [numpy_helper.from_array(v, k) for k, v in
                               dict(w_zero=w_zero, w_inf=w_inf, w_ok=w_ok, emb=emb, bias=bias).items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.save(model, tmp_path / "g.onnx")
    storage = store_weights_int8(tmp_path / "g.onnx", tmp_path / "g.onnx", min_elements=100)   # in place
    assert (storage.converted, storage.kept_fp16, storage.kept_fp32) == (1, 2, 1)
    inits = _inits(tmp_path / "g.onnx")
    assert inits["w_ok__int8"].dtype == np.int8 and inits["w_ok__scale"].shape == (4, 1, 1, 1)
    assert inits["w_zero__fp16"].dtype == np.float16 and inits["emb__fp16"].dtype == np.float16
    assert inits["w_inf"].dtype == np.float32 and inits["bias"].dtype == np.float32   # not finite; small


def _pose_graphs(tmp_path, net, n_feeds=3):
    """A float32 graph of `net` as the export's step-2 record holds it (one stage, "pose")."""
    x = torch.rand(4, 3, 8, 8)
    path = export_graph(net, (x,), tmp_path / "pose.onnx", ["x"], ["y"], {"x": {0: "b"}, "y": {0: "b"}})
    rng = np.random.default_rng(2)
    feeds = [{"x": rng.random((4, 3, 8, 8), dtype=np.float32)} for _ in range(n_feeds)]
    return Graphs({"pose": path}, "x", "y", {}, {"pose": feeds}, {"pose": 1})


def test_store_float_weights_records_the_change_and_refuses_over_the_limit(tmp_path, monkeypatch):
    g = _pose_graphs(tmp_path, _net())
    ref = run_session(ort_session(g.files["pose"]), g.held_out("pose")[0])["y"]
    checks = store_float_weights(g, tmp_path, ("pose",), "int8")   # the first conv (864 values) is small
    rec = checks["pose"]
    assert rec["converted"] == 2 and rec["limit_rel_rms"] == FLOAT_WEIGHTS["int8"][1]["pose"]
    assert 0 < rec["vs_fp32_weights"]["y"]["rel_rms"] <= rec["limit_rel_rms"]
    assert rec["bytes_after"] == g.files["pose"].stat().st_size and not list(tmp_path.glob("*int8-weights*"))
    got = run_session(ort_session(g.files["pose"]), g.held_out("pose")[0])["y"]
    assert compare_outputs(ref, got).rel_rms <= rec["limit_rel_rms"]
    # over the limit: refused, naming the storage to fall back to, and the float32 graph left as it was
    (tmp_path / "b").mkdir()
    g2 = _pose_graphs(tmp_path / "b", _net())
    before = g2.files["pose"].read_bytes()
    monkeypatch.setitem(FLOAT_WEIGHTS, "int8", (FLOAT_WEIGHTS["int8"][0], {"pose": 1e-6}))
    with pytest.raises(ExportError, match=r"pose: int8 weights change the output .* --float-weights fp16"):
        store_float_weights(g2, tmp_path / "b", ("pose",), "int8")
    assert g2.files["pose"].read_bytes() == before and not list((tmp_path / "b").glob("*int8-weights*"))
    with pytest.raises(ExportError, match="float weight storage"):
        store_float_weights(g2, tmp_path / "b", ("pose",), "fp32")
    # float16 falls back to float32, and stores within its own limit
    monkeypatch.setitem(FLOAT_WEIGHTS, "fp16", (FLOAT_WEIGHTS["fp16"][0], {"pose": 0.0}))
    with pytest.raises(ExportError, match="--float-weights fp32"):
        store_float_weights(g2, tmp_path / "b", ("pose",), "fp16")
    monkeypatch.undo()
    half = store_float_weights(g2, tmp_path / "b", ("pose",), "fp16")["pose"]
    assert half["converted"] == 2 and half["vs_fp32_weights"]["y"]["rel_rms"] <= half["limit_rel_rms"] == 5e-3


@pytest.fixture(scope="module")
def tiny_pair(tmp_path_factory):
    """The same tiny networks exported with float32 and with int8-stored weights."""
    cfg = get_config("tiny")
    root = tmp_path_factory.mktemp("w8")
    calib = make_calibration_set(cfg, frames=4, max_crops=16, seed=0, synthetic=True)
    reports = {w: export_bundle(cfg, root / w, seed=0, random_init=True, calib=calib, float_weights=w).report
               for w in ("fp32", "int8")}
    return root, reports, calib


def test_tiny_bundle_with_int8_weights_loads_and_matches_float32(tiny_pair):
    root, reports, calib = tiny_pair
    assert check_bundle(root / "int8") == []
    assert "weights_int8" not in reports["fp32"]["checks"] and "weights_fp16" not in reports["fp32"]["checks"]
    rec = reports["int8"]["checks"]["weights_int8"]
    b32, b8 = load_bundle(root / "fp32"), load_bundle(root / "int8")
    feeds = {"detector": [{"images": calib.images[i:i + 1]} for i in range(2)],
             "fusion": [{"rgb": calib.rgb_crops[:8], "depth": calib.depth_crops[:8]}]}
    feats = run_session(ort_session(b32.graph("fusion")), feeds["fusion"][0])["features"]
    from pallet6d.runtime.pose_inputs import gather_features
    feeds["pose"] = [{"points": calib.points[:8], "features": gather_features(feats, calib.choose[:8])}]
    for stage in ("detector", "fusion", "pose"):
        assert rec[stage]["converted"] > 0 and rec[stage]["kept_fp32"] == 0, rec[stage]
        assert (root / "int8" / f"{stage}.onnx").stat().st_size < 0.6 * (root / "fp32" / f"{stage}.onnx").stat().st_size
        s32, s8 = ort_session(b32.graph(stage)), ort_session(b8.graph(stage))
        for f in feeds[stage]:
            ref, got = run_session(s32, f), run_session(s8, f)
            for name in ref:
                d = compare_outputs(ref[name], got[name])
                assert d.rel_rms <= rec[stage]["limit_rel_rms"], (stage, name, d)
                assert d.max_abs > 0, (stage, name)   # the weights did change


def test_export_refuses_unknown_storage(tmp_path, tiny_pair):
    with pytest.raises(ExportError, match="float weight storage"):
        export_bundle(get_config("tiny"), tmp_path / "x", random_init=True, calib=tiny_pair[2], float_weights="int4")
    assert not (tmp_path / "x").exists()


def test_cli_float_weights_option_and_old_spelling():
    import argparse

    from pallet6d.export.cli import add_arguments
    p = argparse.ArgumentParser()
    add_arguments(p)
    base = ["--config", "tiny", "--random-init", "--out", "x"]
    assert p.parse_args(base).float_weights == "int8"
    assert p.parse_args([*base, "--float-weights", "fp16"]).float_weights == "fp16"
    assert p.parse_args([*base, "--fp32-weights"]).float_weights == "fp32"
    with pytest.raises(SystemExit):
        p.parse_args([*base, "--float-weights", "int4"])
