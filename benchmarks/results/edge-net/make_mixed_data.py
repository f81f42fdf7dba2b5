"""Generate a dataset of a preset with all three catalogue pallet types (epal, gma, eur3): PRESET FRAMES SEED OUT."""
import dataclasses, sys, time
from pallet6d.sim.presets import get_preset
from pallet6d.sim.dataset import write_dataset
preset, frames, seed, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
cfg = dataclasses.replace(get_preset(preset), pallet_models=("epal", "gma", "eur3"))
t = time.time()
write_dataset(cfg, frames, seed, out)
print(f"{frames} frames in {time.time() - t:.1f} s", flush=True)
