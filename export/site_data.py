"""A site's own labelled photographs, added to an imported real dataset (what `pallet6d train detector --real`
trains on and `benchmarks/real_data.py` measures), so the detector can be fine-tuned on the warehouse it will run in.

    python -m pallet6d.export.site_data --images DIR --labels DIR --name SITE --licence TEXT --into data/real \\
        [--pallet-classes 0] [--kinds wood,plastic] [--sequence-length 25] [--heldout-fraction 0.2]

- images: every .jpg / .jpeg / .png under `--images` (sub-folders included), e.g. the `rgb/` folders of
  `pallet6d record` recordings; labels: YOLO text files at the same relative path under `--labels` (`class cx cy w
  h` or a polygon per line, normalised), boxes around each pallet's visible extent without its load (the detector's
  convention). An image without a label file is skipped as unlabelled; an empty label file (or one with other classes
  only) marks a pallet-free photo, which trains the detector not to box floors, racks and cartons.
- sequences and the held-out split: the images of one folder in name order, `--sequence-length` at a time, are one
  sequence (neighbouring frames of a recording are near duplicates); whole sequences go to the held-out split until
  it holds `--heldout-fraction` of the site's images. The held-out split is never trained on: it is the site's own
  test of a fine-tuned detector (`benchmarks/real_data.py --source SITE`).
- the dataset under `--into` keeps its other sources; importing the same `--name` again replaces that site's images.
  The data card (`card.json`, `card.md`) gains the site as a source with the licence given, and is what a bundle
  trained on the data ships (`python -m pallet6d.export.real_data card`).
"""
from __future__ import annotations

import argparse
import json
import logging
import re
import shutil
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from .real_data import (IMAGE_SUFFIXES, SOURCES, ImageRecord, card_markdown, card_summary, load_records,
                        parse_yolo_label, split_by_sequence)

__all__ = ["import_site"]

log = logging.getLogger(__name__)

_NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")


def _site_entry(name: str, images_dir: Path, licence: str, attribution: str, kinds: Sequence[str],
                sequence_length: int, dropped: dict[str, int]) -> dict:
    """The site's entry in the data card (the fields `card_markdown` prints)."""
    return {"name": name, "repository": "", "commit": "", "folders": [images_dir.name], "licence": licence,
            "licence_file": "", "attribution": attribution, "url": "", "kinds": list(kinds),
            "shows": "the site's own photographs", "label_convention": "whole_pallet", "original_aspect": None,
            "aspect_known": True, "augmented_folders": [], "dropped": dropped,
            "split_rule": f"runs of {sequence_length} images of one folder in name order are one sequence; whole "
                          "runs are held out"}


