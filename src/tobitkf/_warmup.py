"""``tobitkf warmup``: compile the common kernels into numba's on-disk cache ahead of their first use.

Each target runs one family on a tiny problem (a few runs, a few steps) through the public API, so the
kernels are compiled for the argument types a user's call passes (float64, C-contiguous; numba
specialises on types, not sizes). A kernel already in the cache is loaded, not compiled: a second
warmup takes seconds. The targets are the filters most calls use (the Kalman and Tobit Kalman filters
with their online step, the assumed-density filters, the fading and protocol filters, the smoother, the
particle filter on censored readings)
and the censored-AR fit of ``tobitkf fit``.

numba compiles one kernel at a time per process, so on a machine with several cores the targets run in
that many worker processes at once (``jobs``), each compiling into the same on-disk cache; the cache's
files are written whole and renamed into place, so two processes compiling a kernel they share leave one
valid entry.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import numpy as np

__all__ = ["TARGETS", "default_jobs", "warmup"]


def _oscillator():
    from .channels.censoring import Censoring
    from .models.linear import LinearSystem

    w = 0.1 * np.pi
    A = 0.95 * np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    system = LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.1 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=np.eye(2))
    return system, Censoring(lower=0.0)


def _readings(system, runs: int = 4, steps: int = 6, **channel):
    from .simulate.core import simulate

    return simulate(system, steps, runs, seed=0, **channel).y


def _kalman_tobit() -> None:
    from .filters.kalman import KalmanFilter
    from .filters.tobit import TobitKalmanFilter

    system, cens = _oscillator()
    y = _readings(system, censoring=cens)
    KalmanFilter(system).filter(y)
    tkf = TobitKalmanFilter(system, cens)
    tkf.filter(y)
    tkf.filter(y, outputs=("mean",))
    state = tkf.init(batch_shape=(y.shape[0],))
    for k in range(2):
        state = tkf.step(state, y[:, k])


def _assumed_density() -> None:
    from .channels.saturation import RandomSaturation
    from .filters.adf_saturation import SaturationAssumedDensityFilter
    from .filters.assumed_density import AssumedDensityTobitFilter
    from .models.linear import LinearSystem

    system, cens = _oscillator()
    AssumedDensityTobitFilter(system, cens).filter(_readings(system, censoring=cens))
    sys2 = LinearSystem(A=system.A.at(0), C=np.eye(2), Q=0.1 * np.eye(2), R=0.01 * np.eye(2), x0=[0, 0], P0=np.eye(2))
    sat = RandomSaturation([0.7, 0.6], [0.7, 0.75])
    SaturationAssumedDensityFilter(sys2, sat).filter(_readings(sys2, channel=sat))


def _fading() -> None:
    from .channels.fading import RiceFading
    from .filters.adf_fading import FadingAssumedDensityFilter
    from .filters.fading import FadingTobitKalmanFilter

    system, cens = _oscillator()
    fading = RiceFading.gaussian(2, [0.8, 0.3, 0.1], [0.01, 0.01, 0.01])
    y = _readings(system, censoring=cens, measurement=fading)
    FadingTobitKalmanFilter(system, fading, cens).filter(y)
    FadingAssumedDensityFilter(system, fading, cens).filter(y)


def _protocol() -> None:
    from .channels.protocol import ProtocolChannel
    from .filters.adf_protocol import ProtocolAssumedDensityFilter
    from .filters.protocol import ProtocolTobitKalmanFilter
    from .models.linear import LinearSystem

    system = LinearSystem(A=np.eye(2), C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    channel = ProtocolChannel(2, window=2, threshold=0.0)
    y = _readings(system, channel=channel)
    ProtocolTobitKalmanFilter(system, channel).filter(y)
    ProtocolAssumedDensityFilter(system, channel).filter(y)


def _smoother() -> None:
    from .inference.smoothing import smooth

    system, cens = _oscillator()
    smooth(system, _readings(system, censoring=cens)[0], censoring=cens)


def _censored_ar() -> None:
    from .inference.censored_ar import CensoredAR
    from .inference.fitting import fit

    rng = np.random.default_rng(0)
    e = rng.standard_normal(60)
    x = np.empty(60)
    x[0] = e[0]
    for t in range(1, 60):
        x[t] = 0.5 * x[t - 1] + e[t]
    y = np.maximum(x, -0.5)
    for p in (1, 2):
        fit(CensoredAR(p), y, lower=-0.5)


def _particle() -> None:
    from .filters.particle import ParticleFilter

    system, cens = _oscillator()
    y = _readings(system, censoring=cens)
    for proposal in ("optimal", "prior"):
        ParticleFilter(system, cens, particles=64, proposal=proposal, seed=0).filter(y)


TARGETS: list[tuple[str, Callable[[], None]]] = [
    ("Kalman and Tobit Kalman filters (filter, online step)", _kalman_tobit),
    ("assumed-density filters (censoring, saturation)", _assumed_density),
    ("fading filters (TKF-FM, its assumed-density filter)", _fading),
    ("protocol filters (PBTKF-IMSF, its assumed-density filter)", _protocol),
    ("smoother", _smoother),
    ("particle filter (censored readings)", _particle),
    ("censored AR fit (tobitkf fit)", _censored_ar),
]
"""What ``tobitkf warmup`` compiles: (label, a function that runs it on a tiny problem)."""


def default_jobs() -> int:
    """The worker processes of :func:`warmup` by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _timed(target: Callable[[], None]) -> tuple[float, int, float]:
    """Run one target in this process: (its seconds, kernels it compiled, seconds spent compiling)."""
    from . import _compiled

    before = _compiled.compile_stats()
    t0 = time.perf_counter()
    target()
    seconds = time.perf_counter() - t0
    after = _compiled.compile_stats()
    return seconds, int(after["compiled"]) - int(before["compiled"]), float(after["seconds"]) - float(before["seconds"])


