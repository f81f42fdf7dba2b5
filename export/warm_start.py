"""Start a network of one config from the trained weights of another (e.g. ``edge2`` from the shipped ``edge``
bundle): every parameter and buffer whose name and shape agree is copied; a fusion attention's position
embedding is resized bilinearly to the new token grid; a narrower layer4 / PSP head of the same layout takes the
wider one's most important channels (`channel_prune`); everything else keeps its fresh initialisation.

``edge`` -> ``edge2`` copies both ResNet18 backbones (layer3/4 lose their dilation but keep their kernels), the
PSP stages and bottleneck, the attention and the whole pose network; new are the stride-8 output convs
(`final`) of the two branches.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .channel_prune import prune_plan, slice_tensor
from .config import get_config
from .fusion import build_fusion
from .pose import build_pose

__all__ = ["transfer_state", "init_config", "warm_start"]

log = logging.getLogger(__name__)


def _resize_tokens(pos: torch.Tensor, n_new: int) -> torch.Tensor | None:
    """(1, n, d) position embedding of a square token grid -> (1, n_new, d), or None when a grid is not square."""
    n, d = pos.shape[1], pos.shape[2]
    s_old, s_new = math.isqrt(n), math.isqrt(n_new)
    if s_old * s_old != n or s_new * s_new != n_new:
        return None
    grid = pos.reshape(1, s_old, s_old, d).permute(0, 3, 1, 2)
    grid = F.interpolate(grid, size=(s_new, s_new), mode="bilinear", align_corners=False)
    return grid.permute(0, 2, 3, 1).reshape(1, n_new, d)


def transfer_state(source: dict[str, torch.Tensor], net: nn.Module) -> dict:
    """Copy `source` entries into `net` where name and shape agree (position embeddings: resized; the layers of
    a narrower ResNet18+PSP branch: their most important channels).

    :return: {"copied": count, "resized": [names], "pruned": [names], "new": [names of `net` left as initialised]}.
    """
    target = net.state_dict()
    plan = prune_plan(source, target)
    copied, resized, pruned, new = 0, [], [], []
    for name, value in target.items():
        src = source.get(name)
        if src is not None and src.shape == value.shape:
            target[name] = src.to(value.dtype).clone()
            copied += 1
        elif src is not None and name in plan and (cut := slice_tensor(src, plan[name])).shape == value.shape:
            target[name] = cut.to(value.dtype).clone()
            pruned.append(name)
        elif src is not None and name.endswith("pos") and src.dim() == 3 and value.dim() == 3 \
                and (r := _resize_tokens(src.float(), value.shape[1])) is not None and r.shape == value.shape:
            target[name] = r.to(value.dtype)
            resized.append(name)
        else:
            new.append(name)
    net.load_state_dict(target)
    return {"copied": copied, "resized": resized, "pruned": pruned, "new": new}


def init_config(path: str | Path) -> str:
    """The config name of a training checkpoint or a bundle folder. :raises ValueError: neither."""
    path = Path(path)
    if path.is_dir():
        from pallet6d.runtime.bundle import load_bundle
        return load_bundle(path).config
    from .train_loop import load_checkpoint
    name = load_checkpoint(path).get("config")
    if not isinstance(name, str):
        raise ValueError(f"{path}: the checkpoint does not say its config")
    return name


def warm_start(path: str | Path, nets: dict[str, nn.Module]) -> dict:
    """Load `nets` ("fusion", "pose") from a checkpoint or bundle of another config, by `transfer_state`.

    :return: what to record: the source's own load record and, per net, what was copied and what is new.
    """
    from .train_loop import load_init_weights

    src_cfg = get_config(init_config(path))
    builders = {"fusion": lambda: build_fusion(src_cfg.fusion),
                "pose": lambda: build_pose(src_cfg.pose, src_cfg.fusion.feature_dim)}
    unknown = set(nets) - set(builders)
    if unknown:
        raise ValueError(f"warm start covers the fusion and pose networks, not {sorted(unknown)}")
    source = {k: builders[k]() for k in nets}
    record = {"source": load_init_weights(path, source), "source_config": src_cfg.name, "transfer": {}}
    for k, net in nets.items():
        record["transfer"][k] = transfer_state(source[k].state_dict(), net)
        t = record["transfer"][k]
        log.info("%s: %d tensors from %s (%s), %d resized, %d channel-pruned, %d new", k, t["copied"], path,
                 src_cfg.name, len(t["resized"]), len(t["pruned"]), len(t["new"]))
    return record
