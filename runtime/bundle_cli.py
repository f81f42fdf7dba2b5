"""`pallet6d bundle check DIR`: validate a model bundle (files, sha256, graph inputs/outputs) without torch."""
from __future__ import annotations

import argparse
import json
import sys

HELP = "validate a model bundle: manifest fields, files, sha256, graph input/output names and shapes"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bundle_command", metavar="ACTION", required=True)
    check = sub.add_parser("check", help="check a bundle folder; exit 0 when usable, 1 otherwise")
    check.add_argument("path", nargs="?", help="bundle folder (holds manifest.json; default: the default bundle, "
                                               "as `pallet6d run` finds it)")
    check.add_argument("--no-run", action="store_true", help="do not run the graphs once on zero inputs")
    info = sub.add_parser("info", help="print a bundle's manifest summary")
    info.add_argument("path", nargs="?", help="bundle folder (default: the default bundle)")


def main(args: argparse.Namespace) -> int:
    from .bundle import BundleError, check_bundle, load_bundle
    from .default_bundle import default_bundle

    if args.path is None:
        try:
            args.path = str(default_bundle())
        except BundleError as exc:
            print(f"pallet6d bundle: {exc}", file=sys.stderr)
            return 1
    if args.bundle_command == "info":
        try:
            b = load_bundle(args.path)
        except BundleError as exc:
            print(f"pallet6d bundle: {exc}", file=sys.stderr)
            return 1
        print(json.dumps({"name": b.name, "config": b.config, "classes": list(b.classes),
                          "precision": list(b.precision), "detector_input_hw": list(b.detector.input_hw),
                          "detector_input_sizes": [list(hw) for hw in b.detector.input_sizes],
                          "crop_hw": list(b.fusion.crop_hw), "num_points": b.pose.num_points,
                          "format_version": b.manifest.format_version,
                          "pallet_types": [{"name": t.name, "class_id": t.class_id, "size_m": list(t.size_m),
                                            "pocket_faces": list(t.pockets_m), "refine_starts": len(t.refine_starts)}
                                           for t in b.pallet_types],
                          "checks": b.checks.get("gflops", {}),
                          "provenance": {k: b.provenance.get(k) for k in ("command", "created", "random_init")}},
                         indent=1))
        return 0
    problems = check_bundle(args.path, run=not args.no_run)
    if problems:
        print(f"bundle {args.path}: {len(problems)} problem(s)", file=sys.stderr)
        for p in problems:
            print(f"  - {p}", file=sys.stderr)
        return 1
    print(f"bundle {args.path}: OK")
    return 0
