"""Detector training's mosaic (`train_data.place_mosaic`, `DetectorTrainer(mosaic=)`): four frames to an input,
each drawn as it would be alone, its boxes clipped to its quarter."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.train_data import AugmentConfig, place_in_window, place_mosaic  # noqa: E402
from pallet6d.export.train_detector import DetectorTrainer, load_detector_data  # noqa: E402

CFG = get_config("tiny")
BLOCK_COLOURS = ((200, 60, 30), (90, 200, 230), (240, 140, 90), (30, 180, 160))   # no mix of two is a third


def _frames(hw=(60, 120), with_depth=False):
    """Four frames: a grey background, one block of the frame's own colour; boxes carry the frame index as class."""
    out = []
    for k, colour in enumerate(BLOCK_COLOURS):
        img = np.full((*hw, 3), 10, np.uint8)
        x1, y1 = 10 + 20 * k, 15 + 5 * k
        img[y1:y1 + 25, x1:x1 + 40] = colour
        depth = np.full(hw, 1.0 + k, np.float32) if with_depth else None
        out.append((img, depth, np.array([[x1, y1, x1 + 40, y1 + 25, k]], np.float32)))
    return out


@pytest.mark.parametrize("seed", range(8))
def test_each_kept_box_covers_its_own_frames_block(seed):
    window_hw = (64, 128)
    out, depth, boxes = place_mosaic(_frames(), window_hw, np.random.default_rng(seed), 0.4, 2.0, 0.1)
    assert out.shape == (*window_hw, 3) and depth is None and boxes.shape[1] == 5
    assert (boxes[:, [0, 2]] >= 0).all() and (boxes[:, [2]] <= window_hw[1]).all()
    assert (boxes[:, [1, 3]] >= 0).all() and (boxes[:, [3]] <= window_hw[0]).all()
    for x1, y1, x2, y2, k in boxes:
        inside = out[int(np.ceil(y1 + 1)):int(y2 - 1), int(np.ceil(x1 + 1)):int(x2 - 1)]
        if inside.size:     # interpolation touches a pixel at each side
            assert (inside == BLOCK_COLOURS[int(k)]).all()
    for k, colour in enumerate(BLOCK_COLOURS):     # a kept box is the block's shown pixels; a hidden block no box
        shown = np.argwhere((out == colour).all(axis=2))
        mine = boxes[boxes[:, 4] == k]
        if not len(shown):
            assert not len(mine)
        for x1, y1, x2, y2, _ in mine:
            ys, xs = shown[:, 0], shown[:, 1]
            np.testing.assert_allclose([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], [x1, y1, x2, y2], atol=1.5)


@pytest.mark.parametrize("seed", range(4))
def test_without_zoom_or_shift_each_quarter_is_its_frames_letterbox(seed):
    """Each frame is drawn as `place_in_window` draws it alone; the split point is the generator's first two draws."""
    window_hw = (48, 96)
    frames = _frames(with_depth=True)
    out, depth, boxes = place_mosaic(frames, window_hw, np.random.default_rng(seed), 0.0, 1.0, 0.0)
    rng = np.random.default_rng(seed)
    cx, cy = int(round(rng.uniform(0.25, 0.75) * 96)), int(round(rng.uniform(0.25, 0.75) * 48))
    quarters = [(slice(0, cy), slice(0, cx)), (slice(0, cy), slice(cx, 96)),
                (slice(cy, 48), slice(0, cx)), (slice(cy, 48), slice(cx, 96))]
    for k, ((img, _, b), (ys, xs)) in enumerate(zip(frames, quarters)):
        alone, _ = place_in_window(img, b, window_hw, np.random.default_rng(0), 0.0, 1.0, 0.0)
        np.testing.assert_array_equal(out[ys, xs], alone[ys, xs])
        lit = depth[ys, xs]     # the depth of the frame's own quarter, 0 where the letterbox leaves no frame
        assert set(np.unique(lit)) <= {0.0, 1.0 + k}


def test_a_mosaic_takes_four_frames_and_the_depth_of_all_or_none():
    frames = _frames(with_depth=True)
    with pytest.raises(ValueError, match="4 frames"):
        place_mosaic(frames[:3], (32, 64), np.random.default_rng(0), 0.4, 2.0, 0.1)
    mixed = frames[:3] + [(frames[3][0], None, frames[3][2])]
    with pytest.raises(ValueError, match="all four frames or of none"):
        place_mosaic(mixed, (32, 64), np.random.default_rng(0), 0.4, 2.0, 0.1)
    empty = [(img, None, np.zeros((0, 5), np.float32)) for img, _, _ in frames]
    assert place_mosaic(empty, (32, 64), np.random.default_rng(0), 0.4, 2.0, 0.1)[2].shape == (0, 5)


def test_trainer_with_mosaic_mixes_frames_and_still_learns(sim_bop_dataset, tmp_path):
    dd = load_detector_data(CFG, [sim_bop_dataset], seed=0, cache_dir=tmp_path, progress=False)
    plain = DetectorTrainer(CFG, dd, AugmentConfig())
    mosaic = DetectorTrainer(CFG, dd, AugmentConfig(), mosaic=1.0)
    off = DetectorTrainer(CFG, dd, AugmentConfig(), mosaic=0.0)
    idx = dd.train_idx[:2]
    x_plain, _ = plain.batch(idx, np.random.default_rng(5))
    x_off, _ = off.batch(idx, np.random.default_rng(5))
    x_mosaic, t_mosaic = mosaic.batch(idx, np.random.default_rng(5))
    assert torch.equal(x_plain, x_off)      # no mosaic: the augmentation stream is the plain trainer's
    assert not torch.equal(x_plain, x_mosaic)
    h, w = x_mosaic.shape[2:]
    for t in t_mosaic:
        assert ((t[:, 1:] >= 0) & (t[:, [1, 3]] <= w).all(1, keepdim=True)).all()
    loss, _ = mosaic.step(np.arange(len(idx)), np.random.default_rng(1))
    assert torch.isfinite(loss)
    with pytest.raises(ValueError, match="mosaic"):
        DetectorTrainer(CFG, dd, AugmentConfig(), mosaic=1.5)
