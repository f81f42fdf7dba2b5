"""`pallet6d run`: estimate pallet poses on a camera or a recording, one JSON line per frame.

Every input frame gets exactly one line, in order: its result, or `{"frame": N, "error": "..."}` when the frame
cannot be read (missing, truncated or corrupt file, bad camera.json entry) or its estimation fails. One bad
frame must not stop a forklift's perception: the run goes on. `--max-failures` failed frames in a row (a fault
that persists) end the run with exit status 1, as a camera that fails does: the supervisor then restarts it.
A summary line (`{"summary": {...}}`) ends every run, also one stopped by SIGINT or SIGTERM.

On a BOP dataset (`--source bop:DIR`, e.g. from `pallet6d sim`) the ground truth is read too: each line then
carries ADD and symmetry-aware ADD per ground-truth pallet (metres), and the summary the
`pallet6d.runtime.evaluation` protocol's scores.

Only these lines go to stdout: whatever a native library prints there (depthai's USB warning) is sent to
stderr with the logging. Exit status: 0 the source ended, `--max-frames` was reached or a stop signal came,
and at least one frame was estimated (or a signal stopped the run); 1 the source failed, `--max-failures`
was reached, or no frame at all could be estimated; 2 a bad option, `--out` or bundle.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from .calibration import CalibrationError
from .cli_paths import writable_folder
from .cli_signals import StopSignals
from .estimator_cli import add_estimator_arguments, load_estimator
from .forklift_cli import ForkliftOutput, add_forklift_arguments

HELP = "estimate pallet poses on a camera or recording (one JSON line per frame)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", required=True,
                        help="replay:DIR, bop:DIR, bag:FILE, realsense[:SERIAL] or oakd[:MXID]")
    add_estimator_arguments(parser)
    parser.add_argument("--out", type=Path, help="write overlay PNGs (3D boxes and axes) here, named by frame number")
    parser.add_argument("--max-frames", type=int, default=0, help="stop after N input frames (0: all)")
    parser.add_argument("--format", choices=("json", "text"), default="json",
                        help="json: one JSON line per frame (default); text: a readable report")
    parser.add_argument("--max-failures", type=int, default=10,
                        help="give up (exit 1) after this many frames in a row that could not be read or estimated "
                             "(default 10)")
    add_forklift_arguments(parser)


def _frames(source, stop: StopSignals) -> Iterator[tuple[int, object | None, str | None]]:
    """(frame number, RGBDFrame or None, error or None) for each input frame of a started source, until it
    ends or a stop is requested. A live camera is read through `LatestFrame`: the estimator is slower than
    the camera, so it always gets the newest frame and stale ones are dropped, never queued. Recordings are
    played frame by frame, so none is skipped, and an unreadable one comes out as its number and the reason."""
    from .cameras import FrameReadError, LatestFrame

    if source.live:
        with LatestFrame(source) as grab:
            while not stop.requested and (frame := grab.get(timeout_s=5.0)) is not None:
                yield frame.frame_number, frame, None
            log.info("%s: %d frames received, %d dropped while the estimator was busy", source.name, grab.received,
                     grab.dropped)
        return
    while not stop.requested:
        try:
            frame = source.read()
        except FrameReadError as exc:
            if exc.frame_number is None:   # not one frame's fault: the recording as a whole
                raise
            yield exc.frame_number, None, str(exc)
            continue
        if frame is None:
            return
        yield frame.frame_number, frame, None


def _open(spec: str):
    """The (not yet started) source; recordings report unreadable frames instead of skipping them."""
    from .cameras import open_source, parse_source_spec

    kind, _ = parse_source_spec(spec)
    return open_source(spec, on_error="raise") if kind in ("replay", "bop") else open_source(spec)


@contextlib.contextmanager
def _result_stream() -> Iterator[IO[str]]:
    """The stream the result lines go to: the process's stdout, which is meanwhile pointed at stderr, so that
    what native libraries write to file descriptor 1 cannot interleave with the JSON lines. When stdout is not
    a real file descriptor (captured in-process), it is simply sys.stdout."""
    try:
        is_fd1 = sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        is_fd1 = False
    if not is_fd1:
        yield sys.stdout
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    out = os.fdopen(os.dup(saved), "w", buffering=1)
    try:
        yield out
    finally:
        with contextlib.suppress(BrokenPipeError):
            out.close()
        sys.stdout.flush()   # what Python code printed meanwhile goes to stderr too, before stdout is back
        os.dup2(saved, 1)
        os.close(saved)


class _Tally:
    """What a run has done so far: input frames, estimated ones, errors (and the current run of them)."""

    def __init__(self) -> None:
        from .evaluation import ScoreTally

        self.frames = self.estimated = self.errors = self.in_a_row = self.poses = self.overlay_errors = 0
        self.scores = ScoreTally()
        self.models = None   # a BOP source's models, each ground truth scored with its own

    def summary(self, stopped_by: str | None) -> dict:
        out = {"frames": self.frames, "estimated": self.estimated, "errors": self.errors, "poses": self.poses}
        if self.overlay_errors:
            out["overlay_errors"] = self.overlay_errors
        if stopped_by:
            out["stopped_by"] = stopped_by
        if self.scores:
            out.update(self.scores.summary())
        return out


def main(args: argparse.Namespace) -> int:
    from .cameras import CameraError

    if args.max_failures < 1 or args.max_frames < 0:   # before loading the bundle: a wrong option fails at once
        print(f"pallet6d run: --max-failures must be >= 1 and --max-frames >= 0, got {args.max_failures} and "
              f"{args.max_frames}", file=sys.stderr)
        return 2
    try:
        forklift = ForkliftOutput.from_args(args)
        source = _open(args.source)
    except (ValueError, TypeError) as exc:
        print(f"pallet6d run: {exc}", file=sys.stderr)
        return 2
    if args.out and (why := writable_folder(args.out)):
        print(f"pallet6d run: {why}", file=sys.stderr)
        return 2
    est = load_estimator(args, "run")
    if est is None:
        return 2
    tally = _Tally()
    with StopSignals() as stop, _result_stream() as out:
        try:
            with source:
                status = _run(args, est, forklift, source, stop, tally, out)
        except BrokenPipeError:   # the reader of the results went away (`| head`): nobody to tell
            log.info("stdout closed after %d frames", tally.frames)
            return 1
        except (CameraError, ValueError, OSError) as exc:
            print(f"pallet6d run: {args.source}: {exc}", file=sys.stderr)
            status = 1
        except KeyboardInterrupt:   # a second stop signal while blocked
            stop.requested = stop.requested or "SIGINT"
            status = None
        if status is None and not stop.requested and tally.estimated == 0:
            print(f"pallet6d run: {args.source}: no frame could be estimated ({tally.frames} input frames, "
                  f"{tally.errors} errors)", file=sys.stderr)
            status = 1
        summary = tally.summary(stop.requested)
        if args.format == "json":
            print(json.dumps({"summary": summary}), file=out, flush=True)
        else:
            print("\n" + _text_summary(summary), file=out, flush=True)
    log.info("%d frames, %d estimated, %d errors%s", tally.frames, tally.estimated, tally.errors,
             f", stopped by {stop.requested}" if stop.requested else "")
    return 0 if status is None else status


def _run(args: argparse.Namespace, est, forklift: ForkliftOutput, source, stop: StopSignals, tally: _Tally,
         out: IO[str]) -> int | None:
    """Estimate every frame of a started source, one line each; an exit status when the run must end
    with one, None when the frames ran out or a stop was asked for."""
    with contextlib.closing(_frames(source, stop)) as frames:   # a live camera's grabber stops on a break
        for number, frame, error in frames:
            if args.max_frames and tally.frames >= args.max_frames:
                break
            tally.frames += 1
            gts = _ground_truth(source, frame) if error is None else None
            if gts is not None and tally.models is None:
                from .evaluation import dataset_models
                tally.models = dataset_models(source.dataset, est.pallet_types)
            result, calibration_error = None, False
            if error is None:
                try:
                    result = forklift.estimate(est, frame)
                except CalibrationError as exc:   # a moved camera or a wrong calibration: no vehicle-frame output
                    error, calibration_error = f"CalibrationError: {exc}", True
                except Exception as exc:  # noqa: BLE001 - any one frame's failure is reported, never fatal alone
                    log.debug("frame %d: estimation failed", number, exc_info=True)
                    error = f"{type(exc).__name__}: {exc}"
            if error is not None:
                tally.errors += 1
                # a moved camera is reported on every frame until the floor agrees again; it does not end the run
                tally.in_a_row += 0 if calibration_error else 1
                line = {"frame": int(number), "timestamp_s": None if frame is None else frame.timestamp_s,
                        "error": error}
                if gts is not None:  # its pallets count as missed
                    line["gt"] = _evaluate(est, number, None, gts, tally)
                print(json.dumps(line) if args.format == "json" else f"frame {number}: error: {error}", file=out,
                      flush=True)
                if tally.in_a_row >= args.max_failures:
                    print(f"pallet6d run: {args.source}: {tally.in_a_row} frames in a row failed, giving up; last: "
                          f"{error}", file=sys.stderr)
                    return 1
                continue
            tally.in_a_row = 0
            tally.estimated += 1
            tally.poses += len(result.poses)
            line = {"frame": int(number), "timestamp_s": frame.timestamp_s, **result.to_dict()}
            if gts is not None:
                line["gt"] = _evaluate(est, number, result, gts, tally)
            if args.out:
                why = _write_overlay(args.out / f"{int(number):06d}.png", frame, result, est, gts)
                if why:
                    tally.overlay_errors += 1
                    line["overlay_error"] = why
                    log.warning("frame %d: %s", number, why)
            print(json.dumps(line) if args.format == "json" else _text(line), file=out, flush=True)
        return None


def _ground_truth(source, frame) -> list | None:
    """The evaluation protocol's ground truth of the frame a BOP source just read, None for other sources."""
    gts = getattr(source, "last_gts", None)
    if gts is None or frame is None:
        return None
    from .evaluation import ground_truths_from_bop
    return ground_truths_from_bop(gts, frame.rgb.shape[:2])[0]


