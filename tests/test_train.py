"""Training: data preparation (targets, augmentation, cache), learning on a tiny batch, checkpoints, resume,
checkpoint -> export_bundle -> PalletEstimator. Tiny config, the 3-frame `sim_bop_dataset` fixture."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.calib_data import make_calibration_set, pose_input_spec  # noqa: E402
from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.train_data import (NO_AUGMENT, AugmentConfig, augment_depth, build_pose_samples,  # noqa: E402
                                        dataset_fingerprint, flip_horizontal, jitter_box, load_or_build,
                                        place_in_window)
from pallet6d.export.train_detector import DetectorTrainer, load_detector_data  # noqa: E402
from pallet6d.export.train_loop import (LoopSettings, conv_layout, keep_bn_stats, load_checkpoint,  # noqa: E402
                                       load_init_weights, lr_at, train_epochs)
from pallet6d.export.train_pose import PoseTrainer, load_pose_data, subsample_points, train_pose  # noqa: E402

CFG = get_config("tiny")


@pytest.fixture(scope="module")
def pose_data(sim_bop_dataset, tmp_path_factory):
    return load_pose_data(CFG, [sim_bop_dataset], variants=1, seed=0, aug=NO_AUGMENT,
                          cache_dir=tmp_path_factory.mktemp("cache"), progress=False)


def _overfit(trainer, step_fn, n_steps: int, lr: float) -> tuple[float, float]:
    params = [p for net in trainer.nets.values() for p in net.parameters()]
    opt = torch.optim.Adam(params, lr=lr)
    for net in trainer.nets.values():
        net.train()
    losses = []
    for _ in range(n_steps):
        loss = step_fn()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return float(np.mean(losses[:3])), float(np.mean(losses[-3:]))


def test_pose_targets_put_the_model_on_the_observed_points(sim_bop_dataset):
    """T_gt is in the centred frame: model points under T_gt must lie on the sampled (centred) points."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.export.train_data import model_points_for

    cfg = CFG.replace(pose=CFG.pose.__class__(num_points=64, point_dims=(16, 16), global_dims=(32, 64),
                                              head_dims=(32, 16, 16), attention_heads=2))
    s = build_pose_samples(sim_bop_dataset, pose_input_spec(cfg), variants=1, seed=0, aug=NO_AUGMENT)
    model, _ = model_points_for(BopDataset(sim_bop_dataset), 1, 3000, "epal")
    fractions = []
    for k in range(len(s)):
        T = s.T_gt[k].astype(np.float64)
        model_cam = model @ T[:3, :3].T + T[:3, 3]
        d = np.linalg.norm(s.points[k][:, None, :] - model_cam[None], axis=2).min(1)
        fractions.append(np.mean(d < 0.03))
    # mask-free boxes include some background, but most sampled points of a visible pallet are on it
    assert np.median(fractions) > 0.5
    assert s.points.shape[1:] == (64, 3) and np.allclose(s.points.mean(1), 0, atol=1e-4)


def test_pose_training_reduces_loss_on_a_tiny_batch(pose_data):
    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data)
    idx = pose_data.train_idx[:4]
    first, last = _overfit(trainer, lambda: trainer.forward_loss(idx)[0], 30, 2e-3)
    assert last < 0.7 * first, (first, last)


def test_subsampled_points_are_recentred_with_their_target(pose_data):
    s = pose_data.samples
    idx = pose_data.train_idx[:3]
    pts, choose, T = (torch.from_numpy(np.ascontiguousarray(a)) for a in (s.points[idx], s.choose[idx], s.T_gt[idx]))
    n = pts.shape[1] // 2
    sub, sub_choose, sub_T = subsample_points(pts, choose, T, n)
    assert sub.shape == (3, n, 3) and torch.allclose(sub.mean(1), torch.zeros(3, 3), atol=1e-6)
    assert torch.equal(sub_choose, choose[:, :n])
    model = torch.randn(50, 3, dtype=torch.float64)
    for k in range(3):   # the model lies where it lay relative to the points: both moved by the same shift
        shift = pts[k, :n].double().mean(0)
        before = model @ T[k, :3, :3].double().T + T[k, :3, 3].double()
        after = model @ sub_T[k, :3, :3].double().T + sub_T[k, :3, 3].double()
        assert torch.allclose(after + shift, before, atol=1e-5)
        assert torch.allclose(sub[k].double() + shift, pts[k, :n].double(), atol=1e-6)
    assert torch.equal(T, torch.from_numpy(s.T_gt[idx]))   # the caller's targets are not changed