def _run_target(target: Callable[[], None]) -> tuple[float, int, float]:
    """Run one target in a worker process (:func:`_timed`), the compile notice left to the parent."""
    from . import _compiled

    _compiled.watch_compiles()
    with _compiled._LOCK:
        _compiled._STATS["announced"] = True  # the parent has said that kernels compile
    return _timed(target)


def warmup(
    report: Callable[[str], None] = print,
    targets: list[tuple[str, Callable[[], None]]] | None = None,
    jobs: int = 1,
) -> tuple[float, int, float]:
    """Run every target once, compiling its kernels into the on-disk cache.

    Parameters
    ----------
    report
        Gets a line per target with its time (``[i/n] label: s``), in the order the targets finish.
    targets
        (label, function) pairs; default :data:`TARGETS`. With ``jobs > 1`` each function must be picklable
        (a module-level function).
    jobs
        Worker processes (``spawn``), each running whole targets; 1 runs them here, one after the other.

    Returns
    -------
    (seconds, compiled, compile_seconds)
        The wall seconds of the whole warmup, and the kernels compiled and the seconds spent compiling them,
        summed over the processes (0 and 0.0 when every kernel was cached).

    Raises
    ------
    ValidationError
        ``jobs`` below 1.
    """
    from ._validation import ValidationError

    if int(jobs) != jobs or jobs < 1:
        raise ValidationError(f"jobs: expected an integer >= 1, got {jobs!r}")
    todo = TARGETS if targets is None else targets
    t_all = time.perf_counter()
    compiled, compile_seconds = 0, 0.0
    if jobs == 1 or len(todo) == 1:
        for i, (label, target) in enumerate(todo, 1):
            seconds, n, s = _timed(target)
            compiled += n
            compile_seconds += s
            report(f"[{i}/{len(todo)}] {label}: {seconds:.1f} s")
        return time.perf_counter() - t_all, compiled, compile_seconds
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    context = multiprocessing.get_context("spawn")  # a fresh interpreter: no forked numba or thread state
    workers = min(int(jobs), len(todo))
    report(f"compiling the compiled paths of {len(todo)} families, {workers} processes at once")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = {pool.submit(_run_target, target): label for label, target in todo}
        for i, future in enumerate(as_completed(futures), 1):
            seconds, n, s = future.result()
            compiled += n
            compile_seconds += s
            report(f"[{i}/{len(todo)}] {futures[future]}: {seconds:.1f} s")
    return time.perf_counter() - t_all, compiled, compile_seconds
