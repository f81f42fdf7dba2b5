"""Region of interest and depth hint: detections where no pallet is expected are dropped before the pose stage
(reason "outside_roi"), which cuts false detections and the time spent posing them. Pure numpy.

A forklift usually knows where the pallet it was sent for is: roughly how far ahead (a depth hint, from the
warehouse system or the previous frames) and in which part of the image.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RegionOfInterest", "roi_filter"]


@dataclass(frozen=True)
class RegionOfInterest:
    """Where pallets are expected. Either criterion may be None (not used).

    :ivar box_xyxy: (4,) image box (x1, y1, x2, y2) pixels: a detection's box centre must lie inside it.
    :ivar distance_m: expected camera depth of the pallet: the median valid depth over the middle half of a
        detection's box must be within `distance_m +- tolerance_m`.
    :ivar tolerance_m: half-width of the depth window.
    """

    box_xyxy: tuple[float, float, float, float] | None = None
    distance_m: float | None = None
    tolerance_m: float = 0.5

    def __post_init__(self) -> None:
        if self.box_xyxy is not None:
            box = tuple(float(v) for v in self.box_xyxy)
            if len(box) != 4 or not np.all(np.isfinite(box)) or box[2] <= box[0] or box[3] <= box[1]:
                raise ValueError(f"RegionOfInterest.box_xyxy must be finite (x1, y1, x2, y2) with x2 > x1 and "
                                 f"y2 > y1, got {self.box_xyxy!r}")
            object.__setattr__(self, "box_xyxy", box)
        if self.distance_m is not None and not (np.isfinite(self.distance_m) and self.distance_m > 0):
            raise ValueError(f"RegionOfInterest.distance_m must be positive, got {self.distance_m}")
        if not (np.isfinite(self.tolerance_m) and self.tolerance_m > 0):
            raise ValueError(f"RegionOfInterest.tolerance_m must be positive, got {self.tolerance_m}")


def _box_depth_m(depth_m: np.ndarray, box: np.ndarray) -> float:
    """Median valid depth over the middle half of a box (NaN when it has none)."""
    h, w = depth_m.shape
    x1, y1, x2, y2 = box
    cx, cy, hw, hh = (x1 + x2) / 2, (y1 + y2) / 2, (x2 - x1) / 4, (y2 - y1) / 4
    c0, c1 = int(np.clip(np.floor(cx - hw), 0, w)), int(np.clip(np.ceil(cx + hw), 0, w))
    r0, r1 = int(np.clip(np.floor(cy - hh), 0, h)), int(np.clip(np.ceil(cy + hh), 0, h))
    patch = depth_m[r0:r1, c0:c1]
    valid = patch[np.isfinite(patch) & (patch > 0)]
    return float(np.median(valid)) if valid.size else float("nan")


def roi_filter(boxes_xyxy: np.ndarray, depth_m: np.ndarray | None, roi: RegionOfInterest | None
               ) -> tuple[np.ndarray, list[str]]:
    """Which detections lie in the region of interest.

    :param boxes_xyxy: (n, 4) detector boxes, image pixels. :param depth_m: (H, W) metres (0 = none); needed
        only with a depth hint. A box without valid depth passes the depth hint (the pose stage judges it).
    :return: (n,) bool keep mask, and for each detection a sentence why it was dropped ("" when kept).
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    keep = np.ones(len(boxes), dtype=bool)
    why = [""] * len(boxes)
    if roi is None or not len(boxes):
        return keep, why
    if roi.box_xyxy is not None:
        x1, y1, x2, y2 = roi.box_xyxy
        cx, cy = (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2
        inside = (cx >= x1) & (cx <= x2) & (cy >= y1) & (cy <= y2)
        for i in np.flatnonzero(~inside):
            keep[i] = False
            why[i] = f"box centre ({cx[i]:.0f}, {cy[i]:.0f}) outside the region of interest {list(roi.box_xyxy)}"
    if roi.distance_m is not None:
        if depth_m is None:
            raise ValueError("a depth hint (RegionOfInterest.distance_m) needs the frame's depth")
        depth_m = np.asarray(depth_m)
        if depth_m.ndim != 2:
            raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
        for i in np.flatnonzero(keep):
            z = _box_depth_m(depth_m, boxes[i])
            if np.isfinite(z) and abs(z - roi.distance_m) > roi.tolerance_m:
                keep[i] = False
                why[i] = (f"depth {z:.2f} m outside the hint {roi.distance_m:.2f} +- {roi.tolerance_m:.2f} m")
    return keep, why


def estimate_in_roi(estimator, frame, roi: RegionOfInterest, T_vehicle_cam=None):
    """The estimator's `FrameResult` for an `RGBDFrame` with detections outside `roi` dropped before posing
    (as "outside_roi" rejections): the detector runs, `roi_filter` judges its boxes, the pose stage runs on
    the boxes kept (`T_vehicle_cam`: the camera's calibration, as `PalletEstimator.estimate` takes it)."""
    from .results import Rejection

    det = estimator.detect(frame.rgb, frame.depth_m)
    keep, why = roi_filter(det.boxes_xyxy, frame.depth_m, roi)
    result = estimator.estimate_boxes(frame, boxes_xyxy=det.boxes_xyxy[keep], scores=det.scores[keep],
                                      T_vehicle_cam=T_vehicle_cam)
    dropped = [Rejection(det.boxes_xyxy[i], det.scores[i], "outside_roi", why[i]) for i in np.flatnonzero(~keep)]
    return type(result)(poses=result.poses, rejected=list(result.rejected) + dropped,
                        timings_ms=result.timings_ms, image_hw=result.image_hw)
