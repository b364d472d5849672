"""A hand-fused scalar numba TKF: the speed limit that ``bench_limit.py`` measures ours against.

One measurement channel, a lower limit only, the dissertation's noise term, the standard
covariance update (Miller (3.20)–(3.22), (3.37)–(3.41), (3.55)); one run at a time, all the
algebra of a step in one compiled loop body (its time update the package's scalar-loop
:func:`tobitkf.inference._compiled_ss.predict_into`, a compiled call), the outputs written straight
into the (N, T, ...) arrays, and the closed-form censored statistics (``erfc``/``exp``, no tail
treatment: fine while the standardized limit stays below ~37, which the benchmark's data do). It is
a benchmark yardstick, not a filter of the package: no checks, no missing readings, no far tails.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tobitkf.inference._compiled_ss import predict_into

_SQRT1_2 = math.sqrt(0.5)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@njit(cache=True, error_model="numpy", nogil=True)
def fused_tkf(y, A, Q, C, sigma, lower, x0, P0, means, covs):
    """TKF over y (N, T) (one channel); means (N, T, n), covs (N, T, n, n) filled in place."""
    N, T = y.shape
    n = A.shape[0]
    x = np.empty(n)
    P = np.empty((n, n))
    xp = np.empty(n)
    Pp = np.empty((n, n))
    AP = np.empty((n, n))
    pc = np.empty(n)
    for r in range(N):
        for i in range(n):
            x[i] = x0[i]
            for j in range(n):
                P[i, j] = P0[i, j]
        for t in range(T):
            predict_into(A, Q, x, P, xp, AP, Pp)  # (3.20)-(3.21), the package's compiled time update
            # censored statistics at the prior, closed form (3.37), (3.8), (3.41)
            mu = 0.0
            for i in range(n):
                mu += C[i] * xp[i]
            a = (lower - mu) / sigma
            gam = 0.5 * math.erfc(a * _SQRT1_2)
            lam = math.exp(-0.5 * a * a) * _INV_SQRT_2PI / gam
            ruu = sigma * sigma * (1.0 + a * lam - lam * lam)
            ey = (1.0 - gam) * lower + gam * (mu + sigma * lam)
            # gain and update (3.39)-(3.40), (3.32), (3.22), (3.55)
            cpc = 0.0
            for i in range(n):
                s = 0.0
                for k in range(n):
                    s += Pp[i, k] * C[k]
                pc[i] = s
                cpc += C[i] * s
            ree = gam * gam * cpc + ruu
            e = y[r, t] - ey
            g = gam / ree
            for i in range(n):
                x[i] = xp[i] + g * pc[i] * e
                means[r, t, i] = x[i]
            for i in range(n):
                for j in range(i, n):
                    v = Pp[i, j] - g * gam * pc[i] * pc[j]
                    P[i, j] = v
                    P[j, i] = v
                    covs[r, t, i, j] = v
                    covs[r, t, j, i] = v
