import numpy as np
import pytest

from pallet6d.runtime.detector import (Detections, choose_input_hw, decode_yolov8, letterbox, nms, to_nchw,
                                      undo_letterbox, unmirror_yolov8)


def _yolo_output(boxes_cxcywh, class_scores, n_anchors=50, nc=2):
    """A (1, 4 + nc, A) YOLOv8 output with the given anchors filled in and zeros elsewhere."""
    out = np.zeros((1, 4 + nc, n_anchors), dtype=np.float32)
    out[0, :4, :] = 10.0  # empty anchors: a small box with score 0
    for a, (box, sc) in enumerate(zip(boxes_cxcywh, class_scores)):
        out[0, :4, a] = box
        out[0, 4:, a] = sc
    return out


def test_letterbox_geometry_and_exact_undo():
    rgb = np.zeros((370, 1224, 3), np.uint8)
    img, lb = letterbox(rgb, (192, 640))
    assert img.shape == (192, 640, 3) and img.dtype == np.uint8
    # height limits: r = 192 / 370, width 1224 r = 635.1 -> 635, padded 2 + 3
    assert lb.scale_y == pytest.approx(192 / 370) and lb.scale_x == pytest.approx(635 / 1224)
    assert lb.pad_y == 0 and lb.pad_x == 2
    assert np.all(img[:, :2] == 114) and np.all(img[:, 637:] == 114) and np.all(img[:, 2:637] == 0)
    # a box in image pixels -> input pixels -> back is exact
    box_img = np.array([[100.0, 50.0, 400.0, 300.0]])
    box_in = box_img.copy()
    box_in[:, [0, 2]] = box_in[:, [0, 2]] * lb.scale_x + lb.pad_x
    box_in[:, [1, 3]] = box_in[:, [1, 3]] * lb.scale_y + lb.pad_y
    np.testing.assert_allclose(undo_letterbox(box_in, lb), box_img, atol=1e-9)


def test_letterbox_reuses_buffer_and_pads_tall_images():
    buf = np.empty((64, 64, 3), np.uint8)
    img, lb = letterbox(np.full((100, 50, 3), 7, np.uint8), (64, 64), out=buf)
    assert img is buf
    assert lb.pad_x == 16 and lb.pad_y == 0
    assert np.all(img[:, :16] == 114) and np.all(img[:, 16:48] == 7)


def test_undo_letterbox_clips_to_image():
    _, lb = letterbox(np.zeros((100, 200, 3), np.uint8), (64, 64))
    out = undo_letterbox(np.array([[-10.0, -10.0, 100.0, 100.0]]), lb)
    assert out.min() >= 0 and out[0, 2] <= 200 and out[0, 3] <= 100


def test_to_nchw_normalises():
    img = np.array([[[255, 0, 51]]], np.uint8)
    out = to_nchw(img, mean=np.array([0.5, 0.0, 0.0]), std=np.array([0.5, 1.0, 0.2]))
    assert out.shape == (1, 3, 1, 1) and out.dtype == np.float32
    np.testing.assert_allclose(out.ravel(), [1.0, 0.0, 1.0], atol=1e-6)
    bgr = to_nchw(img, mean=np.zeros(3), std=np.ones(3), pixel_scale=1.0, bgr=True)
    np.testing.assert_allclose(bgr.ravel(), [51, 0, 255])


def test_decode_converts_centre_size_to_corners_and_thresholds():
    out = _yolo_output([(100, 50, 40, 20), (300, 60, 10, 10)], [(0.9, 0.1), (0.2, 0.3)])
    det = decode_yolov8(out, score_threshold=0.5, iou_threshold=0.5)
    assert len(det) == 1
    np.testing.assert_allclose(det.boxes_xyxy[0], [80, 40, 120, 60])
    assert det.scores[0] == pytest.approx(0.9) and det.class_ids[0] == 0


def test_decode_filters_classes():
    out = _yolo_output([(100, 50, 40, 20), (300, 60, 10, 10)], [(0.9, 0.1), (0.1, 0.8)])
    det = decode_yolov8(out, 0.5, 0.5, class_ids=(1,))
    assert len(det) == 1 and det.class_ids[0] == 1
    np.testing.assert_allclose(det.boxes_xyxy[0], [295, 55, 305, 65])


def test_nms_suppresses_overlaps_within_a_class_only():
    boxes = [(100, 100, 40, 40), (102, 101, 40, 40), (100, 100, 40, 40), (300, 100, 40, 40)]
    scores = [(0.9, 0.0), (0.8, 0.0), (0.0, 0.7), (0.6, 0.0)]
    det = decode_yolov8(_yolo_output(boxes, scores), 0.5, 0.5)
    # the second box overlaps the first (same class) and goes; the third is another class and stays
    np.testing.assert_allclose(det.scores, [0.9, 0.7, 0.6])
    np.testing.assert_array_equal(det.class_ids, [0, 1, 0])
    # across classes (pallet types of one object), the third box goes too
    det = decode_yolov8(_yolo_output(boxes, scores), 0.5, 0.5, agnostic=True)
    np.testing.assert_allclose(det.scores, [0.9, 0.6])
    np.testing.assert_array_equal(det.class_ids, [0, 0])


def test_nms_iou_threshold_boundary():
    boxes = np.array([[0, 0, 10, 10], [5, 0, 15, 10]], float)  # IoU = 50 / 150 = 1/3
    assert list(nms(boxes, np.array([0.9, 0.8]), 0.3)) == [0]
    assert list(nms(boxes, np.array([0.9, 0.8]), 0.34)) == [0, 1]
    assert list(nms(np.zeros((0, 4)), np.zeros(0), 0.5)) == []


