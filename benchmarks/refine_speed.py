"""Refinement for all pallets of a frame at once (`refine_batch`) against the detection-by-detection path.

    .venv/bin/python benchmarks/refine_speed.py --bundle models/epal-default \
        --data data/val-virtual-clean data/val-virtual-occluded data/val-indoor-noisy

For each frame and each count P in --pallets, the estimator poses the frame's P most visible ground-truth
boxes (`PalletEstimator.candidates` on those boxes, so P does not depend on the detector); the inputs of its
refinement stage are taken per detection from the candidates (the network's pose, the sampled points, the box's
depth points), and both paths run on exactly those inputs: detection by detection (`refine_pose`, `fit_score`,
`best_landing`, as `per_detection` below) and the refiner stage's `refine` (`refine_batch`). Reports the
largest pose difference between the two (translation mm, rotation degrees, fit score) and the refinement
CPU time per frame (p50, p90; one process, the paths alternating, so both see the same load). Writes
benchmarks/results/refine-speed.md (and .json).

`--baseline REV` also times `refine_batch` as of git revision REV (its `runtime/refine.py` and `runtime/fit.py`,
loaded beside the current ones) on the same inputs in the same run, and reports how far its poses are from the
current ones. Recording the inputs runs the network on every frame (minutes on a busy machine):
`--save-inputs FILE` keeps them (a pickle) and `--inputs FILE` reuses them.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pallet6d.runtime.evaluation import counted_pallets


def _record(est, frame, n_pallets: int):
    """The refinement inputs of the frame's n most visible pallets: (T_net (n, 4, 4), obs (n, N, 3), box_obs
    [n (m, 3)], type_index (n,), depth_m, K), or None when the frame has too few.

    Beyond 8 pallets, a frame with at least 8 visible ones repeats them up to n (the validation frames hold
    at most 14): the work per detection is the same.
    """
    from pallet6d.runtime.detector import Detections

    counted = counted_pallets(frame.gts, unknown_visib_counts=False)   # a known visible fraction to sort by
    gts = sorted((g for g, c in zip(frame.gts, counted) if c), key=lambda g: -g.visib_fract)[:n_pallets]
    if len(gts) < min(n_pallets, 8):
        return None
    gts = [gts[i % len(gts)] for i in range(n_pallets)]
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (g.bbox_visib_xywh for g in gts)], float)
    rgb, depth_m, K = est.check_inputs(frame.rgb, frame.depth_m, frame.K)
    det = Detections(boxes, np.ones(len(boxes)), np.full(len(boxes), est.bundle.pallet_class_ids[0]))
    cands = est.candidates(rgb, depth_m, K, detections=det)
    cands = cands[~np.isnan(cands.fit[:, 2])]                # the rows the refiner ran on
    if not len(cands):
        return None
    box_obs = [est.refiner.box_points(cands.pixels[i], depth_m, K) for i in range(len(cands))]
    return cands.T_net, cands.points_cam, box_obs, cands.type_index, depth_m, K


def per_detection(est, T_net, obs, box_obs, g, depth_m, K):
    """One detection refined step by step (the reference path): ICP, the RMS and fit gate, the starts.

    :return: (T_cam_pallet (4, 4), fit score at `fit_tol_m`).
    """
    from pallet6d.runtime.fit import fit_score
    from pallet6d.runtime.refine import best_landing, refine_pose

    o = est.options
    T = T_net
    res = refine_pose(T_net, box_obs, g.boxes_m, iterations=o.refine_iterations)
    if np.isfinite(res.rms_m) and res.rms_m < o.refine_max_rms_m:
        fit_icp = fit_score(res.T_cam_pallet, obs, g.points_m, depth_m, K, o.fit_tol_m)
        fit_net = fit_score(T_net, obs, g.points_m, depth_m, K, o.fit_tol_m)
        if fit_icp.score >= fit_net.score + o.refine_margin:
            T = res.T_cam_pallet
    if o.refine_starts > 0:
        T, _ = best_landing(T, box_obs, g.boxes_m, o.refine_starts, o.refine_start_points,
                            lambda T_: fit_score(T_, box_obs, g.points_m, depth_m, K, o.refine_select_tol_m,
                                                 g.boxes_m).score, o.refine_start_max_rms_m, o.refine_iterations)
    return T, fit_score(T, obs, g.points_m, depth_m, K, o.fit_tol_m).score


def _pose_diff(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    """(translation difference mm, rotation difference degrees)."""
    dt = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3])) * 1000.0
    c = (np.trace(Ta[:3, :3].T @ Tb[:3, :3]) - 1.0) / 2.0
    return dt, float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def load_baseline(rev: str):
    """`runtime/refine.py` (with its `fit.py`) as of git revision `rev`, as a module beside the current one."""
    import pallet6d.runtime  # noqa: F401  (the package the loaded modules' relative imports resolve in)

    repo = Path(__file__).resolve().parents[1]
    folder = Path(tempfile.mkdtemp(prefix="refine-baseline-"))
    mods = {}
    for name in ("fit", "refine"):
        src = subprocess.run(["git", "-C", str(repo), "show", f"{rev}:runtime/{name}.py"], check=True,
                             capture_output=True, text=True).stdout
        src = src.replace("from .fit import", "from ._baseline_fit import")
        path = folder / f"_baseline_{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(f"pallet6d.runtime._baseline_{name}", path)
        mods[name] = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mods[name]
        spec.loader.exec_module(mods[name])
    return mods["refine"]


def _baseline_refine(base, est):
    """(T_net, obs, box_obs, types, depth_m, K) -> T_cam_pallet (n, 4, 4) by the baseline's `refine_batch`."""
    o = est.refiner.refine_options
    opts = base.RefineOptions(**{f: getattr(o, f) for f in base.RefineOptions.__dataclass_fields__})
    geoms = [None if g is None else base.RefineGeometry(g.model_points_m, g.boxes_m, g.starts)
             for g in est.refiner._refine_geometry]

    def refine(T_net, obs, box_obs, types, depth_m, K):
        return base.refine_batch(T_net, obs, box_obs, [geoms[int(j)] for j in types], depth_m, K, opts).T_cam_pallet
    return refine


