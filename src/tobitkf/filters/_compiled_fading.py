r"""Compiled (numba) time loop of the Tobit Kalman filter with Rice fading measurements (TKF-FM).

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.fading.FadingTobitKalmanFilter` (Geng et al. 2017, Table 1, with the
repaired (20')), not a second algorithm: the augmented state
:math:`\xi_k = \mathrm{col}\{x_k, \dots, x_{k-L}\}` of fixed size :math:`n_\xi = n(L+1)`, the
predict (17)–(18) with the block-shift structure of :math:`\mathcal A` (as
:func:`tobitkf.filters.core.shift_predict`), the measurement matrix :math:`H_k = \bar\theta_k\mathcal C_k` (its blocks
:math:`s > k` zero, so ``H`` is indexed by :math:`\min(k, L)`), the censored statistics at
:math:`\hat\chi = H_k\hat\xi_{k|k-1}` (Lemma 1), :math:`\hat y` (21), the gain scale
:math:`\bar\Upsilon_k` (so :math:`G_k = \bar\Upsilon_kH_k`), the noise :math:`N_k` = the truncated
variance (12) or, with ``exact_tobit_variance``, the censored variance, and the update in the
Joseph or the standard form, both in the rank-m arithmetic of the shared numpy update.

Everything that is not specific to the fading model is shared with the TKF kernel of
:mod:`tobitkf.filters._compiled_tobit`: the censored-normal statistics (continued-fraction tails,
quadrature: :func:`~tobitkf.filters._compiled_tobit.censored_stats`; for a lower limit alone the vectorised
statistics of a whole block, :func:`~tobitkf.filters._compiled_censored.lower_stats_block`), the block scratch, the moments of the
scaled update and the masked gain (missing or degenerate channels get a zero gain column): for m > 1
the block solve :func:`~tobitkf.filters._compiled_block._gain_block` over all runs of a block at once, as in
the TKF kernel.

Covered (the dispatcher in ``fading.py`` decides): time-invariant A, B, Q, C, R, no control input,
``p_uncensored_mode="augmented"``, ``fading_variance_term=False``, both ``exact_tobit_variance``
values, ``covariance_update`` ``"joseph"`` and ``"standard"``, any limits (constant or (T, m), one-
or two-sided), NaN readings, ``keep_smoothed`` either way, ``keep_augmented=False``. Everything
else runs on numpy.

Outputs are staged for :data:`~tobitkf.filters._compiled_block.CHUNK` steps per block of runs and written
run by run into the preallocated ``(N, T, ...)`` arrays (as in the TKF kernel); an array of shape
``(N, 0, ...)`` is not requested: it gets no staging and is not written. The driver carves the
requested arrays from one allocation (:func:`tobitkf.filters.kalman.output_arrays`: fewer first-touch page
faults).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_block import (
    _block_dims,
    _cov_update,
    _flush,
    _gain,
    _gain_block,
    _innovation_moments,
    _load,
    _mean_scratch,
    _stage_cov,
    _stage_shape,
    _store_last,
    _update_scratch,
    mean_predict,
)
from ._compiled_censored import lower_stats_block
from ._compiled_tobit import _INF, GL_W, GL_X, censored_stats

__all__ = [
    "fading_tkf_kernel",
    "fading_tkf_step",
    "step_constants",
    "shift_predict_block",
    "AUG_BLOCK",
    "aug_block_dims",
]

#: runs per block of the augmented-state loops (this one and the protocol loop), twice the large-n TKF's
#: :data:`~tobitkf.filters._compiled_block.BLOCK`: a step of these loops is some 300 short loops over the runs of a block
#: (n_xi = 6), whose fixed cost per loop 64 runs share better than 32. Measured (1000 runs x 100 steps, all
#: outputs, thread CPU time, old/new processes alternated twice, load 4.5-5.8): fading default 164-167 -> 148-152,
#: protocol "variance" 163 -> 152-157 ns per run-step; the staging of the fading loop's 33 numbers per run-step is
#: then 1.1 MB (64 steps x 64 runs)
AUG_BLOCK = 64


@njit(cache=True)
def aug_block_dims(N, T):
    """``(B, S)`` of the augmented-state loops: :func:`~tobitkf.filters._compiled_block._block_dims` with
    :data:`AUG_BLOCK` runs per block."""
    return _block_dims(N, T, 0, AUG_BLOCK)


@njit(cache=True, error_model="numpy")
def shift_predict_block(A, Qd, x, P, xp, Pp, X, nb):
    r"""Block-shift time update of a block of runs, as :func:`tobitkf.filters.core.shift_predict` (source 0):
    :math:`\bar\xi = [A\xi_0; \xi_0; \dots; \xi_{L-1}]`, :math:`X = P_{:,0}A^T`,
    :math:`\bar P_{00} = \mathrm{sym}(X_0^TA^T + Q_d)`, :math:`\bar P_{i+1,0} = X_i`,
    :math:`\bar P_{i+1,j+1} = P_{ij}`. ``A``, ``Qd`` (n, n); ``x`` (nxi, B), ``P`` (nxi, nxi, B)
    exactly symmetric; ``X`` (nxi, n, B) scratch. O(n n_xi^2) instead of O(n_xi^3)."""
    nxi, n = x.shape[0], A.shape[0]
    mean_predict(A, x, xp, nb)
    for i in range(n, nxi):
        for b in range(nb):
            xp[i, b] = x[i - n, b]
    for i in range(nxi):
        for j in range(n):
            for b in range(nb):
                X[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    X[i, j, b] += P[i, k, b] * a
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                Pp[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    Pp[i, j, b] += X[k, i, b] * a
            q = Qd[i, j]
            for b in range(nb):
                Pp[i, j, b] += q
    for i in range(n):
        for j in range(i + 1, n):
            for b in range(nb):
                v = 0.5 * (Pp[i, j, b] + Pp[j, i, b])
                Pp[i, j, b] = v
                Pp[j, i, b] = v
    for i in range(n, nxi):
        for j in range(n):
            for b in range(nb):
                v = X[i - n, j, b]
                Pp[i, j, b] = v
                Pp[j, i, b] = v
        for j in range(n, nxi):
            for b in range(nb):
                Pp[i, j, b] = P[i - n, j - n, b]


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
    (n, n) the transition and process covariance of the top block; ``Hs`` (L+1, m, nxi) with
    ``Hs[j] = H_j`` (block s zero for s > j), step k using ``Hs[min(k, L)]``; ``sigma`` (m,);
    ``lo``/``hi`` (T, m); ``n`` the size of one block; ``exact`` selects the censored variance as
    :math:`N_k`. Outputs: ``means``/``pmeans`` (N, T, n), ``covs``/``pcovs`` (N, T, n, n) (block 0),
    ``pu``/``ey``/``lam_out`` (N, T, m), ``sm_mean`` (N, T, L+1, n), ``sm_cov`` (N, T, L+1, n, n)
    (NaN for the blocks s > k); each of shape ``(N, 0, ...)`` when not requested. ``x_last``
    (N, nxi) and ``P_last`` (N, nxi, nxi) receive the state after the last step.
    """
    N, T, m = y.shape
    nxi = Hs.shape[2]
    L = Hs.shape[0] - 1
    B, S = aug_block_dims(N, T)
    x, xp, e, mu_b = _mean_scratch(nxi, m, B)
    st_g, st_lam, st_tv, st_cm, st_cv = np.empty(B), np.empty(B), np.empty(B), np.empty(B), np.empty(B)
    blk, run, solve, buf = _update_scratch(nxi, A.shape[0], m, B, glx.shape[0])
    P, Pp, X, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    Rs, Ws, Ks, oks, Rxs, ds = run
    Rw, Wb, db, bad = solve
    want_m, want_c, want_pm, want_pc = means.shape[1] > 0, covs.shape[1] > 0, pmeans.shape[1] > 0, pcovs.shape[1] > 0
    want_x, want_sm, want_sc = pu.shape[1] > 0, sm_mean.shape[1] > 0, sm_cov.shape[1] > 0
    # outputs staged for S steps, then written run by run (contiguous), as in the TKF kernel
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_cov, s_pcov = np.empty(_stage_shape(covs, B, S)), np.empty(_stage_shape(pcovs, B, S))
    s_pu, s_ey, s_lam = (
        np.empty(_stage_shape(pu, B, S)),
        np.empty(_stage_shape(ey, B, S)),
        np.empty(_stage_shape(lam_out, B, S)),
    )
    s_smm, s_smc = np.empty(_stage_shape(sm_mean, B, S)), np.empty(_stage_shape(sm_cov, B, S))
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x0, P0, r0, nb, x, P)
        for t in range(T):
            k = k0 + t + 1
            tt = t % S
            C = Hs[min(k, L)]
            shift_predict_block(A, Qd, x, P, xp, Pp, X, nb)  # (17)-(18)
            if want_pm:
                for i in range(n):
                    for b in range(nb):
                        s_pmean[tt, i, b] = xp[i, b]
            if want_pc:
                _stage_cov(Pp, s_pcov, tt, nb)
            # Lemma 1 at chi = H_k xi_{k|k-1}; (6), (21), (12) or the censored variance
            for l in range(m):
                for b in range(nb):  # chi = H_k xi for the whole block (vectorised; the same sums in the same order)
                    mu_b[l, b] = 0.0
                for j in range(nxi):
                    c = C[l, j]
                    for b in range(nb):
                        mu_b[l, b] += xp[j, b] * c
                lower = hi[t, l] == _INF and lo[t, l] != -_INF
                if lower:  # a lower limit alone: the statistics of the block at once, vectorised
                    lower_stats_block(mu_b[l], sigma[l], lo[t, l], nb, st_g, st_lam, st_tv, st_cm, st_cv)
                for b in range(nb):
                    if lower:
                        g, lm, tv, cm, cv = st_g[b], st_lam[b], st_tv[b], st_cm[b], st_cv[b]
                    else:
                        st = censored_stats(mu_b[l, b], sigma[l], lo[t, l], hi[t, l], glx, glw, buf)
                        g, lm, tv, cm, cv = st[2], st[3], st[5], st[6], st[7]
                    gam[l, b] = g
                    noise[l, l, b] = cv if exact else tv
                    e[l, b] = y[r0 + b, t, l] - cm
                    if want_x:
                        s_pu[tt, l, b] = g
                        s_ey[tt, l, b] = cm
                        s_lam[tt, l, b] = lm
            # Sigma_xy = P G^T, Sigma_yy = G P G^T + N_k, G = diag(gamma) H_k  (24)-(26)
            _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
            if m > 1:  # (23), (19)
                _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, Wb, db, bad, Rs, Ws, Ks, oks, Rxs, ds)
            else:
                _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)
            _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb)  # (20')
            if want_m:
                for i in range(n):
                    for b in range(nb):
                        s_mean[tt, i, b] = x[i, b]
            if want_c:
                _stage_cov(P, s_cov, tt, nb)  # P or its diagonal (outputs=("var",))
            if want_sm:  # the blocks s > k (before the record's start) are NaN
                for s in range(L + 1):
                    for i in range(n):
                        if s <= k:
                            for b in range(nb):
                                s_smm[tt, s, i, b] = x[s * n + i, b]
                        else:
                            s_smm[tt, s, i, :nb] = np.nan
            if want_sc:
                for s in range(L + 1):
                    for i in range(n):
                        for j in range(n):
                            if s <= k:
                                for b in range(nb):
                                    s_smc[tt, s, i, j, b] = P[s * n + i, s * n + j, b]
                            else:
                                s_smc[tt, s, i, j, :nb] = np.nan
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_pu, pu, r0, t0, nb, tt + 1)
                _flush(s_ey, ey, r0, t0, nb, tt + 1)
                _flush(s_lam, lam_out, r0, t0, nb, tt + 1)
                _flush(s_smm, sm_mean, r0, t0, nb, tt + 1)
                _flush(s_smc, sm_cov, r0, t0, nb, tt + 1)
        _store_last(x, P, r0, nb, x_last, P_last)


