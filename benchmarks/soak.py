"""Soak run: the estimator on a looping recording for a long while; resident memory and latency per window.

A forklift runs the estimator for months: memory must level off after the warm-up and latency must not creep
up. This reads a recording in a loop through the same camera layer as `pallet6d run` and, every `--window`
frames, records the process's resident memory and the window's latency percentiles (never run by the tests).

    python benchmarks/soak.py --bundle models/epal-default [--int8] [--source bop:DIR|replay:DIR] [--calibrated] \\
        --minutes 10 [--fps F] --out benchmarks/results/soak

`--calibrated` (with `--source bop:DIR` of a forklift preset) passes each frame's camera calibration, so the
calibrated path runs too: levelling, the type search, weak boxes and the depth's proposals.

`--fps F` delivers the frames at most F a second, as a camera does (the estimator then idles between frames, as
it does on a forklift; back to back without it). Each window also records the machine's 1-minute load average, so a
window slowed by other work on the machine shows as such.

Without `--source` it makes a 30-frame `virtual-occluded` recording (seed 7, as `make run`) in a temporary folder.
Writes soak.json and soak.md in `--out`.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np


def rss_mb() -> float:
    """Current resident set size of this process, MB (Linux /proc; elsewhere the peak from getrusage)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def default_source(root: Path) -> str:
    """Generate the default recording in a subprocess, so the generator's imports do not count in the RSS."""
    cmd = [sys.executable, "-m", "pallet6d.runtime.cli", "sim", "--preset", "virtual-occluded", "--frames", "30",
           "--seed", "7", "--out", str(root)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"soak: could not generate the default recording:\n{done.stderr[-2000:]}")
    return f"bop:{root}"


