"""`pallet6d record`: save a camera or recording to the replay format (or a RealSense .bag)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .cli_paths import writable_folder
from .cli_signals import StopSignals

HELP = "record a camera or recording to the replay format (or a RealSense .bag)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", required=True,
                        help="realsense[:SERIAL], oakd[:MXID], bag:FILE, replay:DIR or bop:DIR")
    parser.add_argument("--out", required=True, help="output folder (replay) or .bag file (--format bag)")
    parser.add_argument("--frames", type=int, default=None, help="stop after N frames (default: until the "
                        "recording ends or Ctrl-C)")
    parser.add_argument("--format", choices=("replay", "bag"), default="replay",
                        help="replay folder (PNG/JPEG + 16-bit depth PNG + camera.json) or RealSense .bag "
                             "(depth stored registered to colour)")
    parser.add_argument("--rgb-format", choices=("png", "jpg"), default="png", help="colour image files (replay)")
    parser.add_argument("--size", default=None, help="camera colour/depth size WxH, e.g. 848x480 (live cameras)")
    parser.add_argument("--fps", type=int, default=30, help="camera frame rate (live cameras)")
    parser.add_argument("--filters", default="", help="RealSense depth filters, comma separated: "
                        "decimation,spatial,temporal,hole_filling")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing recording in --out")


def _source_options(args: argparse.Namespace, kind: str) -> dict:
    opts: dict = {}
    size = None
    if args.size:
        try:
            w, h = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise ValueError(f"--size must look like 848x480, got {args.size!r}") from None
        if w <= 0 or h <= 0:
            raise ValueError(f"--size must be positive, got {args.size!r}")
        size = (w, h)
    if args.fps <= 0:
        raise ValueError(f"--fps must be positive, got {args.fps}")
    if kind == "realsense":
        opts.update(fps=args.fps, filters=tuple(f for f in args.filters.split(",") if f))
        if size:
            opts.update(color_size=size, depth_size=size)
    elif kind == "oakd":
        opts.update(fps=args.fps)
        if size:
            opts.update(size=size)
    elif kind == "bag":
        opts.update(filters=tuple(f for f in args.filters.split(",") if f))
    return opts


def main(args: argparse.Namespace) -> int:
    """Exit status: 0 recorded to the end, to --frames, or until SIGINT/SIGTERM; 1 the source or the disk
    failed (the frames written so far stay listed in the index); 2 a bad option or --out."""
    from pallet6d.runtime.cameras import CameraError, open_source, parse_source_spec

    if args.frames is not None and args.frames <= 0:
        print("pallet6d record: --frames must be positive", file=sys.stderr)
        return 2
    try:
        kind, _ = parse_source_spec(args.source)
        source = open_source(args.source, **_source_options(args, kind))
    except (ValueError, TypeError) as exc:
        print(f"pallet6d record: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.format == "bag" and out.is_dir():
        why = f"--out {out} is a folder; --format bag writes a .bag file"
    else:
        why = writable_folder(out if args.format == "replay" else out.parent)
    if why:
        print(f"pallet6d record: {why}", file=sys.stderr)
        return 2
    counter = {"n": 0}
    with StopSignals() as stop:
        try:
            with source:
                _record(args, source, stop, counter)
        except FileExistsError as exc:
            print(f"pallet6d record: {exc}", file=sys.stderr)
            return 2
        except (CameraError, OSError, ValueError) as exc:
            print(f"pallet6d record: {exc} (kept {counter['n']} frames in {args.out})", file=sys.stderr)
            return 1
        except KeyboardInterrupt:   # a second stop signal: the writer's `with` has closed the index already
            stop.requested = stop.requested or "SIGINT"
    how = f", stopped by {stop.requested}" if stop.requested else ""
    print(f"recorded {counter['n']} frames from {args.source} to {args.out}{how}")
    return 0


def _record(args: argparse.Namespace, source, stop: StopSignals, counter: dict) -> None:
    """Copy frames from a started source to the writer until the end, --frames or a stop signal; the writer
    rewrites its index atomically on the way out, so it lists every frame on disk."""
    from pallet6d.runtime.cameras import ReplayWriter

    if args.format == "bag":
        from pallet6d.runtime.cameras.rsbag import RealSenseBagWriter
        first = source.read()
        if first is None:
            raise ValueError("the source has no frames")
        writer = RealSenseBagWriter(args.out, (first.width, first.height), first.K,
                                    depth_scale_m=first.depth_scale_m, fps=args.fps)
        pending = [first]
    else:
        writer = ReplayWriter(args.out, rgb_format=args.rgb_format, overwrite=args.overwrite)
        pending = []
    with writer:
        while not stop.requested and (args.frames is None or counter["n"] < args.frames):
            frame = pending.pop() if pending else source.read()
            if frame is None:
                break
            if args.format == "bag":
                writer.write(frame.rgb, frame.depth, frame.timestamp_s, frame.frame_number)
            else:
                writer.write(frame)
            counter["n"] += 1
            if counter["n"] % 100 == 0:
                log.info("recorded %d frames", counter["n"])
