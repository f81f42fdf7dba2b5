"""Latency of the runtime per stage and end to end, on this machine's cores (never run by the tests).

For each bundle x precision (fp32, int8) x threads (1, 2) x pallets (1, 4) [x pallet types, `--pallet-types all
epal`: the bundle's every type (the default) or a site's named types] [x extra ICP starts, `--refine-starts 0 6 10`,
default the estimator's] [x refinement's ICP and fit scores, `--kernel compiled numpy`: the compiled kernel or numpy,
default the kernel]: `--frames` frames of a 1224x370 synthetic warehouse scene with at least P pallets (`_scene`);
the detector runs on the whole frame, and the pose stage gets exactly P pallets (the scene's P most visible
ground-truth boxes, so the count does not depend on a random-init detector). Reports p50/p95/p99 in milliseconds per
stage and end to end, the same networks in torch eager (built from `pallet6d.export` with the bundle's config) for
the ratio, and peak RSS and import time of the runtime in a fresh subprocess.

    .venv/bin/python benchmarks/latency.py --bundle /tmp/bundles/edge --bundle /tmp/bundles/paper --frames 200

Writes benchmarks/results/latency.json and latency.md.
"""
from __future__ import annotations

import argparse
import functools
import itertools
import json
import os
import subprocess
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np

STAGES = ("preprocess", "detector", "decode_nms", "pose_inputs", "fusion", "pose", "selection", "refine", "fit", "total")


def _pct(values: list[float]) -> dict:
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)), "p99": float(np.percentile(a, 99))}


@functools.lru_cache(maxsize=None)
def _scene(n_pallets: int, min_height_px: float = 8.0):
    """A 1224x370 synthetic frame with at least `n_pallets` ground-truth pallets at least `min_height_px` tall,
    and their boxes, most visible first: virtual-clean seed 0 (7 pallets) while it has enough, else the first
    virtual-occluded frame (seeds 0-9) that has."""
    from pallet6d.sim.generate import generate_frame
    from pallet6d.sim.presets import get_preset

    for preset, seeds in (("virtual-clean", [0]), ("virtual-occluded", range(10))):
        for seed in seeds:
            frame = generate_frame(get_preset(preset), seed=seed)
            boxes = [[x, y, x + w, y + h] for x, y, w, h in
                     (p.bbox_visib_xywh for p in sorted(frame.pallets, key=lambda p: -p.visib_fract))
                     if h >= min_height_px]
            if len(boxes) >= n_pallets:
                return frame, np.array(boxes, float)
    raise SystemExit(f"no synthetic frame with {n_pallets} pallets found (virtual-clean seed 0, virtual-occluded "
                     "seeds 0-9): ask for fewer --pallets")


def _detector_ms(est, rgb) -> dict[str, float]:
    """The detector stage on one image, step by step (ms)."""
    out = {}
    t = time.perf_counter()
    x, lb = est.detector.preprocess(rgb)
    out["preprocess"] = (time.perf_counter() - t) * 1000
    t = time.perf_counter()
    raw = est.detector.infer(x)
    out["detector"] = (time.perf_counter() - t) * 1000
    t = time.perf_counter()
    est.detector.postprocess(raw, lb)
    out["decode_nms"] = (time.perf_counter() - t) * 1000
    return out


def _spinning_off(runtime_options):
    """`runtime_options` (the runtime's `session_options`) with the pools' spinning off altogether: the baseline of
    `--spinning off`."""
    def options(threads: int):
        import onnxruntime as ort

        ort.set_default_logger_severity(3)      # not the warning that each entry is set again
        so = runtime_options(threads)
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.add_session_config_entry("session.force_spinning_stop", "0")
        return so
    return options


def bench_runtime(bundle: str, precision: str, threads: int, pallets: int, frames: int, frame, boxes,
                  refine_starts: int, pallet_lanes: int = 1, kernel: str = "compiled", spinning: str = "run",
                  pallet_types: tuple[str, ...] | None = None) -> dict:
    """:param pallet_types: `EstimatorOptions.pallet_types` (None: the bundle's every type, the default)."""
    from dataclasses import replace
    from unittest import mock

    from pallet6d.runtime import sessions
    from pallet6d.runtime.estimator import PalletEstimator

    # "off": the sessions are built with their pools' spinning off (the estimator keeps them)
    with (mock.patch.object(sessions, "session_options", _spinning_off(sessions.session_options))
          if spinning == "off" else nullcontext()):
        est = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, min_fit=0.0,
                                          refine_starts=refine_starts, pallet_lanes=pallet_lanes,
                                          pallet_types=pallet_types)
    # "numpy": refinement (ICP and fit scores) without the compiled kernel (the same poses), to compare in one run
    est.refiner.refine_options = replace(est.refiner.refine_options, compiled=kernel == "compiled")
    scores = np.linspace(0.9, 0.5, pallets)
    samples: dict[str, list[float]] = {s: [] for s in STAGES}
    for i in range(frames + 5):
        # the detector stage runs on the frame; its (random-init) boxes are replaced by the scene's P boxes,
        # which the pose stages get (estimate_boxes' total includes its own input check)
        det_ms = _detector_ms(est, frame.rgb)
        r = est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes[:pallets], scores=scores)
        ms = r.timings_ms | det_ms
        ms["total"] = r.timings_ms["total"] + sum(det_ms.values())
        if i >= 5:  # warm-up
            for s in STAGES:
                samples[s].append(ms[s])
    return {s: _pct(v) for s, v in samples.items()}


