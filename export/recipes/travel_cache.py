"""Make a trainer's cache small enough to travel to a lent machine, and whole again there.

A negatives cache (`negative_crops._cached`: float32 crops, int64 pixel indices) of a few hundred crops is about
50 MB; a call carries 64 MiB with the repository. `pack` keeps N of its crops (a seeded random subset), stores the
floats as float16 and the indices as int16, compressed (about 6 MB for 190 crops); `unpack` restores the dtypes the
trainers read, under the same file names, so the cache key still matches.

usage: python travel_cache.py pack SRC.npz DST.npz [--keep N] [--seed S]
       python travel_cache.py unpack SRC_DIR DST_DIR
"""
import argparse
from pathlib import Path

import numpy as np


def pack(src: Path, dst: Path, keep: int | None, seed: int) -> None:
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    n = len(next(iter(arrays.values())))
    rows = np.arange(n) if keep is None or keep >= n else np.sort(np.random.default_rng(seed).choice(n, keep, False))
    out = {}
    for k, v in arrays.items():
        v = v[rows]
        if np.issubdtype(v.dtype, np.floating):
            out[k] = v.astype(np.float16)
        elif v.size and v.min() >= np.iinfo(np.int16).min and v.max() <= np.iinfo(np.int16).max:
            out[k] = v.astype(np.int16)
        else:
            out[k] = v
    dst.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(dst, **out)
    print(f"{dst}: {len(rows)} of {n} rows")


def unpack(src_dir: Path, dst_dir: Path) -> None:
    dst_dir.mkdir(parents=True, exist_ok=True)
    for f in sorted(src_dir.glob("*.npz")):
        with np.load(f) as z:
            out = {k: z[k].astype(np.float32 if np.issubdtype(z[k].dtype, np.floating) else np.int64) for k in z.files}
        np.savez(dst_dir / f.name, **out)
        print(f"{dst_dir / f.name}: unpacked")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    p.add_argument("--keep", type=int, help="rows kept (default: all)")
    p.add_argument("--seed", type=int, default=1)
    u = sub.add_parser("unpack")
    u.add_argument("src", type=Path)
    u.add_argument("dst", type=Path)
    a = ap.parse_args()
    if a.cmd == "pack":
        pack(a.src, a.dst, a.keep, a.seed)
    else:
        unpack(a.src, a.dst)


if __name__ == "__main__":
    main()
