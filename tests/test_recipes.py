"""The accelerator round's tools: checkpoint parts round-trip into a checkpoint the trainers read, and the caches a
chunk is prepared with are the ones training then reads (no sample is built twice)."""
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

RECIPES = Path(__file__).resolve().parents[1] / "export" / "recipes"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300)


def _checkpoint(path: Path) -> dict:
    from pallet6d.export.train_loop import CKPT_FORMAT

    g = torch.Generator().manual_seed(0)
    fusion = {"a.weight": torch.randn(4, 3, generator=g), "bn.num_batches_tracked": torch.tensor(7)}
    pose = {"b.weight": torch.randn(5, generator=g, dtype=torch.float64)}
    ckpt = {"config": "edge2-dilated", "format": CKPT_FORMAT, "format_version": 1, "stage": "pose", "epoch": 3,
            "fusion": fusion, "pose": pose, "optimizer": {"state": {}, "param_groups": []}, "provenance": {"seed": 1}}
    torch.save(ckpt, path)
    return ckpt


def test_parts_hold_one_network_each_and_join_back(tmp_path):
    ckpt = _checkpoint(tmp_path / "c.pt")
    r = _run(str(RECIPES / "checkpoint_parts.py"), "split", str(tmp_path / "c.pt"), str(tmp_path / "p"))
    assert r.returncode == 0, r.stderr
    parts = sorted(tmp_path.glob("p.*.pt"))
    assert [p.name for p in parts] == ["p.fusion.pt", "p.pose.pt"]
    for p in parts:
        part = torch.load(p, weights_only=True)
        assert "optimizer" not in part and part["epoch"] == 3
        net = p.name.split(".")[1]
        assert {"fusion", "pose"} & set(part) == {net}
        assert all(v.dtype in (torch.float16, torch.int64) for v in part[net].values())

    r = _run(str(RECIPES / "checkpoint_parts.py"), "join", str(tmp_path / "j.pt"), *map(str, parts))
    assert r.returncode == 0, r.stderr
    from pallet6d.export.train_loop import load_checkpoint

    back = load_checkpoint(tmp_path / "j.pt")
    assert back["stage"] == "pose" and back["provenance"] == {"seed": 1} and "optimizer" not in back
    for net in ("fusion", "pose"):
        for k, v in ckpt[net].items():
            if torch.is_floating_point(v):
                assert back[net][k].dtype == torch.float32
                assert torch.allclose(back[net][k].double(), v.double(), rtol=1e-3, atol=1e-3)
            else:
                assert torch.equal(back[net][k], v)


def test_a_prepared_chunk_is_read_from_its_cache(sim_bop_dataset, tmp_path, monkeypatch):
    root = tmp_path / "chunk"
    shutil.copytree(sim_bop_dataset, root)
    cache = tmp_path / "cache"
    r = _run(str(RECIPES / "prep_chunk.py"), str(root), str(cache), "21")
    assert r.returncode == 0, r.stderr
    assert len(list(cache.glob("pose_chunk_*.npz"))) == 1 and len(list(cache.glob("detector_chunk_*.npz"))) == 1

    from pallet6d.export import train_detector, train_pose
    from pallet6d.export.config import get_config
    from pallet6d.export.train_data import AugmentConfig

    def never(*args, **kwargs):
        raise AssertionError("a sample was built again instead of read from the prepared cache")

    monkeypatch.setattr(train_pose, "build_pose_samples", never)
    monkeypatch.setattr(train_detector, "build_detector_samples", never)
    cfg = get_config("edge2-dilated")
    pd = train_pose.load_pose_data(cfg, [root], 2, 21, AugmentConfig(), cache, progress=False)
    dd = train_detector.load_detector_data(cfg, [root], 21, cache, progress=False)
    assert len(pd.samples) > 0 and len(dd.samples) == 3
    assert np.all(np.isfinite(pd.samples.points))


def test_a_packed_negatives_cache_is_read_back_as_the_same_cache(tmp_path, monkeypatch):
    from pallet6d.export import negative_crops

    rng = np.random.default_rng(0)
    crops = {"rgb_crops": rng.normal(size=(12, 3, 8, 8)).astype(np.float32),
             "depth_crops": rng.uniform(-1, 1, (12, 1, 8, 8)).astype(np.float32),
             "choose": rng.integers(0, 64, (12, 5)), "points": rng.normal(size=(12, 5, 3)).astype(np.float32)}
    settings = {"format": 2, "seed": 3}
    built = negative_crops._cached("negatives", settings, tmp_path / "made", lambda: negative_crops.NegativeCrops(
        crops["rgb_crops"], crops["depth_crops"], crops["choose"], crops["points"]))
    src = next((tmp_path / "made").glob("negatives_*.npz"))
    r = _run(str(RECIPES / "travel_cache.py"), "pack", str(src), str(tmp_path / "packed" / src.name), "--keep", "8")
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "packed" / src.name) as z:
        assert z["rgb_crops"].dtype == np.float16 and z["choose"].dtype == np.int16 and len(z["choose"]) == 8
    r = _run(str(RECIPES / "travel_cache.py"), "unpack", str(tmp_path / "packed"), str(tmp_path / "cache"))
    assert r.returncode == 0, r.stderr

    def never():
        raise AssertionError("the crops were built again instead of read from the unpacked cache")

    back = negative_crops._cached("negatives", settings, tmp_path / "cache", never)
    assert len(back) == 8 and back.rgb_crops.dtype == np.float32 and back.choose.dtype == np.int64
    rows = [int(np.flatnonzero((built.choose == c).all(1))[0]) for c in back.choose]
    assert rows == sorted(set(rows))                          # a subset, in order
    np.testing.assert_allclose(back.rgb_crops, built.rgb_crops[rows], atol=2e-3)
    np.testing.assert_array_equal(back.choose, built.choose[rows])
