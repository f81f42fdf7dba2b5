import pytest

from pallet6d.runtime import cli
from pallet6d.runtime.bop import BopDataset


def test_sim_cli_writes_a_dataset_and_previews(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = cli.main(["sim", "--preset", "indoor-noisy", "--frames", "2", "--seed", "3", "--size", "160x120",
                   "--out", str(out), "--split", "val", "--preview"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "previews:" in printed
    previews = sorted((out / "preview" / "val").glob("*.png"))
    assert len(previews) == 2 and str(previews[0].parent) in printed
    ds = BopDataset(out)
    assert ds.split == "val" and len(ds) == 2 and ds[1].rgb.shape == (120, 160, 3)


def test_sim_cli_rejects_unknown_preset(tmp_path):
    with pytest.raises(SystemExit) as exc:
        cli.main(["sim", "--preset", "nope", "--out", str(tmp_path)])
    assert exc.value.code == 2


def test_sim_cli_bad_size(tmp_path, capsys):
    assert cli.main(["sim", "--frames", "1", "--size", "big", "--out", str(tmp_path)]) == 2
    assert "--size" in capsys.readouterr().err


def test_sim_cli_forklift_approach_writes_the_forklift_side_file(tmp_path, capsys):
    import json

    out = tmp_path / "fa"
    rc = cli.main(["sim", "--preset", "forklift-approach", "--frames", "1", "--seed", "2", "--size", "160x96",
                   "--out", str(out)])
    assert rc == 0
    side = json.loads((out / "train" / "000000" / "scene_forklift.json").read_text())
    assert list(side) == ["0"] and side["0"]["cam_R_c2v"] is not None
    assert any(p["target"] for p in side["0"]["pallets"])
    assert len(BopDataset(out)) == 1


def test_sim_cli_pallet_types_choose_the_catalogue(tmp_path, capsys):
    out = tmp_path / "gma"
    rc = cli.main(["sim", "--preset", "mixed", "--frames", "2", "--seed", "4", "--size", "160x96",
                   "--pallet-types", "gma", "--out", str(out)])
    assert rc == 0
    from pallet6d.sim.generate import obj_id_of

    ds = BopDataset(out)
    assert {g.obj_id for i in range(len(ds)) for g in ds[i].gts} == {obj_id_of("gma")}
    assert cli.main(["sim", "--frames", "1", "--pallet-types", "epal,crate", "--out", str(tmp_path / "x")]) == 2
    assert "unknown pallet type(s) ['crate']" in capsys.readouterr().err


def test_sim_cli_sensor_renders_the_same_scenes_with_another_depth_sensor(tmp_path):
    import json

    import numpy as np

    outs = {}
    for sensor in (None, "ideal"):
        out = tmp_path / (sensor or "preset")
        extra = ["--sensor", sensor] if sensor else []
        assert cli.main(["sim", "--preset", "forklift-approach", "--frames", "1", "--seed", "3", "--size", "212x120",
                         "--out", str(out), *extra]) == 0
        outs[sensor] = out / "train" / "000000"
    gt = [json.loads((d / "scene_gt.json").read_text()) for d in outs.values()]
    assert gt[0] == gt[1]                                       # the same pallets at the same poses
    depth = [BopDataset(d.parent.parent)[0].depth_m for d in outs.values()]
    assert not np.array_equal(depth[0], depth[1])               # the preset's D435-like depth is noisy, ideal is not
    assert (depth[1] > 0).mean() >= (depth[0] > 0).mean()       # exact depth has no stereo holes
