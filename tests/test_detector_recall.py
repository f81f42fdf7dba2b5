"""runtime/detector_recall.py: one row per counted pallet, and misses told apart by their nearest detection."""
import numpy as np

from pallet6d.runtime.detector_recall import recall_report, recall_rows


def test_rows_count_every_pallet_at_least_10_percent_visible(bundle_dir, sim_bop_dataset):
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.02, max_pallets=1000)
    rows = recall_rows(est, sim_bop_dataset, 0)
    ds = BopDataset(sim_bop_dataset)
    n = sum(1 for i in range(len(ds)) for g in ds[i].gts if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1)
    assert rows.shape == (n, 5) and n > 0
    assert np.all(rows[:, 0] >= 0.1) and np.all((rows[:, 2] >= 0) & (rows[:, 2] <= 1))


def test_report_splits_the_misses():
    # visible fraction, box height px, best IoU, its score
    rows = np.array([[0.9, 50, 0.8, 0.9, 1],     # found
                     [0.9, 50, 0.8, 0.1, 1],     # overlapping box, low score
                     [0.5, 20, 0.4, 0.9, 2],     # loose box
                     [0.2, 10, 0.0, 0.0, 2]])    # nothing near
    text = recall_report("x", rows, 0.25, {1: "epal", 2: "gma"})
    assert "4 pallets, recall 0.250" in text
    assert "1 found with a score below 0.25, 1 with a loose box (IoU 0.3-0.5), 1 with nothing near" in text
    assert "| >= 40 px | 2 | 0.50 |" in text and "| 0-15 px | 1 | 0.00 |" in text
    assert "| epal | 2 | 0.50 |" in text and "| gma | 2 | 0.00 |" in text
    assert "pallet type" not in recall_report("one type", rows[:2], 0.25)
