"""Starting a narrower ResNet18+PSP fusion network from a wider one's most important channels."""
from __future__ import annotations

import dataclasses

import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.channel_prune import prune_plan  # noqa: E402
from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.fusion import build_fusion  # noqa: E402
from pallet6d.export.warm_start import transfer_state  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")

_TINY = get_config("tiny").fusion
# tiny widths in the sampled stride-8 layout; the wide network's layer4 and PSP head are twice the narrow one's
WIDE = dataclasses.replace(_TINY, up_channels=(), sample_stride=8, attention_stride=8, resnet_widths=(8, 8, 16, 32),
                           psp_out=32)
NARROW = dataclasses.replace(WIDE, resnet_widths=(8, 8, 16, 16), psp_out=16, project_layer4=True)


def _inputs(cfg, b: int = 3):
    g = torch.Generator().manual_seed(1)
    h, w = cfg.crop_hw
    return (torch.randn(b, 3, h, w, generator=g), torch.randn(b, 1, h, w, generator=g),
            torch.randint(0, h * w, (b, 20), generator=g))


def _silence(net, keep: dict[str, torch.Tensor]) -> None:
    """Make every channel of `net`'s layer4 / PSP head outside `keep` carry nothing, in both branches."""
    sd = net.state_dict()

    def zero(name: str, kept: torch.Tensor, dim: int = 0) -> None:
        drop = torch.ones(sd[name].shape[dim], dtype=torch.bool)
        drop[kept] = False
        sd[name].index_fill_(dim, drop.nonzero().flatten(), 0.0)

    for p in ("rgb.", "depth."):
        l4 = p + "backbone.layer4."
        for bn in ("0.bn2", "0.down.1", "1.bn2"):
            zero(f"{l4}{bn}.weight", keep["residual"])
            zero(f"{l4}{bn}.bias", keep["residual"])
        for b in (0, 1):
            zero(f"{l4}{b}.bn1.weight", keep[f"inner{b}"])
            zero(f"{l4}{b}.bn1.bias", keep[f"inner{b}"])
        for i in range(len(WIDE.psp_sizes)):
            zero(f"{p}stages.{i}.weight", keep["stage"])
        zero(p + "bottleneck.0.weight", keep["psp"])
        zero(p + "bottleneck.0.bias", keep["psp"])
    net.load_state_dict(sd)


def test_a_wide_network_whose_other_channels_are_silent_is_copied_exactly():
    torch.manual_seed(0)
    wide, narrow = build_fusion(WIDE), build_fusion(NARROW)
    g = torch.Generator().manual_seed(2)
    keep = {k: torch.randperm(32, generator=g)[:16].sort().values for k in ("residual", "inner0", "inner1", "stage")}
    keep["psp"] = torch.randperm(32, generator=g)[:16].sort().values
    with torch.no_grad():                          # BatchNorm biases away from zero so that every kept channel counts
        for m in wide.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.bias.uniform_(0.1, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    _silence(wide, keep)

    record = transfer_state(wide.state_dict(), narrow)

    assert record["new"] == [] and len(record["pruned"]) > 0
    plan = prune_plan(wide.state_dict(), narrow.state_dict())
    torch.testing.assert_close(plan["rgb.backbone.layer4.0.bn2.weight"][0], keep["residual"])
    torch.testing.assert_close(plan["depth.bottleneck.0.bias"][0], keep["psp"])
    wide.eval(), narrow.eval()
    with torch.no_grad():
        torch.testing.assert_close(narrow(*_inputs(WIDE)), wide(*_inputs(WIDE)), rtol=1e-5, atol=1e-5)


def test_the_kept_channels_are_the_ones_that_carry_most():
    torch.manual_seed(0)
    wide, narrow = build_fusion(WIDE), build_fusion(NARROW)
    sd = wide.state_dict()
    loud = torch.arange(0, 32, 2)                   # the even residual channels ten times as large as the odd ones
    for bn in ("0.bn2", "0.down.1", "1.bn2"):
        for f in ("weight", "bias"):
            sd[f"rgb.backbone.layer4.{bn}.{f}"] = torch.full((32,), 0.1).index_fill_(0, loud, 1.0)
    plan = prune_plan(sd, narrow.state_dict())
    torch.testing.assert_close(plan["rgb.backbone.layer4.1.conv1.weight"][1], loud)
    torch.testing.assert_close(plan["rgb.stages.0.weight"][1], loud)


def test_equal_widths_copy_everything_and_other_layouts_are_left_to_train():
    torch.manual_seed(0)
    wide = build_fusion(WIDE)
    same = transfer_state(wide.state_dict(), build_fusion(WIDE))
    assert same["pruned"] == [] and same["new"] == []
    # layer4 as wide as layer3 without a projection shortcut: no place for the wide one's projection
    identity = transfer_state(wide.state_dict(), build_fusion(dataclasses.replace(NARROW, project_layer4=False)))
    assert identity["pruned"] == []
    assert "rgb.backbone.layer4.0.conv2.weight" in identity["new"] and "rgb.final.weight" in identity["new"]
