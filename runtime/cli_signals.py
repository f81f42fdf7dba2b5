"""Stopping a long-running command cleanly on SIGINT (Ctrl-C) and SIGTERM (a supervisor's stop).

The first signal only asks to stop: the command finishes the frame in hand, writes its index or summary and
exits normally. A second signal raises `KeyboardInterrupt` at once, for a command stuck in a blocking call.
"""
from __future__ import annotations

import signal
import threading

__all__ = ["StopSignals"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """Context manager: while inside, SIGINT and SIGTERM set `requested` (the signal's name) instead of killing
    the process. Outside the main thread (where Python cannot install handlers) it does nothing.

    >>> with StopSignals() as stop:
    ...     while not stop.requested: work()
    """

    def __init__(self) -> None:
        self.requested: str | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, _frame) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for s in _SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()
