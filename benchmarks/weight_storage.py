"""What the float graphs' weight storage costs at run time: compare bundles that differ only in it (never run by
the tests).

For each float graph (detector, fusion, pose) of each bundle: the graph onnxruntime runs after its session
build (node and initializer types; the decoding nodes of a stored weight must be folded away), the session
build time and the resident memory it adds in a fresh process (right after the build, and after handing freed
heap back with malloc_trim, which leaves the live memory), interleaved over `--rounds`; then the latency at
batch 1 with the bundles' sessions side by side in one process, runs alternating (`--runs` each).

    .venv/bin/python benchmarks/weight_storage.py --bundle runs/bundle-fp16 --bundle runs/bundle-int8w

Prints a table per measure; on a busy machine compare the minima and the live memory, not single runs.
"""
from __future__ import annotations

import argparse
import collections
import ctypes
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from pallet6d.runtime.bundle import load_bundle
from pallet6d.runtime.sessions import session_options

STAGES = ("detector", "fusion", "pose")


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS"))


def _session(path: Path, threads: int = 2, optimized: Path | None = None) -> ort.InferenceSession:
    so = session_options(threads)
    if optimized is not None:
        so.optimized_model_filepath = str(optimized)
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _feeds(sess: ort.InferenceSession, hw: tuple[int, int]) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    feeds = {}
    for i in sess.get_inputs():
        shape = [1, 3, *hw] if len(i.shape) == 4 and i.shape[1] == 3 and not isinstance(i.shape[2], int) \
            else [d if isinstance(d, int) else 1 for d in i.shape]
        feeds[i.name] = (rng.random(shape, dtype=np.float32) if "float" in i.type
                         else np.zeros(shape, np.int64))
    return feeds


def optimized_graph(path: Path) -> dict:
    """Node and initializer type counts of the graph onnxruntime runs after the session build."""
    with tempfile.TemporaryDirectory() as tmp:
        _session(path, optimized=Path(tmp) / "opt.onnx")
        g = onnx.load(str(Path(tmp) / "opt.onnx")).graph
    return {"nodes": dict(collections.Counter(n.op_type for n in g.node)),
            "initializers": dict(collections.Counter(onnx.TensorProto.DataType.Name(i.data_type)
                                                     for i in g.initializer))}


def load_cost(path: Path) -> dict:
    """In this (fresh) process: session build seconds, MB resident added by the build, and after malloc_trim."""
    base = _rss_mb()
    t = time.perf_counter()
    sess = _session(path)
    build_s = time.perf_counter() - t
    loaded = _rss_mb()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    out = {"build_s": build_s, "rss_load_mb": loaded - base, "rss_live_mb": _rss_mb() - base}
    del sess
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", action="append", type=Path, default=[], help="a bundle folder (give 2 or more)")
    ap.add_argument("--rounds", type=int, default=3, help="fresh processes per graph for build time and memory")
    ap.add_argument("--runs", type=int, default=150, help="latency runs per graph")
    ap.add_argument("--one", type=Path, help=argparse.SUPPRESS)   # internal: measure one graph's load cost
    args = ap.parse_args()
    if args.one:
        print(json.dumps(load_cost(args.one)))
        return 0
    if len(args.bundle) < 2:
        ap.error("give at least two --bundle folders to compare")
    bundles = {b.name: load_bundle(b) for b in args.bundle}
    names = list(bundles)
    print("| stage | bundle | file MB | nodes after build | initializers after build |\n|---|---|---|---|---|")
    for stage in STAGES:
        for name, b in bundles.items():
            g = optimized_graph(b.graph(stage))
            print(f"| {stage} | {name} | {b.graph(stage).stat().st_size / 1e6:.1f} | {sum(g['nodes'].values())} "
                  f"(Cast {g['nodes'].get('Cast', 0)}, Mul {g['nodes'].get('Mul', 0)}, DequantizeLinear "
                  f"{g['nodes'].get('DequantizeLinear', 0)}) | {g['initializers']} |")
    cost = collections.defaultdict(list)
    for r in range(args.rounds):
        for stage in STAGES:
            for name in (names if r % 2 == 0 else names[::-1]):
                out = subprocess.run([sys.executable, __file__, "--one",
                                      str(bundles[name].graph(stage))], capture_output=True, text=True, check=True)
                cost[stage, name].append(json.loads(out.stdout))
    print("\n| stage | bundle | build s (min / median) | MB after build (median) | MB live (median) |\n|---|---|---|---|---|")
    for (stage, name), rs in cost.items():
        col = {k: [x[k] for x in rs] for k in rs[0]}
        print(f"| {stage} | {name} | {min(col['build_s']):.2f} / {np.median(col['build_s']):.2f} | "
              f"{np.median(col['rss_load_mb']):.1f} | {np.median(col['rss_live_mb']):.1f} |")
    print("\n| stage | bundle | latency ms, batch 1 (min / p25 / median) |\n|---|---|---|")
    for stage in STAGES:
        sess = {n: _session(b.graph(stage)) for n, b in bundles.items()}
        hw = tuple(bundles[names[0]].detector.input_hw)
        feeds = _feeds(sess[names[0]], hw)
        times = {n: [] for n in names}
        for s in sess.values():
            s.run(None, feeds)
        for r in range(args.runs):
            for n in (names if r % 2 == 0 else names[::-1]):
                t = time.perf_counter()
                sess[n].run(None, feeds)
                times[n].append(1e3 * (time.perf_counter() - t))
        for n, v in times.items():
            print(f"| {stage} | {n} | {np.min(v):.2f} / {np.percentile(v, 25):.2f} / {np.median(v):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
