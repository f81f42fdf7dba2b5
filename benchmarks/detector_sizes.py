"""Detector input sizes: one detector graph's latency at each input size, fp32 and int8, what a graph with
dynamic height/width costs against a static one at the same size, and how far int8 strays from fp32 at each
size when it was calibrated on frames letterboxed at every size.

    nice -n 15 .venv/bin/python benchmarks/detector_sizes.py --bundle models/epal-default \\
        --sizes 192x640,288x384,256x448 --out runs/detinput

Weights: the bundle's detector read back into torch (`export.bundle_weights.bundle_checkpoint`). Graphs: one
static at the bundle's input_hw, one with dynamic height/width (`bundle_export.DET_DYNAMIC_AXES`), each
quantized with the export's int8 recipe: the dynamic one calibrated on sim frames letterboxed at every size
(the first 3/4 of --calib-frames; the rest are held out), the static one on the same frames at its size.
Timings: `OnnxModel.run` on a letterboxed sim frame, --threads threads, the graphs taking turns in one process,
p10/p50/p95 over --runs runs; on a shared machine compare numbers within one run only.

Writes detector-sizes.json and detector-sizes.md to --out.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import time
from pathlib import Path

import numpy as np


def _sizes(text: str) -> list[tuple[int, int]]:
    return [tuple(int(v) for v in part.split("x")) for part in text.split(",")]


def build(bundle: Path, sizes: list[tuple[int, int]], out: Path, calib_frames: int) -> tuple[dict, object, int]:
    """Export and quantize the static and the dynamic graph; return their paths, the calibration set and the
    number of calibration frames (the rest are held out)."""
    import torch

    from pallet6d.export.bundle_export import DET_DYNAMIC_AXES
    from pallet6d.export.bundle_weights import bundle_checkpoint
    from pallet6d.export.calib_data import make_calibration_set
    from pallet6d.export.config import get_config
    from pallet6d.export.detector import build_detector
    from pallet6d.export.export_inputs import DET_IN, DET_OUT
    from pallet6d.export.onnx_io import check_parity, export_graph
    from pallet6d.export.quantize import INT8_RECIPES, quantize_graph
    from pallet6d.runtime.bundle import load_bundle

    b = load_bundle(bundle)
    ref = tuple(b.detector.input_hw)
    cfg = get_config(b.config)
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=ref))
    ckpt = bundle_checkpoint(bundle, "detector")
    net = build_detector(cfg.detector).eval()
    net.load_state_dict(ckpt["detector"])
    calib = make_calibration_set(cfg, frames=calib_frames, max_crops=4, detector_sizes=sizes)
    n_cal = max(1, (3 * calib_frames) // 4)
    out.mkdir(parents=True, exist_ok=True)
    example = (torch.from_numpy(calib.images[:1]),)
    paths = {"static": export_graph(net, example, out / "static.onnx", [DET_IN], [DET_OUT]),
             "dynamic": export_graph(net, example, out / "dynamic.onnx", [DET_IN], [DET_OUT], DET_DYNAMIC_AXES)}
    for hw in sizes:
        check_parity(net, (torch.from_numpy(calib.images_at(hw)[:1]),), paths["dynamic"], [DET_IN], [DET_OUT])
    feeds = {"static": [{DET_IN: calib.images[i:i + 1]} for i in range(n_cal)],
             "dynamic": [{DET_IN: calib.images_at(hw)[i:i + 1]} for i in range(n_cal) for hw in sizes]}
    for kind in ("static", "dynamic"):
        paths[f"{kind}-int8"] = quantize_graph(paths[kind], out / f"{kind}.int8.onnx", feeds[kind],
                                               **INT8_RECIPES["detector"])
    return paths, calib, n_cal


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, 4), (m, 4) xyxy -> (n, m) IoU."""
    lt, rb = np.maximum(a[:, None, :2], b[None, :, :2]), np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area = lambda x: np.prod(x[:, 2:] - x[:, :2], axis=1)  # noqa: E731
    return inter / (area(a)[:, None] + area(b)[None, :] - inter)


