"""The most important channels of a wider ResNet18+PSP branch, to start a narrower one of the same layout.

A narrower layer4 / PSP bottleneck trained from scratch must relearn what the wider one knows; started from the
wider one's most important channels (network slimming: a BatchNorm'd channel's scale says how much it carries)
it starts close to it, and distillation (`pallet6d train pose --distill`) closes the rest.

Importance from the weights alone, no data: a channel after a BatchNorm carries about sqrt(gamma^2 + beta^2) (its
output's RMS where the input is normalised; for a bundle's folded BatchNorms, which `bundle_weights` gives the
input's own statistics, exactly its output's RMS), a sum of such channels (a residual) the root of their squares'
sum; what reads it weighs it by the norm of its weights on that channel. Channels without a BatchNorm (the PSP
stages, the bottleneck) are weighed by the norms of the weights that write and that read them.

`branch_plan` says, for every layer4, PSP and output tensor of one branch, which indices of each dimension to keep;
`slice_tensor` applies it. Kept channels stay in their original order.
"""
from __future__ import annotations

import torch

__all__ = ["branch_plan", "prune_plan", "slice_tensor"]

_BN = ("weight", "bias", "running_mean", "running_var")
Plan = dict[str, tuple[torch.Tensor | None, ...]]


def _bn_rms(sd: dict[str, torch.Tensor], name: str) -> torch.Tensor:
    """(C,) sqrt(gamma^2 + beta^2) of the BatchNorm `name`."""
    return torch.sqrt(sd[name + ".weight"].float() ** 2 + sd[name + ".bias"].float() ** 2)


def _in_norms(w: torch.Tensor) -> torch.Tensor:
    """(C_in,) norm of a conv weight (C_out, C_in, ...) over everything but its input channel."""
    return w.float().transpose(0, 1).reshape(w.shape[1], -1).norm(dim=1)


def _out_norms(w: torch.Tensor) -> torch.Tensor:
    """(C_out,) norm of a conv weight over everything but its output channel."""
    return w.float().reshape(w.shape[0], -1).norm(dim=1)


def _top(importance: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the k largest entries, ascending (ties: the lower index)."""
    return torch.sort(torch.argsort(-importance, stable=True)[:k]).values


def branch_plan(source: dict[str, torch.Tensor], target: dict[str, torch.Tensor], prefix: str) -> Plan:
    """Which channels of the branch at `prefix` ("rgb." in a fusion network) `target`'s narrower layer4, PSP
    stages, bottleneck and output conv take from `source`'s.

    :param source, target: state dicts of the wider and the narrower network (same layout: `target`'s layer4
        starts with a projection shortcut where `source`'s does, the same PSP bin count, no upsampling stages).
    :return: {tensor name: one index tensor (or None: all) per dimension}; empty when the layouts differ.
    """
    l4 = prefix + "backbone.layer4."
    names = [l4 + "0.conv1.weight", l4 + "0.down.0.weight", prefix + "bottleneck.0.weight", prefix + "final.weight"]
    if any(n not in source or n not in target for n in names) or prefix + "up.1.weight" in source:
        return {}
    c4, w4 = source[l4 + "0.conv1.weight"].shape[0], target[l4 + "0.conv1.weight"].shape[0]
    c_psp, w_psp = source[prefix + "bottleneck.0.weight"].shape[0], target[prefix + "bottleneck.0.weight"].shape[0]
    bottleneck = source[prefix + "bottleneck.0.weight"].float()
    n_stages = bottleneck.shape[1] // c4 - 1
    if w4 > c4 or w_psp > c_psp or target[prefix + "bottleneck.0.weight"].shape[1] != w4 * (n_stages + 1):
        return {}
    stages = [source[f"{prefix}stages.{i}.weight"] for i in range(n_stages)]
    reads = _in_norms(bottleneck)                                  # (c4 * (n_stages + 1),) per concatenated input

    # layer4's residual channels: both blocks' sums, weighed by what the PSP head reads of them
    block0 = torch.sqrt(_bn_rms(source, l4 + "0.bn2") ** 2 + _bn_rms(source, l4 + "0.down.1") ** 2)
    out = torch.sqrt(_bn_rms(source, l4 + "1.bn2") ** 2 + block0 ** 2)
    residual = _top(out * (reads[:c4] + sum(_in_norms(s) for s in stages)), w4)
    inner = [_top(_bn_rms(source, f"{l4}{b}.bn1") * _in_norms(source[f"{l4}{b}.conv2.weight"]), w4) for b in (0, 1)]
    kept_stages = [_top(_out_norms(s) * reads[(i + 1) * c4:(i + 2) * c4], w4) for i, s in enumerate(stages)]
    psp = _top((_out_norms(bottleneck) + source[prefix + "bottleneck.0.bias"].float().abs())
               * _in_norms(source[prefix + "final.weight"]), w_psp)

    plan: Plan = {}
    for b, conv1_in in ((0, None), (1, residual)):
        plan[f"{l4}{b}.conv1.weight"] = (inner[b], conv1_in)
        plan[f"{l4}{b}.conv2.weight"] = (residual, inner[b])
        for f in _BN:
            plan[f"{l4}{b}.bn1.{f}"] = (inner[b],)
            plan[f"{l4}{b}.bn2.{f}"] = (residual,)
    plan[l4 + "0.down.0.weight"] = (residual, None)
    for f in _BN:
        plan[f"{l4}0.down.1.{f}"] = (residual,)
    for i, kept in enumerate(kept_stages):
        plan[f"{prefix}stages.{i}.weight"] = (kept, residual)
    concat = torch.cat([residual] + [(i + 1) * c4 + kept for i, kept in enumerate(kept_stages)])
    plan[prefix + "bottleneck.0.weight"] = (psp, concat)
    plan[prefix + "bottleneck.0.bias"] = (psp,)
    plan[prefix + "final.weight"] = (None, psp)
    return plan


def prune_plan(source: dict[str, torch.Tensor], target: dict[str, torch.Tensor]) -> Plan:
    """`branch_plan` for every ResNet18+PSP branch of a network (found by their layer4)."""
    suffix = "backbone.layer4.0.conv1.weight"
    plan: Plan = {}
    for name in source:
        if name.endswith(suffix):
            plan.update(branch_plan(source, target, name[:-len(suffix)]))
    return plan


def slice_tensor(value: torch.Tensor, index: tuple[torch.Tensor | None, ...]) -> torch.Tensor:
    """`value` with each leading dimension cut to its index tensor (None: whole)."""
    for dim, idx in enumerate(index):
        if idx is not None:
            value = value.index_select(dim, idx)
    return value
