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

__all__ = ["BACKENDS", "numba_available", "kernels", "use_kernel", "system_gap"]

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
