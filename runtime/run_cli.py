"""`pallet6d run`: estimate pallet poses on a camera or a recording, one JSON line per frame.

On a BOP dataset (`--source bop:DIR`, e.g. from `pallet6d sim`) the ground truth is read too: each
line then carries ADD and symmetry-aware ADD per ground-truth pallet (metres), and a summary line
(`"summary": {...}`, the `pallet6d.runtime.evaluation` protocol) ends the run.

A frame whose estimation fails gets an error line (`{"frame": N, "error": "..."}`) and the run goes on: one bad
frame must not stop a forklift's perception. Only `--max-failures` failures in a row (a fault that persists) end
the run, with exit status 1, as a camera that fails does: the supervisor then restarts it.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Iterator

import numpy as np

from .estimator_cli import add_estimator_arguments, load_estimator
from .forklift_cli import ForkliftOutput, add_forklift_arguments

HELP = "estimate pallet poses on a camera or recording (one JSON line per frame)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", required=True,
                        help="replay:DIR, bop:DIR, bag:FILE, realsense[:SERIAL] or oakd[:MXID]")
    add_estimator_arguments(parser)
    parser.add_argument("--out", type=Path, help="write overlay PNGs (3D boxes and axes) here")
    parser.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0: all)")
    parser.add_argument("--format", choices=("json", "text"), default="json",
                        help="json: one JSON line per frame (default); text: a readable report")
    parser.add_argument("--max-failures", type=int, default=10,
                        help="give up (exit 1) after this many frames in a row whose estimation failed (default 10)")
    add_forklift_arguments(parser)


def _bop_frames(root: str) -> Iterator[tuple[object, list | None]]:
    """(RGBDFrame, ground truth list) for each image of a BOP dataset, in order."""
    from .bop import BopDataset
    from .cameras import RGBDFrame
    from .evaluation import ground_truths_from_bop

    ds = BopDataset(root)
    for i in range(len(ds)):
        f = ds[i]
        frame = RGBDFrame.from_depth_m(f.rgb, f.depth_m, f.K, timestamp_s=float(i), frame_number=i,
                                       source=f"bop:{root}", depth_scale_m=float(f.depth_scale_mm) * 1e-3)
        gts, _ = ground_truths_from_bop(f.gts, f.rgb.shape[:2])
        yield frame, gts


def _source_frames(spec: str) -> Iterator[tuple[object, list | None]]:
    """Frames of a camera or recording. A live camera is read through `LatestFrame`: the estimator is
    slower than the camera, so it always gets the newest frame and stale ones are dropped, never queued.
    Recordings are played frame by frame, so none is skipped."""
    from .cameras import LatestFrame, open_source

    source = open_source(spec)
    if not source.live:
        with source:
            for frame in source:
                yield frame, None
        return
    with LatestFrame(source) as grab:
        while (frame := grab.get(timeout_s=5.0)) is not None:
            yield frame, None
        log.info("%s: %d frames received, %d dropped while the estimator was busy", spec, grab.received,
                 grab.dropped)


def main(args: argparse.Namespace) -> int:
    from .calibration import CalibrationError
    from .cameras import CameraError

    if args.max_failures < 1:   # before loading the bundle: a wrong option fails at once
        print(f"pallet6d run: --max-failures must be >= 1, got {args.max_failures}", file=sys.stderr)
        return 2
    try:
        forklift = ForkliftOutput.from_args(args)
    except ValueError as exc:
        print(f"pallet6d run: {exc}", file=sys.stderr)
        return 2
    est = load_estimator(args, "run")
    if est is None:
        return 2
    frames = _bop_frames(args.source[4:]) if args.source.lower().startswith("bop:") else _source_frames(args.source)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    records, tp, fp, n, failures = [], 0, 0, 0, 0
    try:
        for frame, gts in frames:
            if args.max_frames and n >= args.max_frames:
                break
            try:
                result = forklift.estimate(est, frame)
            except CalibrationError as exc:   # a moved camera or a wrong calibration: no vehicle-frame output
                n += 1
                print(json.dumps({"frame": int(frame.frame_number), "timestamp_s": frame.timestamp_s,
                                  "error": f"CalibrationError: {exc}"}) if args.format == "json"
                      else f"frame {frame.frame_number}: error: {exc}", flush=True)
                continue
            except Exception as exc:  # noqa: BLE001 - any one frame's failure is reported, never fatal alone
                failures += 1
                n += 1
                log.warning("frame %d: estimation failed (%d in a row)", frame.frame_number, failures, exc_info=True)
                err = {"frame": int(frame.frame_number), "timestamp_s": frame.timestamp_s,
                       "error": f"{type(exc).__name__}: {exc}"}
                if gts is not None:  # its pallets count as missed
                    err["gt"], _, _ = _evaluate(est, frame.frame_number, None, gts, records)
                print(json.dumps(err) if args.format == "json" else f"frame {err['frame']}: error: {err['error']}",
                      flush=True)
                if failures >= args.max_failures:
                    print(f"pallet6d run: {args.source}: {failures} frames in a row failed, giving up; last: "
                          f"{err['error']}", file=sys.stderr)
                    return 1
                continue
            failures = 0
            line = {"frame": int(frame.frame_number), "timestamp_s": frame.timestamp_s, **result.to_dict()}
            if gts is not None:
                line["gt"], f_tp, f_fp = _evaluate(est, frame.frame_number, result, gts, records)
                tp, fp = tp + f_tp, fp + f_fp
            print(json.dumps(line) if args.format == "json" else _text(line), flush=True)
            if args.out:
                _write_overlay(args.out / f"{n:06d}.png", frame, result, est, gts)
            n += 1
    except (CameraError, ValueError, OSError) as exc:
        print(f"pallet6d run: {args.source}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    if records or tp or fp:
        from .eval_cli import format_table
        from .evaluation import summarize
        summary = {"frames": n, **summarize(records, tp, fp)}
        print(json.dumps({"summary": summary}) if args.format == "json" else "\n" + format_table(summary), flush=True)
    log.info("%d frames", n)
    return 0


def _text(line: dict) -> str:
    """A frame's JSON line as a few readable lines: the poses, then each ground-truth pallet's error."""
    out = [f"frame {line['frame']}: {len(line['poses'])} pallet(s), {len(line['rejected'])} rejected, "
           f"{line['timings_ms']['total']:.0f} ms"]
    for p in line["poses"]:
        t, q = p["t_m"], p["quat_wxyz"]
        out.append(f"  {p['class']}  t_cam = ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:.3f}) m  q_wxyz = "
                   f"({q[0]:+.3f}, {q[1]:+.3f}, {q[2]:+.3f}, {q[3]:+.3f})  confidence {p['confidence']:.2f}  "
                   f"fit {p['fit']['score']:.2f}")
        if "forklift" in p:
            fk = p["forklift"]
            c = fk["face_centre_m"]
            out.append(f"    vehicle: face {fk['face']} at ({c[0]:.3f}, {c[1]:+.3f}, {c[2]:.3f}) m, yaw "
                       f"{fk['face_yaw_deg']:+.1f} deg, pockets {'/'.join(q['state'] for q in fk['pockets'])}, "
                       + ("pick safe" if fk["pick_safe"] else f"NOT safe: {fk['detail']}"))
    for g in line.get("gt", []):
        where = f"  ground truth at {g['distance_m']:.1f} m ({100 * g['visib_fract']:.0f}% visible): "
        if not g["detected"] or g["add_sym_m"] is None:
            out.append(where + "missed")
        else:
            out.append(where + f"ADD {100 * g['add_m']:.1f} cm, ADD-sym {100 * g['add_sym_m']:.1f} cm")
    return "\n".join(out)


def _evaluate(est, frame_number: int, result, gts: list, records: list) -> tuple[list[dict], int, int]:
    """Per-pallet ADD / ADD-sym of one frame (evaluation protocol); appends to `records`."""
    from .evaluation import Estimate, evaluate_frame

    poses = result.poses if result is not None else []   # None: the frame's estimation failed
    estimates = [Estimate(p.T_cam_pallet, p.box_xyxy, p.detector_score) for p in poses]
    recs, tp, fp = evaluate_frame(frame_number, estimates, gts, est.model_points_m, est.symmetries)
    records.extend(recs)

    def m(v: float):
        return None if not np.isfinite(v) else round(float(v), 4)

    return [{"detected": r.detected, "distance_m": round(r.distance_m, 3), "visib_fract": round(r.visib_fract, 3),
             "add_m": m(r.add_m), "add_sym_m": m(r.add_sym_m)} for r in recs], tp, fp


def _write_overlay(path: Path, frame, result, est, gts) -> None:
    import cv2

    from .draw import draw_result

    img = draw_result(frame.rgb, result, frame.K, est.model_size_m,
                      [g.T_cam_model for g in gts] if gts else None)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
