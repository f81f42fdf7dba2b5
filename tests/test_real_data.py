"""export/real_data.py: the real-photograph importer on a tiny fixture made here, and the sequence split."""
from __future__ import annotations

import json

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from pallet6d.export.real_data import (ImageRecord, Source, file_stem, import_sources, load_records, nearest_labels,
                                       parse_yolo_label, sequence_of, split_by_sequence, timestamp_runs,
                                       unstretched_size)


@pytest.mark.parametrize("name, stem", [
    ("1000736-6303_jpg.rf.92c0d6c8403755071eac22527c9ad815.jpg", "1000736-6303"),
    ("1000736-6303_jpg.rf.0f869d3362cd4a183f05a6b51c9383aa.txt", "1000736-6303"),
    ("palet101_PNG.rf.9579aacb1c5ec010a661629d440003a1.jpg", "palet101"),
    ("20221018_133840.jpg", "20221018_133840"),
    ("plain.png", "plain"),
])
def test_file_stem_drops_the_roboflow_hash(name, stem):
    assert file_stem(name) == stem


def test_parse_box_and_polygon_lines_keeping_pallet_classes():
    text = "1 0.5 0.5 0.2 0.4\n0 0.1 0.1 0.2 0.2\n1 0.1 0.2 0.3 0.2 0.3 0.6 0.1 0.6 0.1 0.2\n\n1 0.9 0.9 0.4 0.4\n"
    boxes, classes = parse_yolo_label(text, keep_classes=(1,))
    assert classes == {0, 1}
    np.testing.assert_allclose(boxes, [[0.4, 0.3, 0.6, 0.7], [0.1, 0.2, 0.3, 0.6], [0.7, 0.7, 1.0, 1.0]])


@pytest.mark.parametrize("text", ["1 0.5 0.5 0.2", "1 0.1 0.1 0.2 0.2 0.3", "x 0.5 0.5 0.2 0.2"])
def test_parse_rejects_malformed_lines(text):
    with pytest.raises(ValueError, match="line 1"):
        parse_yolo_label(text, (1,))


def test_degenerate_boxes_are_dropped():
    boxes, _ = parse_yolo_label("0 0.5 0.5 0.0 0.3\n0 1.2 0.5 0.2 0.2\n", (0,))
    assert boxes.shape == (0, 4)


@pytest.mark.parametrize("wh, aspect, expected", [((416, 416), 16 / 9, (555, 312)), ((640, 640), 1.0, (640, 640)),
                                                  ((400, 400), 0.5, (283, 566))])
def test_unstretched_size_keeps_the_pixel_count(wh, aspect, expected):
    assert unstretched_size(wh, aspect) == expected
    with pytest.raises(ValueError):
        unstretched_size((0, 10), 1.0)


def test_sequences_from_video_frames_and_timestamps():
    assert sequence_of("WhatsApp-Video_mp4-0019", "video") == sequence_of("WhatsApp-Video_mp4-0003", "video")
    assert sequence_of("palet101", "video") != sequence_of("palet7", "video")
    assert sequence_of("no-number-here", "video") is None
    keys = [sequence_of(s, "timestamp") for s in ("20221018_133827", "20221018_133840", "20221018_140000")]
    runs = timestamp_runs(keys)
    assert runs[0] == runs[1] != runs[2]


@pytest.mark.parametrize("stem, day", [("1579163820-2578418", "2020-01-16"), ("1583416212270", "2020-03-05"),
                                       ("1564564602344-34", "2019-07-31"), ("1000736-6303", None), ("abc", None)])
def test_capture_day_from_unix_time_stems(stem, day):
    assert sequence_of(stem, "capture-day") == day


def test_nearest_labels():
    ref = np.array([[0.0, 0.0], [10.0, 0.0]])
    assert nearest_labels(np.array([[1.0, 1.0], [9.0, -1.0]]), ref, ["a", "b"]) == ["a", "b"]
    assert nearest_labels(np.zeros((0, 2)), ref, ["a", "b"]) == []
    with pytest.raises(ValueError):
        nearest_labels(np.zeros((1, 2)), np.zeros((0, 2)), [])


