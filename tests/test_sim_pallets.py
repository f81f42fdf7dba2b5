import numpy as np
import pytest

from pallet6d.sim.pallets import PALLET_MODELS, ROT_Z_180, PalletModel, box_corners, get_pallet_model


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
