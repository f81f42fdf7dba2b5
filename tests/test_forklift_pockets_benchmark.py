"""benchmarks/forklift_pockets.py on a small generated forklift-approach BOP dataset: every pallet is scored
with its own type (obj_id -> the sim catalogue), and the ground-truth poses give exact pockets."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "forklift_pockets.py"


def _module():
    spec = importlib.util.spec_from_file_location("forklift_pockets", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def forklift_bop(tmp_path_factory):
    from pallet6d.runtime.cli import main

    out = tmp_path_factory.mktemp("forklift_bop") / "bop"
    assert main(["sim", "--preset", "forklift-approach", "--frames", "4", "--seed", "3", "--size", "424x240",
                 "--out", str(out)]) == 0
    return out


def test_obj_ids_name_the_catalogue_types():
    mod = _module()
    assert mod.catalogue_name(1) == "epal" and mod.catalogue_name(11, {11: {"name": "plastic_closed_1210"}})
    with pytest.raises(ValueError, match="not a pallet type"):
        mod.catalogue_name(99)
    with pytest.raises(ValueError, match="catalogue 'epal'"):
        mod.catalogue_name(1, {1: {"name": "gma"}})


def test_each_pallet_is_scored_with_its_own_type(forklift_bop, tmp_path):
    from pallet6d.runtime.bop import BopDataset

    mod = _module()
    ds = BopDataset(forklift_bop)
    frames = list(mod.bop_frames(forklift_bop))
    assert len(frames) == len(ds)
    for fr, k in zip(frames, range(len(ds))):
        gts = ds[k].gts
        for fc in fr["faces"]:
            assert mod.get_pallet_model(fc["model"]).obj_id == gts[fc["gt_index"]].obj_id
    out = tmp_path / "pockets.json"
    done = subprocess.run([sys.executable, str(SCRIPT), "--bop", str(forklift_bop), "--all", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    res = json.loads(out.read_text())["bop"]
    models = {fc["model"] for fr in frames for fc in fr["faces"] if fc["face_centre_vehicle_mm"] is not None}
    assert len(models) >= 2 and set(res["per_type"]) == models
    assert sum(s["pallets"] for s in res["per_type"].values()) == res["pallets"]
    targets = [r for r in res["rows"] if r["target"]]
    assert targets and all(r["pocket_err_m"] < 1e-6 and r["yaw_err_deg"] < 1e-6 for r in targets)


@pytest.mark.parametrize("flag", [["--int8"], ["--gt-boxes"], ["--pallet-types", "gma"]])
def test_estimator_options_without_an_estimator_are_refused(tmp_path, flag):
    done = subprocess.run([sys.executable, str(SCRIPT), "--frames", str(tmp_path), *flag],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 2 and "need --estimator" in done.stderr


class _PoseOn:
    """An estimator stub whose one pose has the given box and pose."""

    def __init__(self, box_xyxy, T_cam_pallet):
        self.result = SimpleNamespace(poses=[SimpleNamespace(box_xyxy=box_xyxy, T_cam_pallet=T_cam_pallet,
                                                             pallet_type="epal", class_name="pallet")], rejected=[])

    def estimate(self, rgb, depth, K, T_vehicle_cam=None):
        return self.result


def test_a_pose_on_the_pallet_one_up_a_stack_is_not_scored_as_the_target(forklift_bop):
    mod = _module()
    fr = next(f for f in mod.bop_frames(forklift_bop) if any(fc["target"] for fc in f["faces"]))
    target = next(fc for fc in fr["faces"] if fc["target"])
    T_above = np.asarray(target["T_cam_pallet"], dtype=np.float64).copy()
    T_above[:3, 3] += 0.144 * (np.linalg.inv(fr["T_vehicle_cam"])[:3, :3] @ np.array([0.0, 0.0, 1.0]))
    above = {**target, "target": False, "T_cam_pallet": T_above.tolist()}
    fr = {**fr, "faces": [target, above]}
    x, y, w, h = target["box_xywh"]
    box = np.array([x, y, x + w, y + h], dtype=np.float64)
    depth = fr["depths"]["bop"]

    rows = mod._frame_rows(fr, depth, {}, mod.ForkliftParams(), _PoseOn(box, T_above), False, False)
    assert len(rows) == 1 and rows[0]["other_pallet"] and "pocket_err_m" not in rows[0]
    summary = mod.summarize(rows)
    assert summary["other_pallet"] == 1 and summary["posed"] == 0 and summary["detected"] == 0
    assert sum(summary["pick_safe_table"].values()) == 0

    # the same pose slid 1 cm stays the target's (it lies nearer the target than the pallet above)
    T_near = np.asarray(target["T_cam_pallet"], dtype=np.float64).copy()
    T_near[:3, 3] += 0.01
    assert mod.nearest_pallet(fr["faces"], T_near) is target
    assert mod.nearest_pallet(fr["faces"], T_above) is above


class _Rejecting:
    """An estimator stub without poses, whose rejections have the given boxes and reasons."""

    def __init__(self, rejected):
        self.result = SimpleNamespace(poses=[], rejected=[SimpleNamespace(box_xyxy=np.asarray(b, dtype=np.float64),
                                                                          reason=r) for b, r in rejected])

    def estimate(self, rgb, depth, K, T_vehicle_cam=None):
        return self.result


@pytest.mark.parametrize("shift, expected", [(0, "no_pallet_structure"), (0.8, "no_box")])
def test_a_target_without_a_pose_counts_by_the_reason_over_it(forklift_bop, shift, expected):
    mod = _module()
    fr = next(f for f in mod.bop_frames(forklift_bop) if any(fc["target"] for fc in f["faces"]))
    target = next(fc for fc in fr["faces"] if fc["target"])
    x, y, w, h = target["box_xywh"]
    box = [x + shift * w, y, x + w + shift * w, y + h]          # shifted by 0.8 of its width: IoU 0.11 < 0.3
    far = [x + 2 * w, y, x + 3 * w, y + h]
    est = _Rejecting([(far, "poor_fit"), (box, "no_pallet_structure")])

    rows = mod._frame_rows({**fr, "faces": [target]}, fr["depths"]["bop"], {}, mod.ForkliftParams(), est, False,
                           False)
    assert len(rows) == 1 and rows[0]["missed"] == expected and not rows[0]["detected"]
    summary = mod.summarize(rows)
    assert summary["missed"] == {expected: 1} and summary["posed"] == 0
