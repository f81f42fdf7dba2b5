"""benchmarks/detector_levels.py (levels that fire, recall by width) and benchmarks/pose_type_probe.py (a linear
probe for the pallet type) on small inputs."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).parents[1] / "benchmarks"


def _module(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_detector_levels_reports_each_level_and_every_counted_pallet(bundle_dir, sim_bop_dataset, tmp_path):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.evaluation import counted_pallets

    out = tmp_path / "levels.md"
    assert _module("detector_levels").main(["--bundle", str(bundle_dir), "--data", str(sim_bop_dataset),
                                            "--max-frames", "2", "--threads", "1", "--out", str(out)]) == 0
    text = out.read_text()
    for stride in (8, 16, 32):
        assert f"\n| {stride} | " in text
    ds = BopDataset(sim_bop_dataset)
    n = sum(sum(counted_pallets(ds[i].gts)) for i in range(2))
    assert f"{n} pallets, recall " in text
    counts = [int(line.split("|")[2]) for line in text.splitlines() if line.startswith("| ") and " px |" in line]
    assert sum(counts) == n


def test_type_probe_separates_separable_features_and_not_noise():
    pytest.importorskip("torch")
    probe = _module("pose_type_probe")
    rng = np.random.default_rng(0)
    n = 3000
    rows = np.repeat(np.arange(3), n // 3)
    train, val = np.arange(0, n, 2), np.arange(1, n, 2)
    separable = rng.normal(size=(n, 8)).astype(np.float32)
    separable[:, 0] += 10.0 * rows                                  # the type written into one feature
    p = probe.probe(separable, rows, train, val, hidden=0, seed=0, epochs=100, lr=1e-2)
    assert p.shape == (n // 2, 3) and np.mean(p.argmax(1) == rows[val]) > 0.9
    noise = rng.normal(size=(n, 8)).astype(np.float32)
    assert np.mean(probe.probe(noise, rows, train, val, hidden=0, seed=0, epochs=100, lr=1e-2).argmax(1)
                   == rows[val]) < 0.45                             # chance: 1/3
    text = probe.report(separable, rows, train, val, ["epal", "gma", "eur6"], 0, "x")
    assert f"| gma | {n // 6} |" in text and "## linear: held-out accuracy" in text
