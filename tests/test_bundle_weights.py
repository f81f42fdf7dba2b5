"""Torch weights read back from a bundle's float graphs (`export/bundle_weights.py`): they reproduce the graphs,
folded BatchNorms get realistic statistics again, and a fine-tuning run can start from a bundle folder."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.bundle_weights import (BundleWeightsError, _module_path, bundle_checkpoint,  # noqa: E402
                                            load_bundle_weights)
from pallet6d.export.calib_data import make_calibration_set  # noqa: E402
from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.detector import build_detector  # noqa: E402
from pallet6d.export.fusion import build_fusion  # noqa: E402
from pallet6d.export.pose import build_pose  # noqa: E402
from pallet6d.export.train_loop import LoopSettings, load_checkpoint, load_init_weights  # noqa: E402
from pallet6d.export.train_pose import train_pose  # noqa: E402

CFG = get_config("tiny")
_BN = torch.nn.modules.batchnorm._BatchNorm


def _nets(cfg=CFG) -> dict:
    torch.manual_seed(123)     # weights unlike the bundle's
    return {"detector": build_detector(cfg.detector), "fusion": build_fusion(cfg.fusion),
            "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}


@pytest.fixture(scope="module")
def loaded(bundle_dir):
    nets = _nets()
    return nets, load_bundle_weights(bundle_dir, nets, calib_frames=2)


@pytest.mark.parametrize("node, module", [
    ("/rgb/backbone/layer1/layer1.0/conv1/Conv", "rgb.backbone.layer1.0.conv1"),
    ("/rgb/stages.0/Conv", "rgb.stages.0"),
    ("/rgb/up/up.2/PRelu", "rgb.up.2"),
    ("/stem/conv/Conv", "stem.conv"),
    ("/c2f2/m.0/cv1/conv/Conv", "c2f2.m.0.cv1.conv"),
    ("/attention/qkv/MatMul", "attention.qkv"),
])
def test_module_path_from_the_exporters_node_names(node, module):
    assert _module_path(node) == module


def test_read_back_weights_reproduce_every_graph(loaded, bundle_dir):
    nets, record = loaded
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    assert record["config"] == "tiny" and len(record["sha256"]) == 64
    for stage in ("detector", "fusion", "pose"):
        assert record["graphs"][stage]["sha256"] == manifest["files"][f"{stage}.onnx"]
        outputs = {k: v for k, v in record["parity"][stage].items() if isinstance(v, dict)}
        assert outputs, stage
        for name, diff in outputs.items():
            assert diff["max_abs"] <= 1e-4 * max(1.0, diff["ref_max_abs"]), (stage, name, diff)
            assert diff["corr"] > 0.9999, (stage, name, diff)
    # the convolutional stages had their BatchNorms folded into the convolutions by the exporter
    n_bn = sum(isinstance(m, _BN) for m in nets["detector"].modules())
    assert record["graphs"]["detector"]["batchnorms_restored"] == n_bn
    assert record["graphs"]["fusion"]["batchnorms_restored"] > 0


def test_restored_batchnorms_carry_their_inputs_statistics(loaded, bundle_dir):
    """Training mode normalises by batch statistics: with the statistics restored, a batch like the calibration
    data gives nearly what eval mode gives (an identity BatchNorm would rescale every channel to unit variance)."""
    nets, _ = loaded
    fusion = nets["fusion"]
    for m in fusion.modules():
        if isinstance(m, _BN):
            np.testing.assert_allclose(m.weight.detach().numpy() ** 2, m.running_var.numpy() + m.eps, rtol=1e-4)
    calib = make_calibration_set(CFG, frames=2, seed=5)          # other frames than the ones measured
    rgb, depth = torch.from_numpy(calib.rgb_crops[:16]), torch.from_numpy(calib.depth_crops[:16])
    with torch.no_grad():
        fusion.eval()
        ref = fusion(rgb, depth)
        fusion.train()
        train_mode = fusion(rgb, depth)
        fusion.eval()
    rel = float(torch.sqrt(((train_mode - ref) ** 2).mean()) / torch.sqrt((ref ** 2).mean()))
    assert rel < 0.25, rel


def test_a_bundle_of_another_config_or_no_bundle_is_a_clear_error(bundle_dir, tmp_path):
    with pytest.raises(BundleWeightsError, match="another config"):
        load_bundle_weights(bundle_dir, {"pose": build_pose(get_config("edge").pose, 64)}, calib_frames=1)
    with pytest.raises(BundleWeightsError, match="--init"):
        load_bundle_weights(tmp_path, {"pose": build_pose(CFG.pose, CFG.fusion.feature_dim)})
    # a graph that is not the manifest's (edited after export) fails the bundle's checksum
    broken = tmp_path / "broken"
    shutil.copytree(bundle_dir, broken)
    (broken / "pose.onnx").write_bytes((bundle_dir / "fusion.onnx").read_bytes())
    with pytest.raises(BundleWeightsError, match="pose.onnx"):
        load_bundle_weights(broken, {"pose": build_pose(CFG.pose, CFG.fusion.feature_dim)}, calib_frames=1)


def test_fine_tuning_starts_from_a_bundle_folder(bundle_dir, sim_bop_dataset, tmp_path, loaded):
    nets = {"fusion": build_fusion(CFG.fusion), "pose": build_pose(CFG.pose, CFG.fusion.feature_dim)}
    info = load_init_weights(bundle_dir, nets)
    assert info["bundle"] == str(bundle_dir)
    ref = loaded[0]["pose"].state_dict()
    assert all(torch.equal(v, ref[k]) for k, v in nets["pose"].state_dict().items())
    train_pose(CFG, [sim_bop_dataset], tmp_path / "ft", LoopSettings(epochs=1, batch=4, lr=1e-4, seed=1), variants=1,
               progress=False, init=bundle_dir)
    ckpt = load_checkpoint(tmp_path / "ft" / "last.pt")
    assert ckpt["provenance"]["init"]["graphs"]["pose"]["sha256"] == info["graphs"]["pose"]["sha256"]
    # the bundle's record of how its pose stage was trained (none: this one is random-init) goes with it
    report = json.loads((bundle_dir / "report.json").read_text())
    trained = (report["provenance"].get("training") or {}).get("pose")
    assert ckpt["provenance"]["init"]["training"] == {"pose": trained}
    assert all(torch.isfinite(v).all() for v in ckpt["pose"].values() if v.is_floating_point())


def test_a_bundle_merged_back_and_exported_computes_what_it_computed(bundle_dir, tmp_path):
    """bundle -> `train merge` (both stages from the folder) -> export: the same functions, the provenance kept."""
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.onnx_io import compare_outputs, ort_session, run_session
    from pallet6d.export.train_cli import merge_checkpoints

    merged = merge_checkpoints(bundle_dir, bundle_dir, tmp_path / "model.pt")
    assert merged["provenance"]["detector"]["read_back_from_bundle"]["bundle"] == str(bundle_dir)
    assert merged["provenance"]["detector"]["input_hw"] == json.loads(
        (bundle_dir / "manifest.json").read_text())["detector"]["input_hw"]
    calib = make_calibration_set(CFG, frames=2, max_crops=4, seed=3)
    export_bundle(CFG, tmp_path / "again", checkpoint=tmp_path / "model.pt", calib=calib)
    feeds = {"detector.onnx": {"images": calib.images[:1]},
             "fusion.onnx": {"rgb": calib.rgb_crops[:4], "depth": calib.depth_crops[:4]}}
    for graph, feed in feeds.items():
        before = run_session(ort_session(bundle_dir / graph), feed)
        after = run_session(ort_session(tmp_path / "again" / graph), feed)
        for name, ref in before.items():
            # float16 weight storage rounds the re-folded weights again: well below the networks' own precision
            assert compare_outputs(ref, after[name]).rel_rms < 2e-3, (graph, name)
    with pytest.raises(BundleWeightsError, match="stage must be"):
        bundle_checkpoint(bundle_dir, "fusion")


def test_export_keeps_another_bundles_detector_and_fusion_graphs_for_the_same_networks(bundle_dir, tmp_path):
    """`--detector-from`, `--fusion-from`: the merged checkpoint's networks are the bundle's, so its graphs go in
    unchanged."""
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.export_inputs import ExportError
    from pallet6d.export.train_cli import merge_checkpoints
    from pallet6d.runtime.bundle import sha256_file

    merge_checkpoints(bundle_dir, bundle_dir, tmp_path / "model.pt")
    calib = make_calibration_set(CFG, frames=2, max_crops=4, seed=3)
    out = export_bundle(CFG, tmp_path / "kept", checkpoint=tmp_path / "model.pt", calib=calib,
                        keep_from={"detector": bundle_dir, "fusion": bundle_dir})
    theirs = json.loads((bundle_dir / "report.json").read_text())["checks"]
    for stage in ("detector", "fusion"):
        assert sha256_file(tmp_path / "kept" / f"{stage}.onnx") == sha256_file(bundle_dir / f"{stage}.onnx")
        assert out.manifest.files[f"{stage}.onnx"] == sha256_file(bundle_dir / f"{stage}.onnx")
        assert out.report["checks"][f"{stage}_from"]["bundle"] == str(bundle_dir)
        assert out.report["checks"]["parity"][stage] == theirs["parity"][stage]
    with pytest.raises(ExportError, match="no int8 detector graph"):     # the tiny bundle is float only
        export_bundle(CFG, tmp_path / "int8", checkpoint=tmp_path / "model.pt", calib=calib, int8=True,
                      keep_from={"detector": bundle_dir})
    other = export_bundle(CFG, tmp_path / "other", random_init=True, seed=5, calib=calib).root
    for stage in ("detector", "fusion"):
        with pytest.raises(ExportError, match="another network"):
            export_bundle(CFG, tmp_path / f"mixed-{stage}", checkpoint=tmp_path / "model.pt", calib=calib,
                          keep_from={stage: other})
    with pytest.raises(ExportError, match="give --checkpoint"):
        export_bundle(CFG, tmp_path / "fresh", random_init=True, calib=calib, keep_from={"detector": bundle_dir})
    with pytest.raises(ExportError, match="not \\['pose'\\]"):
        export_bundle(CFG, tmp_path / "pose", checkpoint=tmp_path / "model.pt", calib=calib,
                      keep_from={"pose": bundle_dir})


def test_a_kept_stage_is_not_quantized_again(tmp_path, monkeypatch):
    """With `--int8`, a stage kept from another bundle takes that bundle's int8 graph; only the others are
    quantized."""
    import pallet6d.export.bundle_export as bundle_export
    from pallet6d.export.train_cli import merge_checkpoints
    from pallet6d.runtime.bundle import sha256_file

    calib = make_calibration_set(CFG, frames=2, max_crops=4, seed=3)
    source = bundle_export.export_bundle(CFG, tmp_path / "source", random_init=True, seed=4, calib=calib,
                                         int8=True).root
    merge_checkpoints(source, source, tmp_path / "model.pt")
    quantized = []
    real_quantize = bundle_export.quantize_graph

    def recording_quantize(path, *args, **kwargs):
        quantized.append(path.name)
        return real_quantize(path, *args, **kwargs)

    monkeypatch.setattr(bundle_export, "quantize_graph", recording_quantize)
    out = bundle_export.export_bundle(CFG, tmp_path / "kept", checkpoint=tmp_path / "model.pt", calib=calib,
                                      int8=True, keep_from={"fusion": source})
    assert quantized == ["detector.onnx"]
    assert sha256_file(out.root / "fusion.int8.onnx") == sha256_file(source / "fusion.int8.onnx")
    assert out.manifest.files["fusion.int8.onnx"] == sha256_file(source / "fusion.int8.onnx")
    theirs = json.loads((source / "report.json").read_text())["checks"]["int8"]
    assert out.report["checks"]["int8"]["fusion"] == theirs["fusion"]
