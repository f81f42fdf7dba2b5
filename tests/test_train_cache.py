"""The training cache holds plain arrays only: it loads with allow_pickle=False and gives back what was stored."""
import numpy as np
import pytest

from pallet6d.export.train_data import DetectorSamples, _from_cache, _to_cache


def _roundtrip(samples, tmp_path):
    path = tmp_path / "c.npz"
    np.savez(path, **_to_cache(samples))
    with np.load(path, allow_pickle=False) as z:
        return _from_cache(DetectorSamples, z)


@pytest.mark.parametrize("counts", [[2, 0, 3], [2, 2], [0], [1]])
def test_detector_cache_roundtrip(tmp_path, counts):
    rng = np.random.default_rng(0)
    boxes = np.empty(len(counts), dtype=object)
    images = np.empty(len(counts), dtype=object)
    for i, n in enumerate(counts):
        boxes[i] = rng.uniform(0, 100, (n, 4)).astype(np.float32)
        images[i] = rng.integers(0, 255, (8 + i, 12 - i, 3), dtype=np.uint8)   # frames of different sizes
    s = DetectorSamples(images, boxes, np.arange(len(counts), dtype=np.int64))
    back = _roundtrip(s, tmp_path)
    assert np.array_equal(back.frame, s.frame)
    assert back.boxes.dtype == object and len(back.boxes) == len(counts) and len(back.images) == len(counts)
    for a, b in zip([*back.boxes, *back.images], [*s.boxes, *s.images]):
        assert a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)


def test_detector_cache_with_mismatched_counts_is_refused(tmp_path):
    path = tmp_path / "c.npz"
    np.savez(path, images=np.zeros((64, 3), np.uint8), images_shape=np.array([[8, 8, 3]]),
             boxes=np.zeros((2, 4), np.float32), boxes_shape=np.array([[3, 4]]), frame=np.zeros(1, np.int64),
             types=np.zeros(3, np.int64), types_shape=np.array([[3]]))
    with np.load(path, allow_pickle=False) as z, pytest.raises(ValueError, match="disagree"):
        _from_cache(DetectorSamples, z)


def test_detector_cache_without_types_is_refused(tmp_path):
    """A cache from before detector samples carried pallet types is rebuilt, not read with made-up types."""
    path = tmp_path / "c.npz"
    np.savez(path, images=np.zeros((192, 3), np.uint8), images_shape=np.array([[8, 8, 3]]),
             boxes=np.zeros((1, 4), np.float32), boxes_shape=np.array([[1, 4]]), frame=np.zeros(1, np.int64))
    with np.load(path, allow_pickle=False) as z, pytest.raises(ValueError, match="types"):
        _from_cache(DetectorSamples, z)
