"""Weak detections in a calibrated view: boxes the detector scores under its threshold are posed too, and kept only
where the depth shows a pallet's structure clearly. Pure numpy.

The detector is least sure of what a forklift most needs: pallets seen near and obliquely, and types it saw
little of (on calibrated forklift views a quarter of the pallets under 4 m have a box on them that scores under
the detector's 0.25). Lowering the threshold for every box accepts poses on carton stacks and loads, whose
structure evidence is weak; a box the detector is unsure of is therefore asked for the evidence those lack: with a
calibration the pose is levelled on the floor and its structure judged there (`level.py`, `structure.py`), and a
weak box is kept only where nearly every ray agrees with the posed pallet and its openings are open
(docs/experiments/forklift.md, "Weak detections").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["WeakBoxes", "weak_box_failures"]


@dataclass(frozen=True)
class WeakBoxes:
    """Which weak detections are posed and what they must show.

    :ivar score_threshold: detections scoring at least this (and under `EstimatorOptions.score_threshold`) are
        posed when the frame comes with the camera's calibration.
    :ivar min_agreement: their structure agreement (`StructureScore.agreement`) must reach this...
    :ivar min_open_fraction: ...and their open fraction (`StructureScore.open_fraction`) this. On calibrated
        forklift views the carton stacks and loads posed from weak boxes show open fractions up to 0.43.
    """

    score_threshold: float = 0.1
    min_agreement: float = 0.85
    min_open_fraction: float = 0.85

    def __post_init__(self) -> None:
        for name in ("score_threshold", "min_agreement", "min_open_fraction"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"WeakBoxes.{name} must be a number in [0, 1], got {v!r}")


def weak_box_failures(agreement: np.ndarray, open_fraction: np.ndarray, params: WeakBoxes) -> list[str]:
    """Why each weak detection's posed pallet falls short ("" where it does not).

    :param agreement: (n,) structure agreement of the poses. :param open_fraction: (n,) their open fractions
        (NaN counts as short). :return: n sentences."""
    agreement = np.asarray(agreement, dtype=np.float64).reshape(-1)
    open_fraction = np.asarray(open_fraction, dtype=np.float64).reshape(-1)
    if agreement.shape != open_fraction.shape:
        raise ValueError(f"weak_box_failures: {agreement.shape[0]} agreements but {open_fraction.shape[0]} "
                         "open fractions")
    out = []
    for a, o in zip(agreement, open_fraction):
        short = []
        if not a >= params.min_agreement:
            short.append(f"agreement {a:.2f} < {params.min_agreement}")
        if not o >= params.min_open_fraction:
            short.append(f"openings open {o:.2f} < {params.min_open_fraction}")
        out.append(", ".join(short))
    return out
