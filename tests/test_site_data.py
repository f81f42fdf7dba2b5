"""A site's own labelled photographs added to an imported real dataset: records, split, card, merge, errors."""
import json
from dataclasses import asdict

import cv2
import numpy as np
import pytest

from pallet6d.export.real_data import ImageRecord, load_records
from pallet6d.export.real_samples import load_real_samples
from pallet6d.export.site_data import import_site, main


def _site(tmp_path, folders=(("rec-a", 30), ("rec-b", 10))):
    """Photographs 64 x 48 in recording folders, a label per image: a pallet box, every fifth one empty
    (pallet-free); the last image of rec-a without a label."""
    images, labels = tmp_path / "photos", tmp_path / "labels"
    for folder, n in folders:
        (images / folder).mkdir(parents=True)
        (labels / folder).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(images / folder / f"frame-{i:04d}.png"), np.full((48, 64, 3), i * 5 % 255, np.uint8))
            if folder == "rec-a" and i == n - 1:
                continue
            text = "" if i % 5 == 0 else "0 0.5 0.5 0.25 0.5\n3 0.2 0.2 0.1 0.1\n"
            (labels / folder / f"frame-{i:04d}.txt").write_text(text)
    return images, labels


def _other_source(root):
    """A dataset holding one record of another source, with its card."""
    (root / "images" / "loco").mkdir(parents=True)
    cv2.imwrite(str(root / "images" / "loco" / "x.jpg"), np.zeros((48, 64, 3), np.uint8))
    rec = ImageRecord(image="images/loco/x.jpg", source="loco", stem="x", width=64, height=48,
                      boxes_xyxy=[[1, 2, 30, 40]], convention="whole_pallet", kinds=["wood"], sequence="loco/d")
    (root / "labels.json").write_text(json.dumps([asdict(rec)]))
    source = {"name": "loco", "repository": "https://github.com/o/r", "commit": "c", "folders": ["f"],
              "licence": "CC BY 4.0", "licence_file": "L", "attribution": "a", "url": "u", "shows": "s",
              "kinds": ["wood"], "label_convention": "whole_pallet", "original_aspect": 1.78, "aspect_known": False,
              "augmented_folders": [], "split_rule": "r", "dropped": {}, "counts": {}}
    (root / "card.json").write_text(json.dumps({"format": "pallet6d-data-card", "format_version": 1,
                                                "box_convention": "b", "heldout_fraction": 0.2, "seed": 0,
                                                "sources": [source]}))


def test_a_sites_photographs_become_records_split_by_whole_sequences(tmp_path):
    images, labels = _site(tmp_path)
    into = tmp_path / "data"
    recs = import_site(images, labels, into, "hall-3", "own photographs, all rights reserved",
                       sequence_length=10, heldout_fraction=0.2)
    assert len(recs) == 39                                       # the unlabelled image is left out
    assert sum(r.negative for r in recs) == 8 and all(not r.boxes_xyxy for r in recs if r.negative)
    boxed = [r for r in recs if not r.negative]
    assert all(r.boxes_xyxy == [[24.0, 12.0, 40.0, 36.0]] for r in boxed)     # class 0 only, in pixels
    assert {r.sequence for r in recs} == {"hall-3/rec-a/0000", "hall-3/rec-a/0001", "hall-3/rec-a/0002",
                                          "hall-3/rec-b/0000"}
    split_of = {}
    for r in recs:
        assert split_of.setdefault(r.sequence, r.split) == r.split             # a sequence is never in two splits
    assert set(split_of.values()) == {"train", "heldout"}
    assert sum(r.split == "heldout" for r in recs) >= 0.2 * len(recs)
    assert all((into / r.image).is_file() for r in recs)
    assert [r.stem for r in load_records(into)] == [r.stem for r in recs]
    card = json.loads((into / "card.json").read_text())
    assert card["sources"][0]["name"] == "hall-3" and card["sources"][0]["dropped"] == {"unlabelled": 1,
                                                                                       "unreadable": 0}
    assert "own photographs, all rights reserved" in (into / "card.md").read_text()
    train, val, fp, _ = load_real_samples(into, max_side=640, val_fraction=0.2)     # the detector's --real reads it
    assert len(train) + len(val) == sum(r.split == "train" for r in recs) and len(val) > 0


