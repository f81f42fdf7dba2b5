"""The calibration file of one camera: intrinsics, camera-to-vehicle transform and the floor it saw.

One human-readable TOML file per camera, written by `pallet6d calib` and read by the estimator's run loop:

    format_version = 1
    serial = "815412070123"          # the camera's serial number ("" when unknown)
    date = "2026-11-23"              # when it was calibrated (ISO 8601)
    camera = "realsense"             # free text: model, mount

    [intrinsics]                     # of the colour image (depth is aligned to it)
    width = 848
    height = 480
    K = [[610.0, 0.0, 423.5], [0.0, 610.0, 239.5], [0.0, 0.0, 1.0]]
    dist = [0.0, 0.0, 0.0, 0.0, 0.0]
    source = "sdk"                   # sdk | camera.json | board

    [extrinsics]                     # x_vehicle = T_vehicle_cam @ x_cam (vehicle frame: x forward along the
    T_vehicle_cam = [[...], [...], [...], [0.0, 0.0, 0.0, 1.0]]   # forks, y left, z up, origin on the floor
    source = "floor+mount"           # between the fork roots; metres)

    [floor]                          # the floor seen at calibration time, camera frame: n . p + d = 0
    normal_cam = [0.0, -0.96, 0.27]
    d_m = 1.21

The floor must agree with `T_vehicle_cam` (its plane is the vehicle's z = 0): a file where they disagree is
refused. `CalibrationMonitor` checks, at start and while running, that each frame's floor still agrees, and
withholds vehicle-frame output while it does not (a knocked camera).
"""
from __future__ import annotations

import datetime as _dt
import logging
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .floor import FloorCheck, FloorPlane, check_floor, plane_angle_deg
from .geometry import check_K

