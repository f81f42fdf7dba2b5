"""A detector that reports the pallet type: type labels through the training samples, their cache and the
augmentation, one class per type in training and export, and a one-class detector widened into a typed one."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pallet6d.export.config import get_config
from pallet6d.export.detector import build_detector, widen_class_outputs
from pallet6d.export.export_inputs import ExportError, trained_classes
from pallet6d.export.pallet_types import class_ids_for_types
from pallet6d.export.train_cli import detector_classes
from pallet6d.export.train_data import (NO_AUGMENT, AugmentConfig, DetectorSamples, build_detector_samples,
                                        flip_horizontal, load_or_build, place_in_window)
from pallet6d.export.train_detector import (DetectorData, DetectorTrainer, balanced_type_accuracy,
                                           detector_class_of_type)
from pallet6d.sim.pallets import PALLET_MODELS

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _samples(types_per_frame):
    images = [np.zeros((40, 60, 3), np.uint8) for _ in types_per_frame]
    boxes = [np.tile(np.array([[5, 5, 30, 20]], np.float32), (len(t), 1)) for t in types_per_frame]
    return DetectorSamples(_obj(images), _obj(boxes), np.arange(len(images)), _obj([np.array(t, np.int64)
                                                                                    for t in types_per_frame]))


def _obj(items):
    out = np.empty(len(items), dtype=object)
    for i, a in enumerate(items):
        out[i] = a
    return out


def test_samples_default_to_unknown_types_and_check_their_count():
    s = DetectorSamples(_obj([np.zeros((4, 4, 3), np.uint8)]), _obj([np.zeros((2, 4), np.float32)]), np.arange(1))
    assert s.types[0].tolist() == [-1, -1]
    with pytest.raises(ValueError, match="one pallet type per box"):
        DetectorSamples(s.images, s.boxes, s.frame, _obj([np.zeros(3, np.int64)]))
    both = DetectorSamples.concat([_samples([[0, 2]]), _samples([[], [5]])])
    assert [t.tolist() for t in both.types] == [[0, 2], [], [5]]
    assert [t.tolist() for t in both.take(np.array([2, 0])).types] == [[5], [0, 2]]


def test_simulated_frames_carry_their_types_through_the_cache(sim_bop_dataset, tmp_path):
    from pallet6d.runtime.bop import BopDataset

    built = build_detector_samples(sim_bop_dataset, 320)
    ds = BopDataset(sim_bop_dataset)
    names = {k: v["name"] for k, v in ds.models_info.items()}
    for i, t in enumerate(built.types):
        assert len(t) == len(built.boxes[i])
    counted = [PALLET_MODELS[int(t)] for ts in built.types for t in ts]
    assert counted and set(counted) <= set(names.values())
    first, _ = load_or_build("detector", sim_bop_dataset, {"max_side": 320}, tmp_path,
                             lambda: build_detector_samples(sim_bop_dataset, 320))
    again, _ = load_or_build("detector", sim_bop_dataset, {"max_side": 320}, tmp_path,
                             lambda: pytest.fail("the cache should be read"))
    assert [t.tolist() for t in again.types] == [t.tolist() for t in first.types] == \
        [t.tolist() for t in built.types]


def test_augmentation_carries_a_class_column_with_its_box():
    img = np.zeros((100, 200, 3), np.uint8)
    boxes = np.array([[10, 10, 60, 50, 3], [150, 60, 190, 90, 7]], np.float32)
    flipped_img, flipped = flip_horizontal(img, boxes)
    assert flipped.shape == (2, 5) and flipped[:, 4].tolist() == [3, 7]
    np.testing.assert_allclose(flipped[0, :4], [140, 10, 190, 50])
    rng = np.random.default_rng(0)
    out, moved = place_in_window(img, boxes, (64, 128), rng, 0.0, 1.0, 0.0)
    assert moved.shape == (2, 5) and moved[:, 4].tolist() == [3, 7]
    np.testing.assert_allclose(moved[:, :4], boxes[:, :4] * 0.64)
    # a box pushed out of the window leaves with its class
    _, kept = place_in_window(img, boxes, (64, 128), np.random.default_rng(1), 0.0, 3.0, 0.5)
    assert set(kept[:, 4].tolist()) <= {3.0, 7.0}
    assert place_in_window(img, np.zeros((0, 4)), (64, 128), rng, 0.0, 1.0, 0.0)[1].shape == (0, 4)


@pytest.mark.parametrize("right, found, expected", [
    ([90, 0, 0], [90, 5, 5], (1 / 3, 0.0)),          # every pallet called an EPAL: 90 % of the boxes, 1 of 3 types
    ([9, 4, 0], [10, 5, 0], ((0.9 + 0.8) / 2, 0.8)),  # a type never found does not count
])
def test_type_accuracy_is_balanced_over_the_types(right, found, expected):
    assert balanced_type_accuracy(np.array(right), np.array(found)) == pytest.approx(expected)


def test_type_accuracy_needs_a_typed_box():
    with pytest.raises(ValueError, match="no typed box"):
        balanced_type_accuracy(np.zeros(3), np.zeros(3))


def test_class_of_each_type():
    data = DetectorData(_samples([[0, 1], [1]]), np.arange(2), np.arange(2), [])
    one = detector_class_of_type(("pallet",), data)
    assert one.shape == (len(PALLET_MODELS) + 1,) and not one.any()
    typed = detector_class_of_type(("gma", "epal"), data)
    assert typed[PALLET_MODELS.index("epal")] == 1 and typed[PALLET_MODELS.index("gma")] == 0
    assert typed[-1] == -1 and typed[PALLET_MODELS.index("eur6")] == -1
    with pytest.raises(ValueError, match=r"\['gma'\]"):
        detector_class_of_type(("epal", "eur6"), data)
    real = DetectorData(_samples([[0], [1]]), np.arange(2), np.arange(2), [], real=np.array([False, True]))
    assert detector_class_of_type(("epal", "eur6"), real)[0] == 0   # a real photograph's types are not asked


def test_typed_detector_targets_are_the_types_and_real_boxes_any_type():
    cfg = get_config("tiny")
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, classes=("gma", "epal")))
    samples = _samples([[PALLET_MODELS.index("epal")], [PALLET_MODELS.index("gma")], [-1]])
    data = DetectorData(samples, np.arange(3), np.arange(3), [], real=np.array([False, False, True]))
    trainer = DetectorTrainer(cfg, data, NO_AUGMENT)
    _, targets = trainer.batch(np.arange(3), None)
    assert [t[:, 0].tolist() for t in targets] == [[1.0], [0.0], [-1.0]]
    _, augmented = trainer.batch(np.arange(3), np.random.default_rng(0))
    assert all(set(t[:, 0].tolist()) <= {c} for t, c in zip(augmented, (1.0, 0.0, -1.0)))
    loss, _ = trainer.step(np.arange(2), np.random.default_rng(0))
    assert torch.isfinite(loss)
    v = trainer.validate(score_threshold=0.0, iou=0.0)   # an untrained detector: every box found, types by chance
    assert v["n_typed"] == 2 and v["type_accuracy"] in (0.0, 0.5, 1.0)
    with_aug = DetectorTrainer(cfg, data, AugmentConfig())
    assert with_aug.class_of_type[PALLET_MODELS.index("epal")] == 1


def test_a_one_class_detector_starts_every_class_of_a_typed_one():
    cfg = get_config("tiny").detector
    torch.manual_seed(0)
    one = build_detector(cfg)
    typed = build_detector(dataclasses.replace(cfg, classes=("epal", "gma", "eur6")))
    with pytest.raises(RuntimeError):
        typed.load_state_dict(one.state_dict())
    typed.load_state_dict(widen_class_outputs(one.state_dict(), typed))
    one.eval()
    typed.eval()
    x = torch.rand(1, 3, *cfg.input_hw)
    with torch.no_grad():
        a, b = one(x), typed(x)
    for k in range(3):   # every type scores as the one class did; boxes are unchanged
        torch.testing.assert_close(b[:, 4 + k], a[:, 4])
    torch.testing.assert_close(b[:, :4], a[:, :4])


def test_classes_are_matched_to_types_by_name_and_read_from_the_checkpoint():
    assert class_ids_for_types(("epal", "gma"), ("gma", "eur6", "epal"), external=False) == (2, 0)
    assert class_ids_for_types(("epal", "gma"), ("pallet",), external=False) == (0, 0)
    assert class_ids_for_types(("epal", "gma"), ("a", "b"), external=False) == (0, 1)
    assert trained_classes({"provenance": {"stage": "detector", "classes": ["epal", "gma"]}}) == ("epal", "gma")
    assert trained_classes({"provenance": {"detector": {"classes": ["pallet"]}}}) == ("pallet",)
    assert trained_classes({"provenance": {"stage": "detector"}}) is None
    with pytest.raises(ExportError, match="classes"):
        trained_classes({"provenance": {"stage": "detector", "classes": []}})


def test_detector_classes_option(sim_bop_dataset):
    from pallet6d.runtime.bop import BopDataset

    names = {v["name"] for v in BopDataset(sim_bop_dataset).models_info.values()}
    found = detector_classes("types", [sim_bop_dataset])
    assert set(found) == names & set(PALLET_MODELS) and list(found) == [n for n in PALLET_MODELS if n in found]
    assert detector_classes("gma, epal", []) == ("gma", "epal")
    for bad in ("epal,chep", "", "epal,epal"):
        with pytest.raises(ValueError, match="detector-classes"):
            detector_classes(bad, [])


def test_class_outputs_learn_at_their_own_rate(sim_bop_dataset, tmp_path):
    from pallet6d.export.train_detector import class_output_names, train_detector
    from pallet6d.export.train_loop import LoopSettings, load_checkpoint

    cfg = get_config("tiny")
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, classes=detector_classes("types", [sim_bop_dataset])))
    names = class_output_names(build_detector(cfg.detector))
    assert names == {f"head.cls.{k}.2.{p}" for k in range(3) for p in ("weight", "bias")}
    settings = LoopSettings(epochs=1, batch=2, lr=1e-5, seed=0)
    moved = {}
    for mult in (1.0, 1000.0):
        torch.manual_seed(0)                          # train_detector's own seeding: the same start
        start = build_detector(cfg.detector).state_dict()
        train_detector(cfg, [sim_bop_dataset], tmp_path / f"run{mult}", settings, aug=NO_AUGMENT, progress=False,
                       class_lr_mult=mult, cache_dir=tmp_path / "cache")
        end = load_checkpoint(tmp_path / f"run{mult}" / "last.pt")["detector"]
        moved[mult] = {n: float((end[n].float() - start[n].float()).abs().max())
                       for n in (*names, "head.cls.0.0.conv.weight")}
        assert load_checkpoint(tmp_path / f"run{mult}" / "last.pt")["provenance"]["class_lr_mult"] == mult
    # the class outputs move far more at 1000x; the rest of the network about as much
    assert all(moved[1000.0][n] > 20 * moved[1.0][n] for n in names)
    assert moved[1000.0]["head.cls.0.0.conv.weight"] < 20 * moved[1.0]["head.cls.0.0.conv.weight"] + 1e-6
    with pytest.raises(ValueError, match="class_lr_mult"):
        train_detector(cfg, [sim_bop_dataset], tmp_path / "bad", settings, progress=False, class_lr_mult=0.0)
