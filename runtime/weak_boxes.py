"""Weak detections: boxes the detector scores under its threshold are posed too, and kept only where the depth shows
a pallet's structure clearly. Pure numpy.

The detector is least sure of what a forklift most needs: pallets seen near and obliquely, and types it saw
little of (on calibrated forklift views nearly one in five of the pallets under 4 m has a box on it that scores
under the detector's 0.25), and of pallets mostly hidden behind others. Lowering the threshold for every box accepts
poses on carton stacks and loads, whose structure evidence is weak; a box the detector is unsure of is therefore
asked for the evidence those lack: its pose's structure is judged (`structure.py`; with a calibration levelled on the
floor first, `level.py`), and a weak box is kept only where nearly every ray agrees with the posed pallet and its
openings are open (docs/experiments/forklift.md, "Weak detections", "Weak detections without a calibration").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["WeakBoxes", "weak_box_failures", "inside_fraction"]

CUT_NOTE = " (the image's top or bottom edge cuts the box)"


@dataclass(frozen=True)
class WeakBoxes:
    """Which weak detections are posed and what they must show.

    :ivar score_threshold: detections scoring above this (and not above `EstimatorOptions.score_threshold`) are
        posed.
    :ivar min_agreement: their structure agreement (`StructureScore.agreement`) must reach this...
    :ivar min_open_fraction: ...and their open fraction (`StructureScore.open_fraction`) this. On calibrated
        forklift views the carton stacks and loads posed from weak boxes show open fractions up to 0.43; some
        pallets seen 30-40 degrees off their face 0.74-0.82.
    :ivar min_open_fraction_cut: the open fraction asked where the image's top or bottom edge cuts the box
        (`StructureScore.box_cut`): the object's height is not seen and its pose is less certain; the one carton
        pose of the tuned pallet-free views that reaches 0.7 is on such a box (docs/experiments/forklift.md, "Weak
        boxes seen obliquely").
    :ivar max_inside: a weak box that lies at least this much (a fraction of its area) inside a stronger detection's
        box is a part of what that one found: it is not posed ("duplicate").
    :ivar min_confidence: the pose of a box the detector is sure of whose network confidence is under
        `EstimatorOptions.min_confidence` but at least this is weak too (the network unsure of it, as the detector
        is of a weak box); a weak box's or a depth proposal's pose still needs `EstimatorOptions.min_confidence`.
        On the calibrated forklift validation frames such poses, kept with clear structure, add 5 pallets of 470
        within 5 cm and no wrong pose (docs/experiments/forklift.md, "Poses the network is unsure of").
    """

    score_threshold: float = 0.1
    min_agreement: float = 0.85
    min_open_fraction: float = 0.7
    min_open_fraction_cut: float = 0.85
    max_inside: float = 0.9
    min_confidence: float = 0.05

    def __post_init__(self) -> None:
        for name in ("score_threshold", "min_agreement", "min_open_fraction", "min_open_fraction_cut", "max_inside",
                     "min_confidence"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"WeakBoxes.{name} must be a number in [0, 1], got {v!r}")


def weak_box_failures(agreement: np.ndarray, open_fraction: np.ndarray, params: WeakBoxes,
                      box_cut: np.ndarray | None = None) -> list[str]:
    """Why each weak detection's posed pallet falls short ("" where it does not).

    :param agreement: (n,) structure agreement of the poses. :param open_fraction: (n,) their open fractions
        (NaN counts as short). :param box_cut: (n,) bool: boxes the image's top or bottom edge cuts
        (`StructureScore.box_cut`; None: none).
    :return: n sentences."""
    agreement = np.asarray(agreement, dtype=np.float64).reshape(-1)
    open_fraction = np.asarray(open_fraction, dtype=np.float64).reshape(-1)
    cut = np.zeros(len(agreement), dtype=bool) if box_cut is None else np.asarray(box_cut, dtype=bool).reshape(-1)
    if not agreement.shape == open_fraction.shape == cut.shape:
        raise ValueError(f"weak_box_failures: {agreement.shape[0]} agreements but {open_fraction.shape[0]} "
                         f"open fractions and {cut.shape[0]} cut flags")
    out = []
    for a, o, c in zip(agreement, open_fraction, cut):
        short = []
        if not a >= params.min_agreement:
            short.append(f"agreement {a:.2f} < {params.min_agreement}")
        least = params.min_open_fraction_cut if c else params.min_open_fraction
        if not o >= least:
            short.append(f"openings open {o:.2f} < {least}" + (CUT_NOTE if c else ""))
        out.append(", ".join(short))
    return out


def inside_fraction(boxes_xyxy: np.ndarray, others_xyxy: np.ndarray) -> np.ndarray:
    """The largest share of each box's area inside one of the other boxes.

    :param boxes_xyxy: (n, 4) pixels. :param others_xyxy: (m, 4) pixels. :return: (n,) in [0, 1] (0 without
        others, or for a box of no area)."""
    a = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(others_xyxy, dtype=np.float64).reshape(-1, 4)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a))
    iw = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    ih = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    area = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = (iw * ih).max(axis=1) / area
    return np.where(area > 0, frac, 0.0)