def test_a_site_joins_the_dataset_and_replaces_itself_when_imported_again(tmp_path):
    into = tmp_path / "data"
    _other_source(into)
    images, labels = _site(tmp_path)
    import_site(images, labels, into, "hall-3", "own photographs")
    first = load_records(into)
    assert [r.source for r in first].count("loco") == 1 and len(first) == 40
    import_site(images, labels, into, "hall-3", "own photographs, CC BY 4.0", sequence_length=5)
    again = load_records(into)
    assert len(again) == 40 and [r.source for r in again].count("hall-3") == 39
    card = json.loads((into / "card.json").read_text())
    assert [s["name"] for s in card["sources"]] == ["loco", "hall-3"]
    assert card["sources"][0]["counts"]["train"]["images"] == 1
    assert card["sources"][1]["licence"] == "own photographs, CC BY 4.0"
    assert len(list((into / "images" / "hall-3").glob("*.jpg"))) == 39
    (labels / "rec-b" / "frame-0003.txt").write_text("0 0.5\n")          # a damaged label: nothing changes
    with pytest.raises(ValueError, match="frame-0003.txt"):
        import_site(images, labels, into, "hall-3", "own photographs")
    assert load_records(into) == again and len(list((into / "images" / "hall-3").glob("*.jpg"))) == 39
    assert sorted(p.name for p in (into / "images").iterdir()) == ["hall-3", "loco"]


@pytest.mark.parametrize("change, match", [
    ({"name": "Hall 3"}, "name must be"),
    ({"name": "loco"}, "public source"),
    ({"licence": " "}, "licence"),
    ({"sequence_length": 0}, "sequence_length"),
])
def test_bad_arguments_are_refused(tmp_path, change, match):
    images, labels = _site(tmp_path)
    args = {"images_dir": images, "labels_dir": labels, "into": tmp_path / "data", "name": "hall-3",
            "licence": "own photographs"} | change
    with pytest.raises(ValueError, match=match):
        import_site(**args)


def test_bad_files_are_named(tmp_path):
    images, labels = _site(tmp_path, folders=(("rec-a", 3),))
    (labels / "rec-a" / "frame-0001.txt").write_text("0 0.5 0.5\n")
    with pytest.raises(ValueError, match="frame-0001.txt"):
        import_site(images, labels, tmp_path / "data", "hall-3", "own photographs")
    with pytest.raises(ValueError, match="no .jpg"):
        import_site(tmp_path / "labels", labels, tmp_path / "data", "hall-3", "own photographs")
    with pytest.raises(ValueError, match="readable label"):
        import_site(images, tmp_path / "nowhere", tmp_path / "data", "hall-3", "own photographs")


def test_the_command_line(tmp_path, capsys):
    images, labels = _site(tmp_path, folders=(("rec-a", 12),))
    into = tmp_path / "data"
    assert main(["--images", str(images), "--labels", str(labels), "--name", "dock", "--licence", "own",
                 "--into", str(into), "--kinds", "plastic", "--sequence-length", "4"]) == 0
    assert "added 11 images of dock" in capsys.readouterr().out
    assert {tuple(r.kinds) for r in load_records(into)} == {("plastic",)}
    assert main(["--images", str(images), "--labels", str(labels), "--name", "epal!", "--licence", "own",
                 "--into", str(into)]) == 1
    assert "name must be" in capsys.readouterr().err


def test_the_real_data_benchmark_measures_the_sites_held_out_part_alone(tmp_path, capsys):
    import importlib.util
    from pathlib import Path

    images, labels = _site(tmp_path)
    into = tmp_path / "data"
    _other_source(into)
    recs = import_site(images, labels, into, "hall-3", "own photographs", sequence_length=10)
    script = Path(__file__).parents[1] / "benchmarks" / "real_data.py"
    spec = importlib.util.spec_from_file_location("real_data_benchmark", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    bundle = Path(__file__).parents[1] / "models" / "epal-default"
    assert mod.main(["--bundle", str(bundle), "--data", str(into), "--source", "elsewhere"]) == 2
    assert "from source(s) elsewhere" in capsys.readouterr().err
    out = tmp_path / "report"
    assert mod.main(["--bundle", str(bundle), "--int8", "--data", str(into), "--source", "hall-3", "--out",
                     str(out)]) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    held = [r for r in recs if r.split == "heldout"]
    assert report["settings"]["source"] == "hall-3"
    assert report["overall"]["boxes"] == sum(len(r.boxes_xyxy) for r in held)
    assert report["negative_frames"] == sum(r.negative for r in held)
