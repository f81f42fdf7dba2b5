"""Pallet-type geometry of a bundle: fork pockets derived from boxes, ICP starts, rigid symmetries."""
import numpy as np
import pytest

from pallet6d.runtime.pallet_geometry import FACES, asymmetric, check_rigid, default_refine_starts, derive_pockets_m
from pallet6d.runtime.refine import MAX_STARTS, offsets_from_starts, start_offsets
from pallet6d.sim.pallets import PALLET_MODELS, ROT_Z_180, get_pallet_model


def _extent(pockets):
    """(2, 3) width of each opening's box per axis."""
    return pockets[:, 1] - pockets[:, 0]


@pytest.mark.parametrize("name, face, width_m, height_m", [
    ("epal", "+x", 0.2275, 0.100),     # short side: between the blocks, floor to stringer board
    ("epal", "+y", 0.3825, 0.100),     # long side: above the bottom boards, up to the top deck
    ("eur3", "-x", 0.3275, 0.100),
    ("gma", "+x", 0.451, 0.089),       # stringer ends: between the stringers, deck to deck
    ("gma", "-y", 0.229, 0.038),       # the stringers' notches
])
def test_pockets_of_the_sim_pallets(name, face, width_m, height_m):
    model = get_pallet_model(name)
    pockets = derive_pockets_m(model.boxes_m)
    assert tuple(pockets) == FACES
    ext = _extent(pockets[face])
    across = 1 if face[1] == "x" else 0
    np.testing.assert_allclose(ext[:, across], width_m, atol=1e-9)
    np.testing.assert_allclose(ext[:, 2], height_m, atol=1e-9)
    # each runs the whole depth of the pallet through the face
    np.testing.assert_allclose(ext[:, 1 - across], model.size_m[1 - across], atol=1e-9)
    # every opening is free of wood: no box overlaps it
    for box in pockets[face]:
        overlap = np.minimum(box[1], model.boxes_m[:, 1]) - np.maximum(box[0], model.boxes_m[:, 0])
        assert not np.any(np.all(overlap > 1e-9, axis=1))


def test_pockets_are_ordered_left_then_right_seen_from_outside():
    p = derive_pockets_m(get_pallet_model("epal").boxes_m)
    centre = lambda face: p[face].mean(axis=1)  # noqa: E731
    assert centre("+x")[0, 1] < centre("+x")[1, 1] and centre("-x")[0, 1] > centre("-x")[1, 1]
    assert centre("+y")[0, 0] > centre("+y")[1, 0] and centre("-y")[0, 0] < centre("-y")[1, 0]
    # a turn by 180 degrees about z maps the +x face's left opening onto the -x face's left one
    np.testing.assert_allclose(np.sort(p["+x"][0] @ ROT_Z_180[:3, :3].T, axis=0), p["-x"][0], atol=1e-12)


@pytest.mark.parametrize("boxes", [
    np.array([[[-0.5, -0.4, -0.1], [0.5, 0.4, 0.1]]]),                           # a solid block: no opening
    np.array([[[-0.5, -0.4, 0.0], [0.5, 0.4, 0.1]], [[-0.5, -0.4, -0.1], [0.5, -0.3, 0.0]]]),  # one opening
])
def test_solid_or_one_sided_shapes_have_no_pockets(boxes):
    assert derive_pockets_m(boxes) == {}


def test_bad_boxes_are_refused():
    with pytest.raises(ValueError, match=r"\(k, 2, 3\)"):
        derive_pockets_m(np.zeros((2, 3)))


def test_default_starts_of_an_epal_are_the_refiners():
    rows = default_refine_starts((1.2, 0.8, 0.144))
    assert rows.shape == (MAX_STARTS, 3)
    np.testing.assert_allclose(offsets_from_starts(rows), start_offsets(MAX_STARTS), atol=1e-12)
    assert offsets_from_starts(np.zeros((0, 3))).shape == (0, 4, 4)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_default_starts_scale_with_length_and_width(name):
    size = get_pallet_model(name).size_m
    rows, epal = default_refine_starts(size), default_refine_starts((1.2, 0.8, 0.144))
    np.testing.assert_allclose(rows[:, 0], epal[:, 0])
    np.testing.assert_allclose(rows[:, 1], epal[:, 1] * size[0] / 1.2)
    np.testing.assert_allclose(rows[:, 2], epal[:, 2] * size[1] / 0.8)


@pytest.mark.parametrize("T, bad", [
    (np.stack([np.eye(4), ROT_Z_180]), []),
    (np.stack([np.eye(4), np.diag([1.0, 1.0, 2.0, 1.0])]), [1]),               # a scale
    (np.stack([np.diag([-1.0, 1.0, 1.0, 1.0])]), [0]),                         # a mirror: det -1
    (np.stack([np.eye(4) + np.eye(4, k=-3)]), [0]),                            # a last row that is not 0 0 0 1
    (np.stack([np.eye(4), np.full((4, 4), np.nan)]), [1]),
])
def test_check_rigid(T, bad):
    assert check_rigid(T) == bad


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_derived_pockets_agree_with_the_sim_catalogue(name):
    """Where a sim model lists its fork pockets, deriving them from its boxes gives the same openings."""
    model = get_pallet_model(name)
    listed = getattr(model, "pockets_m", None)
    if listed is None:
        pytest.skip(f"the sim model {name} lists no pockets")
    derived = derive_pockets_m(model.boxes_m)
    assert set(derived) == set(listed)
    for face in derived:
        np.testing.assert_allclose(derived[face], listed[face], atol=1e-6)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_sim_pallets_are_symmetric_as_they_say(name):
    model = get_pallet_model(name)
    assert asymmetric(model.symmetries, model.boxes_m) == []
    turn_90 = np.eye(4)
    turn_90[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    mirror_z = np.diag([1.0, 1.0, -1.0, 1.0])
    slide = np.eye(4)
    slide[0, 3] = 0.01
    assert asymmetric(np.stack([turn_90, mirror_z, slide]), model.boxes_m) == [0, 1, 2]