def record_inputs(est, data: list[Path], pallets: list[int], max_frames: int) -> dict:
    """{set name: {P: [refinement inputs of one frame (`_record`)]}}."""
    from pallet6d.runtime.bop import BopDataset

    out: dict = {}
    for path in data:
        ds = BopDataset(path)
        out[path.name] = {P: [r for r in (_record(est, ds[i], P) for i in range(min(len(ds), max_frames)))
                              if r is not None] for P in pallets}
    return out


def _cpu_ms(fn, *args):
    """(fn(*args), CPU milliseconds of this process while it ran)."""
    t = time.process_time()
    res = fn(*args)
    return res, (time.process_time() - t) * 1000.0


def _stats(ms: list[float]) -> dict:
    return {"p50": float(np.median(ms)), "p90": float(np.percentile(ms, 90))}


def run(est, inputs: dict, baseline=None) -> dict:
    """Both paths (and the baseline's, when given) on the recorded inputs."""
    out: dict = {"sets": {}}
    for name, by_p in inputs.items():
        per_p = {}
        for P, recs in by_p.items():
            worst = {"dt": 0.0, "dr": 0.0, "fit": 0.0, "base_dt": 0.0, "base_dr": 0.0}
            t_loop, t_batch, t_base, n_det = [], [], [], 0
            for T_net, obs, box_obs, types, depth_m, K in recs:
                loop, ms = _cpu_ms(lambda: [per_detection(est, T_net[k], obs[k], box_obs[k],
                                                          est.pallet_types[int(types[k])], depth_m, K)
                                            for k in range(len(T_net))])
                t_loop.append(ms)
                (T_batch, fit_batch), ms = _cpu_ms(est.refiner.refine, T_net, obs, box_obs, types, depth_m, K)
                t_batch.append(ms)
                for k, (T_ref, fit_ref) in enumerate(loop):
                    dt, dr = _pose_diff(T_batch[k], T_ref)
                    worst["dt"], worst["dr"] = max(worst["dt"], dt), max(worst["dr"], dr)
                    worst["fit"] = max(worst["fit"], abs(fit_batch[k, 2] - fit_ref))
                if baseline is not None:
                    T_base, ms = _cpu_ms(baseline, T_net, obs, box_obs, types, depth_m, K)
                    t_base.append(ms)
                    for k in range(len(T_net)):
                        dt, dr = _pose_diff(T_batch[k], T_base[k])
                        worst["base_dt"], worst["base_dr"] = max(worst["base_dt"], dt), max(worst["base_dr"], dr)
                n_det += len(loop)
            if not recs:
                continue
            per_p[P] = {"frames": len(recs), "detections": n_det, "max_dt_mm": worst["dt"],
                        "max_drot_deg": worst["dr"], "max_dfit": worst["fit"], "loop_ms": _stats(t_loop),
                        "batch_ms": _stats(t_batch)}
            if baseline is not None:
                per_p[P].update(baseline_ms=_stats(t_base), baseline_max_dt_mm=worst["base_dt"],
                                baseline_max_drot_deg=worst["base_dr"])
            print(f"{name} P={P}: {per_p[P]}", flush=True)
        out["sets"][name] = per_p
    return out


