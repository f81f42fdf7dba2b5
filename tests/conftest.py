"""Shared fixtures. `sim_bop_dataset` is a tiny synthetic BOP dataset rendered once per test session."""
from __future__ import annotations

import pytest

SIM_BOP_PRESET = "virtual-occluded"
SIM_BOP_SIZE = (320, 120)      # width, height: small renders keep the session cheap (~1 s)
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