def test_pose_trainer_takes_fewer_points_than_prepared(pose_data):
    prepared = pose_data.samples.points.shape[1]
    trainer = PoseTrainer(CFG, pose_data, num_points=prepared // 2)
    loss, d, conf = trainer.forward_loss(pose_data.train_idx[:2])
    assert d.shape == conf.shape == (2, prepared // 2) and torch.isfinite(loss)
    for bad in (0, prepared + 1):
        with pytest.raises(ValueError, match="num_points must be in"):
            PoseTrainer(CFG, pose_data, num_points=bad)


def test_detector_training_reduces_loss_on_a_tiny_batch(sim_bop_dataset, tmp_path):
    torch.manual_seed(0)
    dd = load_detector_data(CFG, [sim_bop_dataset], seed=0, cache_dir=tmp_path, progress=False)
    trainer = DetectorTrainer(CFG, dd, NO_AUGMENT)
    x, targets = trainer.batch(dd.train_idx[:2], None)
    assert sum(len(t) for t in targets) > 0
    first, last = _overfit(trainer, lambda: trainer.loss(trainer.detector.forward_raw(x), targets)[0], 25, 3e-3)
    assert last < 0.7 * first, (first, last)


def test_bf16_autocast_runs_the_networks_in_bfloat16_and_still_learns(pose_data, sim_bop_dataset, tmp_path):
    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data, amp=True)
    idx = pose_data.train_idx[:4]
    for net in trainer.nets.values():
        net.eval()
    with torch.no_grad():
        loss32, d32, _ = trainer.forward_loss(idx)
        loss16, d16, _ = trainer.forward_loss(idx, amp=True)
    assert loss16.dtype == torch.float32 and d16.dtype == torch.float32      # the loss is float32 either way
    assert not torch.equal(d16, d32)                                         # bfloat16 did run
    assert torch.allclose(d16, d32, rtol=0.05, atol=0.01)
    first, last = _overfit(trainer, lambda: trainer.step(idx, np.random.default_rng(0))[0], 30, 2e-3)
    assert last < 0.7 * first, (first, last)
    assert all(p.dtype == torch.float32 for net in trainer.nets.values() for p in net.parameters())

    torch.manual_seed(0)
    dd = load_detector_data(CFG, [sim_bop_dataset], seed=0, cache_dir=tmp_path, progress=False)
    det = DetectorTrainer(CFG, dd, NO_AUGMENT, amp=True)
    first, last = _overfit(det, lambda: det.step(np.arange(min(2, len(dd.train_idx))), np.random.default_rng(0))[0],
                           25, 3e-3)
    assert last < 0.7 * first, (first, last)


def test_flip_keeps_boxes_on_the_object():
    img = np.zeros((20, 40, 3), np.uint8)
    img[5:10, 2:8] = 255
    flipped, boxes = flip_horizontal(img, np.array([[2, 5, 8, 10]]))
    x1, y1, x2, y2 = boxes[0].astype(int)
    assert (x1, y1, x2, y2) == (32, 5, 38, 10)
    assert flipped[y1:y2, x1:x2].min() == 255 and flipped.sum() == img.sum()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("window_hw", [(64, 160), (96, 96), (32, 64)])
def test_place_in_window_moves_boxes_with_the_image(seed, window_hw):
    img = np.full((64, 160, 3), 114, np.uint8)
    img[20:40, 50:100] = 255
    out, boxes = place_in_window(img, np.array([[50, 20, 100, 40]]), window_hw, np.random.default_rng(seed),
                                 0.4, 2.0, 0.1)
    assert out.shape == (*window_hw, 3)
    ys, xs = np.nonzero(out[..., 0] > 200)
    if len(boxes):   # the white block's pixel extent is the moved box (to a pixel of interpolation)
        np.testing.assert_allclose([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], boxes[0], atol=1.5)
    else:            # dropped: less than a fifth of it is left in the window
        assert len(xs) < 0.2 * 50 * 20 * (out.shape[1] / 160) ** 2 * 4


def test_place_in_window_without_zoom_or_shift_is_the_letterbox():
    img = np.random.default_rng(0).integers(0, 255, (50, 100, 3), dtype=np.uint8)
    boxes = np.array([[0, 10, 30, 40], [40, 10, 60, 30]], np.float32)
    from pallet6d.runtime.detector import letterbox
    for hw in [(50, 100), (64, 64), (32, 96)]:
        out, moved = place_in_window(img, boxes, hw, np.random.default_rng(0), 0.0, 1.0, 0.0)
        ref, lb = letterbox(img, hw)
        s = min(hw[0] / 50, hw[1] / 100)
        np.testing.assert_allclose(moved[:, [0, 2]], boxes[:, [0, 2]] * s + (hw[1] - 100 * s) / 2, atol=1e-4)
        np.testing.assert_allclose(moved[:, [1, 3]], boxes[:, [1, 3]] * s + (hw[0] - 50 * s) / 2, atol=1e-4)
        if hw == (50, 100):
            np.testing.assert_array_equal(out, img)
        assert abs(lb.scale_x - s) < 0.02


def test_place_in_window_clips_and_drops_boxes_pushed_out():
    img = np.full((50, 100, 3), 114, np.uint8)
    boxes = np.array([[0, 10, 30, 40], [90, 10, 100, 20], [40, 10, 60, 30]], np.float32)

    class Draws:  # rng stand-in: shift +0.2 of the width beyond the centre... as draws of uniform(-1, 1)
        def __init__(self):
            self.values = [0.4, 1.0]   # tx = 0.4 * 0.5 * 100 = 20 px, ty = 1.0 * 0.5 * 50 = 25 px

        def uniform(self, lo, hi):
            return self.values.pop(0)

    out, moved = place_in_window(img, boxes, (50, 100), Draws(), 0.0, 1.0, 0.5)
    # +20 px right, +25 px down: the first and third boxes are cut at the bottom (half or more stays: kept),
    # the second leaves the image
    np.testing.assert_allclose(moved, [[20, 35, 50, 50], [60, 35, 80, 50]])
    assert out[:25].max() == 114
    assert place_in_window(img, np.zeros((0, 4)), (64, 64), np.random.default_rng(0), 0.4, 2.0, 0.1)[1].shape == (0, 4)


def test_detector_batches_take_one_input_size_and_validation_letterboxes_like_the_runtime(sim_bop_dataset, tmp_path):
    dd = load_detector_data(CFG, [sim_bop_dataset], seed=0, cache_dir=tmp_path, progress=False)
    sizes = [tuple(CFG.detector.input_hw), (96, 96)]
    trainer = DetectorTrainer(CFG, dd, AugmentConfig(), input_sizes=sizes)
    seen = set()
    for seed in range(12):
        x, _ = trainer.batch(dd.train_idx[:2], np.random.default_rng(seed), sizes[seed % 2])
        seen.add(tuple(x.shape[2:]))
        assert torch.isfinite(trainer.step(np.arange(min(2, len(dd.train_idx))), np.random.default_rng(seed))[0])
    assert seen == set(sizes)
    from pallet6d.runtime.detector import choose_input_hw, letterbox
    i = int(dd.val_idx[0])
    hw = choose_input_hw(dd.samples.images[i].shape[:2], sizes)
    x, _ = trainer.batch(np.array([i]), None)
    ref, _ = letterbox(dd.samples.images[i], hw)
    np.testing.assert_allclose(x[0].permute(1, 2, 0).numpy() * 255.0, ref, atol=1e-3)
    with pytest.raises(ValueError, match="multiples of 32"):
        DetectorTrainer(CFG, dd, AugmentConfig(), input_sizes=[(100, 96)])


def test_detector_batches_are_the_same_with_loader_threads(sim_bop_dataset, tmp_path):
    """Each frame's augmentation has its own seed drawn up front: threads change the speed, never the batch."""
    dd = load_detector_data(CFG, [sim_bop_dataset], seed=0, cache_dir=tmp_path, progress=False)
    one = DetectorTrainer(CFG, dd, AugmentConfig())
    four = DetectorTrainer(CFG, dd, AugmentConfig(), loader_threads=4)
    idx = dd.train_idx[:4]
    for rng in (lambda: np.random.default_rng(3), lambda: None):
        (x1, t1), (x4, t4) = one.batch(idx, rng()), four.batch(idx, rng())
        assert torch.equal(x1, x4) and all(torch.equal(a, b) for a, b in zip(t1, t4))
    assert not torch.equal(one.batch(idx, np.random.default_rng(3))[0], one.batch(idx, np.random.default_rng(4))[0])
    with pytest.raises(ValueError, match="loader_threads"):
        DetectorTrainer(CFG, dd, AugmentConfig(), loader_threads=0)


def test_init_starts_from_a_checkpoints_weights(pose_run, sim_bop_dataset, tmp_path):
    from pallet6d.export.fusion import build_fusion
    from pallet6d.export.pose import build_pose

    run, _ = pose_run
    nets = {"fusion": build_fusion(CFG.fusion), "pose": build_pose(CFG.pose, CFG.fusion.feature_dim)}
    info = load_init_weights(run / "best.pt", nets)
    best = load_checkpoint(run / "best.pt")
    assert all(torch.equal(v, best["pose"][k]) for k, v in nets["pose"].state_dict().items())
    assert info["stage"] == "pose" and len(info["sha256"]) == 64 and info["checkpoint"] == str(run / "best.pt")
    with pytest.raises(ValueError, match="no 'detector' weights"):
        load_init_weights(run / "best.pt", {"detector": torch.nn.Linear(2, 2)})
    with pytest.raises(ValueError, match="do not fit"):
        load_init_weights(run / "best.pt", {"pose": torch.nn.Linear(2, 2)})
    # a fine-tuning run records where its weights came from
    train_pose(CFG, [sim_bop_dataset], tmp_path / "ft",
               LoopSettings(epochs=1, batch=4, lr=1e-4, seed=1), variants=1, progress=False, init=run / "best.pt")
    ft = load_checkpoint(tmp_path / "ft" / "last.pt")["provenance"]
    assert ft["init"]["sha256"] == info["sha256"]
    # ... and how those weights were trained, so a chain of fine-tuning runs is reproducible from its last link
    assert ft["init"]["provenance"]["command"] == best["provenance"]["command"]
    assert ft["init"]["provenance"]["seed"] == best["provenance"]["seed"]


def test_box_jitter_and_depth_augmentation_are_seeded_and_sane():
    box = np.array([100.0, 50.0, 200.0, 100.0])
    a = jitter_box(box, np.random.default_rng(1), 0.08, 0.05)
    assert np.array_equal(a, jitter_box(box, np.random.default_rng(1), 0.08, 0.05))
    boxes = np.array([jitter_box(box, np.random.default_rng(i), 0.08, 0.05) for i in range(200)])
    assert np.all(boxes[:, 2] > boxes[:, 0]) and abs(np.mean(boxes[:, 2] - boxes[:, 0]) - 100) < 5
    depth = np.full((30, 40), 2.0, np.float32)
    depth[0, 0] = 0.0
    out = augment_depth(depth, np.random.default_rng(0), AugmentConfig(depth_dropout_prob=1.0))
    assert out[0, 0] == 0.0 and (out == 0).sum() > 1 and np.all(out >= 0)
    assert 0 < np.std(out[out > 0] - 2.0) < 0.05


def test_cache_is_reused_and_invalidated(sim_bop_dataset, tmp_path):
    spec = pose_input_spec(CFG)
    calls = []

    def build(variants):
        calls.append(variants)
        return build_pose_samples(sim_bop_dataset, spec, variants, 0, NO_AUGMENT)

    a, fp = load_or_build("pose", sim_bop_dataset, {"v": 1}, tmp_path, lambda: build(1))
    b, _ = load_or_build("pose", sim_bop_dataset, {"v": 1}, tmp_path, lambda: build(1))
    assert calls == [1] and np.array_equal(a.points, b.points) and np.array_equal(a.T_gt, b.T_gt)
    load_or_build("pose", sim_bop_dataset, {"v": 2}, tmp_path, lambda: build(2))
    assert calls == [1, 2]
    assert fp["frames"] == 3 and fp["sim"][0]["preset"] == "virtual-occluded" and fp["sim"][0]["seed"] == 7
    assert fp == dataset_fingerprint(sim_bop_dataset)


def test_lr_schedule():
    s = LoopSettings(epochs=10, batch=2, lr=1e-3, warmup_epochs=1.0)
    assert lr_at(s, 0.0) < 1e-4 and lr_at(s, 1.0) == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5 * (1 + np.cos(0.1 * np.pi))))
    assert lr_at(s, 10.0) == pytest.approx(5e-5)
    with pytest.raises(ValueError):
        LoopSettings(epochs=0, batch=2, lr=1e-3)


