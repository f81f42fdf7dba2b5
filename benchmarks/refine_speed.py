"""Refinement for all pallets of a frame at once (`refine_batch`) against the detection-by-detection path.

    .venv/bin/python benchmarks/refine_speed.py --bundle models/epal-default \
        --data /work/data/val-virtual-clean /work/data/val-virtual-occluded /work/data/val-indoor-noisy

For each frame and each count P in --pallets, the estimator poses the frame's P most visible ground-truth
boxes (`PalletEstimator.candidates` on those boxes, so P does not depend on the detector); the inputs of its
refinement stage are taken per detection from the candidates (the network's pose, the sampled points, the box's
depth points), and both paths run on exactly those inputs: detection by detection (`refine_pose`, `fit_score`,
`best_landing`, as `per_detection` below) and the refiner stage's `refine` (`refine_batch`). Reports the
largest pose difference between the two (translation mm, rotation degrees, fit score) and the refinement
time per frame (p50, p90; one process, the paths alternating, so both see the same load). Writes
benchmarks/results/refine-speed.md (and .json).
"""
from __future__ import annotations

import argparse
import json
import sys
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


def run(bundle: Path, data: list[Path], pallets: list[int], precision: str, max_frames: int) -> dict:
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator

    est = PalletEstimator.from_bundle(bundle, threads=2, precision=precision)
    out: dict = {"bundle": str(bundle), "precision": precision, "sets": {}}
    for path in data:
        ds = BopDataset(path)
        per_p = {}
        for P in pallets:
            worst_t = worst_r = worst_fit = 0.0
            t_loop, t_batch, n_det, n_frames = [], [], 0, 0
            for i in range(min(len(ds), max_frames)):
                frame = ds[i]
                rec = _record(est, frame, P)
                if rec is None:
                    continue
                T_net, obs, box_obs, types, depth_m, K = rec
                t = time.perf_counter()
                loop = [per_detection(est, T_net[k], obs[k], box_obs[k], est.pallet_types[int(types[k])], depth_m, K)
                        for k in range(len(T_net))]
                t_loop.append((time.perf_counter() - t) * 1000.0)
                t = time.perf_counter()
                T_batch, fit_batch = est.refiner.refine(T_net, obs, box_obs, types, depth_m, K)
                t_batch.append((time.perf_counter() - t) * 1000.0)
                for k, (T_ref, fit_ref) in enumerate(loop):
                    dt, dr = _pose_diff(T_batch[k], T_ref)
                    worst_t, worst_r = max(worst_t, dt), max(worst_r, dr)
                    worst_fit = max(worst_fit, abs(fit_batch[k, 2] - fit_ref))
                n_det += len(loop)
                n_frames += 1
            if not n_frames:
                continue
            per_p[P] = {"frames": n_frames, "detections": n_det, "max_dt_mm": worst_t, "max_drot_deg": worst_r,
                        "max_dfit": worst_fit,
                        "loop_ms": {"p50": float(np.median(t_loop)), "p90": float(np.percentile(t_loop, 90))},
                        "batch_ms": {"p50": float(np.median(t_batch)), "p90": float(np.percentile(t_batch, 90))}}
            print(f"{path.name} P={P}: {per_p[P]}", flush=True)
        out["sets"][path.name] = per_p
    return out


def to_markdown(res: dict) -> str:
    lines = [f"# Batched refinement vs detection by detection ({res['bundle']}, {res['precision']}, 2 threads)", "",
             "Both paths on the same recorded network poses and points; time per frame of the refinement stage "
             "alone (ICP, starts, fit scores), milliseconds, measured on a shared 2-core machine (noisy).", "",
             "| set | pallets | frames | max dt mm | max drot deg | max dfit | per-detection p50 | batch p50 | "
             "batch p90 |", "|---|---|---|---|---|---|---|---|---|"]
    for name, per_p in res["sets"].items():
        for P, r in per_p.items():
            lines.append(f"| {name} | {P} | {r['frames']} | {r['max_dt_mm']:.4f} | {r['max_drot_deg']:.4f} | "
                         f"{r['max_dfit']:.4f} | {r['loop_ms']['p50']:.1f} | {r['batch_ms']['p50']:.1f} | "
                         f"{r['batch_ms']['p90']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=Path("models/epal-default"))
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument("--pallets", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--precision", default="int8", choices=("fp32", "int8"))
    ap.add_argument("--frames", type=int, default=30, help="at most this many frames per set")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/refine-speed"))
    a = ap.parse_args(argv)
    res = run(a.bundle, a.data, a.pallets, a.precision, a.frames)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    md = to_markdown(res)
    a.out.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
