"""The outputs of the compiled loop: the ``(runs, T, ...)`` arrays it writes, carved from one allocation of the output
pool (:func:`output_arrays`, laid out by :func:`state_specs` / :func:`cov_spec`), and the :class:`FilterResult` read
back from them (:func:`compiled_result`, :func:`loop_array`). Shared by the compiled loop and the families' glue;
:mod:`tobitkf.filters.kalman` re-exports them."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ._pool import take_buffer
from .core import FilterResult, FilterState

__all__ = ["loop_array", "cov_spec", "state_specs", "output_arrays", "compiled_result"]


_EMPTY: dict[tuple, np.ndarray] = {}


def _empty(shape: tuple) -> np.ndarray:
    """A cached zero-size float64 output (an output the compiled loop is not asked to write)."""
    arr = _EMPTY.get(shape)
    if arr is None:
        arr = _EMPTY[shape] = np.empty(shape)
    return arr


_F64 = np.dtype(np.float64)


def loop_input(a: np.ndarray) -> np.ndarray:
    """``a`` as the compiled loop takes an input: C-contiguous, writable float64 (numba types read-only arrays
    apart, and each would compile the loop once more); ``a`` itself when it already is one. The test by its
    flags, not ``np.require``, whose argument handling costs ~1 µs, a tenth of an online step."""
    if a.dtype is _F64 or a.dtype == _F64:
        flags = a.flags
        if flags.c_contiguous and flags.writeable:
            return a
    return np.require(a, float, ("C", "W"))


def loop_array(a: np.ndarray, batch: tuple[int, ...]) -> np.ndarray | None:
    """A compiled loop's output ``(N or 1, T, ...)`` as ``batch + (T, ...)``: None when it was not requested
    (``T`` axis of length 0), a read-only broadcast view when the loop wrote one row for all runs (a
    covariance shared by the runs)."""
    if a.shape[1] == 0:
        return None
    runs = int(np.prod(batch, dtype=int))
    if a.shape[0] == 1 and runs != 1:
        return np.broadcast_to(a[0], batch + a.shape[1:])
    return a.reshape(batch + a.shape[1:])


def cov_spec(want, n: int) -> tuple[bool, tuple[int, ...]]:
    """The filtered-covariance output of a compiled loop as an ``(on, shape)`` entry of :func:`output_arrays`:
    ``(runs, T, n, n)`` when ``"cov"`` is requested, ``(runs, T, n, 1)`` (the diagonals only, no n x n array
    per step) when only ``"var"`` is, not written otherwise; :func:`compiled_result` reads it back."""
    if "cov" in want:
        return True, (n, n)
    return ("var" in want), ((n, 1) if "var" in want else (n, n))


def state_specs(want, n: int) -> tuple[tuple[bool, tuple[int, ...]], ...]:
    """The four state outputs of a compiled loop as :func:`output_arrays` entries, in the order mean,
    covariance (:func:`cov_spec`), predicted mean, predicted covariance; ``n`` the state size reported."""
    return (("mean" in want, (n,)), cov_spec(want, n), ("pred_mean" in want, (n,)), ("pred_cov" in want, (n, n)))


def output_arrays(runs: int, T: int, *specs: tuple[bool, tuple[int, ...]]) -> list[np.ndarray]:
    """The ``(runs, T) + shape`` outputs of a compiled loop, one per ``(on, shape)`` entry, carved from ONE
    fresh allocation (each a C-contiguous view at a multiple of 64 bytes from its start); an entry that is off gets a
    cached ``(runs, 0) + shape`` array (not requested, not written). Why one allocation: the first touch of
    fresh memory costs a page fault per 4 KiB page, and numpy asks for transparent huge pages
    (``madvise``) on allocations of 4 MiB and more only, so separate arrays of a few MiB each (the
    fading and protocol loops' 9 and 7 outputs at 1000 runs x 100 steps) fault page by page: measured on
    the 2-core VM, ~4000 faults and ~45 ns per run-step of the fading loop's ~250. The views keep the one
    buffer alive together; a buffer of 4 MiB or more comes from the output pool
    (:mod:`tobitkf.filters._pool`), which hands it out again once the last of those views is freed."""
    sizes = [runs * T * math.prod(shape) if on else 0 for on, shape in specs]
    starts, total = [], 0
    for size in sizes:
        starts.append(total)
        total += -(-size // 8) * 8  # the next view 64 bytes further on
    buf = take_buffer(total)  # from the output pool (tobitkf.filters._pool) when large enough
    out = []
    for (on, shape), start, size in zip(specs, starts, sizes):
        if on:
            out.append(buf[start : start + size].reshape((runs, T) + shape))
        else:
            out.append(_empty((runs, 0) + shape))
    return out


def compiled_result(
    want, batch, T: int, means, covs, pmeans, pcovs, extras: dict[str, Any], final: FilterState
) -> FilterResult:
    """The :class:`FilterResult` of a compiled loop over T readings ending at ``final`` (the compiled loops of
    every family): its outputs by :func:`loop_array`, ``covs`` as laid out by :func:`cov_spec`
    (``var`` the diagonals of the covariances, or the diagonals the loop wrote alone), ``times`` the
    readings' time indices."""
    cov = loop_array(covs, batch)
    if cov is None or "var" not in want:
        var = None
    elif "cov" in want:
        var = np.diagonal(cov, axis1=-2, axis2=-1)
    else:
        var = cov[..., 0]
    return FilterResult(
        mean=loop_array(means, batch),
        cov=cov if "cov" in want else None,
        pred_mean=loop_array(pmeans, batch),
        pred_cov=loop_array(pcovs, batch),
        extras=extras,
        times=np.arange(final.k - T + 1, final.k + 1),
        var=var,
        final=final,
    )
