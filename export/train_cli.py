"""`pallet6d train`: train the detector or the pose stage on BOP datasets, and merge the two checkpoints.

    pallet6d train detector|pose --config paper|edge|densefusion --data DIR [DIR ...] --out RUN_DIR
                   [--epochs E] [--batch B] [--lr LR] [--seed S] [--resume] [--device cpu|cuda] [--max-minutes M]
    pallet6d train merge --detector RUN/best.pt|BUNDLE_DIR --pose RUN/best.pt|BUNDLE_DIR --out model.pt
    pallet6d export --config edge --checkpoint model.pt --int8 --out models/edge

RUN_DIR receives `last.pt`, `best.pt` (lowest validation metric: pose = mean symmetric ADD of the most
confident hypothesis; detector = validation loss), `train_log.jsonl` (one line per epoch: losses, validation,
lr, seconds) and `cache/` (prepared samples, reused while the data and settings are unchanged). A run is
stopped cleanly by `--max-minutes` and continued with `--resume` (same arguments). `--init CKPT` starts a new
run from a checkpoint's weights (fine-tuning, e.g. on more data, with a fresh schedule); the checkpoint's path and
sha256 go into the new run's provenance. `--init models/epal-default` starts from a shipped bundle instead: the
weights are read back from its float graphs (`bundle_weights.py`; parity with the graphs is checked and recorded),
so training can go on from what ships when the run that made it is gone; `--freeze-bn-stats` keeps its BatchNorms'
statistics through such a round. `--detector-input HxW` trains the detector at another letterboxed size than the
config's (it is fully convolutional); the size is recorded in the checkpoint, and `pallet6d export` exports the
detector at the size it was trained at.

Default recipe for the shipped `edge` bundle (and, unchanged, the `densefusion` ablation)
------------------------------------------------------------------------------------------
Data (training seeds are 1000+, never the test seeds 9001-9003 of `benchmarks/accuracy.py`)::

    pallet6d sim --preset virtual-clean    --frames 400 --seed 1000 --out data/train/virtual-clean
    pallet6d sim --preset virtual-occluded --frames 800 --seed 1001 --out data/train/virtual-occluded
    pallet6d sim --preset indoor-noisy     --frames 400 --seed 1002 --out data/train/indoor-noisy

Training (`RECIPES` holds these defaults; flags override them)::

    D="data/train/virtual-clean data/train/virtual-occluded data/train/indoor-noisy"
    pallet6d train detector --config edge --data $D --out runs/edge-det        # 20 epochs, batch 16, lr 2e-3
    pallet6d train pose     --config edge --data $D --out runs/edge-pose       # 5 epochs, batch 16, lr 3e-4,
                                                                               # 2 augmented views per pallet
    pallet6d train merge --detector runs/edge-det/best.pt --pose runs/edge-pose/best.pt --out runs/edge.pt
    pallet6d export --config edge --checkpoint runs/edge.pt --int8 --out models/edge

Ablation: the same commands with `--config edge-densefusion` (the edge network without attention; `merge`
takes the edge detector for it) or `densefusion` / `paper` at paper size; same data, seeds, epochs and batch, so
the only difference is the network.

Cost on this 2-core machine, detector and pose trained side by side with one torch thread each
(`OMP_NUM_THREADS=1`; 2026-11-21): sim ~2 frames/s per core at 1224x370; the 1600 frames above give 1440
detector training frames (~2 min per detector epoch: 12 epochs in 24 min reached validation precision 0.89,
recall 0.88) and ~6.2k pose samples with 1 view per pallet (~19 min per pose epoch; sample preparation is a
one-off of a few minutes, cached). The pose stage is the long pole: 5 epochs x 2 views is ~3 h. Run each in
the background with `--no-progress --max-minutes M` and continue with `--resume` (a larger `--epochs` with
`--resume` extends a finished run). The shipped `models/epal-default` came from 45 detector epochs (90 min) and
13 pose epochs x 1 view (245 min) this way, each run once extended (commands in benchmarks/results/README.md).
On CUDA (`--device cuda`) epochs take seconds to a minute: use `--epochs 40` (pose) and `--epochs 100`
(detector) there rather than more data. The `densefusion`/`paper` networks are ~5x the edge pose-stage FLOPs: train them on CUDA.
"""
from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import logging
import math
import shlex
import sys
from pathlib import Path

