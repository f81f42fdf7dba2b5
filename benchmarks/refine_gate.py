"""When to keep the ICP-refined pose: the network's and ICP's pose errors per detected pallet, and gates on them.

    python benchmarks/refine_gate.py --bundle models/epal-default --data DIR [DIR ...] [--int8] [--out FILE.md]

For every detection matched to a ground-truth pallet (IoU >= 0.5, >= 10 % visible) it records the symmetric ADD of
the network's pose and of ICP's pose, both poses' fit scores and ICP's final point-to-plane RMS, then scores gates
(`EstimatorOptions.refine_max_rms_m`, `refine_margin`) on them offline: the table that chose the defaults. Use
validation sets (`pallet6d sim` with seeds other than training's 1000+ and test's 9001-9003), not the test sets.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from pallet6d.runtime import metrics
from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.evaluation import box_iou, counted_pallets, ground_truths_from_bop
from pallet6d.runtime.refine import refine_pose

THRESHOLDS_M = (0.02, 0.05, 0.1)
GATES = [("network alone", None, None), ("ICP always", 1.0, -1.0)] + \
    [(f"RMS < {r * 1000:g} mm, margin {m:g}", r, m) for r in (0.003, 0.004, 0.005) for m in (0.0, 0.02)] + \
    [(f"fit score only, margin {m:g}", 1.0, m) for m in (0.0, 0.02)]


def icp_rows(est: PalletEstimator, f):
    """A frame's posed candidates (network poses: `est` without refinement) and ICP from each network pose,
    through the stages' public API.

    :return: the posed `Candidates` (n rows), ICP's poses (n, 4, 4), and per candidate (n, 3): fit score of the
        network's pose, of ICP's pose, ICP's final RMS (m; nan: ICP gave no result, its pose is the network's).
    """
    rgb, depth_m, K = est.check_inputs(f.rgb, f.depth_m, f.K)
    cands = est.candidates(rgb, depth_m, K)
    cands = cands[cands.alive]
    T_icp, rows = cands.T_net.copy(), np.zeros((len(cands), 3))
    for i in range(len(cands)):
        g = est.pallet_types[int(cands.type_index[i])]
        box_obs = est.refiner.box_points(cands.pixels[i], depth_m, K)
        res = refine_pose(cands.T_net[i], box_obs, g.boxes_m, iterations=est.options.refine_iterations)
        if np.isfinite(res.rms_m):
            T_icp[i] = res.T_cam_pallet
        fit_icp = est.fit_check.score(T_icp[i:i + 1], cands.points_cam[i:i + 1], cands.type_index[i:i + 1],
                                      depth_m, K)[0, 2]
        rows[i] = cands.fit[i, 2], fit_icp, res.rms_m
    return cands, T_icp, rows


def pallet_rows(bundle: str, data: Path, precision: str, threads: int) -> np.ndarray:
    """(n, 5): ADD-sym of the network's pose, of ICP's pose (m), their fit scores, ICP's RMS (m; nan: no result)."""
    plain = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, refine=False, min_fit=0.0, structure=None)
    rows = []
    ds = BopDataset(data)
    for i in range(len(ds)):
        f = ds[i]
        gts, _ = ground_truths_from_bop(f.gts)
        counted = counted_pallets(gts)
        cands, T_icp, fit_rms = icp_rows(plain, f)
        if not gts or not len(cands):
            continue
        iou = box_iou(cands.boxes_xyxy, np.array([g.box_visib_xyxy for g in gts]))
        for k in range(len(cands)):
            j = int(iou[k].argmax())
            if iou[k, j] < 0.5 or not counted[j]:
                continue
            g = plain.pallet_types[int(cands.type_index[k])]
            R_gt, t_gt = gts[j].T_cam_model[:3, :3], gts[j].T_cam_model[:3, 3]
            err = [metrics.add_sym(T[:3, :3], T[:3, 3], R_gt, t_gt, g.points_m, g.symmetries)
                   for T in (cands.T_net[k], T_icp[k])]
            rows.append([*err, *fit_rms[k]])
    return np.array(rows).reshape(-1, 5)


def gate_errors(rows: np.ndarray, max_rms_m: float | None, margin: float | None) -> np.ndarray:
    """ADD-sym (m) of the pose the gate keeps, per pallet (None: the network's pose)."""
    err_net, err_icp, fit_net, fit_icp, rms = rows.T
    if max_rms_m is None:
        return err_net
    keep = np.nan_to_num(rms, nan=np.inf) < max_rms_m
    keep &= fit_icp >= fit_net + margin
    return np.where(keep, err_icp, err_net)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="BOP datasets (validation sets)")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, help="write the markdown table here too")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    per_set = {d.name if d.name != "train" else d.parent.name: pallet_rows(args.bundle, d, "int8" if args.int8 else "fp32",
                                                                          args.threads) for d in args.data}
    lines = [f"ADD-sym accuracy at {' / '.join(f'{t * 100:g}' for t in THRESHOLDS_M)} cm of the detected pallets, "
             f"bundle {args.bundle} ({'int8' if args.int8 else 'fp32'}).", "",
             "| gate | " + " | ".join(f"{name} (n={len(r)})" for name, r in per_set.items()) + " |",
             "|---|" + "---|" * len(per_set)]
    for label, max_rms_m, margin in GATES:
        cells = [" / ".join(f"{100 * np.mean(gate_errors(r, max_rms_m, margin) < t):.1f}" for t in THRESHOLDS_M)
                 for r in per_set.values()]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for name, r in per_set.items():
        rms = r[:, 4][np.isfinite(r[:, 4])]
        if len(rms):
            lines.append(f"\n{name}: ICP RMS percentiles 10/50/90: "
                         + " / ".join(f"{v * 1000:.1f}" for v in np.percentile(rms, [10, 50, 90])) + " mm")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
