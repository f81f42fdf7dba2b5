"""Symmetric ADD of pose-stage checkpoints on held-out BOP datasets, per pallet type and per dataset.

Each ground-truth pallet (visible >= 10 %) is prepared once, unjittered and unaugmented, from its visible box
(the runtime's `prepare_pose_inputs`); the error is the symmetric ADD (over the type's symmetries) of the most
confident per-point hypothesis, the runtime's choice, before refinement. A checkpoint of any config works
(`pallet6d train pose` runs, `train merge` files, or `bundle_weights.bundle_checkpoint` saved with torch.save).

    .venv/bin/python benchmarks/pose_heldout.py --ckpt edge=runs/edge-net/edge/best.pt \\
        --ckpt edge2=runs/edge-net/edge2/best.pt --data data/edge-net/val-* --out results.json
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch

from pallet6d.export.config import get_config
from pallet6d.export.train_data import NO_AUGMENT
from pallet6d.export.train_loop import load_checkpoint
from pallet6d.export.train_pose import PoseTrainer, load_pose_data


def _summary(e: np.ndarray) -> dict:
    return {"n": int(len(e)), "acc_0.05": round(float((e < 0.05).mean()), 4) if len(e) else None,
            "acc_0.1": round(float((e < 0.1).mean()), 4) if len(e) else None,
            "median_m": round(float(np.median(e)), 4) if len(e) else None}


@torch.no_grad()
def evaluate(ckpt_path: Path, data: list[Path], cache: Path, batch: int = 16) -> dict:
    ckpt = load_checkpoint(ckpt_path)
    cfg = get_config(ckpt["config"])
    pd = load_pose_data(cfg, data, variants=1, seed=0, aug=NO_AUGMENT, cache_dir=cache, val_fraction=0.0,
                        progress=False)
    trainer = PoseTrainer(cfg, pd)
    for k, net in trainer.nets.items():
        net.load_state_dict(ckpt[k])
        net.eval()
    idx_all = np.arange(len(pd.samples))
    errs = []
    for i in range(0, len(idx_all), batch):
        _, d, conf = trainer.forward_loss(idx_all[i:i + batch])
        errs.append(d.gather(1, conf.argmax(1, keepdim=True))[:, 0].numpy())
    e = np.concatenate(errs)
    s = pd.samples
    # frames are numbered across datasets in order; recover each sample's dataset from the offsets
    bounds = np.cumsum([fp["frames"] for fp in pd.fingerprints])
    ds_of = np.searchsorted(bounds, s.frame, side="right")
    return {"config": cfg.name, "checkpoint": str(ckpt_path), "epoch": ckpt.get("epoch"), "all": _summary(e),
            "by_type": {pd.type_names[int(o)]: _summary(e[s.obj_id == o]) for o in np.unique(s.obj_id)},
            "by_dataset": {Path(data[k]).name: _summary(e[ds_of == k]) for k in np.unique(ds_of)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", action="append", required=True, help="NAME=checkpoint path")
    ap.add_argument("--data", nargs="+", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    results = {}
    with tempfile.TemporaryDirectory() as cache:
        for item in args.ckpt:
            name, path = item.split("=", 1)
            results[name] = evaluate(Path(path), args.data, Path(cache))
            print(name, json.dumps(results[name]["all"]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": [str(d) for d in args.data], "results": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
