r"""Sample times for the filters of a continuous-time model: the per-gap system, and the state on a grid.

A filter of a :class:`~tobitkf.ContinuousLinearSystem` given ``times=`` runs on the exact discretisation of
each gap (:meth:`~tobitkf.ContinuousLinearSystem.at_times`): :func:`at_times` returns a copy of the
estimator on that time-varying system (its options kept), which every entry point (``filter``,
``smooth``, ``log_likelihood``) then calls as usual. :func:`smooth_on_grid` returns the smoothed state at
any requested times: the grid times join the sample times as missing readings (NaN), the smoother runs on
the union, and the rows of the grid are returned,

.. math::

    \hat x(g) = E[x(g) \mid y_{1:T}], \quad P(g) = \mathrm{Cov}[x(g) \mid y_{1:T}], \qquad g \in \text{grid}.

Known inputs on the grid (a daily covariate) enter with zero-order hold: the value at a grid time acts
over the gap that ends there, so ``u`` is given on the grid and every sample time must be a grid time.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ..channels.censoring import Censoring
from ..models.continuous import ContinuousLinearSystem, _as_dates, check_increasing
from .core import FilterResult

__all__ = ["at_times", "system_at_times", "model_times", "smooth_on_grid"]

_CACHES = ("_loop_mats",)  # per-system caches of an estimator (rebuilt for the new system)


def _continuous(est: Any) -> ContinuousLinearSystem:
    sys_ = est.system
    if not isinstance(sys_, ContinuousLinearSystem):
        raise ValidationError(
            "times: sample times need a model in continuous time (tk.ContinuousLinearSystem), "
            f"got a discrete {type(sys_).__name__}"
        )
    return sys_


def model_times(system: ContinuousLinearSystem, times: Any, *others: Any) -> list[np.ndarray | None]:
    """``times`` and each of ``others`` (None passes through) as floats in the model's unit with one origin
    (the earliest date of all), so that they can be merged; dates and numbers are not mixed."""
    groups = [times, *others]
    dates = [None if g is None else _as_dates(g) for g in groups]
    given = [d for g, d in zip(groups, dates) if g is not None]
    if any(d is None for d in given) and any(d is not None for d in given):
        raise ValidationError("times/grid/start: give all as dates or all as numbers, not a mix")
    origin = None
    if given and given[0] is not None:
        origin = min(np.asarray(d).min() for d in given if d is not None and np.asarray(d).size)
    out: list[np.ndarray | None] = []
    for g in groups:
        out.append(None if g is None else system.time_values(np.atleast_1d(g), origin=origin))
    return out


def system_at_times(system: Any, times: Any, y: Any = None, *, start: Any = None) -> Any:
    """The discrete system of ``system`` (a :class:`~tobitkf.ContinuousLinearSystem`) at the sample ``times``
    of the readings ``y`` (..., T, m); errors as :func:`at_times`."""
    return at_times(_Holder(system), times, y, start=start).system


class _Holder:
    """A bare holder of a system, so that :func:`system_at_times` shares :func:`at_times`' checks."""

    def __init__(self, system: Any):
        self.system = system

    def _setup_system(self, system: Any) -> None:
        self.system = system


def at_times(est: Any, times: Any, y: Any = None, *, start: Any = None) -> Any:
    """A copy of the estimator ``est`` (its options kept) on the exact discretisation of its continuous-time
    system at ``times`` (:meth:`~tobitkf.ContinuousLinearSystem.at_times`, the prior at ``start``).

    Raises
    ------
    ValidationError
        ``est`` has a discrete-time system; bad times (see ``at_times``).
    ShapeError
        ``len(times)`` differs from the time axis of ``y`` (..., T, m).
    """
    sys_ = _continuous(est)
    if y is not None:
        arr = np.asarray(y, dtype=float)
        T = arr.shape[-2] if arr.ndim >= 2 else arr.shape[0]
        if np.size(times) != T:
            raise ShapeError(f"times: expected one time per reading ({T}), got {np.size(times)}")
    new = copy.copy(est)
    for key in _CACHES:
        new.__dict__.pop(key, None)
    new._setup_system(sys_.at_times(times, start=start))
    return new