@pytest.mark.parametrize("freeze", [False, True])
def test_freeze_bn_stats_keeps_running_statistics_while_weights_learn(tmp_path, freeze):
    torch.manual_seed(0)
    nn = torch.nn
    net = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.ReLU(), nn.Conv2d(4, 1, 1))
    x = torch.randn(8, 3, 6, 6) * 3.0 + 2.0     # far from the fresh statistics (mean 0, variance 1)
    before = {k: v.clone() for k, v in net.state_dict().items()}

    def step(idx, rng):
        assert net[1].training is not freeze and net[0].training      # the rest of the net trains either way
        return net(x[idx]).square().mean(), {}

    s = LoopSettings(epochs=1, batch=4, lr=1e-2, seed=0, freeze_bn_stats=freeze)
    train_epochs(tmp_path, "toy", "toy", {"net": net}, torch.optim.SGD(net.parameters(), lr=1e-2), s, len(x), step,
                 lambda: {"metric": 0.0}, {}, progress=False)
    after = net.state_dict()
    stats_kept = all(torch.equal(before[f"1.{k}"], after[f"1.{k}"]) for k in ("running_mean", "running_var"))
    assert stats_kept is freeze
    assert not torch.equal(before["1.weight"], after["1.weight"])
    assert not torch.equal(before["0.weight"], after["0.weight"])
    assert load_checkpoint(tmp_path / "last.pt")["provenance"]["freeze_bn_stats"] is freeze
    assert keep_bn_stats(net.train()) == 1 and not net[1].training and net[0].training


