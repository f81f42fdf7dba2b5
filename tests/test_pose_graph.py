"""The pose heads' first convolution meets the global feature once per sample (`export/pose.py`), the shipped graph
gives the most confident hypothesis alone (`MostConfidentPose`), graphs of the older layouts (one convolution over
the concatenation; every point's hypothesis) still read back and run, and `export/regraph.py` re-exports a bundle's
pose graph from its own weights."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from pallet6d.export.bundle_weights import _state_from_graph, load_bundle_weights  # noqa: E402
from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.export_inputs import ExportError  # noqa: E402
from pallet6d.export.onnx_io import compare_outputs, export_graph, ort_session, run_session  # noqa: E402
from pallet6d.export.pose import MostConfidentPose, SplitInputConv1d, build_pose  # noqa: E402
from pallet6d.export.regraph import regraph_pose  # noqa: E402
from pallet6d.runtime.bundle import check_bundle, load_bundle, sha256_file  # noqa: E402
from pallet6d.runtime.estimator import PalletEstimator  # noqa: E402

from estimator_fixtures import scene, visible_boxes  # noqa: E402

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


def test_the_most_confident_hypothesis_is_the_networks_argmax():
    torch.manual_seed(3)
    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    points, feats = _inputs(4)
    with torch.no_grad():
        quat, trans, conf = net(points, feats)
        q1, t1, c1 = MostConfidentPose(net)(points, feats)
    rows, idx = torch.arange(4), conf.argmax(1)
    assert torch.allclose(q1, quat[rows, idx], atol=1e-6)
    assert torch.allclose(t1, points[rows, idx] + trans[rows, idx], atol=1e-6)
    assert torch.equal(c1, conf[rows, idx])
    assert set(MostConfidentPose(net).state_dict()) == set(net.state_dict())    # the same weights, same names


def test_equal_confidences_choose_the_first_point_as_numpy_does():
    torch.manual_seed(4)
    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    with torch.no_grad():
        net.head_c[-1].weight.zero_()         # every point's confidence the same
    points, feats = _inputs(2)
    with torch.no_grad():
        quat, trans, _ = net(points, feats)
        q1, t1, _ = MostConfidentPose(net)(points, feats)
    assert torch.allclose(q1, quat[:, 0], atol=1e-6)
    assert torch.allclose(t1, points[:, 0] + trans[:, 0], atol=1e-6)


def _per_point_bundle(bundle_dir, out):
    """A copy of `bundle_dir` whose pose graph gives every point's hypothesis (the older layout), same weights."""
    import shutil
    shutil.copytree(bundle_dir, out)
    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    load_bundle_weights(bundle_dir, {"pose": net}, calib_frames=2)
    names, outputs = ["points", "features"], ["quat", "trans", "conf"]
    export_graph(net, _inputs(2), out / "pose.onnx", names, outputs, {k: {0: "batch"} for k in names + outputs})
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["pose"]["hypotheses"] = "per_point"
    manifest["files"]["pose.onnx"] = sha256_file(out / "pose.onnx")
    (out / "manifest.json").write_text(json.dumps(manifest))
    return out


def _network_poses(bundle) -> tuple[np.ndarray, np.ndarray]:
    """The pose stage's most confident hypotheses (T_cam_pallet, confidence) on the shared scene's pallets."""
    frame = scene()
    est = PalletEstimator.from_bundle(bundle, threads=1)
    stage = est.pose_network
    batch, _ = stage.preprocess(frame.rgb, frame.depth_m, frame.K, visible_boxes(frame, 3))
    return stage.postprocess(*stage.infer(batch), batch)


def test_bundles_of_either_hypothesis_layout_give_the_same_poses(bundle_dir, tmp_path):
    old = _per_point_bundle(bundle_dir, tmp_path / "per-point")
    assert load_bundle(old).pose.hypotheses == "per_point" and load_bundle(bundle_dir).pose.hypotheses == \
        "most_confident"
    T_old, c_old = _network_poses(old)
    T_new, c_new = _network_poses(bundle_dir)
    assert T_old.shape == (3, 4, 4)
    np.testing.assert_allclose(T_new, T_old, atol=1e-5)
    np.testing.assert_allclose(c_new, c_old, atol=1e-6)
    out = regraph_pose(old, tmp_path / "again", frames=2, command="test")      # the older layout re-exported
    assert load_bundle(out).pose.hypotheses == "most_confident"
    record = json.loads((out / "report.json").read_text())["provenance"]["pose_graph"]
    assert all(v["rel_rms"] < 0.02 for v in record["vs_previous_graph"].values())
    np.testing.assert_allclose(_network_poses(out)[0], T_old, atol=2e-3)      # int8-stored weights, as before


def test_bundle_check_reports_a_graph_that_does_not_give_what_the_manifest_says(bundle_dir, tmp_path):
    wrong = _per_point_bundle(bundle_dir, tmp_path / "wrong")
    manifest = json.loads((wrong / "manifest.json").read_text())
    manifest["pose"]["hypotheses"] = "most_confident"          # a per-point graph called a most-confident one
    (wrong / "manifest.json").write_text(json.dumps(manifest))
    problems = check_bundle(wrong, run=False)
    assert any("pose" in p and "quat" in p for p in problems), problems
    assert check_bundle(bundle_dir, run=True) == []
