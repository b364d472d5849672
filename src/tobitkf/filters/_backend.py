"""Choice between the numpy reference path and the compiled (numba) kernels of a filter.

``backend="auto"`` (the default of the filters that have a kernel) uses the kernel
when numba imports and the case is covered, else numpy; ``"numpy"`` always runs the
reference path; ``"numba"`` insists on the kernel and raises if it cannot be used.
numba is imported lazily, on the first filter call that may use it, so ``import
tobitkf`` does not pay for it.
"""

from __future__ import annotations

from functools import lru_cache
from types import ModuleType

from .._validation import ValidationError

__all__ = ["BACKENDS", "numba_available", "kernels", "use_kernel", "system_gap", "default_threads", "check_threads",
           "run_split", "check_square_root"]

BACKENDS = ("auto", "numpy", "numba")


@lru_cache(maxsize=1)
def _load() -> ModuleType | None:
    try:
        from . import _kernels
    except ImportError:
        return None
    return _kernels


def numba_available() -> bool:
    """True when numba imports (the kernels can be compiled)."""
    return _load() is not None


def kernels() -> ModuleType:
    """The :mod:`tobitkf.filters._kernels` module (imports numba)."""
    mod = _load()
    if mod is None:
        raise ImportError("backend='numba' needs the numba package (pip install numba); "
                          "use backend='auto' or 'numpy'")
    return mod


def system_gap(system, u) -> str | None:
    """Why the kernels cannot run this system/input, or None when they can."""
    if not system.time_invariant:
        return "time-varying system matrices (A, B, C, Q or R indexed by k)"
    if u is not None:
        return "control inputs u"
    return None


def use_kernel(backend: str, gap: str | None, what: str) -> bool:
    """Decide whether to run the compiled kernel of ``what``.

    Raises
    ------
    ImportError
        ``backend="numba"`` without numba installed.
    ValidationError
        ``backend="numba"`` for a case the kernel does not cover (``gap`` says which).
    """
    if backend == "numpy":
        return False
    if backend == "numba":
        kernels()
        if gap is not None:
            raise ValidationError(f"backend: the numba kernel of {what} does not cover {gap}; "
                                  "use backend='auto' or 'numpy'")
        return True
    return gap is None and numba_available()


def check_square_root(backend: str, covariance_update: str, what: str) -> str | None:
    """Refuse ``backend="numba"`` with ``covariance_update="square_root"`` (the kernels have no
    square-root form); return the reason the kernel cannot run that form (for :func:`use_kernel`'s
    ``gap``), or None for the other forms.

    Raises
    ------
    ValidationError
        ``backend="numba"`` together with ``covariance_update="square_root"``.
    """
    if covariance_update != "square_root":
        return None
    if backend == "numba":
        raise ValidationError(f"backend: the numba kernel of {what} has no square-root form, so "
                              "covariance_update='square_root' needs backend='auto' or 'numpy' "
                              "(or use covariance_update='standard' or 'joseph' with 'numba')")
    return "covariance_update='square_root'"


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