@pytest.mark.parametrize("seed", range(5))
def test_split_never_puts_one_sequence_in_two_splits(seed):
    rng = np.random.default_rng(seed)
    seqs = [f"s{int(k)}" for k in rng.integers(0, 15, size=200)]
    split = split_by_sequence(seqs, 0.2, salt=str(seed))
    by_seq: dict[str, set] = {}
    for s, sp in zip(seqs, split):
        by_seq.setdefault(s, set()).add(sp)
    assert all(len(v) == 1 for v in by_seq.values())
    frac = split.count("heldout") / len(split)
    assert 0.2 <= frac < 0.6
    assert set(split_by_sequence(["a", "b"], 0.2)) == {"train", "heldout"}
    assert split_by_sequence(["a", "a"], 0.5) == ["train", "train"]
    with pytest.raises(ValueError):
        split_by_sequence(seqs, 1.0)


# ------------------------------------------------------------------------------------------- the fixture


def _write(folder, name, img, label):
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "images" / f"{name}.jpg"), img)
    if label is not None:
        (folder / "labels" / f"{name}.txt").write_text(label)


def _rect(cls, x1, y1, x2, y2):
    """A label line as LOCO's export writes boxes: a closed 4-point polygon."""
    return f"{cls} {x2} {y2} {x2} {y1} {x1} {y1} {x1} {y2} {x2} {y2}\n"


@pytest.fixture
def raw_sources(tmp_path):
    """Two sources in the uploaders' layouts: a LOCO-like set stretched to 64x64 (4-point polygons, class 1 pallet,
    class 0 forklift, an augmented train folder repeating a stem, a pallet-free frame, an unlabelled image) and a
    video-frame set (plain boxes, loaded units) that repeats a LOCO stem."""
    rng = np.random.default_rng(0)
    raw = tmp_path / "raw"
    loco = raw / "loco-like"
    looks = {"2020-01-16": np.tile(np.linspace(0, 250, 64, dtype=np.uint8)[None, :, None], (64, 1, 3)),
             "2020-03-05": np.tile(np.linspace(250, 0, 64, dtype=np.uint8)[:, None, None], (1, 64, 3))}
    for k in range(6):   # three frames of each of two capture days (stems: Unix seconds, then milliseconds)
        stem, look = (f"157916382{k}-{k}", looks["2020-01-16"]) if k < 3 else (f"158341621227{k}", looks["2020-03-05"])
        img = look + rng.integers(0, 5, (64, 64, 3), dtype=np.uint8)
        label = _rect(1, 0.25, 0.5, 0.75, 0.75) + _rect(0, 0, 0, .1, .1)
        _write(loco / "valid", f"{stem}_jpg.rf.{'a' * 32}", img, label)
    _write(loco / "valid", f"2000-1_jpg.rf.{'b' * 32}", looks["2020-01-16"], _rect(0, 0.1, 0.1, 0.3, 0.3))
    _write(loco / "valid", f"2001-1_jpg.rf.{'c' * 32}", np.zeros((64, 64, 3), np.uint8), None)
    _write(loco / "train", f"1579163820-0_jpg.rf.{'d' * 32}", np.zeros((64, 64, 3), np.uint8), _rect(1, .1, .1, .2, .2))
    _write(loco / "train", f"3000-9_jpg.rf.{'e' * 32}", looks["2020-03-05"], _rect(1, 0.1, 0.1, 0.5, 0.5))
    video = raw / "video-like"
    for k in range(0, 60, 5):
        _write(video / "test", f"clip_mp4-{k:04d}_jpg.rf.{'f' * 32}", np.full((48, 48, 3), k, np.uint8),
               "0 0.5 0.5 0.5 0.8\n")
    _write(video / "test", f"1579163821-1_jpg.rf.{'0' * 32}", np.zeros((48, 48, 3), np.uint8), "0 0.5 0.5 0.5 0.5\n")
    common = dict(repo="someone/repo", commit="0" * 40, licence="CC BY 4.0", attribution="someone",
                  url="https://example.invalid", shows="test")
    sources = (
        Source(name="loco-like", folders=("valid",), augmented_folders=("train",), pallet_classes=(1,),
               other_classes=(0, 2), original_aspect=16 / 9, aspect_known=False, convention="whole_pallet",
               kinds=("wood",), sequence_rule="capture-day", **common),
        Source(name="video-like", folders=("test",), pallet_classes=(0,), original_aspect=2.0, aspect_known=True,
               convention="loaded_unit", kinds=("plastic", "loaded"), sequence_rule="video", **common),
        Source(name="missing", folders=("x",), pallet_classes=(0,), original_aspect=1.0, aspect_known=True,
               convention="whole_pallet", kinds=("wood",), sequence_rule="video", **common),
    )
    return raw, sources


