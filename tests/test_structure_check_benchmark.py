"""benchmarks/structure_check.py's poses: each scored against the image's own pallets, also on mismatched inputs,
where a pose can still be right (another frame's depth of a scene that stands where the image's does)."""
import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "structure_check.py"


@pytest.fixture
def structure_check(monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    spec = importlib.util.spec_from_file_location("structure_check_benchmark", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class _Estimator:
    """Poses each frame's first pallet where it stands, and a copy of it 10 m above, whatever the depth."""

    def __init__(self, ds):
        self.frames, self.i = ds, 0
        self.pallet_types = ()              # the dataset's own models score the poses
        self.model_points_m, self.symmetries = np.zeros((1, 3)), np.eye(4)[None]

    def estimate(self, rgb, depth_m, K):
        T = self.frames[self.i].gts[0].T_cam_model
        self.i += 1
        off = T.copy()
        off[1, 3] -= 10.0                       # camera frame: y points down
        return SimpleNamespace(poses=[SimpleNamespace(T_cam_pallet=M, box_xyxy=np.array([0, 0, 10, 10.0]),
                                                      fit=SimpleNamespace(score=0.9)) for M in (T, off)])


@pytest.mark.parametrize("variant", ["as_recorded", "other_frame", "focal_x2"])
def test_poses_are_scored_against_the_images_pallets_on_every_input(structure_check, sim_bop_dataset, variant):
    from pallet6d.runtime.bop import BopDataset

    ds = BopDataset(sim_bop_dataset, split="train")
    r = structure_check.estimate(_Estimator(ds), ds, variant, len(ds))
    assert r["frame"].tolist() == [0, 0, 1, 1, 2, 2]
    assert np.all(r["err"][0::2] < 1e-6)                  # the image's pallet where it stands: right
    assert np.all(r["err"][1::2] > 5.0)                   # far above every pallet: made up
