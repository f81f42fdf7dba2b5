"""What `PalletEstimator` returns: small validated dataclasses (numpy only).

- `FitScore`: how well a posed pallet model agrees with the observed depth (see `fit.py`).
- `PalletPose`: one accepted pallet: `T_cam_pallet`, quaternion, network confidence, detector score,
  box, valid-point count, fit score, detector class and pallet type.
- `Rejection`: one detection that did not become a pose, with the reason; when a pose was computed but
  failed a check (fit score, network confidence) it is attached for debugging, never returned as accepted.
- `FrameResult`: everything about one frame: accepted poses, rejections, per-stage milliseconds.

An empty result is a normal result (`FrameResult.empty(...)`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .forklift import ForkliftInfo
from .geometry import rot_to_quat

__all__ = ["FitScore", "PalletPose", "Rejection", "FrameResult", "REJECT_REASONS"]

# Reasons a detection can be rejected, as stable codes an integrator can switch on.
REJECT_REASONS = (
    "box_outside_image",    # the detector's box does not overlap the image after clamping
    "too_few_points",       # fewer valid depth pixels in the box (and depth range) than min_valid_points
    "low_confidence",       # the best per-point network confidence is below min_confidence
    "poor_fit",             # the posed pallet model disagrees with the observed depth (fit.py)
    "no_pallet_structure",  # the depth does not show the pallet's boards and openings where the pose puts them,
                            # or the detector's box does not match the posed pallet (structure.py)
    "size_mismatch",        # the detector's box has no pallet's metric size at the depth inside it: depth scale or
                            # focal length off (structure.py)
    "depth_image_mismatch",  # the depth's edges do not coincide with the colour image's: another frame's depth,
                             # or depth not registered to the image (registration.py: every candidate of the frame)
    "time_budget",          # skipped: the frame's time budget was spent before this detection was posed
    "outside_roi",          # outside the region of interest or the depth hint (roi.py), dropped before posing
    "duplicate",            # its pose occupies the space of a higher-scoring detection's accepted pose (overlap.py),
                            # or, a weak detection, its box lies inside a stronger detection's (weak_boxes.py)
)


def _array(value, shape: tuple[int, ...], name: str, dtype=np.float64) -> np.ndarray:
    arr = np.asarray(value, dtype=dtype)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: must be finite, got {arr}")
    arr = arr.copy()
    arr.setflags(write=False)
    return arr


def _unit(value: float, name: str) -> float:
    v = float(value)
    if not (0.0 <= v <= 1.0):
        raise ValueError(f"{name}: expected a value in [0, 1], got {v}")
    return v


@dataclass(frozen=True)
class FitScore:
    """Agreement of a posed pallet model with the observed depth (all in [0, 1]).

    :ivar inlier_fraction: observed object points within the tolerance of the posed model.
    :ivar free_space_violation: posed model points that lie in front of the observed surface by more
        than the tolerance (the camera saw through where the model says wood is), among those that
        project onto valid depth.
    :ivar score: `inlier_fraction * (1 - free_space_violation)`.
    """

    inlier_fraction: float
    free_space_violation: float
    score: float

    def __post_init__(self) -> None:
        for name in ("inlier_fraction", "free_space_violation", "score"):
            object.__setattr__(self, name, _unit(getattr(self, name), f"FitScore.{name}"))

    def to_dict(self) -> dict:
        return {"inlier_fraction": round(self.inlier_fraction, 4),
                "free_space_violation": round(self.free_space_violation, 4), "score": round(self.score, 4)}


@dataclass(frozen=True)
class PalletPose:
    """One pallet's 6D pose in the camera frame (OpenCV axes, metres).

    :ivar T_cam_pallet: (4, 4) maps pallet-frame points into the camera frame.
    :ivar confidence: the network's per-point confidence of the chosen hypothesis.
    :ivar detector_score: the detector's class score for the box.
    :ivar box_xyxy: (4,) the detector's box in image pixels (x1, y1, x2, y2).
    :ivar n_valid_points: valid depth pixels in the box (before sampling/oversampling).
    :ivar fit: geometric agreement with the observed depth.
    :ivar class_name: the detector class.
    :ivar pallet_type: the pallet type whose geometry posed and checked it (e.g. "epal"; "" when unknown).
    :ivar T_vehicle_pallet: (4, 4) the pose in the calibrated vehicle frame (None without a calibration).
    :ivar forklift: front face, pockets and `pick_safe` (vehicle frame; None without a calibration or pockets).
    """

    T_cam_pallet: np.ndarray
    confidence: float
    detector_score: float
    box_xyxy: np.ndarray
    n_valid_points: int
    fit: FitScore
    class_name: str = "pallet"
    pallet_type: str = ""
    T_vehicle_pallet: np.ndarray | None = None
    forklift: ForkliftInfo | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.pallet_type, str) or not isinstance(self.class_name, str):
            raise TypeError(f"PalletPose.class_name and pallet_type must be str, got {type(self.class_name).__name__}, "
                            f"{type(self.pallet_type).__name__}")
        if self.T_vehicle_pallet is not None:
            object.__setattr__(self, "T_vehicle_pallet",
                               _array(self.T_vehicle_pallet, (4, 4), "PalletPose.T_vehicle_pallet"))
        if self.forklift is not None and not isinstance(self.forklift, ForkliftInfo):
            raise TypeError(f"PalletPose.forklift must be a ForkliftInfo or None, got {type(self.forklift).__name__}")
        T = _array(self.T_cam_pallet, (4, 4), "PalletPose.T_cam_pallet")
        R = T[:3, :3]
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-5) \
                or np.linalg.det(R) < 0:
            raise ValueError("PalletPose.T_cam_pallet: must be a rigid transform (orthonormal R, det +1, last row 0 0 0 1)")
        object.__setattr__(self, "T_cam_pallet", T)
        object.__setattr__(self, "box_xyxy", _array(self.box_xyxy, (4,), "PalletPose.box_xyxy"))
        object.__setattr__(self, "confidence", float(self.confidence))
        object.__setattr__(self, "detector_score", float(self.detector_score))
        if not np.isfinite(self.confidence) or not np.isfinite(self.detector_score):
            raise ValueError("PalletPose: confidence and detector_score must be finite")
        if int(self.n_valid_points) < 0:
            raise ValueError(f"PalletPose.n_valid_points must be >= 0, got {self.n_valid_points}")
        object.__setattr__(self, "n_valid_points", int(self.n_valid_points))
        if not isinstance(self.fit, FitScore):
            raise TypeError(f"PalletPose.fit must be a FitScore, got {type(self.fit).__name__}")

    @property
    def R(self) -> np.ndarray:
        """(3, 3) rotation pallet -> camera."""
        return self.T_cam_pallet[:3, :3]

    @property
    def t_m(self) -> np.ndarray:
        """(3,) position of the pallet's centre in the camera frame, metres."""
        return self.T_cam_pallet[:3, 3]

    @property
    def quat_wxyz(self) -> np.ndarray:
        """(4,) unit quaternion (w, x, y, z), w >= 0."""
        return rot_to_quat(self.R)

    def to_dict(self) -> dict:
        return {"class": self.class_name, "pallet_type": self.pallet_type,
                "t_m": [round(float(x), 4) for x in self.t_m],
                "quat_wxyz": [round(float(x), 5) for x in self.quat_wxyz],
                "confidence": round(self.confidence, 4), "detector_score": round(self.detector_score, 4),
                "box_xyxy": [round(float(x), 1) for x in self.box_xyxy], "n_valid_points": self.n_valid_points,
                "fit": self.fit.to_dict(), **self._vehicle_dict()}

    def _vehicle_dict(self) -> dict:
        if self.T_vehicle_pallet is None:
            return {}
        out = {"t_vehicle_m": [round(float(x), 4) for x in self.T_vehicle_pallet[:3, 3]],
               "quat_vehicle_wxyz": [round(float(x), 5) for x in rot_to_quat(self.T_vehicle_pallet[:3, :3])]}
        if self.forklift is not None:
            out["forklift"] = self.forklift.to_dict()
        return out