def frames_in_a_loop(source: str, calibrated: bool):
    """(`estimate`'s positional arguments, its `T_vehicle_cam`) of each frame of `source`, played in a loop; with
    `calibrated` the frames of a BOP dataset (`bop:DIR`) with their own calibrations."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.cameras import open_source

    if not calibrated:
        with open_source(source, loop=True) as cam:
            for frame in cam:
                yield (frame,), None
        return
    if not source.startswith("bop:"):
        raise SystemExit(f"soak: --calibrated needs --source bop:DIR, got {source!r}")
    ds = BopDataset(source[len("bop:"):])
    if len(ds) == 0 or ds[0].T_vehicle_cam is None:
        raise SystemExit(f"soak: {source} has no frames with a vehicle calibration (scene_forklift.json)")
    while True:
        for i in range(len(ds)):
            f = ds[i]
            yield (f.rgb, f.depth_m, f.K), f.T_vehicle_cam


def soak(bundle: str, precision: str, threads: int, source: str, minutes: float, window: int,
         refine_starts: int | None = None, fps: float | None = None, calibrated: bool = False) -> dict:
    from pallet6d.runtime.estimator import PalletEstimator

    rss_start = rss_mb()
    extra = {} if refine_starts is None else {"refine_starts": refine_starts}
    est = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, **extra)
    windows, ms, poses, frames = [], [], 0, 0
    period_s = 1.0 / fps if fps else 0.0
    t_start = time.perf_counter()
    t_next = t_start
    for args, T_vehicle_cam in frames_in_a_loop(source, calibrated):
        if period_s:
            # the camera's next frame: wait for it, or take it at once when the last one ran late
            time.sleep(max(0.0, t_next - time.perf_counter()))
            t_next = max(t_next + period_s, time.perf_counter())
        result = est.estimate(*args, T_vehicle_cam=T_vehicle_cam)
        ms.append(result.timings_ms["total"])
        poses += len(result.poses)
        frames += 1
        if frames % window == 0:
            elapsed = time.perf_counter() - t_start
            windows.append({"frames": frames, "minutes": round(elapsed / 60, 2), "rss_mb": round(rss_mb(), 1),
                            "p50_ms": round(float(np.percentile(ms, 50)), 1),
                            "p95_ms": round(float(np.percentile(ms, 95)), 1), "poses_per_frame": poses / len(ms),
                            "load_1min": round(os.getloadavg()[0], 2)})
            print(json.dumps(windows[-1]), flush=True)
            ms, poses = [], 0
            if elapsed >= minutes * 60:
                break
    if len(windows) < 3:
        raise SystemExit("soak: fewer than three windows; run longer or use a smaller --window")
    return {"bundle": bundle, "precision": precision, "threads": threads, "fps": fps, "calibrated": calibrated,
            "refine_starts": est.options.refine_starts, "source": source, "frames": frames,
            "rss_before_mb": round(rss_start, 1), **rss_summary(windows), **latency_summary(windows),
            "windows": windows}


def rss_summary(windows: list[dict]) -> dict:
    """Memory growth after the first (warm-up) window: the peak of the second half minus the peak of the first
    (RSS rises and falls with the frames' content, so single readings or a fitted slope mislead), and the range."""
    rss = [w["rss_mb"] for w in windows[1:]]
    half = len(rss) // 2
    return {"rss_min_mb": min(rss), "rss_max_mb": max(rss),
            "rss_peak_growth_mb": round(max(rss[half:]) - max(rss[:half]), 1)}


def latency_summary(windows: list[dict]) -> dict:
    """Latency drift after the first (warm-up) window: the median window p50 / p95 of the second half minus
    that of the first half, ms (medians, so one window disturbed by other work on the machine does not decide)."""
    w = windows[1:]
    half = len(w) // 2

    def drift(key: str) -> float:
        return round(float(np.median([x[key] for x in w[half:]]) - np.median([x[key] for x in w[:half]])), 1)

    return {"p50_drift_ms": drift("p50_ms"), "p95_drift_ms": drift("p95_ms")}


def markdown(doc: dict, command: str) -> str:
    w = doc["windows"]
    lines = ["# Soak run", "", f"`{command}` on {doc['created']}, {doc['machine']}.", "",
             f"{doc['frames']} frames of `{doc['source']}` in a loop"
             f"{' at ' + format(doc['fps'], 'g') + ' frames/s' if doc.get('fps') else ', back to back'}, "
             f"{'each with its camera calibration, ' if doc.get('calibrated') else ''}"
             f"{doc['precision']}, onnxruntime threads={doc['threads']}, "
             f"{doc['refine_starts']} extra ICP starts. "
             f"RSS before loading the bundle {doc['rss_before_mb']} MB; after the first window it stays within "
             f"{doc['rss_min_mb']}-{doc['rss_max_mb']} MB, and the peak of the second half minus that of the first "
             f"is {doc['rss_peak_growth_mb']:+} MB. Latency drift (median window of the second half minus the "
             f"first, after the first window): p50 {doc['p50_drift_ms']:+} ms, p95 {doc['p95_drift_ms']:+} ms.", "",
             "| frames | minutes | RSS (MB) | p50 ms | p95 ms | poses / frame | load (1 min) |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {x['frames']} | {x['minutes']} | {x['rss_mb']} | {x['p50_ms']} | {x['p95_ms']} | "
              f"{x['poses_per_frame']:.2f} | {x.get('load_1min', '-')} |" for x in w]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", default="models/epal-default")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--source", help="bop:DIR or replay:DIR, played in a loop (default: a generated recording)")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--refine-starts", type=int, default=None,
                    help="extra ICP starts (default: EstimatorOptions.refine_starts)")
    ap.add_argument("--window", type=int, default=200, help="frames per reported window")
    ap.add_argument("--fps", type=float, default=None,
                    help="deliver at most this many frames a second, as a camera does (default: back to back)")
    ap.add_argument("--calibrated", action="store_true",
                    help="pass each frame's camera calibration (needs --source bop:DIR of a forklift preset)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/soak"))
    args = ap.parse_args(argv)
    if args.fps is not None and not args.fps > 0:
        ap.error(f"--fps must be positive, got {args.fps}")
    with tempfile.TemporaryDirectory() as tmp:
        source = args.source or default_source(Path(tmp) / "recording")
        doc = soak(args.bundle, "int8" if args.int8 else "fp32", args.threads, source, args.minutes, args.window,
                   args.refine_starts, args.fps, args.calibrated)
    if not args.source:
        doc["source"] = "generated: pallet6d sim --preset virtual-occluded --frames 30 --seed 7"
    doc["created"] = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    doc["machine"] = f"{os.cpu_count()} CPUs, {platform.machine()}, Python {platform.python_version()}"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "soak.json").write_text(json.dumps(doc, indent=1) + "\n")
    command = " ".join(["python benchmarks/soak.py", *sys.argv[1:]])
    (args.out / "soak.md").write_text(markdown(doc, command))
    print(f"RSS {doc['rss_min_mb']}-{doc['rss_max_mb']} MB after the first window, peak growth "
          f"{doc['rss_peak_growth_mb']:+} MB; latency drift p50 {doc['p50_drift_ms']:+} ms, p95 "
          f"{doc['p95_drift_ms']:+} ms; wrote {args.out}/soak.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