@pytest.fixture(scope="module")
def pose_run(sim_bop_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("pose_run")
    s = LoopSettings(epochs=1, batch=4, lr=1e-3, seed=3)
    train_pose(CFG, [sim_bop_dataset], run, s, variants=1, command="test", progress=False)
    first = load_checkpoint(run / "last.pt")
    train_pose(CFG, [sim_bop_dataset], run, LoopSettings(epochs=2, batch=4, lr=1e-3, seed=3), variants=1,
               resume=True, progress=False)
    return run, first


def test_checkpoint_and_resume_continue_at_the_right_epoch(pose_run):
    run, first = pose_run
    assert first["epoch"] == 1 and first["stage"] == "pose" and first["config"] == "tiny"
    prov = first["provenance"]
    assert prov["seed"] == 3 and prov["command"] == "test" and prov["data"][0]["frames"] == 3
    last = load_checkpoint(run / "last.pt")
    assert last["epoch"] == 2
    lines = [json.loads(x) for x in (run / "train_log.jsonl").read_text().splitlines()]
    assert [x["epoch"] for x in lines] == [1, 2]
    assert all(np.isfinite(x["train_loss"]) and x["seconds"] >= 0 and "lr" in x for x in lines)
    changed = any(not torch.equal(first["pose"][k], last["pose"][k]) for k in first["pose"])
    assert changed
    assert (run / "best.pt").exists()
    with pytest.raises(ValueError, match="not a pallet6d training checkpoint|no checkpoint"):
        load_checkpoint(run / "missing.pt")


def test_checkpoint_exports_to_a_bundle_the_runtime_loads(pose_run, sim_bop_dataset, tmp_path):
    from pallet6d.export.bundle_export import export_bundle
    from pallet6d.export.train_cli import merge_checkpoints
    from pallet6d.export.train_detector import train_detector
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    run, _ = pose_run
    train_detector(CFG, [sim_bop_dataset], tmp_path / "det", LoopSettings(epochs=1, batch=2, lr=1e-3),
                   progress=False)
    merged = merge_checkpoints(tmp_path / "det" / "last.pt", run / "best.pt", tmp_path / "model.pt")
    assert set(merged["provenance"]) == {"detector", "pose"}
    with pytest.raises(ValueError, match="detector and a pose"):
        merge_checkpoints(run / "best.pt", run / "best.pt", tmp_path / "bad.pt")
    # one detector serves every variant with the same detector network (edge and its ablation
    # edge-densefusion); a detector of another network is refused
    det_ckpt = torch.load(tmp_path / "det" / "last.pt", weights_only=False)
    pose_ckpt = torch.load(run / "best.pt", weights_only=False)
    torch.save({**det_ckpt, "config": "edge"}, tmp_path / "det-edge.pt")
    torch.save({**pose_ckpt, "config": "edge-densefusion"}, tmp_path / "pose-edf.pt")
    assert merge_checkpoints(tmp_path / "det-edge.pt", tmp_path / "pose-edf.pt", tmp_path / "m2.pt")["config"] \
        == "edge-densefusion"
    with pytest.raises(ValueError, match="whose detector differs"):
        merge_checkpoints(tmp_path / "det-edge.pt", run / "best.pt", tmp_path / "m3.pt")
    # the detector's scores moved up: its class output convs' biases alone change, by the offset, recorded
    shifted = merge_checkpoints(tmp_path / "det" / "last.pt", run / "best.pt", tmp_path / "m4.pt", 0.288)
    moved = {k for k, v in merged["detector"].items() if not torch.equal(v, shifted["detector"][k])}
    assert moved and all(k.startswith("head.cls.") and k.endswith(".2.bias") for k in moved)
    for k in moved:
        torch.testing.assert_close(shifted["detector"][k] - merged["detector"][k],
                                   torch.full_like(merged["detector"][k], 0.288))
    assert shifted["provenance"]["detector"]["logit_offset"] == 0.288
    assert "logit_offset" not in merged["provenance"]["detector"]
    with pytest.raises(ValueError, match="finite"):
        merge_checkpoints(tmp_path / "det" / "last.pt", run / "best.pt", tmp_path / "m5.pt", float("nan"))
    calib = make_calibration_set(CFG, frames=2, max_crops=4, seed=0, synthetic=True)
    manifest = export_bundle(CFG, tmp_path / "bundle", checkpoint=tmp_path / "model.pt", calib=calib)
    # the training recipe, data and seeds travel into the bundle's provenance
    training = manifest.report["provenance"]["training"]
    assert set(training) == {"detector", "pose"} and training["pose"]["seed"] == merged["provenance"]["pose"]["seed"]
    assert training["detector"]["stage"] == "detector" and training["pose"]["stage"] == "pose"
    assert training["pose"]["data"][0]["frames"] == len(BopDataset(sim_bop_dataset))
    est = PalletEstimator.from_bundle(tmp_path / "bundle", threads=1, min_fit=0.0, structure=None)
    f = BopDataset(sim_bop_dataset)[0]
    boxes = [[x, y, x + w, y + h] for x, y, w, h in (g.bbox_visib_xywh for g in f.gts if g.visib_fract > 0.3)]
    result = est.estimate_boxes(f.rgb, f.depth_m, f.K, boxes_xyxy=boxes)
    assert len(result.poses) + len(result.rejected) == len(boxes)
    assert all(np.isfinite(p.T_cam_pallet).all() for p in result.poses)
    # the exported pose graph carries the trained weights, not a fresh initialisation
    import onnxruntime as ort
    from pallet6d.export.pose import build_pose

    net = build_pose(CFG.pose, CFG.fusion.feature_dim).eval()
    net.load_state_dict(torch.load(tmp_path / "model.pt", weights_only=True)["pose"])
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.3, (2, CFG.pose.num_points, 3)).astype(np.float32)
    feats = rng.normal(0, 1, (2, CFG.pose.num_points, CFG.fusion.feature_dim)).astype(np.float32)
    sess = ort.InferenceSession(str(tmp_path / "bundle" / "pose.onnx"), providers=["CPUExecutionProvider"])
    conf_onnx = sess.run(["conf"], {"points": pts, "features": feats})[0]      # the most confident point's
    with torch.no_grad():
        conf_torch = net(torch.from_numpy(pts), torch.from_numpy(feats))[2].max(1).values.numpy()
    np.testing.assert_allclose(conf_onnx, conf_torch, atol=1e-4)


