"""`FloorWatch`: does the floor still lie where the daemon's calibration says it does?

The calibration's `T_vehicle_cam` puts the floor at the vehicle's z = 0; seen from the camera that is a plane
(`Calibration.vehicle_floor`). Every `interval_s` the camera loop hands its newest frame over (`offer`, which
returns at once) and a thread of its own fits the floor in that frame's depth (`floor.check_floor`, through a
`CalibrationMonitor`) and compares: the floor's tilt and the camera's height above it must agree within the
configured tolerances. Where no floor lies near the calibrated one, the check looks for it in the whole image:
a floor found far from where the calibration puts it (a camera height off by a metre, a tilt of 20 degrees)
disagrees with its measured numbers. A check that finds no floor anywhere (a wall filling the view, no depth)
says "unknown". A check costs about 0.1 s of one core (docs/daemon.md), on this thread, never on the camera loop's.

States (`FloorStatus.state`):
- "ok": the last check agreed (or one disagreement after agreeing before: a ramp edge is not a knock);
- "failed": the camera counts as moved (the first check disagreed, or two in a row later; three agreeing checks
  in a row end it), or the frames are not of the calibrated camera (intrinsics or size);
- "unknown": not checked yet, or the last check saw no floor of enough support anywhere in the view.

While "failed", vehicle-frame output is withheld (`blocked_reason`); `GET /readyz` is ready in "ok" and, when
`when_unseen = "ready"`, in "unknown".
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

from ..calibration import Calibration, CalibrationError, CalibrationMonitor
from ..cameras import RGBDFrame
from .config import FloorCheckConfig
from .metrics import Metrics

__all__ = ["FloorWatch", "FloorStatus", "STATES"]

log = logging.getLogger(__name__)

STATES = ("ok", "failed", "unknown")
TICK_S = 0.5   # how often the idle thread looks for the stop request


@dataclass(frozen=True)
class FloorStatus:
    """The floor check's latest outcome.

    :ivar state: one of `STATES`. :ivar detail: a sentence with the numbers.
    :ivar tilt_deg: angle between the seen and the calibrated floor (NaN when not seen).
    :ivar height_m: the camera's height above the seen floor, metres (NaN when not seen).
    :ivar checks: checks done so far. :ivar checked_monotonic: `time.monotonic()` of the last (-inf: none).
    """

    state: str
    detail: str
    tilt_deg: float = math.nan
    height_m: float = math.nan
    checks: int = 0
    checked_monotonic: float = -math.inf

    def __post_init__(self) -> None:
        if self.state not in STATES:
            raise ValueError(f"FloorStatus.state must be one of {STATES}, got {self.state!r}")


class FloorWatch:
    """The floor check of a calibrated daemon, on a thread of its own (see the module docstring).

    :param calibration: the validated calibration. :param config: tolerances, interval, `when_unseen`.
    :param metrics: where check results go (`pallet6d_floor_checks_total`, `pallet6d_calibration_ok`, ...).
    """

    def __init__(self, calibration: Calibration, config: FloorCheckConfig, metrics: Metrics) -> None:
        self.calibration = calibration
        self.config = config
        self.metrics = metrics
        self.expected = calibration.vehicle_floor
        self.monitor = CalibrationMonitor(calibration, every_n=1, max_tilt_deg=config.max_tilt_deg,
                                          max_height_diff_m=config.max_height_diff_m, floor=self.expected)
        self.status = FloorStatus("unknown", "not checked yet")
        self._frame: RGBDFrame | None = None
        self._busy = threading.Event()     # set from a handed-over frame until its check is done
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._next_due = -math.inf

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> "FloorWatch":
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="floor-check", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)

    # -- the camera loop's side -------------------------------------------------------------------------
    def offer(self, frame: RGBDFrame) -> None:
        """The camera loop's newest frame; returns at once. It is checked when a check is due and none runs."""
        now = time.monotonic()
        if now < self._next_due or self._busy.is_set():
            return
        self._next_due = now + self.config.interval_s
        self._frame = frame
        self._busy.set()

    def blocked_reason(self, frame: RGBDFrame) -> str:
        """Why vehicle-frame output must not be given for `frame` ("" when it may): a frame of another camera or
        size than the calibrated one, or a camera that moved since it was calibrated."""
        try:
            self.calibration.check_camera(frame.K, (frame.height, frame.width))
            self.monitor.require_ok()
        except CalibrationError as exc:
            return str(exc)
        return ""

    # -- what GET /readyz reads -----------------------------------------------------------------------
    def ready(self) -> bool:
        state = self.status.state
        return state == "ok" or (state == "unknown" and self.config.when_unseen == "ready")

    def to_dict(self) -> dict:
        """The status as `GET /readyz` gives it: state, the measured values beside the expected ones."""
        st, cfg = self.status, self.config
        age = time.monotonic() - st.checked_monotonic
        return {"state": st.state, "detail": st.detail, "when_unseen": cfg.when_unseen, "checks": st.checks,
                "checked_age_s": _number(age, 3),
                "camera_height_m": {"measured": _number(st.height_m, 4), "expected": _number(self.expected.d, 4),
                                    "tolerance": cfg.max_height_diff_m},
                "floor_tilt_deg": {"measured": _number(st.tilt_deg, 3), "expected": 0.0,
                                   "tolerance": cfg.max_tilt_deg}}

    # -- the thread -----------------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._busy.wait(TICK_S):
                continue
            frame, self._frame = self._frame, None
            try:
                if frame is not None:
                    self._check(frame)
            except Exception:  # noqa: BLE001 - a failed check must not end the watch
                log.exception("floor check failed")
            finally:
                self._busy.clear()

    def _check(self, frame: RGBDFrame) -> None:
        n = self.status.checks + 1
        now = time.monotonic()
        try:
            self.calibration.check_camera(frame.K, (frame.height, frame.width))
        except CalibrationError as exc:
            self._set("wrong_camera", FloorStatus("failed", str(exc), checks=n, checked_monotonic=now))
            return
        check = self.monitor.update(frame.depth_m, frame.K)
        if check.agrees is None:
            state = "failed" if not self.monitor.ok else "unknown"
            self._set("unseen", FloorStatus(state, check.detail, checks=n, checked_monotonic=now))
            return
        self.metrics.floor_tilt.set(check.tilt_deg)
        self.metrics.floor_height_diff.set(check.height_diff_m)
        state = "ok" if self.monitor.ok else "failed"
        self._set("agrees" if check.agrees else "disagrees",
                  FloorStatus(state, check.detail, check.tilt_deg, self.expected.d + check.height_diff_m, n, now))

    def _set(self, result: str, status: FloorStatus) -> None:
        if status.state != self.status.state:
            (log.warning if status.state == "failed" else log.info)("floor check: %s (%s)", status.state,
                                                                     status.detail)
        self.status = status
        self.metrics.floor_checks.labels(result).inc()
        self.metrics.calibration_ok.set(0 if status.state == "failed" else 1)


def _number(x: float, digits: int) -> float | None:
    return round(float(x), digits) if math.isfinite(x) else None
