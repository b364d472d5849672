r"""The block steps of the square-root (Cholesky) form of the nonlinear filters (``covariance_update="square_root"``).

The numpy square-root form of :mod:`tobitkf.filters.nonlinear` (whose module docstring states it) run by numba: a
factor :math:`S`, :math:`P = SS^T`, is carried instead of P. Per step and run:

* the **prediction** (:func:`predict`): by the rule, the points :math:`\chi_i = \hat x + S\xi_i`,
  :math:`\bar x = \sum_iw^m_if(\chi_i)` and the lower factor :math:`\bar S` of one QR of
  :math:`[\sqrt{w^c_i}(f(\chi_i) - \bar x)^T;\ Q^{1/2\,T}]` over the non-negative weights, then a rank-one
  Cholesky downdate per negative weight; extended, one QR of :math:`[(FS)^T;\ Q^{1/2\,T}]`;
* the **update** (:func:`joint`): the array form (:func:`~tobitkf.filters.core.sqrt_update`) with the statistical
  linearisation :math:`\mathcal H = Z^T\bar S^{-1}`, :math:`Z = \sum_iw^c_i\xi_i(h(\chi_i) - \hat y)^T`, and the
  noise factored from the residual rows :math:`\sqrt{w^c_i}(h(\chi_i) - \hat y - Z^T\xi_i)` and :math:`R^{1/2}`
  (Kalman), or with :math:`\mathcal H \to G\mathcal H` and the residuals scaled by :math:`G` with
  :math:`\mathrm{diag}(N)^{1/2}` (Tobit); the extended form takes the Jacobian and no residual. The
  assumed-density filter projects channel by channel (iterated, :func:`adf_channel`), the array form with noise
  :math:`\Omega + R_{ll}` followed by one QR for :math:`+KVK^T`.

Every step is a QR or a triangular solve: the covariance stays PSD by construction. The time loop, the points,
the differences and the copies are the covariance form's (:mod:`tobitkf.filters._compiled_nonlinear_loop`,
:mod:`tobitkf.filters._compiled_nonlinear`). Equal to the numpy square-root form to rounding (tested).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._compiled_linalg import psd_root
from ._compiled_moments import CENSORED, classify, family_block
from ._compiled_nonlinear import KALMAN, rule_mean, tobit_terms
from ._compiled_tobit import GL_W, GL_X

__all__ = ["predict", "joint", "adf_channel", "record"]

_TINY = float(np.finfo(np.float64).tiny)


# --------------------------------------------------------------------------- factors


@njit(error_model="numpy", cache=True)
def _lower_factor(rows, W):
    r"""The lower factor ``W`` (r, r), positive diagonal, of :math:`\text{rows}^T\text{rows}` (rows (k, r)) by
    one QR (zero rows padded when k < r)."""
    k, r = rows.shape
    if k < r:
        M = np.zeros((r, r))
        M[:k] = rows
    else:
        M = rows
    U = np.linalg.qr(M)[1]
    for i in range(r):
        s = -1.0 if U[i, i] < 0.0 else 1.0
        for j in range(r):
            W[j, i] = s * U[i, j] if j >= i else 0.0


@njit(error_model="numpy", cache=True)
def _downdate(W, v):
    r"""``W`` <- the lower factor of :math:`WW^T - vv^T` (``v`` is overwritten); NaN where it is indefinite."""
    r = W.shape[0]
    for j in range(r):
        d = W[j, j]
        rad = d * d - v[j] * v[j]
        if not rad >= 0.0:
            W[:] = np.nan
            return
        new = math.sqrt(rad)
        if d > 0.0:
            c, s = new / d, v[j] / d
        else:
            c, s = 1.0, 0.0
        W[j, j] = new
        cs = c if c > 0.0 else 1.0
        for i in range(j + 1, r):
            col = (W[i, j] - s * v[i]) / cs
            v[i] = c * v[i] - s * col
            W[i, j] = col


@njit(error_model="numpy", cache=True)
def _weighted_factor(D, wc, root, W):
    r"""``W`` (r, r) <- the lower factor of :math:`\sum_iw_id_id_i^T + \text{root}\,\text{root}^T` from the rows
    ``D`` (L, r) and ``root`` (r, c): one QR over the non-negative weights, a downdate per negative one."""
    L, r = D.shape
    c = root.shape[1]
    npos = 0
    for i in range(L):
        if wc[i] >= 0.0:
            npos += 1
    rows = np.empty((npos + c, r))
    q = 0
    for i in range(L):
        if wc[i] >= 0.0:
            sw = math.sqrt(wc[i])
            for a in range(r):
                rows[q, a] = sw * D[i, a]
            q += 1
    for j in range(c):
        for a in range(r):
            rows[npos + j, a] = root[a, j]
    _lower_factor(rows, W)
    v = np.empty(r)
    for i in range(L):
        if wc[i] < 0.0:
            sw = math.sqrt(-wc[i])
            for a in range(r):
                v[a] = sw * D[i, a]
            _downdate(W, v)


@njit(error_model="numpy", cache=True)
def _array_update(x, S, e, H, root, ok, xo, So, K):
    r"""The array form of the masked Kalman update (:func:`~tobitkf.filters.core.sqrt_update`) of one run: one QR
    of :math:`[R^{1/2\,T}, 0;\ \bar S^TH^T, \bar S^T]`; a channel not ``ok`` (or with a degenerate innovation
    variance) takes no part (a zero row of H, a unit noise decoupled from the others, a zero innovation). Writes
    ``xo``, the factor ``So`` and the gain ``K`` (n, m)."""
    n = x.shape[0]
    m = e.shape[0]
    HS = H @ S
    use = np.empty(m, dtype=np.bool_)
    every = True
    for a in range(m):
        d = 0.0
        for j in range(n):
            d += HS[a, j] * HS[a, j]
        for c in range(m):
            d += root[a, c] * root[a, c]
        use[a] = ok[a] and d > _TINY
        if not use[a]:
            every = False
    Rr = root
    if not every:  # the noise of the channels taking part, the others decoupled with unit noise
        N = root @ root.T
        for a in range(m):
            for c in range(m):
                if not (use[a] and use[c]):
                    N[a, c] = 1.0 if a == c else 0.0
        Rr = np.empty((m, m))
        psd_root(N, Rr)
    M = np.zeros((m + n, m + n))
    for a in range(m):
        for c in range(m):
            M[c, a] = Rr[a, c]
        for j in range(n):
            M[m + j, a] = HS[a, j] if use[a] else 0.0
    for i in range(n):
        for j in range(n):
            M[m + j, m + i] = S[i, j]
    U = np.linalg.qr(M)[1]
    # K^T = U11^{-1} U12 by back substitution (U11 upper triangular)
    for i in range(n):
        for a in range(m - 1, -1, -1):
            s = U[a, m + i]
            for c in range(a + 1, m):
                s -= U[a, c] * K[i, c]
            K[i, a] = s / U[a, a]
    for i in range(n):
        s = x[i]
        for a in range(m):
            if use[a]:
                s += K[i, a] * e[a]
        xo[i] = s
        for j in range(n):
            So[i, j] = U[m + j, m + i]


@njit(error_model="numpy", cache=True)
def _add_retained(S, K, V):
    r"""``S`` <- the factor of :math:`SS^T + KVK^T` (one channel: K (n,), V >= 0) by one QR."""
    n = S.shape[0]
    rows = np.empty((n + 1, n))
    for i in range(n):
        for j in range(n):
            rows[i, j] = S[j, i]
    sv = math.sqrt(max(V, 0.0))
    for j in range(n):
        rows[n, j] = sv * K[j]
    _lower_factor(rows, S)


# --------------------------------------------------------------------------- block steps


@njit(error_model="numpy", cache=True)
def predict(sigma, Y, J, Ss, wm, wc, Qroot, xps, Sps, nb):
    """The predicted mean and factor of the block's runs: by the rule from ``Y`` = f(points), or extended from
    ``Y`` = f(means) and the Jacobians ``J``."""
    n = xps.shape[1]
    L = wm.shape[0]
    q = Qroot.shape[1]
    for b in range(nb):
        if sigma:
            for a in range(n):
                s = 0.0
                for p in range(L):
                    s += wm[p] * Y[b * L + p, a]
                xps[b, a] = s
            D = np.empty((L, n))
            for p in range(L):
                for a in range(n):
                    D[p, a] = Y[b * L + p, a] - xps[b, a]
            _weighted_factor(D, wc, Qroot, Sps[b])
        else:
            xps[b] = Y[b]
            FS = J[b] @ Ss[b]
            rows = np.empty((n + q, n))
            for i in range(n):
                for a in range(n):
                    rows[i, a] = FS[a, i]
            for j in range(q):
                for a in range(n):
                    rows[n + j, a] = Qroot[a, j]
            _lower_factor(rows, Sps[b])


@njit(error_model="numpy", cache=True)
def _linearise(Yb, xi, wm, wc, Sp, ym, Hl, E):
    r"""The statistical linearisation of the values ``Yb`` (L, r) at the points of :math:`N(\bar x, \bar S\bar S^T)`:
    ``ym``, :math:`\mathcal H` (r, n) = :math:`Z^T\bar S^{-1}` (a least-squares solve when S is singular) and
    the residual rows ``E`` (L, r)."""
    L, r = Yb.shape
    n = xi.shape[1]
    rule_mean(Yb, wm, ym)
    Z = np.zeros((n, r))
    for p in range(L):
        for a in range(r):
            d = wc[p] * (Yb[p, a] - ym[a])
            for j in range(n):
                Z[j, a] += xi[p, j] * d
    for p in range(L):
        for a in range(r):
            s = Yb[p, a] - ym[a]
            for j in range(n):
                s -= xi[p, j] * Z[j, a]
            E[p, a] = s
    singular = False
    for j in range(n):
        if not abs(Sp[j, j]) > 0.0:
            singular = True
    if singular:
        Hl[:] = (np.linalg.pinv(Sp).T @ Z).T
    else:
        Hl[:] = np.linalg.solve(Sp.T, Z).T


@njit(error_model="numpy", cache=True)
def joint(code, sigma, Y, J, xi, wm, wc, xps, Sps, y, r0, t, R, Rroot, lo, hi, noise_code, xs, Ss, ey, slope, nb):
    """The update of all channels at once (Kalman or Tobit) of the block's runs from the values ``Y`` of h: at the
    points (``sigma``) or at the means with the Jacobians ``J``; the Tobit extras into ``ey``, ``slope``."""
    n = xps.shape[1]
    m = y.shape[2]
    L = wm.shape[0]
    ym, E, g, V, e = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    ok = np.empty(m, dtype=np.bool_)
    Hl = np.empty((m, n))
    K = np.empty((n, m))
    buf = np.empty((2, GL_X.shape[0]))
    for b in range(nb):
        Eres = np.empty((max(L, 1), m))
        if sigma:
            # the run's rows as a strided view (layout A), as adf_channel's column: _linearise compiled once
            _linearise(Y[b * L : (b + 1) * L, :], xi, wm, wc, Sps[b], ym, Hl, Eres)
        else:
            ym[:] = Y[b]
            Hl[:] = J[b]
        yt = y[r0 + b, t]
        if code == KALMAN:
            for a in range(m):
                E[a] = ym[a]
                g[a] = 1.0
            root = Rroot
        else:
            tobit_terms(ym, R, lo, hi, noise_code, g, E, V, buf)
            root = np.zeros((m, m))
            for a in range(m):
                root[a, a] = math.sqrt(max(V[a], 0.0))
            for a in range(m):
                for j in range(n):
                    Hl[a, j] *= g[a]
            if sigma:
                for p in range(L):
                    for a in range(m):
                        Eres[p, a] *= g[a]
        if sigma:
            W = np.empty((m, m))
            _weighted_factor(Eres[:L], wc, root, W)
            root = W
        for a in range(m):
            ok[a] = not math.isnan(yt[a])
            e[a] = yt[a] - E[a] if ok[a] else 0.0
        _array_update(xps[b], Sps[b], e, Hl, root, ok, xs[b], Ss[b], K)
        if ey.shape[1] > 0:
            ey[r0 + b, t] = E
            slope[r0 + b, t] = g


@njit(error_model="numpy", cache=True)
def adf_channel(it, ch, Y, xi, wm, wc, y, r0, t, xs, Ss, xms, Sms, act, rl, family, lo, hi, par, lsum, nb):
    r"""Linearisation ``it`` of channel ``ch`` (the numpy ``_channel_sqrt``) for the runs in ``act``, from the values
    ``Y`` of h at their stacked points of :math:`N(x_m, S_mS_m^T)`: the affine model (about the prior when
    ``it`` = 0), the channel's moments of the latent reading, then the array update of the prior ``xs``, ``Ss``
    with noise :math:`\Omega + R_{ll}` and one QR for :math:`+KVK^T`, into ``xms``, ``Sms``. ``family`` the
    channel's family as a kind (:func:`~tobitkf.filters._compiled_moments.kind`)."""
    L = wm.shape[0]
    n = xs.shape[1]
    ym = np.empty(1)
    Hl = np.empty((1, n))
    E = np.empty((L, 1))
    K = np.empty((n, 1))
    e = np.empty(1)
    okv = np.ones(1, dtype=np.bool_)
    root = np.empty((1, 1))
    cls = np.empty(1, dtype=np.int8)
    yv, hx, hph, rb, lo_c, hi_c = np.empty(1), np.empty(1), np.empty(1), np.empty(1), np.empty(1), np.empty(1)
    alpha, beta, llb, pu = np.empty(1), np.empty(1), np.empty(1), np.empty(1)
    comp = np.empty((0, 1))
    buf = np.empty((2, GL_X.shape[0]))
    q = 0
    for b in range(nb):
        if not act[b]:
            continue
        Yb = Y[q * L : (q + 1) * L, ch : ch + 1]
        q += 1
        _linearise(Yb, xi, wm, wc, Sms[b], ym, Hl, E)
        omega = 0.0
        for p in range(L):
            omega += wc[p] * E[p, 0] * E[p, 0]
        omega = max(omega, 0.0)
        mu = ym[0]
        if it > 0:
            for i in range(n):
                mu += Hl[0, i] * (xs[b, i] - xms[b, i])
        HS = Hl[0] @ Ss[b]
        s2 = np.dot(HS, HS) + omega + rl
        if not s2 > _TINY:
            xms[b] = xs[b]
            Sms[b] = Ss[b]
            act[b] = False
            continue
        yb = y[r0 + b, t, ch]
        yv[0], hx[0], hph[0], rb[0], lo_c[0], hi_c[0], llb[0] = yb, mu, s2 - rl, rl, lo, hi, 0.0
        cls[0] = classify(yb, lo, hi) if len(family) == CENSORED else 1
        family_block(family, 1, yv, cls, hx, hph, rb, lo_c, hi_c, par, alpha, beta, llb, pu, comp, GL_X, GL_W, buf)
        e[0] = alpha[0] * s2  # E[y* | y] - mu
        Vr = s2 - beta[0] * s2 * s2  # Var[y* | y]
        root[0, 0] = math.sqrt(omega + rl)
        _array_update(xs[b], Ss[b], e, Hl, root, okv, xms[b], Sms[b], K)
        _add_retained(Sms[b], K[:, 0], Vr)
        if it == 0:
            lsum[b] += llb[0]


@njit(error_model="numpy", cache=True)
def record(xs, Ss, r0, t, nb, means, covs):
    """The block's mean and covariance :math:`SS^T` at step t (``covs`` (N, T or 0, n, n or 1: the diagonals))."""
    n = xs.shape[1]
    for b in range(nb):
        if means.shape[1] > 0:
            means[r0 + b, t] = xs[b]
        if covs.shape[1] > 0:
            P = Ss[b] @ Ss[b].T
            if covs.shape[3] == 1:
                for i in range(n):
                    covs[r0 + b, t, i, 0] = P[i, i]
            else:
                for i in range(n):
                    for j in range(n):
                        covs[r0 + b, t, i, j] = 0.5 * (P[i, j] + P[j, i])
