import numpy as np
import pytest

from pallet6d.sim.pallets import PALLET_MODELS, ROT_Z_180, PalletModel, box_corners, get_pallet_model
from pallet6d.sim.scene import MATERIALS


def box_set(boxes: np.ndarray) -> np.ndarray:
    """Boxes as rows sorted lexicographically (rounded to 0.1 mm), to compare sets of boxes."""
    rows = np.round(boxes.reshape(len(boxes), 6) * 1e4).astype(np.int64)
    return rows[np.lexsort(rows.T[::-1])]


def transform_boxes(T: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    c = box_corners(boxes) @ T[:3, :3].T + T[:3, 3]
    return np.stack([c.min(1), c.max(1)], 1)


def test_epal_has_real_dimensions_and_parts():
    m = get_pallet_model()
    assert m.name == "epal"
    np.testing.assert_allclose(m.size_m, [1.2, 0.8, 0.144], atol=1e-9)
    assert m.boxes_m.shape == (20, 2, 3)
    # By height: 5 top deck boards, 3 stringer boards, 9 blocks (78 mm), 3 bottom boards, all 22 mm decks.
    z_lo = np.round(m.boxes_m[:, 0, 2] * 1000).astype(int)
    counts = {z: int((z_lo == z).sum()) for z in np.unique(z_lo)}
    assert counts == {-72: 3, -50: 9, 28: 3, 50: 5}
    widths_top = sorted(np.round((m.boxes_m[z_lo == 50, 1, 1] - m.boxes_m[z_lo == 50, 0, 1]) * 1000).astype(int))
    assert widths_top == [100, 100, 145, 145, 145]
    blocks = m.boxes_m[z_lo == -50]
    assert np.allclose(blocks[:, 1, 2] - blocks[:, 0, 2], 0.078)
    assert m.diameter_m == pytest.approx(np.linalg.norm([1.2, 0.8, 0.144]))


def test_gma_dimensions():
    m = get_pallet_model("gma")
    np.testing.assert_allclose(m.size_m, [1.219, 1.016, 0.121], atol=1e-9)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_model_frame_is_bbox_centre(name):
    m = get_pallet_model(name)
    lo, hi = m.boxes_m[:, 0].min(0), m.boxes_m[:, 1].max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(hi - lo, m.size_m)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_symmetries_map_the_pallet_onto_itself(name):
    m = get_pallet_model(name)
    assert m.symmetries.shape == (2, 4, 4)
    np.testing.assert_allclose(m.symmetries[0], np.eye(4))
    np.testing.assert_allclose(m.symmetries[1], ROT_Z_180)
    pts = m.surface_points(3000, seed=1).astype(np.float64)
    for T in m.symmetries:
        np.testing.assert_array_equal(box_set(transform_boxes(T, m.boxes_m)), box_set(m.boxes_m))
        moved = pts @ T[:3, :3].T + T[:3, 3]
        assert m.surface_distance_m(moved).max() < 1e-6


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_upside_down_is_not_a_symmetry(name):
    m = get_pallet_model(name)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])   # 180 deg about x
    moved = m.surface_points(2000, seed=2).astype(np.float64) @ flip[:3, :3].T
    assert m.surface_distance_m(moved).max() > 0.01


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_surface_points_lie_on_the_outer_surface(name):
    m = get_pallet_model(name)
    pts = m.surface_points(5000, seed=0)
    assert pts.shape == (5000, 3) and pts.dtype == np.float32
    assert m.surface_distance_m(pts).max() < 1e-6
    np.testing.assert_array_equal(pts, m.surface_points(5000, seed=0))
    assert not np.array_equal(pts, m.surface_points(5000, seed=1))
    lo, hi = pts.min(0), pts.max(0)
    np.testing.assert_allclose(hi - lo, m.size_m, atol=0.02)


def test_surface_points_exclude_contact_faces():
    m = get_pallet_model("epal")
    pts = m.surface_points(20000, seed=3).astype(np.float64)
    # The top of the blocks (z = 28 mm) is covered by the stringer boards exactly above them.
    blocks_top = np.abs(pts[:, 2] - 0.028) < 1e-9
    in_x = np.any(np.abs(pts[:, None, 0] - np.array([-0.5275, 0.0, 0.5275])) < 0.0725 - 1e-6, axis=1)
    in_y = (np.abs(np.abs(pts[:, 1]) - 0.35) < 0.05 - 1e-6) | (np.abs(pts[:, 1]) < 0.0725 - 1e-6)
    assert not np.any(blocks_top & in_x & in_y)
    # ... while the stringer's underside between the blocks is visible and sampled.
    assert np.any(blocks_top & in_x & ~in_y)


