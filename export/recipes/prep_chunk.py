"""Build the trainers' sample caches of one simulated dataset, so that many can be prepared in parallel and the
training processes only read them (the same cache keys `pallet6d train` looks up: same config, seed and defaults).

usage: python prep_chunk.py DATASET_ROOT CACHE_DIR SEED [CONFIG]
"""
import json
import sys
import time
from pathlib import Path

from pallet6d.export.config import get_config
from pallet6d.export.train_data import AugmentConfig
from pallet6d.export.train_detector import load_detector_data
from pallet6d.export.train_pose import load_pose_data

root, cache, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
cfg = get_config(sys.argv[4] if len(sys.argv) > 4 else "edge2-dilated")
t0 = time.monotonic()
# a pallet-free chunk (`pallet6d sim --pallet-free`) is the detector's negative alone: no pose samples
pallet_free = any(json.loads(p.read_text()).get("pallet_free") for p in Path(root).glob("*/sim_config_*.json"))
if not pallet_free:
    load_pose_data(cfg, [root], 2, seed, AugmentConfig(), cache, progress=False)
load_detector_data(cfg, [root], seed, cache, progress=False)
print(f"prepared {root} in {time.monotonic() - t0:.1f} s", flush=True)
