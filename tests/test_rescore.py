"""`eval_cli.rescore` (benchmarks/rescore.py): saved per-pallet results re-scored against re-annotated ground
truth."""
import json
import shutil

import pytest

from pallet6d.runtime.eval_cli import rescore


@pytest.fixture(scope="module")
def results(bundle_dir, sim_bop_dataset):
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.eval_cli import evaluate_dataset

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, min_fit=0.0, structure=None)
    out = evaluate_dataset(est, sim_bop_dataset, gt_boxes=True)
    return {**out["summary"], "records": out["records"]}


def test_same_annotations_give_the_same_scores(results, sim_bop_dataset):
    after = rescore(results, sim_bop_dataset)
    for key in ("n_gt", "n_detected", "recall", "precision", "add_acc", "add_sym_acc"):
        assert after[key] == pytest.approx(results[key]), key


def test_a_pallet_now_under_10_percent_visible_no_longer_counts(results, sim_bop_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(sim_bop_dataset, data)
    info_path = data / "train" / "000000" / "scene_gt_info.json"
    info = json.loads(info_path.read_text())
    first = results["records"][0]
    gt = json.loads((data / "train" / "000000" / "scene_gt.json").read_text())
    frame_key = sorted(info, key=int)[first["frame"]]
    # the annotation of the first scored pallet: the one at its distance
    dists = [sum((v / 1000) ** 2 for v in g["cam_t_m2c"]) ** 0.5 for g in gt[frame_key]]
    j = min(range(len(dists)), key=lambda i: abs(dists[i] - first["distance_m"]))
    info[frame_key][j]["visib_fract"] = 0.05
    info_path.write_text(json.dumps(info))
    after = rescore(results, data)
    assert after["n_gt"] == results["n_gt"] - 1
    assert after["n_detected"] == results["n_detected"] - int(first["detected"])


def test_results_of_another_dataset_are_refused(results, sim_bop_dataset):
    moved = {**results, "records": [{**results["records"][0], "distance_m": 99.0}]}
    with pytest.raises(ValueError, match="another dataset"):
        rescore(moved, sim_bop_dataset)
