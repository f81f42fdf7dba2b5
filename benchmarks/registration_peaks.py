"""The registration test's statistic per frame on ground-truth boxes: each frame's own depth against another frame's.

For each frame of BOP datasets with a pallet at least 10 % visible, the frame-level registration score
(`runtime/registration.py`, default `StructureParams`) over the visible boxes of those pallets, with the frame's own
depth and with the depth of the frame half the set away. Reports per dataset the peak's minimum, 5 % quantile,
median and maximum, frames without evidence, how many frames each peak threshold would refuse (with AUC(0) below
`registered_edge_auc`), and the test's milliseconds per frame. No estimator: it measures the statistic, not poses.

    python benchmarks/registration_peaks.py --data DIR [DIR ...] [--frames 100] --out FILE.json
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.structure import StructureParams, frame_registration

THRESHOLDS = (0.03, 0.05, 0.08)


def visible_boxes(frame, min_visible: float = 0.1) -> np.ndarray:
    """(n, 4) xyxy visible boxes of the frame's pallets at least `min_visible` visible."""
    b = [[g.bbox_visib_xywh[0], g.bbox_visib_xywh[1], g.bbox_visib_xywh[0] + g.bbox_visib_xywh[2],
          g.bbox_visib_xywh[1] + g.bbox_visib_xywh[3]] for g in frame.gts
         if g.bbox_visib_xywh is not None and g.visib_fract >= min_visible]
    return np.array(b, float).reshape(-1, 4)


def summary(auc_peak: np.ndarray, params: StructureParams) -> dict:
    """Peak statistics of (frames, 2) AUC(0) and peak rows (NaN: no evidence)."""
    judged = np.isfinite(auc_peak[:, 1])
    pk = auc_peak[judged, 1]
    out = {"frames": len(auc_peak), "unjudged": int((~judged).sum())}
    if len(pk):
        out |= {"peak_min": float(pk.min()), "peak_p05": float(np.percentile(pk, 5)),
                "peak_median": float(np.median(pk)), "peak_max": float(pk.max())}
    for t in THRESHOLDS:
        out[f"refused_at_{t}"] = int((judged & (auc_peak[:, 1] < t) & (auc_peak[:, 0] < params.registered_edge_auc)).sum())
    return out


def run(data: list[str], frames: int, params: StructureParams) -> dict:
    out = {}
    for root in data:
        ds = BopDataset(root)
        n = min(frames, len(ds))
        own, other, ms = [], [], []
        for i in range(n):
            f = ds[i]
            boxes = visible_boxes(f)
            if not len(boxes):
                continue
            t = time.perf_counter()
            r, _ = frame_registration(f.depth_m, f.rgb, boxes, params)
            ms.append(1e3 * (time.perf_counter() - t))
            o, _ = frame_registration(ds[(i + n // 2) % n].depth_m, f.rgb, boxes, params)
            own.append((r.auc_0, r.peak))
            other.append((o.auc_0, o.peak))
        res = {"own_depth": summary(np.array(own).reshape(-1, 2), params),
               "other_frame_depth": summary(np.array(other).reshape(-1, 2), params),
               "ms_median": float(np.median(ms)) if ms else None, "ms_max": float(np.max(ms)) if ms else None}
        out[Path(root).name] = res
        print(f"{Path(root).name}: {json.dumps(res)}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    res = run(args.data, args.frames, StructureParams())
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
