"""Refinement for all pallets of a frame at once (`refine_batch`) against the detection-by-detection path.

    # the reference: any installed version of pallet6d (e.g. main's) records its per-detection refinement
    /work/main/.venv/bin/python benchmarks/refine_speed.py record --data /work/data/val-virtual-clean \
        /work/data/val-virtual-occluded /work/data/val-indoor-noisy --out /work/runs/refine-ref.pkl
    # this checkout: refine_batch on the same inputs, compared with the recording, timed against main's path
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/refine_speed.py compare --ref /work/runs/refine-ref.pkl \
        --ref-src /work/main

For each frame and each count P in --pallets, the estimator poses the frame's P most visible ground-truth
boxes (`estimate_boxes`, so P does not depend on the detector); the inputs of its refinement stage are
recorded per detection (the network's pose, the sampled points, the box's depth points) with its result
(`PalletEstimator._refine`, detection by detection) and the time it took. `compare` runs `refine_batch` on
exactly those inputs and reports the largest pose difference (translation mm, rotation degrees, fit score),
and per frame the CPU time of `refine_batch` and of the per-detection path (this checkout's, or with
--ref-src another checkout's runtime imported beside it), alternating in one run (CPU time: one thread's
work, less sensitive to other jobs than wall time on a shared machine; hold numpy's BLAS to one thread,
OPENBLAS_NUM_THREADS=1). Writes benchmarks/results/refine-speed.md (and .json).
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

MIN_VISIB = 0.1


def _record(est, frame, n_pallets: int) -> list[tuple] | None:
    """The refinement inputs of the frame's n most visible pallets: [(T_net, obs, box_obs, T_ref, fit_ref)].

    Beyond 8 pallets, a frame with at least 8 visible ones repeats them up to n (the validation frames hold
    at most 14): the work per detection is the same.
    """
    from pallet6d.runtime.fit import fit_score

    gts = sorted((g for g in frame.gts if g.bbox_visib_xywh is not None and g.visib_fract >= MIN_VISIB),
                 key=lambda g: -g.visib_fract)[:n_pallets]
    if len(gts) < min(n_pallets, 8):
        return None
    gts = [gts[i % len(gts)] for i in range(n_pallets)]
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (g.bbox_visib_xywh for g in gts)], float)
    rows: list[tuple] = []
    original = est._refine

    def recorder(T_net, obs, box_obs, depth_m, K):
        T, fit = original(T_net, obs, box_obs, depth_m, K)
        if fit is None:
            fit = fit_score(T, obs, est.model_points_m, depth_m, K, est.options.fit_tol_m)
        rows.append((T_net.copy(), obs.copy(), box_obs.copy(), T.copy(), fit))
        return T, fit

    est._refine = recorder
    try:
        est.estimate_boxes(frame.rgb, frame.depth_m, frame.K, boxes_xyxy=boxes)
    finally:
        del est._refine
    return rows


def _pose_diff(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    """(translation difference mm, rotation difference degrees)."""
    dt = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3])) * 1000.0
    c = (np.trace(Ta[:3, :3].T @ Tb[:3, :3]) - 1.0) / 2.0
    return dt, float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def record(bundle: Path, data: list[Path], pallets: list[int], precision: str, max_frames: int) -> dict:
    """Per set and count P: frames of [(T_net, obs, box_obs, T_ref, fit_ref)] with depth, K and CPU ms."""
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle, threads=2, precision=precision)
    o = est.options
    out: dict = {"bundle": str(bundle), "precision": precision, "refine_starts": o.refine_starts, "sets": {}}
    for path in data:
        ds = BopDataset(path)
        out["sets"][path.name] = per_p = {}
        for P in pallets:
            frames = []
            for i in range(min(len(ds), max_frames)):
                frame = ds[i]
                rows = _record(est, frame, P)
                if not rows:
                    continue
                t = time.process_time()
                for r in rows:
                    est._refine(r[0], r[1], r[2], frame.depth_m, frame.K)
                ms = (time.process_time() - t) * 1000.0
                frames.append({"rows": [(r[0], r[1], r[2], r[3], (r[4].inlier_fraction, r[4].free_space_violation,
                                                                 r[4].score)) for r in rows],
                               "depth_m": frame.depth_m, "K": frame.K, "cpu_ms": ms})
            per_p[P] = frames
            print(f"{path.name} P={P}: {len(frames)} frames", flush=True)
    return out


def _runtime_from(src: Path):
    """The `runtime` package of another checkout (its folder `src/runtime`), imported under another name."""
    name = "pallet6d_reference_runtime"
    spec = importlib.util.spec_from_file_location(name, src / "runtime" / "__init__.py",
                                                  submodule_search_locations=[str(src / "runtime")])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return importlib.import_module(f"{name}.estimator")


def compare(ref: dict, bundle: Path, ref_src: Path | None) -> dict:
    from pallet6d.runtime import estimator
    from pallet6d.runtime.refine import RefineGeometry, default_starts, refine_batch

    module = estimator if ref_src is None else _runtime_from(ref_src)
    est = module.PalletEstimator.from_bundle(bundle, threads=2, precision=ref["precision"],
                                             refine_starts=ref["refine_starts"])
    geom = RefineGeometry(est.model_points_m, est.model_boxes_m, default_starts(ref["refine_starts"]))
    out: dict = {"bundle": ref["bundle"], "precision": ref["precision"], "sets": {},
                 "per_detection_code": str(ref_src or "this checkout")}
    for name, per_p in ref["sets"].items():
        out["sets"][name] = res_p = {}
        for P, frames in per_p.items():
            if not frames:
                continue
            worst_t = worst_r = worst_fit = 0.0
            t_batch, t_loop = [], []
            for f in frames:
                rows = f["rows"]
                args = (np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows]), [r[2] for r in rows], geom,
                        f["depth_m"], f["K"])
                t = time.process_time()            # the per-detection path, in the same run
                for r in rows:
                    est._refine(r[0], r[1], r[2], f["depth_m"], f["K"])
                t_loop.append((time.process_time() - t) * 1000.0)
                t = time.process_time()
                res = refine_batch(*args)
                t_batch.append((time.process_time() - t) * 1000.0)
                for k, r in enumerate(rows):
                    dt, dr = _pose_diff(res.T_cam_pallet[k], r[3])
                    worst_t, worst_r = max(worst_t, dt), max(worst_r, dr)
                    worst_fit = max(worst_fit, abs(res.fits[k].score - r[4][2]))
            t_rec = [f["cpu_ms"] for f in frames]
            res_p[P] = {"recorded_ms": {"p50": float(np.median(t_rec))}, "frames": len(frames),
                        "detections": sum(len(f["rows"]) for f in frames),
                        "max_dt_mm": worst_t, "max_drot_deg": worst_r, "max_dfit": worst_fit,
                        "loop_ms": {"p50": float(np.median(t_loop)), "p90": float(np.percentile(t_loop, 90))},
                        "batch_ms": {"p50": float(np.median(t_batch)), "p90": float(np.percentile(t_batch, 90))}}
            print(f"{name} P={P}: {res_p[P]}", flush=True)
    return out


def to_markdown(res: dict) -> str:
    lines = [f"# Batched refinement vs detection by detection ({res['bundle']}, {res['precision']})", "",
             "Both paths on the same recorded network poses and points; CPU time per frame of the refinement stage "
             "alone (ICP, starts, fit scores), milliseconds, one thread, on a shared 2-core machine.", "",
             f"per-detection: `PalletEstimator._refine` of {res['per_detection_code']}, detection by detection, "
             "timed in the same run as the batch (alternating per frame); recorded: the recording's own "
             "per-detection time (another run, other load).", "",
             "| set | pallets | frames | max dt mm | max drot deg | max dfit | per-detection p50 | batch p50 | "
             "batch p90 | recorded p50 |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, per_p in res["sets"].items():
        for P, r in per_p.items():
            lines.append(f"| {name} | {P} | {r['frames']} | {r['max_dt_mm']:.4f} | {r['max_drot_deg']:.4f} | "
                         f"{r['max_dfit']:.4f} | {r['loop_ms']['p50']:.1f} | {r['batch_ms']['p50']:.1f} | "
                         f"{r['batch_ms']['p90']:.1f} | {r['recorded_ms']['p50']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record the per-detection path's inputs, results and times")
    r.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    r.add_argument("--data", type=Path, nargs="+", required=True)
    r.add_argument("--pallets", type=int, nargs="+", default=[1, 4, 16])
    r.add_argument("--precision", default="int8", choices=("fp32", "int8"))
    r.add_argument("--frames", type=int, default=30, help="at most this many frames per set")
    r.add_argument("--out", type=Path, required=True)
    c = sub.add_parser("compare", help="refine_batch on a recording: differences and times")
    c.add_argument("--ref", type=Path, required=True)
    c.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    c.add_argument("--out", type=Path, default=Path("benchmarks/results/refine-speed"))
    c.add_argument("--ref-src", type=Path, help="time the per-detection path of this checkout's runtime instead "
                                                "(e.g. /work/main); default: this checkout's")
    a = ap.parse_args(argv)
    if a.cmd == "record":
        a.out.parent.mkdir(parents=True, exist_ok=True)
        with open(a.out, "wb") as fh:
            pickle.dump(record(a.bundle, a.data, a.pallets, a.precision, a.frames), fh)
        return 0
    with open(a.ref, "rb") as fh:
        res = compare(pickle.load(fh), a.bundle, a.ref_src)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    md = to_markdown(res)
    a.out.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
