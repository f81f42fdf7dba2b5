"""Structure check on posed pallets: true poses kept, poses on mismatched inputs refused.

For each frame of BOP datasets, runs the estimator on the frame as recorded and on inputs that do not belong
together (a flat wall's depth under the image, another frame's depth, depth 10x too near, a focal length 2x too
long, a transposed K, fx = fy = 1e9; frames the estimator refuses count as `refused_frames`), and scores every
pose the estimator accepts with its fit check alone (`structure=None`) with `runtime/structure.py` the way the
fit-check stage does: per frame the registration test over all its poses' boxes (`runtime/registration.py`), the
structure check of each pose, then the frame's size veto and size majority. Reports, per dataset and variant: those
poses, how many are within 5 cm (ADD-sym) of a ground-truth pallet, how many of each the structure
check keeps, and the registration test's milliseconds per frame. The estimator's poses are cached per dataset and
variant (`--cache DIR`), so re-scoring with other thresholds takes seconds. Measures only.

    python benchmarks/structure_check.py --bundle models/epal-default --data DIR [DIR ...] --frames 30 \
        --cache /tmp/structure-cache --out FILE.json
"""
from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import PalletEstimator
from pallet6d.runtime.evaluation import dataset_models
from pallet6d.runtime.metrics import add_sym
from pallet6d.runtime.structure import StructureParams, frame_registration, frame_size_rule, structure_check
from pallet6d.sim.mismatch import MISMATCHES, mismatched

VARIANTS = ("as_recorded", "flat_wall", "other_frame", "depth_x0.1", "focal_x2", "K_transposed", "focal_1e9")


def mismatch(name: str, frame, other=None) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m, K) of an input built from `frame` that does (as_recorded) or does not belong to its image.

    :param other: another frame of the same size, for "other_frame".
    """
    d, K = frame.depth_m, frame.K.copy()
    if name == "as_recorded":
        return d, K
    if name in MISMATCHES:
        return mismatched(name, d, K, None if other is None else other.depth_m)
    if name == "K_transposed":
        return d, K.T.copy()
    if name == "focal_1e9":
        K[0, 0] = K[1, 1] = 1e9
        return d, K
    raise ValueError(f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")


def _other(ds: BopDataset, i: int, n: int):
    return ds[(i + n // 2) % n]


def estimate(est: PalletEstimator, ds: BopDataset, variant: str, n: int) -> dict[str, np.ndarray]:
    """The poses the estimator accepts, with each one's ADD-sym error to the nearest pallet of the image (each
    ground truth's own model; inf without one), and how many frames it refused with a ValueError (`refused`).

    On a mismatched input a pose can still be right: another frame's depth of a scene that stands where the image's
    does shows the image's pallet where it is, and a pose found there is not made up."""
    rows = {"frame": [], "T": [], "box": [], "err": [], "fit": []}
    pts, sym = est.model_points_m, est.symmetries
    models = dataset_models(ds, est.pallet_types)
    refused = 0
    for i in range(n):
        f = ds[i]
        depth_m, K = mismatch(variant, f, _other(ds, i, n) if variant == "other_frame" else None)
        try:
            poses = est.estimate(f.rgb, depth_m, K).poses
        except ValueError:
            refused += 1
            continue
        for p in poses:
            T = p.T_cam_pallet
            err = min((add_sym(T[:3, :3], T[:3, 3], g.T_cam_model[:3, :3], g.T_cam_model[:3, 3],
                               *models.get(g.obj_id, (pts, sym))) for g in f.gts), default=np.inf)
            for k, v in (("frame", i), ("T", T), ("box", p.box_xyxy), ("err", err), ("fit", p.fit.score)):
                rows[k].append(v)
    return {"frame": np.array(rows["frame"], int), "T": np.array(rows["T"]).reshape(-1, 4, 4),
            "box": np.array(rows["box"]).reshape(-1, 4), "err": np.array(rows["err"]), "fit": np.array(rows["fit"]),
            "refused": np.array(refused)}


