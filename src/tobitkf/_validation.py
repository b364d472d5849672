"""Input checks shared by every public entry point.

Every check raises a :class:`ValueError` subclass whose message names the
argument, what was expected and what was found. Checks run once at the public
boundary (constructors, ``filter``, ``simulate``), never inside a time loop.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

__all__ = [
    "as_generator",
    "check_count",
    "ShapeError",
    "ValidationError",
    "as_float_array",
    "check_finite",
    "check_instance",
    "check_option",
    "check_psd",
    "check_probability",
    "TimeSequence",
]


class ValidationError(ValueError):
    """A public argument has an invalid value (NaN, out of range, unknown option...)."""


class ShapeError(ValidationError):
    """A public argument has the wrong shape."""


def as_float_array(value: Any, name: str, *, ndim: int | Iterable[int] | None = None,
                   allow_nan: bool = False, allow_inf: bool = False) -> np.ndarray:
    """Convert ``value`` to a float64 array and check dimension and finiteness."""
    if type(value) is np.ndarray and value.dtype == np.float64:   # already numbers: no conversion to check
        return _checked(value, name, ndim, allow_nan, allow_inf)
    try:
        with warnings.catch_warnings():
            # complex input: numpy would drop the imaginary part with only a warning
            warnings.simplefilter("error", np.exceptions.ComplexWarning)
            arr = np.asarray(value, dtype=float)
    except np.exceptions.ComplexWarning:
        raise ValidationError(f"{name}: expected real numbers, got complex values") from None
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"{name}: expected an array of numbers, got {type(value).__name__} ({exc})") from None
    return _checked(arr, name, ndim, allow_nan, allow_inf)


def _checked(arr: np.ndarray, name: str, ndim, allow_nan: bool, allow_inf: bool) -> np.ndarray:
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in allowed:
            raise ShapeError(f"{name}: expected {' or '.join(str(a) for a in allowed)} dimension(s), "
                             f"got shape {arr.shape}")
    check_finite(arr, name, allow_nan=allow_nan, allow_inf=allow_inf)
    return arr


def check_finite(arr: np.ndarray, name: str, *, allow_nan: bool = False, allow_inf: bool = False) -> None:
    """Raise if ``arr`` holds NaN (unless allowed) or +-inf (unless allowed)."""
    if not allow_nan and np.isnan(arr).any():
        raise ValidationError(f"{name}: expected finite numbers, found NaN")
    if not allow_inf and np.isinf(arr).any():
        raise ValidationError(f"{name}: expected finite numbers, found inf")


def check_instance(value: Any, cls: type, name: str) -> None:
    """Raise :class:`ValidationError` naming ``name`` unless ``value`` is a ``cls``."""
    if not isinstance(value, cls):
        article = "an" if cls.__name__[:1].lower() in "aeiou" else "a"
        raise ValidationError(f"{name}: expected {article} {cls.__name__}, got {type(value).__name__}")


def check_option(value: Any, name: str, allowed: Iterable[Any]) -> Any:
    """Raise unless ``value`` is one of ``allowed``; return it."""
    allowed = tuple(allowed)
    if value not in allowed:
        raise ValidationError(f"{name}: expected one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
    return value


def check_probability(value: Any, name: str, *, open_low: bool = False, open_high: bool = False) -> np.ndarray:
    """Check that every entry lies in [0, 1] (or the requested open interval)."""
    arr = as_float_array(value, name)
    lo_bad = arr <= 0 if open_low else arr < 0
    hi_bad = arr >= 1 if open_high else arr > 1
    if (lo_bad | hi_bad).any():
        interval = ("(" if open_low else "[") + "0, 1" + (")" if open_high else "]")
        raise ValidationError(f"{name}: expected probabilities in {interval}, got {arr.ravel()[(lo_bad | hi_bad).ravel()][:3]}")
    return arr


def check_psd(mat: np.ndarray, name: str, *, strict: bool = False, rtol: float = 1e-9) -> None:
    """Check that ``mat`` (..., n, n) is symmetric and positive semi-definite.

    Symmetry is checked to ``rtol`` relative to the largest entry; the smallest
    eigenvalue must be >= -rtol * scale (or > 0 when ``strict``).
    """
    if mat.ndim < 2 or mat.shape[-1] != mat.shape[-2]:
        raise ShapeError(f"{name}: expected a square matrix (..., n, n), got shape {mat.shape}")
    scale = max(float(np.abs(mat).max(initial=0.0)), np.finfo(float).tiny)
    with np.errstate(over="ignore"):  # +-1e308 entries: the difference overflows to inf, i.e. asymmetric
        asym = float(np.abs(mat - np.swapaxes(mat, -1, -2)).max(initial=0.0))
    if asym > rtol * scale:
        raise ValidationError(f"{name}: expected a symmetric matrix, asymmetry {asym:.3g} relative to scale {scale:.3g}")
    eig = np.linalg.eigvalsh(0.5 * mat + 0.5 * np.swapaxes(mat, -1, -2))  # halves first: no overflow at 1e308
    lo = float(eig.min(initial=np.inf))
    if strict and lo <= 0:
        raise ValidationError(f"{name}: expected a positive definite matrix, smallest eigenvalue {lo:.3g}")
    if lo < -rtol * scale:
        raise ValidationError(f"{name}: expected a positive semi-definite matrix, smallest eigenvalue {lo:.3g}")


class TimeSequence:
    """A matrix that is constant, given per step, or a callable of the time index.

    Parameters
    ----------
    value : array_like or callable
        ``(r, c)`` constant, ``(T, r, c)`` one matrix per step, or ``f(k) -> (r, c)``.
    name : str
        Argument name used in error messages.
    core_ndim : int
        2 for matrices, 1 for vectors.
    offset : int
        Array index of paper time ``k`` is ``k - offset`` (0 for A, Q, B whose
        first use is at k = 0; 1 for C, R whose first use is y_1).
    """

    def __init__(self, value: Any, name: str, *, core_ndim: int = 2, offset: int = 0,
                 psd: bool = False, strict_psd: bool = False):
        self.name = name
        self.offset = offset
        self.core_ndim = core_ndim
        self._psd = psd
        self._strict = strict_psd
        if callable(value):
            self.fn: Callable[[int], Any] | None = value
            first = as_float_array(value(offset), f"{name}({offset})", ndim=core_ndim)
            self.core_shape = first.shape
            self.array = None
            self.varying = True
            self._check(first, f"{name}({offset})")
        else:
            self.fn = None
            arr = as_float_array(value, name, ndim=(core_ndim, core_ndim + 1))
            self.varying = arr.ndim == core_ndim + 1
            self.core_shape = arr.shape[1:] if self.varying else arr.shape
            self.array = arr
            self._check(arr, name)

    def _check(self, arr: np.ndarray, name: str) -> None:
        if self._psd:
            check_psd(arr, name, strict=self._strict)

    @property
    def steps(self) -> int | None:
        """Number of steps stored, or None for constants and callables."""
        return self.array.shape[0] if (self.varying and self.array is not None) else None

    def at(self, k: int) -> np.ndarray:
        """The matrix at paper time ``k``."""
        if self.fn is not None:
            mat = np.asarray(self.fn(k), dtype=float)
            if mat.shape != self.core_shape:
                raise ShapeError(f"{self.name}({k}): expected shape {self.core_shape}, got {mat.shape}")
            return mat
        if self.varying:
            idx = k - self.offset
            if not 0 <= idx < self.array.shape[0]:
                raise ShapeError(f"{self.name}: time-indexed array has {self.array.shape[0]} steps, "
                                 f"step k={k} (index {idx}) requested")
            return self.array[idx]
        return self.array

    def check_horizon(self, steps: int) -> None:
        """Raise if a time-indexed array is shorter than ``steps``."""
        if self.steps is not None and self.steps < steps:
            raise ShapeError(f"{self.name}: time-indexed array has {self.steps} steps, {steps} needed")

    def validate_all(self, steps: int) -> None:
        """Check a callable over the whole horizon once (shapes and PSD)."""
        if self.fn is not None:
            for k in range(self.offset, self.offset + steps):
                mat = self.at(k)
                check_finite(mat, f"{self.name}({k})")
                self._check(mat, f"{self.name}({k})")


def check_count(value: Any, name: str) -> int:
    """A positive integer count (``steps``, ``runs``, ...); booleans and floats are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValidationError(f"{name}: expected a positive integer, got {value!r}")
    if value < 1:
        raise ValidationError(f"{name}: expected a positive integer, got {value}")
    return int(value)


def as_generator(seed: Any) -> np.random.Generator:
    """A ``numpy.random.Generator`` from an int, a SeedSequence or a Generator (an explicit seed)."""
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None:
        raise ValidationError("seed: expected an int, SeedSequence or Generator (an explicit seed), got None")
    try:
        return np.random.default_rng(seed)
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"seed: expected an int, SeedSequence or Generator, got {seed!r} ({exc})") from None
