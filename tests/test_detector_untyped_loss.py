"""DetectorLoss with untyped boxes (class -1, real photographs): box and "is a pallet" only."""
import dataclasses

import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.config import get_config  # noqa: E402
from pallet6d.export.detector import build_detector  # noqa: E402
from pallet6d.export.losses import DetectorLoss  # noqa: E402

TARGET = [[0.0, 10.0, 8.0, 60.0, 40.0], [0.0, 70.0, 20.0, 120.0, 60.0]]


def _raw(classes, **detector):
    torch.manual_seed(0)
    cfg = dataclasses.replace(get_config("tiny").detector, classes=classes, **detector)
    det = build_detector(cfg).eval()
    with torch.no_grad():
        raw = det.forward_raw(torch.rand(2, 3, *cfg.input_hw))
        for r in raw:     # types that score differently (random init gives them equal scores)
            r[:, -len(classes):] += torch.linspace(0.0, 2.0, len(classes)).view(1, -1, 1, 1) * torch.randn(r.shape[2:])
    return det, raw


def _targets(cls):
    t = torch.tensor(TARGET)
    t[:, 0] = cls
    return [t, t[:1].clone()]


def test_untyped_equals_typed_with_one_class():
    det, raw = _raw(("pallet",))
    loss = DetectorLoss(det)
    typed, parts_t = loss(raw, _targets(0))
    untyped, parts_u = loss(raw, _targets(-1))
    assert float(typed) == pytest.approx(float(untyped), rel=1e-6)
    assert parts_t["fg"] == parts_u["fg"] > 0


def _swap_classes(raw, nc):
    return [torch.cat([r[:, :-nc], r[:, -nc:].flip(1)], 1) for r in raw]


def test_untyped_loss_does_not_care_which_type_scores():
    det, raw = _raw(("epal", "gma"))
    loss = DetectorLoss(det)
    swapped = _swap_classes(raw, 2)
    u, _ = loss(raw, _targets(-1))
    u_swapped, _ = loss(swapped, _targets(-1))
    assert float(u) == pytest.approx(float(u_swapped), rel=1e-5)
    t, _ = loss(raw, _targets(0))
    t_swapped, _ = loss(swapped, _targets(0))
    assert float(t) != pytest.approx(float(t_swapped), rel=1e-3)


def test_untyped_box_leaves_the_other_types_free():
    det, raw = _raw(("epal", "gma"))
    raw = [r.clone().requires_grad_(True) for r in raw]
    loss, parts = DetectorLoss(det)(raw, _targets(-1))
    loss.backward()
    # on every anchor exactly the class logits that carry a loss get a gradient: on background anchors both
    # types (pushed to 0), on assigned anchors only the highest-scoring type
    grads = torch.cat([r.grad[:, -2:].flatten(2) for r in raw], 2)            # (B, 2, A)
    logits = torch.cat([r[:, -2:].detach().flatten(2) for r in raw], 2)
    with_grad = (grads != 0).sum(1)                                           # (B, A)
    assert (with_grad == 1).sum() == parts["fg"] > 0
    one = with_grad == 1
    top = logits.argmax(1)
    assert torch.all(((grads != 0).float().argmax(1) == top)[one])


def test_a_large_box_goes_to_anchors_that_can_reach_its_edges():
    """A level whose class scores fell to nothing is never ranked first by TAL; the reach rule still gives it the
    boxes the finer levels cannot draw (their distance bins span reg_max - 1 strides)."""
    from pallet6d.export.detector import STRIDES, make_anchors

    det, raw = _raw(("pallet",), reg_max=4)                    # reach 3 strides: 24 / 48 / 96 px on a 64 x 128 image
    h, w = det.cfg.input_hw
    coarse = [r.clone() for r in raw]
    coarse[-1][:, -1] = -30.0                                    # the coarsest level's scores dead
    scores = torch.cat([r[:, -1:].flatten(2) for r in coarse], 2).transpose(1, 2).sigmoid()[:1]
    anchors, strides = make_anchors([tuple(r.shape[2:]) for r in raw])
    loss = DetectorLoss(det)

    def levels(target, with_reach=True):
        tb = torch.tensor([target])
        drawn = tb[:, 1:].expand(1, len(anchors), 4)              # every anchor draws the box: TAL ranks by score
        _, _, fg, _ = loss._assign(scores, drawn, anchors * strides, tb[None, :, 0],
                                   tb[None, :, 1:], torch.ones(1, 1, dtype=torch.bool),
                                   strides if with_reach else None)
        return set(strides[fg[0], 0].tolist())

    big = [0.0, 0.0, 0.0, float(w), float(h)]                    # half-width 64 px: only the coarsest level reaches
    assert levels(big) == {float(STRIDES[-1])}
    assert float(STRIDES[0]) in levels([0.0, 10.0, 8.0, 30.0, 24.0])       # small: every level reaches, TAL ranks
    # without the rule the dead level is passed over and finer anchors take the large box
    assert float(STRIDES[-1]) not in levels(big, with_reach=False)
