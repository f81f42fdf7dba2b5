"""The daemon's Prometheus metrics, in a registry of its own (no process-global state: two daemons in one
process, as the tests run them, never share counters)."""
from __future__ import annotations

import time
from typing import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client import CONTENT_TYPE_LATEST

__all__ = ["Metrics", "RequestTimer", "CONTENT_TYPE_LATEST", "FAILURE_REASONS", "FLOOR_CHECK_RESULTS"]

# Why a frame produced no result: stable label values.
FAILURE_REASONS = (
    "bad_frame",        # the estimator rejected the frame's data (ValueError/TypeError: shapes, NaN depth, ...)
    "estimator",        # any other error inside the estimator
    "read_error",       # the source skipped an unreadable recorded frame
    "camera",           # the source failed (disconnect, timeout); the loop reconnects
    "calibration",      # vehicle-frame output withheld: the camera moved since calibration, or is another camera
)
# Outcomes of the floor-consistency check: stable label values.
FLOOR_CHECK_RESULTS = (
    "agrees",           # the floor lies where the calibration says
    "disagrees",        # it does not (tilt or camera height beyond the tolerance)
    "unseen",           # too little floor in view to tell
    "wrong_camera",     # the frame's intrinsics or size are not the calibrated ones
)

# seconds: a stage of a few ms up to a whole frame of a few hundred ms on two cores
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56)
PALLET_BUCKETS = (0, 1, 2, 3, 4, 6, 8, 12, 16)
HTTP_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0)


class Metrics:
    """Counters and histograms the camera loop updates and `GET /metrics` exposes."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.stage_latency = Histogram("pallet6d_stage_latency_seconds", "Estimator latency per stage and in total",
                                       ["stage"], buckets=LATENCY_BUCKETS_S, registry=r)
        self.frames = Counter("pallet6d_frames", "Frames estimated", registry=r)
        self.frames_received = Counter("pallet6d_frames_received", "Frames taken from the camera", registry=r)
        self.frames_dropped = Counter("pallet6d_frames_dropped",
                                      "Camera frames replaced by a newer one before the loop took them", registry=r)
        self.failures = Counter("pallet6d_failures", "Frames without a result, by reason", ["reason"], registry=r)
        for reason in FAILURE_REASONS:
            self.failures.labels(reason)
        self.reconnects = Counter("pallet6d_camera_reconnects", "Times the camera was reopened after a failure",
                                  registry=r)
        self.camera_up = Gauge("pallet6d_camera_up", "1 while the camera is streaming", registry=r)
        self.pallets = Histogram("pallet6d_pallets_per_frame", "Accepted pallets per estimated frame",
                                 buckets=PALLET_BUCKETS, registry=r)
        self.result_age = Gauge("pallet6d_result_age_seconds", "Seconds since the latest result's frame arrived",
                                registry=r)
        self.http_latency = Histogram("pallet6d_http_request_seconds",
                                      "Time from a request's arrival to the end of its response, by route",
                                      ["route"], buckets=HTTP_BUCKETS_S, registry=r)
        self.snapshots = Counter("pallet6d_snapshots", "Snapshot recordings written", registry=r)
        self.floor_checks = Counter("pallet6d_floor_checks", "Floor-consistency checks of the calibration, by result",
                                    ["result"], registry=r)
        for result in FLOOR_CHECK_RESULTS:
            self.floor_checks.labels(result)
        self.calibration_ok = Gauge("pallet6d_calibration_ok", "0 while the floor check says the camera moved since "
                                    "calibration (or is another camera), else 1 (also without a calibration)",
                                    registry=r)
        self.calibration_ok.set(1)
        self.floor_tilt = Gauge("pallet6d_floor_tilt_degrees", "Angle between the seen and the calibrated floor "
                                "at the last check that saw it (NaN before)", registry=r)
        self.floor_height_diff = Gauge("pallet6d_floor_height_diff_meters", "Seen minus calibrated camera height "
                                       "above the floor at the last check that saw it (NaN before)", registry=r)
        self.floor_tilt.set(float("nan"))
        self.floor_height_diff.set(float("nan"))

    def observe_result(self, timings_ms: dict[str, float], n_pallets: int) -> None:
        self.frames.inc()
        for stage, ms in timings_ms.items():
            self.stage_latency.labels(stage).observe(ms / 1000.0)
        self.pallets.observe(n_pallets)

    def set_age_function(self, age_s: Callable[[], float]) -> None:
        self.result_age.set_function(age_s)

    def exposition(self) -> bytes:
        return generate_latest(self.registry)


class RequestTimer:
    """ASGI middleware: observes each request to one of `routes` (exact paths) in `histogram`."""

    def __init__(self, app, histogram: Histogram, routes: tuple[str, ...]) -> None:
        self.app, self.histogram, self.routes = app, histogram, frozenset(routes)

    async def __call__(self, scope, receive, send) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or path not in self.routes:
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        try:
            await self.app(scope, receive, send)
        finally:
            self.histogram.labels(path).observe(time.perf_counter() - t0)