def test_import_unstretches_deduplicates_and_marks(raw_sources, tmp_path):
    raw, sources = raw_sources
    out = tmp_path / "real"
    recs = import_sources(raw, out, sources, heldout_fraction=0.3, seed=0)
    by_stem = {r.stem: r for r in recs}
    # duplicates: "1579163820-0" (augmented copy) and "1579163821-1" (other source) are kept once, where first seen
    stems_a = [f"157916382{k}-{k}" for k in range(3)]
    stems_b = [f"158341621227{k}" for k in range(3, 6)]
    assert sorted(by_stem) == sorted(stems_a + stems_b + ["2000-1", "3000-9"]
                                     + [f"clip_mp4-{k:04d}" for k in range(0, 60, 5)])
    assert by_stem["1579163820-0"].source == "loco-like" and not by_stem["1579163820-0"].augmented
    assert by_stem["3000-9"].augmented
    # capture days are the sequences; undated frames join the day they look like
    assert {by_stem[s].sequence for s in stems_a} == {"loco-like/2020-01-16"} == {by_stem["2000-1"].sequence}
    assert {by_stem[s].sequence for s in stems_b} == {"loco-like/2020-03-05"} == {by_stem["3000-9"].sequence}
    # LOCO-like: 64x64 stretched from 16:9 -> 85x48, the box in unstretched pixels
    r = by_stem["1579163822-2"]
    assert (r.width, r.height) == (85, 48)
    np.testing.assert_allclose(r.box_array(), [[0.25 * 85, 0.5 * 48, 0.75 * 85, 0.75 * 48]], atol=0.01)
    img = cv2.imread(str(out / r.image))
    assert img.shape[:2] == (48, 85)
    # pallet-free frame (other classes labelled) is a negative; an unlabelled image is dropped
    assert by_stem["2000-1"].negative and by_stem["2000-1"].boxes_xyxy == []
    assert "2001-1" not in by_stem
    v = by_stem["clip_mp4-0010"]
    assert v.convention == "loaded_unit" and v.kinds == ["plastic", "loaded"] and (v.width, v.height) == (68, 34)
    # the split: whole sequences, and records read back unchanged
    seq_splits: dict[str, set] = {}
    for rec in recs:
        seq_splits.setdefault(rec.sequence, set()).add(rec.split)
    assert all(len(s) == 1 for s in seq_splits.values())
    assert {r.split for r in recs if r.source == "video-like"} == {"train", "heldout"}
    assert [r.stem for r in load_records(out)] == [r.stem for r in recs]
    card = json.loads((out / "card.json").read_text())
    names = [s["name"] for s in card["sources"]]
    assert names == ["loco-like", "video-like", "missing"]
    loco_counts = card["sources"][0]["counts"]
    assert sum(c["images"] for c in loco_counts.values()) == 8
    assert sum(c["negatives"] for c in loco_counts.values()) == 1
    assert card["sources"][0]["dropped"]["duplicates"] == 1 and card["sources"][1]["dropped"]["duplicates"] == 1
    assert "CC BY 4.0" in (out / "card.md").read_text()


