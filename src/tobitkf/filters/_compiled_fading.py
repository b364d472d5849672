r"""The fading Tobit Kalman filter's (TKF-FM) pieces of the one compiled loop
(:func:`~tobitkf.filters._compiled_loop.compiled_loop`, update code
:data:`~tobitkf.filters._compiled_loop.FADING`).

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.fading.FadingTobitKalmanFilter` (Geng et al. 2017, Table 1, with the
repaired (20')), not a second algorithm: the augmented state
:math:`\xi_k = \mathrm{col}\{x_k, \dots, x_{k-L}\}` of fixed size :math:`n_\xi = n(L+1)`, the
predict (17)–(18) with the block-shift structure of :math:`\mathcal A` (:func:`shift_predict_block`, as
:func:`tobitkf.filters.core.shift_predict`; also the predict of the protocol filter's augmented state), and the
update :func:`fading_update_block`: the censored statistics at :math:`\hat\chi = H_k\hat\xi_{k|k-1}` (Lemma 1,
:math:`H_k = \bar\theta_k\mathcal C_k`, the loop's rows of the step), :math:`\hat y` (21), the gain scale
:math:`\bar\Upsilon_k` (so :math:`G_k = \bar\Upsilon_kH_k`), the noise :math:`N_k` = the truncated variance (12)
or, with ``exact_tobit_variance``, the censored variance, and the update in the Joseph or the standard form,
both in the rank-m arithmetic of the shared numpy update.

Everything that is not specific to the fading model is shared with the Tobit Kalman filter's update
(:func:`~tobitkf.filters._compiled_tobit.tobit_update_block`): the censored-normal statistics
(:func:`~tobitkf.filters._compiled_censored.censored_stats`; for a lower limit alone the vectorised statistics
of a whole block, :func:`_lower_block`), the noise term
(:func:`~tobitkf.filters._compiled_censored.noise_term`: the truncated variance is the TKF's ``"dissertation"``
term, the censored variance its ``"total_variance"``), the moments of the scaled update and the masked gain
(missing or degenerate channels get a zero gain column; for m > 1 the block solve over all runs of a block).
What the fading update adds is the inverse Mills ratio :math:`\lambda` among its outputs.
"""

from __future__ import annotations

from numba import njit

from ._compiled_block import _block_dims, mean_predict, scaled_update
from ._compiled_censored import GL_W, GL_X, _one_sided_at, censored_stats, noise_term
from ._compiled_tobit import _INF

__all__ = [
    "fading_update_block",
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


@njit(cache=True, error_model="numpy")
def _lower_block(ym, sd, lo, nb, noise_code, gam, lam, noise):
    """The statistics of the runs ``b < nb`` of a block for a lower limit ``lo`` alone, vectorised: γ into ``gam``,
    the inverse Mills ratio into ``lam``, the noise term of ``noise_code`` (0 the truncated, 1 the censored
    variance) into ``noise``, the censored mean over the means ``ym`` (each (B,)); the numbers of
    :func:`~tobitkf.filters._compiled_censored.censored_stats`. A function of its own, as the TKF's
    :func:`~tobitkf.filters._compiled_censored.one_sided_block`: compiled apart from the loop, its loop over the
    runs vectorises."""
    for b in range(nb):
        _plo, g, lm, _tmean, tv, cm, cv = _one_sided_at(ym[b], sd, lo)
        gam[b] = g
        lam[b] = lm
        noise[b] = tv if noise_code == 0 else cv
        ym[b] = cm


@njit(cache=True, error_model="numpy", inline="always")
def fading_update_block(C, sigma, lo, hi, tl, noise_code, joseph, y, du, r0, t, xp, Pp, x, P, mu, e, lam, scratch, nb):
    r"""The TKF-FM measurement update of a block of ``nb`` runs ((6), (21), (23)–(26), (19), (20')), all channel
    statistics at the prediction :math:`\hat\chi = H_k\hat\xi_{k|k-1} + Du_k` (Lemma 1).

    ``C`` (m, n_ξ) the step's rows :math:`H_k`; ``sigma`` (m,) the noise standard deviations; ``lo``/``hi``
    (TL, m) the limits, row ``tl`` this step's; run b reads ``y[r0 + b, t]`` (NaN: missing) and ``du[r0 + b,
    t]`` (``du`` with no steps: no feedthrough); ``noise_code`` 0 (the truncated variance (12), the source) or 1
    (the censored variance, ``exact_tobit_variance``) of :func:`~tobitkf.filters._compiled_censored.noise_term`;
    ``xp`` (n_ξ, B), ``Pp`` (n_ξ, n_ξ, B) the prediction. Writes the posterior ``x``, ``P``, :math:`\hat y`
    (21) into ``mu`` (m, B), the innovation into ``e``, the inverse Mills ratio into ``lam`` (m, B) and
    :math:`\bar\gamma` into ``gam`` of ``blk``; ``scratch`` the ``(blk, run, solve, buf)`` of
    :func:`~tobitkf.filters._compiled_block._update_scratch` (``buf`` the (2, G) buffer of the quadrature)."""
    buf = scratch[3]
    noise, gam = scratch[0][8], scratch[0][9]
    m, nxi = C.shape
    has_du = du.shape[1] > 0
    for l in range(m):
        ml = mu[l]
        for b in range(nb):  # chi = H_k xi + D u for the whole block (vectorised; the numpy path's sums in order)
            ml[b] = 0.0
        for j in range(nxi):
            c = C[l, j]
            for b in range(nb):
                ml[b] += xp[j, b] * c
        if has_du:
            for b in range(nb):
                ml[b] += du[r0 + b, t, l]
        sd, lo_l, hi_l = sigma[l], lo[tl, l], hi[tl, l]
        if hi_l == _INF and lo_l != -_INF:  # a lower limit alone: the statistics of the block at once, vectorised
            _lower_block(ml, sd, lo_l, nb, noise_code, gam[l], lam[l], noise[l, l])
            for b in range(nb):
                e[l, b] = y[r0 + b, t, l] - ml[b]
            continue
        for b in range(nb):
            st = censored_stats(ml[b], sd, lo_l, hi_l, GL_X, GL_W, buf)
            gam[l, b] = st[2]
            lam[l, b] = st[3]
            noise[l, l, b] = noise_term(noise_code, ml[b], st[2], st[4], st[5], st[7])
            ml[b] = st[6]
            e[l, b] = y[r0 + b, t, l] - st[6]
    # Sigma_xy = P G^T, Sigma_yy = G P G^T + N_k, G = diag(gamma) H_k (24)-(26); the gain (23), (19); P (20')
    scaled_update(C, joseph, xp, Pp, e, x, P, scratch, nb)