def import_site(images_dir: str | Path, labels_dir: str | Path, into: str | Path, name: str, licence: str,
                attribution: str = "", pallet_classes: Sequence[int] = (0,), kinds: Sequence[str] = ("wood",),
                sequence_length: int = 25, heldout_fraction: float = 0.2, seed: int = 0,
                jpeg_quality: int = 92) -> list[ImageRecord]:
    """Add a site's labelled photographs to the dataset under `into` (created when missing), as source `name`.

    :return: the site's records, as written to `into/labels.json` beside the dataset's other sources.
    :raises ValueError: a bad name or argument, no images, a label file that is not YOLO, no labelled image.
    """
    import cv2

    images_dir, labels_dir, into = Path(images_dir), Path(labels_dir), Path(into)
    if not _NAME.fullmatch(name):
        raise ValueError(f"name must be lower-case letters, digits, '-' and '_', got {name!r}")
    if name in {s.name for s in SOURCES}:
        raise ValueError(f"name {name!r} is a public source's: choose another")
    if not licence.strip():
        raise ValueError("give the photographs' licence (e.g. 'own photographs, all rights reserved'): the data "
                         "card of every bundle trained on them names it")
    if int(sequence_length) < 1:
        raise ValueError(f"sequence_length must be >= 1, got {sequence_length}")
    if not images_dir.is_dir():
        raise ValueError(f"{images_dir} is not a folder")
    images = sorted(p for p in images_dir.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise ValueError(f"no .jpg, .jpeg or .png images under {images_dir}")

    # the photographs go to a new folder that replaces the site's old one only once every label has been read: a
    # failed import leaves the dataset as it was
    out_dir, new_dir = into / "images" / name, into / "images" / f".{name}.new"
    shutil.rmtree(new_dir, ignore_errors=True)
    dropped = {"unlabelled": 0, "unreadable": 0}
    records, index_in_folder = [], {}
    for path in images:
        rel = path.relative_to(images_dir)
        label = labels_dir / rel.with_suffix(".txt")
        if not label.is_file():
            dropped["unlabelled"] += 1
            continue
        try:
            boxes_n, _ = parse_yolo_label(label.read_text(), pallet_classes)
        except ValueError as exc:
            shutil.rmtree(new_dir, ignore_errors=True)
            raise ValueError(f"{label}: {exc}") from None
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            dropped["unreadable"] += 1
            continue
        h, w = bgr.shape[:2]
        stem = "__".join(rel.with_suffix("").parts)
        written = new_dir / f"{stem}.jpg"
        written.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(written), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]):
            shutil.rmtree(new_dir, ignore_errors=True)
            raise ValueError(f"could not write {written}")
        k = index_in_folder.get(rel.parent, 0)
        index_in_folder[rel.parent] = k + 1
        records.append(ImageRecord(image=str(Path("images") / name / written.name), source=name, stem=stem,
                                   width=w, height=h, boxes_xyxy=np.round(boxes_n * np.array([w, h, w, h]), 2).tolist(),
                                   convention="whole_pallet", kinds=list(kinds),
                                   sequence=f"{name}/{rel.parent.as_posix()}/{k // int(sequence_length):04d}",
                                   negative=len(boxes_n) == 0, origin=str(rel)))
    if not records:
        shutil.rmtree(new_dir, ignore_errors=True)
        raise ValueError(f"none of the {len(images)} images under {images_dir} has a readable label file under "
                         f"{labels_dir} (the same relative path, .txt)")
    for r, split in zip(records, split_by_sequence([r.sequence for r in records], heldout_fraction,
                                                   salt=str(seed))):
        r.split = split

    others = [r for r in load_records(into) if r.source != name] if (into / "labels.json").exists() else []
    everything = others + records
    shutil.rmtree(out_dir, ignore_errors=True)              # importing the site again replaces its photographs
    new_dir.rename(out_dir)
    (into / "labels.json").write_text(json.dumps([asdict(r) for r in everything], indent=0))
    _write_card(into, everything, _site_entry(name, images_dir, licence, attribution, kinds, sequence_length,
                                              dropped), heldout_fraction, seed)
    log.info("site %s: %d images (%d pallet-free), %d held out; %s", name, len(records),
             sum(r.negative for r in records), sum(r.split == "heldout" for r in records), dropped)
    return records


def _write_card(into: Path, records: Sequence[ImageRecord], site: dict, heldout_fraction: float, seed: int) -> None:
    """The dataset's card with `site` added (or replaced) and every source's counts taken again."""
    path = into / "card.json"
    card = json.loads(path.read_text()) if path.exists() else {
        "format": "pallet6d-data-card", "format_version": 1, "dataset": "real pallet photographs",
        "box_convention": "whole_pallet: the pallet's visible extent, no load (as the simulator labels it)",
        "heldout_fraction": heldout_fraction, "seed": seed, "sources": []}
    card["sources"] = [s for s in card["sources"] if s["name"] != site["name"]] + [site]
    summary = card_summary(records)
    for s in card["sources"]:
        s["counts"] = summary.get(s["name"], {})
    path.write_text(json.dumps(card, indent=1))
    (into / "card.md").write_text(card_markdown(card))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pallet6d.export.site_data", description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, required=True, help="folder of the site's photographs (sub-folders too)")
    ap.add_argument("--labels", type=Path, required=True, help="YOLO label files at the images' relative paths")
    ap.add_argument("--name", required=True, help="the site's source name in the dataset, e.g. hall-3")
    ap.add_argument("--licence", required=True, help="the photographs' licence, as the data card will state it")
    ap.add_argument("--attribution", default="", help="who took them, for the data card")
    ap.add_argument("--into", type=Path, required=True, help="the imported dataset (created when missing)")
    ap.add_argument("--pallet-classes", default="0", help="label class ids that are pallets (default 0)")
    ap.add_argument("--kinds", default="wood", help="pallet kinds shown: wood, plastic, loaded (comma-separated)")
    ap.add_argument("--sequence-length", type=int, default=25, help="images of one folder per sequence (25)")
    ap.add_argument("--heldout-fraction", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        classes = tuple(int(c) for c in args.pallet_classes.split(","))
        recs = import_site(args.images, args.labels, args.into, args.name, args.licence, args.attribution,
                           classes, tuple(k.strip() for k in args.kinds.split(",") if k.strip()),
                           args.sequence_length, args.heldout_fraction, args.seed)
    except ValueError as exc:
        print(f"site_data: {exc}", file=sys.stderr)
        return 1
    print(f"added {len(recs)} images of {args.name} to {args.into} ({sum(r.split == 'heldout' for r in recs)} held "
          f"out); card: {args.into / 'card.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