__all__ = ["Calibration", "CalibrationError", "CalibrationMonitor", "load_calibration", "save_calibration",
           "to_toml", "NO_CALIBRATION_HINT"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
NO_CALIBRATION_HINT = ("calibrate the camera first (pallet6d calib floor --source ... --out cam.toml, see "
                       "docs/forklift.md) and pass --calibration cam.toml, or ask for camera-frame poses with "
                       "--frame camera")
# the stored floor may disagree with T_vehicle_cam's floor (z = 0) by at most this much
_FLOOR_AGREE_DEG = 1.0
_FLOOR_AGREE_M = 0.02


class CalibrationError(ValueError):
    """A missing, unreadable, inconsistent or outdated calibration: vehicle-frame output is impossible."""


def _rigid(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise CalibrationError(f"{what} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-5) \
            or np.linalg.det(R) < 0:
        raise CalibrationError(f"{what} must be a rigid transform (orthonormal R, det +1, last row 0 0 0 1)")
    return T


@dataclass(frozen=True)
class Calibration:
    """One camera's calibration (see the module docstring for the file).

    :ivar width, height: image size the intrinsics are for. :ivar K: (3, 3). :ivar dist: (5,) OpenCV k1 k2 p1 p2 k3.
    :ivar T_vehicle_cam: (4, 4) camera -> vehicle. :ivar floor: the floor seen at calibration time (camera frame).
    """

    serial: str
    date: str
    width: int
    height: int
    K: np.ndarray
    T_vehicle_cam: np.ndarray
    floor: FloorPlane
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    camera: str = ""
    intrinsics_source: str = ""
    extrinsics_source: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.serial, str) or not isinstance(self.camera, str):
            raise CalibrationError("serial and camera must be strings")
        try:
            _dt.date.fromisoformat(str(self.date))
        except ValueError:
            raise CalibrationError(f"date must be an ISO date (YYYY-MM-DD), got {self.date!r}") from None
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        try:
            K = check_K(self.K)
        except ValueError as exc:
            raise CalibrationError(str(exc)) from None
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if dist.shape not in ((4,), (5,), (8,)) or not np.all(np.isfinite(dist)):
            raise CalibrationError(f"dist must hold 4, 5 or 8 finite OpenCV coefficients, got shape {dist.shape}")
        T = _rigid(self.T_vehicle_cam, "T_vehicle_cam")
        if not isinstance(self.floor, FloorPlane):
            raise CalibrationError(f"floor must be a FloorPlane, got {type(self.floor).__name__}")
        up_cam = T[2, :3]                                   # vehicle z in camera coordinates
        tilt = plane_angle_deg(up_cam, self.floor.normal)
        if tilt > _FLOOR_AGREE_DEG or abs(T[2, 3] - self.floor.d) > _FLOOR_AGREE_M:
            raise CalibrationError(
                f"the stored floor disagrees with T_vehicle_cam: {tilt:.2f} deg apart, camera height "
                f"{self.floor.d:.3f} m vs {T[2, 3]:.3f} m; run pallet6d calib floor again")
        for name, value in (("K", K), ("dist", dist), ("T_vehicle_cam", T)):
            value = value.copy()
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "date", str(self.date))

    @property
    def vehicle_floor(self) -> FloorPlane:
        """The floor `T_vehicle_cam` implies (the vehicle's z = 0), camera frame: normal = the vehicle's z axis in
        camera coordinates, d = the camera's height."""
        return FloorPlane(self.T_vehicle_cam[2, :3].copy(), float(self.T_vehicle_cam[2, 3]))

    def check_camera(self, K: np.ndarray, image_hw: tuple[int, int], rtol: float = 0.01) -> None:
        """Raise `CalibrationError` when a frame's intrinsics or size are not the calibrated ones."""
        h, w = image_hw
        if (w, h) != (self.width, self.height):
            raise CalibrationError(f"the calibration is for {self.width}x{self.height} images, the camera gives "
                                   f"{w}x{h}: calibrate at this resolution")
        K = check_K(K)
        if not np.allclose(K, self.K, rtol=rtol, atol=rtol * self.K[0, 0]):
            raise CalibrationError(f"the camera's intrinsics differ from the calibration's (fx {K[0, 0]:.1f} vs "
                                   f"{self.K[0, 0]:.1f}): wrong calibration file for this camera?")

    def to_dict(self) -> dict:
        return {"format_version": FORMAT_VERSION, "serial": self.serial, "date": self.date, "camera": self.camera,
                "intrinsics": {"width": self.width, "height": self.height, "K": self.K.tolist(),
                               "dist": self.dist.tolist(), "source": self.intrinsics_source},
                "extrinsics": {"T_vehicle_cam": self.T_vehicle_cam.tolist(), "source": self.extrinsics_source},
                "floor": {"normal_cam": self.floor.normal.tolist(), "d_m": self.floor.d,
                          "rms_m": self.floor.rms_m, "inlier_ratio": self.floor.inlier_ratio}}

    @classmethod
    def from_dict(cls, data: dict, source: str = "calibration") -> "Calibration":
        try:
            version = data.get("format_version")
            if version != FORMAT_VERSION:
                raise CalibrationError(f"format_version {version!r} is not {FORMAT_VERSION}")
            intr, ext, fl = data["intrinsics"], data["extrinsics"], data["floor"]
            floor = FloorPlane(np.asarray(fl["normal_cam"], dtype=np.float64), float(fl["d_m"]),
                               float(fl.get("inlier_ratio", 1.0)), float(fl.get("rms_m", 0.0)))
            return cls(serial=str(data.get("serial", "")), date=str(data["date"]), width=int(intr["width"]),
                       height=int(intr["height"]), K=np.asarray(intr["K"], dtype=np.float64),
                       dist=np.asarray(intr.get("dist", np.zeros(5)), dtype=np.float64),
                       T_vehicle_cam=np.asarray(ext["T_vehicle_cam"], dtype=np.float64), floor=floor,
                       camera=str(data.get("camera", "")), intrinsics_source=str(intr.get("source", "")),
                       extrinsics_source=str(ext.get("source", "")))
        except KeyError as exc:
            raise CalibrationError(f"{source}: missing field {exc.args[0]!r}") from None
        except CalibrationError as exc:
            raise CalibrationError(f"{source}: {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(f"{source}: {exc}") from None


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(float(v)):
            raise ValueError(f"TOML cannot hold {v}")
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(data: dict) -> str:
    """A dict of scalars, lists and one level of tables as TOML text (what `tomllib` reads back)."""
    head = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    tables = [f"\n[{k}]\n" + "\n".join(f"{kk} = {_toml_value(vv)}" for kk, vv in v.items())
              for k, v in data.items() if isinstance(v, dict)]
    return "# pallet6d camera calibration (docs/forklift.md)\n" + "\n".join(head) + "\n" + "\n".join(tables) + "\n"


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    Path(path).write_text(to_toml(calibration.to_dict()))


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration file; `CalibrationError` says what is wrong and what to run."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read the calibration: {exc.strerror or exc}; "
                               f"{NO_CALIBRATION_HINT}") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not a TOML calibration file: {exc}") from None
    return Calibration.from_dict(data, source=str(path))


class CalibrationMonitor:
    """Whether vehicle-frame output may be given now: the floor must keep agreeing with the calibration.

    `update(depth_m, K)` checks the floor every `every_n` frames (the first frame always, and every frame while
    a check disagrees). At start, before any check has agreed, one that sees the floor elsewhere stops vehicle-frame
    output; later it takes `n_bad` in a row (a forklift driving over a ramp edge is not a knock). The camera then
    counts as moved: `ok` stays False until `n_good` checks in a row agree again. Frames that show too little floor
    change nothing.
    """

    def __init__(self, calibration: Calibration, every_n: int = 30, n_bad: int = 2, n_good: int = 3,
                 max_tilt_deg: float = 1.0, max_height_diff_m: float = 0.03, floor: FloorPlane | None = None) -> None:
        """:param floor: the floor to compare with (default the calibration's stored floor)."""
        if every_n < 1 or n_bad < 1 or n_good < 1:
            raise ValueError("every_n, n_bad and n_good must be >= 1")
        self.calibration = calibration
        self.floor = calibration.floor if floor is None else floor
        self.every_n, self.n_bad, self.n_good = int(every_n), int(n_bad), int(n_good)
        self.max_tilt_deg, self.max_height_diff_m = float(max_tilt_deg), float(max_height_diff_m)
        self.ok = True
        self.last: FloorCheck | None = None
        self._frames = 0
        self._bad = 0
        self._good = 0
        self._verified = False     # no check has agreed yet: at start one disagreement is enough

    def update(self, depth_m: np.ndarray, K: np.ndarray) -> FloorCheck | None:
        """Check this frame's floor when one is due; return the check (None when none was due)."""
        due = self._frames % self.every_n == 0 or not self.ok or self._bad > 0
        self._frames += 1
        if not due:
            return None
        check = check_floor(self.floor, depth_m, K, self.max_tilt_deg, self.max_height_diff_m)
        self.last = check
        if check.agrees is None:
            return check
        if check.agrees:
            self._verified = True
            self._bad, self._good = 0, self._good + 1
            if not self.ok and self._good >= self.n_good:
                self.ok = True
                log.warning("camera floor agrees with the calibration again: vehicle-frame output resumes")
        else:
            self._good, self._bad = 0, self._bad + 1
            if self.ok and (self._bad >= self.n_bad or not self._verified):
                self.ok = False
                log.error("camera moved since calibration (%s): vehicle-frame output stops", check.detail)
        return check

    def require_ok(self) -> None:
        """Raise `CalibrationError` while the camera counts as moved."""
        if not self.ok:
            detail = self.last.detail if self.last is not None else ""
            raise CalibrationError(f"the camera moved since it was calibrated ({detail}): re-seat it or run "
                                   f"pallet6d calib floor again")
