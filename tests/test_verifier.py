"""The pose network's verifier head (`PoseConfig.verifier`): the confidence head keeps choosing the hypothesis, the
verifier gives the graph's confidence at the chosen point; trained alone (`--verifier-only`), every pose stays."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.bundle_weights import load_bundle_weights  # noqa: E402
from pallet6d.export.calib_data import make_calibration_set  # noqa: E402
from pallet6d.export.config import CONFIGS, get_config  # noqa: E402
from pallet6d.export.fusion import build_fusion  # noqa: E402
from pallet6d.export.pose import MostConfidentPose, build_pose  # noqa: E402
from pallet6d.export.train_loop import LoopSettings, load_checkpoint  # noqa: E402
from pallet6d.export.train_data import NO_AUGMENT  # noqa: E402
from pallet6d.export.train_pose import (CONF_FLOOR, PoseTrainer, calibrate_floor, calibrate_verifier,  # noqa: E402
                                        load_pose_data, train_pose)

CFG = get_config("tiny")
TINY_V = CFG.replace(name="tiny-verified", pose=dataclasses.replace(CFG.pose, verifier=True))


@pytest.fixture
def verified(monkeypatch):
    monkeypatch.setitem(CONFIGS, TINY_V.name, TINY_V)
    return TINY_V


def _inputs(cfg, batch=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(batch, cfg.pose.num_points, 3, generator=g) * 0.3,
            torch.randn(batch, cfg.pose.num_points, cfg.fusion.feature_dim, generator=g))


def test_the_verifier_gives_the_confidence_at_the_point_the_confidence_head_chose():
    torch.manual_seed(0)
    net_v = build_pose(TINY_V.pose, CFG.fusion.feature_dim).eval()
    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    net.load_state_dict({k: v for k, v in net_v.state_dict().items() if not k.startswith("head_v.")})
    pts, feats = _inputs(CFG)
    with torch.no_grad():
        quat_v, trans_v, conf_v = MostConfidentPose(net_v)(pts, feats)
        quat, trans, conf = MostConfidentPose(net)(pts, feats)
        verdict, choice = net_v.verify(pts, feats)
    torch.testing.assert_close(quat_v, quat)            # the same hypothesis: the confidence head chose it
    torch.testing.assert_close(trans_v, trans)
    torch.testing.assert_close(conf, choice.amax(1))
    torch.testing.assert_close(conf_v, verdict.gather(1, choice.argmax(1, keepdim=True))[:, 0])
    assert not torch.allclose(conf_v, conf)               # its own head, not the confidence head
    assert sorted(MostConfidentPose(net_v).state_dict()) == sorted(net_v.state_dict())
    with pytest.raises(ValueError, match="no verifier head"):
        net.verify(pts, feats)


def test_the_verifier_trained_alone_leaves_every_pose_and_ships_in_the_pose_graph(verified, bundle_dir,
                                                                                  sim_bop_dataset, tmp_path):
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.onnx_io import ort_session, run_session
    from pallet6d.export.train_cli import merge_checkpoints

    run = tmp_path / "v"
    train_pose(verified, [sim_bop_dataset], run, LoopSettings(epochs=1, batch=4, lr=1e-2, seed=1), variants=1,
               progress=False, init=bundle_dir, verifier_only=True, mismatched_frames=2, negative_conf_weight=1.0)
    ckpt = load_checkpoint(run / "last.pt")
    assert ckpt["provenance"]["trainable"] == "verifier_head"
    assert set(ckpt["provenance"]["verifier_calibration"]) == {"logit_shift", "threshold_before", "pallet_share",
                                                               "val_pallets"}
    assert ckpt["provenance"]["init"]["verifier"] == "the confidence head's weights"
    shipped = {"fusion": build_fusion(CFG.fusion),
               "pose": build_pose(CFG.pose, CFG.fusion.feature_dim)}
    load_bundle_weights(bundle_dir, shipped)
    for net in ("fusion", "pose"):                       # everything but the verifier is the bundle's
        for k, v in shipped[net].state_dict().items():
            assert torch.equal(ckpt[net][k], v), (net, k)
    moved = [not torch.equal(ckpt["pose"][f"head_v.{k[len('head_c.'):]}"], v)
             for k, v in ckpt["pose"].items() if k.startswith("head_c.")]
    assert any(moved)

    merge_checkpoints(bundle_dir, run / "last.pt", tmp_path / "model.pt")
    calib = make_calibration_set(CFG, frames=2, max_crops=4, seed=3)
    out = export_bundle(verified, tmp_path / "bundle", checkpoint=tmp_path / "model.pt", calib=calib,
                        keep_from={"detector": bundle_dir, "fusion": bundle_dir})
    pts, feats = (x.numpy() for x in _inputs(CFG, seed=4))
    before = run_session(ort_session(bundle_dir / "pose.onnx"), {"points": pts, "features": feats})
    after = run_session(ort_session(out.root / "pose.onnx"), {"points": pts, "features": feats})
    np.testing.assert_allclose(after["quat"], before["quat"], atol=1e-5)      # the same poses
    np.testing.assert_allclose(after["trans"], before["trans"], atol=1e-5)
    assert not np.allclose(after["conf"], before["conf"])                     # the verifier's confidence
    read_back = {"pose": build_pose(verified.pose, CFG.fusion.feature_dim)}
    load_bundle_weights(out.root, read_back)                                  # parity-checked against the graph
    for k, v in read_back["pose"].state_dict().items():
        if k.startswith("head_v.") and v.is_floating_point():
            torch.testing.assert_close(v, ckpt["pose"][k], atol=2e-3, rtol=2e-3)


def test_verifier_training_needs_a_verifier_and_excludes_the_other_heads_training(bundle_dir, sim_bop_dataset,
                                                                                  tmp_path):
    settings = LoopSettings(epochs=1, batch=4, lr=1e-3, seed=1)
    with pytest.raises(ValueError, match="has no verifier head to train"):
        train_pose(CFG, [sim_bop_dataset], tmp_path / "a", settings, variants=1, progress=False, init=bundle_dir,
                   verifier_only=True)
    with pytest.raises(ValueError, match="exclude each other"):
        train_pose(TINY_V, [sim_bop_dataset], tmp_path / "b", settings, variants=1, progress=False,
                   init=bundle_dir, verifier_only=True, conf_head_only=True)


def _val_shares(trainer):
    """(share of verifier confidences at the chosen points >= the floor, share of best confidences >= it)."""
    with torch.no_grad():
        _, _, conf = trainer.forward_loss(trainer.data.val_idx)
    verifier_share = float((trainer.last_confidence >= CONF_FLOOR).float().mean())
    return verifier_share, float((conf.amax(1) >= CONF_FLOOR).float().mean())


@pytest.mark.parametrize("offset", [-4.0, 0.0, 4.0])
def test_calibration_makes_the_floor_keep_as_many_validation_pallets_as_the_confidence_head(
        sim_bop_dataset, tmp_path, offset):
    pd = load_pose_data(TINY_V, [sim_bop_dataset], variants=1, seed=0, aug=NO_AUGMENT, cache_dir=tmp_path,
                        progress=False)
    pd = dataclasses.replace(pd, val_idx=np.arange(len(pd.samples.points)))    # every sample, so shares are fine
    torch.manual_seed(2)
    trainer = PoseTrainer(TINY_V, pd)
    with torch.no_grad():           # the confidence head's best near the floor, the verifier far from it either way
        trainer.pose.head_c[-1].bias.fill_(-2.2)
        trainer.pose.head_v[-1].bias.fill_(-2.2 + offset)
    for net in trainer.nets.values():
        net.eval()
    before, kept = _val_shares(trainer)
    poses = {k: v.clone() for k, v in trainer.pose.state_dict().items()}
    record = calibrate_verifier(trainer)
    after, kept_after = _val_shares(trainer)
    assert after == pytest.approx(kept) and kept_after == kept
    assert record["pallet_share"] == pytest.approx(kept) and record["val_pallets"] == len(pd.val_idx)
    assert np.sign(record["logit_shift"]) == -np.sign(offset) or before == pytest.approx(kept)
    moved = [k for k, v in trainer.pose.state_dict().items() if not torch.equal(v, poses[k])]
    assert moved == ([] if record["logit_shift"] == 0 else ["head_v.6.bias"])     # only the verifier's last bias
    assert abs(calibrate_verifier(trainer)["logit_shift"]) < 1e-6      # idempotent


def test_calibration_needs_a_verifier(sim_bop_dataset, tmp_path):
    pd = load_pose_data(CFG, [sim_bop_dataset], variants=1, seed=0, aug=NO_AUGMENT, cache_dir=tmp_path,
                        progress=False)
    with pytest.raises(ValueError, match="no verifier head"):
        calibrate_verifier(PoseTrainer(CFG, pd))


def _chosen_points(trainer):
    with torch.no_grad():
        _, _, conf = trainer.forward_loss(trainer.data.val_idx)
    return conf.argmax(1), float((conf.amax(1) >= CONF_FLOOR).float().mean())


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_the_confidence_head_calibrated_keeps_the_share_asked_for_and_every_chosen_point(sim_bop_dataset, tmp_path,
                                                                                         share):
    pd = load_pose_data(CFG, [sim_bop_dataset], variants=1, seed=0, aug=NO_AUGMENT, cache_dir=tmp_path,
                        progress=False)
    pd = dataclasses.replace(pd, val_idx=np.arange(len(pd.samples.points)))
    torch.manual_seed(3)
    trainer = PoseTrainer(CFG, pd)
    for net in trainer.nets.values():
        net.eval()
    chosen, _ = _chosen_points(trainer)
    poses = {k: v.clone() for k, v in trainer.pose.state_dict().items()}
    record = calibrate_floor(trainer, share)
    chosen_after, kept = _chosen_points(trainer)
    n = len(pd.val_idx)
    assert kept == pytest.approx(round(share * n) / n) and record["pallet_share"] == pytest.approx(kept)
    assert torch.equal(chosen_after, chosen)                    # every pallet keeps its hypothesis
    moved = [k for k, v in trainer.pose.state_dict().items() if not torch.equal(v, poses[k])]
    assert moved == [f"head_c.{len(trainer.pose.head_c) - 1}.bias"]
    assert abs(calibrate_floor(trainer, share)["logit_shift"]) < 1e-6      # idempotent
    with pytest.raises(ValueError, match="share must be in"):
        calibrate_floor(trainer, 1.2)


def test_a_run_calibrated_to_a_share_records_it_and_a_finished_run_resumed_only_calibrates(sim_bop_dataset,
                                                                                           tmp_path):
    run = tmp_path / "r"
    settings = LoopSettings(epochs=1, batch=4, lr=1e-3, seed=1)
    train_pose(CFG, [sim_bop_dataset], run, settings, variants=1, progress=False, calibrate_share=0.75)
    ckpt = load_checkpoint(run / "last.pt")
    record = ckpt["provenance"]["confidence_calibration"]
    assert record["val_pallets"] >= 1 and abs(record["pallet_share"] - 0.75) <= 0.5 / record["val_pallets"]
    entry = train_pose(CFG, [sim_bop_dataset], run, settings, variants=1, progress=False, resume=True,
                       calibrate_share=0.75)
    assert entry == {}                                          # no epoch left to train
    again = load_checkpoint(run / "last.pt")
    assert abs(again["provenance"]["confidence_calibration"]["logit_shift"]) < 1e-5
    for k, v in ckpt["pose"].items():
        torch.testing.assert_close(again["pose"][k], v, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="not with --verifier-only"):
        train_pose(TINY_V, [sim_bop_dataset], tmp_path / "v", settings, variants=1, progress=False,
                   verifier_only=True, calibrate_share=0.5)


def test_the_pallet_target_is_one_at_the_chosen_point(sim_bop_dataset, tmp_path):
    pd = load_pose_data(TINY_V, [sim_bop_dataset], variants=1, seed=0, aug=NO_AUGMENT, cache_dir=tmp_path,
                        progress=False)
    torch.manual_seed(3)
    trainer = PoseTrainer(TINY_V, pd, trainable="verifier", verifier_target="pallet")
    for net in trainer.nets.values():
        net.eval()
    idx = pd.train_idx[:4]
    loss, _, _ = trainer.forward_loss(idx)
    chosen = trainer.last_confidence
    torch.testing.assert_close(loss, -torch.log(chosen).mean())
    trainer.verifier_target = "confidence"          # the other target: the confidence head's, at every point
    other, _, _ = trainer.forward_loss(idx)
    torch.testing.assert_close(trainer.last_confidence, chosen)
    assert not torch.isclose(other, loss)
    with pytest.raises(ValueError, match="verifier_target must be one of"):
        PoseTrainer(TINY_V, pd, trainable="verifier", verifier_target="pose")
