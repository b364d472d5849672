r"""Compiled (numba) time loop of the Tobit Kalman filter with Rice fading measurements (TKF-FM).

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.fading.FadingTobitKalmanFilter` (Geng et al. 2017, Table 1, with the
repaired (20')), not a second algorithm: the augmented state
:math:`\xi_k = \mathrm{col}\{x_k, \dots, x_{k-L}\}` of fixed size :math:`n_\xi = n(L+1)`, the
predict (17)–(18) with the augmented shift matrix :math:`\mathcal A` (dense here: the zeros add
exact zeros), the measurement matrix :math:`H_k = \bar\theta_k\mathcal C_k` (its blocks
:math:`s > k` zero, so ``H`` is indexed by :math:`\min(k, L)`), the censored statistics at
:math:`\hat\chi = H_k\hat\xi_{k|k-1}` (Lemma 1), :math:`\hat y` (21), the gain scale
:math:`\bar\Upsilon_k` (so :math:`G_k = \bar\Upsilon_kH_k`), the noise :math:`N_k` = the truncated
variance (12) or, with ``exact_tobit_variance``, the censored variance, and the update in the
Joseph or the standard form.

Everything that is not specific to the fading model is shared with the TKF kernel of
:mod:`tobitkf.filters._kernels`: the censored-normal statistics (continued-fraction tails,
quadrature) :func:`~tobitkf.filters._kernels.censored_stats`, the block predict, the masked gain
(missing or degenerate channels get a zero gain column) and the covariance update.

Covered (the dispatcher in ``fading.py`` decides): time-invariant A, B, Q, C, R, no control input,
``p_uncensored_mode="augmented"``, ``fading_variance_term=False``, both ``exact_tobit_variance``
values, ``covariance_update`` ``"joseph"`` and ``"standard"``, any limits (constant or (T, m), one-
or two-sided), NaN readings, ``keep_smoothed`` either way, ``keep_augmented=False``. Everything
else runs on numpy.

Outputs are written directly into the preallocated ``(N, T, ...)`` arrays; an array of shape
``(N, 0, ...)`` is not requested and not written.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._kernels import _TINY, BLOCK, _cov_update, _gain, _load, _predict, _store_last, censored_stats

__all__ = ["fading_tkf_kernel"]


@njit(cache=True, error_model="numpy", nogil=True)
def fading_tkf_kernel(
    y,
    A,
    Qd,
    Hs,
    sigma,
    lo,
    hi,
    x0,
    P0,
    k0,
    n,
    exact,
    joseph,
    glx,
    glw,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    lam_out,
    sm_mean,
    sm_cov,
    x_last,
    P_last,
):
    """TKF-FM over ``N`` runs of ``T`` steps from the augmented state ``x0`` (N, nxi), ``P0`` (N, nxi, nxi).

    ``y`` (N, T, m) (NaN = missing) holds the readings of steps ``k0 + 1 .. k0 + T``; ``A``/``Qd``
    (nxi, nxi) the augmented transition and process covariance; ``Hs`` (L+1, m, nxi) with
    ``Hs[j] = H_j`` (block s zero for s > j), step k using ``Hs[min(k, L)]``; ``sigma`` (m,);
    ``lo``/``hi`` (T, m); ``n`` the size of one block; ``exact`` selects the censored variance as
    :math:`N_k`. Outputs: ``means``/``pmeans`` (N, T, n), ``covs``/``pcovs`` (N, T, n, n) (block 0),
    ``pu``/``ey``/``lam_out`` (N, T, m), ``sm_mean`` (N, T, L+1, n), ``sm_cov`` (N, T, L+1, n, n)
    (NaN for the blocks s > k); each of shape ``(N, 0, ...)`` when not requested. ``x_last``
    (N, nxi) and ``P_last`` (N, nxi, nxi) receive the state after the last step.
    """
    N, T, m = y.shape
    nxi = A.shape[0]
    L = Hs.shape[0] - 1
    B = min(BLOCK, max(N, 1))
    x = np.empty((nxi, B))
    P = np.empty((nxi, nxi, B))
    xp = np.empty((nxi, B))
    Pp = np.empty((nxi, nxi, B))
    AP = np.empty((nxi, nxi, B))
    CP = np.empty((m, nxi, B))
    Rxe = np.empty((nxi, m, B))
    Ree = np.empty((m, m, B))
    K = np.empty((nxi, m, B))
    G = np.empty((m, nxi, B))
    noise = np.zeros((m, m, B))
    IKH = np.empty((nxi, nxi, B))
    T1 = np.empty((nxi, nxi, B))
    gam = np.empty((m, B))
    e = np.empty((m, B))
    ok = np.empty((m, B), dtype=np.bool_)
    Rs = np.empty((m, m))
    Ws = np.empty((m, nxi))
    Ks = np.empty((nxi, m))
    Rxs = np.empty((nxi, m))
    oks = np.empty(m, dtype=np.bool_)
    ds = np.empty(m)
    buf = np.empty((2, glx.shape[0]))
    want_m, want_c, want_pm, want_pc = means.shape[1] > 0, covs.shape[1] > 0, pmeans.shape[1] > 0, pcovs.shape[1] > 0
    want_x, want_sm, want_sc = pu.shape[1] > 0, sm_mean.shape[1] > 0, sm_cov.shape[1] > 0
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x0, P0, r0, nb, x, P)
        for t in range(T):
            k = k0 + t + 1
            C = Hs[min(k, L)]
            _predict(A, Qd, x, P, xp, Pp, AP, nb)  # (17)-(18)
            if want_pm:
                for b in range(nb):
                    for i in range(n):
                        pmeans[r0 + b, t, i] = xp[i, b]
            if want_pc:
                for b in range(nb):
                    for i in range(n):
                        for j in range(n):
                            pcovs[r0 + b, t, i, j] = Pp[i, j, b]
            # Lemma 1 at chi = H_k xi_{k|k-1}; (6), (21), (12) or the censored variance
            for l in range(m):
                for b in range(nb):
                    mu = 0.0
                    for j in range(nxi):
                        mu += xp[j, b] * C[l, j]
                    st = censored_stats(mu, sigma[l], lo[t, l], hi[t, l], glx, glw, buf)
                    g = st[2]
                    gam[l, b] = g
                    noise[l, l, b] = st[7] if exact else st[5]
                    e[l, b] = y[r0 + b, t, l] - st[6]
                    if want_x:
                        pu[r0 + b, t, l] = g
                        ey[r0 + b, t, l] = st[6]
                        lam_out[r0 + b, t, l] = st[3]
            # Sigma_xy = P G^T, Sigma_yy = G P G^T + N_k, G = diag(gamma) H_k  (24)-(26)
            for l in range(m):
                for j in range(nxi):
                    for b in range(nb):
                        CP[l, j, b] = 0.0
                    for q in range(nxi):
                        c = C[l, q]
                        if c != 0.0:
                            for b in range(nb):
                                CP[l, j, b] += c * Pp[q, j, b]
            for l in range(m):
                for j in range(nxi):
                    for b in range(nb):
                        Rxe[j, l, b] = CP[l, j, b] * gam[l, b]
                for q in range(m):
                    for b in range(nb):
                        Ree[l, q, b] = 0.0
                    for j in range(nxi):
                        c = C[q, j]
                        for b in range(nb):
                            Ree[l, q, b] += CP[l, j, b] * c
                    for b in range(nb):
                        Ree[l, q, b] = Ree[l, q, b] * gam[l, b] * gam[q, b]
                for b in range(nb):
                    Ree[l, l, b] += noise[l, l, b]
            for l in range(m):
                for b in range(nb):
                    good = (Ree[l, l, b] > _TINY) and not math.isnan(e[l, b])
                    ok[l, b] = good
                    if not good:
                        e[l, b] = 0.0
                    if joseph:
                        for j in range(nxi):
                            G[l, j, b] = C[l, j] * gam[l, b] if good else 0.0
            _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)  # (23), (19)
            _cov_update(Pp, K, Rxe, G, noise, joseph, P, IKH, T1, nb)  # (20')
            if want_m:
                for b in range(nb):
                    for i in range(n):
                        means[r0 + b, t, i] = x[i, b]
            if want_c:
                for b in range(nb):
                    for i in range(n):
                        for j in range(n):
                            covs[r0 + b, t, i, j] = P[i, j, b]
            if want_sm:
                for b in range(nb):
                    for s in range(L + 1):
                        for i in range(n):
                            sm_mean[r0 + b, t, s, i] = x[s * n + i, b] if s <= k else np.nan
            if want_sc:
                for b in range(nb):
                    for s in range(L + 1):
                        for i in range(n):
                            for j in range(n):
                                sm_cov[r0 + b, t, s, i, j] = P[s * n + i, s * n + j, b] if s <= k else np.nan
        _store_last(x, P, r0, nb, x_last, P_last)
