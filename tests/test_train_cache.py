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
    for i, n in enumerate(counts):
        boxes[i] = rng.uniform(0, 100, (n, 4)).astype(np.float32)
    s = DetectorSamples(rng.integers(0, 255, (len(counts), 8, 8, 3), dtype=np.uint8), boxes,
                        np.arange(len(counts), dtype=np.int64))
    back = _roundtrip(s, tmp_path)
    assert np.array_equal(back.images, s.images) and np.array_equal(back.frame, s.frame)
    assert back.boxes.dtype == object and len(back.boxes) == len(counts)
    for a, b in zip(back.boxes, s.boxes):
        assert a.shape == b.shape and np.array_equal(a, b)


def test_detector_cache_with_mismatched_counts_is_refused(tmp_path):
    path = tmp_path / "c.npz"
    np.savez(path, images=np.zeros((1, 8, 8, 3), np.uint8), boxes=np.zeros((2, 4), np.float32),
             boxes_count=np.array([3]), frame=np.zeros(1, np.int64))
    with np.load(path, allow_pickle=False) as z, pytest.raises(ValueError, match="disagree"):
        _from_cache(DetectorSamples, z)
