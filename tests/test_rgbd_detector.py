"""An RGB-D detector: depth as a fourth input channel, letterboxed like the image, through training samples,
their cache and augmentation, a warm start from an RGB detector, export, the manifest and the runtime."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from pallet6d.runtime.detector import depth_channel, letterbox, letterbox_depth
from pallet6d.runtime.manifest import DetectorSpec
from pallet6d.runtime.manifest_fields import FieldError

torch = pytest.importorskip("torch")

from pallet6d.export.calib_data import make_calibration_set  # noqa: E402
from pallet6d.export.config import DetectorConfig, get_config  # noqa: E402
from pallet6d.export.detector import build_detector, widen_input_channels  # noqa: E402
from pallet6d.export.train_data import (NO_AUGMENT, DetectorSamples, build_detector_samples, load_or_build,  # noqa: E402
                                        place_in_window, place_rgbd_in_window)
from pallet6d.export.train_data import _objects as _obj  # noqa: E402
from pallet6d.export.train_detector import DetectorData, DetectorTrainer  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_depth_is_letterboxed_where_the_image_is_with_no_data_in_the_padding():
    rgb = np.zeros((100, 300, 3), np.uint8)
    depth = np.tile(np.linspace(1.0, 4.0, 300, dtype=np.float32), (100, 1))
    depth[:, 150:] = 0.0
    img, lb = letterbox(rgb, (192, 320))
    d = letterbox_depth(depth, lb)
    assert d.shape == (192, 320) and d.dtype == np.float32
    assert lb.pad_y > 0 and np.all(d[:lb.pad_y] == 0) and np.all(d[-lb.pad_y:] == 0)
    row = d[96]
    # nearest neighbour: every value is one of the input's, none invented between them
    assert set(np.round(row[row > 0], 5)) <= set(np.round(depth[0], 5))
    assert np.all(row[:150] > 0) and np.all(row[165:] == 0)
    with pytest.raises(ValueError, match="letterboxed image"):
        letterbox_depth(depth[:50], lb)


@pytest.mark.parametrize("depth, expected", [
    (np.array([[0.0, 5.0, 10.0, 25.0]], np.float32), [[0.0, 0.5, 1.0, 1.0]]),
    (np.array([[np.nan, -1.0, 2.0, np.inf]], np.float32), [[0.0, 0.0, 0.2, 1.0]]),
])
def test_depth_channel_scales_and_clips(depth, expected):
    np.testing.assert_allclose(depth_channel(depth, 10.0), expected, atol=1e-7)


def test_depth_channel_needs_a_positive_scale():
    with pytest.raises(ValueError, match="depth_max_m"):
        depth_channel(np.zeros((2, 2), np.float32), 0.0)


def test_manifest_writes_depth_max_only_for_an_rgbd_detector():
    base = dict(file="d.onnx", file_int8=None, input_name="images", output_name="output0", input_hw=(192, 640),
                letterbox_pad_value=114, pixel_scale=1 / 255, rgb_mean=(0, 0, 0), rgb_std=(1, 1, 1),
                channel_order="RGB", classes=("pallet",))
    rgb = DetectorSpec(**base)
    assert rgb.input_channels == 3 and "depth_max_m" not in rgb.to_dict()
    rgbd = DetectorSpec(**base, depth_max_m=10.0)
    assert rgbd.input_channels == 4 and rgbd.to_dict()["depth_max_m"] == 10.0
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(FieldError, match="depth_max_m"):
            DetectorSpec(**base, depth_max_m=bad)
    with pytest.raises(ValueError, match="depth_max_m"):
        DetectorConfig(depth_max_m=0.0)


def test_an_rgbd_detector_warm_started_from_an_rgb_one_ignores_depth_at_first():
    cfg = get_config("tiny").detector
    rgb_net = build_detector(cfg).eval()
    rgbd_net = build_detector(dataclasses.replace(cfg, depth_max_m=10.0)).eval()
    rgbd_net.load_state_dict(widen_input_channels(rgb_net.state_dict(), rgbd_net))
    x = torch.rand(1, 3, *cfg.input_hw)
    with torch.no_grad():
        expected = rgb_net(x)
        for depth in (torch.zeros(1, 1, *cfg.input_hw), torch.rand(1, 1, *cfg.input_hw)):
            torch.testing.assert_close(rgbd_net(torch.cat((x, depth), 1)), expected)
    assert rgbd_net.stem.conv.weight.shape[1] == 4


def test_place_rgbd_moves_depth_with_the_image_and_draws_the_same_window():
    rng_img = np.random.default_rng(0)
    image = rng_img.integers(0, 255, (60, 90, 3), dtype=np.uint8)
    depth = np.full((60, 90), 2.0, np.float32)
    depth[:, :45] = 3.0
    boxes = np.array([[10, 10, 40, 30, 0]], np.float32)
    img_a, boxes_a = place_in_window(image, boxes, (64, 96), np.random.default_rng(3), 0.4, 2.0, 0.1)
    img_b, d_b, boxes_b = place_rgbd_in_window(image, depth, boxes, (64, 96), np.random.default_rng(3), 0.4, 2.0, 0.1)
    np.testing.assert_array_equal(img_a, img_b)
    np.testing.assert_array_equal(boxes_a, boxes_b)
    assert d_b.shape == (64, 96) and set(np.unique(d_b)) <= {0.0, 2.0, 3.0}
    assert (d_b == 3.0).any() and (d_b == 2.0).any()
    # without zoom and shift the window is the letterbox, and the depth is the runtime's letterboxed depth
    img_c, d_c, _ = place_rgbd_in_window(image, depth, boxes, (64, 96), np.random.default_rng(3), 0.0, 1.0, 0.0)
    img_lb, lb = letterbox(image, (64, 96))
    np.testing.assert_array_equal(d_c, letterbox_depth(depth, lb))
    with pytest.raises(ValueError, match="depth is"):
        place_rgbd_in_window(image, depth[:10], boxes, (64, 96), np.random.default_rng(3), 0.4, 2.0, 0.1)


def test_samples_keep_depth_through_concat_take_and_the_cache(sim_bop_dataset, tmp_path):
    built = build_detector_samples(sim_bop_dataset, 320, depth=True)
    assert all(d.dtype == np.uint16 and d.shape == im.shape[:2] for d, im in zip(built.depths, built.images))
    assert any((d > 0).any() for d in built.depths)
    m = built.depth_m(0)
    assert m.dtype == np.float32 and 0.1 < float(np.median(m[m > 0])) < 30.0
    settings = {"max_side": 320, "depth": True}
    load_or_build("detector", sim_bop_dataset, settings, tmp_path, lambda: built)
    cached, _ = load_or_build("detector", sim_bop_dataset, settings, tmp_path, lambda: pytest.fail("cache missed"))
    for a, b in zip(cached.depths, built.depths):
        np.testing.assert_array_equal(a, b)
    photo = DetectorSamples(_obj([np.zeros((8, 8, 3), np.uint8)]), _obj([np.zeros((0, 4), np.float32)]),
                            np.arange(1))
    both = DetectorSamples.concat([built, photo])
    assert both.depths[-1].shape == (0, 0) and both.depth_m(len(both) - 1) is None
    assert both.take(np.array([len(both) - 1, 0])).depths[1].shape == built.depths[0].shape
    with pytest.raises(ValueError, match="depth"):
        DetectorSamples(photo.images, photo.boxes, photo.frame, depths=_obj([np.zeros((3, 3), np.uint16)]))


def test_rgbd_training_batches_carry_depth_and_photographs_none(sim_bop_dataset):
    cfg = get_config("tiny")
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, depth_max_m=10.0))
    sim = build_detector_samples(sim_bop_dataset, 320, depth=True)
    photo = DetectorSamples(_obj([np.full((120, 320, 3), 90, np.uint8)]),
                            _obj([np.array([[5, 5, 60, 40]], np.float32)]), np.arange(1))
    samples = DetectorSamples.concat([sim, photo])
    n = len(samples)
    real = np.zeros(n, bool)
    real[-1] = True
    trainer = DetectorTrainer(cfg, DetectorData(samples, np.arange(n), np.arange(n), [], real), NO_AUGMENT)
    x, targets = trainer.batch(np.arange(n), None)
    assert x.shape[1] == 4 and len(targets) == n
    assert float(x[:n - 1, 3].max()) > 0 and float(x[n - 1, 3].abs().max()) == 0.0
    assert 0.0 <= float(x[:, 3].min()) and float(x[:, 3].max()) <= 1.0
    loss, parts = trainer.step(np.arange(n), np.random.default_rng(0))
    assert torch.isfinite(loss)


@pytest.fixture(scope="module")
def rgbd_bundle(tmp_path_factory):
    from pallet6d.export.bundle_export import export_bundle

    cfg = get_config("tiny")
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, depth_max_m=8.0))
    out = tmp_path_factory.mktemp("b") / "tiny-rgbd"
    calib = make_calibration_set(cfg, frames=4, max_crops=16, seed=0, synthetic=True)
    assert calib.images.shape[1] == 4
    export_bundle(cfg, out, seed=0, random_init=True, int8=True, calib=calib, command="test")
    return out


def test_an_rgbd_bundle_takes_depth_in_its_detector(rgbd_bundle):
    import onnxruntime as ort

    from pallet6d.runtime.bundle import load_bundle
    from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator

    manifest = json.loads((rgbd_bundle / "manifest.json").read_text())
    assert manifest["detector"]["depth_max_m"] == 8.0
    bundle = load_bundle(rgbd_bundle)
    shape = ort.InferenceSession(str(bundle.graph("detector", "fp32"))).get_inputs()[0].shape
    assert shape[1] == 4
    for precision in ("fp32", "int8"):
        est = PalletEstimator(bundle, precision=precision, options=EstimatorOptions(score_threshold=0.0))
        rng = np.random.default_rng(0)
        h, w = 96, 200
        rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        depth_m = rng.uniform(1.0, 4.0, (h, w)).astype(np.float32)
        K = np.array([[150.0, 0, w / 2], [0, 150.0, h / 2], [0, 0, 1]])
        x, lb = est.detector.preprocess(rgb, depth_m)
        assert x.shape[1] == 4 and float(x[0, 3].max()) > 0
        x, lb = est.detector.preprocess(rgb, None)
        assert float(np.abs(x[0, 3]).max()) == 0.0
        with_depth, without = est.detect(rgb, depth_m), est.detect(rgb)
        assert len(with_depth.scores) and len(without.scores)
        est.estimate(rgb, depth_m, K)   # the whole pipeline runs
        with pytest.raises(ValueError, match="depth_m is"):
            est.detect(rgb, depth_m[:10])


def test_depth_that_does_not_belong_to_the_image_is_a_frame_without_pallets(sim_bop_dataset, monkeypatch):
    import pallet6d.export.train_detector as td
    from pallet6d.export.train_data import AugmentConfig

    cfg = get_config("tiny")
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, depth_max_m=10.0))
    sim = build_detector_samples(sim_bop_dataset, 320, depth=True)
    n = len(sim)
    trainer = DetectorTrainer(cfg, DetectorData(sim, np.arange(n), np.arange(n), [], np.zeros(n, bool)),
                              AugmentConfig(flip_prob=0.0))
    frame = int(np.argmax([len(b) for b in sim.boxes]))
    assert len(sim.boxes[frame])
    monkeypatch.setattr(td, "DEPTH_MISMATCH_PROB", 1.0)
    kinds = set()
    for seed in range(12):
        img, channel, targets = trainer._prepare((frame, (128, 320), seed))
        assert len(targets) == 0 and channel is not None and channel.shape == img.shape[:2]
        assert (channel > 0).mean() > 0.2                      # valid depth, never "no depth"
        own = trainer._prepare((frame, (128, 320), seed))      # the same seed gives the same window
        np.testing.assert_array_equal(own[1], channel)
        kinds.add(round(float(np.median(channel[channel > 0])), 2))
    assert len(kinds) > 3                                       # planes and other frames' depths, not one image
    monkeypatch.setattr(td, "DEPTH_MISMATCH_PROB", 0.0)
    _, _, targets = trainer._prepare((frame, (128, 320), 0))
    assert len(targets)
