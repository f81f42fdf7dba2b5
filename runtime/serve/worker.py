"""`EstimatorProcess`: the `PalletEstimator` in a child process, with the same `estimate(frame)` call.

Why a process: the estimator's Python stages (ICP refinement above all) hold the interpreter lock for most of a
frame; in the same process every HTTP answer would compete with them for it (a waiting thread gets it after up
to 5 ms, the switch interval, each time). In a child the API answers from its own interpreter, and a native
crash of onnxruntime costs one frame and a restart of the child, never the daemon. A frame crosses the pipe
pickled (about 2 MB at 848x480).
"""
from __future__ import annotations

import logging
import multiprocessing
import threading

import numpy as np

__all__ = ["EstimatorProcess", "EstimatorCrashed"]

log = logging.getLogger(__name__)

START_TIMEOUT_S = 300.0   # loading a bundle on a busy two-core computer


class EstimatorCrashed(RuntimeError):
    """The estimator process ended (it is restarted for the next frame)."""


def _child(conn, bundle: str, threads: int, precision: str, options: dict, T_vehicle_cam: np.ndarray | None) -> None:
    """The child's loop: load the bundle, then answer frames until the pipe closes (in the vehicle frame when
    `T_vehicle_cam` is given). Signals are the parent's business (systemd signals the whole service): the child
    ends when the parent closes the pipe or dies."""
    import signal

    from pallet6d.runtime.estimator import PalletEstimator
    from pallet6d.runtime.forklift import vehicle_frame_result

    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    try:
        est = PalletEstimator.from_bundle(bundle, threads=threads, precision=precision, **options)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which decides
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", {"model_size_m": est.model_size_m, "bundle": est.bundle.name}))
    while True:
        try:
            frame = conn.recv()
        except (EOFError, OSError):
            return
        try:
            result = est.estimate(frame, T_vehicle_cam=T_vehicle_cam)
            if T_vehicle_cam is not None:
                result = vehicle_frame_result(result, T_vehicle_cam, est.bundle, frame)
            conn.send(("ok", result))
        except (ValueError, TypeError) as exc:
            conn.send(("input", f"{type(exc).__name__}: {exc}"))
        except Exception as exc:  # noqa: BLE001 - one frame's failure goes back to the parent
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


class EstimatorProcess:
    """`PalletEstimator.from_bundle(bundle, threads, precision, **options)` in a child process; with
    `T_vehicle_cam` (4, 4) its results are in the vehicle frame (`forklift.vehicle_frame_result`).

    `estimate(frame)` raises `ValueError` for frames the estimator rejects, `RuntimeError` for its other errors
    and `EstimatorCrashed` when the child died (a new one is started on the next call). Not thread-safe, like
    the estimator: one caller at a time.

    :raises ValueError: the bundle cannot be loaded (the child's message).
    """

    def __init__(self, bundle: str, threads: int = 2, precision: str = "fp32", options: dict | None = None,
                 T_vehicle_cam: np.ndarray | None = None) -> None:
        T = None if T_vehicle_cam is None else np.array(T_vehicle_cam, dtype=np.float64)
        self._args = (str(bundle), int(threads), precision, dict(options or {}), T)
        self._ctx = multiprocessing.get_context("spawn")   # no fork of a process with threads
        self._lock = threading.Lock()
        self._proc = None
        self._conn = None
        self.restarts = 0
        self._start()
        self.model_size_m = np.asarray(self._info["model_size_m"], dtype=np.float64)
        self.bundle_name = self._info["bundle"]

    def _start(self) -> None:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_child, args=(child, *self._args), name="pallet6d-estimator", daemon=True)
        proc.start()
        child.close()
        if not parent.poll(START_TIMEOUT_S):
            proc.kill()
            raise ValueError(f"the estimator process did not load the bundle within {START_TIMEOUT_S:.0f} s")
        try:
            kind, value = parent.recv()
        except EOFError:
            raise ValueError(f"the estimator process ended while loading (exit status {proc.exitcode})") from None
        if kind != "ready":
            proc.join(5)
            raise ValueError(value)
        self._proc, self._conn, self._info = proc, parent, value

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def estimate(self, frame):
        with self._lock:
            if not self.alive:
                try:
                    self._restart()
                except ValueError as exc:
                    raise EstimatorCrashed(f"the estimator process cannot start again: {exc}") from None
            try:
                self._conn.send(frame)
                kind, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self._proc.join(2)   # reaped: its exit status says how it ended
                code = self._proc.exitcode
                self._close()
                raise EstimatorCrashed(f"the estimator process ended (exit status {code}): {exc!r}") from None
        if kind == "ok":
            return value
        if kind == "input":
            raise ValueError(value)
        raise RuntimeError(value)

    def _restart(self) -> None:
        self._close()
        self.restarts += 1
        log.warning("starting the estimator process again (restart %d)", self.restarts)
        self._start()

    def _close(self) -> None:
        conn, proc, self._conn, self._proc = self._conn, self._proc, None, None
        if conn is not None:
            conn.close()   # the child's recv() ends: it returns
        if proc is not None:
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join(5)

    def close(self) -> None:
        with self._lock:
            self._close()