from .config import CONFIGS, DETECTOR_ACTIVATIONS, DETECTOR_ARCHITECTURES, get_config

HELP = "train the detector or the pose stage on BOP datasets (sim presets or annotated recordings)"

log = logging.getLogger(__name__)

# (config, stage) -> defaults, sized for 2 CPU cores (module docstring). Pose: ~8.4k samples per epoch.
RECIPES: dict[tuple[str, str], dict] = {
    ("edge", "detector"): {"epochs": 20, "batch": 16, "lr": 2e-3},
    ("edge", "pose"): {"epochs": 5, "batch": 16, "lr": 3e-4, "variants": 2},
    ("edge-densefusion", "detector"): {"epochs": 20, "batch": 16, "lr": 2e-3},
    ("edge-densefusion", "pose"): {"epochs": 5, "batch": 16, "lr": 3e-4, "variants": 2},
    ("paper", "detector"): {"epochs": 20, "batch": 8, "lr": 2e-3},
    ("paper", "pose"): {"epochs": 5, "batch": 16, "lr": 3e-4, "variants": 2},
    ("densefusion", "detector"): {"epochs": 20, "batch": 8, "lr": 2e-3},
    ("densefusion", "pose"): {"epochs": 5, "batch": 16, "lr": 3e-4, "variants": 2},
    ("tiny", "detector"): {"epochs": 3, "batch": 2, "lr": 2e-3},
    ("tiny", "pose"): {"epochs": 3, "batch": 4, "lr": 1e-3, "variants": 2},
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("stage", choices=("detector", "pose", "merge"),
                        help="what to train, or 'merge' a detector and a pose checkpoint for `pallet6d export`")
    parser.add_argument("--config", choices=sorted(CONFIGS), help="network variant (detector/pose)")
    parser.add_argument("--data", nargs="+", type=Path, help="BOP dataset roots (e.g. from `pallet6d sim`)")
    parser.add_argument("--out", type=Path, required=True, help="run folder (detector/pose) or merged file (merge)")
    parser.add_argument("--epochs", type=int, help="total epochs (default: the config's recipe)")
    parser.add_argument("--batch", type=int, help="samples per step (default: the recipe)")
    parser.add_argument("--lr", type=float, help="peak learning rate (default: the recipe)")
    parser.add_argument("--variants", type=int, help="pose: augmented views prepared per pallet (default 2)")
    parser.add_argument("--num-points", type=int, metavar="N",
                        help="pose: train on N points per pallet (a random subset of the config's, re-centred); "
                             "export the result with the same `pallet6d export --num-points N`")
    parser.add_argument("--distill", type=Path, metavar="BUNDLE|CKPT",
                        help="pose: also train the fusion network to give these weights' fused features (a bundle or "
                             "checkpoint whose fusion network takes the same crops, e.g. a smaller config learning "
                             "from models/epal-default). detector: also match this detector's class scores and box "
                             "distributions at every anchor (e.g. a ReLU detector learning from the SiLU one)")
    parser.add_argument("--distill-weight", type=float, default=1.0,
                        help="weight of --distill's term in the loss (pose: the feature error relative to the "
                             "teacher's variance; default 1)")
    parser.add_argument("--negatives", metavar="PRESET,...",
                        help="pose: crops without a pallet, the boxes --negatives-detector finds in pallet-free scenes "
                             "of these sim presets (their loads set down and left hanging; seed --seed): with "
                             "--distill the teacher's features are matched there, with --negative-conf-weight the "
                             "confidence is taught to be low there")
    parser.add_argument("--negative-frames", type=int, default=30, metavar="N",
                        help="pose: pallet-free frames per preset and load placement for --negatives (30)")
    parser.add_argument("--negatives-detector", type=Path, metavar="BUNDLE",
                        help="pose: the bundle whose detector boxes the --negatives crops (default: --distill, else "
                             "--init)")
    parser.add_argument("--mismatched-frames", type=int, default=0, metavar="N",
                        help="pose: add to the negatives the pallets of N training frames drawn at random under depth "
                             "or intrinsics that do not belong to the image (another frame's depth, depth 10x too "
                             "near, focal 2x too long, a flat wall; 0: none)")
    parser.add_argument("--negative-conf-weight", type=float, default=0.0, metavar="W",
                        help="pose: weight of the pose network's confidence on the --negatives crops (mean of "
                             "-log(1 - confidence)) in the loss (default 0: not trained there)")
    parser.add_argument("--negative-conf-top", type=float, default=1.0, metavar="F",
                        help="pose: the --negative-conf-weight term over this fraction of each negative crop's most "
                             "confident points (default 1: all; the runtime refuses by the best point alone)")
    parser.add_argument("--conf-head-only", action="store_true",
                        help="pose: train the pose network's confidence head alone, the rest as --init gives it "
                             "(every point's rotation and translation stay)")
    parser.add_argument("--keep-pallet-conf", action="store_true",
                        help="pose, with --conf-head-only: train the pallets' confidences toward --init's own "
                             "(binary cross-entropy per point) instead of the eq. 4 loss, so that the negatives alone "
                             "move the confidence")
    parser.add_argument("--verifier-only", action="store_true",
                        help="pose: train the verifier head alone (a config with one, e.g. edge2-verified; started as a "
                             "copy of --init's confidence head): it follows the confidence head on the pallets and "
                             "learns to be low at the --negatives' chosen points; every pose stays --init's")
    parser.add_argument("--verifier-target", choices=("confidence", "pallet"), default="confidence",
                        help="pose, with --verifier-only: on the pallets the verifier follows the confidence head "
                             "(confidence, default) or learns 1 at the chosen point (pallet: pallet or not, whatever "
                             "the pose's error)")
    parser.add_argument("--calibrate-share", type=float, metavar="S",
                        help="pose: after training, shift the confidence's output logit in each checkpoint so that the "
                             "runtime's floor (min_confidence 0.1) keeps share S of the validation pallets (every pose "
                             "and its ranking stay; recorded in the provenance); with --resume on a finished run, only "
                             "that. Not with --verifier-only, which calibrates the verifier to the confidence head")
    parser.add_argument("--freeze-pose", action="store_true",
                        help="pose: train the fusion network alone, the pose network fixed as --init gives it")
    parser.add_argument("--pose-only", action="store_true",
                        help="pose: train the pose network alone, the fusion network fixed as --init gives it; its "
                             "features are computed once per sample, so a step costs the pose network's passes only "
                             "(many epochs on a CPU)")
    parser.add_argument("--seed", type=int, default=0, help="seed of augmentation, sampling, shuffling, init")
    parser.add_argument("--resume", action="store_true", help="continue RUN_DIR/last.pt")
    parser.add_argument("--init", type=Path,
                        help="start from these weights: a run's best.pt, a merged file, or a model bundle folder "
                             "(e.g. models/epal-default: read back from its float graphs, checked against them); "
                             "fine-tuning with a fresh schedule, e.g. on more data; ignored with --resume")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="torch device (default cpu)")
    parser.add_argument("--amp", action="store_true",
                        help="bfloat16 autocast of the forward passes: about 1.8x faster on CPUs with AVX512-BF16 or "
                             "AMX, slower on CPUs without (weights, validation and export stay float32)")
    parser.add_argument("--freeze-bn-stats", action="store_true",
                        help="BatchNorms normalise with their running statistics and keep them (their scale and "
                             "shift still learn): for a fine-tuning round from trained weights (--init)")
    parser.add_argument("--max-minutes", type=float, default=0.0, help="stop cleanly after M minutes (0: no limit)")
    parser.add_argument("--max-frames", type=int, help="use at most N frames of each dataset")
    parser.add_argument("--val-fraction", type=float, default=0.1, help="frames held out for validation (0.1)")
    parser.add_argument("--cache-dir", type=Path, help="prepared-sample cache (default RUN_DIR/cache)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (background runs)")
    parser.add_argument("--detector-input", type=_hw, metavar="HxW",
                        help="detector: train at this letterboxed input size instead of the config's (multiples "
                             "of 32, e.g. 256x832 for small, far pallets); export uses the size it was trained at")
    parser.add_argument("--detector-input-sizes", type=_hw_list, metavar="HxW,HxW,...",
                        help="detector: the input sizes it runs at, each frame at the one that draws it largest (e.g. "
                             "192x640,256x480,288x416,320x384: wide paper frames, 16:9 and 4:3 cameras at one "
                             "cost); the first is the reference size unless --detector-input names another of them")
    parser.add_argument("--detector-depth-max-m", type=float, metavar="M",
                        help="detector: an RGB-D detector, depth as a 4th input channel (depth / M, clipped to 1); "
                             "`--init` from an RGB detector starts it as that detector (depth kernels at zero)")
    parser.add_argument("--detector-activation", choices=DETECTOR_ACTIVATIONS,
                        help="detector: silu (YOLOv8's) or relu (folds into the int8 convolutions: about a quarter "
                             "less detector time on 2 cores); default the --init detector's, else silu. `--init` "
                             "from a detector of the other activation starts from its weights")
    parser.add_argument("--detector-architecture", choices=DETECTOR_ARCHITECTURES,
                        help="detector: yolov8 (C2f backbone, BatchNorm) or yolox-nano (depthwise CSP network laid "
                             "out so that published COCO weights can start it, --pretrained); default the --init "
                             "detector's, else yolov8")
    parser.add_argument("--pretrained", type=Path, metavar="ONNX",
                        help="detector: start a yolox-nano detector from the published YOLOX-Nano ONNX export "
                             "(docs/data.md, Pretrained weights)")
    parser.add_argument("--real", type=Path,
                        help="detector: also train on the train split of real photographs imported by "
                             "`python -m pallet6d.export.real_data import` (this folder; docs/data.md)")
    parser.add_argument("--real-max-images", type=int, help="detector: use at most N real photographs")
    parser.add_argument("--real-keep-kind", action="append", default=[], metavar="KIND",
                        help="detector: real photographs of this pallet kind (e.g. plastic) are always among "
                             "--real-max-images and trained --real-repeat-large times (repeatable)")
    parser.add_argument("--detector-classes", metavar="types|NAME,...",
                        help="detector: its classes: 'types' (one per pallet type of the training data, so the "
                             "detector reports the type), or names of pallet types; default one class, 'pallet'")
    parser.add_argument("--class-lr-mult", type=float, default=1.0, metavar="X",
                        help="detector: learning rate of the class outputs, times --lr (default 1)")
    parser.add_argument("--mosaic", type=float, default=0.0, metavar="P",
                        help="detector: share of the training inputs that hold four frames, a quarter each "
                             "(YOLOv8's mosaic; default 0)")
    parser.add_argument("--real-repeat-large", type=int, default=1, metavar="K",
                        help="detector: train real photographs holding a box >= 20%% of the image tall K times (1)")
    parser.add_argument("--loader-threads", type=int, default=1,
                        help="detector: threads that prepare a batch's frames (the same batches for any number; "
                             "an accelerator needs several to be kept busy)")
    parser.add_argument("--select", choices=("loss", "near_f1"), default="loss",
                        help="detector: best.pt by validation loss (default) or by F1 of real near-box recall "
                             "(boxes >= 8%% of the image tall) and real precision")
    parser.add_argument("--detector", type=Path,
                        help="merge: detector checkpoint, or a bundle folder to take its detector")
    parser.add_argument("--pose", type=Path, help="merge: pose checkpoint, or a bundle folder to take its pose stage")
    parser.add_argument("--detector-logit-offset", type=float, default=0.0, metavar="D",
                        help="merge: add D to the detector's class logits, so that a detector whose scores run lower "
                             "than the one it replaces reads at the runtime's threshold as that one did (0.288 moves "
                             "a score of 0.20 to 0.25); recorded in the provenance")


