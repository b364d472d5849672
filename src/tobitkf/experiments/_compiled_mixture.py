r"""The assumed-density filter of the river model's scale-mixture noise, compiled (numba): the compiled form of
:func:`tobitkf.experiments.records_common._mixture_filter`, which stays the numpy reference (tested against it to
1e-12).

Run i of N, step k of T: the exact diagonal prediction over the gap,

.. math::

    \bar x = a_{ik} \odot \hat x, \qquad \bar P = \mathrm{diag}(a_{ik})\,\hat P\,\mathrm{diag}(a_{ik})
    + \mathrm{diag}(q^d_{ik}),

then the update of :func:`~tobitkf.experiments.records_common.mixture_update`: for each noise component j
(variance :math:`r^2_{ik}` and :math:`c_i^2 r^2_{ik}`) the censored update of the package's compiled block
(:func:`~tobitkf.filters._compiled_moments.censored_block`, the two components as two runs of one block), a
rank-one change along :math:`\bar Pc_k^T`,

.. math::

    \hat x_j = \bar x + \alpha_j\,\bar Pc_k^T, \qquad P_j = \bar P - \beta_j\,\bar Pc_k^T c_k\bar P,

with its evidence :math:`\ell_j`; the log-likelihood term :math:`\ell = \log(e^{\log w_1 + \ell_1} +
e^{\log w_2 + \ell_2})` and the moment-matched merge with the posterior weights
:math:`\pi_j = e^{\log w_j + \ell_j - \ell}` (the prior weights where that is not finite), itself a rank-one
change (:mod:`tobitkf.filters._compiled_moments`):

.. math::

    \hat x = \bar x + \bar\alpha\,\bar Pc_k^T, \qquad P = \bar P - \bar\beta\,\bar Pc_k^T c_k\bar P, \qquad
    \bar\alpha = \sum_j \pi_j\alpha_j, \quad \bar\beta = \sum_j \pi_j\left(\beta_j - (\alpha_j -
    \bar\alpha)^2\right),

symmetric by construction. A missing reading leaves the prediction and adds 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..filters._compiled_moments import MISSING, censored_block, classify
from ..filters._compiled_tobit import GL_W, GL_X

__all__ = ["compiled_mixture_filter"]

_LOG2 = math.log(2.0)


@njit(cache=True, error_model="numpy", inline="always")
def _logaddexp(u, v):
    """``numpy.logaddexp`` of two floats, by its formula (the same rounding)."""
    if u == v:
        return u + _LOG2
    t = u - v
    if t > 0:
        return u + math.log1p(math.exp(-t))
    if t <= 0:
        return v + math.log1p(math.exp(t))
    return t  # NaN


@njit(cache=True, error_model="numpy", inline="always")
def _row(v, i):
    """The row of run i of an (N or 1, T) input."""
    return i if v.shape[0] > 1 else 0


@njit(cache=True, error_model="numpy")
def compiled_mixture_filter(
    x0, P0, rate, diffusion, gaps, C, y, cls, given, lo, hi, r2, dy, logw, c2, store, xp, Pp, xs, Ps, terms
):
    r"""The filter of the module docstring for every run; writes ``terms`` (N, T) and, with ``store``, the
    predicted and filtered moments ``xp``, ``xs`` (N, T, n), ``Pp``, ``Ps`` (N, T, n, n) (else those are not
    touched and may be any size).

    Parameters
    ----------
    x0 : (N, n) ; P0 : (N, n, n) ; rate, diffusion : (N, n) the continuous-time model of each run, taken over
        each gap as :func:`~tobitkf.experiments.records_common.gap_matrices` does
    C : (T, n) ; gaps, y, lo, hi, r2, dy : (N or 1, T) (one row: shared by the runs)
    cls : (N, T) int8 the reading classes when ``given`` (a recorded indicator's,
        :func:`~tobitkf.filters._readings.interval_classes`); else not read, the classes are the limit rule's
        (:func:`~tobitkf.filters._compiled_moments.classify`)
    logw : (N, 2) log prior weights of the two components (:math:`\log(1 - w)`, :math:`\log w`; -inf for w = 0)
    c2 : (N,) variance ratio of the second component
    """
    N, n = x0.shape
    T = y.shape[1]
    x = np.empty(n)
    P = np.empty((n, n))
    pc = np.empty(n)
    ak, qk = np.empty(n), np.empty(n)
    yy, hx, hph, rb = np.empty(2), np.empty(2), np.empty(2), np.empty(2)
    lob, hib = np.empty(2), np.empty(2)
    cc = np.empty(2, dtype=np.int8)
    alpha, beta, ll, pu = np.empty(2), np.empty(2), np.empty(2), np.empty(2)
    post = np.empty(2)
    par = np.zeros(0)
    comp = np.zeros((0, 2))
    buf = np.empty((2, GL_X.shape[0]))
    for i in range(N):
        for p in range(n):
            x[p] = x0[i, p]
            for q in range(n):
                P[p, q] = P0[i, p, q]
        ig, iy, il, ih = _row(gaps, i), _row(y, i), _row(lo, i), _row(hi, i)
        ir, idy = _row(r2, i), _row(dy, i)
        for k in range(T):
            dt = gaps[ig, k]
            for p in range(n):  # gap_matrices: a = e^(-lambda dt), qd = q dt psi(2 lambda dt)
                ak[p] = math.exp(-rate[i, p] * dt)
                z = 2.0 * rate[i, p] * dt
                qk[p] = diffusion[i, p] * dt * (-math.expm1(-z) / z if z > 0 else 1.0)
            for p in range(n):
                x[p] = ak[p] * x[p]
            for p in range(n):
                for q in range(n):
                    P[p, q] = P[p, q] * ak[p] * ak[q]
                P[p, p] += qk[p]
            if store:
                for p in range(n):
                    xp[i, k, p] = x[p]
                    for q in range(n):
                        Pp[i, k, p, q] = P[p, q]
            c = cls[i, k] if given else classify(y[iy, k], lo[il, k], hi[ih, k])
            if c == MISSING:
                terms[i, k] = 0.0
            else:
                mu = dy[idy, k]
                cpc = 0.0
                for p in range(n):
                    mu += x[p] * C[k, p]
                    s = 0.0
                    for q in range(n):
                        s += P[p, q] * C[k, q]
                    pc[p] = s
                    cpc += C[k, p] * s
                for j in range(2):
                    yy[j] = y[iy, k]
                    cc[j] = c
                    hx[j] = mu
                    hph[j] = cpc
                    lob[j] = lo[il, k]
                    hib[j] = hi[ih, k]
                    ll[j] = 0.0
                rb[0] = r2[ir, k]
                rb[1] = c2[i] * r2[ir, k]
                censored_block(2, yy, cc, hx, hph, rb, lob, hib, par, alpha, beta, ll, pu, comp, GL_X, GL_W, buf)
                j0 = logw[i, 0] + ll[0]
                j1 = logw[i, 1] + ll[1]
                tot = _logaddexp(j0, j1)
                terms[i, k] = tot
                post[0] = math.exp(j0 - tot)
                post[1] = math.exp(j1 - tot)
                if not math.isfinite(post[0]):
                    post[0] = math.exp(logw[i, 0])
                if not math.isfinite(post[1]):
                    post[1] = math.exp(logw[i, 1])
                # the merge of the two rank-one updates along Pc (module docstring): alpha and beta of the mixture
                am = post[0] * alpha[0] + post[1] * alpha[1]
                bm = post[0] * (beta[0] - (alpha[0] - am) ** 2) + post[1] * (beta[1] - (alpha[1] - am) ** 2)
                for p in range(n):
                    x[p] += am * pc[p]
                for p in range(n):
                    for q in range(p, n):
                        v = P[p, q] - bm * pc[p] * pc[q]
                        P[p, q] = v
                        P[q, p] = v
            if store:
                for p in range(n):
                    xs[i, k, p] = x[p]
                    for q in range(n):
                        Ps[i, k, p, q] = P[p, q]