def bench_torch(config: str, threads: int, pallets: int, frames: int) -> dict:
    """The same three networks in torch eager (random weights, same shapes): p50/p95/p99 of their sum."""
    import torch

    from pallet6d.export.config import get_config
    from pallet6d.export.detector import build_detector
    from pallet6d.export.fusion import build_fusion
    from pallet6d.export.pose import build_pose

    torch.set_num_threads(threads)
    cfg = get_config(config)
    nets = [build_detector(cfg.detector).eval(), build_fusion(cfg.fusion).eval(),
            build_pose(cfg.pose, cfg.fusion.feature_dim).eval()]
    h, w = cfg.detector.input_hw
    ch, cw = cfg.fusion.crop_hw
    n, c = cfg.pose.num_points, cfg.fusion.feature_dim
    x_det = torch.zeros(1, 3, h, w)
    x_rgb, x_d = torch.randn(pallets, 3, ch, cw), torch.randn(pallets, 1, ch, cw)
    x_pts, x_feat = torch.randn(pallets, n, 3) * 0.3, torch.randn(pallets, n, c)
    # a sampled-feature fusion net (edge2*) takes the chosen pixels too: row * crop width + col
    x_choose = (torch.randint(0, ch * cw, (pallets, n)),) if cfg.fusion.sampled else ()
    out = []
    with torch.inference_mode():
        for i in range(frames + 3):
            t = time.perf_counter()
            nets[0](x_det)
            nets[1](x_rgb, x_d, *x_choose)
            nets[2](x_pts, x_feat)
            if i >= 3:
                out.append((time.perf_counter() - t) * 1000)
    return _pct(out)


_FOOTPRINT = """
import sys, time
t = time.perf_counter()
import numpy as np
from pallet6d.runtime.estimator import PalletEstimator
import_s = time.perf_counter() - t
est = PalletEstimator.from_bundle(sys.argv[1], threads=2, precision=sys.argv[2])
with np.load(sys.argv[3]) as z:
    rgb, depth, K, boxes = z["rgb"], z["depth_m"], z["K"], z["boxes"]
for _ in range(3):
    est.estimate(rgb, depth, K)
    est.estimate_boxes(rgb, depth, K, boxes_xyxy=boxes, scores=np.linspace(0.9, 0.5, len(boxes)))
# VmHWM, not ru_maxrss: after fork + exec ru_maxrss keeps the parent's size at the fork (this benchmark's own)
hwm_kb = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
print(import_s, hwm_kb / 1024, "torch" in sys.modules)
"""


def footprint(bundle: str, precision: str, pallets: int) -> dict:
    """Import time and peak RSS of a fresh process that runs the estimator on the scene of `pallets` pallets
    (detector on the frame, then the pose stages on those pallets' boxes)."""
    import tempfile

    frame, boxes = _scene(pallets)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "frame.npz"
        np.savez(path, rgb=frame.rgb, depth_m=frame.depth_m, K=frame.K, boxes=boxes[:pallets])
        out = subprocess.run([sys.executable, "-c", _FOOTPRINT, bundle, precision, str(path)], capture_output=True,
                             text=True, check=True)
    import_s, rss_mb, torch_loaded = out.stdout.split()
    return {"import_s": float(import_s), "peak_rss_mb": float(rss_mb), "torch_loaded": torch_loaded == "True",
            "pallets": pallets}


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what `platform` knows: the same code's timings differ
    between the machines a cloud hands out, so each table names its CPU."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_info(bundles: list[str]) -> dict:
    """What was measured, where and how: enough to reproduce the table and to judge it."""
    import platform

    import onnxruntime

    from pallet6d.runtime import kernels
    from pallet6d.runtime.bundle import load_bundle

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip() or None
    return {"command": " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "git_commit": commit,
            "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine(), "cpu_model": cpu_model(),
            "python": platform.python_version(), "onnxruntime": onnxruntime.__version__, "numpy": np.__version__,
            "kernels": kernels.available(),
            "bundles": {b.config: {"name": b.name, "random_init": bool(b.provenance.get("random_init"))}
                        for b in map(load_bundle, bundles)}}


