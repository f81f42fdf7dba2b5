"""Int8 recipes for the detector: quantize a bundle's float detector several ways, time each graph, write
candidate bundles whose recall `benchmarks/detector_recall.py --int8` then measures.

    .venv/bin/python benchmarks/detector_int8.py --bundle models/epal-default --out runs/speed-refine/det

Recipes (`export/quantize.py`): "convs" quantizes the convolutions but the box/class output convs (the
shipped recipe), "graph" also the SiLU activations, residual adds, concats, pooling and upsampling
(`DETECTOR_OPS`), "graph+heads" the output convs too (`INT8_RECIPES["detector"]`, what `pallet6d export
--int8` does). The box decoding after the output convs stays float
in all. Calibration: `make_calibration_set` with the bundle's config, the images `export_bundle` uses.
Each candidate bundle is a copy of --bundle with its detector.int8.onnx replaced (manifest sha256
updated). Timings: the graphs alternate in one process on --threads threads, p50 over --runs runs of a
real letterboxed frame; on a shared machine compare them within one run only.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

OUTPUT_CONVS = ("/head/box.*.2/Conv", "/head/cls.*.2/Conv")
RECIPES = ("convs", "graph", "graph+heads")


def _recipe(name: str) -> dict:
    from pallet6d.export.quantize import DETECTOR_OPS, INT8_RECIPES

    return {"convs": {"exclude_nodes": OUTPUT_CONVS, "float_after": OUTPUT_CONVS},
            "graph": {"op_types": DETECTOR_OPS, "exclude_nodes": OUTPUT_CONVS, "float_after": OUTPUT_CONVS},
            "graph+heads": INT8_RECIPES["detector"]}[name]


def build(bundle: Path, out: Path, recipes: list[str]) -> dict[str, Path]:
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config
    from pallet6d.export.quantize import quantize_graph
    from pallet6d.runtime.bundle import sha256_file

    manifest = json.loads((bundle / "manifest.json").read_text())
    calib = make_calibration_set(get_config(manifest["config"]))
    n_cal = max(1, (3 * len(calib.images)) // 4)           # as export_bundle: 3/4 calibrate, the rest held out
    feeds = [{manifest["detector"]["input_name"]: calib.images[i:i + 1]} for i in range(n_cal)]
    made = {}
    for name in recipes:
        dst = out / name
        if dst.exists():
            shutil.rmtree(dst)
        shutil.copytree(bundle, dst)
        int8 = dst / manifest["detector"]["file_int8"]
        quantize_graph(dst / manifest["detector"]["file"], int8, feeds, **_recipe(name))
        m = json.loads((dst / "manifest.json").read_text())
        m["files"][manifest["detector"]["file_int8"]] = sha256_file(int8)
        (dst / "manifest.json").write_text(json.dumps(m, indent=2))
        made[name] = dst
    return made


def time_graphs(paths: dict[str, Path], threads: int, runs: int) -> dict[str, dict]:
    import onnxruntime as ort

    from pallet6d.runtime.detector import letterbox, to_nchw
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    frame = generate_frame(get_preset("virtual-clean"), seed=0)
    sessions, single = {}, {}
    for name, path in paths.items():
        for store, n in ((sessions, threads), (single, 1)):
            so = ort.SessionOptions()
            so.intra_op_num_threads, so.inter_op_num_threads = n, 1
            store[name] = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    s0 = next(iter(sessions.values()))
    _, _, h, w = s0.get_inputs()[0].shape
    img, _ = letterbox(frame.rgb, (h, w), 114)
    x = np.empty((1, 3, h, w), np.float32)
    to_nchw(img, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1 / 255, False, out=x)
    times: dict[str, list[float]] = {k: [] for k in sessions}
    cpu: dict[str, list[float]] = {k: [] for k in sessions}
    for _ in range(3):
        for s in (*sessions.values(), *single.values()):
            s.run(None, {s.get_inputs()[0].name: x})
    for _ in range(runs):
        for k, s in sessions.items():                       # alternate: all graphs see the same load
            t = time.perf_counter()
            s.run(None, {s.get_inputs()[0].name: x})
            times[k].append((time.perf_counter() - t) * 1000.0)
            # one thread's CPU time: the work itself, less sensitive to other jobs on a shared machine
            t = time.process_time()
            single[k].run(None, {s.get_inputs()[0].name: x})
            cpu[k].append((time.process_time() - t) * 1000.0)
    return {k: {"p50_ms": float(np.median(v)), "p10_ms": float(np.percentile(v, 10)),
                "cpu_1thread_p50_ms": float(np.median(cpu[k]))} for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    ap.add_argument("--out", type=Path, required=True, help="folder for the candidate bundles")
    ap.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=RECIPES)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--time-only", action="store_true", help="time the candidates already under --out")
    a = ap.parse_args(argv)
    made = {k: a.out / k for k in a.recipes} if a.time_only else build(a.bundle, a.out, a.recipes)
    manifest = json.loads((a.bundle / "manifest.json").read_text())
    graphs = {"shipped": a.bundle / manifest["detector"]["file_int8"], "fp32": a.bundle / manifest["detector"]["file"]}
    graphs.update({k: p / manifest["detector"]["file_int8"] for k, p in made.items()})
    res = time_graphs(graphs, a.threads, a.runs)
    lines = [f"| detector graph | wall p50 ms ({a.threads} threads) | wall p10 ms | CPU ms, 1 thread (p50) |",
             "|---|---|---|---|"]
    lines += [f"| {k} | {v['p50_ms']:.1f} | {v['p10_ms']:.1f} | {v['cpu_1thread_p50_ms']:.1f} |"
              for k, v in res.items()]
    print("\n".join(lines))
    (a.out / "timings.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