def test_detector_trained_at_another_input_size_exports_at_that_size(pose_run, sim_bop_dataset, tmp_path):
    import dataclasses

    from pallet6d.export.bundle_export import export_bundle, trained_input_hw
    from pallet6d.export.train_cli import merge_checkpoints
    from pallet6d.export.train_detector import train_detector
    from pallet6d.runtime.bundle import load_bundle

    big = CFG.replace(detector=dataclasses.replace(CFG.detector, input_hw=(96, 160)))
    train_detector(big, [sim_bop_dataset], tmp_path / "det", LoopSettings(epochs=1, batch=2, lr=1e-3),
                   progress=False)
    det = load_checkpoint(tmp_path / "det" / "last.pt")
    assert det["provenance"]["input_hw"] == [96, 160] and trained_input_hw(det) == (96, 160)
    # trained channels-last (`conv_layout`), stored contiguous: a checkpoint's layout is the same whoever trained it
    assert det["detector"]["stem.conv.weight"].dim() == 4
    assert all(v.is_contiguous() for v in det["detector"].values())
    with pytest.raises(ValueError, match="trained at input"):   # resuming at the config's size is refused
        train_detector(CFG, [sim_bop_dataset], tmp_path / "det", LoopSettings(epochs=2, batch=2, lr=1e-3),
                       resume=True, progress=False)
    merged = merge_checkpoints(tmp_path / "det" / "last.pt", pose_run[0] / "best.pt", tmp_path / "model.pt")
    assert trained_input_hw(merged) == (96, 160)
    calib = make_calibration_set(big, frames=2, max_crops=4, seed=0, synthetic=True)
    export_bundle(CFG, tmp_path / "bundle", checkpoint=tmp_path / "model.pt", calib=calib)
    assert tuple(load_bundle(tmp_path / "bundle").detector.input_hw) == (96, 160)
    assert trained_input_hw({"provenance": {"stage": "pose"}}) is None and trained_input_hw({}) is None


def test_train_cli_parses_the_detector_input_size():
    import argparse

    from pallet6d.export.train_cli import _hw

    assert _hw("256x832") == (256, 832) and _hw("256X832") == (256, 832)
    for bad in ("256", "256x", "axb", "1x2x3"):
        with pytest.raises(argparse.ArgumentTypeError, match="HxW"):
            _hw(bad)


def test_distillation_pulls_the_fusion_features_towards_the_teachers(pose_data, bundle_dir):
    from pallet6d.export.fusion import build_fusion
    from pallet6d.export.train_pose import _teacher

    teacher, record = _teacher(bundle_dir, CFG)
    assert record["config"] == "tiny"
    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data, teacher=teacher, distill_weight=1.0)
    idx = pose_data.train_idx[:4]
    first, last = _overfit(trainer, lambda: trainer.forward_loss(idx)[0], 30, 2e-3)
    assert last < 0.7 * first, (first, last)
    assert 0 <= trainer.feature_error < 1.0          # closer to the teacher's features than their mean is
    same = PoseTrainer(CFG, pose_data, teacher=build_fusion(CFG.fusion))
    same.fusion.load_state_dict(same.teacher.state_dict())
    same.fusion.eval()                                  # BatchNorm on its running statistics, as the teacher
    same.forward_loss(idx)
    assert same.feature_error == pytest.approx(0.0, abs=1e-9)     # a network is its own perfect student
    assert not any(p.requires_grad for p in trainer.teacher.parameters())


def test_distillation_run_records_its_teacher_and_refuses_one_that_takes_other_crops(sim_bop_dataset, bundle_dir,
                                                                                       tmp_path):
    from pallet6d.export.pose import build_pose
    entry = train_pose(CFG, [sim_bop_dataset], tmp_path / "d", LoopSettings(epochs=1, batch=4, lr=1e-3, seed=1),
                       variants=1, progress=False, distill=bundle_dir, distill_weight=0.5, init=bundle_dir,
                       freeze_pose=True)
    assert np.isfinite(entry["val_feature_error"]) and np.isfinite(entry["train_feat"])
    ckpt = load_checkpoint(tmp_path / "d" / "last.pt")
    prov = ckpt["provenance"]
    assert prov["distill"]["weight"] == 0.5 and prov["distill"]["config"] == "tiny" and prov["freeze_pose"]
    start = build_pose(CFG.pose, CFG.fusion.feature_dim)
    load_init_weights(bundle_dir, {"pose": start})
    for k, v in start.state_dict().items():          # the pose network stayed as --init gave it
        assert torch.equal(ckpt["pose"][k], v), k
    with pytest.raises(ValueError, match="does not take and give"):
        train_pose(get_config("edge2-slim"), [sim_bop_dataset], tmp_path / "e",
                   LoopSettings(epochs=1, batch=4, lr=1e-3), variants=1, progress=False, distill=bundle_dir)


