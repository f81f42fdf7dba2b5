"""The epoch loop shared by detector and pose training: learning-rate schedule, tqdm progress, JSON-lines
log, checkpoints (last + best) in the format `export_bundle` reads, `--resume`, and a wall-clock budget.

Everything that varies with the epoch is a pure function of (seed, epoch): the shuffling generator is
`np.random.default_rng((seed, epoch))`, the learning rate `lr_at(epoch + step / steps)`, so a resumed run
continues exactly as an uninterrupted one would, without saving RNG states.

Checkpoint (``torch.save`` of plain types, loadable with ``weights_only=True``)::

    {"config": name, "<net>": state_dict, ...,            # what export_bundle reads ("detector"/"fusion"/"pose")
     "format": "pallet6d-train", "format_version": 1, "stage": "detector" | "pose",
     "epoch": completed epochs, "best_metric": float, "val": {...}, "optimizer": state_dict,
     "provenance": {"stage", "config", "seed", "command", "data": [dataset fingerprints], ...}}
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

__all__ = ["LoopSettings", "autocast", "conv_layout", "conv_input", "contiguous_state", "lr_at", "save_checkpoint",
           "load_checkpoint", "train_epochs", "CKPT_FORMAT", "LAST", "BEST", "LOG"]

log = logging.getLogger(__name__)

CKPT_FORMAT = "pallet6d-train"
LAST, BEST, LOG = "last.pt", "best.pt", "train_log.jsonl"


@dataclass(frozen=True)
class LoopSettings:
    """:ivar epochs: total epochs (a resumed run continues to this). :ivar batch: samples per step.
    :ivar lr: peak learning rate. :ivar warmup_epochs: linear warm-up length (may be fractional).
    :ivar min_lr_fraction: the cosine schedule ends at lr * this. :ivar max_minutes: stop (after saving)
    when this much wall time has passed in this process; 0 = no limit. :ivar grad_clip: max grad norm.
    :ivar amp: bfloat16 autocast of the training forward passes (`autocast`); weights, optimizer state and
    validation stay float32, so checkpoints and exports are unchanged. :ivar freeze_bn_stats: every BatchNorm
    normalises with its running statistics while training and never updates them (`keep_bn_stats`); its scale
    and shift still learn."""

    epochs: int
    batch: int
    lr: float
    seed: int = 0
    warmup_epochs: float = 0.0
    min_lr_fraction: float = 0.05
    max_minutes: float = 0.0
    grad_clip: float = 10.0
    device: str = "cpu"
    amp: bool = False
    freeze_bn_stats: bool = False

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch < 1:
            raise ValueError(f"epochs and batch must be >= 1, got {self.epochs}, {self.batch}")
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")
        if self.max_minutes < 0:
            raise ValueError(f"max_minutes must be >= 0, got {self.max_minutes}")


def autocast(device: str, enabled: bool):
    """Context for a training forward pass: convolutions and matrix products in bfloat16 when `enabled`.

    On CPUs with AVX512-BF16 (or AMX) oneDNN runs them about 1.8x faster than float32 (forward + backward of
    the edge pose stage, measured here); losses are computed on float32 copies of the outputs."""
    return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16, enabled=enabled)


def conv_layout(net: torch.nn.Module) -> torch.nn.Module:
    """`net` with its 4-D weights in channels-last layout, for inputs passed through `conv_input`: oneDNN's
    convolutions then skip a layout conversion at every layer (bfloat16 on a 2-core AMX CPU: the edge detector's
    forward and backward about 20 % faster, the edge fusion network's about 9 %, a distilled detector epoch about
    12 % shorter). Checkpoints store contiguous copies (`contiguous_state`), so nothing downstream sees the layout."""
    return net.to(memory_format=torch.channels_last)


def conv_input(x: torch.Tensor) -> torch.Tensor:
    """A (B, C, H, W) network input in the layout `conv_layout` gives the weights."""
    return x.contiguous(memory_format=torch.channels_last)


def keep_bn_stats(net: torch.nn.Module) -> int:
    """Put every BatchNorm of `net` (in train mode otherwise) in eval mode: it normalises with its running
    statistics and leaves them as they are. A round that fine-tunes a trained network on a new mix of frames (a
    few real photographs among many simulated ones, batches of 16) otherwise re-estimates statistics the rest of
    the network was fitted to. :return: the number of BatchNorms set."""
    norms = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    for m in norms:
        m.eval()
    return len(norms)


def lr_at(s: LoopSettings, epoch_f: float) -> float:
    """Learning rate at fractional epoch `epoch_f`: linear warm-up, then cosine to lr * min_lr_fraction."""
    warm = min(1.0, (epoch_f + 1e-9) / s.warmup_epochs) if s.warmup_epochs > 0 else 1.0
    frac = min(1.0, epoch_f / s.epochs)
    cos = s.min_lr_fraction + (1 - s.min_lr_fraction) * 0.5 * (1 + math.cos(math.pi * frac))
    return s.lr * warm * cos


def save_checkpoint(path: Path, payload: dict) -> None:
    """Atomic write (a crash never leaves a half-written checkpoint)."""
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def contiguous_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """`net.state_dict()` with every tensor contiguous (a `conv_layout` net's weights are channels-last)."""
    return {k: v.contiguous() for k, v in net.state_dict().items()}


def load_checkpoint(path: str | Path) -> dict:
    """A training checkpoint. :raises ValueError: missing or not a pallet6d training checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt file
        raise ValueError(f"cannot read checkpoint {path}: {exc}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CKPT_FORMAT:
        raise ValueError(f"{path} is not a pallet6d training checkpoint")
    return ckpt


def load_init_weights(path: str | Path, nets: dict[str, torch.nn.Module]) -> dict:
    """Load each net's weights from a checkpoint, or from a model bundle's float graphs (a folder:
    `bundle_weights`); return what to record of it (path, sha256, config, epoch or parity, and how those
    weights were trained: a chain of fine-tuning runs stays reproducible from the last one's record).

    :raises ValueError: not a checkpoint or bundle, a net missing from it, or weights that do not fit the net.
    """
    if Path(path).is_dir():
        from .bundle_weights import load_bundle_weights
        return load_bundle_weights(path, nets)
    ckpt = load_checkpoint(path)
    for k, net in nets.items():
        if k not in ckpt:
            raise ValueError(f"--init {path} has no {k!r} weights (it is a {ckpt.get('stage')!r} checkpoint)")
        state = ckpt[k]
        if k == "detector":   # a one-class detector starts every class of a typed one; an RGB one an RGB-D one
            from .detector import widen_class_outputs, widen_input_channels
            state = widen_input_channels(widen_class_outputs(state, net), net)
        try:
            net.load_state_dict(state)
        except RuntimeError as exc:
            raise ValueError(f"--init {path}: its {k!r} weights do not fit this config's network: "
                             f"{str(exc).splitlines()[0]}") from None
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    log.info("starting from the weights of %s (%s)", path, ", ".join(nets))
    return {"checkpoint": str(path), "sha256": digest, "stage": ckpt.get("stage"), "config": ckpt.get("config"),
            "epoch": ckpt.get("epoch"), "provenance": ckpt.get("provenance")}


def _batches(n: int, batch: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Shuffled index batches; a final batch of one sample is dropped (BatchNorm needs two)."""
    perm = rng.permutation(n)
    out = [perm[i:i + batch] for i in range(0, n, batch)]
    return [b for b in out if len(b) >= 2] or out


def train_epochs(run_dir: Path, stage: str, config_name: str, nets: dict[str, torch.nn.Module],
                 optimizer: torch.optim.Optimizer, s: LoopSettings, n_train: int,
                 step: Callable[[np.ndarray, np.random.Generator], tuple[torch.Tensor, dict]],
                 validate: Callable[[], dict], provenance: dict, resume: bool = False,
                 progress: bool = True, init: str | Path | None = None) -> dict:
    """Train `nets` for the remaining epochs; return the last log entry.

    :param step: (index batch, rng) -> (loss to minimise, {name: float} to log).
    :param validate: () -> {"metric": float (lower is better), ...}; nets are in eval mode during it.
    :param provenance: stored in every checkpoint (seed, command, data fingerprints, ...).
    :param init: a checkpoint (of this stage, or merged) or a model bundle folder whose weights start a new
        run: fine-tuning with a fresh schedule and optimizer. Ignored when resuming (the run's own last.pt has
        the weights).
    """
    from tqdm import tqdm

    run_dir.mkdir(parents=True, exist_ok=True)
    start_epoch, best = 0, math.inf
    if resume:
        ckpt = load_checkpoint(run_dir / LAST)
        if ckpt.get("stage") != stage or ckpt.get("config") != config_name:
            raise ValueError(f"{run_dir / LAST} is a {ckpt.get('stage')!r}/{ckpt.get('config')!r} run, not "
                             f"{stage!r}/{config_name!r}")
        before = ckpt.get("provenance", {})
        if before.get("input_hw", provenance.get("input_hw")) != provenance.get("input_hw"):
            raise ValueError(f"{run_dir / LAST} was trained at input {before['input_hw']}, not "
                             f"{provenance.get('input_hw')}: resume with the same --detector-input")
        if before.get("input_sizes", provenance.get("input_sizes")) != provenance.get("input_sizes"):
            raise ValueError(f"{run_dir / LAST} was trained at input sizes {before['input_sizes']}, not "
                             f"{provenance.get('input_sizes')}: resume with the same --detector-input-sizes")
        for k, net in nets.items():
            net.load_state_dict(ckpt[k])
        optimizer.load_state_dict(ckpt["optimizer"])
        start_epoch, best = int(ckpt["epoch"]), float(ckpt["best_metric"])
        # a resumed run may go on longer than first planned (a larger --epochs): keep what came before
        earlier = [*before.get("earlier_runs", []),
                   {"command": before.get("command", ""), "epochs": before.get("epochs"), "stopped_at_epoch": start_epoch}]
        provenance = {**provenance, "earlier_runs": earlier}
        log.info("resuming %s at epoch %d (best metric so far %.4g)", run_dir, start_epoch, best)
    elif init is not None:
        provenance = {**provenance, "init": load_init_weights(init, nets)}
    if n_train < 1:
        raise ValueError("no training samples")
    provenance = {**provenance, "freeze_bn_stats": s.freeze_bn_stats}
    t_start = time.monotonic()
    entry: dict = {}
    for epoch in range(start_epoch, s.epochs):
        t0 = time.monotonic()
        rng = np.random.default_rng((s.seed, epoch))
        torch.manual_seed(s.seed * 100003 + epoch)
        for net in nets.values():
            net.train()
            if s.freeze_bn_stats:
                keep_bn_stats(net)
        batches = _batches(n_train, s.batch, rng)
        sums: dict[str, float] = {}
        stopped = False
        bar = tqdm(batches, desc=f"{stage} epoch {epoch + 1}/{s.epochs}", unit="batch", file=sys.stderr,
                   disable=not progress, leave=False)
        n_done = 0
        for k, idx in enumerate(bar):
            lr = lr_at(s, epoch + k / len(batches))
            for g in optimizer.param_groups:
                g["lr"] = lr * g.get("lr_mult", 1.0)
            loss, parts = step(idx, rng)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"{stage} loss became {float(loss)} at epoch {epoch + 1}, batch {k}; "
                                         "lower --lr or check the data")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            params = [p for net in nets.values() for p in net.parameters()]
            torch.nn.utils.clip_grad_norm_(params, s.grad_clip)
            optimizer.step()
            n_done += 1
            parts = {"loss": float(loss.detach()), **parts}
            for name, v in parts.items():
                sums[name] = sums.get(name, 0.0) + float(v)
            bar.set_postfix(loss=f"{sums['loss'] / n_done:.4f}", lr=f"{lr:.2e}")
            if s.max_minutes and time.monotonic() - t_start > 60 * s.max_minutes:
                stopped = True
                break
        bar.close()
        for net in nets.values():
            net.eval()
        with torch.no_grad():
            val = validate()
        completed = epoch if stopped else epoch + 1
        entry = {"epoch": epoch + 1, "completed": not stopped, "batches": n_done,
                 **{f"train_{k}": v / max(n_done, 1) for k, v in sums.items()},
                 **{f"val_{k}": v for k, v in val.items()}, "lr": lr_at(s, epoch + n_done / len(batches)),
                 "seconds": round(time.monotonic() - t0, 2)}
        with open(run_dir / LOG, "a", encoding="utf-8") as f:
            f.write(json.dumps(entry) + "\n")
        log.info("%s epoch %d: %s", stage, epoch + 1,
                 ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in entry.items()))
        payload = {"config": config_name, **{k: contiguous_state(net) for k, net in nets.items()},
                   "format": CKPT_FORMAT, "format_version": 1, "stage": stage, "epoch": completed,
                   "epochs": s.epochs, "val": val, "optimizer": optimizer.state_dict(),
                   "provenance": provenance}
        improved = val["metric"] < best
        if improved and not stopped:
            best = float(val["metric"])
        payload["best_metric"] = best
        save_checkpoint(run_dir / LAST, payload)
        if improved and not stopped:
            save_checkpoint(run_dir / BEST, payload)
        if stopped:
            log.info("stopped after %.1f minutes (--max-minutes); resume with --resume", s.max_minutes)
            break
    return entry
