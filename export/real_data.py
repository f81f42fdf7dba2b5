"""Real pallet photographs with box labels: one detection dataset from licensed public sources, and its data card.

    python -m pallet6d.export.real_data extract --mirrors MIRRORS --out data/real/raw
    python -m pallet6d.export.real_data import --raw data/real/raw --out data/real
    python -m pallet6d.export.real_data card --data data/real --bundle models/NAME

`extract` copies each source's labelled folders out of its git snapshot (`git archive` at the pinned commit);
`import` turns them into `OUT/images/<source>/<stem>.jpg`, `OUT/labels.json` (one record per image, boxes in
pixels of the stored image, xyxy) and the data card `OUT/card.json` + `OUT/card.md`; `card` copies the data card
beside a bundle trained on the data (`data_card.json`, `data_card.md`).

What `import` does, per source (`SOURCES`):
- pairs images and YOLO label files (a line is `class cx cy w h`, or `class x1 y1 x2 y2 ...`, a polygon whose
  bounding box is the box), keeps the source's pallet classes;
- undoes the uploader's square stretch: the image is resized to the source's original aspect ratio at the same
  pixel count (normalised label coordinates are unaffected);
- deduplicates by file stem without the `.rf.<hash>` suffix, across sources (the first source listed wins) and
  across the uploader's augmented copies (unaugmented splits first);
- records the label convention (`whole_pallet`, the detector's convention, or `loaded_unit`: the box covers the load
  as well) and the pallet kinds shown; frames of a source with labels of other objects but no pallet are
  pallet-free negatives;
- gives every image a capture sequence: the capture day for LOCO (its file names start with the Unix time of the
  frame; its five days are its five warehouses), a video's run of frames, or a run of photos by their file-name
  timestamps; then holds out whole sequences: a sequence is never in two splits.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import logging
import re
import subprocess
import sys
import tarfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .unit_boxes import PALLET_COLOURS, colour_mask, pallet_boxes_in_units

__all__ = ["Source", "SOURCES", "ImageRecord", "parse_yolo_label", "file_stem", "unstretched_size",
           "sequence_of", "nearest_labels", "split_by_sequence", "import_sources", "write_card",
           "load_records", "ship_card", "box_size_bins", "SIZE_BINS"]

log = logging.getLogger(__name__)

CONVENTIONS = ("whole_pallet", "loaded_unit")
SEQUENCE_RULES = ("capture-day", "video", "timestamp")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class Source:
    """One licensed image set inside a public git repository.

    :ivar folders: folders (relative to the repository) holding `images/` and `labels/`, unaugmented splits first.
    :ivar augmented_folders: folders whose images are the uploader's augmented copies (rotations etc.).
    :ivar pallet_classes: label class ids that are pallets; `other_classes`: labelled non-pallet objects.
    :ivar original_aspect: width / height of the photographs before the uploader stretched them square.
    :ivar sequence_rule: "capture-day" (stem starts with Unix seconds or milliseconds: the day is the scene; an
        image without one joins its nearest dated neighbour's day by appearance), "video" (`<name>-NNNN`) or
        "timestamp" (`YYYYMMDD_HHMMSS`).
    """

    name: str
    repo: str
    commit: str
    folders: tuple[str, ...]
    licence: str
    attribution: str
    url: str
    pallet_classes: tuple[int, ...]
    original_aspect: float
    aspect_known: bool
    convention: str
    kinds: tuple[str, ...]
    sequence_rule: str
    shows: str
    augmented_folders: tuple[str, ...] = ()
    other_classes: tuple[int, ...] = ()
    licence_file: str = ""
    pallet_colour: str = ""     # loaded_unit sources: the pallets' colour (`unit_boxes.PALLET_COLOURS`) finds them

    def __post_init__(self) -> None:
        if self.convention not in CONVENTIONS:
            raise ValueError(f"source {self.name}: convention must be one of {CONVENTIONS}, got {self.convention!r}")
        if self.sequence_rule not in SEQUENCE_RULES:
            raise ValueError(f"source {self.name}: unknown sequence rule {self.sequence_rule!r}")
        if self.original_aspect <= 0:
            raise ValueError(f"source {self.name}: original_aspect must be > 0")
        if self.pallet_colour and (self.convention != "loaded_unit" or self.pallet_colour not in PALLET_COLOURS):
            raise ValueError(f"source {self.name}: pallet_colour needs convention 'loaded_unit' and one of "
                             f"{sorted(PALLET_COLOURS)}, got {self.pallet_colour!r}")

    @property
    def all_folders(self) -> tuple[str, ...]:
        return self.folders + self.augmented_folders


def _loco_copy(name: str, repo: str, commit: str, root: str, licence: str, attribution: str, url: str) -> Source:
    """Another upload of LOCO frames (segmentation labels: class 0 floor, class 1 pallet)."""
    return Source(name=name, repo=repo, commit=commit, folders=tuple(f"{root}/{s}" for s in ("valid", "test", "train")),
                  licence=licence, licence_file=f"{root}/README.dataset.txt",
                  attribution=f"{attribution}, frames of TUM LOCO (CC0)", url=url, pallet_classes=(1,),
                  other_classes=(0,), original_aspect=16 / 9, aspect_known=False, convention="whole_pallet",
                  kinds=("wood",), sequence_rule="capture-day", shows="the LOCO test frames again (segmentation "
                  "polygons)")


_LOCO = "data/industry_dataset3.v1i.yolov8"
_AGUS = "yolov5-lidar-fusion/datasets/pallet"

SOURCES: tuple[Source, ...] = (
    Source(name="loco", repo="alaahatoum/pallet-detection-ground-segmentation-ros2",
           commit="ae0ff1d7d56c4d9c92914cc78c31723263c03dc0",
           folders=(f"{_LOCO}/valid", f"{_LOCO}/test"), augmented_folders=(f"{_LOCO}/train",),
           licence="CC BY 4.0 (Roboflow export industry_dataset3 v1); photographs from TUM LOCO, CC0",
           licence_file=f"{_LOCO}/README.dataset.txt",
           attribution="industry_dataset3 by Roboflow user robot-potk5 (CC BY 4.0), frames of LOCO: Logistics "
                       "Objects in Context, Mayershofer et al., TUM fml, ICMLA 2020 (CC0)",
           url="https://universe.roboflow.com/robot-potk5/industry_dataset3/dataset/1 ; "
               "https://github.com/tum-fml/loco",
           pallet_classes=(1,), other_classes=(0, 2, 3, 4), original_aspect=16 / 9, aspect_known=False,
           convention="whole_pallet", kinds=("wood",), sequence_rule="capture-day",
           shows="European warehouses seen from walking height: wooden EUR pallets on floors and in racks, loaded "
                 "and empty, many small and far; about 24 pallets per image"),
    Source(name="agus-wooden", repo="AgusRaharja69/pallet-detection-distance-cal",
           commit="3780a9d001f30c4113a861d1f76b323f7d7fe7f4",
           folders=(f"{_AGUS}/valid", f"{_AGUS}/test", f"{_AGUS}/train"),
           licence="CC BY 4.0", licence_file=f"{_AGUS}/README.dataset.txt",
           attribution="Palet dataset v5 by Roboflow user agus (CC BY 4.0)",
           url="https://universe.roboflow.com/agus/palet-zsfnn/dataset/5",
           pallet_classes=(0,), original_aspect=4 / 3, aspect_known=False, convention="whole_pallet",
           kinds=("wood",), sequence_rule="timestamp",
           shows="single small wooden pallets, often stacked, front-on at floor level from close range "
                 "(forklift-like)"),
    Source(name="ranggarh-plastic", repo="ranggarh/pallet-counter", commit="981f761040ba340adbd2ee077e3e321cd7611292",
           folders=("valid", "test"), augmented_folders=("train",), licence="CC BY 4.0",
           licence_file="README.dataset.txt",
           attribution="Palet Counter With Zone Detect v3 by Roboflow user ranggadev (CC BY 4.0)",
           url="https://universe.roboflow.com/ranggadev/palet-counter-with-zone-detect-lxfz6/dataset/3",
           pallet_classes=(0,), original_aspect=1024 / 579, aspect_known=True, convention="loaded_unit",
           kinds=("plastic", "loaded"), sequence_rule="video", pallet_colour="red",
           shows="red plastic pallets loaded with beer cases on a roller conveyor, frames of two videos (the "
                 "repository's unlabelled `dataset/` folder holds the 1024x579 originals of the `palet` frames); "
                 "the box covers the whole loaded unit"),
    # The two below hold only copies of LOCO frames already imported above; listed so the card says why they add
    # no image (deduplicated by stem).
    _loco_copy("phybhavya-loco-copy", "phybhavya/Pallet_detection", "399cba8d1174cc0c221808ef759a2f649a02a58c",
               "datasets", "MIT", "pallet-detecction v1 by Roboflow user dev-mdtnd (MIT)",
               "https://universe.roboflow.com/dev-mdtnd/pallet-detecction/dataset/1"),
    _loco_copy("vybhavraghav-loco-copy", "vybhavraghav/Pallets-detection", "b1e6f52988ebc158519d1a6ce5d59d28483e9f52",
               "src/Dataset", "CC BY 4.0", "Pallets v2 by Roboflow user spam-raghav (CC BY 4.0)",
               "https://universe.roboflow.com/spam-raghav/pallets-e5c5a/dataset/2"),
)


@dataclass
class ImageRecord:
    """One imported image. Boxes are xyxy pixels of the stored (unstretched) image."""

    image: str            # path relative to the dataset root
    source: str
    stem: str
    width: int
    height: int
    boxes_xyxy: list[list[float]]
    convention: str
    kinds: list[str]
    sequence: str
    split: str = "train"
    negative: bool = False
    augmented: bool = False
    origin: str = ""      # path inside the source repository
    boxes_from: str = "label"   # "label", or "colour": found inside the uploader's loaded-unit boxes (`unit_boxes`)
    unit_boxes_xyxy: list[list[float]] = field(default_factory=list)   # where "colour": the loaded-unit boxes

    def box_array(self) -> np.ndarray:
        """(n, 4) float64 xyxy pixels."""
        return np.asarray(self.boxes_xyxy, np.float64).reshape(-1, 4)


# ------------------------------------------------------------------------------------------------ parsing


def file_stem(filename: str) -> str:
    """The uploader's original stem: `1000736-6303_jpg.rf.92c0...jpg` -> `1000736-6303`."""
    stem = Path(filename).name
    stem = re.sub(r"\.(jpe?g|png|txt)$", "", stem, flags=re.IGNORECASE)
    stem = re.sub(r"\.rf\.[0-9a-fA-F]+$", "", stem)
    return re.sub(r"_(jpe?g|png)$", "", stem, flags=re.IGNORECASE)


def parse_yolo_label(text: str, keep_classes: Iterable[int]) -> tuple[np.ndarray, set[int]]:
    """Boxes of the kept classes from a YOLO label file.

    :param text: lines `cls cx cy w h` (box) or `cls x1 y1 x2 y2 ...` (polygon, >= 3 points), normalised.
    :return: (n, 4) float64 normalised xyxy clipped to [0, 1] (degenerate boxes dropped), and the set of every
        class id present in the file.
    :raises ValueError: a line that is neither a box nor a polygon.
    """
    keep = set(keep_classes)
    boxes, classes = [], set()
    for ln, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        try:
            cls, vals = int(float(parts[0])), [float(v) for v in parts[1:]]
        except ValueError:
            raise ValueError(f"label line {ln}: not numbers: {line!r}") from None
        classes.add(cls)
        if len(vals) == 4:
            cx, cy, w, h = vals
            box = [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]
        elif len(vals) >= 6 and len(vals) % 2 == 0:
            pts = np.asarray(vals).reshape(-1, 2)
            box = [*pts.min(0), *pts.max(0)]
        else:
            raise ValueError(f"label line {ln}: expected 4 box values or an even count >= 6 of polygon values, "
                             f"got {len(vals)}")
        if cls in keep:
            boxes.append(box)
    b = np.clip(np.asarray(boxes, np.float64).reshape(-1, 4), 0.0, 1.0)
    return b[(b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])], classes