def _text_summary(summary: dict) -> str:
    head = (f"{summary['frames']} frames: {summary['estimated']} estimated, {summary['errors']} errors, "
            f"{summary['poses']} poses" + (f"; stopped by {summary['stopped_by']}" if "stopped_by" in summary else ""))
    if "n_gt" not in summary:
        return head
    from .eval_cli import format_table
    return head + "\n" + format_table(summary)


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


def _evaluate(est, frame_number: int, result, gts: list, tally: _Tally) -> list[dict]:
    """The frame's line entry per counted ground-truth pallet (ADD / ADD-sym, evaluation protocol); the frame's
    score joins the run's."""
    from .evaluation import evaluate_poses

    poses = result.poses if result is not None else []   # None: the frame's estimation failed
    score = tally.scores.add(evaluate_poses(frame_number, poses, gts, est.model_points_m, est.symmetries,
                                            models=tally.models, rejected=() if result is None else result.rejected))

    def m(v: float):
        return None if not np.isfinite(v) else round(float(v), 4)

    return [{"detected": r.detected, "distance_m": round(r.distance_m, 3), "visib_fract": round(r.visib_fract, 3),
             "add_m": m(r.add_m), "add_sym_m": m(r.add_sym_m)} for r in score.records]


def _write_overlay(path: Path, frame, result, est, gts) -> str | None:
    """Draw and write one overlay PNG; the reason it could not be written, or None."""
    import cv2

    from .draw import draw_result

    img = draw_result(frame.rgb, result, frame.K, est.model_size_m,
                      [g.T_cam_model for g in gts] if gts else None)
    try:
        if cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            return None
    except cv2.error as exc:
        return f"cannot write overlay {path}: {exc}"
    return f"cannot write overlay {path} (disk full or folder gone?)"
