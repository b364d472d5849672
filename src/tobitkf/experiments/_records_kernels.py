r"""Compiled (numba) log-likelihood of :func:`~tobitkf.experiments.records_common.adf_pass`: many runs of a
scalar censored reading, each run its own diagonal transition, noise and sample noise.

Not a second algorithm: the same exact discretisation of each gap
(:func:`~tobitkf.experiments.records_common.gap_matrices`: :math:`a_j = e^{-\lambda_j\Delta}`,
:math:`q^d_j = q_j\Delta\,\psi(2\lambda_j\Delta)`), the same Gaussian prediction with the diagonal
:math:`A` and :math:`Q`,

.. math::

    \bar x = a \odot x, \qquad \bar P = (a a^T) \odot P + \mathrm{diag}(q^d),

and the package's compiled censored update of one channel (the classes of
:func:`~tobitkf.filters._compiled_moments.classify`, the scalars of
:func:`~tobitkf.filters._compiled_moments._censored_one`, which
:func:`~tobitkf.filters.assumed_density.censored_channel_update` takes with ``compiled=True``), applied
as its rank-one change :math:`x = \bar x + \alpha \bar Pc^T`, :math:`P = \bar P - \beta\,\bar Pc^T c\bar P`.
The numpy pass is the reference (equal to rounding, tested); this one only removes the per-step Python
cost, which dominates the fits (a few hundred steps of a few dozen runs per likelihood evaluation).
Compiled on first use, cached on disk.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..filters._compiled_moments import MISSING, _censored_one, classify

__all__ = ["diag_adf_terms"]


@njit(cache=True, error_model="numpy")
def diag_adf_terms(x0, P0, rate, diffusion, gaps, C, y, lo, hi, r2, dy, terms):  # pragma: no cover - compiled
    """``x0`` (N, n), ``P0`` (N, n, n), ``rate`` and ``diffusion`` (N, n) the continuous-time model of each
    run, ``gaps`` (N, T), ``C`` (T, n), ``y``, ``lo``, ``hi``, ``r2``, ``dy`` (N, T); writes the
    log-likelihood term of every reading into ``terms`` (N, T) (0 for a missing one)."""
    N, n = rate.shape
    T = y.shape[1]
    x = np.empty(n)
    P = np.empty((n, n))
    Pc = np.empty(n)
    a = np.empty(n)
    for i in range(N):
        for j in range(n):
            x[j] = x0[i, j]
            for l in range(n):
                P[j, l] = P0[i, j, l]
        for k in range(T):
            dt = gaps[i, k]
            for j in range(n):
                a[j] = math.exp(-rate[i, j] * dt)
            for j in range(n):
                x[j] *= a[j]
                for l in range(n):
                    P[j, l] *= a[j] * a[l]
                z = 2.0 * rate[i, j] * dt
                P[j, j] += diffusion[i, j] * dt * (-math.expm1(-z) / z if z > 0.0 else 1.0)
            yk = y[i, k]
            c = classify(yk, lo[i, k], hi[i, k])
            if c == MISSING:
                terms[i, k] = 0.0
                continue
            mu = dy[i, k]
            cPc = 0.0
            for j in range(n):
                mu += C[k, j] * x[j]
                s = 0.0
                for l in range(n):
                    s += P[j, l] * C[k, l]
                Pc[j] = s
                cPc += C[k, j] * s
            alpha, beta, ll, _pu = _censored_one(yk, c, mu, cPc + r2[i, k], lo[i, k], hi[i, k])
            terms[i, k] = ll
            for j in range(n):
                x[j] += alpha * Pc[j]
            for j in range(n):
                for l in range(j, n):
                    v = P[j, l] - beta * Pc[j] * Pc[l]
                    P[j, l] = v
                    P[l, j] = v
