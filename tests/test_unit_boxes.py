"""Whole-pallet boxes found by colour inside loaded-unit boxes (`pallet6d.export.unit_boxes`)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pallet6d.export.real_data import Source, import_sources, load_records
from pallet6d.export.unit_boxes import PALLET_COLOURS, colour_mask, pallet_boxes_in_units

RED, TAN, GREY = (200, 30, 40), (190, 150, 100), (120, 120, 120)


def _unit(img, x1, y1, x2, y2, pallet_h, logos=True):
    """A loaded unit drawn into `img`: tan cartons on a red pallet `pallet_h` px tall, with two pockets; small red
    logos on the cartons."""
    img[y1:y2 - pallet_h, x1:x2] = TAN
    img[y2 - pallet_h:y2, x1:x2] = RED
    w = x2 - x1
    img[y2 - pallet_h // 2:y2 - 2, x1 + w // 6:x1 + w // 3] = (20, 20, 20)
    img[y2 - pallet_h // 2:y2 - 2, x2 - w // 3:x2 - w // 6] = (20, 20, 20)
    if logos:
        for cy in range(y1 + 10, y2 - pallet_h - 10, 25):
            img[cy:cy + 4, x1 + w // 2:x1 + w // 2 + 4] = RED


@pytest.fixture
def scene():
    img = np.full((240, 400, 3), GREY, np.uint8)
    _unit(img, 40, 60, 160, 200, pallet_h=24)
    _unit(img, 220, 40, 360, 190, pallet_h=30)
    return img


def test_colour_mask_finds_red_and_not_tan(scene):
    mask = colour_mask(scene, PALLET_COLOURS["red"])
    assert mask[190, 100] and mask[185, 300]
    assert not mask[100, 60] and not mask[10, 10]


def test_colour_mask_rejects_non_rgb():
    with pytest.raises(ValueError, match="uint8"):
        colour_mask(np.zeros((4, 4), np.uint8), PALLET_COLOURS["red"])


def test_each_unit_gets_its_pallet_band(scene):
    mask = colour_mask(scene, PALLET_COLOURS["red"])
    # the uploader's boxes are loose by a few pixels around each unit
    units = np.array([[35, 55, 165, 203], [215, 35, 365, 193]], np.float64)
    found = pallet_boxes_in_units(mask, units)
    np.testing.assert_allclose(found[0], [40, 176, 160, 200], atol=1)
    np.testing.assert_allclose(found[1], [220, 160, 360, 190], atol=1)


@pytest.mark.parametrize("case", ["no pallet", "pallet too thin", "pallet only under half the unit", "tiny box"])
def test_implausible_or_missing_pallets_are_none(case):
    img = np.full((240, 400, 3), GREY, np.uint8)
    unit = np.array([[40, 60, 160, 200]], np.float64)
    if case == "no pallet":
        img[60:200, 40:160] = TAN
    elif case == "pallet too thin":
        _unit(img, 40, 60, 160, 200, pallet_h=1, logos=False)
    elif case == "pallet only under half the unit":
        _unit(img, 40, 60, 160, 200, pallet_h=24)
        img[176:200, 40:110] = GREY
    else:
        unit = np.array([[40, 60, 42, 64]], np.float64)
    assert pallet_boxes_in_units(colour_mask(img, PALLET_COLOURS["red"]), unit) == [None]


def test_red_goods_above_the_unit_and_a_neighbours_pallet_are_not_taken(scene):
    img = scene.copy()
    img[0:50, 40:160] = RED                 # red crates stacked behind, reaching into the box's top
    mask = colour_mask(img, PALLET_COLOURS["red"])
    found = pallet_boxes_in_units(mask, np.array([[35, 20, 165, 203]], np.float64))
    np.testing.assert_allclose(found[0], [40, 176, 160, 200], atol=1)
    # a box around the second unit that also covers a sliver of the first unit's pallet
    found = pallet_boxes_in_units(mask, np.array([[150, 35, 365, 193]], np.float64))
    np.testing.assert_allclose(found[0], [220, 160, 360, 190], atol=1)


def test_touching_pallets_of_neighbouring_units_are_split_at_their_boxes():
    img = np.full((240, 400, 3), GREY, np.uint8)
    _unit(img, 40, 60, 120, 200, pallet_h=24)
    _unit(img, 120, 60, 300, 200, pallet_h=24)          # the two pallets touch: one red region, mostly the second's
    mask = colour_mask(img, PALLET_COLOURS["red"])
    found = pallet_boxes_in_units(mask, np.array([[38, 58, 120, 202], [120, 58, 302, 202]], np.float64))
    np.testing.assert_allclose(found[0], [40, 176, 120, 200], atol=1)
    np.testing.assert_allclose(found[1], [120, 176, 300, 200], atol=1)
    # the same region running on into red goods no unit's box holds is not split: its owner is unknown
    img[176:200, 300:380] = RED
    mask = colour_mask(img, PALLET_COLOURS["red"])
    found = pallet_boxes_in_units(mask, np.array([[38, 58, 120, 202], [120, 58, 302, 202]], np.float64))
    assert found[0] is None


def test_import_turns_found_units_into_whole_pallet_photos(tmp_path):
    """A loaded-unit source with a pallet colour: photos whose every unit's pallet is found become whole-pallet
    photos (their unit boxes kept); a photo with a unit whose pallet is hidden keeps its loaded-unit boxes."""
    folder = tmp_path / "raw" / "conveyor" / "test"
    (folder / "images").mkdir(parents=True)
    (folder / "labels").mkdir(parents=True)
    good = np.full((240, 400, 3), GREY, np.uint8)
    _unit(good, 40, 60, 160, 200, pallet_h=24)
    hidden = good.copy()
    hidden[170:200, 40:160] = GREY
    for name, img in (("clip_mp4-0000", good), ("clip_mp4-0030", hidden)):
        cv2.imwrite(str(folder / "images" / f"{name}.png"), img[:, :, ::-1])
        (folder / "labels" / f"{name}.txt").write_text(f"0 {100 / 400} {130 / 240} {128 / 400} {146 / 240}\n")
    src = Source(name="conveyor", repo="someone/repo", commit="0" * 40, folders=("test",), licence="CC BY 4.0",
                 attribution="someone", url="https://example.invalid", pallet_classes=(0,), original_aspect=400 / 240,
                 aspect_known=True, convention="loaded_unit", kinds=("plastic", "loaded"), sequence_rule="video",
                 shows="test", pallet_colour="red")
    out = tmp_path / "real"
    import_sources(tmp_path / "raw", out, (src,), heldout_fraction=0.3)
    recs = {r.stem: r for r in load_records(out)}
    found, kept = recs["clip_mp4-0000"], recs["clip_mp4-0030"]
    assert found.convention == "whole_pallet" and found.boxes_from == "colour"
    np.testing.assert_allclose(found.box_array(), [[40, 176, 160, 200]], atol=1.5)
    np.testing.assert_allclose(found.unit_boxes_xyxy, [[36, 57, 164, 203]], atol=0.5)
    assert kept.convention == "loaded_unit" and kept.boxes_from == "label" and kept.unit_boxes_xyxy == []
    card = json.loads((out / "card.json").read_text())["sources"][0]
    assert card["pallet_colour"] == "red"
    assert sum(c["boxes_by_colour"] for c in card["counts"].values()) == 1
    assert "found by the pallet's colour (red)" in (out / "card.md").read_text()


@pytest.mark.parametrize("convention, colour", [("whole_pallet", "red"), ("loaded_unit", "chartreuse")])
def test_source_refuses_a_pallet_colour_it_cannot_use(convention, colour):
    with pytest.raises(ValueError, match="pallet_colour"):
        Source(name="x", repo="a/b", commit="0" * 40, folders=("f",), licence="CC BY 4.0", attribution="a",
               url="u", pallet_classes=(0,), original_aspect=1.0, aspect_known=True, convention=convention,
               kinds=("plastic",), sequence_rule="video", shows="s", pallet_colour=colour)