def unstretched_size(stretched_wh: tuple[int, int], aspect: float) -> tuple[int, int]:
    """(width, height) with the original aspect ratio (width / height) and the stretched image's pixel count."""
    w, h = stretched_wh
    if w <= 0 or h <= 0 or aspect <= 0:
        raise ValueError(f"unstretched_size: need positive sizes and aspect, got {stretched_wh}, {aspect}")
    area = float(w * h)
    return max(1, int(round(np.sqrt(area * aspect)))), max(1, int(round(np.sqrt(area / aspect))))


# ---------------------------------------------------------------------------------------------- sequences


_VIDEO = re.compile(r"^(.*?)[-_]?(\d+)$")
VIDEO_CHUNK = 25   # consecutive frame numbers per sequence where a source names frames of a video
_STAMP = re.compile(r"(\d{8})_(\d{2})(\d{2})(\d{2})")


def sequence_of(stem: str, rule: str) -> str | None:
    """A stem's sequence key under `rule`: "capture-day": the UTC day of a stem that starts with Unix seconds (10
    digits) or milliseconds (13); "video" (`<video><sep><frame number>`): the video name and the run of
    VIDEO_CHUNK consecutive frame numbers; "timestamp": the seconds of the day of the file name's timestamp, as a
    sortable string (grouped into runs by `timestamp_runs`). None when the stem has none."""
    if rule == "capture-day":
        head = stem.split("-")[0]
        if not head.isdigit() or len(head) not in (10, 13):
            return None
        t = int(head) / (1000.0 if len(head) == 13 else 1.0)
        return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).strftime("%Y-%m-%d")
    if rule == "video":
        m = _VIDEO.match(stem)
        return f"{m.group(1)}-{int(m.group(2)) // VIDEO_CHUNK:03d}" if m else None
    if rule == "timestamp":
        m = _STAMP.search(stem)
        if not m:
            return None
        day, hh, mm, ss = m.groups()
        return f"{day}_{int(hh) * 3600 + int(mm) * 60 + int(ss):05d}"
    raise ValueError(f"sequence_of: rule must be one of {SEQUENCE_RULES}, got {rule!r}")