def test_pose_only_trains_the_pose_network_on_the_fixed_fusions_features_computed_once(sim_bop_dataset, bundle_dir,
                                                                                      tmp_path, pose_data):
    from pallet6d.export.fusion import build_fusion
    from pallet6d.export.pose import build_pose

    trainer = PoseTrainer(CFG, pose_data, trainable="pose", num_points=20)
    load_init_weights(bundle_dir, trainer.nets)
    trainer.fusion.train()                       # the cache is computed in inference mode whatever the mode
    cache = trainer.cached_features()
    assert cache.shape == (len(pose_data.samples.frame), 20, CFG.fusion.feature_dim)
    assert trainer.cached_features() is cache    # computed once
    s, idx = pose_data.samples, pose_data.train_idx[:3]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    trainer.fusion.eval()
    with torch.no_grad():
        own = trainer._features(trainer.fusion, t(s.rgb_crops[idx]), t(s.depth_crops[idx]), t(s.choose[idx][:, :20]))
    torch.testing.assert_close(torch.from_numpy(cache[idx]).float(), own, atol=2e-3, rtol=2e-3)   # float16 copies
    with pytest.raises(RuntimeError, match="trainable 'pose'"):
        PoseTrainer(CFG, pose_data).cached_features()
    with pytest.raises(ValueError, match="keeps the fusion network fixed"):
        PoseTrainer(CFG, pose_data, trainable="pose", teacher=build_fusion(CFG.fusion))

    entry = train_pose(CFG, [sim_bop_dataset], tmp_path / "p",            # bfloat16 autocast, as a CPU run trains
                       LoopSettings(epochs=2, batch=4, lr=1e-3, seed=1, amp=True), variants=1, progress=False,
                       init=bundle_dir, pose_only=True)
    assert np.isfinite(entry["val_metric"])
    ckpt = load_checkpoint(tmp_path / "p" / "last.pt")
    assert ckpt["provenance"]["trainable"] == "pose_network"
    # built as the trainer builds it: its BatchNorm statistics come from a forward pass, whose rounding the layout moves
    fusion, pose = conv_layout(build_fusion(CFG.fusion)), build_pose(CFG.pose, CFG.fusion.feature_dim)
    load_init_weights(bundle_dir, {"fusion": fusion, "pose": pose})
    for k, v in fusion.state_dict().items():     # the fusion network stayed as --init gave it, BatchNorm included
        assert torch.equal(ckpt["fusion"][k], v), k
    assert any(not torch.equal(ckpt["pose"][k], v) for k, v in pose.state_dict().items())
    with pytest.raises(ValueError, match="exclude each other"):
        train_pose(CFG, [sim_bop_dataset], tmp_path / "q", LoopSettings(epochs=1, batch=4, lr=1e-3), variants=1,
                   progress=False, pose_only=True, freeze_pose=True)


def test_negative_crops_are_the_runtimes_inputs_on_the_detectors_boxes(bundle_dir, tmp_path):
    from pallet6d.export.negative_crops import build_negative_crops, load_negative_crops
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.pose_inputs import prepare_pose_inputs
    from pallet6d.sim.pallet_free import render_pallet_free

    spec = pose_input_spec(CFG)
    crops = build_negative_crops(bundle_dir, spec, ["virtual-clean"], frames=1, seed=3, score_threshold=0.0,
                                 max_boxes=2)
    assert 1 <= len(crops) <= 4 and crops.choose.shape[1] == spec.num_points
    assert crops.points.shape == (len(crops), spec.num_points, 3)
    # the first crop: frame 0 of the preset (loads left hanging), its detector's best box
    rgb, depth_m, K, _ = render_pallet_free("virtual-clean", 3, 0, set_down=False)
    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0)    # fp32: the tiny bundle's
    box = est.detect(rgb).boxes_xyxy[:1]
    est.close()
    batch = prepare_pose_inputs(rgb, depth_m, K, box, spec, np.random.default_rng((3, 0)))
    if batch.n_valid[0] >= 50:
        np.testing.assert_array_equal(crops.rgb_crops[0], batch.rgb_crops[0])
        np.testing.assert_array_equal(crops.choose[0], batch.choose[0])
        np.testing.assert_array_equal(crops.points[0], batch.points[0])
    again, record = load_negative_crops(bundle_dir, spec, ["virtual-clean"], 1, 3, tmp_path, score_threshold=0.0,
                                        max_boxes=2)
    cached, _ = load_negative_crops(bundle_dir, spec, ["virtual-clean"], 1, 3, tmp_path, score_threshold=0.0,
                                    max_boxes=2)
    np.testing.assert_array_equal(again.depth_crops, crops.depth_crops)
    np.testing.assert_array_equal(cached.choose, crops.choose)
    assert record["crops"] == len(crops) and len(record["detector_sha256"]) == 64
    with pytest.raises(ValueError, match="no detection"):
        build_negative_crops(bundle_dir, spec, ["virtual-clean"], frames=1, seed=3, score_threshold=1.0)
    with pytest.raises(ValueError, match="need a model bundle"):
        load_negative_crops(tmp_path, spec, ["virtual-clean"], 1, 3, None)


