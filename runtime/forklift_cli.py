"""`pallet6d run`'s forklift options: the output frame, the calibration, the region of interest.

Vehicle-frame output (the default) needs a valid calibration file; without one `pallet6d run` refuses to start
and says what to run. Camera-frame output must be asked for (`--frame camera`).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from .calibration import NO_CALIBRATION_HINT, Calibration, CalibrationError, CalibrationMonitor, load_calibration
from .forklift import vehicle_frame_result
from .roi import RegionOfInterest, estimate_in_roi

__all__ = ["add_forklift_arguments", "ForkliftOutput"]


def add_forklift_arguments(parser: argparse.ArgumentParser) -> None:
    """--frame, --calibration, --floor-check-every, --roi, --depth-hint, --depth-tolerance."""
    parser.add_argument("--frame", choices=("vehicle", "camera"), default="vehicle",
                        help="vehicle: poses also in the calibrated vehicle frame, with fork pockets and pick_safe "
                             "(default; needs --calibration); camera: camera-frame poses only")
    parser.add_argument("--calibration", type=Path, help="the camera's calibration file (pallet6d calib)")
    parser.add_argument("--floor-check-every", type=int, default=30,
                        help="check every N frames that the floor still agrees with the calibration (default 30)")
    parser.add_argument("--roi", help="only detections whose box centre lies in this image box: X1,Y1,X2,Y2 pixels")
    parser.add_argument("--depth-hint", type=float, help="only detections whose depth is within "
                                                         "--depth-tolerance of this many metres")
    parser.add_argument("--depth-tolerance", type=float, default=0.5, help="metres (default 0.5)")


@dataclass
class ForkliftOutput:
    """What `pallet6d run` does around the estimator: the region of interest before the pose stage, the floor
    check and the vehicle-frame outputs after it."""

    calibration: Calibration | None
    monitor: CalibrationMonitor | None
    roi: RegionOfInterest | None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "ForkliftOutput":
        """:raises CalibrationError: vehicle frame without a usable calibration; ValueError: a bad option."""
        roi = None
        if args.roi is not None or args.depth_hint is not None:
            box = None
            if args.roi is not None:
                try:
                    box = tuple(float(v) for v in args.roi.split(","))
                except ValueError:
                    raise ValueError(f"--roi must be X1,Y1,X2,Y2 pixels, got {args.roi!r}") from None
            roi = RegionOfInterest(box, args.depth_hint, args.depth_tolerance)
        if args.frame == "camera":
            return cls(None, None, roi)
        if args.calibration is None:
            raise CalibrationError(f"vehicle-frame output needs a calibration: {NO_CALIBRATION_HINT}")
        calibration = load_calibration(args.calibration)
        return cls(calibration, CalibrationMonitor(calibration, every_n=args.floor_check_every), roi)

    def estimate(self, estimator, frame):
        """The frame's `FrameResult`, in the vehicle frame when calibrated.

        :raises CalibrationError: the frame is not from the calibrated camera, or the camera moved.
        """
        if self.calibration is not None:
            self.calibration.check_camera(frame.K, (frame.height, frame.width))
            self.monitor.update(frame.depth_m, frame.K)
            self.monitor.require_ok()
        T_vc = None if self.calibration is None else self.calibration.T_vehicle_cam
        result = estimator.estimate(frame, T_vehicle_cam=T_vc) if self.roi is None \
            else estimate_in_roi(estimator, frame, self.roi, T_vehicle_cam=T_vc)
        if self.calibration is None:
            return result
        return vehicle_frame_result(result, self.calibration.T_vehicle_cam, estimator.bundle, frame)
