r"""Readings of a censored channel: which limit each one sits at, and its exact log-likelihood.

Shared by the particle filter and the assumed-density filters. A reading within
``1e-12 max(1, |limit|)`` of a finite limit counts as censored there (the rule of
:meth:`tobitkf.Censoring.censored_mask`); NaN is a missing reading. With a recorded indicator, the
assumed-density filters also take an *interval* reading (class ``INTERVAL``): one flagged censored that lies
strictly inside two finite limits says only :math:`\text{lower} \le y^* \le \text{upper}` (an interval-censored
laboratory value, EGRET's ``ConcLow < ConcHigh``); its likelihood is the predictive mass of the interval.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import log_ndtr

from .._validation import ShapeError, ValidationError

__all__ = [
    "compiled_censored_moments",
    "classify_readings",
    "censored_log_likelihood",
    "censoring_sides",
    "interval_classes",
    "MISSING",
    "INTERIOR",
    "LOWER",
    "UPPER",
    "INTERVAL",
]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_RTOL_LIMIT = 1e-12
_MISSING, _INTERIOR, _LOWER, _UPPER, _INTERVAL = 0, 1, 2, 3, 4
MISSING, INTERIOR, LOWER, UPPER, INTERVAL = _MISSING, _INTERIOR, _LOWER, _UPPER, _INTERVAL


def classify_readings(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Class of each reading, elementwise: ``MISSING`` (NaN), ``INTERIOR``, ``LOWER`` or ``UPPER`` (at that limit).

    Parameters
    ----------
    y, lo, hi : arrays broadcasting together
        Readings and the limits (``-inf``/``+inf`` for none).

    Returns
    -------
    int8 ndarray of the shape of ``y``
    """
    tol_lo = _RTOL_LIMIT * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
    tol_hi = _RTOL_LIMIT * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
    with np.errstate(invalid="ignore"):
        at_lo = np.isfinite(lo) & (y <= lo + tol_lo)
        at_hi = np.isfinite(hi) & (y >= hi - tol_hi) & ~at_lo
    cls = np.full(y.shape, _INTERIOR, dtype=np.int8)
    cls[at_lo] = _LOWER
    cls[at_hi] = _UPPER
    cls[np.isnan(y)] = _MISSING
    return cls


def censored_log_likelihood(
    y: Any, mean: Any, std: Any, lower: Any = -np.inf, upper: Any = np.inf, *, classes: Any = None
) -> np.ndarray:
    r"""Log-likelihood of a censored normal reading, elementwise and safe in the tails.

    For :math:`y = \mathrm{clip}(y^*, l, h)`, :math:`y^* \sim N(\mu, \sigma^2)`:
    :math:`\log\phi((y-\mu)/\sigma) - \log\sigma` when :math:`l < y < h`,
    :math:`\log\Phi((l-\mu)/\sigma)` when :math:`y = l` and :math:`\log\Phi((\mu-h)/\sigma)` when
    :math:`y = h` (``scipy.special.log_ndtr``, finite for limits thousands of σ away); NaN readings
    give 0 (missing). A reading within ``1e-12 max(1, |limit|)`` of a finite limit counts as censored.
    A reading of class ``INTERVAL`` (only through ``classes``) scores the mass of its interval,
    :math:`\log(\Phi((h-\mu)/\sigma) - \Phi((l-\mu)/\sigma))`
    (:func:`~tobitkf.channels.base.log_interval_mass`).

    Parameters
    ----------
    y, mean, std, lower, upper : array_like
        Broadcasting together; ``std > 0``.
    classes : int array_like, optional
        The class of each reading (``MISSING``, ``INTERIOR``, ``LOWER``, ``UPPER``), e.g. from a recorded
        censoring indicator (a reading at the limit recorded as uncensored is ``INTERIOR`` and gets the
        density); default :func:`classify_readings`.

    Returns
    -------
    ndarray
        The log-likelihood, of the broadcast shape.

    Examples
    --------
    >>> round(float(censored_log_likelihood(0.0, 40.0, 1.0, lower=0.0)), 2)    # 40 sigma into the tail
    -804.61
    """
    y, mu, sd, lo, hi = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (y, mean, std, lower, upper)))
    cls = classify_readings(y, lo, hi) if classes is None else np.broadcast_to(classes, y.shape)
    out = np.zeros(y.shape)
    i = cls == _INTERIOR
    z = (y[i] - mu[i]) / sd[i]
    out[i] = -0.5 * z * z - np.log(sd[i]) - _LOG_SQRT_2PI
    i = cls == _LOWER
    out[i] = log_ndtr((lo[i] - mu[i]) / sd[i])
    i = cls == _UPPER
    out[i] = log_ndtr((mu[i] - hi[i]) / sd[i])
    i = cls == _INTERVAL
    if i.any():
        from ..channels.base import log_interval_mass

        with np.errstate(invalid="ignore"):
            out[i] = log_interval_mass((lo[i] - mu[i]) / sd[i], (hi[i] - mu[i]) / sd[i])
    return out