def test_decode_keeps_every_class_score_of_each_detection():
    boxes = [(100, 100, 40, 40), (102, 101, 40, 40), (300, 100, 40, 40)]
    scores = [(0.9, 0.5), (0.8, 0.1), (0.2, 0.6)]
    det = decode_yolov8(_yolo_output(boxes, scores), 0.5, 0.5, agnostic=True)
    np.testing.assert_allclose(det.class_scores, [(0.9, 0.5), (0.2, 0.6)])   # the second box lost the NMS
    np.testing.assert_allclose(det.take(np.array([1])).class_scores, [(0.2, 0.6)])
    assert det.class_scores.dtype == np.float64
    none = det.take(np.flatnonzero(det.scores > 1))                          # taking nothing keeps the classes
    assert len(none) == 0 and none.class_scores.shape == (0, 2)


def test_decode_max_detections_and_empty():
    boxes = [(50 * i + 20, 20, 10, 10) for i in range(10)]
    det = decode_yolov8(_yolo_output(boxes, [(0.5 + 0.04 * i, 0) for i in range(10)]), 0.4, 0.5, max_detections=3)
    assert len(det) == 3 and np.all(np.diff(det.scores) < 0) and det.scores[0] == pytest.approx(0.86)
    assert len(decode_yolov8(_yolo_output([], []), 0.25, 0.5)) == 0


def test_decode_ignores_non_finite_boxes():
    out = _yolo_output([(np.nan, 50, 40, 20), (100, 50, 40, 20)], [(0.9, 0), (0.8, 0)])
    det = decode_yolov8(out, 0.5, 0.5)
    assert len(det) == 1 and det.scores[0] == pytest.approx(0.8)


@pytest.mark.parametrize("shape", [(2, 6, 10), (3, 10), (6,)])
def test_decode_rejects_bad_layouts(shape):
    with pytest.raises(ValueError, match="YOLOv8 output|one image"):
        decode_yolov8(np.zeros(shape, np.float32), 0.5, 0.5)


def _anchor_centres(input_hw, nc=2):
    """(1, 4 + nc, A) with every anchor's cx, cy at its own cell's centre, in YOLOv8's anchor order."""
    H, W = input_hw
    cells = [np.stack([(x + 0.5) * s, (y + 0.5) * s], 0).reshape(2, -1)
             for s in (8, 16, 32) for y, x in [np.mgrid[0:H // s, 0:W // s]]]
    out = np.zeros((1, 4 + nc, sum(c.shape[1] for c in cells)), np.float32)
    out[0, :2] = np.concatenate(cells, 1)
    out[0, 2:4] = 16.0
    return out


def test_unmirror_moves_each_anchor_to_the_one_it_mirrors():
    hw = (64, 96)
    centres = _anchor_centres(hw)
    np.testing.assert_array_equal(unmirror_yolov8(centres, hw), centres)    # a cell's centre mirrors onto its twin's
    scored = centres.copy()
    first16 = (64 // 8) * (96 // 8)                      # stride 16's first anchor: row 0, column 0 of a 4 x 6 grid
    scored[0, 4, first16] = 0.9
    scored[0, 0, first16] = 10.0                          # its box left of the cell's centre
    back = unmirror_yolov8(scored, hw)
    twin = first16 + 96 // 16 - 1                         # row 0, last column
    assert back[0, 4, twin] == pytest.approx(0.9) and back[0, 0, twin] == pytest.approx(96 - 10.0)
    assert np.count_nonzero(back[0, 4]) == 1
    np.testing.assert_array_equal(unmirror_yolov8(back, hw), scored)        # twice: as it was
    assert back.shape == scored.shape and scored[0, 4, first16] == pytest.approx(0.9)    # a new array


def test_unmirror_refuses_another_anchor_layout():
    with pytest.raises(ValueError, match="anchor layout"):
        unmirror_yolov8(np.zeros((1, 6, 100), np.float32), (64, 96))


def test_detections_validate_lengths():
    with pytest.raises(ValueError, match="2 boxes, 1 scores"):
        Detections(np.zeros((2, 4)), np.zeros(1), np.zeros(2))
    with pytest.raises(ValueError, match=r"class_scores: expected \(2, nc\), got \(3, 2\)"):
        Detections(np.zeros((2, 4)), np.zeros(2), np.zeros(2), np.zeros((3, 2)))
    assert len(Detections.empty()) == 0 and Detections.empty().class_scores is None


SIZES = [(192, 640), (256, 480), (288, 416), (320, 384)]


@pytest.mark.parametrize("image_hw, sizes, expected", [
    ((370, 1224), SIZES, (192, 640)),      # wide paper frames: the wide input
    ((480, 848), SIZES, (256, 480)),       # 16:9 stereo camera
    ((480, 640), SIZES, (288, 416)),       # 4:3: 288x416 and 320x384 draw it alike; the smaller input wins
    ((400, 640), SIZES, (288, 416)),
    ((480, 640), [(192, 640)], (192, 640)),
    ((480, 640), [(320, 384), (384, 320)], (320, 384)),   # scale 0.6 vs 0.667: the larger drawing wins
])
def test_choose_input_hw(image_hw, sizes, expected):
    assert choose_input_hw(image_hw, sizes) == expected


@pytest.mark.parametrize("image_hw, sizes", [((0, 640), SIZES), ((480, 640), [])])
def test_choose_input_hw_rejects(image_hw, sizes):
    with pytest.raises(ValueError):
        choose_input_hw(image_hw, sizes)
