"""`pallet6d export`: export the networks of a config to an ONNX model bundle."""
from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
from dataclasses import replace

from .config import CONFIGS, get_config

HELP = "export the detector, fusion and pose networks to an ONNX model bundle (manifest.json + graphs)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, choices=sorted(CONFIGS),
                        help="network variant: paper, edge (2-core CPU), densefusion (no attention), tiny (tests)")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="trained weights: torch.save({'detector':..., 'fusion':..., 'pose':...})")
    src.add_argument("--random-init", action="store_true", help="export untrained networks (to build/test the runtime)")
    parser.add_argument("--seed", type=int, default=0, help="seed for initialisation and calibration data")
    parser.add_argument("--int8", action="store_true", help="also write static int8 (QDQ) graphs")
    parser.add_argument("--int8-stages",
                        help="with --int8: comma-separated stages to quantize (default detector,fusion: the pose "
                             "net loses accuracy when quantized); the others run their float graph at int8 too")
    det = parser.add_mutually_exclusive_group()
    det.add_argument("--detector-onnx", help="use this YOLOv8 ONNX graph (ultralytics export layout) as detector")
    det.add_argument("--detector-from", metavar="BUNDLE",
                     help="keep this bundle's detector graphs (float and int8) byte for byte, e.g. when only the pose "
                          "stage was retrained (`pallet6d train merge --detector BUNDLE`); the checkpoint's detector "
                          "must be the same network")
    parser.add_argument("--fusion-from", metavar="BUNDLE",
                        help="keep this bundle's fusion graphs (float and int8) byte for byte; the checkpoint's fusion "
                             "network must be the same network (e.g. only the pose network's confidence retrained)")
    parser.add_argument("--detector-input-sizes", type=_sizes, metavar="HxW,HxW,...",
                        help="detector input sizes, one chosen per frame by its aspect (default: those the "
                             "checkpoint's detector was trained on); several give a graph with dynamic height/width")
    parser.add_argument("--classes", help="comma-separated class names of --detector-onnx (default: its metadata)")
    weights = parser.add_mutually_exclusive_group()
    weights.add_argument("--float-weights", choices=("fp32", "fp16", "int8"), default="int8",
                         help="how the float graphs store their weights on disk: int8 (default, per output channel, "
                              "a quarter of float32), fp16 (half) or fp32; the arithmetic is float32 in every case")
    weights.add_argument("--fp32-weights", dest="float_weights", action="store_const", const="fp32",
                         help="same as --float-weights fp32")
    parser.add_argument("--calib-frames", type=int, default=96,
                        help="simulated frames for calibration, the presets in turn (default 96: ~32 indoor crops)")
    parser.add_argument("--calib-presets", default=None,
                        help="comma-separated sim presets the calibration frames and crops come from, in turn "
                             "(default: virtual-occluded,indoor-noisy,virtual-clean)")
    parser.add_argument("--calib-crops", type=int, default=96,
                        help="pallet crops for calibration, taken from the presets in turn (default 96)")
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="torch intra-op threads (0 = torch's default); 1 is fastest for --config tiny on a busy machine")
    parser.add_argument("--pallet-types",
                        help="comma-separated pallet types of pallet6d.sim.pallets the bundle carries (default: the "
                             "config's one, epal); with several, the detector gets one class per type")
    parser.add_argument("--num-points", type=int, default=None,
                        help="points sampled per pallet (default: the config's); the pose network's weights do not "
                             "depend on it, so a trained network can be exported for fewer points (less work per "
                             "pallet) and measured")
    parser.add_argument("--name", help="bundle name (default: the output folder's name)")
    parser.add_argument("--out", required=True, help="output folder (new or empty), e.g. models/edge")


def _sizes(text: str) -> tuple[tuple[int, int], ...]:
    """'192x640,256x480' -> ((192, 640), (256, 480))."""
    try:
        sizes = tuple(tuple(int(v) for v in part.lower().split("x")) for part in text.split(","))
    except ValueError:
        sizes = ()
    if not sizes or any(len(hw) != 2 for hw in sizes):
        raise argparse.ArgumentTypeError(f"expected HxW[,HxW...], e.g. 192x640,256x480, got {text!r}")
    return sizes


def main(args: argparse.Namespace) -> int:
    from .bundle_export import INT8_STAGES, ExportError, export_bundle
    from .onnx_io import ParityError
    from .pallet_types import parse_pallet_types

    if args.torch_threads > 0:
        import torch
        torch.set_num_threads(args.torch_threads)
    classes = tuple(c.strip() for c in args.classes.split(",")) if args.classes else None
    command = "pallet6d export " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 2 else ""
    try:
        types = parse_pallet_types(args.pallet_types) if args.pallet_types else None
        cfg = get_config(args.config)
        if args.num_points is not None:
            if args.num_points < 1:
                raise ExportError(f"--num-points must be a positive integer, got {args.num_points}")
            cfg = replace(cfg, pose=replace(cfg.pose, num_points=args.num_points))
        exported = export_bundle(cfg, args.out, seed=args.seed, checkpoint=args.checkpoint,
                                 random_init=args.random_init, int8=args.int8, detector_onnx=args.detector_onnx,
                                 classes=classes, name=args.name, command=command, calib_frames=args.calib_frames,
                                 calib_crops=args.calib_crops, calib_presets=tuple(
                                     p.strip() for p in args.calib_presets.split(",") if p.strip())
                                 if args.calib_presets else None,
                                 float_weights=args.float_weights,
                                 int8_stages=INT8_STAGES if args.int8_stages is None else
                                 tuple(s.strip() for s in args.int8_stages.split(",") if s.strip()),
                                 pallet_types=types, detector_input_sizes=args.detector_input_sizes,
                                 keep_from={k: v for k, v in (("detector", args.detector_from),
                                                              ("fusion", args.fusion_from)) if v})
    except (ExportError, ParityError) as exc:
        print(f"pallet6d export: {exc}", file=sys.stderr)
        return 1
    m = exported.manifest
    print(f"wrote bundle {args.out} ({m.config}, precision {', '.join(m.precision)}, pallet types "
          f"{', '.join(t.name for t in m.pallet_types)})")
    print(json.dumps(exported.report["checks"], indent=1))
    return 0
