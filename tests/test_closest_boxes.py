"""Closest point on a pallet's boxes (`closest_on_boxes`, ICP's search) equals a plain box-by-box search bit for
bit: the same box, closest point, normal and distance, the same ties, on every pallet type of the catalogue."""
import numpy as np
import pytest

from pallet6d.runtime.refine import closest_on_boxes

pallets = pytest.importorskip("pallet6d.sim.pallets")


def _plain(p: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every point against every box, (n, k) arrays written out: outside distance first (the first least box);
    a point in some box takes the box whose surface is nearest, its depth below the nearest face where it is
    in the box, else its outside distance; inside, the nearest face in the order -x -y -z +x +y +z."""
    lo, hi = boxes[None, :, 0], boxes[None, :, 1]                        # (1, k, 3)
    x = p[:, None]                                                         # (n, 1, 3)
    gap = np.maximum(np.maximum(lo - x, x - hi), 0.0)
    gap = gap * gap
    o2 = gap[..., 0] + gap[..., 1] + gap[..., 2]                           # (n, k)
    depth = np.minimum(np.minimum(x - lo, hi - x)[..., 0], np.minimum(x - lo, hi - x)[..., 1])
    depth = np.minimum(depth, np.minimum(x - lo, hi - x)[..., 2])
    q, normal, d = np.zeros_like(p), np.zeros_like(p), np.zeros(len(p))
    for i in range(len(p)):
        b = int(np.argmin(o2[i]))
        off = o2[i, b] > 0.0
        d[i] = np.sqrt(o2[i, b])
        if not off:
            dist = np.where(o2[i] > 0.0, np.sqrt(o2[i]), np.maximum(depth[i], 0.0))
            b = int(np.argmin(dist))
            d[i], off = dist[b], o2[i, b] > 0.0
        q[i] = np.minimum(np.maximum(p[i], boxes[b, 0]), boxes[b, 1])
        if off:
            normal[i] = (p[i] - q[i]) / d[i]
        else:
            f = int(np.argmin(np.concatenate([p[i] - boxes[b, 0], boxes[b, 1] - p[i]])))
            q[i, f % 3] = boxes[b, 1, f % 3] if f >= 3 else boxes[b, 0, f % 3]
            normal[i, f % 3] = 1.0 if f >= 3 else -1.0
    return q, normal, d


def _points(boxes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Points where the search has cases to tell apart: inside boards and blocks, in the gaps, on faces, edges
    and corners (shared faces of touching boxes among them), just outside, within ICP's window, far away."""
    lo, hi = boxes[:, 0], boxes[:, 1]
    k = len(boxes)
    pick = rng.integers(0, k, 300)
    inside = lo[pick] + rng.random((300, 3)) * (hi[pick] - lo[pick])
    on_face = inside[:200].copy()
    axis = rng.integers(0, 3, 200)
    side = np.where(rng.random(200) < 0.5, lo[pick[:200], axis], hi[pick[:200], axis])
    on_face[np.arange(200), axis] = side
    corners = np.where(rng.random((100, 3)) < 0.5, lo[pick[:100]], hi[pick[:100]])
    edges = corners.copy()
    edges[np.arange(100), rng.integers(0, 3, 100)] = inside[:100, 0]
    bb_lo, bb_hi = lo.min(0), hi.max(0)
    window = bb_lo - 0.08 + rng.random((400, 3)) * (bb_hi - bb_lo + 0.16)       # gaps, pockets, around
    near = on_face[:100] + rng.normal(0.0, 0.002, (100, 3))
    far = rng.normal(0.0, 5.0, (50, 3))
    return np.concatenate([inside, on_face, corners, edges, window, near, far])


def _assert_same(got, want) -> None:
    for g, w, name in zip(got, want, ("closest", "normal", "distance")):
        assert np.array_equal(g, w), name
        assert np.array_equal(np.signbit(g), np.signbit(w)), f"{name}: sign of zero"


@pytest.mark.parametrize("name", pallets.PALLET_MODELS)
def test_closest_equals_a_plain_search_on_every_pallet_type(name):
    boxes = pallets.get_pallet_model(name).boxes_m.astype(np.float64)
    pts = _points(boxes, np.random.default_rng(sum(map(ord, name))))
    _assert_same(closest_on_boxes(pts, boxes), _plain(pts, boxes))


def test_closest_in_overlapping_and_touching_boxes():
    # a point held by several boxes measures each one's depth; ties go to the first box
    boxes = np.array([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], [[0.5, 0.0, 0.0], [1.5, 1.0, 1.0]],
                      [[1.0, 0.0, 0.0], [2.0, 1.0, 0.5]], [[0.0, 0.0, 1.0], [1.0, 1.0, 1.2]]])
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.random((500, 3)) * [2.2, 1.2, 1.4] - 0.1,
                          [[0.75, 0.5, 0.5], [1.0, 0.5, 0.25], [0.5, 0.5, 1.0], [1.0, 0.5, 0.5], [0.5, 0.5, 0.5]]])
    _assert_same(closest_on_boxes(pts, boxes), _plain(pts, boxes))
    q, n, d = closest_on_boxes(np.array([[0.75, 0.5, 0.5]]), boxes)         # 0.25 deep in boxes 0 and 1
    np.testing.assert_array_equal(q[0], [1.0, 0.5, 0.5])                   # box 0's +x face: the first box
    np.testing.assert_array_equal(n[0], [1.0, 0.0, 0.0])
    assert d[0] == 0.25


def test_closest_of_no_point_and_of_one():
    boxes = pallets.get_pallet_model("epal").boxes_m
    q, n, d = closest_on_boxes(np.zeros((0, 3)), boxes)
    assert q.shape == (0, 3) and n.shape == (0, 3) and d.shape == (0,)
    one = np.array([[0.01, 0.02, 0.2]])
    _assert_same(closest_on_boxes(one, boxes), _plain(one, boxes.astype(np.float64)))