def detector_classes(spec: str, data: list[Path]) -> tuple[str, ...]:
    """The detector's class names: "types" = every pallet type the datasets' models_info names, in catalogue
    order; else comma-separated catalogue type names.

    :raises ValueError: an unknown type name, or no type found in the data.
    """
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.sim.pallets import PALLET_MODELS

    if spec.strip() == "types":
        found = {v.get("name") for root in data for v in BopDataset(root).models_info.values()}
        names = tuple(n for n in PALLET_MODELS if n in found)
        if not names:
            raise ValueError("--detector-classes types: the datasets name no pallet type of the catalogue "
                             f"({', '.join(PALLET_MODELS)})")
        return names
    names = tuple(n.strip() for n in spec.split(",") if n.strip())
    unknown = [n for n in names if n not in PALLET_MODELS]
    if unknown or not names or len(set(names)) != len(names):
        raise ValueError(f"--detector-classes {spec!r}: give 'types' or distinct pallet types of "
                         f"{', '.join(PALLET_MODELS)}")
    return names


def _hw(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW, e.g. 256x832, got {text!r}") from None
    return h, w


def _hw_list(text: str) -> list[tuple[int, int]]:
    return [_hw(t) for t in text.split(",") if t.strip()]


def merge_checkpoints(detector_ckpt: Path, pose_ckpt: Path, out: Path, detector_logit_offset: float = 0.0) -> dict:
    """One checkpoint with detector + fusion + pose weights (the `export_bundle` format) and both provenances.
    Either side may be a bundle folder: its stage is read back from its graphs (`bundle_weights.bundle_checkpoint`).

    :param detector_logit_offset: added to the detector's class logits (the biases of its class output convs,
        `head.cls.*.2.bias`) and recorded in the provenance: a detector whose scores run lower than the one it
        replaces then reads at the runtime's score threshold as that one did (a ReLU detector whose recall and false
        boxes at 0.20 match the SiLU one's at 0.25: logit(0.25) - logit(0.20) = 0.288).
    :raises ValueError: wrong stages or configs that differ, an offset that is not finite.
    """
    if not math.isfinite(detector_logit_offset):
        raise ValueError(f"detector_logit_offset must be a finite number, got {detector_logit_offset}")
    from .bundle_weights import bundle_checkpoint
    from .train_loop import load_checkpoint, save_checkpoint

    def read(path: Path, stage: str) -> dict:
        return bundle_checkpoint(path, stage) if Path(path).is_dir() else load_checkpoint(path)

    det, pose = read(detector_ckpt, "detector"), read(pose_ckpt, "pose")
    if det.get("stage") != "detector" or pose.get("stage") != "pose":
        raise ValueError(f"expected a detector and a pose checkpoint, got stages {det.get('stage')!r} and "
                         f"{pose.get('stage')!r}")
    # one detector serves variants that differ only in the pose stage (edge and its ablation edge-densefusion)
    if get_config(det["config"]).detector != get_config(pose["config"]).detector:
        raise ValueError(f"the detector was trained with config {det['config']!r}, whose detector differs from "
                         f"that of the pose stage's {pose['config']!r}: export needs one config")
    det_weights, det_record = dict(det["detector"]), {}
    if detector_logit_offset:
        cls_biases = [k for k in det_weights if fnmatch.fnmatchcase(k, "head.cls.*.2.bias")]
        if not cls_biases:
            raise ValueError("the detector has no class output convs (head.cls.*.2) to offset")
        for k in cls_biases:
            det_weights[k] = det_weights[k] + detector_logit_offset
        det_record = {"logit_offset": float(detector_logit_offset)}
    merged = {"config": pose["config"], "detector": det_weights, "fusion": pose["fusion"], "pose": pose["pose"],
              "format": det["format"], "format_version": det["format_version"], "stage": "merged",
              "provenance": {"detector": {**det["provenance"], "checkpoint": str(detector_ckpt),
                                          "epoch": det["epoch"], "val": det["val"], **det_record},
                             "pose": {**pose["provenance"], "checkpoint": str(pose_ckpt), "epoch": pose["epoch"],
                                      "val": pose["val"]}}}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out, merged)
    return merged


