"""Input checks shared by every public entry point.

Every check raises a :class:`ValueError` subclass whose message names the
argument, what was expected and what was found. Checks run once at the public
boundary (constructors, ``filter``, ``simulate``), never inside a time loop.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from ._progress import plural

__all__ = [
    "diagonal_sigma",
    "as_float",
    "as_generator",
    "check_bool",
    "check_int",
    "check_memory",
    "check_scale",
    "READING_LIMIT",
    "memory_limit",
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


_MAX_NESTING = 64  # numpy's own limit on dimensions; deeper lists cannot be arrays
_COMPLEX = "complex"


def _not_a_number(value: Any) -> str | None:
    """Describe the first entry of ``value`` that is text, a boolean or nested too deep, else None.

    Text and booleans convert silently to floats (``"0.5"`` -> 0.5, ``True`` -> 1.0), so a typo in a
    file or a flag passed in a number's place would be taken as a number; integers stay accepted.
    Nested lists are walked without recursion (a list holding itself stops at the depth limit).
    """
    stack = [(value, 0)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, (str, bytes)):
            return f"{type(v).__name__} ({v!r:.40}; text is not a number)"
        if isinstance(v, (bool, np.bool_)):
            return f"bool ({v!r}; a boolean is not a number)"
        if isinstance(v, (complex, np.complexfloating)):
            return _COMPLEX
        if isinstance(v, (list, tuple)):
            if depth >= _MAX_NESTING:
                return f"{type(value).__name__} nested deeper than {_MAX_NESTING} levels"
            stack.extend((x, depth + 1) for x in v)
        elif isinstance(v, np.ndarray):
            if v.dtype.kind == "b":
                return "booleans (an array of True/False is not an array of numbers)"
            if v.dtype.kind in ("U", "S"):
                return "text (an array of strings is not an array of numbers)"
            if v.dtype.kind == "O" and depth < _MAX_NESTING:
                stack.extend((x, depth + 1) for x in v.ravel().tolist())
    return None


#: the native float64 dtype, a singleton: ``dtype is _F64`` is the cheap test of the common case (another
#: float64 descriptor, e.g. byte-swapped, takes the general route, which converts it)
_F64 = np.dtype(np.float64)


def as_float_array(
    value: Any, name: str, *, ndim: int | Iterable[int] | None = None, allow_nan: bool = False, allow_inf: bool = False
) -> np.ndarray:
    """Convert ``value`` to a float64 array and check dimension and finiteness.

    Integer, float, read-only, strided, masked and pandas input is accepted; text (also numeric
    text such as ``"0.5"``), booleans and complex values are refused, naming ``name``. The masked entries
    of a numpy masked array are missing values: NaN where ``allow_nan`` (a missing reading), refused
    otherwise (never the number hidden under the mask).
    """
    if type(value) is np.ndarray and value.dtype is _F64:  # the common case: nothing to convert
        arr = value
    elif isinstance(value, np.ma.MaskedArray):
        arr = _unmask(value, name, allow_nan)
    elif isinstance(value, float) or (
        isinstance(value, int) and not isinstance(value, bool) and -(2**1023) < value < 2**1023
    ):
        arr = np.asarray(value, dtype=float)
    else:
        arr = _convert(value, name)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in allowed:
            raise ShapeError(
                f"{name}: expected {' or '.join(str(a) for a in allowed)} dimension(s), got shape {arr.shape}"
            )
    check_finite(arr, name, allow_nan=allow_nan, allow_inf=allow_inf)
    return arr


def _unmask(value: np.ma.MaskedArray, name: str, allow_nan: bool) -> np.ndarray:
    """float64 array of a masked array with its masked entries NaN (refused unless ``allow_nan``)."""
    data = _convert(np.ma.getdata(value), name)
    mask = np.ma.getmaskarray(value)
    if not mask.any():
        return data
    if not allow_nan:
        raise ValidationError(
            f"{name}: expected finite numbers, found {int(mask.sum())} masked entries (a masked entry is missing: NaN)"
        )
    out = np.array(data, dtype=np.float64, copy=True)  # never write into the caller's data
    out[mask] = np.nan
    return out


def _convert(value: Any, name: str) -> np.ndarray:
    """float64 array of anything but a float64 array: text, booleans and complex values refused."""
    if not (isinstance(value, np.ndarray) and value.dtype.kind in "fiu"):
        if not isinstance(value, (list, tuple, str, bytes, bool, np.generic, np.ndarray, int, float)):
            try:  # pandas, masked arrays, array-likes: look at what they hold
                value = np.asarray(value)
            except Exception:  # noqa: BLE001 - whatever it is, the conversion below names it
                pass
        bad = _not_a_number(value)
        if bad is _COMPLEX:
            raise ValidationError(f"{name}: expected real numbers, got complex values")
        if bad is not None:
            raise ValidationError(f"{name}: expected an array of numbers, got {bad}")
    try:
        with warnings.catch_warnings():
            # complex input: numpy would drop the imaginary part with only a warning
            warnings.simplefilter("error", np.exceptions.ComplexWarning)
            return np.asarray(value, dtype=float)
    except np.exceptions.ComplexWarning:
        raise ValidationError(f"{name}: expected real numbers, got complex values") from None
    except (TypeError, ValueError, OverflowError, RecursionError) as exc:
        raise ValidationError(f"{name}: expected an array of numbers, got {type(value).__name__} ({exc})") from None


def as_float(
    value: Any,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_inf: bool = False,
) -> float:
    """A real number (not text, not a boolean, not NaN; inf only if ``allow_inf``) within the bounds.

    ``low``/``high`` are inclusive unless ``low_open``/``high_open``. The message names ``name``,
    the interval and the value found.
    """
    arr = as_float_array(value, name, allow_inf=allow_inf)
    if arr.ndim != 0:
        raise ShapeError(f"{name}: expected a single number, got shape {arr.shape}")
    x = float(arr)
    below = low is not None and (x <= low if low_open else x < low)
    above = high is not None and (x >= high if high_open else x > high)
    if below or above:
        lo_s = "-inf" if low is None else f"{low:g}"
        hi_s = "inf" if high is None else f"{high:g}"
        interval = (
            ("(" if low_open or low is None else "[") + f"{lo_s}, {hi_s}" + (")" if high_open or high is None else "]")
        )
        raise ValidationError(f"{name}: expected a number in {interval}, got {value!r}")
    return x


def check_int(value: Any, name: str, *, minimum: int = 0, maximum: int | None = None) -> int:
    """An integer ``minimum <= value <= maximum`` (Python or numpy); booleans, floats (also 2.0),
    text, NaN and inf are refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValidationError(f"{name}: expected an integer >= {minimum}, got {value!r} ({type(value).__name__})")
    if value < minimum or (maximum is not None and value > maximum):
        bound = f"in [{minimum}, {maximum}]" if maximum is not None else f">= {minimum}"
        raise ValidationError(f"{name}: expected an integer {bound}, got {value}")
    return int(value)


