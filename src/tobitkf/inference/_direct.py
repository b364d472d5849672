r"""The plumbing every direct fit of a user map :math:`\theta \mapsto` system shares (the state-space, panel and
nonlinear fits): the starting values and their names, the map checked to return the right kind of system, and the
maximisation with its :class:`~tobitkf.inference.FitResult` assembled.

Each fit keeps its own log-likelihood of :math:`\theta`; these helpers only hold what they would otherwise write
alike.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ._optimize import maximize_map
from ._results import FitResult

__all__ = ["start_values", "checked_map", "system_or_none", "fit_map"]


def start_values(theta0: Any, names: Any) -> tuple[np.ndarray, list[Any]]:
    """``theta0`` as a float vector (k,) and its ``names`` (``theta0``, ``theta1``, ... when None).

    Raises
    ------
    ShapeError
        ``theta0`` not a vector of numbers, or ``names`` not k long.
    """
    th0 = as_float_array(theta0, "theta0", ndim=1)
    names = [f"theta{i}" for i in range(th0.size)] if names is None else list(names)
    if len(names) != th0.size:
        raise ShapeError(f"names: expected {th0.size} names, got {len(names)}")
    return th0, names


def checked_map(model: Callable[[np.ndarray], Any], kind: type) -> Callable[[np.ndarray], Any]:
    """``theta -> model(theta)``, refusing a value that is not a ``kind`` (a ``ValidationError`` whose text holds
    "the map returned", which :func:`system_or_none` lets through)."""

    def sys_of(th: np.ndarray) -> Any:
        s = model(np.asarray(th, dtype=float))
        if not isinstance(s, kind):
            raise ValidationError(f"model: the map returned {type(s).__name__}, expected a {kind.__name__}")
        return s

    return sys_of


def system_or_none(sys_of: Callable[[np.ndarray], Any], th: np.ndarray) -> Any:
    """The system ``sys_of(th)``, or None where the system refuses the parameters (a negative variance ...: the
    search scores them -inf); a map returning the wrong kind of object is the user's error and is raised.

    Raises
    ------
    ValidationError
        The map returned no system of the expected kind (:func:`checked_map`).
    """
    try:
        return sys_of(th)
    except ValidationError as exc:
        if "the map returned" in str(exc):
            raise
        return None


def fit_map(
    ll_of: Callable[[np.ndarray], float],
    th0: np.ndarray,
    names: list[Any],
    *,
    gtol: float,
    maxiter: int,
    progress: Any,
    standard_errors: bool,
    started: float,
    model_of: Callable[[np.ndarray], Any],
    check_always: bool = False,
    **fields: Any,
) -> FitResult:
    """:func:`~tobitkf.inference._optimize.maximize_map` of ``ll_of`` from ``th0``, as a direct fit's
    :class:`FitResult`: a value of ``ll_of`` that is not finite scores -inf, ``model`` is ``model_of(theta)``, ``fit_seconds`` counts from ``started``
    (:func:`time.perf_counter`), and ``fields`` give the rest (``n_obs``, ``likelihood``, ``data``, ``extra``).

    Raises
    ------
    ValidationError
        The log-likelihood is not finite at ``th0``.
    """

    def scored(th: np.ndarray) -> float:  # a value that is not finite (nan, +inf) scores -inf
        v = ll_of(th)
        return v if np.isfinite(v) else -np.inf

    out, th, ll, cov = maximize_map(
        scored,
        th0,
        names,
        gtol=gtol,
        maxiter=maxiter,
        progress=progress,
        standard_errors=standard_errors,
        check_always=check_always,
    )
    model = model_of(th)
    return FitResult(
        model=model,
        names=names,
        theta=th,
        cov=cov,
        loglik=ll,
        n_params=th.size,
        method="direct",
        converged=out.converged,
        message=out.message,
        trace=out.trace,
        fit_seconds=time.perf_counter() - started,
        evaluations=out.evaluations,
        **fields,
    )
