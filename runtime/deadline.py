"""A frame's time budget: the stages ask it before each unit of work whether time is left."""
from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["Deadline", "elapsed_ms"]


class Deadline:
    """`budget_ms` milliseconds from `start` on `clock` (seconds); None = no limit.

    :param clock: a monotonic clock in seconds (`time.perf_counter`; tests pass a fake one).
    """

    def __init__(self, budget_ms: float | None, start: float | None = None,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.clock = clock
        self.budget_ms = None if budget_ms is None else float(budget_ms)
        self.start = clock() if start is None else float(start)

    def expired(self) -> bool:
        """True once the budget is spent (never without a budget)."""
        return self.budget_ms is not None and (self.clock() - self.start) * 1000.0 >= self.budget_ms


def elapsed_ms(t: float) -> float:
    """Milliseconds since `t` on `time.perf_counter` (the stages' timings)."""
    return (time.perf_counter() - t) * 1000.0