def check_bool(value: Any, name: str) -> bool:
    """``True`` or ``False`` (also numpy's); 0/1, 1.0 and text such as ``"yes"`` are refused."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValidationError(f"{name}: expected True or False, got {value!r} ({type(value).__name__})")
    return bool(value)


def memory_limit() -> int:
    """Bytes one result may take: ``TOBITKF_MEMORY_LIMIT`` if set, else the machine's physical memory
    (or the container's limit when it is smaller)."""
    env = os.environ.get("TOBITKF_MEMORY_LIMIT")
    if env:
        try:
            return max(int(float(env)), 1)
        except ValueError:
            raise ValidationError(f"TOBITKF_MEMORY_LIMIT: expected a number of bytes, got {env!r}") from None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 2**40
    try:
        with open("/sys/fs/cgroup/memory.max", encoding="ascii") as fh:
            cg = fh.read().strip()
        if cg.isdigit():
            total = min(total, int(cg))
    except OSError:
        pass
    return int(total)


def _bytes(n: int) -> str:
    if n >= 10**21:  # beyond any unit (and beyond float range for huge counts)
        return f"about 10^{len(str(int(n))) - 1} bytes"
    for unit, size in (("EB", 1e18), ("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} bytes"


def check_memory(nbytes: int, name: str, what: str) -> None:
    """Refuse, before anything is allocated, a request whose arrays cannot fit in memory.

    ``nbytes`` is computed with Python integers (no overflow); the message names ``name``, the
    arrays (``what``) and both sizes.
    """
    limit = memory_limit()
    if nbytes > limit:
        raise ValidationError(
            f"{name}: {what} would need {_bytes(nbytes)}, more than the {_bytes(limit)} of memory "
            "available (set TOBITKF_MEMORY_LIMIT to change the limit)"
        )


def check_finite(arr: np.ndarray, name: str, *, allow_nan: bool = False, allow_inf: bool = False) -> None:
    """Raise if ``arr`` holds NaN (unless allowed) or +-inf (unless allowed)."""
    if arr.size <= 4 and arr.dtype is _F64:  # one reading of an online step: Python floats, same verdict
        vals = arr.ravel().tolist()
        # the passing verdict in one C-level map, no generator (all finite; with NaN allowed, no inf); a
        # reading that fails it gets the checks below, which name what they found
        if not any(map(math.isinf, vals)) if allow_nan and not allow_inf else all(map(math.isfinite, vals)):
            return
        if not allow_nan and any(v != v for v in vals):
            raise ValidationError(f"{name}: expected finite numbers, found NaN")
        if not allow_inf and any(v in (math.inf, -math.inf) for v in vals):
            raise ValidationError(f"{name}: expected finite numbers, found inf")
        return
    if not allow_nan and not allow_inf and np.isfinite(arr).all():
        return  # the common case in one pass over the array, not one for NaN and one for inf
    if not allow_nan and np.isnan(arr).any():
        raise ValidationError(f"{name}: expected finite numbers, found NaN")
    if not allow_inf and np.isinf(arr).any():
        raise ValidationError(f"{name}: expected finite numbers, found inf")


#: largest magnitude of a reading: its square (a variance, a likelihood term) must not overflow float64
READING_LIMIT = 1e150
_READING_TOO_BIG = READING_LIMIT.__lt__  # x -> READING_LIMIT < x (False for NaN)


def reading_in_scale(vals: list[float]) -> bool:
    """Whether every (finite or NaN) value of the list lies within :data:`READING_LIMIT` in magnitude: two
    C-level maps, for an online step's reading."""
    return not any(map(_READING_TOO_BIG, map(abs, vals)))


def check_scale(arr: np.ndarray, name: str) -> None:
    """Refuse readings larger than :data:`READING_LIMIT` (1e150) in magnitude, naming ``name``, the value and
    its index: squares of them overflow float64, so no estimate, variance or likelihood of them is finite.
    NaN (missing) passes."""
    if arr.size == 0:
        return
    flat = arr.reshape(-1)
    # two passes without a temporary (fmax/fmin skip NaN); the index is looked for only when one is too big
    if not (np.fmax.reduce(flat) > READING_LIMIT or np.fmin.reduce(flat) < -READING_LIMIT):
        return
    with np.errstate(invalid="ignore"):
        bad = np.abs(arr) > READING_LIMIT
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValidationError(
            f"{name}: reading {float(arr[idx]):.6g} at index {idx} is beyond +-{READING_LIMIT:g}, where its square "
            "overflows float64; rescale the data (e.g. change its units)"
        )


def check_instance(value: Any, cls: type, name: str) -> None:
    """Raise :class:`ValidationError` naming ``name`` unless ``value`` is a ``cls``."""
    if not isinstance(value, cls):
        article = "an" if cls.__name__[:1].lower() in "aeiou" else "a"
        raise ValidationError(f"{name}: expected {article} {cls.__name__}, got {type(value).__name__}")


def _same_option(value: Any, option: Any) -> bool:
    """``value == option`` of the same kind: ``1.0`` is not ``True``, ``True`` is not ``1``, ``"1"`` is not ``1``."""
    if isinstance(option, (bool, np.bool_)) or isinstance(value, (bool, np.bool_)):
        return (
            isinstance(value, (bool, np.bool_)) and isinstance(option, (bool, np.bool_)) and bool(value) == bool(option)
        )
    if isinstance(option, str) or isinstance(value, str):
        return isinstance(value, str) and isinstance(option, str) and value == option
    if isinstance(option, (int, np.integer)) and not isinstance(value, (int, np.integer)):
        return False  # 2.0 is not the option 2 (nor 2.5 rounded to it)
    try:
        return bool(value == option)
    except (TypeError, ValueError):  # arrays and other things that are no option
        return False


def check_option(value: Any, name: str, allowed: Iterable[Any]) -> Any:
    """Raise unless ``value`` is one of ``allowed`` (of the same kind: ``1.0`` is not ``True``); return it."""
    allowed = tuple(allowed)
    if not any(_same_option(value, a) for a in allowed):
        raise ValidationError(f"{name}: expected one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
    return value


def check_probability(value: Any, name: str, *, open_low: bool = False, open_high: bool = False) -> np.ndarray:
    """Check that every entry lies in [0, 1] (or the requested open interval)."""
    arr = as_float_array(value, name)
    lo_bad = arr <= 0 if open_low else arr < 0
    hi_bad = arr >= 1 if open_high else arr > 1
    if (lo_bad | hi_bad).any():
        interval = ("(" if open_low else "[") + "0, 1" + (")" if open_high else "]")
        raise ValidationError(
            f"{name}: expected probabilities in {interval}, got {arr.ravel()[(lo_bad | hi_bad).ravel()][:3]}"
        )
    return arr


def check_psd(mat: np.ndarray, name: str, *, strict: bool = False, rtol: float = 1e-9) -> None:
    """Check that ``mat`` (..., n, n) is symmetric and positive semi-definite.

    Symmetry is checked to ``rtol`` relative to the largest entry; the smallest
    eigenvalue must be >= -rtol * scale (or > 0 when ``strict``).
    """
    if mat.ndim < 2 or mat.shape[-1] != mat.shape[-2]:
        raise ShapeError(f"{name}: expected a square matrix (..., n, n), got shape {mat.shape}")
    tiny = np.finfo(float).tiny
    diag = np.abs(np.diagonal(mat, axis1=-2, axis2=-1))
    sub = (diag > 0) & (diag < tiny)
    if sub.any():  # e.g. R = 1e-320: 1/R overflows, a NEES of such a filter is inf
        raise ValidationError(
            f"{name}: expected variances of 0 or at least {tiny:.3g} on the diagonal, got "
            f"{float(diag[sub][0]):.3g} (a subnormal number, without the precision a variance needs)"
        )
    d = np.diagonal(mat, axis1=-2, axis2=-1)
    if np.count_nonzero(mat) == np.count_nonzero(d):  # diagonal (e.g. one per run): symmetric, its eigenvalues
        scale = max(float(diag.max(initial=0.0)), tiny)
        eig = d
    else:
        scale = max(float(np.abs(mat).max(initial=0.0)), tiny)
        with np.errstate(over="ignore"):  # +-1e308 entries: the difference overflows to inf, i.e. asymmetric
            asym = float(np.abs(mat - np.swapaxes(mat, -1, -2)).max(initial=0.0))
        if asym > rtol * scale:
            raise ValidationError(
                f"{name}: expected a symmetric matrix, asymmetry {asym:.3g} relative to scale {scale:.3g}"
            )
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
        ``(r, c)`` constant, ``(T, r, c)`` one matrix per step, or ``f(k) -> (r, c)`` (with ``batch_ndim``
        also ``f(k) -> (*batch, r, c)``, the run axes of its first value kept at every k).
    name : str
        Argument name used in error messages.
    core_ndim : int
        2 for matrices, 1 for vectors.
    offset : int
        Array index of paper time ``k`` is ``k - offset`` (0 for A, Q, B whose
        first use is at k = 0; 1 for C, R whose first use is y_1).
    batch_ndim : int, default 0
        Number of leading run axes an array may carry: with ``b > 0`` an array of ``core_ndim`` axes is
        shared by every run, one of ``core_ndim + b`` axes is ``(*batch, r, c)`` (one constant matrix per
        run) and one of ``core_ndim + b + 1`` axes ``(*batch, T, r, c)``. ``batch_shape`` holds the run
        axes (``()`` when shared; a callable is always shared) and :meth:`at` returns ``(*batch_shape, r, c)``.
    """

    def __init__(
        self,
        value: Any,
        name: str,
        *,
        core_ndim: int = 2,
        offset: int = 0,
        psd: bool = False,
        strict_psd: bool = False,
        batch_ndim: int = 0,
    ):
        self.name = name
        self.offset = offset
        self.core_ndim = core_ndim
        self._psd = psd
        self._strict = strict_psd
        self._valid_to = offset  # a callable is validated for k < _valid_to (each k once)
        self.batch_shape: tuple[int, ...] = ()
        self.fn: Callable[[int], Any] | None = None
        self.array: np.ndarray | None = None
        if batch_ndim and not callable(value):
            arr = as_float_array(value, name)
            allowed = (core_ndim, core_ndim + batch_ndim, core_ndim + batch_ndim + 1)
            if arr.ndim not in allowed:
                raise ShapeError(
                    f"{name}: expected {core_ndim} axes (shared by the runs), {allowed[1]} (one matrix per run: "
                    f"{batch_ndim} run axes first) or {allowed[2]} (run axes, then time), got shape {arr.shape}"
                )
            self.fn = None
            self.array = arr
            self.batch_shape = arr.shape[:batch_ndim] if arr.ndim > core_ndim else ()
            self.varying = arr.ndim == allowed[2]
            self.core_shape = arr.shape[arr.ndim - core_ndim :]
            self._check(arr, name)
            return
        if callable(value):
            self.fn = value
            first = as_float_array(
                value(offset),
                f"{name}({offset})",
                ndim=(core_ndim, core_ndim + batch_ndim) if batch_ndim else core_ndim,
            )
            self.batch_shape = first.shape[: first.ndim - core_ndim]  # a callable of one matrix per run
            self.core_shape = first.shape[first.ndim - core_ndim :]
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
        return self.array.shape[len(self.batch_shape)] if (self.varying and self.array is not None) else None

    def at(self, k: int) -> np.ndarray:
        """The matrix at paper time ``k``."""
        if self.fn is not None:
            mat = self.fn(k)
            if not (isinstance(mat, np.ndarray) and mat.dtype == np.float64):
                # text, booleans or complex values at a later k: refused by name, never dropped
                mat = as_float_array(mat, f"{self.name}({k})", allow_nan=True, allow_inf=True)
            if mat.shape[len(mat.shape) - len(self.core_shape) :] != self.core_shape or (
                mat.ndim > len(self.core_shape) and mat.shape[: mat.ndim - len(self.core_shape)] != self.batch_shape
            ):
                raise ShapeError(
                    f"{self.name}({k}): expected shape {self.batch_shape + self.core_shape}, got {mat.shape}"
                )
            return mat
        assert self.array is not None, "a constant or time-indexed sequence holds its array"
        if self.varying:
            idx = k - self.offset
            nb = len(self.batch_shape)
            if not 0 <= idx < self.array.shape[nb]:
                raise ShapeError(
                    f"{self.name}: time-indexed array has {plural(self.array.shape[nb], 'step')}, "
                    f"step k={k} (index {idx}) requested"
                )
            return self.array[(slice(None),) * nb + (idx,)]
        return self.array

    def check_horizon(self, steps: int) -> None:
        """Raise if a time-indexed array is shorter than ``steps``."""
        if self.steps is not None and self.steps < steps:
            raise ShapeError(f"{self.name}: time-indexed array has {plural(self.steps, 'step')}, {steps} needed")

    def validate_all(self, steps: int) -> None:
        """Check a callable over the whole horizon (shapes and PSD), each time index once: a later call checks
        only the steps beyond those already checked (an online step extends the horizon by one)."""
        if self.fn is not None:
            end = self.offset + steps
            for k in range(max(self.offset, self.__dict__.get("_valid_to", self.offset)), end):
                mat = self.at(k)
                check_finite(mat, f"{self.name}({k})")
                self._check(mat, f"{self.name}({k})")
                self._valid_to = k + 1


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
    if isinstance(seed, (bool, np.bool_, str, bytes, float, np.floating)):
        raise ValidationError(f"seed: expected an int, SeedSequence or Generator, got {seed!r} ({type(seed).__name__})")
    try:
        return np.random.default_rng(seed)
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"seed: expected an int, SeedSequence or Generator, got {seed!r} ({exc})") from None


def diagonal_sigma(
    R: np.ndarray,
    name: str = "R",
    *,
    who: str = "the Tobit Kalman filter",
    why: str = "Miller Assumption A2, (3.36)",
    positive: str | None = None,
) -> np.ndarray:
    """Channel standard deviations sqrt(diag R) (m,) of a diagonal R (m, m), refusing a correlated or singular
    one (naming ``who`` and the source's reason ``why``); shared by the Tobit families and the closed loops.

    Raises
    ------
    ValidationError
        R not diagonal (to 1e-12 relative) or a variance not positive.
    """
    d = np.diagonal(R, axis1=-2, axis2=-1)  # (m,), or (N, m) for one R per run
    off = R - d[..., :, None] * np.eye(R.shape[-1])
    if np.abs(off).max(initial=0.0) > 1e-12 * max(1.0, float(np.abs(R).max())):
        raise ValidationError(f"{name}: {who} needs a diagonal R ({why})")
    if np.any(d <= 0):
        raise ValidationError(f"{name}: {positive or who + ' needs positive measurement variances'}, got {d}")
    return np.sqrt(d)
