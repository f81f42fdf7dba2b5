"""`EstimatorProcess`: the estimator in a child process answers like the estimator; a crash costs one frame."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from pallet6d.runtime.cameras import open_source
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.serve.worker import EstimatorCrashed, EstimatorProcess

OPTIONS = {"score_threshold": 0.0, "min_fit": 0.0, "refine": False}


@pytest.fixture(scope="module")
def frame(sim_bop_dataset):
    with open_source(f"bop:{sim_bop_dataset}") as src:
        return src.read()


def test_same_result_as_in_process_and_a_crash_costs_one_frame(bundle_dir, frame):
    local = PalletEstimator.from_bundle(bundle_dir, threads=1, **OPTIONS).estimate(frame)
    worker = EstimatorProcess(str(bundle_dir), threads=1, options=OPTIONS)
    try:
        remote = worker.estimate(frame)
        assert len(remote.poses) == len(local.poses) and set(remote.timings_ms) == set(local.timings_ms)
        for a, b in zip(remote.poses, local.poses):
            np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet, atol=1e-6)
        np.testing.assert_array_equal(worker.model_size_m, local_size(bundle_dir))
        with pytest.raises(ValueError, match="depth"):   # the estimator's own input errors keep their type
            worker.estimate(frame.rgb)                    # an image without depth
        with pytest.raises(EstimatorCrashed, match="exit status 3"):
            worker.estimate(ExitsWhenUnpickled())    # the child dies in the middle of a frame
        assert len(worker.estimate(frame).poses) == len(local.poses) and worker.restarts == 1
        os.kill(worker._proc.pid, signal.SIGKILL)    # the child died between frames: started again first
        worker._proc.join(10)
        assert len(worker.estimate(frame).poses) == len(local.poses) and worker.restarts == 2
    finally:
        worker.close()
    assert not worker.alive


class ExitsWhenUnpickled:
    def __reduce__(self):
        return (os._exit, (3,))


def local_size(bundle_dir):
    from pallet6d.runtime.bundle import load_bundle
    return np.asarray(load_bundle(bundle_dir).pallet.size_m, dtype=np.float64)


def test_a_bundle_that_cannot_load_is_a_value_error(tmp_path):
    with pytest.raises(ValueError):
        EstimatorProcess(str(tmp_path / "no-bundle"))