@pytest.fixture(scope="module")
def negatives(bundle_dir):
    """At least 16 negative crops of the tiny bundle's detector (repeated: a random detector boxes few)."""
    from pallet6d.export.negative_crops import build_negative_crops

    crops = build_negative_crops(bundle_dir, pose_input_spec(CFG), ["virtual-clean"], frames=2, seed=3,
                                 score_threshold=0.0, max_boxes=4)
    return crops.take(np.arange(len(crops)).repeat(16 // len(crops) + 1))


def test_negative_crops_pull_the_features_there_and_need_a_use(pose_data, bundle_dir, negatives):
    from pallet6d.export.train_pose import _teacher

    many = negatives
    with pytest.raises(ValueError, match="need a use"):
        PoseTrainer(CFG, pose_data, negatives=many)
    teacher, _ = _teacher(bundle_dir, CFG)
    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data, teacher=teacher, negatives=many, negatives_per_step=4)
    assert len(trainer.negatives_val) == len(many) // 8 and not set(trainer.negatives_val) & set(trainer.negatives_train)
    with torch.no_grad():       # as the training loop validates
        before = trainer.validate(batch=4)["negative_feature_error"]
    rng = np.random.default_rng(0)
    opt = torch.optim.Adam(trainer.fusion.parameters(), lr=2e-3)
    trainer.fusion.train()
    for _ in range(30):
        loss, info = trainer.step(pose_data.train_idx[:4], rng)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert np.isfinite(info["feat_neg"])
    with torch.no_grad():
        after = trainer.validate(batch=4)["negative_feature_error"]
    assert after < 0.7 * before, (before, after)


def test_the_confidence_head_alone_learns_to_refuse_negatives_and_keeps_every_pose(pose_data, negatives):
    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data, negatives=negatives, negative_conf_weight=1.0, trainable="conf")
    trainer.pose.requires_grad_(False)
    trainer.pose.head_c.requires_grad_(True)
    fusion_before = {k: v.clone() for k, v in trainer.fusion.state_dict().items()}
    others_before = {k: v.clone() for k, v in trainer.pose.state_dict().items() if not k.startswith("head_c.")}
    for net in trainer.nets.values():
        net.eval()                                      # as the training loop validates
    with torch.no_grad():
        before = trainer.validate(batch=4)
    idx = pose_data.train_idx[:4]
    with torch.no_grad():
        quat0, trans0, _ = trainer.pose(*_pose_inputs(trainer, idx))
    opt = torch.optim.Adam([p for p in trainer.pose.parameters() if p.requires_grad], lr=1e-2)
    rng = np.random.default_rng(0)
    for net in trainer.nets.values():
        net.train()
    for _ in range(30):
        loss, info = trainer.step(idx, rng)
        opt.zero_grad()
        loss.backward()
        opt.step()
    for net in trainer.nets.values():
        net.eval()
    with torch.no_grad():
        after = trainer.validate(batch=4)
        quat1, trans1, _ = trainer.pose(*_pose_inputs(trainer, idx))
    assert "conf_neg" in info and "feat_neg" not in info
    assert after["negative_conf_pass"] <= before["negative_conf_pass"]
    assert info["conf_neg"] < 0.05                   # every negative point's confidence near 0
    for k, v in trainer.fusion.state_dict().items():  # BatchNorm statistics included: the fusion ran in eval mode
        assert torch.equal(v, fusion_before[k]), k
    for k, v in trainer.pose.state_dict().items():
        if not k.startswith("head_c."):
            assert torch.equal(v, others_before[k]), k
    torch.testing.assert_close(quat1, quat0)
    torch.testing.assert_close(trans1, trans0)
    with pytest.raises(ValueError, match="trainable must be one of"):
        PoseTrainer(CFG, pose_data, trainable="detector")


def test_a_confidence_teacher_holds_the_pallets_confidences_where_they_were(pose_data, negatives):
    import copy

    torch.manual_seed(0)
    trainer = PoseTrainer(CFG, pose_data, trainable="conf")
    teacher = copy.deepcopy(trainer.pose)
    kept = PoseTrainer(CFG, pose_data, trainable="conf", conf_teacher=teacher)
    kept.fusion.load_state_dict(trainer.fusion.state_dict())
    kept.pose.load_state_dict(trainer.pose.state_dict())
    idx = pose_data.train_idx[:4]
    grads = {}
    for name, t in (("eq4", trainer), ("teacher", kept)):
        t.pose.requires_grad_(False)
        t.pose.head_c.requires_grad_(True)
        loss, _ = t.step(idx, np.random.default_rng(0))
        loss.backward()
        grads[name] = max(float(p.grad.abs().max()) for p in t.pose.head_c.parameters())
    # the same network as its teacher: the pallets' term is at its minimum, nothing moves; eq. 4's pulls
    assert grads["teacher"] < 1e-6 < grads["eq4"], grads
    with pytest.raises(ValueError, match="needs trainable='conf'"):
        PoseTrainer(CFG, pose_data, conf_teacher=teacher)
    kept = PoseTrainer(CFG, pose_data, negatives=negatives, negative_conf_weight=1.0, trainable="conf",
                       conf_teacher=teacher)
    kept.fusion.load_state_dict(trainer.fusion.state_dict())
    kept.pose.load_state_dict(teacher.state_dict())
    kept.pose.requires_grad_(False)
    kept.pose.head_c.requires_grad_(True)
    opt = torch.optim.Adam(kept.pose.head_c.parameters(), lr=1e-2)
    rng = np.random.default_rng(0)
    seen = []
    for _ in range(30):
        loss, info = kept.step(idx, rng)
        opt.zero_grad()
        loss.backward()
        opt.step()
        seen.append(info["conf_neg"])
    assert np.mean(seen[-5:]) < 0.5 * np.mean(seen[:5]), seen     # the negatives moved


def test_the_negatives_confidence_term_can_read_their_most_confident_points(pose_data, negatives):
    torch.manual_seed(0)
    n = negatives.choose.shape[1]
    best = PoseTrainer(CFG, pose_data, negatives=negatives, negative_conf_weight=1.0, negative_conf_top=1 / n)
    every = PoseTrainer(CFG, pose_data, negatives=negatives, negative_conf_weight=1.0)
    every.nets["fusion"].load_state_dict(best.fusion.state_dict())
    every.nets["pose"].load_state_dict(best.pose.state_dict())
    for t in (best, every):
        for net in t.nets.values():
            net.eval()
    idx = np.arange(min(3, len(negatives)))
    with torch.no_grad():
        b, e = best.negative_terms(idx), every.negative_terms(idx)
    # one point a crop: the best one, as the runtime decides by
    torch.testing.assert_close(b["conf_neg"], -torch.log1p(-b["conf_max"]).mean())
    assert float(b["conf_neg"]) >= float(e["conf_neg"])
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="negative_conf_top must be in"):
            PoseTrainer(CFG, pose_data, negatives=negatives, negative_conf_weight=1.0, negative_conf_top=bad)