def main(args: argparse.Namespace) -> int:
    from .train_data import AugmentConfig
    from .train_loop import LoopSettings

    if args.stage == "merge":
        if not args.detector or not args.pose:
            print("pallet6d train merge: needs --detector CKPT and --pose CKPT", file=sys.stderr)
            return 2
        try:
            merge_checkpoints(args.detector, args.pose, args.out, args.detector_logit_offset)
        except ValueError as exc:
            print(f"pallet6d train merge: {exc}", file=sys.stderr)
            return 1
        print(f"wrote {args.out}; export it with: pallet6d export --config <config> --checkpoint {args.out} "
              "--int8 --out models/<name>")
        return 0
    if not args.config or not args.data:
        print(f"pallet6d train {args.stage}: needs --config and --data", file=sys.stderr)
        return 2
    if args.device == "cuda":
        import torch
        if not torch.cuda.is_available():
            print("pallet6d train: --device cuda but torch sees no CUDA device", file=sys.stderr)
            return 2
    recipe = RECIPES.get((args.config, args.stage), RECIPES[("edge", args.stage)])
    command = "pallet6d train " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 2 else ""
    try:
        settings = LoopSettings(epochs=args.epochs or recipe["epochs"], batch=args.batch or recipe["batch"],
                                lr=args.lr or recipe["lr"], seed=args.seed, max_minutes=args.max_minutes,
                                warmup_epochs=1.0 if args.stage == "detector" else 0.0, device=args.device,
                                amp=args.amp, freeze_bn_stats=args.freeze_bn_stats)
        cfg = get_config(args.config)
        if args.detector_input is not None:
            if args.stage != "detector":
                print("pallet6d train: --detector-input is for the detector stage", file=sys.stderr)
                return 2
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=args.detector_input))
        if args.detector_classes is not None:
            if args.stage != "detector":
                print("pallet6d train: --detector-classes is for the detector stage", file=sys.stderr)
                return 2
            cfg = cfg.replace(detector=dataclasses.replace(
                cfg.detector, classes=detector_classes(args.detector_classes, args.data)))
        if args.detector_depth_max_m is not None:
            if args.stage != "detector":
                print("pallet6d train: --detector-depth-max-m is for the detector stage", file=sys.stderr)
                return 2
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, depth_max_m=args.detector_depth_max_m))
        if (args.detector_activation or args.detector_architecture or args.pretrained) and args.stage != "detector":
            print("pallet6d train: --detector-activation, --detector-architecture and --pretrained are for the "
                  "detector stage", file=sys.stderr)
            return 2
        if args.stage == "detector":
            from .bundle_weights import detector_activation_of, detector_architecture_of
            activation = args.detector_activation or detector_activation_of(args.init)
            architecture = args.detector_architecture or detector_architecture_of(args.init)
            cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, activation=activation,
                                                           architecture=architecture))
        sizes = args.detector_input_sizes
        if sizes is not None:
            if args.stage != "detector" or not sizes:
                print("pallet6d train: --detector-input-sizes is for the detector stage and needs a size",
                      file=sys.stderr)
                return 2
            if tuple(cfg.detector.input_hw) not in sizes:
                if args.detector_input is not None:
                    print("pallet6d train: --detector-input must be one of --detector-input-sizes", file=sys.stderr)
                    return 2
                cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=sizes[0]))
        common = dict(resume=args.resume, cache_dir=args.cache_dir, val_fraction=args.val_fraction,
                      max_frames=args.max_frames, command=command, progress=not args.no_progress,
                      init=args.init)
        if args.real is not None and args.stage != "detector":
            print("pallet6d train: --real is for the detector stage", file=sys.stderr)
            return 2
        if args.resume and not (args.out / "last.pt").exists():
            print(f"pallet6d train: --resume but {args.out / 'last.pt'} does not exist", file=sys.stderr)
            return 2
        if args.num_points is not None and args.stage != "pose":
            print("pallet6d train: --num-points is for the pose stage", file=sys.stderr)
            return 2
        if (args.freeze_pose or args.pose_only or args.negatives or args.mismatched_frames
                or args.conf_head_only or args.keep_pallet_conf or args.verifier_only
                or args.calibrate_share is not None) and args.stage != "pose":
            print("pallet6d train: --freeze-pose, --pose-only, --negatives, --mismatched-frames, "
                  "--conf-head-only, --keep-pallet-conf, --verifier-only and --calibrate-share are for the pose stage",
                  file=sys.stderr)
            return 2
        if args.verifier_target != "confidence" and not args.verifier_only:
            print("pallet6d train: --verifier-target is for --verifier-only", file=sys.stderr)
            return 2
        boxer = args.negatives_detector or args.distill or args.init
        if args.negatives and boxer is None:
            print("pallet6d train: --negatives needs a bundle whose detector boxes the crops (--negatives-detector, "
                  "--distill or --init)", file=sys.stderr)
            return 2
        if (args.negatives or args.mismatched_frames) and args.distill is None and not args.negative_conf_weight > 0:
            print("pallet6d train: negative crops (--negatives, --mismatched-frames) need a use: --distill or "
                  "--negative-conf-weight", file=sys.stderr)
            return 2
        if args.stage == "pose":
            from .train_pose import train_pose
            negatives = None if not args.negatives else {
                "detector_bundle": boxer, "presets": args.negatives.split(","), "frames": args.negative_frames,
                "seed": args.seed}
            entry = train_pose(cfg, args.data, args.out, settings, variants=args.variants or recipe["variants"],
                               aug=AugmentConfig(), num_points=args.num_points, distill=args.distill,
                               distill_weight=args.distill_weight, freeze_pose=args.freeze_pose,
                               negatives=negatives, negative_conf_weight=args.negative_conf_weight,
                               conf_head_only=args.conf_head_only, mismatched_frames=args.mismatched_frames,
                               keep_pallet_conf=args.keep_pallet_conf, negative_conf_top=args.negative_conf_top,
                               verifier_only=args.verifier_only, verifier_target=args.verifier_target,
                               calibrate_share=args.calibrate_share, pose_only=args.pose_only, **common)
        else:
            from .train_detector import train_detector
            entry = train_detector(cfg, args.data, args.out, settings, aug=AugmentConfig(), real=args.real,
                                   real_max_images=args.real_max_images, input_sizes=sizes,
                                   real_repeat_large=args.real_repeat_large, select=args.select,
                                   loader_threads=args.loader_threads, class_lr_mult=args.class_lr_mult,
                                   mosaic=args.mosaic, distill=args.distill, distill_weight=args.distill_weight,
                                   pretrained=args.pretrained, real_keep_kinds=args.real_keep_kind, **common)
    except (ValueError, FloatingPointError) as exc:
        print(f"pallet6d train {args.stage}: {exc}", file=sys.stderr)
        return 1
    print(f"{args.stage} run {args.out}: last epoch {entry.get('epoch')}, "
          + ", ".join(f"{k}={v:.4g}" for k, v in entry.items() if k.startswith("val_") and isinstance(v, float)))
    print(f"checkpoints: {args.out / 'last.pt'}, {args.out / 'best.pt'}; log: {args.out / 'train_log.jsonl'}")
    return 0
