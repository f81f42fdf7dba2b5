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

import pallet6d.runtime.estimator as estimator_module
from pallet6d.runtime import metrics
from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.evaluation import box_iou, ground_truths_from_bop

THRESHOLDS_M = (0.02, 0.05, 0.1)
GATES = [("network alone", None, None), ("ICP always", 1.0, -1.0)] + \
    [(f"RMS < {r * 1000:g} mm, margin {m:g}", r, m) for r in (0.003, 0.004, 0.005) for m in (0.0, 0.02)] + \
    [(f"fit score only, margin {m:g}", 1.0, m) for m in (0.0, 0.02)]


class _RmsLog:
    """Wraps the estimator's `refine_pose` to keep each call's final RMS (the estimator does not return it)."""

    def __init__(self) -> None:
        self.rms_m: list[float] = []
        self._inner = estimator_module.refine_pose

    def __call__(self, *args, **kwargs):
        res = self._inner(*args, **kwargs)
        self.rms_m.append(res.rms_m)
        return res


def pallet_rows(bundle: str, data: Path, precision: str, threads: int) -> np.ndarray:
    """(n, 5): ADD-sym of the network's pose, of ICP's pose (m), their fit scores, ICP's RMS (m; nan: no result)."""
    plain = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, refine=False, min_fit=0.0)
    icp = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, min_fit=0.0,
                                      refine_max_rms_m=1e9, refine_margin=-1.0,
                                      refine_starts=0)  # always ICP's pose
    pts, sym = plain.model_points_m, plain.symmetries
    rms_log = _RmsLog()
    estimator_module.refine_pose = rms_log
    rows = []
    try:
        ds = BopDataset(data)
        for i in range(len(ds)):
            f = ds[i]
            gts, _ = ground_truths_from_bop(f.gts)
            net = plain.predict(f.rgb, f.depth_m, f.K)
            rms_log.rms_m.clear()
            ref = icp.predict(f.rgb, f.depth_m, f.K)
            if not gts or not net:
                continue
            assert len(net) == len(ref) == len(rms_log.rms_m), "both estimators must see the same detections"
            iou = box_iou(np.array([p.box_xyxy for p in net]), np.array([g.box_visib_xyxy for g in gts]))
            for k, (a, b) in enumerate(zip(net, ref)):
                j = int(iou[k].argmax())
                if iou[k, j] < 0.5 or gts[j].visib_fract < 0.1:
                    continue
                R_gt, t_gt = gts[j].T_cam_model[:3, :3], gts[j].T_cam_model[:3, 3]
                err = [metrics.add_sym(p.T_cam_pallet[:3, :3], p.T_cam_pallet[:3, 3], R_gt, t_gt, pts, sym) for p in (a, b)]
                rows.append([*err, a.fit.score, b.fit.score, rms_log.rms_m[k]])
    finally:
        estimator_module.refine_pose = rms_log._inner
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