def smooth_on_grid(
    est: Any,
    y: Any,
    times: Any,
    grid: Any,
    *,
    u: Any = None,
    censored: Any = None,
    x0: Any = None,
    P0: Any = None,
    start: Any = None,
) -> FilterResult:
    r"""The smoothed state at the ``grid`` times from readings ``y`` (..., T, m) at ``times`` (module docstring).

    Parameters
    ----------
    est : a filter with ``smooth`` (KF, TKF, assumed-density) of a :class:`~tobitkf.ContinuousLinearSystem`
    y : (..., T, m) array_like
        Readings at ``times``; NaN = missing.
    times : (T,) array_like
        Strictly increasing sample times (floats in the model's unit, or dates).
    grid : (G,) array_like
        Strictly increasing times at which the state is wanted (same kind as ``times``); they may
        coincide with sample times.
    u : (..., G, p) array_like, optional
        Known inputs on the grid (zero-order hold: the value at a grid time acts over the gap ending
        there); then every sample time must be a grid time.
    censored : (..., T, m) bool array_like, optional
        The recorded censoring indicator of ``y``.
    x0, P0 : array_like, optional
        Override the prior.
    start : float or date, optional
        The time of the prior (default: the earliest of ``times`` and ``grid``).

    Returns
    -------
    FilterResult
        ``mean`` (..., G, n) and ``cov`` (..., G, n, n) at the grid times; ``times`` the grid as given;
        ``extras``: ``union_times`` (the merged times in the model's unit), ``grid_index`` and
        ``sample_index`` (their rows in the union) and ``smoothed`` (the smoother's result on the union).

    Raises
    ------
    ValidationError
        Duplicate or unordered times or grid, dates mixed with numbers, a sample time off the grid when
        ``u`` is given.
    ShapeError
        ``len(times)`` differs from the readings', ``u`` not on the grid.
    """
    sys_ = _continuous(est)
    t, g, s = model_times(sys_, times, grid, start)
    assert t is not None and g is not None, "times and grid are given"
    check_increasing(t)
    check_increasing(g, "grid")
    arr = as_float_array(y, "y", allow_nan=True)
    arr = arr[:, None] if arr.ndim == 1 else arr
    lead, (T, m) = arr.shape[:-2], arr.shape[-2:]
    if t.size != T:
        raise ShapeError(f"times: expected one time per reading ({T}), got {t.size}")
    union = np.union1d(t, g)
    t0 = union[0] if s is None else float(s[0])
    if t0 > union[0]:
        raise ValidationError("start: the prior's time must be at or before the first sample and grid time")
    i_s, i_g = np.searchsorted(union, t), np.searchsorted(union, g)
    U = union.size
    y_u = np.full(lead + (U, m), np.nan)
    y_u[..., i_s, :] = arr
    c_u = None
    if censored is not None:
        c = np.asarray(censored)
        c_u = np.zeros(lead + (U, m), dtype=bool) if c.ndim < 2 else np.zeros(c.shape[:-2] + (U, m), dtype=bool)
        try:
            c_u[..., i_s, :] = c.reshape(c.shape[:-1] + (m,)) if c.ndim >= 2 else c.reshape(T, m)
        except ValueError:
            raise ShapeError(f"censored: expected the shape of y {arr.shape}, got {c.shape}") from None
    u_u = None
    if u is not None:
        ua = as_float_array(u, "u")
        if ua.ndim < 2 or ua.shape[-2] != g.size:
            raise ShapeError(f"u: expected the inputs on the grid (..., {g.size}, p), got {ua.shape}")
        off = ~np.isin(t, g)
        if off.any():
            raise ValidationError(
                f"u: inputs on the grid need every sample time on the grid; sample {int(np.argmax(off))} "
                f"(time {t[off][0]!r} in the model's unit) is not"
            )
        u_u = ua[..., np.searchsorted(g, union), :]
    est_u = copy.copy(est)
    for key in _CACHES:
        est_u.__dict__.pop(key, None)
    est_u._setup_system(sys_._system_on(union, t0))
    cens = getattr(est, "censoring", None)
    if isinstance(cens, Censoring) and cens.time_varying:  # limits per reading: onto the union
        lo, hi = cens.all_limits(T, m)
        lo_u, hi_u = np.full((U, m), -np.inf), np.full((U, m), np.inf)
        lo_u[i_s], hi_u[i_s] = lo, hi
        est_u.censoring = Censoring(lower=lo_u, upper=hi_u)
    kw: dict[str, Any] = {} if c_u is None else {"censored": c_u}
    res = est_u.smooth(y_u, u=u_u, x0=x0, P0=P0, **kw)
    assert res.mean is not None and res.cov is not None, "the smoother returns means and covariances"
    return FilterResult(
        mean=res.mean[..., i_g, :],
        cov=res.cov[..., i_g, :, :],
        pred_mean=None,
        pred_cov=None,
        extras={"union_times": union, "grid_index": i_g, "sample_index": i_s, "smoothed": res},
        times=np.asarray(grid),
    )