def _markdown(results: list[dict], footprints: dict, info: dict) -> str:
    weights = ", ".join(f"{c}: {'random-init' if v['random_init'] else 'trained'} ({v['name']})"
                        for c, v in info["bundles"].items())
    lines = ["# Runtime latency (ms, 1224x370, this machine)", "",
             f"`{info['command']}` at {info['git_commit']} on {info['date_utc']}; {info['cpus']} CPUs "
             f"({info.get('cpu_model', 'model not recorded')}), "
             f"onnxruntime {info['onnxruntime']}, numpy {info['numpy']}, compiled kernels "
             f"{'built' if info.get('kernels') else 'not built'}. Weights: {weights} "
             "(latency does not depend on the weights' values).", "",
             "| bundle | precision | threads | lanes | pallets | types | kernel | spinning | ICP starts | "
             + " | ".join(f"{s} p50" for s in STAGES[:-1])
             + " | total p50 | total p95 | total p99 | torch eager nets p50 | onnx nets p50 | torch/onnx |",
             "|" + "---|" * (9 + len(STAGES) - 1 + 6)]
    for r in results:
        s = r["stages"]
        nets = s["detector"]["p50"] + s["fusion"]["p50"] + s["pose"]["p50"]
        t = r.get("torch_eager_nets")
        lines.append(f"| {r['bundle']} | {r['precision']} | {r['threads']} | {r.get('pallet_lanes', 1)} | "
                     f"{r['pallets']} | {r.get('pallet_types', 'all')} | {r.get('kernel', 'numpy')} | "
                     f"{r.get('spinning', 'off')} | "
                     f"{r['refine_starts']} | "
                     + " | ".join(f"{s[k]['p50']:.1f}" for k in STAGES[:-1])
                     + f" | {s['total']['p50']:.1f} | {s['total']['p95']:.1f} | {s['total']['p99']:.1f} | "
                     + (f"{t['p50']:.1f} | {nets:.1f} | {t['p50'] / nets:.2f} |" if t else f"- | {nets:.1f} | - |"))
    lines += ["", "| bundle | precision | import (s) | peak RSS (MB) | pallets | torch loaded |",
              "|---|---|---|---|---|---|"]
    for key, f in footprints.items():
        b, p = key.split("|")
        lines.append(f"| {b} | {p} | {f['import_s']:.3f} | {f['peak_rss_mb']:.0f} | {f['pallets']} | "
                     f"{f['torch_loaded']} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", action="append", required=True, help="bundle folder (repeatable)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--pallets", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--precision", nargs="+", default=["fp32", "int8"])
    ap.add_argument("--refine-starts", type=int, nargs="+", default=None,
                    help="extra ICP starts to measure (default: EstimatorOptions.refine_starts)")
    ap.add_argument("--pallet-lanes", type=int, nargs="+", default=[1],
                    help="EstimatorOptions.pallet_lanes to measure (default 1)")
    ap.add_argument("--kernel", nargs="+", choices=["compiled", "numpy"], default=["compiled"],
                    help="refinement (ICP, fit scores) in the compiled kernel (when built) and/or numpy "
                         "(default compiled)")
    ap.add_argument("--spinning", nargs="+", choices=["run", "off"], default=["run"],
                    help="onnxruntime's pools spin while a graph runs (run, the runtime's) or never (off); both: "
                         "measured one after the other (default run)")
    ap.add_argument("--pallet-types", nargs="+", default=["all"],
                    help="each measured: 'all' (the bundle's every type, the estimator's default) or comma-separated "
                         "type names (`EstimatorOptions.pallet_types`, e.g. epal)")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch eager comparison")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()

    from pallet6d.runtime import kernels
    from pallet6d.runtime.bundle import load_bundle
    from pallet6d.runtime.estimator import EstimatorOptions

    starts_list = args.refine_starts or [EstimatorOptions.refine_starts]
    results, footprints = [], {}
    for bundle in args.bundle:
        b = load_bundle(bundle)
        for precision in args.precision:
            if precision not in b.precision:
                print(f"{b.name}: no {precision} graphs, skipped", flush=True)
                continue
            footprints[f"{b.config}|{precision}"] = footprint(bundle, precision, max(args.pallets))
            for threads in args.threads:
                for pallets, types, starts, lanes, kernel, spinning in itertools.product(
                        args.pallets, args.pallet_types, starts_list, args.pallet_lanes, args.kernel, args.spinning):
                    frame, boxes = _scene(pallets)
                    stages = bench_runtime(bundle, precision, threads, pallets, args.frames, frame, boxes, starts,
                                           lanes, kernel, spinning, None if types == "all" else tuple(types.split(",")))
                    r = {"bundle": b.config, "precision": precision, "threads": threads, "pallet_lanes": lanes,
                         "pallets": pallets, "pallet_types": types,
                         "kernel": kernel if kernels.available() else "numpy",
                         "spinning": spinning, "refine_starts": starts, "frames": args.frames, "stages": stages}
                    if not args.no_torch and precision == "fp32":
                        r["torch_eager_nets"] = bench_torch(b.config, threads, pallets, max(20, args.frames // 4))
                    results.append(r)
                    print(json.dumps({k: v for k, v in r.items() if k != "stages"} |
                                     {"total_p50": stages["total"]["p50"]}), flush=True)
    info = run_info(args.bundle)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "latency.json").write_text(json.dumps({"run": info, "results": results, "footprint": footprints},
                                                      indent=1))
    (args.out / "latency.md").write_text(_markdown(results, footprints, info))
    print(_markdown(results, footprints, info))
    return 0


if __name__ == "__main__":
    sys.exit(main())
