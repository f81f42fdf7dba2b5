"""Float16 weight storage: smaller file, float32 arithmetic on the rounded weights, odd tensors left alone."""
import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, numpy_helper

from pallet6d.export.onnx_io import export_graph, ort_session, run_session
from pallet6d.export.weights_fp16 import store_weights_fp16


def _net(seed=0, big_value=None):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 32, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(32, 16, 3),
                              torch.nn.Flatten(), torch.nn.Linear(16 * 6 * 6, 8))
    if big_value is not None:
        with torch.no_grad():
            net[2].weight[0, 0, 0, 0] = big_value
    return net.eval()


def _inits(path):
    return {i.name: i for i in onnx.load(str(path)).graph.initializer}


def test_graph_runs_float32_on_weights_rounded_to_float16(tmp_path):
    net = _net()
    x = torch.rand(2, 3, 8, 8)
    src = export_graph(net, (x,), tmp_path / "m.onnx", ["x"], ["y"])
    storage = store_weights_fp16(src, tmp_path / "h.onnx", min_elements=256)
    assert storage.converted == 3 and storage.kept_fp32 == 0 and storage.bytes_after < 0.6 * storage.bytes_before
    inits = _inits(tmp_path / "h.onnx")
    halves = [i for i in inits.values() if i.data_type == TensorProto.FLOAT16]
    assert len(halves) == 3 and all(i.name.endswith("__fp16") for i in halves)
    assert all(i.data_type == TensorProto.FLOAT for n, i in inits.items() if not n.endswith("__fp16"))  # biases
    # expected: the same network with its large weights rounded to float16, computed in float32
    rounded = _net()
    with torch.no_grad():
        for p in rounded.parameters():
            if p.numel() >= 256:
                p.copy_(p.half().float())
        want = rounded(x).numpy()
        full = net(x).numpy()
    got = run_session(ort_session(tmp_path / "h.onnx"), {"x": x.numpy()})["y"]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(got, full, rtol=0, atol=1e-9)  # the rounding is real ...
    np.testing.assert_allclose(got, full, rtol=0, atol=2e-3 * np.abs(full).max())  # ... and small


def test_tensor_outside_float16_range_stays_float32_and_in_place_works(tmp_path):
    net = _net(big_value=1e6)
    x = torch.rand(1, 3, 8, 8)
    src = export_graph(net, (x,), tmp_path / "m.onnx", ["x"], ["y"])
    want = run_session(ort_session(src), {"x": x.numpy()})["y"]
    storage = store_weights_fp16(src, src, min_elements=256)   # in place
    assert storage.converted == 2 and storage.kept_fp32 == 1
    kept = [i for i in _inits(src).values() if i.data_type == TensorProto.FLOAT and np.prod(i.dims) >= 256]
    assert len(kept) == 1 and numpy_helper.to_array(kept[0]).max() == pytest.approx(1e6)
    got = run_session(ort_session(src), {"x": x.numpy()})["y"]
    np.testing.assert_allclose(got, want, rtol=5e-3, atol=5e-3 * np.abs(want).max())
