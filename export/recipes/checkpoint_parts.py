"""Split a training checkpoint into float16 parts under a size limit (an accelerator returns files of at most
16 MB), and join parts back into a float32 checkpoint that `pallet6d train merge` / `export` read.

usage: python checkpoint_parts.py split CKPT OUT_PREFIX      -> OUT_PREFIX.<net>.pt, one file per network
       python checkpoint_parts.py join OUT_CKPT PART [PART ...]
The optimizer state is dropped (the parts start fine-tuning, they do not resume a run).
"""
import sys
from pathlib import Path

import torch

NETS = ("detector", "fusion", "pose")


def _cast(state: dict, dtype: torch.dtype) -> dict:
    return {k: (v.to(dtype) if torch.is_floating_point(v) else v) for k, v in state.items()}


def split(ckpt_path: str, prefix: str) -> None:
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    meta = {k: v for k, v in ckpt.items() if k not in NETS and k != "optimizer"}
    for net in NETS:
        if net in ckpt:
            torch.save({**meta, net: _cast(ckpt[net], torch.float16)}, f"{prefix}.{net}.pt")


def join(out: str, parts: list[str]) -> None:
    merged: dict = {}
    for p in parts:
        part = torch.load(p, map_location="cpu", weights_only=True)
        for k, v in part.items():
            merged[k] = _cast(v, torch.float32) if k in NETS else merged.get(k, v)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    torch.save(merged, out)


if __name__ == "__main__":
    if sys.argv[1] == "split":
        split(sys.argv[2], sys.argv[3])
    elif sys.argv[1] == "join":
        join(sys.argv[2], sys.argv[3:])
    else:
        sys.exit(__doc__)