def test_train_cli_keeps_pallet_conf_only_for_the_confidence_head(sim_bop_dataset, bundle_dir, tmp_path, capsys):
    from pallet6d.runtime.cli import main

    base = ["train", "pose", "--config", "tiny", "--data", str(sim_bop_dataset), "--out", str(tmp_path / "r"),
            "--epochs", "1", "--no-progress"]
    assert main([*base, "--keep-pallet-conf", "--init", str(bundle_dir)]) == 1
    assert "--keep-pallet-conf needs --conf-head-only and --init" in capsys.readouterr().err
    assert main([*base, "--keep-pallet-conf", "--conf-head-only"]) == 1
    assert "needs --conf-head-only and --init" in capsys.readouterr().err
    assert main(["train", "detector", "--config", "tiny", "--data", str(sim_bop_dataset), "--out",
                 str(tmp_path / "d"), "--keep-pallet-conf"]) == 2
    assert "are for the pose stage" in capsys.readouterr().err
    assert main([*base, "--verifier-target", "pallet"]) == 2
    assert "--verifier-target is for --verifier-only" in capsys.readouterr().err
    for bad in ("0", "1.5"):                # refused by train_pose before any data is read
        assert main([*base, "--calibrate-share", bad]) == 1
        assert f"--calibrate-share {float(bad)}: a share in (0, 1]" in capsys.readouterr().err
    assert main([*base, "--calibrate-share", "0.9", "--verifier-only"]) == 1
    assert "not with --verifier-only" in capsys.readouterr().err


def _pose_inputs(trainer, idx):
    """The pose network's inputs for training samples `idx`, as `forward_loss` makes them (fusion in eval mode)."""
    s = trainer.data.samples
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    trainer.fusion.eval()
    feats = trainer._features(trainer.fusion, t(s.rgb_crops[idx]), t(s.depth_crops[idx]), t(s.choose[idx]))
    return t(s.points[idx]), feats


def test_train_cli_refuses_negatives_without_a_use(sim_bop_dataset, bundle_dir, tmp_path, capsys):
    from pallet6d.runtime.cli import main

    base = ["train", "pose", "--config", "tiny", "--data", str(sim_bop_dataset), "--out", str(tmp_path / "r")]
    assert main([*base, "--negatives", "virtual-clean"]) == 2
    assert "--negatives needs a bundle whose detector" in capsys.readouterr().err
    assert main([*base, "--negatives", "virtual-clean", "--init", str(bundle_dir)]) == 2
    assert "negative crops (--negatives, --mismatched-frames) need a use" in capsys.readouterr().err
    assert main([*base, "--mismatched-frames", "2"]) == 2
    assert "need a use" in capsys.readouterr().err
    assert main(["train", "detector", "--config", "tiny", "--data", str(sim_bop_dataset), "--out",
                 str(tmp_path / "d"), "--mismatched-frames", "2"]) == 2
    assert "are for the pose stage" in capsys.readouterr().err


def test_mismatched_inputs_and_their_crops(sim_bop_dataset):
    from pallet6d.export.negative_crops import build_mismatched_crops
    from pallet6d.sim.mismatch import MISMATCHES, mismatched

    depth = np.array([[0.0, 2.0], [3.0, 4.0]], np.float32)
    K = np.array([[100.0, 0, 1], [0, 100.0, 1], [0, 0, 1]])
    other = np.ones_like(depth)
    np.testing.assert_array_equal(mismatched("other_frame", depth, K, other)[0], other)
    np.testing.assert_allclose(mismatched("depth_x0.1", depth, K, other)[0], depth * 0.1)
    K2 = mismatched("focal_x2", depth, K, other)[1]
    assert (K2[0, 0], K2[1, 1], K2[0, 2]) == (200.0, 200.0, 1.0) and K[0, 0] == 100.0   # the caller's K untouched
    np.testing.assert_array_equal(mismatched("flat_wall", depth, K, other)[0], np.full_like(depth, 3.0))
    with pytest.raises(ValueError, match="unknown mismatch"):
        mismatched("upside_down", depth, K, other)
    with pytest.raises(ValueError, match="needs another frame"):
        mismatched("other_frame", depth, K)
    spec = pose_input_spec(CFG)
    crops = build_mismatched_crops([sim_bop_dataset], spec, frames=2, seed=4)
    again = build_mismatched_crops([sim_bop_dataset], spec, frames=2, seed=4)
    assert len(crops) >= len(MISMATCHES) - 1 and crops.points.shape[1:] == (spec.num_points, 3)
    np.testing.assert_array_equal(crops.points, again.points)                  # seeded
    np.testing.assert_allclose(crops.points.mean(1), 0.0, atol=1e-4)           # centred, as the runtime's points


def test_a_dataset_named_twice_is_trained_twice_and_held_out_once(sim_bop_dataset, tmp_path):
    import shutil

    other = tmp_path / "other"
    shutil.copytree(sim_bop_dataset, other)
    cache = tmp_path / "cache"
    once = load_detector_data(CFG, [sim_bop_dataset, other], seed=0, cache_dir=cache, val_fraction=0.34,
                              progress=False)
    twice = load_detector_data(CFG, [sim_bop_dataset, other, sim_bop_dataset], seed=0, cache_dir=cache,
                               val_fraction=0.34, progress=False)
    assert len(twice.samples) == len(once.samples) == 6                 # loaded once
    assert np.array_equal(twice.val_idx, once.val_idx) and len(once.val_idx) == 2
    first = once.train_idx[once.train_idx < 3]                          # the first dataset's frames
    assert sorted(twice.train_idx.tolist()) == sorted(once.train_idx.tolist() + first.tolist())
    assert not set(twice.train_idx.tolist()) & set(twice.val_idx.tolist())
    assert twice.fingerprints[0]["repeat"] == 2 and "repeat" not in twice.fingerprints[1]

    p_once = load_pose_data(CFG, [sim_bop_dataset, other], variants=1, seed=0, aug=NO_AUGMENT, cache_dir=cache,
                            val_fraction=0.34, progress=False)
    p_twice = load_pose_data(CFG, [other, sim_bop_dataset, other], variants=1, seed=0, aug=NO_AUGMENT,
                             cache_dir=cache, val_fraction=0.34, progress=False)
    assert len(p_twice.samples) == len(p_once.samples)
    held = set(p_twice.samples.frame[p_twice.val_idx].tolist())
    assert held and not held & set(p_twice.samples.frame[p_twice.train_idx].tolist())
    frame = p_twice.samples.frame
    times = np.bincount(frame[p_twice.train_idx], minlength=6)       # training samples per frame
    for f in np.unique(frame[p_twice.train_idx]):                    # frames 0-2: `other`, named twice
        assert times[f] == (2 if f < 3 else 1) * np.sum(frame == f)
