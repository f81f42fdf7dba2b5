"""The estimator options that `pallet6d run` and `pallet6d eval` share, and loading the estimator from them."""
from __future__ import annotations

import argparse
import logging
import sys


def add_estimator_arguments(parser: argparse.ArgumentParser) -> None:
    """--bundle, --int8, --threads, --score-threshold, --max-pallets, --min-fit, --seed, --no-refine,
    --refine-starts, --type-candidates, --type-candidates-levelled, --type-margin, --type-margin-levelled,
    --pallet-types, --time-budget-ms, --pallet-lanes, --no-structure-check, --no-weak-boxes, --no-depth-proposals,
    --floor-from-depth."""
    parser.add_argument("--bundle", help="model bundle folder (default: $PALLET6D_BUNDLE, else the installed "
                                         "pallet6d-models package's epal-default, else ./models/epal-default)")
    parser.add_argument("--no-structure-check", action="store_true",
                        help="accept poses without checking the pallet's boards and openings in the depth")
    parser.add_argument("--no-weak-boxes", action="store_true",
                        help="do not pose detections scoring under --score-threshold (by default those scoring at "
                             "least 0.1 are posed and kept only with clear pallet structure)")
    parser.add_argument("--no-depth-proposals", action="store_true",
                        help="with a calibration, do not pose what stands a pallet's height on the floor in the depth "
                             "where the detector found nothing (by default it is posed and kept only with clear "
                             "pallet structure)")
    parser.add_argument("--floor-from-depth", action="store_true",
                        help="with a calibration, level the poses on each frame's own floor where the depth shows it "
                             "near the calibrated one (for a calibration that drifts or a truck that pitches with its "
                             "load; by default on the calibration's floor)")
    parser.add_argument("--int8", action="store_true", help="use the bundle's int8 graphs")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads per graph (default 2)")
    parser.add_argument("--score-threshold", type=float, default=0.25, help="detector score threshold")
    parser.add_argument("--detector-mirror", action="store_true",
                        help="the detector also sees each frame mirrored and averages the two views' scores (a "
                             "second detector run; fewer false boxes on real photographs)")
    parser.add_argument("--max-pallets", type=int, default=None,
                        help="pose at most this many detections per frame, the highest-scoring ones (default: "
                             "EstimatorOptions.max_pallets)")
    parser.add_argument("--min-fit", type=float, default=0.2, help="reject poses whose fit score is below this")
    parser.add_argument("--seed", type=int, default=0, help="point sampling seed")
    parser.add_argument("--no-refine", action="store_true",
                        help="report the network's poses without the ICP refinement on the depth")
    parser.add_argument("--refine-starts", type=int, default=None,
                        help="extra ICP starts around each pose, 0-14; a landing counts on clean depth only "
                             "(default: EstimatorOptions.refine_starts, 6; 0 is fastest)")
    parser.add_argument("--type-candidates", type=int, default=None,
                        help="where one detector class reports several pallet types, refine each pallet with this "
                             "many of them and keep the best fit (default: EstimatorOptions.type_candidates, 2)")
    parser.add_argument("--type-candidates-levelled", type=int, default=None,
                        help="the same with the camera's calibration, where each is levelled before it is judged "
                             "(default: EstimatorOptions.type_candidates_levelled, 11: every type of the default "
                             "bundle)")
    parser.add_argument("--type-margin", type=float, default=None,
                        help="where the depth chooses among several types, how much better (fit score 0-1) another "
                             "type must be to replace a detection's first type (default: EstimatorOptions.type_margin)")
    parser.add_argument("--type-first-enough", type=float, default=None,
                        help="without a calibration, a pallet whose first type scores at least this (0-1) at its "
                             "refined pose keeps it untried against the others; 1: compared unless it fits "
                             "perfectly (default: EstimatorOptions.type_first_enough, 0.6)")
    parser.add_argument("--type-margin-levelled", type=float, default=None,
                        help="the same where the types are judged levelled, with the camera's calibration "
                             "(default: EstimatorOptions.type_margin_levelled)")
    parser.add_argument("--pallet-types", type=lambda v: tuple(t.strip() for t in v.split(",") if t.strip()),
                        default=None, help="comma-separated pallet types this site uses, e.g. epal: only these are "
                                           "posed (default: every type of the bundle)")
    parser.add_argument("--time-budget-ms", type=float, default=None,
                        help="per-frame time budget: pallets are posed highest detector score first, and those left "
                             "when it is spent are reported as skipped (reason time_budget); default: no limit")
    parser.add_argument("--pallet-lanes", type=int, default=None,
                        help="pallets whose networks run side by side, one thread each (default 1; 2 on 2 cores: "
                             "four pallets about 12 ms sooner, about 60 MB more memory)")


def load_estimator(args: argparse.Namespace, command: str):
    """The `PalletEstimator` the arguments describe, or None after printing why it cannot be loaded.
    Without `--bundle`, `args.bundle` becomes the default bundle's folder (`default_bundle`)."""
    from .bundle import BundleError, load_bundle
    from .default_bundle import BundleNotFoundError, default_bundle
    from .estimator import EstimatorOptions, PalletEstimator, check_threads

    if args.bundle is None:
        try:
            args.bundle = default_bundle()
        except BundleNotFoundError as exc:
            print(f"pallet6d {command}: {exc}", file=sys.stderr)
            return None
        logging.getLogger(__name__).info("bundle: %s", args.bundle)
    try:
        check_threads(args.threads)
        # options left unset on the command line keep EstimatorOptions' defaults (one place says them)
        extra = {k: v for k, v in (("refine_starts", args.refine_starts), ("max_pallets", args.max_pallets),
                                   ("type_candidates", args.type_candidates),
                                   ("type_candidates_levelled", args.type_candidates_levelled),
                                   ("type_margin", args.type_margin),
                                   ("type_margin_levelled", args.type_margin_levelled),
                                   ("type_first_enough", args.type_first_enough),
                                   ("pallet_types", args.pallet_types or None),
                                   ("time_budget_ms", args.time_budget_ms),
                                   ("pallet_lanes", args.pallet_lanes)) if v is not None}
        if args.detector_mirror:
            extra["detector_mirror"] = True
        if args.no_structure_check:
            extra["structure"] = None
        if args.no_weak_boxes:
            extra["weak_boxes"] = None
        if args.no_depth_proposals:
            extra["depth_proposals"] = None
        if args.floor_from_depth:
            from .level import LevelParams
            extra["level"] = LevelParams(floor_from_depth=True)
        options = EstimatorOptions(score_threshold=args.score_threshold, min_fit=args.min_fit, seed=args.seed,
                                   refine=not args.no_refine, **extra)
    except (TypeError, ValueError) as exc:
        print(f"pallet6d {command}: invalid option: {exc}", file=sys.stderr)
        return None
    try:
        return PalletEstimator(load_bundle(args.bundle), threads=args.threads,
                               precision="int8" if args.int8 else "fp32", options=options)
    except (BundleError, FileNotFoundError, ValueError) as exc:
        print(f"pallet6d {command}: cannot load bundle {args.bundle}: {exc}", file=sys.stderr)
        return None
