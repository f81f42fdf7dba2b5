"""runtime/detector_recall.py: one row per counted pallet, and misses told apart by their nearest detection."""
import numpy as np

import pytest

from pallet6d.runtime.detector_recall import average_precision, detector_tally, recall_report, recall_rows


def test_rows_count_every_pallet_at_least_10_percent_visible(bundle_dir, sim_bop_dataset):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.02, max_pallets=1000)
    rows = recall_rows(est, sim_bop_dataset, 0)
    ds = BopDataset(sim_bop_dataset)
    n = sum(1 for i in range(len(ds)) for g in ds[i].gts if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1)
    assert rows.shape == (n, 6) and n > 0
    assert np.all(rows[:, 0] >= 0.1) and np.all((rows[:, 2] >= 0) & (rows[:, 2] <= 1))


def test_tally_scores_every_detection_once_against_the_counted_pallets(bundle_dir, sim_bop_dataset):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.02, max_pallets=1000)
    rows, scored = detector_tally(est, sim_bop_dataset, 0)
    np.testing.assert_array_equal(rows, recall_rows(est, sim_bop_dataset, 0))
    ds = BopDataset(sim_bop_dataset)
    n_det = sum(len(est.detect(ds[i].rgb, ds[i].depth_m)) for i in range(len(ds)))
    assert scored.shape[1] == 2 and 0 < len(scored) <= n_det and set(np.unique(scored[:, 1])) <= {0.0, 1.0}
    assert scored[:, 1].sum() <= len(rows)                     # one true detection per counted pallet at most
    assert 0.0 <= average_precision(scored, len(rows)) <= 1.0


@pytest.mark.parametrize("scored, n_gt, ap", [
    ([[0.9, 1], [0.8, 1]], 2, 1.0),                            # every pallet found, nothing false
    ([[0.9, 0], [0.8, 0]], 2, 0.0),                            # nothing found
    ([[0.9, 1], [0.8, 0], [0.7, 1]], 2, 0.5 + 0.5 * 2 / 3),   # a false box between two true ones
    ([[0.7, 1], [0.8, 0], [0.9, 1]], 2, 0.5 + 0.5 * 2 / 3),   # order by score, not by position
    ([[0.9, 1], [0.8, 0], [0.7, 1]], 3, (1 + 2 / 3) / 3),     # a pallet never found
    ([[0.9, 0], [0.8, 1]], 1, 0.5),                            # the false box scores higher
    ([], 2, 0.0),
    ([[0.9, 1]], 0, 0.0),                                      # nothing to find
])
def test_average_precision(scored, n_gt, ap):
    assert average_precision(np.array(scored, float), n_gt) == pytest.approx(ap)


def test_report_gives_precision_and_average_precision_with_the_detections():
    rows = np.array([[0.9, 50, 0.8, 0.9, 1, 0], [0.9, 50, 0.8, 0.1, 1, 0]])
    scored = np.array([[0.9, 1], [0.5, 0], [0.1, 1]])
    text = recall_report("x", rows, 0.25, scored=scored)
    assert "2 pallets, recall 0.500 at score 0.25, precision 0.500 (1 false boxes); average precision (IoU 0.5) " \
           f"{0.5 + 0.5 * 2 / 3:.3f}" in text
    assert "precision" not in recall_report("x", rows, 0.25)


def test_report_splits_the_misses():
    # visible fraction, box height px, best IoU, its score
    rows = np.array([[0.9, 50, 0.8, 0.9, 1, 0],     # found
                     [0.9, 50, 0.8, 0.1, 1, 0],     # overlapping box, low score
                     [0.5, 20, 0.4, 0.9, 2, 0],     # loose box
                     [0.2, 10, 0.0, 0.0, 2, -1]])   # nothing near
    text = recall_report("x", rows, 0.25, {1: "epal", 2: "gma"})
    assert "4 pallets, recall 0.250" in text
    assert "1 found with a score below 0.25, 1 with a loose box (IoU 0.3-0.5), 1 with nothing near" in text
    assert "| >= 40 px | 2 | 0.50 |" in text and "| 0-15 px | 1 | 0.00 |" in text
    assert "| epal | 2 | 0.50 |" in text and "| gma | 2 | 0.00 |" in text
    assert "pallet type" not in recall_report("one type", rows[:2], 0.25)


def test_report_says_which_type_a_typed_detector_gave():
    # epal found 3 times: twice as epal (class 0), once as gma (class 1); gma found once, as gma
    rows = np.array([[0.9, 50, 0.8, 0.9, 1, 0], [0.9, 50, 0.8, 0.9, 1, 0], [0.9, 50, 0.8, 0.9, 1, 1],
                     [0.9, 50, 0.8, 0.9, 2, 1], [0.9, 50, 0.1, 0.9, 2, 0]])
    text = recall_report("x", rows, 0.25, {1: "epal", 2: "gma"}, {0: "epal", 1: "gma"})
    assert "| epal | 3 | 1.00 | 0.67 | gma 1 |" in text
    assert "| gma | 2 | 0.50 | 1.00 |  |" in text
    assert "type right" not in recall_report("untyped", rows, 0.25, {1: "epal", 2: "gma"})


def test_class_types_lists_classes_of_one_type(bundle_dir):
    import dataclasses

    from pallet6d.runtime.bundle import PalletType, load_bundle
    from pallet6d.runtime.detector_recall import class_types
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.pallet_geometry import default_refine_starts
    from pallet6d.sim.pallets import get_pallet_model

    def typ(name, class_id):
        m = get_pallet_model(name)
        return PalletType(name=name, class_id=class_id, size_m=tuple(m.size_m), diameter_m=m.diameter_m,
                          points_file=f"{name}_points.npy", symmetries=m.symmetries, boxes_m=m.boxes_m,
                          refine_starts=default_refine_starts(m.size_m), points_m=m.surface_points(300, seed=0))

    bundle = load_bundle(bundle_dir)
    c = bundle.pallet_types[0].class_id
    typed = dataclasses.replace(bundle, pallet_types=(typ("epal", c), typ("gma", c + 1)))
    assert class_types(PalletEstimator(typed, threads=1)) == {c: "epal", c + 1: "gma"}
    shared = dataclasses.replace(bundle, pallet_types=(typ("epal", c), typ("gma", c)))   # the depth decides
    assert class_types(PalletEstimator(shared, threads=1)) == {}