@dataclass(frozen=True)
class Rejection:
    """A detection that did not become a pose.

    :ivar reason: one of `REJECT_REASONS`.
    :ivar detail: a human-readable sentence (numbers included).
    :ivar pose: the pose that was computed, fit-scored and then rejected (the fit check), else None (a rejection before
        the fit was scored: too few points, low confidence, the time budget, ...).
    """

    box_xyxy: np.ndarray
    detector_score: float
    reason: str
    detail: str = ""
    n_valid_points: int = 0
    pose: PalletPose | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "box_xyxy", _array(self.box_xyxy, (4,), "Rejection.box_xyxy"))
        object.__setattr__(self, "detector_score", float(self.detector_score))
        if self.reason not in REJECT_REASONS:
            raise ValueError(f"Rejection.reason must be one of {REJECT_REASONS}, got {self.reason!r}")
        if self.pose is not None and not isinstance(self.pose, PalletPose):
            raise TypeError(f"Rejection.pose must be a PalletPose or None, got {type(self.pose).__name__}")

    def to_dict(self) -> dict:
        out = {"reason": self.reason, "detail": self.detail, "detector_score": round(self.detector_score, 4),
               "box_xyxy": [round(float(x), 1) for x in self.box_xyxy], "n_valid_points": self.n_valid_points}
        if self.pose is not None:
            out["pose"] = self.pose.to_dict()
        return out


@dataclass(frozen=True)
class FrameResult:
    """Everything the estimator says about one frame.

    :ivar poses: accepted pallets, highest detector score first.
    :ivar rejected: detections that did not become poses, with reasons.
    :ivar timings_ms: milliseconds per stage (keys: preprocess, detector, decode_nms, pose_inputs,
        fusion, pose, selection, refine, fit, total).
    :ivar image_hw: (H, W) of the input frame.
    """

    poses: list[PalletPose]
    rejected: list[Rejection] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    image_hw: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        if not all(isinstance(p, PalletPose) for p in self.poses):
            raise TypeError("FrameResult.poses must hold PalletPose objects")
        if not all(isinstance(r, Rejection) for r in self.rejected):
            raise TypeError("FrameResult.rejected must hold Rejection objects")

    @classmethod
    def empty(cls, image_hw: tuple[int, int] = (0, 0), timings_ms: dict[str, float] | None = None) -> "FrameResult":
        return cls(poses=[], rejected=[], timings_ms=dict(timings_ms or {}), image_hw=tuple(image_hw))

    def to_dict(self) -> dict:
        return {"image_hw": list(self.image_hw), "poses": [p.to_dict() for p in self.poses],
                "rejected": [r.to_dict() for r in self.rejected],
                "timings_ms": {k: round(v, 2) for k, v in self.timings_ms.items()}}
