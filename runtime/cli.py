"""The `pallet6d` command.

Each subcommand lives in its own module, imported only when that subcommand runs, so that
`pallet6d run` on the forklift never pays for (or needs) torch, and a missing extra gives a
clear message instead of an ImportError trace. A subcommand module provides

    HELP: str
    def add_arguments(parser: argparse.ArgumentParser) -> None
    def main(args: argparse.Namespace) -> int
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Sequence

# Exit statuses every subcommand shares: 0 done, 1 the work failed (source, disk, data), 2 a bad option or
# input named on the command line; these two for failures no subcommand handles itself.
EXIT_INTERNAL = 3          # an unexpected error (a bug): one line, the traceback with -v
EXIT_INTERRUPTED = 130     # Ctrl-C outside a command's own clean stop (128 + SIGINT)

# name -> (module, extra that provides its dependencies or None, one-line summary for `pallet6d --help`)
SUBCOMMANDS: dict[str, tuple[str, str | None, str]] = {
    "sim": ("pallet6d.sim.cli", None, "generate synthetic warehouse RGB-D scenes (BOP format)"),
    "export": ("pallet6d.export.cli", "export", "export the networks to an ONNX model bundle"),
    "bundle": ("pallet6d.runtime.bundle_cli", None, "validate a model bundle"),
    "run": ("pallet6d.runtime.run_cli", None, "estimate pallet poses on a camera or recording"),
    "record": ("pallet6d.runtime.record_cli", None, "record a camera to the replay format"),
    "train": ("pallet6d.export.train_cli", "export", "train the detector or the pose network"),
    "eval": ("pallet6d.runtime.eval_cli", None, "accuracy of a bundle on a BOP dataset"),
    "calib": ("pallet6d.calib.cli", None, "calibrate a forklift camera (intrinsics, board, floor)"),
    "serve": ("pallet6d.runtime.serve.cli", "serve", "the forklift daemon: camera loop and HTTP API"),
}


def _load(name: str):
    module_name, extra, _ = SUBCOMMANDS[name]
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and module_name.startswith(exc.name):
            return None  # subcommand not part of this version
        hint = f" (install it with: pip install 'pallet6d[{extra}]')" if extra else ""
        raise SystemExit(f"pallet6d {name}: missing dependency '{exc.name}'{hint}") from None


def _not_available(name: str) -> int:
    print(f"pallet6d {name}: not available in this version of pallet6d", file=sys.stderr)
    return 2


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pallet6d", description="6D pose estimation of pallets from RGB-D.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # Only the chosen subcommand's module is imported; the others are listed by name.
    chosen = next((a for a in argv if a in SUBCOMMANDS), None)
    for name, (_, _, summary) in SUBCOMMANDS.items():
        if name == chosen:
            module = _load(name)
            if module is None:
                p = sub.add_parser(name, help=summary)
                p.set_defaults(_main=lambda _args, n=name: _not_available(n))
                continue
            p = sub.add_parser(name, help=module.HELP, description=module.HELP)
            module.add_arguments(p)
            p.set_defaults(_main=module.main)
        else:
            sub.add_parser(name, add_help=False, help=summary)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "_main", None) is None:
        parser.print_help()
        return 0 if args.command is None else 2
    try:
        return int(args._main(args) or 0)
    except KeyboardInterrupt:
        print(f"pallet6d {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - the user gets one line; -v gives the traceback
        logging.getLogger("pallet6d").debug("unexpected error", exc_info=True)
        print(f"pallet6d {args.command}: unexpected error: {type(exc).__name__}: {exc}"
              + ("" if args.verbose else " (run with -v for the traceback)"), file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
