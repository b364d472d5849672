r"""Compiled (numba) log-likelihood of a time-invariant linear state-space model with censored readings,
for the direct fits of :mod:`tobitkf.inference.state_space`.

An implementation of the package's assumed-density filter's log-likelihood
(:func:`tobitkf.inference.likelihood.adf_log_likelihood`: :class:`~tobitkf.AssumedDensityTobitFilter`,
``order="uncensored_first"``, standard covariance form) for one record and constant matrices, not a
second algorithm: the same predict, the same scalar update of each channel in the same order (the
readings inside the limits of a step first, in channel order, then the censored ones), the same
censored-normal statistics (:func:`tobitkf.filters._compiled_censored.beyond`, the filters' compiled
route), the same log-likelihood terms:

.. math::

    \bar x = A x + B^u u_k, \quad \bar P = A P A^T + Q, \qquad
    \mu = c_l^T x + d_l^T u_k, \quad s^2 = c_l^TPc_l + r_l, \quad K = Pc_l/s^2,

    \text{inside: } \ell \mathrel{+}= \log N(y; \mu, s^2),\ x \mathrel{+}= K(y - \mu),\ P \mathrel{-}= KK^Ts^2;
    \quad \text{censored: } \ell \mathrel{+}= \log P(\text{event}),\ x \mathrel{+}= K(m_{tr} - \mu),\
    P \mathrel{-}= KK^T(s^2 - V_{tr}),

with :math:`m_{tr}`, :math:`V_{tr}` the moments of :math:`N(\mu, s^2)` truncated to the censoring event
and :math:`\log P` taken through the inverse Mills ratio in the far tail (finite 40 sd away). A
latent of variance not above the smallest normal number gives no update and the indicator of the
reading (0 when the point agrees with it, else ``-inf``). Equal to the filter's log-likelihood to
rounding (tested). Without censoring (every reading inside) it is the Kalman log-likelihood for a
diagonal R (the scalar updates in sequence are the joint update). Compiled on first use, cached on disk.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..filters._compiled_censored import beyond

_LOG_2PI = math.log(2.0 * math.pi)
_TINY = np.finfo(float).tiny


@njit(cache=True, error_model="numpy", nogil=True)
def predict_into(A, Q, x, P, xp, AP, Pp):  # pragma: no cover - compiled
    r"""The time update :math:`\bar x = Ax`, :math:`\bar P = APA^T + Q` of one run in scalar loops, written into
    ``xp`` (n,) and ``Pp`` (n, n) (symmetric by construction; ``AP`` (n, n) is scratch). ``Pp`` may be ``P``
    itself: AP is formed in full before it is written."""
    n = A.shape[0]
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += A[i, j] * x[j]
        xp[i] = s
        for j in range(n):
            s = 0.0
            for q in range(n):
                s += A[i, q] * P[q, j]
            AP[i, j] = s
    for i in range(n):
        for j in range(i, n):
            s = Q[i, j]
            for q in range(n):
                s += AP[i, q] * A[j, q]
            Pp[i, j] = s
            Pp[j, i] = s


@njit(cache=True, error_model="numpy")
def log_likelihood(A, Q, C, r, Bu, D, x0, P0, y, side, lim, u):  # pragma: no cover - compiled
    """``A`` (n, n), ``Q`` (n, n), ``C`` (m, n), ``r`` (m,) the diagonal of R, ``Bu`` (n, p), ``D`` (m, p),
    ``x0`` (n,), ``P0`` (n, n); ``y`` (T, m) readings (NaN missing), ``side`` (T, m) int8 (-1 censored at
    the lower limit, 1 at the upper, 0 inside), ``lim`` (T, m) the limit of a censored reading, ``u``
    (T, p) inputs (p = 0: none). Returns the log-likelihood."""
    T, m = y.shape
    n = A.shape[0]
    p = u.shape[1]
    x = x0.copy()
    P = P0.copy()
    xn = np.empty(n)
    AP = np.empty((n, n))
    Pc = np.empty(n)
    total = 0.0
    for k in range(T):
        predict_into(A, Q, x, P, xn, AP, P)
        for i in range(n):
            s = xn[i]
            for j in range(p):
                s += Bu[i, j] * u[k, j]
            x[i] = s
        for stage in range(2):  # the readings inside the limits first, then the censored ones
            for l in range(m):
                yl = y[k, l]
                if yl != yl:
                    continue
                sd_ = side[k, l]
                if (stage == 0) != (sd_ == 0):
                    continue
                mu = 0.0
                for j in range(n):
                    mu += C[l, j] * x[j]
                for j in range(p):
                    mu += D[l, j] * u[k, j]
                s2 = r[l]
                for i in range(n):
                    s = 0.0
                    for j in range(n):
                        s += P[i, j] * C[l, j]
                    Pc[i] = s
                    s2 += C[l, i] * s
                if not s2 > _TINY:
                    if sd_ == 0:
                        agrees = yl == mu
                    elif sd_ < 0:
                        agrees = mu <= lim[k, l]
                    else:
                        agrees = mu >= lim[k, l]
                    if not agrees:
                        return -np.inf
                    continue
                sd = math.sqrt(s2)
                if sd_ == 0:
                    e = yl - mu
                    total += -0.5 * (_LOG_2PI + math.log(s2) + e * e / s2)
                    obs = yl
                    V = 0.0
                else:  # beyond the limit: y* <= l (sd_ < 0) or y* >= h
                    _p, logp, obs, V = beyond(mu, sd, lim[k, l], float(sd_))
                    total += logp
                f = (obs - mu) / s2
                h = (s2 - V) / (s2 * s2)
                for i in range(n):
                    x[i] += Pc[i] * f
                for i in range(n):
                    for j in range(i, n):
                        v = P[i, j] - Pc[i] * Pc[j] * h
                        P[i, j] = v
                        P[j, i] = v
    return total