def timestamp_runs(keys: Sequence[str], max_gap_s: int = 120) -> list[str]:
    """Group timestamp keys (`sequence_of(..., "timestamp")`) into runs with gaps <= max_gap_s; one name per key."""
    order = sorted(set(keys))
    run_of, run, prev = {}, None, None
    for k in order:
        day, sec = k.split("_")
        if prev is None or day != prev[0] or int(sec) - prev[1] > max_gap_s:
            run = f"{day}-{sec}"
        run_of[k], prev = run, (day, int(sec))
    return [run_of[k] for k in keys]


def thumbnail(rgb: np.ndarray, size: tuple[int, int] = (16, 12)) -> np.ndarray:
    """Appearance descriptor: the central 70 % of the image (robust to the uploader's small rotations and crops),
    shrunk to `size` (w, h), colour, zero-mean and unit norm. :return: (h * w * 3,) float64."""
    import cv2

    h, w = rgb.shape[:2]
    y0, x0 = int(0.15 * h), int(0.15 * w)
    small = cv2.resize(rgb[y0:h - y0, x0:w - x0], size, interpolation=cv2.INTER_AREA).astype(np.float64).ravel()
    small -= small.mean()
    return small / max(np.linalg.norm(small), 1e-9)


def nearest_labels(query: np.ndarray, ref: np.ndarray, ref_labels: Sequence[str]) -> list[str]:
    """The label of each query descriptor's nearest reference descriptor (Euclidean).

    :param query: (n, d); :param ref: (m, d), m >= 1; :param ref_labels: m labels. :return: n labels.
    """
    query, ref = np.asarray(query, np.float64), np.asarray(ref, np.float64)
    if len(query) == 0:
        return []
    if len(ref) == 0 or len(ref) != len(ref_labels):
        raise ValueError(f"nearest_labels: need m >= 1 references with m labels, got {len(ref)} and {len(ref_labels)}")
    d = (query ** 2).sum(1)[:, None] - 2 * query @ ref.T + (ref ** 2).sum(1)[None]
    return [ref_labels[j] for j in d.argmin(1)]


