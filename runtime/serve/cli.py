"""`pallet6d serve --config FILE`: the forklift daemon (see `docs/daemon.md`).

Exit status: 0 after SIGTERM or SIGINT (a clean stop), 2 for a configuration or bundle error found at start,
1 when the HTTP server cannot start (address in use). Under systemd (`Type=notify`) it reports READY once the
model is loaded and the API listens, and pings the watchdog only while both the camera loop and the HTTP event
loop make progress, so a hung estimator or SDK call gets the service restarted.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys
import threading
import time

import fastapi  # noqa: F401 - the serve extra: without it `pallet6d serve` says which extra to install
import prometheus_client  # noqa: F401
import uvicorn  # noqa: F401

HELP = "the forklift daemon: camera loop + HTTP API (health, metrics, results, snapshots)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="TOML configuration (see deploy/serve.toml)")
    parser.add_argument("--check", action="store_true",
                        help="validate the configuration and load the bundle, then exit (0: fine)")


def main(args: argparse.Namespace) -> int:
    from .config import ConfigError, ServeConfig

    try:
        config = ServeConfig.load(args.config)
    except ConfigError as exc:
        print(f"pallet6d serve: {exc}", file=sys.stderr)
        return 2
    if args.check:
        estimator = _load_estimator(config)
        if estimator is None:
            return 2
        cal = config.output.loaded
        where = "" if cal is None else (f", calibration {config.output.calibration} (camera {cal.serial or '?'}, "
                                        f"{cal.T_vehicle_cam[2, 3]:.3f} m above the floor)")
        print(f"pallet6d serve: {args.config}: configuration valid, bundle {estimator.bundle.name} loaded, "
              f"{config.output.frame}-frame output{where}")
        return 0
    from .worker import EstimatorProcess

    bundle = _bundle_path(config)
    if bundle is None:
        return 2
    log.info("bundle: %s (%s, %d threads)", bundle, config.model.precision, config.model.threads)
    calibration = config.output.loaded
    vehicle = config.output.frame == "vehicle"
    log.info("output: %s frame%s", config.output.frame,
             f", calibration {config.output.calibration}" if calibration is not None else "")
    try:
        estimator = EstimatorProcess(bundle, config.model.threads, config.model.precision,
                                     _options(config.estimator), calibration.T_vehicle_cam if vehicle else None)
    except ValueError as exc:
        print(f"pallet6d serve: cannot load the bundle {bundle}: {exc}", file=sys.stderr)
        return 2
    try:
        return serve(config, estimator)
    finally:
        estimator.close()


def _bundle_path(config) -> str | None:
    from ..default_bundle import BundleNotFoundError, default_bundle

    try:
        return str(config.model.bundle or default_bundle())
    except BundleNotFoundError as exc:
        print(f"pallet6d serve: {exc}", file=sys.stderr)
        return None


def _load_estimator(config):
    """The estimator in this process (`--check`), or None after printing why not."""
    from ..bundle import BundleError
    from ..estimator import PalletEstimator

    bundle = _bundle_path(config)
    if bundle is None:
        return None
    try:
        return PalletEstimator.from_bundle(bundle, threads=config.model.threads, precision=config.model.precision,
                                           **_options(config.estimator))
    except (BundleError, FileNotFoundError, ValueError) as exc:
        print(f"pallet6d serve: cannot load the bundle {bundle}: {exc}", file=sys.stderr)
        return None


def serve(config, estimator) -> int:
    """Run the daemon until SIGTERM/SIGINT."""
    from .app import create_app
    from .floor_watch import FloorWatch
    from .loop import CameraLoop
    from .metrics import Metrics
    from .snapshots import FrameRing

    metrics = Metrics()
    ring = FrameRing(config.snapshot.frames)
    calibration = config.output.loaded
    floor_watch = None if calibration is None else FloorWatch(calibration, config.floor_check, metrics)
    loop = CameraLoop(config, estimator, metrics, ring, floor_watch=floor_watch)
    app = create_app(config, loop, metrics, ring, {"version": _version()})
    server = uvicorn.Server(uvicorn.Config(
        app, host=config.api.host, port=config.api.port, log_config=None, access_log=False, lifespan="on",
        timeout_graceful_shutdown=3, limit_concurrency=256, timeout_keep_alive=30, server_header=False))
    stopped = threading.Event()

    def on_signal(signum, _frame) -> None:
        # uvicorn handles the signal first (graceful shutdown) and then calls this one again: just note it
        stopped.set()
        server.should_exit = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    loop.start()
    watchdog = _Watchdog(server, loop, app.state.ticks)
    watchdog.start()
    try:
        server.run()
    finally:
        watchdog.stop()
        app.state.hub.close()
        loop.stop()
    if not server.started:
        print(f"pallet6d serve: the HTTP server did not start on {config.api.host}:{config.api.port}",
              file=sys.stderr)
        return 1
    log.info("stopped%s", " (signal)" if stopped.is_set() else "")
    return 0


class _Watchdog:
    """systemd notification: READY=1 once the API listens, then WATCHDOG=1 every half `WatchdogSec` while the
    camera loop and the HTTP event loop both tick. Does nothing outside systemd (no NOTIFY_SOCKET)."""

    def __init__(self, server, loop, ticks: dict) -> None:
        self.server, self.loop, self.ticks = server, loop, ticks
        usec = os.environ.get("WATCHDOG_USEC", "")
        self.interval_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else 0.0
        # a frame may take seconds on a loaded machine; a loop silent for this long is hung
        self.max_silence_s = max(30.0, 2 * self.interval_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._notifier = None
        if os.environ.get("NOTIFY_SOCKET"):
            try:
                import sdnotify
                self._notifier = sdnotify.SystemdNotifier()
            except ImportError:
                log.warning("NOTIFY_SOCKET is set but sdnotify is not installed: no systemd notification")

    def start(self) -> None:
        if self._notifier is not None:
            self._thread = threading.Thread(target=self._run, name="systemd-notify", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._notifier is not None:
            self._notifier.notify("STOPPING=1")

    def _run(self) -> None:
        while not self.server.started and not self._stop.wait(0.2):
            pass
        if self._stop.is_set():
            return
        self._notifier.notify("READY=1")
        period = self.interval_s or 5.0
        while not self._stop.wait(period):
            event_loop_ok = time.monotonic() - self.ticks["event_loop"] < self.max_silence_s
            camera_ok = self.loop.alive(self.max_silence_s)
            status = "camera streaming" if self.loop.camera_up else f"camera down: {self.loop.last_error}"
            self._notifier.notify(f"STATUS={status[:200]}")
            if self.interval_s and event_loop_ok and camera_ok:
                self._notifier.notify("WATCHDOG=1")
            elif self.interval_s:
                log.error("watchdog not fed: camera loop %s, event loop %s",
                          "ok" if camera_ok else "hung", "ok" if event_loop_ok else "hung")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("pallet6d")
    except PackageNotFoundError:
        return ""


def _options(options) -> dict:
    """`EstimatorOptions` as keyword arguments, its nested settings (structure thresholds, region of interest) kept
    as the objects they are (`dataclasses.asdict` would turn them into dicts)."""
    return {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}