def test_train_samples_never_read_the_heldout_split(raw_sources, tmp_path):
    pytest.importorskip("torch")
    from pallet6d.export.real_samples import build_real_samples, real_train_val, validation_unit

    raw, sources = raw_sources
    out = tmp_path / "real"
    recs = import_sources(raw, out, sources, heldout_fraction=0.3, seed=0)
    train, val = real_train_val(recs, val_fraction=0.3)
    assert train and all(r.split == "train" and r.convention == "whole_pallet" for r in train + val)
    assert not {validation_unit(r) for r in train} & {validation_unit(r) for r in val}
    s = build_real_samples(out, train, 64)
    assert len(s.images) == len(train) and all(max(im.shape[:2]) <= 64 for im in s.images)
    # 85x48 photographs capped at 64 px: scale 64/85, boxes scaled with them
    r0, b0 = train[0], s.boxes[0]
    assert s.images[0].shape[:2] == (36, 64)
    np.testing.assert_allclose(b0, r0.box_array() * 64 / 85, rtol=1e-5)
    held = next(r for r in recs if r.split == "heldout")
    with pytest.raises(ValueError, match="train split"):
        build_real_samples(out, [held], 64)


def test_detector_data_mixes_real_frames_as_untyped_boxes(raw_sources, sim_bop_dataset, tmp_path):
    pytest.importorskip("torch")
    from pallet6d.export.config import get_config
    from pallet6d.export.train_data import NO_AUGMENT
    from pallet6d.export.train_detector import DetectorTrainer, load_detector_data

    raw, sources = raw_sources
    out = tmp_path / "real"
    recs = import_sources(raw, out, sources, heldout_fraction=0.3, seed=0)
    cfg = get_config("tiny")
    dd = load_detector_data(cfg, [sim_bop_dataset], seed=0, cache_dir=tmp_path / "cache", progress=False,
                            real=out)
    n_usable = sum(r.split == "train" and r.convention == "whole_pallet" for r in recs)
    assert int(dd.real.sum()) == n_usable and len(dd.real) == 3 + n_usable
    trainer = DetectorTrainer(cfg, dd, NO_AUGMENT)
    real_idx = np.flatnonzero(dd.real)
    _, targets = trainer.batch(np.concatenate([[0], real_idx]), None)
    assert all(float(c) == 0.0 for c in targets[0][:, 0])
    assert all(float(c) == -1.0 for t in targets[1:] for c in t[:, 0])
    v = trainer.validate()
    assert "recall" in v and ("recall_real" in v) == bool(dd.real[dd.val_idx].any())
    # the cache is reused and gives the same frames
    again = load_detector_data(cfg, [sim_bop_dataset], seed=0, cache_dir=tmp_path / "cache", progress=False,
                               real=out)
    assert len(again.samples) == len(dd.samples)
    for a, b in zip(again.samples.images, dd.samples.images):
        np.testing.assert_array_equal(a, b)


