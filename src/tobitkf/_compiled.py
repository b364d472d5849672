"""Whether the compiled (numba) paths can run, and how many threads they use.

numba is imported lazily, on the first call that may use a kernel, so ``import tobitkf`` does
not pay for it. Each layer keeps its kernels beside its code (:mod:`tobitkf.filters._kernels`,
:mod:`tobitkf._linalg_kernels`); this module only answers the questions they share.
"""

from __future__ import annotations

from functools import lru_cache

from ._validation import ValidationError

__all__ = ["numba_available", "default_threads", "check_threads", "run_split"]


@lru_cache(maxsize=1)
def numba_available() -> bool:
    """True when numba imports (the kernels can be compiled)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def default_threads() -> int:
    """Threads for the compiled kernels: ``TOBITKF_NUM_THREADS``, else ``OMP_NUM_THREADS``
    (Dask sets it to 1 in its workers), else the number of CPUs."""
    import os

    for var in ("TOBITKF_NUM_THREADS", "OMP_NUM_THREADS"):
        val = os.environ.get(var, "")
        if val.isdigit() and int(val) >= 1:
            return int(val)
    return os.cpu_count() or 1


def check_threads(threads) -> int:
    """Validate a ``threads`` option (None = :func:`default_threads`)."""
    if threads is None:
        return default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValidationError(f"threads: expected a positive integer or None, got {threads!r}")
    return threads


def run_split(work, runs: int, threads: int, *, min_runs: int = 256) -> None:
    """Call ``work(a, b)`` on disjoint slices of the runs, in threads when worthwhile.

    The kernels release the GIL and runs are independent, so the result is the same
    bit for bit whatever the split; slices smaller than ``min_runs`` are not split.
    """
    parts = max(1, min(threads, runs // min_runs))
    if parts == 1:
        work(0, runs)
        return
    from concurrent.futures import ThreadPoolExecutor

    edges = [runs * i // parts for i in range(parts + 1)]
    with ThreadPoolExecutor(max_workers=parts) as pool:
        for fut in [pool.submit(work, a, b) for a, b in zip(edges[:-1], edges[1:])]:
            fut.result()
