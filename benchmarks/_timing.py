"""Timing helper shared by the benchmark scripts (imported as a sibling module)."""

from __future__ import annotations

import time
from collections.abc import Callable


def best_time(fn: Callable[[], object], repeat: int, *, cpu: bool = False) -> float:
    """Best of ``repeat`` calls of ``fn``: wall-clock seconds, or process CPU seconds with ``cpu=True``
    (robust on a machine shared with other jobs). Never below 1e-9."""
    clock = time.process_time if cpu else time.perf_counter
    best = float("inf")
    for _ in range(repeat):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return max(best, 1e-9)
