r"""Compiled (numba) dense linear algebra shared by the filters' kernels and the metrics.

:func:`gauss_solve` is Gaussian elimination with partial pivoting (what LAPACK's gesv behind
``numpy.linalg.solve`` does), written once and called by the TKF's gain solve
(:mod:`tobitkf.filters._compiled_tobit`) and by :func:`nees_terms` (:func:`tobitkf.metrics.nees_terms`).
:func:`cholesky_lower` (one implementation, :func:`cholesky_leading`) and :func:`psd_root` are the square roots of a covariance that the compiled nonlinear
filters (sigma points) and the compiled particle filters (the optimal proposal's draws) take.
Compiled on first use and cached on disk; importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["gauss_solve", "nees_terms", "cholesky_leading", "cholesky_lower", "psd_root"]

_INF = math.inf


# One version for every caller: its callers hand it whole arrays (C-contiguous) and views of a work array (any
# layout, 'A'); typed lazily, each caller's layout compiled a version of its own. Declared for any layout, it is
# compiled once (on import, or loaded from the disk cache) and a C-contiguous array converts to it.
@njit("b1(f8[:, :], f8[:, :])", cache=True, error_model="numpy")
def gauss_solve(M, W):
    """Solve ``M X = W`` in place (``W`` (m, r) becomes X; ``M`` (m, m) is overwritten) by Gaussian
    elimination with partial pivoting, like LAPACK gesv behind ``numpy.linalg.solve``. Returns
    False, leaving both half-eliminated, when a pivot is exactly zero (a singular ``M``). Both float64 and
    writable, of any layout (one compiled version serves every caller)."""
    m, r = W.shape
    for c in range(m):
        p = c
        best = abs(M[c, c])
        for q in range(c + 1, m):
            if abs(M[q, c]) > best:
                best = abs(M[q, c])
                p = q
        if p != c:
            for j in range(m):
                t = M[c, j]
                M[c, j] = M[p, j]
                M[p, j] = t
            for i in range(r):
                t = W[c, i]
                W[c, i] = W[p, i]
                W[p, i] = t
        if M[c, c] == 0.0:
            return False
        for q in range(c + 1, m):
            f = M[q, c] / M[c, c]
            for j in range(c, m):
                M[q, j] -= f * M[c, j]
            for i in range(r):
                W[q, i] -= f * W[c, i]
    for c in range(m - 1, -1, -1):
        for i in range(r):
            t = W[c, i]
            for j in range(c + 1, m):
                t -= M[c, j] * W[j, i]
            W[c, i] = t / M[c, c]
    return True


@njit(cache=True, error_model="numpy", inline="always")
def cholesky_leading(M, L, n):
    r"""The lower Cholesky factor of the leading (n, n) block of the symmetric ``M`` into the leading block of
    ``L`` (:math:`LL^T = M`, read from M's lower triangle, L's strict upper triangle zeroed); False (``L``
    unfinished) when that block is not numerically positive definite (a pivot not > 0).

    Inlined into its caller, so that a state size the caller knows at compile time (the nonlinear filters'
    block steps pass one) unrolls its loops; :func:`cholesky_lower` is the call for a whole matrix."""
    for i in range(n):
        for c in range(i + 1, n):
            L[i, c] = 0.0
    for j in range(n):
        d = M[j, j]
        for c in range(j):
            d -= L[j, c] * L[j, c]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            s = M[i, j]
            for c in range(j):
                s -= L[i, c] * L[j, c]
            L[i, j] = s / d
    return True


@njit(cache=True, error_model="numpy")
def cholesky_lower(M, L):
    """The lower Cholesky factor of the symmetric ``M`` (n, n) into ``L`` (:math:`LL^T = M`, read from M's lower
    triangle); False (``L`` unfinished) when M is not numerically positive definite (a pivot not > 0)."""
    return cholesky_leading(M, L, M.shape[0])


@njit(cache=True, error_model="numpy")
def psd_root(M, L):
    r"""A square root of the symmetric PSD ``M`` (n, n) into ``L`` (:math:`LL^T = M`): the lower Cholesky factor
    (:func:`cholesky_lower`), or the eigen root :math:`V\mathrm{diag}(\sqrt{\max(w, 0)})` of M's symmetric part
    when M is not numerically positive definite (as :func:`tobitkf._linalg.psd_sqrt`)."""
    if cholesky_lower(M, L):
        return
    n = M.shape[0]
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    for i in range(n):
        for c in range(n):
            L[i, c] = V[i, c] * math.sqrt(max(w[c], 0.0))


@njit(cache=True, error_model="numpy", nogil=True)
def nees_terms(err, cov, out):
    r""":math:`e_k^T P_k^{-1} e_k` for ``err`` (K, n) and ``cov`` (Kc, n, n), run ``k`` using
    ``cov[k % Kc]`` (a covariance shared by the runs broadcasts this way); written to ``out`` (K,).

    The compiled form of :func:`tobitkf.metrics.nees_terms`: one :func:`gauss_solve` per matrix
    (as ``numpy.linalg.solve``), so a matrix with an exactly zero pivot (singular) gives ``inf``
    for its own term only."""
    K, n = err.shape
    Kc = cov.shape[0]
    M = np.empty((n, n))
    v = np.empty((n, 1))
    for k in range(K):
        c0 = k % Kc
        for i in range(n):
            v[i, 0] = err[k, i]
            for j in range(n):
                M[i, j] = cov[c0, i, j]
        if not gauss_solve(M, v):
            out[k] = _INF
            continue
        s = 0.0
        for i in range(n):
            s += err[k, i] * v[i, 0]
        out[k] = s
