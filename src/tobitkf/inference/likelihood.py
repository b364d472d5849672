r"""Log-likelihood of a run: exact for the Kalman filter, assumed-density for censored readings.

Prediction-error decomposition (Schweppe 1965; Harvey 1989 §3.4): with the filter's predictions
:math:`\bar x_{k|k-1}`, :math:`\bar P_{k|k-1}`,

.. math::

    \log p(y_{1:T}) = \sum_{k=1}^T \log p(y_k \mid y_{1:k-1}), \qquad
    \log p(y_k \mid y_{1:k-1}) = \log N(y_{k,o};\ C_{k,o}\bar x_{k|k-1} + D_{k,o}u_k,\ C_{k,o}\bar P_{k|k-1}C_{k,o}^T + R_{k,oo})

over the readings o present at step k (NaN readings are skipped: integrated out), with all constants.
For the linear Gaussian model this is exact (equal to the stacked Gaussian density of all readings,
tested). With censored readings (:func:`adf_log_likelihood`) each censored reading contributes its
predictive mass at the limit, :math:`\log\Phi(\pm(\text{limit} - \mu)/s)`, under the assumed-density
filter's Gaussian prediction (:class:`~tobitkf.AssumedDensityTobitFilter`, its ``log_likelihood``
extras, the uncensored readings of a step first); exact for one step, approximate after
several censored steps. Where the approximation is not good enough (long censored runs), the exact
likelihood of a regression with AR errors is :func:`tobitkf.inference.censored_ar.exact_log_likelihood`.

Time convention: :math:`x_0 \sim N(\bar x_0, P_0)` the prior, :math:`y_1` at index 0.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..channels.censoring import Censoring
from ..filters._times import system_at_times
from ..filters.assumed_density import assumed_density_filter
from ..filters.kalman import KalmanFilter
from ..filters.likelihood import prediction_log_densities
from ..models.linear import LinearSystem

__all__ = ["kalman_log_likelihood", "adf_log_likelihood", "log_likelihood", "prediction_log_densities", "LIKELIHOODS"]

LIKELIHOODS = ("kalman", "adf")


def kalman_log_likelihood(
    system: LinearSystem,
    y: Any,
    *,
    u: Any = None,
    x0: Any = None,
    P0: Any = None,
    per_step: bool = False,
    times: Any = None,
) -> np.ndarray:
    r"""Exact log-likelihood :math:`\log p(y_{1:T})` of the linear Gaussian model (NaN readings skipped).

    Parameters
    ----------
    system : LinearSystem
    y : (..., T, m) array_like
    u : (..., T, p) array_like, optional
    x0, P0 : array_like, optional
        Override the system's prior.
    per_step : bool, default False
        Return the per-step terms (..., T) instead of their sum (...).
    times : (T,) array_like, optional
        Sample times, for a :class:`~tobitkf.ContinuousLinearSystem` (each gap discretised exactly).

    Returns
    -------
    ndarray
        (...) or (..., T).

    Raises
    ------
    ValidationError, ShapeError
        The Kalman filter's input errors.

    Examples
    --------
    One reading, prior N(0, 1), R = 1: :math:`y_1 \sim N(0, 2)`.

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> ll = tk.kalman_log_likelihood(sys, [[0.5]])
    >>> bool(np.isclose(ll, -0.5 * (np.log(2 * np.pi * 2) + 0.25 / 2)))
    True
    """
    check_instance(system, LinearSystem, "system")
    system = system if times is None else system_at_times(system, times, y)
    res = KalmanFilter(system).filter(y, u=u, x0=x0, P0=P0, outputs=("pred_mean", "pred_cov"))
    terms = prediction_log_densities(system, y, res, u=u)
    return terms if per_step else terms.sum(-1)


def adf_log_likelihood(
    system: LinearSystem,
    censoring: Censoring,
    y: Any,
    *,
    censored: Any = None,
    u: Any = None,
    x0: Any = None,
    P0: Any = None,
    per_step: bool = False,
    times: Any = None,
    lower: Any = None,
    upper: Any = None,
) -> np.ndarray:
    r"""Assumed-density log-likelihood of censored readings (see the module docstring).

    With a ``system`` of one model per run (``batch_ndim``), each run's likelihood is under its own
    model: a batch of parameter vectors evaluated in one pass.

    Parameters
    ----------
    system : LinearSystem
        R diagonal when m > 1; R = 0 allowed.
    censoring : Censoring
    y : (..., T, m) array_like
        Censored readings hold their limit; NaN = missing.
    censored : (..., T, m) bool array_like, optional
        The recorded indicator (default: the limit rule).
    u, x0, P0 : optional
        Inputs and a prior override.
    per_step : bool, default False
    times : (T,) array_like, optional
        Sample times, for a :class:`~tobitkf.ContinuousLinearSystem` (each gap discretised exactly).
    lower, upper : array_like broadcastable to (..., T, m), optional
        Limits of each run and step replacing the censoring's (e.g. each subject's limits in a panel).

    Returns
    -------
    ndarray
        (...) or (..., T).

    Raises
    ------
    ValidationError, ShapeError
        The assumed-density filter's input errors.

    Examples
    --------
    One reading censored at 0 under a N(0, 1) predictive: :math:`\log\tfrac12`.

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    >>> bool(np.isclose(tk.adf_log_likelihood(sys, tk.Censoring(lower=0.0), [[0.0]]), np.log(0.5)))
    True
    """
    check_instance(system, LinearSystem, "system")
    system = system if times is None else system_at_times(system, times, y)
    res = assumed_density_filter(system, censoring).filter(
        y, u=u, censored=censored, x0=x0, P0=P0, outputs=("extras",), lower=lower, upper=upper
    )
    terms = res.extras["log_likelihood"]
    return terms if per_step else terms.sum(-1)


def log_likelihood(
    system: LinearSystem,
    y: Any,
    *,
    censoring: Censoring | None = None,
    censored: Any = None,
    method: str = "auto",
    u: Any = None,
    x0: Any = None,
    P0: Any = None,
    per_step: bool = False,
    times: Any = None,
) -> np.ndarray:
    r"""Log-likelihood of readings ``y`` under ``system`` (and ``censoring``).

    Parameters
    ----------
    system : LinearSystem
    y : (..., T, m) array_like
    censoring : Censoring, optional
        Without it the model is linear Gaussian and the likelihood exact.
    censored : (..., T, m) bool array_like, optional
        The recorded censoring indicator.
    method : {"auto", "kalman", "adf"}, default "auto"
        ``"kalman"``: :func:`kalman_log_likelihood` (every reading as an exact reading, censored or
        not); ``"adf"``: :func:`adf_log_likelihood`; ``"auto"``: ``"kalman"`` without censoring, else
        ``"adf"``.
    u, x0, P0 : optional
    per_step : bool, default False
    times : (T,) array_like, optional
        Sample times, for a :class:`~tobitkf.ContinuousLinearSystem` (each gap discretised exactly).

    Returns
    -------
    ndarray

    Raises
    ------
    ValidationError
        Unknown method; ``"adf"`` without ``censoring``.
    """
    if method == "auto":
        method = "kalman" if censoring is None else "adf"
    if method not in LIKELIHOODS:
        raise ValidationError(f"method: expected one of auto, {', '.join(LIKELIHOODS)}, got {method!r}")
    if method == "kalman":
        return kalman_log_likelihood(system, y, u=u, x0=x0, P0=P0, per_step=per_step, times=times)
    if censoring is None:
        raise ValidationError("censoring: the assumed-density likelihood needs the censoring limits")
    return adf_log_likelihood(
        system, censoring, y, censored=censored, u=u, x0=x0, P0=P0, per_step=per_step, times=times
    )
