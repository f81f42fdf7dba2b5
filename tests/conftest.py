"""Shared fixtures. `sim_bop_dataset` is a tiny synthetic BOP dataset rendered once per test run."""
from __future__ import annotations

import pytest

SIM_BOP_PRESET = "virtual-occluded"
SIM_BOP_SIZE = (320, 120)      # width, height: small renders keep the fixture cheap (~1 s)
SIM_BOP_FRAMES = 3
SIM_BOP_SEED = 7


@pytest.fixture(scope="session")
def sim_bop_dataset(tmp_path_factory):
    """Root of a BOP dataset (split "train", models for every pallet type) of 3 rendered frames of the
    virtual-occluded preset at 320x120, seed 7. Read-only: copy it before changing files."""
    from pallet6d.sim.dataset import write_dataset
    from pallet6d.sim.presets import get_preset

    root = tmp_path_factory.mktemp("sim_bop")
    config = get_preset(SIM_BOP_PRESET).with_image_size(*SIM_BOP_SIZE)
    write_dataset(config, SIM_BOP_FRAMES, SIM_BOP_SEED, root, split="train")
    return root


@pytest.fixture(scope="session")
def bundle_dir(tmp_path_factory):
    """A random-init `tiny` bundle from `pallet6d export`, built once per test run (about 3 s).

    `PALLET6D_TEST_BUNDLE=/path/to/bundle` uses an existing bundle instead."""
    import os
    from pathlib import Path

    env = os.environ.get("PALLET6D_TEST_BUNDLE")
    if env:
        return Path(env)
    pytest.importorskip("torch")
    from pallet6d.runtime.cli import main

    out = tmp_path_factory.mktemp("bundle") / "tiny"
    # one torch thread and two calibration frames: a tiny export is dominated by thread start-up on 2 cores
    rc = main(["export", "--config", "tiny", "--random-init", "--torch-threads", "1", "--calib-frames", "2",
               "--out", str(out)])
    assert rc == 0, "pallet6d export --config tiny --random-init failed"
    return out


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny tensors: one thread is faster, and far faster on a busy 2-core machine (no spin-waiting)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
