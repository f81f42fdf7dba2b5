import numpy as np
import pytest

from pallet6d.runtime.candidates import Candidates


def _cands(n=4, num_points=5):
    boxes = np.arange(n * 4, dtype=float).reshape(n, 4)
    return Candidates.new(boxes, np.linspace(0.9, 0.6, n), np.arange(n) % 2, np.arange(n) % 2, num_points)


def test_new_rows_are_alive_with_nothing_computed():
    c = _cands()
    assert len(c) == 4 and c.alive.all()
    assert c.points_cam.shape == (4, 5, 3) and c.T_net.shape == (4, 4, 4) and np.isnan(c.fit).all()
    np.testing.assert_array_equal(c.T_cam_pallet, np.tile(np.eye(4), (4, 1, 1)))
    assert all(len(v) == 0 and len(u) == 0 for v, u in c.pixels)
    empty = Candidates.new(np.zeros((0, 4)), [], [], [], 5)
    assert len(empty) == 0 and len(empty[empty.alive]) == 0


@pytest.mark.parametrize("index", [np.array([False, True, False, True]), np.array([1, 3])])
def test_mask_and_index_selection_give_copies_of_the_rows(index):
    c = _cands()
    c.assign([1, 3], confidence=[0.5, 0.7], pixels=[(np.array([1]), np.array([2])), (np.array([3]), np.array([4]))])
    sub = c[index]
    assert len(sub) == 2
    np.testing.assert_array_equal(sub.boxes_xyxy, c.boxes_xyxy[[1, 3]])
    np.testing.assert_array_equal(sub.confidence, [0.5, 0.7])
    assert sub.pixels[1][0].tolist() == [3] and sub.class_ids.tolist() == [1, 1]
    sub.confidence[:] = 0.0                                     # a copy: the record is unchanged
    assert c.confidence[1] == 0.5


def test_concat_keeps_every_row_and_field_in_order():
    a, b = _cands(2), _cands(3)
    b.assign([0], confidence=[0.4], pixels=[(np.array([7]), np.array([8]))])
    b.reject([2], "poor_fit", "fit 0.1 < 0.2")
    c = Candidates.concat([a, b])
    assert len(c) == 5 and c.alive.tolist() == [True, True, True, True, False]
    np.testing.assert_array_equal(c.boxes_xyxy, np.concatenate([a.boxes_xyxy, b.boxes_xyxy]))
    assert c.confidence[2] == 0.4 and c.pixels[2][0].tolist() == [7] and c.detail[4] == "fit 0.1 < 0.2"
    assert len(Candidates.concat([a, b[b.alive & False]])) == 2


def test_reject_sets_reasons_and_details_and_alive_follows():
    c = _cands()
    c.reject(np.array([0, 2]), "poor_fit", ["fit 0.1", "fit 0.0"])
    c.reject(c.scores < 0.65, "time_budget", "no time left")
    assert c.alive.tolist() == [False, True, False, False]
    assert c.reason.tolist() == ["poor_fit", "", "poor_fit", "time_budget"]
    assert c.detail.tolist() == ["fit 0.1", "", "fit 0.0", "no time left"]
    c.reject(np.zeros(0, np.int64), "poor_fit", [])             # nothing to reject is fine
    with pytest.raises(ValueError, match="2 rows but 1 details"):
        c.reject([1, 2], "poor_fit", ["one"])


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(scores=[0.5]), ValueError, "2 boxes but 1 scores"),
    (dict(type_index=[0, 0, 0]), ValueError, "3 type indexes"),
    (dict(type_options=[(0, 1)]), ValueError, "2 boxes need 2 type options"),
    (dict(type_options=[(0, 1), (1, 2)]), ValueError, "each with its row's type index"),
])
def test_new_checks_row_counts(kwargs, error, match):
    args = dict(boxes_xyxy=np.zeros((2, 4)), scores=[0.5, 0.4], class_ids=[0, 0], type_index=[0, 0], num_points=3)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        Candidates.new(**args)


def test_bad_index_and_field_and_ragged_rows_raise():
    c = _cands()
    with pytest.raises(TypeError, match="boolean mask or integer"):
        c[np.array([0.5])]
    with pytest.raises(AttributeError, match="no field 'pose'"):
        c.assign([0], pose=np.eye(4))
    with pytest.raises(ValueError, match=r"Candidates.scores: expected an array of 4 rows"):
        Candidates(**{**{f: getattr(c, f) for f in c.__dataclass_fields__}, "scores": np.zeros(3)})
