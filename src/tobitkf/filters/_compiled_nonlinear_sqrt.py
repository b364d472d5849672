r"""The square-root (Cholesky) form of the nonlinear filters' compiled loop (``covariance_update="square_root"``).

The numpy square-root form of :mod:`tobitkf.filters.nonlinear` (whose module docstring states it) run by numba: a
factor :math:`S`, :math:`P = SS^T`, is carried instead of P, for a :class:`~tobitkf.NonlinearSystem` whose ``f``
and ``h`` (and ``F``, ``H`` when given) are ``numba.njit`` functions. Per step and run:

* the **prediction**: by the rule, the points :math:`\chi_i = \hat x + S\xi_i`, :math:`\bar x = \sum_iw^m_if(\chi_i)`
  and the lower factor :math:`\bar S` of one QR of :math:`[\sqrt{w^c_i}(f(\chi_i) - \bar x)^T;\ Q^{1/2\,T}]` over
  the non-negative weights, then a rank-one Cholesky downdate per negative weight; extended, one QR of
  :math:`[(FS)^T;\ Q^{1/2\,T}]`;
* the **update**: the array form (:func:`~tobitkf.filters.core.sqrt_update`) with the statistical linearisation
  :math:`\mathcal H = Z^T\bar S^{-1}`, :math:`Z = \sum_iw^c_i\xi_i(h(\chi_i) - \hat y)^T`, and the noise factored
  from the residual rows :math:`\sqrt{w^c_i}(h(\chi_i) - \hat y - Z^T\xi_i)` and :math:`R^{1/2}` (Kalman), or
  with :math:`\mathcal H \to G\mathcal H` and the residuals scaled by :math:`G` with
  :math:`\mathrm{diag}(N)^{1/2}` (Tobit); the extended form takes the Jacobian and no residual. The
  assumed-density filter projects channel by channel (iterated), the array form with noise
  :math:`\Omega + R_{ll}` followed by one QR for :math:`+KVK^T`.

Every step is a QR or a triangular solve: the covariance stays PSD by construction. The runs go in blocks of
:data:`BLOCK` and each call of f, h (F, H) takes the stacked points of a block, as the standard form's loop
(:mod:`tobitkf.filters._compiled_nonlinear`) calls them. Equal to the numpy square-root form to rounding (tested).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_inputs import active_inputs
from ._compiled_moments import CENSORED, classify, family_block
from ._compiled_nonlinear import ADF, KALMAN, _block_inputs, _call, _input_scratch
from ._compiled_tobit import GL_W, GL_X, censored_stats

__all__ = ["BLOCK", "sqrt_loop", "compiled_run"]

BLOCK = 64  #: runs per block
_TINY = float(np.finfo(np.float64).tiny)
_CBRT_EPS = float(np.cbrt(np.finfo(np.float64).eps))


# --------------------------------------------------------------------------- factors


@njit(error_model="numpy", cache=True)
def _psd_root(P, out):
    """A root of the symmetric PSD ``P`` into ``out``: the lower Cholesky factor, or the eigen root."""
    n = P.shape[0]
    out[:] = 0.0
    ok = True
    for j in range(n):
        d = P[j, j]
        for c in range(j):
            d -= out[j, c] * out[j, c]
        if not d > 0.0:
            ok = False
            break
        d = math.sqrt(d)
        out[j, j] = d
        for i in range(j + 1, n):
            s = P[i, j]
            for c in range(j):
                s -= out[i, c] * out[j, c]
            out[i, j] = s / d
    if ok:
        return
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    for i in range(n):
        for c in range(n):
            out[i, c] = V[i, c] * math.sqrt(max(w[c], 0.0))


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
        _psd_root(N, Rr)
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
def _points(xs, Ss, xi, X, nb, act):
    """The points :math:`x + S\\xi_l` of the runs b < nb with ``act[b]``, stacked in ``X``; returns how many runs."""
    L, n = xi.shape
    q = 0
    for b in range(nb):
        if not act[b]:
            continue
        for p in range(L):
            for i in range(n):
                s = xs[b, i]
                for j in range(n):
                    s += Ss[b, i, j] * xi[p, j]
                X[q * L + p, i] = s
        q += 1
    return q


@njit(error_model="numpy", cache=True)
def _differences(xs, X, deltas, nb):
    """The 2n central-difference points of every run stacked in ``X`` (steps in ``deltas``; as
    :func:`tobitkf.models.nonlinear.jacobian_fd`)."""
    n = xs.shape[1]
    for b in range(nb):
        for j in range(n):
            deltas[b, j] = _CBRT_EPS * max(1.0, abs(xs[b, j]))
        for j in range(n):
            for i in range(n):
                X[2 * n * b + j, i] = xs[b, i]
                X[2 * n * b + n + j, i] = xs[b, i]
            X[2 * n * b + j, j] += deltas[b, j]
            X[2 * n * b + n + j, j] -= deltas[b, j]


@njit(error_model="numpy", cache=True)
def _jacobians(V, deltas, J, nb):
    """The Jacobians ``J[b]`` from the values ``V`` at the points of :func:`_differences`."""
    n = deltas.shape[1]
    r = V.shape[1]
    for b in range(nb):
        for j in range(n):
            for a in range(r):
                J[b, a, j] = (V[2 * n * b + j, a] - V[2 * n * b + n + j, a]) / (2.0 * deltas[b, j])


@njit(error_model="numpy", cache=True)
def _predict(sigma, Y, J, Ss, wm, wc, Qroot, xps, Sps, nb):
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
    for a in range(r):
        s = 0.0
        for p in range(L):
            s += wm[p] * Yb[p, a]
        ym[a] = s
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
def _joint(code, sigma, Y, J, xi, wm, wc, xps, Sps, y, r0, t, R, Rroot, lo, hi, noise_code, xs, Ss, ey, slope, nb):
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
            _linearise(Y[b * L : (b + 1) * L], xi, wm, wc, Sps[b], ym, Hl, Eres)
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
            for a in range(m):
                st = censored_stats(ym[a], math.sqrt(R[a, a]), lo[a], hi[a], GL_X, GL_W, buf)
                g[a] = st[2]
                E[a] = st[6]
                if noise_code == 0:
                    V[a] = st[5]
                elif noise_code == 1:
                    V[a] = st[7]
                else:
                    V[a] = st[2] * (st[5] + (st[4] - ym[a]) ** 2)
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
def _adf_start(y, r0, t, ch, xs, Ss, xms, Sms, act, nb):
    """Start channel ``ch``: the linearisation point is the prior, ``act`` the runs with a reading; how many."""
    q = 0
    for b in range(nb):
        xms[b] = xs[b]
        Sms[b] = Ss[b]
        act[b] = not math.isnan(y[r0 + b, t, ch])
        if act[b]:
            q += 1
    return q


@njit(error_model="numpy", cache=True)
def _adf_channel(it, ch, Y, xi, wm, wc, y, r0, t, xs, Ss, xms, Sms, act, rl, family, lo, hi, par, lsum, nb):
    r"""Linearisation ``it`` of channel ``ch`` (the numpy ``_channel_sqrt``) for the runs in ``act``, from the values
    ``Y`` of h at their stacked points of :math:`N(x_m, S_mS_m^T)`: the affine model (about the prior when
    ``it`` = 0), the channel's moments of the latent reading, then the array update of the prior ``xs``, ``Ss``
    with noise :math:`\Omega + R_{ll}` and one QR for :math:`+KVK^T`, into ``xms``, ``Sms``."""
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
        cls[0] = classify(yb, lo, hi) if family == CENSORED else 1
        family_block(family, 1, yv, cls, hx, hph, rb, lo_c, hi_c, par, alpha, beta, llb, pu, comp, GL_X, GL_W, buf)
        e[0] = alpha[0] * s2  # E[y* | y] - mu
        Vr = s2 - beta[0] * s2 * s2  # Var[y* | y]
        root[0, 0] = math.sqrt(omega + rl)
        _array_update(xs[b], Ss[b], e, Hl, root, okv, xms[b], Sms[b], K)
        _add_retained(Sms[b], K[:, 0], Vr)
        if it == 0:
            lsum[b] += llb[0]


@njit(error_model="numpy", cache=True)
def _record(xs, Ss, r0, t, nb, means, covs):
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


@njit(error_model="numpy")
def sqrt_loop(
    f, h, F, H, code, xi, wm, wc, y, u, uh, Qroots, Rs, Rroots, k0, x0, S0,
    family, lo, hi, par, noise_code, iterations,
    means, covs, pmeans, pcovs, ey, slope, ll, x_last, S_last,
):  # fmt: skip
    """The square-root filter of every nonlinear family over the runs of ``y`` (N, T, m) from the prior ``x0``
    (N, n) and factor ``S0`` (N or 1, n, n) at time ``k0``; the arguments as those of
    :func:`~tobitkf.filters._compiled_nonlinear.nonlinear_loop`, with the roots ``Qroots`` (TQ, n, q) of
    :math:`Q_{k-1}` and ``Rroots`` (TR, m, m) of :math:`R_k`, and the last factor into ``S_last``."""
    N, T, m = y.shape
    n = x0.shape[1]
    L = xi.shape[0]
    TQ, TR, TL, TP = Qroots.shape[0], Rs.shape[0], lo.shape[0], par.shape[0]
    B = min(BLOCK, N)
    rows = L if L > 0 else 2 * n
    xs, Ss, xps, Sps = np.empty((B, n)), np.empty((B, n, n)), np.empty((B, n)), np.empty((B, n, n))
    xms, Sms = np.empty((B, n)), np.empty((B, n, n))
    X, X1 = np.empty((B * rows, n)), np.empty((B, n))
    deltas, J, Hj = np.empty((B, n)), np.empty((B, n, n)), np.empty((B, m, n))
    every, act, lsum = np.ones(B, dtype=np.bool_), np.empty(B, dtype=np.bool_), np.empty(B)
    U = _input_scratch(u if uh is None else uh, B * rows)
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        for b in range(nb):
            xs[b] = x0[r0 + b]
            Ss[b] = S0[r0 + b if S0.shape[0] > 1 else 0]
        for t in range(T):
            k = k0 + t + 1
            Qroot, R, Rroot = Qroots[min(t, TQ - 1)], Rs[min(t, TR - 1)], Rroots[min(t, TR - 1)]
            lo_t, hi_t = lo[min(t, TL - 1)], hi[min(t, TL - 1)]
            if L == 0:
                for b in range(nb):
                    X1[b] = xs[b]
                Y1 = _call(f, X1[:nb], k - 1, _block_inputs(u, r0, nb, t, 1, U))
                if F is None:
                    _differences(xs, X, deltas, nb)
                    V = _call(f, X[: nb * rows], k - 1, _block_inputs(u, r0, nb, t, rows, U))
                    _jacobians(V, deltas, J, nb)
                    _predict(False, Y1, J, Ss, wm, wc, Qroot, xps, Sps, nb)
                else:
                    Jf = _call(F, X1[:nb], k - 1, _block_inputs(u, r0, nb, t, 1, U))
                    _predict(False, Y1, Jf, Ss, wm, wc, Qroot, xps, Sps, nb)
            else:
                _points(xs, Ss, xi, X, nb, every)
                Y = _call(f, X[: nb * L], k - 1, _block_inputs(u, r0, nb, t, L, U))
                _predict(True, Y, J, Ss, wm, wc, Qroot, xps, Sps, nb)
            _record(xps, Sps, r0, t, nb, pmeans, pcovs)
            if code == ADF:
                for b in range(nb):
                    xs[b] = xps[b]
                    Ss[b] = Sps[b]
                lsum[:] = 0.0
                for ch in range(m):
                    if _adf_start(y, r0, t, ch, xs, Ss, xms, Sms, act, nb) == 0:
                        continue
                    for it in range(iterations):
                        q = _points(xms, Sms, xi, X, nb, act)
                        if q == 0:
                            break
                        Yh = _call(h, X[: q * L], k, active_inputs(uh, r0, nb, t, L, U, act))
                        _adf_channel(it, ch, Yh, xi, wm, wc, y, r0, t, xs, Ss, xms, Sms, act, R[ch, ch], family,
                                     lo_t[ch], hi_t[ch], par[min(t, TP - 1), ch], lsum, nb)  # fmt: skip
                    for b in range(nb):
                        xs[b] = xms[b]
                        Ss[b] = Sms[b]
                if ll.shape[1] > 0:
                    for b in range(nb):
                        ll[r0 + b, t] = lsum[b]
            elif L == 0:
                for b in range(nb):
                    X1[b] = xps[b]
                Y1 = _call(h, X1[:nb], k, _block_inputs(uh, r0, nb, t, 1, U))
                if H is None:
                    _differences(xps, X, deltas, nb)
                    Yh = _call(h, X[: nb * rows], k, _block_inputs(uh, r0, nb, t, rows, U))
                    _jacobians(Yh, deltas, Hj, nb)
                    _joint(code, False, Y1, Hj, xi, wm, wc, xps, Sps, y, r0, t, R, Rroot, lo_t, hi_t, noise_code, xs,
                           Ss, ey, slope, nb)  # fmt: skip
                else:
                    Jh = _call(H, X1[:nb], k, _block_inputs(uh, r0, nb, t, 1, U))
                    _joint(code, False, Y1, Jh, xi, wm, wc, xps, Sps, y, r0, t, R, Rroot, lo_t, hi_t, noise_code, xs,
                           Ss, ey, slope, nb)  # fmt: skip
            else:
                _points(xps, Sps, xi, X, nb, every)
                Yh = _call(h, X[: nb * L], k, _block_inputs(uh, r0, nb, t, L, U))
                _joint(code, True, Yh, Hj, xi, wm, wc, xps, Sps, y, r0, t, R, Rroot, lo_t, hi_t, noise_code, xs, Ss,
                       ey, slope, nb)  # fmt: skip
            _record(xs, Ss, r0, t, nb, means, covs)
        for b in range(nb):
            x_last[r0 + b] = xs[b]
            S_last[r0 + b] = Ss[b]


# --------------------------------------------------------------------------- the Python side


def _c(a) -> np.ndarray:
    return np.require(a, dtype=float, requirements=("C", "W"))


def compiled_run(est, y2: np.ndarray, u2, state, want, batch):
    """The compiled square-root ``filter`` of a nonlinear estimator: a :class:`~tobitkf.FilterResult` whose final
    state carries the factor, or None when a factor stopped being finite (the numpy path reruns the call and
    reports where) or the channel is not covered."""
    from .._linalg import psd_sqrt
    from ._compiled_inputs import _model_inputs
    from ._compiled_nonlinear import TOBIT, channel_arrays
    from ._outputs import kernel_result, output_arrays, state_specs
    from .core import FilterState

    N, T, m = y2.shape
    n = est.n
    sys_ = est.system
    arrays = channel_arrays(est, state.k, T)
    if isinstance(arrays, str):
        return None
    family, lo, hi, par, noise_code = arrays
    rule = est.rule
    if rule is None:
        xi, wm, wc = np.empty((0, n)), np.empty(0), np.empty(0)
    else:
        xi, wm, wc = (_c(a) for a in rule.unit(n))
    k0 = state.k
    steps = range(T) if (sys_.Q.varying or sys_.R.varying) else range(1)
    Qroots = _c(np.stack([est._qroot(k0 + t) for t in steps]))
    Rs = _c(np.stack([sys_.measurement_cov(k0 + t + 1) for t in steps]))
    Rroots = _c(psd_sqrt(Rs))
    code = est._compiled_code
    ext = "extras" in want
    means, covs, pmeans, pcovs, ey, slope, ll = output_arrays(
        N, T, *state_specs(want, n), (ext and code == TOBIT, (m,)), (ext and code == TOBIT, (m,)),
        (ext and code == ADF, ()),
    )  # fmt: skip
    S0 = state.S if state.S is not None else psd_sqrt(state.P)
    x_last, S_last = np.empty((N, n)), np.empty((N, n, n))
    uf, uh = _model_inputs(sys_, u2, N, T)
    sqrt_loop(
        sys_.f, sys_.h, sys_.F, sys_.H, code, xi, wm, wc, _c(y2), uf, uh, Qroots, Rs, Rroots, k0, _c(state.x),
        _c(S0), family, lo, hi, par, noise_code, est.iterations if code == ADF else 1,
        means, covs, pmeans, pcovs, ey, slope, ll, x_last, S_last,
    )  # fmt: skip
    if not np.isfinite(S_last).all():
        return None
    extras = {}
    if ext and code == TOBIT:
        extras = {"expected_y": ey, "slope": slope}
    elif ext and code == ADF:
        extras = {"log_likelihood": ll}
    extras = {key: v.reshape(batch + v.shape[1:]) for key, v in extras.items()}
    P_last = S_last @ np.swapaxes(S_last, -1, -2)
    P_last = 0.5 * (P_last + np.swapaxes(P_last, -1, -2))
    final = FilterState(k=k0 + T, batch_shape=batch, x=x_last, P=P_last, n=n, S=S_last, carry=state.carry)
    return kernel_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)
