"""Choice between the numpy reference path and the compiled (numba) path of a filter.

``backend="auto"`` (the default of the filters that have a compiled path) uses the compiled
path when numba imports and the case is covered, else numpy; ``"numpy"`` always runs the
reference path; ``"numba"`` insists on the compiled path and raises if it cannot be used.
numba is imported lazily, on the first filter call that may use it, so ``import
tobitkf`` does not pay for it (:mod:`tobitkf._compiled` answers whether it can be).
"""

from __future__ import annotations

from functools import lru_cache
from types import ModuleType

from .._compiled import check_threads, default_threads, run_split
from .._validation import ValidationError

__all__ = [
    "BACKENDS",
    "numba_available",
    "compiled_module",
    "use_compiled",
    "compiled_ok",
    "system_gap",
    "default_threads",
    "check_threads",
    "run_split",
    "check_square_root",
]

BACKENDS = ("auto", "numpy", "numba")


@lru_cache(maxsize=1)
def _load() -> ModuleType | None:
    try:
        from . import _compiled_tobit
    except ImportError:
        return None
    return _compiled_tobit


def numba_available() -> bool:
    """True when the filters' compiled path can be used (numba imports)."""
    return _load() is not None


def compiled_module() -> ModuleType:
    """The :mod:`tobitkf.filters._compiled_tobit` module (imports numba)."""
    mod = _load()
    if mod is None:
        raise ImportError("backend='numba' needs the numba package (pip install numba); use backend='auto' or 'numpy'")
    return mod


def system_gap(system, u, *, inputs: bool = False, matrices: bool = True) -> str | None:
    """Why the compiled path cannot run this system/input, or None when it can. ``inputs=True``: it
    covers control inputs (constant B^u and D); ``matrices=False``: it covers time-varying and per-run
    system matrices (only the inputs are checked)."""
    if matrices and getattr(system, "per_run", False):
        return "system matrices given per run (batch_ndim)"
    if matrices and not system.time_invariant:
        return "time-varying system matrices (A, B, C, Q or R indexed by k)"
    if u is not None:
        if not inputs:
            return "control inputs u"
        if any(mat is not None and mat.varying for mat in (system.Bu, system.D)):
            return "time-varying input matrices (Bu or D indexed by k)"
    return None


def use_compiled(backend: str, gap: str | None, what: str) -> bool:
    """Decide whether to run the compiled path of ``what``.

    Raises
    ------
    ImportError
        ``backend="numba"`` without numba installed.
    ValidationError
        ``backend="numba"`` for a case the compiled path does not cover (``gap`` says which).
    """
    if backend == "numpy":
        return False
    if backend == "numba":
        compiled_module()
        if gap is not None:
            raise ValidationError(
                f"backend: the compiled path of {what} does not cover {gap}; use backend='auto' or 'numpy'"
            )
        return True
    return gap is None and numba_available()


def compiled_ok(est, u, what: str, *, inputs: bool = False) -> bool:
    """Whether ``est`` (a KF or TKF) runs its compiled path for input ``u``: decided once per estimator
    for the case without input (its system and options do not change), else afresh. ``inputs``: the
    compiled path covers control inputs (see :func:`system_gap`)."""
    if u is None:
        cached = est.__dict__.get("_compiled_static")
        if cached is None:
            cached = est._compiled_static = use_compiled(
                est.backend,
                check_square_root(est.backend, est.covariance_update, what) or system_gap(est.system, None),
                what,
            )
        return cached
    return use_compiled(
        est.backend,
        check_square_root(est.backend, est.covariance_update, what) or system_gap(est.system, u, inputs=inputs),
        what,
    )


def check_square_root(backend: str, covariance_update: str, what: str) -> str | None:
    """Refuse ``backend="numba"`` with ``covariance_update="square_root"`` (the compiled path has
    no square-root form); return the reason it cannot run that form (for :func:`use_compiled`'s
    ``gap``), or None for the other forms.

    Raises
    ------
    ValidationError
        ``backend="numba"`` together with ``covariance_update="square_root"``.
    """
    if covariance_update != "square_root":
        return None
    if backend == "numba":
        raise ValidationError(
            f"backend: the compiled path of {what} has no square-root form, so "
            "covariance_update='square_root' needs backend='auto' or 'numpy' "
            "(or use covariance_update='standard' or 'joseph' with 'numba')"
        )
    return "covariance_update='square_root'"