def split_by_sequence(sequences: Sequence[str], heldout_fraction: float, salt: str = "") -> list[str]:
    """"heldout" or "train" per image: whole sequences, in a fixed hash order, go to the held-out split until it
    holds at least `heldout_fraction` of the images. With two or more sequences both splits get at least one.
    """
    if not 0.0 <= heldout_fraction < 1.0:
        raise ValueError(f"heldout_fraction must be in [0, 1), got {heldout_fraction}")
    counts: dict[str, int] = {}
    for s in sequences:
        counts[s] = counts.get(s, 0) + 1
    order = sorted(counts, key=lambda s: hashlib.sha1(f"{salt}/{s}".encode()).hexdigest())
    held: set[str] = set()
    total, n_held = len(sequences), 0
    for s in order:
        if n_held >= heldout_fraction * total or len(held) >= len(order) - 1:
            break
        held.add(s)
        n_held += counts[s]
    return ["heldout" if s in held else "train" for s in sequences]


# -------------------------------------------------------------------------------------------------- import


def _pairs(folder: Path) -> list[tuple[Path, Path | None]]:
    images = sorted(p for p in (folder / "images").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    return [(p, (folder / "labels" / p.with_suffix(".txt").name)) for p in images]


def import_sources(raw_root: str | Path, out_root: str | Path, sources: Sequence[Source] = SOURCES,
                   heldout_fraction: float = 0.2, seed: int = 0,
                   jpeg_quality: int = 92) -> list[ImageRecord]:
    """Import every source found under `raw_root/<source.name>/` (as `extract` writes it) into `out_root`.

    :return: the records written to `out_root/labels.json`.
    """
    import cv2

    raw_root, out_root = Path(raw_root), Path(out_root)
    seen: dict[str, str] = {}            # stem -> source that holds it
    records: list[ImageRecord] = []
    dropped: dict[str, dict[str, int]] = {}
    for src in sources:
        base = raw_root / src.name
        stats = dropped.setdefault(src.name, {"duplicates": 0, "unlabelled": 0, "unreadable": 0})
        if not base.is_dir():
            log.warning("source %s: %s not found, skipped", src.name, base)
            continue
        recs, descs = [], []
        for folder in src.all_folders:
            augmented = folder in src.augmented_folders
            for img_path, lbl_path in _pairs(base / folder):
                stem = file_stem(img_path.name)
                if stem in seen:
                    stats["duplicates"] += 1
                    continue
                if lbl_path is None or not lbl_path.exists():
                    stats["unlabelled"] += 1
                    continue
                boxes_n, classes = parse_yolo_label(lbl_path.read_text(), src.pallet_classes)
                bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
                if bgr is None:
                    stats["unreadable"] += 1
                    continue
                seen[stem] = src.name
                w, h = unstretched_size((bgr.shape[1], bgr.shape[0]), src.original_aspect)
                bgr = cv2.resize(bgr, (w, h), interpolation=cv2.INTER_AREA if w * h <= bgr.size // 3
                                 else cv2.INTER_LINEAR)
                rel = Path("images") / src.name / f"{stem}.jpg"
                (out_root / rel).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(out_root / rel), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
                boxes = boxes_n * np.array([w, h, w, h], np.float64)
                negative = len(boxes) == 0 and bool(classes & set(src.other_classes))
                if len(boxes) == 0 and not negative:
                    stats["unlabelled"] += 1    # an empty label file says nothing: pallets may be unlabelled
                rec = ImageRecord(image=str(rel), source=src.name, stem=stem, width=w, height=h,
                                  boxes_xyxy=np.round(boxes, 2).tolist(), convention=src.convention,
                                  kinds=list(src.kinds), sequence="", negative=negative,
                                  augmented=augmented, origin=str(img_path.relative_to(base)))
                if src.pallet_colour and len(boxes):
                    _pallet_boxes_by_colour(rec, bgr[:, :, ::-1], src.pallet_colour)
                recs.append(rec)
                if src.sequence_rule == "capture-day":
                    descs.append(thumbnail(bgr[:, :, ::-1]))
        keep = [k for k, r in enumerate(recs) if r.boxes_xyxy or r.negative]
        for k in sorted(set(range(len(recs))) - set(keep)):
            (out_root / recs[k].image).unlink(missing_ok=True)
        recs = [recs[k] for k in keep]
        if src.sequence_rule == "capture-day":
            descs = [descs[k] for k in keep]
            days = [sequence_of(r.stem, "capture-day") for r in recs]
            dated = [k for k, d in enumerate(days) if d is not None]
            undated = [k for k, d in enumerate(days) if d is None]
            if dated:
                for k, d in zip(undated, nearest_labels([descs[k] for k in undated], [descs[k] for k in dated],
                                                        [days[k] for k in dated])):
                    days[k] = d
            for r, d in zip(recs, days):
                r.sequence = f"{src.name}/{d or 'undated'}"
        else:
            keys = [sequence_of(r.stem, src.sequence_rule) or r.stem for r in recs]
            if src.sequence_rule == "timestamp":
                stamped = [k for k in keys if re.fullmatch(r"\d{8}_\d{5}", k)]
                runs = dict(zip(stamped, timestamp_runs(stamped)))
                keys = [runs.get(k, k) for k in keys]
            for r, k in zip(recs, keys):
                r.sequence = f"{src.name}/{k}"
        for r, s in zip(recs, split_by_sequence([r.sequence for r in recs], heldout_fraction, salt=str(seed))):
            r.split = s
        log.info("source %s: %d images (%s)", src.name, len(recs), stats)
        records.extend(recs)
    out_root.mkdir(parents=True, exist_ok=True)
    (out_root / "labels.json").write_text(json.dumps([asdict(r) for r in records], indent=0))
    write_card(out_root, records, sources, dropped, heldout_fraction, seed)
    return records


def _pallet_boxes_by_colour(rec: ImageRecord, rgb: np.ndarray, colour: str) -> None:
    """Turn a loaded-unit record into a whole-pallet one where every unit's pallet is found by its colour; a record
    with any unit not found keeps its loaded-unit boxes (half-labelled photos would teach the detector that the
    other pallets are background)."""
    found = pallet_boxes_in_units(colour_mask(np.ascontiguousarray(rgb), PALLET_COLOURS[colour]), rec.box_array())
    if any(b is None for b in found):
        return
    rec.unit_boxes_xyxy = rec.boxes_xyxy
    rec.boxes_xyxy = np.round(np.stack(found), 2).tolist()
    rec.convention, rec.boxes_from = "whole_pallet", "colour"


def load_records(root: str | Path) -> list[ImageRecord]:
    """The records of an imported dataset (`root/labels.json`)."""
    path = Path(root) / "labels.json"
    if not path.exists():
        raise ValueError(f"{path} not found: import the real data first (python -m pallet6d.export.real_data)")
    return [ImageRecord(**r) for r in json.loads(path.read_text())]


# ---------------------------------------------------------------------------------------------------- card


SIZE_BINS = ("small", "medium", "large")


def box_size_bins(box_h_px: np.ndarray, image_h_px: float) -> np.ndarray:
    """Box size classes by box height as a fraction of the image height (the detector's letterbox scales by it):
    small < 8 % (under ~15 px at a 192 px tall input), medium 8-20 %, large >= 20 %.

    :param box_h_px: (n,) box heights. :return: (n,) names from SIZE_BINS.
    """
    f = np.asarray(box_h_px, np.float64).reshape(-1) / max(float(image_h_px), 1e-9)
    return np.where(f < 0.08, "small", np.where(f < 0.2, "medium", "large"))


def card_summary(records: Sequence[ImageRecord]) -> dict:
    """Counts per source and split: images, negatives, boxes, boxes per size bin, and images whose pallet boxes were
    found by colour inside loaded-unit boxes."""
    out: dict = {}
    for r in records:
        s = out.setdefault(r.source, {}).setdefault(r.split, {"images": 0, "negatives": 0, "boxes": 0,
                                                             "small": 0, "medium": 0, "large": 0,
                                                             "boxes_by_colour": 0, "sequences": set()})
        s["images"] += 1
        s["boxes_by_colour"] += int(r.boxes_from == "colour")
        s["negatives"] += int(r.negative)
        s["boxes"] += len(r.boxes_xyxy)
        s["sequences"].add(r.sequence)
        boxes = r.box_array()
        for name in box_size_bins(boxes[:, 3] - boxes[:, 1], r.height):
            s[str(name)] += 1
    for splits in out.values():
        for s in splits.values():
            s["sequences"] = len(s["sequences"])
    return out


def write_card(out_root: Path, records: Sequence[ImageRecord], sources: Sequence[Source],
               dropped: dict[str, dict[str, int]], heldout_fraction: float, seed: int) -> dict:
    """`card.json` and `card.md` beside the dataset: what every source is, its licence, counts and split."""
    summary = card_summary(records)
    split_rule = {"capture-day": "the capture day (file names start with the frame's Unix time; an image without "
                                 "one joins the day of its most similar dated image) is the sequence: whole days, "
                                 "i.e. whole warehouses, are held out",
                  "video": f"runs of {VIDEO_CHUNK} consecutive frame numbers of one video are one sequence; whole "
                           "runs are held out",
                  "timestamp": "photos taken within 2 minutes of each other (file-name timestamps) are one "
                               "sequence; whole sequences are held out"}
    card = {"format": "pallet6d-data-card", "format_version": 1, "dataset": "real pallet photographs",
            "box_convention": "whole_pallet: the pallet's visible extent, no load (as the simulator labels it); "
                              "loaded_unit boxes are kept but marked and not trained on by default",
            "heldout_fraction": heldout_fraction, "seed": seed, "sources": []}
    for src in sources:
        card["sources"].append({
            "name": src.name, "repository": f"https://github.com/{src.repo}", "commit": src.commit,
            "folders": list(src.all_folders), "licence": src.licence, "licence_file": src.licence_file,
            "attribution": src.attribution, "url": src.url, "shows": src.shows, "kinds": list(src.kinds),
            "label_convention": src.convention, "pallet_colour": src.pallet_colour,
            "original_aspect": round(src.original_aspect, 4), "aspect_known": src.aspect_known,
            "augmented_folders": list(src.augmented_folders), "split_rule": split_rule[src.sequence_rule],
            "dropped": dropped.get(src.name, {}), "counts": summary.get(src.name, {})})
    (out_root / "card.json").write_text(json.dumps(card, indent=1))
    (out_root / "card.md").write_text(card_markdown(card))
    return card


def card_markdown(card: dict) -> str:
    lines = ["# Data card: real pallet photographs", "",
             f"Box convention: {card['box_convention']}.", "",
             f"Held-out split: whole capture sequences, at least {card['heldout_fraction']:.0%} of each source's "
             "images; never trained or tuned on.", "",
             "| source | licence | split | images | negatives | boxes | small/medium/large | sequences |",
             "|---|---|---|---|---|---|---|---|"]
    for s in card["sources"]:
        counts = s["counts"] or {"-": {}}
        for split, c in sorted(counts.items()):
            lines.append(f"| {s['name']} | {s['licence']} | {split} | {c.get('images', 0)} | "
                         f"{c.get('negatives', 0)} | {c.get('boxes', 0)} | {c.get('small', 0)}/"
                         f"{c.get('medium', 0)}/{c.get('large', 0)} | {c.get('sequences', 0)} |")
    lines.append("")
    for s in card["sources"]:
        if not s["repository"]:           # a site's own photographs (`export/site_data.py`)
            lines += [f"## {s['name']}", "", f"- the site's own photographs, folder {', '.join(s['folders'])}",
                      f"- licence: {s['licence']}", f"- attribution: {s['attribution'] or '-'}",
                      f"- kinds: {', '.join(s['kinds'])}; label convention: {s['label_convention']}",
                      f"- split: {s['split_rule']}", f"- dropped: {s['dropped']}", ""]
            continue
        lines += [f"## {s['name']}", "", f"- repository: {s['repository']} at {s['commit']}, "
                  f"folders {', '.join(s['folders'])}", f"- licence: {s['licence']} ({s['licence_file']})",
                  f"- attribution: {s['attribution']}", f"- url: {s['url']}", f"- shows: {s['shows']}",
                  f"- kinds: {', '.join(s['kinds'])}; label convention: {s['label_convention']}",
                  *_colour_line(s),
                  f"- stretch undone to aspect {s['original_aspect']} "
                  f"({'known' if s['aspect_known'] else 'assumed from the image content'})",
                  f"- uploader's augmented copies: {', '.join(s['augmented_folders']) or 'none used'}",
                  f"- split: {s['split_rule']}", f"- dropped: {s['dropped']}", ""]
    return "\n".join(lines)


def _colour_line(source: dict) -> list[str]:
    if not source.get("pallet_colour"):
        return []
    found = {split: c.get("boxes_by_colour", 0) for split, c in sorted(source["counts"].items())}
    return [f"- pallet boxes found by the pallet's colour ({source['pallet_colour']}) inside the loaded-unit boxes "
            f"(pallet6d.export.unit_boxes), where every unit's pallet was found; those images count as whole-pallet "
            f"photos: {', '.join(f'{k} {v}' for k, v in found.items())}; the rest keep loaded-unit boxes"]


# ----------------------------------------------------------------------------------------------- extract


def extract(mirrors: Path, out: Path, sources: Sequence[Source] = SOURCES) -> None:
    """`git archive` each source's folders (and licence file) at its commit into `out/<name>/`."""
    for src in sources:
        git_dir = mirrors / src.repo.replace("/", "+") / "repo"
        if not git_dir.exists():
            raise ValueError(f"source {src.name}: no snapshot at {git_dir} (fetch github:{src.repo} first)")
        dest = out / src.name
        dest.mkdir(parents=True, exist_ok=True)
        paths = [*src.all_folders] + ([src.licence_file] if src.licence_file else [])
        proc = subprocess.run(["git", "--git-dir", str(git_dir), "archive", src.commit, *paths],
                              capture_output=True, check=False)
        if proc.returncode != 0:
            raise ValueError(f"source {src.name}: git archive failed: {proc.stderr.decode()[-300:]}")
        tar_path = dest / "_archive.tar"
        tar_path.write_bytes(proc.stdout)
        with tarfile.open(tar_path) as tf:
            tf.extractall(dest, filter="data")
        tar_path.unlink()
        log.info("extracted %s into %s", src.name, dest)


def ship_card(data_root: str | Path, bundle_dir: str | Path) -> Path:
    """Copy the data card of `data_root` into a bundle folder as `data_card.json` / `data_card.md`.

    :raises ValueError: no card under `data_root`, or `bundle_dir` is not a bundle (no manifest.json).
    """
    data_root, bundle_dir = Path(data_root), Path(bundle_dir)
    if not (bundle_dir / "manifest.json").exists():
        raise ValueError(f"{bundle_dir} is not a model bundle (no manifest.json)")
    card = data_root / "card.json"
    if not card.exists():
        raise ValueError(f"{card} not found: import the real data first")
    text_json, text_md = card.read_text(), (data_root / "card.md").read_text()
    weights = pretrained_weights_of(bundle_dir)
    if weights is not None:
        text_json = json.dumps({**json.loads(text_json), "pretrained_weights": weights}, indent=1)
        text_md += "\n" + "\n".join(["## Pretrained weights", "", "The detector started from these published weights:",
                                      "", *(f"- {k}: {v}" for k, v in weights.items()), ""])
    (bundle_dir / "data_card.json").write_text(text_json)
    (bundle_dir / "data_card.md").write_text(text_md)
    return bundle_dir / "data_card.json"


def pretrained_weights_of(bundle_dir: Path) -> dict | None:
    """The published weights a bundle's detector started from (its report's training record), with their source
    and licence; None when it started from none.

    :raises ValueError: weights whose source and licence are not known (`pretrained_dw.PUBLISHED_WEIGHTS`).
    """
    report = bundle_dir / "report.json"
    training = json.loads(report.read_text()).get("provenance", {}).get("training", {}) if report.exists() else {}
    record = (training.get("detector") or {}).get("pretrained")
    if not record:
        return None
    from .pretrained_dw import PUBLISHED_WEIGHTS       # torch: only for a detector that started from weights

    known = PUBLISHED_WEIGHTS.get(record.get("sha256", ""))
    if known is None:
        raise ValueError(f"{bundle_dir}: its detector started from {record.get('file')!r} (sha256 "
                         f"{record.get('sha256')}), whose source and licence are not known: no licence, no use")
    return {"file": record["file"], "sha256": record["sha256"], **known}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pallet6d.export.real_data", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("extract", help="copy the sources' labelled folders out of their git snapshots")
    e.add_argument("--mirrors", type=Path, required=True, help="folder of `owner+name/repo` git directories")
    e.add_argument("--out", type=Path, required=True)
    i = sub.add_parser("import", help="build the detection dataset and its data card")
    i.add_argument("--raw", type=Path, required=True, help="what `extract` wrote")
    i.add_argument("--out", type=Path, required=True)
    i.add_argument("--heldout-fraction", type=float, default=0.2)
    i.add_argument("--seed", type=int, default=0)
    c = sub.add_parser("card", help="copy the data card beside a bundle trained on this data")
    c.add_argument("--data", type=Path, required=True, help="the imported dataset (holds card.json)")
    c.add_argument("--bundle", type=Path, required=True)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.cmd == "extract":
            extract(args.mirrors, args.out)
        elif args.cmd == "card":
            print(f"wrote {ship_card(args.data, args.bundle)}")
        else:
            recs = import_sources(args.raw, args.out, heldout_fraction=args.heldout_fraction,
                                  seed=args.seed)
            print(f"wrote {len(recs)} images to {args.out}; card: {args.out / 'card.md'}")
    except ValueError as exc:
        print(f"real_data {args.cmd}: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