def censoring_sides(
    y: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    censored: Any = None,
    *,
    rtol: float = 1e-12,
    name: str = "censored",
    intervals: bool = False,
) -> np.ndarray:
    r"""Side of each reading: 0 uncensored (or missing), -1 censored at ``lower``, +1 at ``upper``.

    Parameters
    ----------
    y : (..., T, m) ndarray
        Readings; NaN = missing (side 0).
    lower, upper : broadcastable to y
        The limits of each reading.
    censored : (..., T, m) bool array_like, optional
        The censoring indicator recorded with the data. Default: the limit rule, a reading within
        ``rtol * max(1, |limit|)`` of a finite limit is censored (as
        :meth:`~tobitkf.Censoring.censored_mask`). With an indicator, a flagged reading is censored at
        the limit it lies at or beyond (within the same tolerance); an unflagged reading is
        uncensored even when it equals a limit (e.g. the 8 such readings of the cloud-ceiling data).
    intervals : bool, default False
        Accept a flagged reading strictly inside two finite limits as an interval reading (side 0; the
        estimators that take them: the assumed-density filters and what is built on them). Without it, or
        inside limits of which one is infinite (a flag that contradicts the reading), refused.

    Returns
    -------
    (..., T, m) int8 ndarray

    Raises
    ------
    ShapeError
        ``censored`` does not have the shape of ``y``.
    ValidationError
        ``censored`` is not boolean (or 0/1), or flags a missing reading, or one strictly inside its
        limits (with ``intervals``: inside limits that are not both finite).
    """
    lo = np.broadcast_to(lower, y.shape)
    hi = np.broadcast_to(upper, y.shape)
    tol_lo = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
    tol_hi = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
    with np.errstate(invalid="ignore"):
        at_lo = np.isfinite(lo) & (y <= lo + tol_lo)
        at_hi = np.isfinite(hi) & (y >= hi - tol_hi)
    if censored is None:
        flag = at_lo | at_hi
    else:
        flag = _as_indicator(censored, y.shape, name)
        bad = flag & np.isnan(y)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValidationError(f"{name}: reading at index {idx} is flagged censored but missing (NaN)")
        bad = flag & ~(at_lo | at_hi)
        if intervals:
            bad = bad & ~(np.isfinite(lo) & np.isfinite(hi))
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            if intervals:
                raise ValidationError(
                    f"{name}: reading {y[idx]:.6g} at index {idx} is flagged censored but lies strictly inside its "
                    f"limits [{lo[idx]:.6g}, {hi[idx]:.6g}] (an interval reading needs two finite limits)"
                )
            raise ValidationError(
                f"{name}: reading {y[idx]:.6g} at index {idx} is flagged censored but lies strictly "
                f"inside its limits [{lo[idx]:.6g}, {hi[idx]:.6g}]"
            )
    side = np.zeros(y.shape, dtype=np.int8)
    side[flag & at_lo] = -1
    side[flag & ~at_lo & at_hi] = 1
    return side


def interval_classes(cls: np.ndarray, flags: np.ndarray, lo: Any, hi: Any) -> np.ndarray:
    """Reading classes by a recorded indicator: a flagged reading keeps the limit it lies at (or beyond); a
    flagged one strictly inside two finite limits is an ``INTERVAL`` reading; an unflagged one at a limit is
    ``INTERIOR``. (A flagged reading inside limits of which one is infinite stays ``INTERIOR``: the callers
    refuse it first.)"""
    at_limit = (cls == _LOWER) | (cls == _UPPER)
    finite = np.isfinite(lo) & np.isfinite(hi)
    out = np.where(at_limit & ~flags, _INTERIOR, cls)
    return np.where(flags & (cls == _INTERIOR) & finite, _INTERVAL, out).astype(np.int8)


def _as_indicator(censored: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(censored)
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number) or not np.isin(arr, (0, 1)).all():
            raise ValidationError(f"{name}: expected a boolean indicator (True = censored) or 0/1 values")
        arr = arr.astype(bool)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ShapeError(f"{name}: expected the shape of y {shape}, got {arr.shape}") from None


def compiled_censored_moments(mean: Any, std: Any, lower: Any, upper: Any) -> Any:
    r"""The censored-normal statistics of :math:`y = \mathrm{clip}(y^*, l, h)`, :math:`y^* \sim N(\mu, \sigma^2)`,
    from :func:`~tobitkf.filters._compiled_censored.censored_stats`, the function the compiled loops call: the
    numbers of the compiled path for the numpy path's Tobit-type updates (the TKF, the fading TKF), written once
    (needs numba, a core dependency). The arguments broadcast together (``lower`` < ``upper``, either infinite;
    ``std`` > 0); returns a :class:`~tobitkf.censored.CensoredMoments` of their broadcast shape.
    :func:`tobitkf.censored_moments` is the high-precision reference (tested against it)."""
    from ..censored import CensoredMoments
    from . import _compiled_censored as kc

    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (mean, std, lower, upper)))
    shape = arrs[0].shape
    flat = [np.require(a, np.float64, ("C", "W")).reshape(-1) for a in arrs]  # one argument type: C, writable
    out = kc.censored_moments_array(flat[0], flat[1], flat[2], flat[3], kc.GL_X, kc.GL_W)
    return CensoredMoments(*(row.reshape(shape) for row in out))
