"""Refinement for all pallets of a frame at once (`refine_batch`) against the detection-by-detection path.

    .venv/bin/python benchmarks/refine_speed.py --bundle models/epal-default \
        --data /work/data/val-virtual-clean /work/data/val-virtual-occluded /work/data/val-indoor-noisy

For each frame and each count P in --pallets, the estimator poses the frame's P most visible ground-truth
boxes (`estimate_boxes`, so P does not depend on the detector); the inputs of its refinement stage are
recorded per detection (the network's pose, the sampled points, the box's depth points), and both paths run
on exactly those inputs: the estimator's own (`PalletEstimator._refine`, detection by detection) and
`refine_batch`. Reports the largest pose difference between the two (translation mm, rotation degrees, fit
score) and the refinement time per frame (p50, p90; one process, the paths alternating, so both see the same
load). Writes benchmarks/results/refine-speed.md (and .json).
"""
from __future__ import annotations

import argparse
import json
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


def run(bundle: Path, data: list[Path], pallets: list[int], precision: str, max_frames: int) -> dict:
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.refine import RefineGeometry, RefineOptions, default_starts, refine_batch

    est = PalletEstimator.from_bundle(bundle, threads=2, precision=precision)
    o = est.options
    geom = RefineGeometry(est.model_points_m, est.model_boxes_m, default_starts(o.refine_starts))
    opts = RefineOptions(o.refine_iterations, o.refine_max_rms_m, o.refine_margin, o.fit_tol_m,
                         o.refine_start_points, o.refine_select_tol_m, o.refine_start_max_rms_m)
    out: dict = {"bundle": str(bundle), "precision": precision, "sets": {}}
    for path in data:
        ds = BopDataset(path)
        per_p = {}
        for P in pallets:
            worst_t = worst_r = worst_fit = 0.0
            t_loop, t_batch, n_det, n_frames = [], [], 0, 0
            for i in range(min(len(ds), max_frames)):
                frame = ds[i]
                rows = _record(est, frame, P)
                if not rows:
                    continue
                T_net = np.stack([r[0] for r in rows])
                obs = np.stack([r[1] for r in rows])
                box_obs = [r[2] for r in rows]
                t = time.perf_counter()
                for r in rows:
                    est._refine(r[0], r[1], r[2], frame.depth_m, frame.K)
                t_loop.append((time.perf_counter() - t) * 1000.0)
                t = time.perf_counter()
                res = refine_batch(T_net, obs, box_obs, geom, frame.depth_m, frame.K, opts)
                t_batch.append((time.perf_counter() - t) * 1000.0)
                for k, r in enumerate(rows):
                    dt, dr = _pose_diff(res.T_cam_pallet[k], r[3])
                    worst_t, worst_r = max(worst_t, dt), max(worst_r, dr)
                    worst_fit = max(worst_fit, abs(res.fits[k].score - r[4].score))
                n_det += len(rows)
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
