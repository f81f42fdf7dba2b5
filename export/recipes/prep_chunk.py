"""Build the trainers' sample caches of one simulated dataset, so that many can be prepared in parallel and the
training processes only read them (the same cache keys `pallet6d train` looks up: same config, seed and defaults).

usage: python prep_chunk.py DATASET_ROOT CACHE_DIR SEED [CONFIG]
"""
import sys
import time

from pallet6d.export.config import get_config
from pallet6d.export.train_data import AugmentConfig
from pallet6d.export.train_detector import load_detector_data
from pallet6d.export.train_pose import load_pose_data

root, cache, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
cfg = get_config(sys.argv[4] if len(sys.argv) > 4 else "edge2-dilated")
t0 = time.monotonic()
load_pose_data(cfg, [root], 2, seed, AugmentConfig(), cache, progress=False)
load_detector_data(cfg, [root], seed, cache, progress=False)
print(f"prepared {root} in {time.monotonic() - t0:.1f} s", flush=True)