def test_unknown_model_lists_known_names():
    with pytest.raises(ValueError, match="epal"):
        get_pallet_model("chep")


def test_bad_model_definitions_raise():
    with pytest.raises(ValueError, match="min"):
        PalletModel("bad", np.array([[[0, 0, 0], [-1, 1, 1]]], dtype=float))
    with pytest.raises(ValueError, match="identity"):
        PalletModel("bad", np.array([[[-1, -1, -1], [1, 1, 1]]], dtype=float), symmetries=ROT_Z_180[None])
    with pytest.raises(ValueError):
        get_pallet_model().surface_points(0)


def test_ply_is_a_millimetre_triangle_mesh(tmp_path):
    m = get_pallet_model("epal")
    path = tmp_path / "obj_000001.ply"
    m.write_ply(path)
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert b"element vertex 160" in header and b"element face 240" in header
    verts = np.frombuffer(body[: 160 * 12], dtype="<f4").reshape(-1, 3)
    np.testing.assert_allclose(verts.max(0), [600, 400, 72], atol=1e-3)
    faces = np.frombuffer(body[160 * 12:], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    assert len(faces) == 240 and np.all(faces["n"] == 3) and faces["i"].max() == 159
    # Outward normals: each triangle's normal points away from its box centre.
    v, f = m.mesh()
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = box_corners(m.boxes_m).mean(1).repeat(12, 0)
    assert np.all(np.einsum("ij,ij->i", normal, tri.mean(1) - centre) > 0)


# --- the catalogue: types, ids, fork pockets, refine starts ----------------------------------------------

CATALOGUE_SIZES_MM = {
    "epal": (1200, 800, 144), "gma": (1219, 1016, 121), "eur3": (1200, 1000, 144), "eur2": (1200, 1000, 162),
    "eur6": (800, 600, 144), "block_1210": (1200, 1000, 150), "plastic_9leg": (1200, 800, 150),
    "plastic_3runner": (1200, 800, 150), "plastic_3runner_1210": (1200, 1000, 150),
    "plastic_closed": (1200, 800, 160), "plastic_closed_1210": (1200, 1000, 160),
}


def test_catalogue_has_every_type_with_stable_obj_ids():
    assert set(PALLET_MODELS) == set(CATALOGUE_SIZES_MM)
    ids = {name: get_pallet_model(name).obj_id for name in PALLET_MODELS}
    assert ids["epal"] == 1 and ids["gma"] == 2 and ids["eur3"] == 3      # the ids of existing datasets
    assert sorted(ids.values()) == list(range(1, len(PALLET_MODELS) + 1))
    for name, size in CATALOGUE_SIZES_MM.items():
        m = get_pallet_model(name)
        np.testing.assert_allclose(m.size_m * 1000, size, atol=1e-6, err_msg=name)
        assert m.material == ("plastic" if name.startswith("plastic") else "wood")
        assert m.points(300).shape == (300, 3)


def _ray_hits(boxes: np.ndarray, depth_axis: int, lateral: float, z: float) -> bool:
    """Whether a line along `depth_axis` through the whole pallet at (lateral, z) passes through a part."""
    lat = 1 - depth_axis
    inside = (boxes[:, 0, lat] < lateral) & (lateral < boxes[:, 1, lat]) & (boxes[:, 0, 2] < z) & (z < boxes[:, 1, 2])
    return bool(inside.any())


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_pockets_are_open_through_the_pallet_and_bounded_by_parts(name):
    m = get_pallet_model(name)
    assert set(m.pockets_m) == {"+x", "-x", "+y", "-y"}      # every catalogue type is four-way
    floor = -m.size_m[2] / 2
    for face, pk in m.pockets_m.items():
        axis = 0 if face[1] == "x" else 1
        lat = 1 - axis
        for lo, hi in pk:
            np.testing.assert_allclose([lo[axis], hi[axis]], [-m.size_m[axis] / 2, m.size_m[axis] / 2])
            assert hi[lat] - lo[lat] >= 0.15 or name == "gma" and face[1] == "y"   # GMA notches: 229 mm
            assert hi[2] - lo[2] >= 0.035
            mid_lat, mid_z = (lo[lat] + hi[lat]) / 2, (lo[2] + hi[2]) / 2
            # Open: lines through the opening (centre and near its corners) pass through no part.
            for dl in (0.0, -0.45, 0.45):
                for dz in (0.0, -0.45, 0.45):
                    assert not _ray_hits(m.boxes_m, axis, mid_lat + dl * (hi[lat] - lo[lat]),
                                         mid_z + dz * (hi[2] - lo[2])), (name, face)
            # Bounded: just beside it, blocks/legs/stringers; just above it, boards or the deck (slatted decks
            # have gaps: somewhere across its width); below, the floor or a base board or runner.
            assert _ray_hits(m.boxes_m, axis, lo[lat] - 0.005, mid_z) and _ray_hits(m.boxes_m, axis, hi[lat] + 0.005,
                                                                                     mid_z), (name, face)
            across = np.linspace(lo[lat], hi[lat], 9)[1:-1]
            assert any(_ray_hits(m.boxes_m, axis, x, hi[2] + 0.005) for x in across), (name, face)
            if lo[2] > floor + 1e-9:
                assert any(_ray_hits(m.boxes_m, axis, x, lo[2] - 0.005) for x in across), (name, face)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_pockets_are_left_then_right_and_symmetric(name):
    m = get_pallet_model(name)
    for face, pk in m.pockets_m.items():
        n = {"+x": [1, 0, 0], "-x": [-1, 0, 0], "+y": [0, 1, 0], "-y": [0, -1, 0]}[face]
        left_dir = np.cross(n, [0, 0, 1])            # seen from outside, left is normal x up
        assert pk[0].mean(0) @ left_dir > pk[1].mean(0) @ left_dir
    # A 180 degree turn maps the +x openings onto the -x ones in the same order (left stays left).
    for a, b in (("+x", "-x"), ("+y", "-y")):
        turned = np.stack([transform_boxes(ROT_Z_180, box[None])[0] for box in m.pockets_m[a]])
        np.testing.assert_allclose(turned, m.pockets_m[b], atol=1e-9)


def test_epal_pockets_have_the_real_entry_sizes():
    m = get_pallet_model("epal")
    size = lambda box, lat: np.round((box[1] - box[0])[[lat, 2]] * 1000, 1).tolist()  # noqa: E731
    assert [size(b, 1) for b in m.pockets_m["+x"]] == [[227.5, 100.0]] * 2     # 800 mm side, from the floor
    assert [size(b, 0) for b in m.pockets_m["+y"]] == [[382.5, 100.0]] * 2     # 1200 mm side, above the boards
    gma = get_pallet_model("gma")
    assert [size(b, 0) for b in gma.pockets_m["+y"]] == [[229.0, 38.0]] * 2      # through the stringer notches


def test_refine_starts_are_epals_scaled_by_size():
    from pallet6d.runtime.refine import _STARTS

    np.testing.assert_allclose(get_pallet_model("epal").refine_starts, _STARTS)
    half = get_pallet_model("eur6")
    assert half.refine_starts.shape == (len(_STARTS), 3)
    np.testing.assert_allclose(half.refine_starts[:, 0], np.asarray(_STARTS)[:, 0])
    np.testing.assert_allclose(half.refine_starts[:, 1:], np.asarray(_STARTS)[:, 1:] * [0.8 / 1.2, 0.6 / 0.8])


def test_bad_pockets_raise():
    box = np.array([[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]])
    with pytest.raises(ValueError, match="pockets_m"):
        PalletModel("bad", box, pockets_m={"+z": np.zeros((2, 2, 3))})
    outside = np.array([[[-1, -2, -1], [1, -0.5, 0]], [[-1, 0.5, -1], [1, 1, 0]]], dtype=float)
    with pytest.raises(ValueError, match="outside"):
        PalletModel("bad", box, pockets_m={"+x": outside})
    with pytest.raises(ValueError, match="face"):
        get_pallet_model().face_centre_m("top")


def test_missing_board_changes_the_boxes_not_the_model():
    from pallet6d.sim.scene import PalletPlacement, pallet_boxes

    m = get_pallet_model("epal")
    p = PalletPlacement(1, "epal", np.eye(4))
    full = pallet_boxes(p, np.array([0.7, 0.6, 0.4]), 0)
    worn = pallet_boxes(p, np.array([0.7, 0.6, 0.4]), 0, missing=(1,), part_colors=np.full((len(m.boxes_m), 3), 0.3))
    assert len(full) == len(m.boxes_m) and len(worn) == len(m.boxes_m) - 1
    assert all(np.allclose(b.color, 0.3) for b in worn)
    assert get_pallet_model(p.model_name) is m
    plastic = pallet_boxes(PalletPlacement(2, "plastic_9leg", np.eye(4)), np.array([0.1, 0.2, 0.6]), 0)
    assert {b.material for b in plastic} == {MATERIALS.index("plastic")}