def score(ds: BopDataset, variant: str, n: int, poses: dict, boxes_m: np.ndarray, params: StructureParams,
          no_rgb: bool = False) -> tuple[list, list, list]:
    """Structure scores of cached poses, in their order, as the fit-check stage decides them (`no_rgb`: without the
    colour image's tests): a frame the registration test refuses makes each of its poses "depth_image_mismatch"
    (first, as in the stage), the size veto and the size majority make the frame's others "size_mismatch".

    :return: the scores, each pose's frame `RegistrationScore` (None without it), and the registration test's
        milliseconds per frame.
    """
    out, regs, ms = [], [], []
    for i in np.unique(poses["frame"]):
        sel = poses["frame"] == i
        f = ds[int(i)]
        depth_m, K = mismatch(variant, f, _other(ds, int(i), n) if variant == "other_frame" else None)
        scores = structure_check(poses["T"][sel], boxes_m, depth_m, K, poses["box"][sel], params,
                                 rgb=None if no_rgb else f.rgb)
        reg, refused = None, False
        if not no_rgb and params.min_registration_peak > 0:
            t = time.perf_counter()
            reg, refused = frame_registration(depth_m, f.rgb, poses["box"][sel], params)
            ms.append(1e3 * (time.perf_counter() - t))
        if refused:
            scores = [replace(s, reason="depth_image_mismatch") for s in scores]
        if frame_size_rule(scores, params):
            scores = [s if s.reason else replace(s, reason="size_mismatch") for s in scores]
        out.extend(scores)
        regs.extend([reg] * len(scores))
    return out, regs, ms


def run(bundle: str, data: list[str], frames: int, params: StructureParams, int8: bool, cache: Path | None,
        no_rgb: bool = False, options: dict | None = None) -> dict:
    """:param options: `EstimatorOptions` overrides for the estimator that makes the poses (its own structure check
        stays off: `params` scores them)."""
    est = None
    out, rows = {}, []
    for root in data:
        ds = BopDataset(root)
        n = min(frames, len(ds))
        for variant in VARIANTS:
            path = None if cache is None else cache / f"{Path(root).name}-{variant}-{n}{'-int8' if int8 else ''}.npz"
            if path is not None and path.exists():
                poses = dict(np.load(path))
            else:
                est = est or PalletEstimator.from_bundle(bundle, threads=2, precision="int8" if int8 else "fp32",
                                                         **{**(options or {}), "structure": None})
                poses = estimate(est, ds, variant, n)
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    np.savez(path, **poses)
            boxes_m = np.asarray((est.model_boxes_m if est else _boxes(bundle)))
            scores, regs, ms = score(ds, variant, n, poses, boxes_m, params, no_rgb)
            good = poses["err"] < 0.05
            kept = np.array([s.ok for s in scores], bool)
            c = {"frames": n, "refused_frames": int(poses.get("refused", 0)), "accepted": len(good),
                 "within_5cm": int(good.sum()), "kept": int(kept.sum()),
                 "kept_within_5cm": int((kept & good).sum()),
                 "reasons": dict(Counter(s.reason or "ok" for s in scores)),
                 "registration_ms": {"frames": len(ms), "median": float(np.median(ms)) if ms else None,
                                     "max": float(np.max(ms)) if ms else None}}
            out[f"{Path(root).name}/{variant}"] = c
            print(f"{Path(root).name:>24} {variant:>12}: {c}", flush=True)
            rows.extend({"data": Path(root).name, "variant": variant, "frame": int(fr), "add_sym_m": float(e),
                         "fit": float(ft), **asdict(s),
                         "registration_auc_0": None if r is None else r.auc_0,
                         "registration_peak": None if r is None else r.peak}
                        for fr, e, ft, s, r in zip(poses["frame"], poses["err"], poses["fit"], scores, regs))
    out["poses"] = rows
    return out


def _boxes(bundle: str) -> np.ndarray:
    from pallet6d.runtime.bundle import load_bundle
    return np.asarray(load_bundle(bundle).pallet.boxes_m)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default="models/epal-default")
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--cache", type=Path, help="folder for the estimator's poses per dataset and variant")
    ap.add_argument("--params", default="{}", help="StructureParams overrides as JSON, e.g. '{\"min_agreement\": 0.7}'")
    ap.add_argument("--no-rgb", action="store_true", help="score without the colour image (no edge test)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    overrides = json.loads(args.params)
    unknown = set(overrides) - {f.name for f in fields(StructureParams)}
    if unknown:
        ap.error(f"unknown StructureParams fields: {sorted(unknown)}")
    res = run(args.bundle, args.data, args.frames, StructureParams(**overrides), args.int8, args.cache, args.no_rgb)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
