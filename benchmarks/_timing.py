"""Timing helpers shared by the benchmark scripts (imported as a sibling module).

Every timed call is measured three ways: wall time (``time.perf_counter``), and the process's user and system
CPU time and minor page faults (``resource.getrusage``; all threads of the process). System time and faults
are where fresh memory shows: a call that writes memory not yet mapped pays a fault per page and the kernel's
zeroing of it, which a wall time alone cannot tell from a slower computation, and a loaded machine shows as a
wall time above user + system. :func:`measure` takes one call, :func:`summary` gives the medians and the spread
of several, :func:`row` prints them per unit of work. A script that imports this module prints, at its exit,
the wall, user and system time and minor faults of its timed calls together and of the whole process (its
children included), so that every benchmark reports all three.
"""

from __future__ import annotations

import atexit
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

try:
    import resource
except ImportError:  # pragma: no cover - Windows: wall time only
    resource = None  # type: ignore[assignment]


@dataclass(frozen=True)
class Sample:
    """One timed call: wall, user and system seconds, minor page faults, and the process's CPU seconds by its
    precise clock (``time.process_time``: user + system, not rounded to the scheduler's tick)."""

    wall: float
    user: float
    sys: float
    faults: int
    cpu: float


def _usage() -> tuple[float, float, int]:
    if resource is None:  # pragma: no cover
        return 0.0, 0.0, 0
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime, r.ru_stime, r.ru_minflt


def measure(fn: Callable[[], object]) -> tuple[Sample, object]:
    """Call ``fn`` once: ``(sample, its return value)``."""
    u0, s0, f0 = _usage()
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    u1, s1, f1 = _usage()
    sample = Sample(max(wall, 1e-9), u1 - u0, s1 - s0, f1 - f0, cpu)
    _LOG.append(sample)
    return sample, out


@dataclass(frozen=True)
class Summary:
    """Medians and (min, max) of several samples, each field scaled by the same factor."""

    wall: float
    wall_range: tuple[float, float]
    user: float
    user_range: tuple[float, float]
    sys: float
    sys_range: tuple[float, float]
    faults: float


def summary(samples: Sequence[Sample], scale: float = 1.0) -> Summary:
    """Medians and spreads of ``samples``, times multiplied by ``scale`` (e.g. ``1e9 / run_steps``)."""

    def med(xs: list[float]) -> tuple[float, tuple[float, float]]:
        return statistics.median(xs) * scale, (min(xs) * scale, max(xs) * scale)

    w, wr = med([s.wall for s in samples])
    u, ur = med([s.user for s in samples])
    sy, sr = med([s.sys for s in samples])
    return Summary(w, wr, u, ur, sy, sr, statistics.median([s.faults for s in samples]))


HEADER = (
    f"{'wall':>8s} {'(min-max)':>13s} {'user':>7s} {'(min-max)':>13s} {'sys':>6s} {'(min-max)':>11s} {'faults':>7s}"
)


def row(s: Summary) -> str:
    """The columns of :data:`HEADER` for one summary: medians, (min-max), median minor faults per call."""
    return (
        f"{s.wall:8.1f} {f'({s.wall_range[0]:.0f}-{s.wall_range[1]:.0f})':>13s} {s.user:7.1f} "
        f"{f'({s.user_range[0]:.0f}-{s.user_range[1]:.0f})':>13s} {s.sys:6.1f} "
        f"{f'({s.sys_range[0]:.0f}-{s.sys_range[1]:.0f})':>11s} {s.faults:7.0f}"
    )


def best_time(fn: Callable[[], object], repeat: int, *, cpu: bool = False) -> float:
    """Best of ``repeat`` calls of ``fn``: wall-clock seconds, or process CPU seconds (user + system) with
    ``cpu=True`` (robust on a machine shared with other jobs). Never below 1e-9. The best call's user and
    system time are kept in :data:`LAST_BEST` for a script that prints them."""
    global LAST_BEST
    best, best_sample = float("inf"), None
    for _ in range(repeat):
        sample, _ = measure(fn)
        value = sample.cpu if cpu else sample.wall
        if value < best:
            best, best_sample = value, sample
    LAST_BEST = best_sample
    return max(best, 1e-9)


LAST_BEST: Sample | None = None  #: the best call of the latest :func:`best_time`


_LOG: list[Sample] = []  # every call measured in this process
_START = time.perf_counter()


def _report_at_exit() -> None:
    """Print the totals of the timed calls and of the process (wall, user, system, minor faults)."""
    if resource is None:  # pragma: no cover
        return
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    timed = ""
    if _LOG:
        timed = (
            f"{len(_LOG)} timed calls: wall {sum(s.wall for s in _LOG):.1f} s, user {sum(s.user for s in _LOG):.1f} s, "
            f"system {sum(s.sys for s in _LOG):.1f} s, {sum(s.faults for s in _LOG)} minor faults; "
        )
    print(
        f"\n[times] {timed}whole process: wall {time.perf_counter() - _START:.1f} s, "
        f"user {me.ru_utime + kids.ru_utime:.1f} s, system {me.ru_stime + kids.ru_stime:.1f} s "
        f"(children {kids.ru_utime + kids.ru_stime:.1f} s), {me.ru_minflt} minor faults",
        file=sys.stdout,
        flush=True,
    )


if os.path.dirname(os.path.abspath(sys.argv[0] or ".")) == os.path.dirname(os.path.abspath(__file__)):
    atexit.register(_report_at_exit)  # a benchmark script run as one (not a test importing this module)
