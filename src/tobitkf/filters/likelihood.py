r"""Prediction-error log-likelihood terms of a Gaussian filter's run (Schweppe 1965; Harvey 1989 §3.4).

With the filter's predictions :math:`\bar x_{k|k-1}`, :math:`\bar P_{k|k-1}`,

.. math::

    \log p(y_k \mid y_{1:k-1}) = \log N(y_{k,o};\ C_{k,o}\bar x_{k|k-1} + D_{k,o}u_k,\ C_{k,o}\bar P_{k|k-1}C_{k,o}^T + R_{k,oo})

over the readings o present at step k (NaN readings are skipped: integrated out), with all constants.
The primitives the filters' ``log_likelihood`` needs; the model-level likelihoods
(:func:`tobitkf.inference.kalman_log_likelihood`, :func:`tobitkf.inference.adf_log_likelihood`) build on them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError
from ..models.linear import LinearSystem
from .core import FilterResult, prepare_inputs, prepare_measurements
from .smoothing import _flat

__all__ = ["prediction_log_densities", "gaussian_log_density", "filter_log_likelihood", "LOG_2PI"]

LOG_2PI = float(np.log(2.0 * np.pi))


def prediction_log_densities(system: LinearSystem, y: Any, result: FilterResult, *, u: Any = None) -> np.ndarray:
    r"""Per-step :math:`\log N(y_{k,o}; C\bar x_{k|k-1} + Du_k, C\bar P_{k|k-1}C^T + R)` from a filter's predictions.

    Parameters
    ----------
    system : LinearSystem
    y : (..., T, m) array_like
        The readings the filter ran on (NaN = missing, skipped).
    result : FilterResult
        With ``pred_mean`` (..., T, n) and ``pred_cov``.
    u : (..., T, p) array_like, optional

    Returns
    -------
    (..., T) ndarray
    """
    y2, batch = prepare_measurements(y, system.m)
    N, T, m = y2.shape
    if result.pred_mean is None or result.pred_cov is None:
        raise ValidationError("result: needs pred_mean and pred_cov (run the filter with outputs='all')")
    xp = _flat(result.pred_mean, N, 1)
    Pp = _flat(result.pred_cov, N, 2)
    u2 = prepare_inputs(system, u, N, T)
    out = np.empty((N, T))
    fixed = not (system.C.varying or system.R.varying) and (u2 is None or system.D is None or not system.D.varying)
    fixed = fixed and system.C.batch_shape == () and system.R.batch_shape == ()  # per-run C or R: step by step
    if fixed:  # every step at once: one batched density over (N, T)
        C, R = system.measurement(1), system.measurement_cov(1)
        yhat = xp @ C.T
        if u2 is not None and system.D is not None:
            yhat = yhat + u2 @ system.D.at(1).T
        S = np.einsum("ij,...jk,lk->...il", C, Pp, C) + R
        S = np.broadcast_to(S, (N, T, m, m)).reshape(N * T, m, m)
        e = (y2 - yhat).reshape(N * T, m)
        out = gaussian_log_density(e, S, ~np.isnan(y2).reshape(N * T, m)).reshape(N, T)
        return out.reshape(batch + (T,))
    for i in range(T):
        k = int(result.times[i]) if result.times is not None else i + 1
        C, R = system.measurement(k), system.measurement_cov(k)
        yhat = np.einsum("...ij,...j->...i", C, xp[:, i])  # C (m, n), or (N or 1, m, n) one per run
        if u2 is not None and system.D is not None:
            yhat = yhat + u2[:, i] @ system.D.at(k).T
        S = C @ Pp[:, i] @ np.swapaxes(C, -1, -2) + R
        out[:, i] = gaussian_log_density(y2[:, i] - yhat, S, ~np.isnan(y2[:, i]))
    return out.reshape(batch + (T,))


def filter_log_likelihood(est: Any, y: Any, *, per_step: bool = True, **keywords: Any) -> np.ndarray:
    """The ``log_likelihood`` extras (..., T) of ``est.filter(y, **keywords)``, the per-step terms of a filter that
    records them (the assumed-density and Gaussian-sum filters), or with ``per_step=False`` their sum (...)."""
    terms = est.filter(y, outputs=("extras",), **keywords).extras["log_likelihood"]
    return terms if per_step else terms.sum(-1)


def gaussian_log_density(e: np.ndarray, S: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    r""":math:`\log N(e_o; 0, S_{oo})` of the valid channels o, batched.

    .. math::

        \ell = -\tfrac12\big(|o|\log 2\pi + \log\det S_{oo} + e_o^TS_{oo}^{-1}e_o\big)

    Parameters
    ----------
    e : (N, m) ndarray
        Innovations (entries of invalid channels are ignored).
    S : (N or 1, m, m) ndarray
        Innovation covariances.
    valid : (N, m) bool ndarray, optional
        Channels that take part; default every channel. A run without a valid channel gives 0.

    Returns
    -------
    (N,) ndarray
        ``-inf`` where :math:`S_{oo}` is singular and the innovation leaves its range.
    """
    m = e.shape[-1]
    if valid is None:
        valid = np.ones(e.shape, dtype=bool)
    e = np.where(valid, e, 0.0)
    if m == 1:
        s = S[..., 0, 0]
        v = valid[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            ll = -0.5 * (LOG_2PI + np.log(s) + e[..., 0] ** 2 / s)
        ll = np.where(s > 0, ll, np.where(e[..., 0] == 0, 0.0, -np.inf))
        return np.where(v, ll, 0.0)
    pair = valid[..., :, None] & valid[..., None, :]
    Sm = np.where(pair, S, np.eye(m))
    sign, logdet = np.linalg.slogdet(Sm)
    quad = np.einsum("...i,...i->...", e, _solve_or_inf(Sm, e))
    ll = -0.5 * (valid.sum(-1) * LOG_2PI + logdet + quad)
    return np.where(sign > 0, ll, -np.inf)


def _solve_or_inf(S: np.ndarray, e: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(S, e[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.einsum("...ij,...j->...i", np.linalg.pinv(S, hermitian=True), e)
