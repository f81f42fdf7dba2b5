"""Where the runtime's memory goes: resident set size step by step (never run by the tests).

Each precision runs in a fresh subprocess (`python benchmarks/memory.py --child ...`) that records VmRSS and
VmHWM (/proc/self/status) after each step: the interpreter + numpy, `import cv2`, `import onnxruntime`, the
runtime's import, the bundle's manifest, each onnxruntime session as the estimator creates it, the first run
of each graph, then frames: `estimate_boxes` with 1, 4, 8 and 16 pallets and `estimate` (detector on the
whole frame) at 1224x370 and 848x480. The numpy column is tracemalloc's peak of traced allocations
during the step (numpy reports its array buffers to tracemalloc; onnxruntime's own allocations are not
traced). The frames are random images with a flat floor 3 m away; the boxes are fixed, so the number of
pallets the pose stages see does not depend on the detector.

    nice -n 15 .venv/bin/python benchmarks/memory.py --bundle models/epal-default

Writes benchmarks/results/memory.md (the table) and memory.json.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path


def _status_mb() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process, MB."""
    vals = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, kb, _ = line.split()
                vals[key[:-1]] = int(kb) / 1024
    return vals["VmRSS"], vals["VmHWM"]


class _Steps:
    """Step records: name, RSS after, RSS added, high-water mark after, traced numpy peak during."""

    def __init__(self) -> None:
        import tracemalloc

        self.tm = tracemalloc
        self.rows: list[dict] = []
        self.last = _status_mb()[0]

    def mark(self, name: str) -> None:
        rss, hwm = _status_mb()
        traced = self.tm.get_traced_memory()[1] / 2**20 if self.tm.is_tracing() else float("nan")
        self.rows.append({"step": name, "rss_mb": rss, "added_mb": rss - self.last, "hwm_mb": hwm,
                          "numpy_peak_mb": traced})
        self.last = rss
        if self.tm.is_tracing():
            self.tm.reset_peak()


def _frame(h: int, w: int, seed: int = 0):
    import numpy as np

    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    depth = np.full((h, w), 3.0, np.float32) + rng.normal(0, 0.005, (h, w)).astype(np.float32)
    K = np.array([[700.0 * w / 1224, 0, w / 2], [0, 700.0 * w / 1224, h / 2], [0, 0, 1]])
    return rgb, depth, K


def _boxes(h: int, w: int, n: int):
    """n boxes of 120x60 px on a grid over the frame."""
    import numpy as np

    cols = max(1, (w - 20) // 130)
    out = [[10 + 130 * (i % cols), 10 + 70 * ((i // cols) % max(1, (h - 20) // 70)), 0, 0] for i in range(n)]
    b = np.array(out, float)
    b[:, 2], b[:, 3] = b[:, 0] + 120, b[:, 1] + 60
    return b


def child(bundle: str, precision: str, threads: int, frames: int) -> list[dict]:
    """The step table of one fresh process (this is the subprocess's body)."""
    steps = _Steps()
    steps.mark("interpreter")
    import numpy as np  # noqa: F401

    steps.mark("import numpy")
    import cv2  # noqa: F401

    steps.mark("import cv2")
    import onnxruntime  # noqa: F401

    steps.mark("import onnxruntime")
    from pallet6d.runtime import sessions
    from pallet6d.runtime.bundle import load_bundle
    from pallet6d.runtime.estimator import EstimatorOptions, PalletEstimator

    steps.mark("import pallet6d.runtime.estimator")
    steps.tm.start()
    b = load_bundle(bundle)
    steps.mark("load_bundle (manifest, pallet points)")

    cls = sessions.OnnxModel
    init, run = cls.__init__, cls.run
    seen: set[str] = set()

    def traced_init(self, path, *a, **k):
        init(self, path, *a, **k)
        steps.mark(f"session {Path(path).name}")

    def traced_run(self, feeds, outputs=None):
        out = run(self, feeds, outputs)
        if self.path.name not in seen:
            seen.add(self.path.name)
            steps.mark(f"first run {self.path.name} (batch {len(next(iter(feeds.values())))})")
        return out

    cls.__init__, cls.run = traced_init, traced_run
    est = PalletEstimator(b, threads=threads, precision=precision, options=EstimatorOptions(min_fit=0.0))
    steps.mark("estimator stages")
    for h, w in ((370, 1224), (480, 848)):
        rgb, depth, K = _frame(h, w)
        for n in (1, 4, 8, 16):
            boxes = _boxes(h, w, n)
            for _ in range(frames):
                est.estimate_boxes(rgb, depth, K, boxes_xyxy=boxes)
            steps.mark(f"{w}x{h}: {frames} frames, {n} pallets")
        for _ in range(frames):
            est.estimate(rgb, depth, K)
        steps.mark(f"{w}x{h}: {frames} frames, detector + its detections")
    cls.__init__, cls.run = init, run
    return steps.rows


def _markdown(runs: dict[str, list[dict]], info: dict) -> str:
    lines = ["# Runtime memory (MB, this machine)", "",
             f"`{info['command']}` at {info['git_commit']} on {info['date_utc']}; onnxruntime {info['onnxruntime']}, "
             f"numpy {info['numpy']}, {info['threads']} threads. RSS after each step and what the step added; HWM: "
             "peak RSS so far; numpy: tracemalloc's peak of numpy buffers during the step.", ""]
    for key, rows in runs.items():
        lines += [f"## {key}", "", "| step | RSS | added | HWM | numpy peak |", "|---|---|---|---|---|"]
        for r in rows:
            npk = "" if r["numpy_peak_mb"] != r["numpy_peak_mb"] else f"{r['numpy_peak_mb']:.1f}"
            lines.append(f"| {r['step']} | {r['rss_mb']:.1f} | {r['added_mb']:+.1f} | {r['hwm_mb']:.1f} | {npk} |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", default=str(Path(__file__).parents[1] / "models" / "epal-default"))
    ap.add_argument("--precision", nargs="+", default=["int8", "fp32"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.bundle, args.precision[0], args.threads, args.frames)))
        return 0
    runs = {}
    for p in args.precision:
        out = subprocess.run([sys.executable, __file__, "--child", "--bundle", args.bundle, "--precision", p,
                              "--threads", str(args.threads), "--frames", str(args.frames)],
                             capture_output=True, text=True, check=True)
        runs[p] = json.loads(out.stdout.strip().splitlines()[-1])
    import numpy
    import onnxruntime

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip() or None
    info = {"command": " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]), "git_commit": commit,
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "onnxruntime": onnxruntime.__version__,
            "numpy": numpy.__version__, "threads": args.threads}
    md = _markdown(runs, info)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "memory.json").write_text(json.dumps({"run": info, "steps": runs}, indent=1))
    (args.out / "memory.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