def test_real_photographs_with_a_large_box_repeat_and_near_f1_selects(raw_sources, sim_bop_dataset, tmp_path):
    pytest.importorskip("torch")
    from pallet6d.export.config import get_config
    from pallet6d.export.train_data import NO_AUGMENT
    from pallet6d.export.train_detector import DetectorTrainer, has_large_box, load_detector_data

    raw, sources = raw_sources
    out = tmp_path / "real"
    import_sources(raw, out, sources, heldout_fraction=0.3, seed=0)
    cfg = get_config("tiny")
    kw = dict(seed=0, cache_dir=tmp_path / "cache", progress=False, real=out, val_fraction=0.0)
    once = load_detector_data(cfg, [sim_bop_dataset], **kw)   # every real photograph trains
    thrice = load_detector_data(cfg, [sim_bop_dataset], real_repeat_large=3, **kw)
    s = once.samples
    large = [i for i in once.train_idx if once.real[i] and has_large_box(s.boxes[i], s.images[i].shape[0])]
    assert large, "the fixture needs a real photograph with a large box"
    counts = np.bincount(thrice.train_idx, minlength=len(s))
    assert all(counts[i] == 3 for i in large)
    assert len(thrice.train_idx) == len(once.train_idx) + 2 * len(large)
    np.testing.assert_array_equal(thrice.val_idx, once.val_idx)
    # photos of a kept kind repeat as the large ones do (here every real photo shows wood)
    kept = load_detector_data(cfg, [sim_bop_dataset], real_repeat_large=3, real_keep_kinds=("wood",), **kw)
    real_train = [i for i in once.train_idx if once.real[i]]
    assert len(real_train) > len(large)
    assert all(np.bincount(kept.train_idx, minlength=len(s))[i] == 3 for i in real_train)
    with pytest.raises(ValueError, match="real_repeat_large"):
        load_detector_data(cfg, [sim_bop_dataset], real_repeat_large=0, **kw)

    with pytest.raises(ValueError, match="real validation"):   # no real validation photographs to select by
        DetectorTrainer(cfg, once, NO_AUGMENT, select="near_f1")
    with_val = load_detector_data(cfg, [sim_bop_dataset], **{**kw, "val_fraction": 0.1})
    assert with_val.real[with_val.val_idx].any()
    v = DetectorTrainer(cfg, with_val, NO_AUGMENT, select="near_f1").validate()
    assert v["n_gt_real_near"] > 0 and 0.0 <= v["recall_real_near"] <= 1.0
    assert 0.0 <= v["near_f1"] <= 1.0 and v["metric"] == pytest.approx(1.0 - v["near_f1"])
    by_loss = DetectorTrainer(cfg, with_val, NO_AUGMENT).validate()
    assert by_loss["metric"] == by_loss["loss"] and "near_f1" not in by_loss
    with pytest.raises(ValueError, match="select"):
        DetectorTrainer(cfg, once, NO_AUGMENT, select="recall")


@pytest.mark.parametrize("boxes, image_h, expected", [
    (np.zeros((0, 4)), 100, False),
    ([[0, 0, 10, 19.9]], 100, False),
    ([[0, 0, 10, 20.0]], 100, True),
    ([[0, 0, 10, 5], [5, 10, 50, 60]], 100, True),
])
def test_has_large_box(boxes, image_h, expected):
    pytest.importorskip("torch")
    from pallet6d.export.train_detector import has_large_box

    assert has_large_box(np.asarray(boxes, float), image_h) is expected


def test_greedy_matching_and_letterboxed_height():
    pytest.importorskip("torch")
    from pallet6d.export.train_detector import letterboxed_height, match_greedy

    gt = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float)
    det = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [21, 21, 30, 30]], float)   # a duplicate claims nothing
    np.testing.assert_array_equal(match_greedy(det, gt, 0.5), [0, 2])
    np.testing.assert_array_equal(match_greedy(det[:2], gt, 0.5), [0, -1])
    assert match_greedy(np.zeros((0, 4)), gt, 0.5).tolist() == [-1, -1]
    assert match_greedy(det, np.zeros((0, 4)), 0.5).shape == (0,)
    assert letterboxed_height((300, 1280), (192, 640)) == pytest.approx(150.0)   # width-bound
    assert letterboxed_height((480, 640), (192, 640)) == pytest.approx(192.0)    # height-bound


def test_card_ships_beside_a_bundle(raw_sources, tmp_path):
    from pallet6d.export.real_data import ship_card

    raw, sources = raw_sources
    out = tmp_path / "real"
    import_sources(raw, out, sources)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    with pytest.raises(ValueError, match="manifest"):
        ship_card(out, bundle)
    (bundle / "manifest.json").write_text("{}")
    assert json.loads(ship_card(out, bundle).read_text())["format"] == "pallet6d-data-card"
    assert (bundle / "data_card.md").read_text() == (out / "card.md").read_text()
    with pytest.raises(ValueError, match="import"):
        ship_card(tmp_path / "nothing", bundle)


