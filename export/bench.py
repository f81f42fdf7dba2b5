"""Latency of a bundle's graphs per stage on this machine: `python -m pallet6d.export.bench DIR [--threads 2]`.

Runs each graph (fp32 and, when present, int8) on zero-free random inputs of the manifest's shapes:
the detector on one frame, fusion + pose on a batch of `--pallets` crops. Prints median ms. A benchmark
measures; no test asserts a timing.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from pallet6d.runtime.bundle import load_bundle
from pallet6d.runtime.sessions import OnnxModel


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times))


def bench(path: str, threads: int = 2, pallets: int = 1, repeats: int = 10) -> dict:
    b = load_bundle(path)
    rng = np.random.default_rng(0)
    (h, w), (ch, cw) = b.detector.input_hw, b.fusion.crop_hw
    n, c = b.pose.num_points, b.fusion.feature_dim
    feeds = {
        "detector": {b.detector.input_name: rng.random((1, 3, h, w), dtype=np.float32)},
        "fusion": {b.fusion.rgb_input: rng.standard_normal((pallets, 3, ch, cw), dtype=np.float32),
                   b.fusion.depth_input: rng.uniform(-1, 1, (pallets, 1, ch, cw)).astype(np.float32)},
        "pose": {b.pose.points_input: (rng.standard_normal((pallets, n, 3)) * 0.3).astype(np.float32),
                 b.pose.features_input: rng.standard_normal((pallets, n, c), dtype=np.float32)},
    }
    out: dict = {}
    for prec in b.precision:
        for stage in ("detector", "fusion", "pose"):
            model = OnnxModel(b.graph(stage, prec), threads=threads)
            out[f"{stage}_{prec}_ms"] = round(_median_ms(lambda: model.run(feeds[stage]), repeats), 2)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bundle")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--pallets", type=int, default=1)
    p.add_argument("--repeats", type=int, default=10)
    a = p.parse_args()
    print(json.dumps(bench(a.bundle, a.threads, a.pallets, a.repeats), indent=1))


if __name__ == "__main__":
    main()