def int8_vs_fp32(paths: dict, calib, n_cal: int, sizes: list[tuple[int, int]], score: float) -> dict:
    """Per size, on the held-out frames: the dynamic int8 graph's raw output against the dynamic fp32 graph's,
    and its detections (score > `score`, NMS 0.5): how many of fp32's it finds at IoU > 0.5 and their median IoU."""
    from pallet6d.export.onnx_io import compare_outputs, ort_session
    from pallet6d.runtime.detector import decode_yolov8

    f32, i8 = ort_session(paths["dynamic"]), ort_session(paths["dynamic-int8"])
    diffs = {}
    for hw in sizes:
        imgs = calib.images_at(hw)[n_cal:]
        raw = [(f32.run(None, {"images": imgs[i:i + 1]})[0], i8.run(None, {"images": imgs[i:i + 1]})[0])
               for i in range(len(imgs))]
        d = compare_outputs(np.concatenate([a.ravel() for a, _ in raw]),
                            np.concatenate([b.ravel() for _, b in raw])).to_dict()
        ious, n_ref, n_int8 = [], 0, 0
        for a, b in raw:
            da, db = decode_yolov8(a, score, 0.5), decode_yolov8(b, score, 0.5)
            n_ref, n_int8 = n_ref + len(da), n_int8 + len(db)
            if len(da):
                ious += list(_iou(da.boxes_xyxy, db.boxes_xyxy).max(axis=1) if len(db) else np.zeros(len(da)))
        ious = np.asarray(ious)
        d.update(fp32_detections=n_ref, int8_detections=n_int8,
                 found_iou50=float(np.mean(ious > 0.5)) if n_ref else None,
                 median_iou=float(np.median(ious)) if n_ref else None)
        diffs[f"{hw[0]}x{hw[1]}"] = d
    return diffs


def time_graphs(paths: dict, calib, sizes: list[tuple[int, int]], ref: tuple[int, int], threads: int,
                runs: int) -> dict:
    """p10/p50/p95 ms per (graph, size); the static graphs at the reference size only. On a loaded machine p10 is
    the closest to the graph's own cost."""
    from pallet6d.runtime.sessions import OnnxModel

    cases = [(kind, hw) for kind in ("dynamic", "dynamic-int8") for hw in sizes]
    cases += [(kind, ref) for kind in ("static", "static-int8")]
    models = {kind: OnnxModel(p, threads, ("images",), ("output0",)) for kind, p in paths.items()}
    inputs = {hw: np.ascontiguousarray(calib.images_at(hw)[:1]) for hw in sizes}
    samples = {c: [] for c in cases}
    for i in range(runs + 5):
        for kind, hw in cases:                      # taking turns: machine load affects all alike
            t = time.perf_counter()
            models[kind].run({"images": inputs[hw]}, ["output0"])
            if i >= 5:
                samples[(kind, hw)].append((time.perf_counter() - t) * 1000)
    return {f"{kind} {hw[0]}x{hw[1]}": {q: float(np.percentile(v, int(q[1:]))) for q in ("p10", "p50", "p95")}
            for (kind, hw), v in samples.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    ap.add_argument("--sizes", type=_sizes, default=_sizes("192x640,288x384,256x448"),
                    help="input sizes HxW,...; the bundle's input_hw first (the static graph's size)")
    ap.add_argument("--calib-frames", type=int, default=24)
    ap.add_argument("--score", type=float, default=0.25, help="detection score threshold of the int8 comparison")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=300)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    paths, calib, n_cal = build(args.bundle, args.sizes, args.out, args.calib_frames)
    ref = tuple(calib.images.shape[2:])
    from pallet6d.export.export_inputs import git_commit

    when = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes")
    result = {"bundle": str(args.bundle), "git_commit": git_commit(), "date": when, "sizes": [list(hw) for hw in args.sizes], "threads": args.threads,
              "runs": args.runs, "calibration": calib.source, "held_out_frames": args.calib_frames - n_cal,
              "int8_vs_fp32": int8_vs_fp32(paths, calib, n_cal, args.sizes, args.score),
              "latency_ms": time_graphs(paths, calib, args.sizes, ref, args.threads, args.runs)}
    (args.out / "detector-sizes.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [f"# Detector latency per input size ({args.bundle}, {args.threads} threads, {args.runs} runs)", "",
             f"`benchmarks/detector_sizes.py`, commit {result['git_commit']}, {when}; on a shared machine compare "
             "within one run only.", "",
             "| graph | input | p10 ms | p50 ms | p95 ms |", "|---|---|---|---|---|"]
    for key, v in result["latency_ms"].items():
        kind, hw = key.split(" ")
        lines.append(f"| {kind} | {hw} | {v['p10']:.1f} | {v['p50']:.1f} | {v['p95']:.1f} |")
    lines += ["", f"int8 vs fp32 on {result['held_out_frames']} held-out frames (detections: score > {args.score})", "",
              "| input | corr | rel. RMS | fp32 / int8 detections | fp32 found by int8 (IoU > 0.5) | median IoU |",
              "|---|---|---|---|---|---|"]
    for hw, d in result["int8_vs_fp32"].items():
        found = "-" if d["found_iou50"] is None else f"{100 * d['found_iou50']:.0f} %"
        iou = "-" if d["median_iou"] is None else f"{d['median_iou']:.3f}"
        lines.append(f"| {hw} | {d['corr']:.5f} | {d['rel_rms']:.4f} | {d['fp32_detections']} / "
                     f"{d['int8_detections']} | {found} | {iou} |")
    (args.out / "detector-sizes.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