def step_constants(A: np.ndarray, Qd: np.ndarray, Hs: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """``A``, ``Qd`` (n, n), ``Hs`` (L+1, m, nxi) and ``sigma`` (m,) flattened into one float64 array in that
    order, as :func:`fading_tkf_step` takes them (built once per estimator)."""
    return np.concatenate([np.ravel(A), np.ravel(Qd), np.ravel(Hs), np.ravel(sigma)]).astype(np.float64)


@njit(cache=True, error_model="numpy", nogil=True)
def fading_tkf_step(y, consts, lohi, x0, P0, k0, n, exact, joseph, out3, sm_mean, sm_cov, x_last, P_last):
    """One step of :func:`fading_tkf_kernel` (the online ``step``) with 14 arguments instead of 26: numba unboxes
    every argument of a call from Python (~0.1-0.2 µs per array), a large part of a one-run step. ``y`` (N, m);
    ``consts`` the flat ``A, Qd, Hs, sigma`` of :func:`step_constants` (m = ``y.shape[1]``, nxi =
    ``x0.shape[1]``, L + 1 = the rest); ``lohi`` (2, 1, m) the step's limits; ``out3`` (3, N, m) receives
    P(uncensored), E[y] and the inverse Mills ratio; ``sm_mean`` (N, L+1, n), ``sm_cov`` (N, L+1, n, n) the
    smoothed blocks, or zero-size arrays when not wanted; ``x_last``, ``P_last`` the new state."""
    N, m = y.shape
    nxi = x0.shape[1]
    nn = n * n
    L1 = (consts.shape[0] - 2 * nn - m) // (m * nxi)
    A = consts[0:nn].reshape((n, n))
    Qd = consts[nn : 2 * nn].reshape((n, n))
    end = 2 * nn + L1 * m * nxi
    Hs = consts[2 * nn : end].reshape((L1, m, nxi))
    sigma = consts[end : end + m]
    ts = 1 if sm_mean.size > 0 else 0
    e_m, e_c = np.empty((N, 0, n)), np.empty((N, 0, n, n))
    fading_tkf_kernel(
        y.reshape((N, 1, m)),
        A,
        Qd,
        Hs,
        sigma,
        lohi[0],
        lohi[1],
        x0,
        P0,
        k0,
        n,
        exact,
        joseph,
        GL_X,
        GL_W,
        e_m,
        e_c,
        e_m,
        e_c,
        out3[0].reshape((N, 1, m)),
        out3[1].reshape((N, 1, m)),
        out3[2].reshape((N, 1, m)),
        sm_mean.reshape((N, ts, L1, n)),
        sm_cov.reshape((N, ts, L1, n, n)),
        x_last,
        P_last,
    )