def to_markdown(res: dict) -> str:
    base = res.get("baseline")
    lines = [f"# Batched refinement vs detection by detection ({res['bundle']}, {res['precision']})", "",
             "All paths on the same recorded network poses and points; CPU time per frame of the refinement stage "
             "alone (ICP, starts, fit scores), milliseconds, one process on a shared 2-core machine (noisy; the "
             "paths alternate frame by frame, so they see the same load; the compiled kernels' threads count "
             "together). max dt / drot / dfit: the batch's largest difference from the per-detection path."
             + (f" baseline: `refine_batch` as of `{base}`, with its largest pose difference from the batch." if base
                else ""), "",
             "| set | pallets | frames | max dt mm | max drot deg | max dfit | per-detection p50 | batch p50 | "
             "batch p90 |" + (" baseline p50 | baseline p90 | vs baseline dt mm / drot deg |" if base else ""),
             "|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if base else "")]
    for name, per_p in res["sets"].items():
        for P, r in per_p.items():
            row = (f"| {name} | {P} | {r['frames']} | {r['max_dt_mm']:.4f} | {r['max_drot_deg']:.4f} | "
                   f"{r['max_dfit']:.4f} | {r['loop_ms']['p50']:.1f} | {r['batch_ms']['p50']:.1f} | "
                   f"{r['batch_ms']['p90']:.1f} |")
            if base:
                row += (f" {r['baseline_ms']['p50']:.1f} | {r['baseline_ms']['p90']:.1f} | "
                        f"{r['baseline_max_dt_mm']:.4f} / {r['baseline_max_drot_deg']:.4f} |")
            lines.append(row)
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    ap.add_argument("--data", type=Path, nargs="+")
    ap.add_argument("--pallets", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--precision", default="int8", choices=("fp32", "int8"))
    ap.add_argument("--frames", type=int, default=30, help="at most this many frames per set")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/refine-speed"))
    ap.add_argument("--baseline", metavar="REV", help="also time refine_batch as of this git revision")
    ap.add_argument("--save-inputs", type=Path, help="write the recorded refinement inputs here (a pickle)")
    ap.add_argument("--inputs", type=Path, help="reuse recorded inputs (from --save-inputs) instead of --data")
    a = ap.parse_args(argv)
    if (a.inputs is None) == (a.data is None):
        ap.error("give --data or --inputs")
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(a.bundle, threads=2, precision=a.precision)
    if a.inputs is not None:
        with open(a.inputs, "rb") as f:
            inputs = pickle.load(f)       # a file this script wrote: trusted
    else:
        inputs = record_inputs(est, a.data, a.pallets, a.frames)
        if a.save_inputs is not None:
            with open(a.save_inputs, "wb") as f:
                pickle.dump(inputs, f)
    baseline = _baseline_refine(load_baseline(a.baseline), est) if a.baseline else None
    res = {"bundle": str(a.bundle), "precision": a.precision, "baseline": a.baseline, **run(est, inputs, baseline)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    md = to_markdown(res)
    a.out.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
