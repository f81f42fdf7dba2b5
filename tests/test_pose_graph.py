"""The pose heads' first convolution meets the global feature once per sample (`export/pose.py`), graphs of the
older layout (one convolution over the concatenation) still read back, and `export/regraph.py` re-exports a
bundle's pose graph from its own weights."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from pallet6d.export.bundle_weights import _state_from_graph  # noqa: E402
from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.export_inputs import ExportError  # noqa: E402
from pallet6d.export.onnx_io import compare_outputs, export_graph, ort_session, run_session  # noqa: E402
from pallet6d.export.pose import SplitInputConv1d, build_pose  # noqa: E402
from pallet6d.export.regraph import regraph_pose  # noqa: E402

CFG = get_config("tiny")


def _inputs(n: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, CFG.pose.num_points, 3, generator=g) * 0.3,
            torch.randn(n, CFG.pose.num_points, CFG.fusion.feature_dim, generator=g))


class _ConcatConv1d(SplitInputConv1d):
    """The older layout: the global feature repeated at every point, one convolution over the concatenation."""

    def forward(self, local, global_feat):
        dense = torch.cat((local, global_feat.expand(-1, -1, local.shape[2])), 1)
        return torch.nn.functional.conv1d(dense, self.weight, self.bias)


def test_the_split_convolution_is_the_convolution_of_the_concatenation():
    torch.manual_seed(0)
    split = SplitInputConv1d(5, 7, 4)
    plain = torch.nn.Conv1d(12, 4, 1)
    plain.load_state_dict(split.state_dict())          # the same parameters under the same keys
    local, g = torch.randn(2, 5, 9), torch.randn(2, 7, 1)
    expected = plain(torch.cat((local, g.expand(-1, -1, 9)), 1))
    assert torch.allclose(split(local, g), expected, atol=1e-6)
    assert set(split.state_dict()) == {"weight", "bias"}


def test_pose_graphs_of_either_layout_read_back(tmp_path):
    torch.manual_seed(1)
    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    example = _inputs()
    names, outputs = ["points", "features"], ["quat", "trans", "conf"]
    axes = {k: {0: "batch"} for k in names + outputs}
    split_graph = export_graph(net, example, tmp_path / "split.onnx", names, outputs, axes)
    convs = [n.name for n in onnx.load(str(split_graph)).graph.node if "head_r.0" in n.name]
    assert len([c for c in convs if c.endswith(("Conv", "Conv_1"))]) == 2   # local and global columns apart
    old = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    old.load_state_dict(net.state_dict())
    for head in (old.head_r, old.head_t, old.head_c):
        head[0].__class__ = _ConcatConv1d
    concat_graph = export_graph(old, example, tmp_path / "concat.onnx", names, outputs, axes)
    feeds = dict(zip(names, (t.numpy() for t in example)))
    a, b = run_session(ort_session(split_graph), feeds), run_session(ort_session(concat_graph), feeds)
    for k in outputs:
        assert compare_outputs(b[k], a[k]).max_abs < 1e-5, k
    for graph in (split_graph, concat_graph):
        fresh = build_pose(CFG.pose, CFG.fusion.feature_dim)
        state, _ = _state_from_graph(fresh, graph, example)
        for key, value in net.state_dict().items():
            assert torch.allclose(state[key], value, atol=1e-6), (graph.name, key)


def test_a_bundle_pose_graph_re_exported_from_its_weights(bundle_dir, tmp_path):
    out = regraph_pose(bundle_dir, tmp_path / "again", frames=2, command="test")
    before = json.loads((bundle_dir / "manifest.json").read_text())
    after = json.loads((out / "manifest.json").read_text())
    assert {k: v for k, v in after.items() if k != "files"} == {k: v for k, v in before.items() if k != "files"}
    for name, sha in before["files"].items():
        if name != "pose.onnx":
            assert after["files"][name] == sha, name
    report = json.loads((out / "report.json").read_text())
    record = report["provenance"]["pose_graph"]
    assert record["command"] == "test" and record["from"]["sha256"] == before["files"]["pose.onnx"]
    assert all(v["rel_rms"] < 0.02 for v in record["vs_previous_graph"].values())
    rng = np.random.default_rng(2)
    feeds = {"points": rng.normal(size=(2, CFG.pose.num_points, 3)).astype(np.float32) * 0.3,
             "features": rng.normal(size=(2, CFG.pose.num_points, CFG.fusion.feature_dim)).astype(np.float32)}
    ref = run_session(ort_session(bundle_dir / "pose.onnx"), feeds)
    got = run_session(ort_session(out / "pose.onnx"), feeds)
    for k, v in ref.items():
        assert compare_outputs(v, got[k]).rel_rms < 0.02, k
    with pytest.raises(ExportError, match="not empty"):
        regraph_pose(bundle_dir, out)