def test_card_lists_the_pretrained_weights_the_detector_started_from(raw_sources, tmp_path):
    pytest.importorskip("torch")
    from pallet6d.export.pretrained_dw import PUBLISHED_WEIGHTS
    from pallet6d.export.real_data import ship_card

    raw, sources = raw_sources
    out = tmp_path / "real"
    import_sources(raw, out, sources)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    sha = next(iter(PUBLISHED_WEIGHTS))

    def report(pretrained):
        (bundle / "report.json").write_text(json.dumps(
            {"provenance": {"training": {"detector": {"pretrained": pretrained}}}}))

    report({"file": "yolox_nano.onnx", "sha256": sha, "convolutions": 104})
    card = json.loads(ship_card(out, bundle).read_text())
    assert card["format"] == "pallet6d-data-card" and card["pretrained_weights"]["sha256"] == sha
    assert card["pretrained_weights"]["licence"] == PUBLISHED_WEIGHTS[sha]["licence"]
    assert "## Pretrained weights" in (bundle / "data_card.md").read_text()
    report({"file": "other.onnx", "sha256": "0" * 64})
    with pytest.raises(ValueError, match="no licence, no use"):
        ship_card(out, bundle)
    report(None)                                       # a detector started from no published weights
    assert "pretrained_weights" not in json.loads(ship_card(out, bundle).read_text())


def test_validation_cut_keeps_capture_time_windows_together():
    from pallet6d.export.real_data import ImageRecord
    from pallet6d.export.real_samples import real_train_val, validation_unit

    def rec(stem, seq, split="train", conv="whole_pallet"):
        return ImageRecord(image="x.jpg", source="s", stem=stem, width=10, height=10, boxes_xyxy=[[0, 0, 5, 5]],
                           convention=conv, kinds=["wood"], sequence=seq, split=split)

    same = [rec(f"15791638{k:02d}-1", "s/2020-01-16") for k in range(0, 60, 7)]     # one 10-minute window
    later = [rec(f"15791650{k:02d}-1", "s/2020-01-16") for k in range(0, 60, 7)]
    assert len({validation_unit(r) for r in same}) == 1 != len({validation_unit(r) for r in same + later})
    assert validation_unit(rec("clip-0001", "s/clip-000")) == "s/clip-000"
    others = [rec("1579163800-1", "s/d", split="heldout"), rec("1579163800-2", "s/d", conv="loaded_unit")]
    train, val = real_train_val(same + later + others, val_fraction=0.3)
    assert val and train and len(train) + len(val) == len(same + later)
    assert {validation_unit(r) for r in train}.isdisjoint(validation_unit(r) for r in val)


def test_subsample_always_keeps_the_rare_kind():
    from pallet6d.export.real_samples import real_train_val

    def rec(k, kinds):
        return ImageRecord(image=f"i{k}.jpg", source="s", stem=f"clip_mp4-{k:04d}", width=10, height=10,
                           boxes_xyxy=[[1, 1, 5, 5]], convention="whole_pallet", kinds=kinds,
                           sequence=f"s/{k}", split="train")

    recs = [rec(k, ["wood"]) for k in range(40)] + [rec(100 + k, ["plastic", "loaded"]) for k in range(3)]
    plain, _ = real_train_val(recs, 0.0, max_images=10, seed=3)
    kept, _ = real_train_val(recs, 0.0, max_images=10, seed=3, keep_kinds=("plastic",))
    assert len(plain) == len(kept) == 10
    assert sum("plastic" in r.kinds for r in kept) == 3
    # without kinds to keep, the draw is the one it always was
    rng_pick = np.sort(np.random.default_rng(3).choice(len(recs), 10, replace=False))
    assert [r.stem for r in plain] == [recs[i].stem for i in rng_pick]
