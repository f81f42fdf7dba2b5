"""Cost of fusion/pose network designs on this machine's cores: GFLOP per pallet (`export/flops.py`) and
onnxruntime latency, fp32 and static int8 (the exporter's quantization: convolutions only, QDQ,
calibrated on random crops), at batch 1, 4 and 16, on 2 threads, as "min (median)" milliseconds over
`--repeats` runs. Random weights: timing only.

Each variant is a `FusionConfig` change of a named config; `--only NAME` measures a subset.

    .venv/bin/python benchmarks/edge_net.py --repeats 30 --out benchmarks/results/edge-net

Writes `costs.json` and `costs.md` to `--out`. Other jobs on the machine make the numbers noisy: compare
variants within one run. `--cpu-time` measures instead the process CPU time per pallet of one thread at
batch 4 (`cpu_costs.json` / `cpu_costs.md`): work done rather than wall time, so far less disturbed by other
jobs on a shared machine (a 2-thread run takes a bit more than half of it).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pallet6d.export.config import get_config
from pallet6d.export.flops import count_gflops
from pallet6d.export.fusion import build_fusion
from pallet6d.export.onnx_io import export_graph, ort_session
from pallet6d.export.pose import build_pose
from pallet6d.export.quantize import quantize_graph

BATCHES = (1, 4, 16)

# name -> (base config, FusionConfig changes, PoseConfig changes)
VARIANTS: dict[str, tuple[str, dict, dict]] = {
    "edge (shipped: dense map, crop 96)": ("edge", {}, {}),
    "sampled s8, crop 96, dilated": ("edge", {"up_channels": (), "sample_stride": 8}, {}),
    "sampled s8, crop 96": ("edge", {"up_channels": (), "sample_stride": 8, "dilated": False}, {}),
    "edge2: sampled s8, crop 80": ("edge2", {}, {}),
    "sampled s4 decoder, crop 80": ("edge2", {"sample_stride": 4}, {}),
    "sampled s8, crop 64": ("edge2", {"crop_hw": (64, 64)}, {}),
    "sampled s8, crop 80, layer4 128, psp 256": ("edge2", {"resnet_widths": (32, 64, 128, 128), "psp_out": 256}, {}),
    "sampled s8, crop 80, no attention": ("edge2", {"attention": False}, {}),
}
POSE_VARIANTS: dict[str, tuple[str, dict]] = {
    "pose edge (N=256)": ("edge", {}),
    "pose edge, N=128": ("edge", {"num_points": 128}),
    "pose edge, heads 160/64/32": ("edge", {"head_dims": (160, 64, 32)}),
}


def _times(sess, feeds: dict[str, np.ndarray], repeats: int, clock) -> np.ndarray:
    """Seconds per run by `clock` (time.perf_counter: wall; time.process_time: this process's CPU)."""
    for _ in range(3):
        sess.run(None, feeds)
    times = []
    for _ in range(repeats):
        t = clock()
        sess.run(None, feeds)
        times.append(clock() - t)
    return np.array(times)


def _feeds(names: list[str], arrays: list[np.ndarray], b: int) -> dict[str, np.ndarray]:
    return {n: np.ascontiguousarray(np.resize(a, (b,) + a.shape[1:])) for n, a in zip(names, arrays)}


def _measure(net: torch.nn.Module, names: list[str], arrays: list[np.ndarray], outputs: list[str], tmp: Path,
             tag: str, repeats: int, exclude: tuple[str, ...], cpu_time: bool = False) -> dict:
    net.eval()
    args = tuple(torch.from_numpy(a[:2]) for a in arrays)
    fp32 = export_graph(net, args, tmp / f"{tag}.onnx", names, outputs,
                        {n: {0: "batch"} for n in names + outputs})
    calib = [_feeds(names, [a[i:i + 4] for a in arrays], 4) for i in range(0, 16, 4)]
    int8 = quantize_graph(fp32, tmp / f"{tag}.int8.onnx", calib, exclude)
    row = {"gflops": round(count_gflops(fp32), 3), "params_m": round(sum(p.numel() for p in net.parameters()) / 1e6, 2)}
    for prec, path in (("fp32", fp32), ("int8", int8)):
        if cpu_time:
            sess = ort_session(path, threads=1)
            # one intra-op thread: no spinning pool threads in the CPU time
            cpu = _times(sess, _feeds(names, arrays, 4), repeats, time.process_time)
            row[f"{prec}_cpu_ms_per_pallet"] = round(float(np.median(cpu)) * 1e3 / 4, 2)
            continue
        sess = ort_session(path, threads=2)
        for b in BATCHES:
            # "min (median)": on a shared machine the minimum is the least disturbed run
            wall = _times(sess, _feeds(names, arrays, b), repeats, time.perf_counter) * 1e3
            row[f"{prec}_b{b}_ms"] = f"{wall.min():.1f} ({np.median(wall):.1f})"
    return row


def fusion_row(base: str, changes: dict, tmp: Path, tag: str, repeats: int, rng: np.random.Generator,
               cpu_time: bool = False) -> dict:
    cfg = dataclasses.replace(get_config(base).fusion, **changes)
    torch.manual_seed(0)
    net = build_fusion(cfg)
    h, w = cfg.crop_hw
    n = get_config(base).pose.num_points
    arrays = [rng.normal(0, 1, (16, 3, h, w)).astype(np.float32), rng.uniform(-1, 1, (16, 1, h, w)).astype(np.float32)]
    names = ["rgb", "depth"]
    if cfg.sampled:
        arrays.append(rng.integers(0, h * w, (16, n)).astype(np.int64))
        names.append("choose")
    row = _measure(net, names, arrays, ["features"], tmp, tag, repeats, ("/*/final/Conv",), cpu_time)
    return {"crop": f"{h}x{w}", "sample_stride": cfg.sample_stride or "dense", "dilated": cfg.dilated, **row}


def pose_row(base: str, changes: dict, tmp: Path, tag: str, repeats: int, rng: np.random.Generator,
             cpu_time: bool = False) -> dict:
    cfg = get_config(base)
    pcfg = dataclasses.replace(cfg.pose, **changes)
    torch.manual_seed(0)
    net = build_pose(pcfg, cfg.fusion.feature_dim)
    n = pcfg.num_points
    arrays = [rng.normal(0, 0.3, (16, n, 3)).astype(np.float32),
              rng.normal(0, 1, (16, n, cfg.fusion.feature_dim)).astype(np.float32)]
    return {"points": n, **_measure(net, ["points", "features"], arrays, ["quat", "trans", "conf"], tmp, tag, repeats,
                                    ("/conv1/Conv", "/head_[rtc]/head_[rtc].6/Conv"), cpu_time)}


def _table(rows: dict[str, dict], first: list[str], cpu_time: bool = False) -> list[str]:
    timed = ([f"{p}_cpu_ms_per_pallet" for p in ("fp32", "int8")] if cpu_time else
             [f"{p}_b{b}_ms" for p in ("fp32", "int8") for b in BATCHES])
    cols = first + ["gflops", "params_m"] + timed
    out = ["| variant | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, r in rows.items():
        out.append(f"| {name} | " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/edge-net"))
    ap.add_argument("--only", nargs="*", default=None, help="variant names (substrings) to measure")
    ap.add_argument("--cpu-time", action="store_true", help="one-thread CPU time per pallet at batch 4 instead")
    args = ap.parse_args()
    torch.set_num_threads(2)
    rng = np.random.default_rng(0)
    pick = lambda names: [v for v in names if args.only is None or any(o in v for o in args.only)]  # noqa: E731
    fusion, pose = {}, {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for i, name in enumerate(pick(VARIANTS)):
            base, changes, _ = VARIANTS[name]
            fusion[name] = fusion_row(base, changes, tmp, f"f{i}", args.repeats, rng, args.cpu_time)
            print(name, fusion[name], flush=True)
        for i, name in enumerate(pick(POSE_VARIANTS)):
            base, changes = POSE_VARIANTS[name]
            pose[name] = pose_row(base, changes, tmp, f"p{i}", args.repeats, rng, args.cpu_time)
            print(name, pose[name], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    stem, what = (("cpu_costs", "onnxruntime 1 thread, batch 4, median process CPU ms per pallet") if args.cpu_time
                  else ("costs", "onnxruntime 2 threads, ms: min (median)"))
    (args.out / f"{stem}.json").write_text(json.dumps({"fusion": fusion, "pose": pose, "repeats": args.repeats,
                                                       "measure": what}, indent=2) + "\n")
    lines = [f"# Fusion and pose graph costs (random weights, {what})", "",
             "Fusion graph per variant:", "", *_table(fusion, ["crop", "sample_stride", "dilated"], args.cpu_time), "",
             "Pose graph:", "", *_table(pose, ["points"], args.cpu_time), ""]
    (args.out / f"{stem}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
