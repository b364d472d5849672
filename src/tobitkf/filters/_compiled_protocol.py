r"""Compiled (numba) time loop of the protocol-based Tobit Kalman filter (PBTKF-IMSF).

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.protocol.ProtocolTobitKalmanFilter` (Geng et al., Theorem 1, Table I), not a
second algorithm. Per step k, with the scheduled sensor :math:`h = \bar h_k`,
:math:`\mathbf H = \bar\Lambda_h\mathcal C_h` and :math:`\zeta = \mathbf H\hat\xi^-_k`:

.. math::

    \hat\xi^-_k, P^-_k &: \text{the block shift (17)–(18)}
        \;(:func:`~tobitkf.filters._compiled_fading.shift_predict_block`) \\
    \lambda, \mathcal R(1-\varphi) &: \text{the censored statistics at } \zeta
        \text{ (:func:`~tobitkf.filters._compiled_censored.lower_stats_block`, lower limit } \tau),
        \text{ the latter floored at } 10^{-12}\mathcal R \\
    \hat y &= \zeta + \sqrt{\mathcal R}\lambda \;(21), \quad
    R_{ee} = \mathbf HP^-_k\mathbf H^T + F_k + \mathcal R(1-\varphi) \;(24) \\
    K &= P^-_k\mathbf H^T/R_{ee},\quad \hat\xi_k = \hat\xi^-_k + K(y_k - \hat y),\quad
    M = P^-_k - KR_{xe}^T \;(19), (20), (22)

and the standard form :math:`P = \mathrm{sym}(M)` or the Joseph form (App. D (44)) in the rank-one
arithmetic of the shared numpy update, :math:`P = \mathrm{sym}(M - (M\mathbf H^T - KN)K^T)`
(:func:`~tobitkf.filters._compiled_block._cov_update`). A reading that is censored
(:math:`\gamma_k = 0`) or whose :math:`R_{ee}` is not above the smallest normal number leaves the
prediction unchanged (K = 0), as the numpy path.

The failure term :math:`F_k` (``mode``): 0 ``"variance"`` :math:`\check\Lambda_h\mathcal C_hP^-_k\mathcal C_h^T`,
1 ``"literal"`` :math:`(\bar\Lambda_h^2+\check\Lambda_h)\mathcal C_hP^-_k\mathcal C_h^T`, 2 ``"second_moment"``
:math:`\check\Lambda_h(\mathcal C_hP^-_k\mathcal C_h^T + (\mathcal C_h\hat\xi^-_k)^2)`, 3 ``"lmmse_unconditional"``
the per-step value ``F_fixed[t]`` (the same for every run; the driver runs the deterministic recursion of
:math:`\mathfrak X_k`).

Covered (the dispatcher in ``protocol.py`` decides): time-invariant A, Q, C, R, every failure-term mode,
``covariance_update`` ``"joseph"`` and ``"standard"``, a given or default :math:`\gamma_k`,
``keep_augmented=False``. Everything else runs on numpy.

Outputs are staged for :data:`~tobitkf.filters._compiled_block.CHUNK` steps per block of runs and written run
by run into the preallocated ``(N, T, ...)`` arrays (as in the TKF kernel); an array of shape
``(N, 0, ...)`` is not requested: it gets no staging and is not written. The driver carves the
requested arrays from one allocation (:func:`tobitkf.filters.kalman.output_arrays`: fewer first-touch page
faults).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_block import _cov_update, _flush, _load, _mean_scratch, _stage_cov, _stage_shape, _store_last
from ._compiled_censored import lower_stats_block
from ._compiled_fading import aug_block_dims, shift_predict_block
from ._compiled_tobit import _INF, _TINY, censored_stats

__all__ = ["protocol_kernel", "N_EXTRAS", "EXTRA_NAMES"]

#: the per-step scalars of the ``ext`` output, in its last axis
EXTRA_NAMES = (
    "theta_bar",
    "inverse_mills",
    "trunc_var_factor",
    "expected_y",
    "innovation",
    "p_uncensored",
    "innovation_var",
)
N_EXTRAS = len(EXTRA_NAMES)
_FLOOR = 1e-12  # R (1 - phi) floored at 1e-12 R, as protocol._TINY


@njit(cache=True, error_model="numpy")
def _stage_vec(v, buf, tt, nb, lo, hi):
    """``buf[tt, i - lo, b] = v[i, b]`` for i in [lo, hi) (a staging buffer with no steps is skipped)."""
    if buf.shape[0] == 0:
        return
    for i in range(lo, hi):
        for b in range(nb):
            buf[tt, i - lo, b] = v[i, b]


@njit(cache=True, error_model="numpy", nogil=True)
def protocol_kernel(
    y,
    gam_in,
    sched,
    A,
    Qd,
    Cs,
    Hs,
    rs,
    lam_mean,
    lam_var,
    F_fixed,
    tau,
    mode,
    joseph,
    x0,
    P0,
    glx,
    glw,
    means,
    covs,
    pmeans,
    pcovs,
    amean,
    apmean,
    ext,
    x_last,
    P_last,
):
    """PBTKF-IMSF over ``N`` runs of ``T`` steps from the augmented state ``x0`` (N, nxi), ``P0`` (N, nxi, nxi).

    ``y`` (N, T) the received readings, ``gam_in`` (N, T) bool the :math:`\\gamma_k`; ``sched`` (T,) the
    0-based scheduled sensor of each step; ``A``/``Qd`` (n, n) the transition and process covariance of the
    top block; ``Cs``/``Hs`` (p, nxi) :math:`\\mathcal C_h` and :math:`\\bar\\Lambda_h\\mathcal C_h`; ``rs``
    (p,) :math:`\\mathcal R`; ``lam_mean``/``lam_var`` (p,); ``F_fixed`` (T,) the failure term of mode 3
    (any length otherwise); ``tau`` the threshold; ``mode`` the failure-term mode (module docstring);
    ``joseph`` the covariance form. Outputs: ``means``/``pmeans`` (N, T, n), ``covs``/``pcovs``
    (N, T, n, n) (block 0), ``amean``/``apmean`` (N, T, nxi), ``ext`` (N, T, N_EXTRAS) in the order of
    :data:`EXTRA_NAMES`; each of shape ``(N, 0, ...)`` when not requested. ``x_last`` (N, nxi) and
    ``P_last`` (N, nxi, nxi) receive the state after the last step. Returns whether every variance
    (diagonal entry) of ``P_last`` is finite (the check of ``kalman._finite_or_none``, which the online
    step then need not make in Python).
    """
    N, T = y.shape
    nxi = Cs.shape[1]
    n = A.shape[0]
    B, S = aug_block_dims(N, T)  # 64 runs per block, as the fading loop
    x, xp, _e, _yb = _mean_scratch(nxi, 1, B)
    P = np.empty((nxi, nxi, B))
    Pp = np.empty((nxi, nxi, B))
    X = np.empty((nxi, n, B))
    K = np.empty((nxi, 1, B))
    Rxe = np.empty((nxi, 1, B))
    MH = np.empty((nxi, 1, B))
    PC = np.empty((nxi, B))
    noise = np.zeros((1, 1, B))
    gone = np.ones((1, B))
    Hrow = np.empty((1, nxi))
    ee = np.empty(B)
    # the per-run scalars of a step, each a dot product over xi computed for the whole block at once
    # (the same sums in the same order as one run at a time, so the same rounding)
    zeta_b, HPH_b, CPC_b, xc_b = np.empty(B), np.empty(B), np.empty(B), np.empty(B)
    Ree_b = np.empty(B)
    good_b = np.empty(B, dtype=np.bool_)
    st_g, st_lam, st_tv, st_cm, st_cv = np.empty(B), np.empty(B), np.empty(B), np.empty(B), np.empty(B)
    lower = tau != -_INF  # the upper limit is infinite
    buf = np.empty((2, glx.shape[0]))
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_cov, s_pcov = np.empty(_stage_shape(covs, B, S)), np.empty(_stage_shape(pcovs, B, S))
    s_am, s_apm = np.empty(_stage_shape(amean, B, S)), np.empty(_stage_shape(apmean, B, S))
    s_ext = np.empty(_stage_shape(ext, B, S))
    want_x = ext.shape[1] > 0
    sd_all = np.sqrt(rs)
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x0, P0, r0, nb, x, P)
        for t in range(T):
            tt = t % S
            h = sched[t]
            r = rs[h]
            sd = sd_all[h]
            lm, lv = lam_mean[h], lam_var[h]
            for j in range(nxi):
                Hrow[0, j] = Hs[h, j]
            shift_predict_block(A, Qd, x, P, xp, Pp, X, nb)  # (17)-(18)
            _stage_vec(xp, s_pmean, tt, nb, 0, n)
            _stage_cov(Pp, s_pcov, tt, nb)
            _stage_vec(xp, s_apm, tt, nb, 0, nxi)
            # R_xe = P H^T, and P C^T for the failure term (the numpy path's row products)
            for i in range(nxi):
                for b in range(nb):
                    Rxe[i, 0, b] = 0.0
                    PC[i, b] = 0.0
                for k in range(nxi):
                    hk = Hs[h, k]
                    ck = Cs[h, k]
                    for b in range(nb):
                        Rxe[i, 0, b] += Pp[i, k, b] * hk
                        PC[i, b] += Pp[i, k, b] * ck
            for b in range(nb):
                zeta_b[b] = 0.0
                HPH_b[b] = 0.0
                CPC_b[b] = 0.0
                xc_b[b] = 0.0
            for j in range(nxi):
                hj = Hs[h, j]
                cj = Cs[h, j]
                for b in range(nb):
                    zeta_b[b] += xp[j, b] * hj
                    HPH_b[b] += Rxe[j, 0, b] * hj
                    CPC_b[b] += PC[j, b] * cj
                    xc_b[b] += xp[j, b] * cj
            if lower:  # the statistics of the block at once, vectorised
                lower_stats_block(zeta_b, sd, tau, nb, st_g, st_lam, st_tv, st_cm, st_cv)
            for b in range(nb):
                zeta, HPH, CPC, xc = zeta_b[b], HPH_b[b], CPC_b[b], xc_b[b]
                if lower:  # (13)-(16)
                    pg, lam, tv = st_g[b], st_lam[b], st_tv[b]
                else:
                    st = censored_stats(zeta, sd, tau, math.inf, glx, glw, buf)
                    pg, lam, tv = st[2], st[3], st[5]
                nz = max(tv, _FLOOR * r)  # R (1 - phi), floored
                if mode == 0:
                    F = lv * CPC
                elif mode == 1:
                    F = (lm * lm + lv) * CPC
                elif mode == 2:
                    F = lv * (CPC + xc * xc)
                else:
                    F = F_fixed[t]
                ntot = F + nz
                yhat = zeta + sd * lam  # (21), gamma = 1
                Ree = HPH + ntot  # (24)
                g = gam_in[r0 + b, t]
                good = g and Ree > _TINY
                noise[0, 0, b] = ntot
                ee[b] = y[r0 + b, t] - yhat if good else 0.0
                if want_x:
                    s_ext[tt, 0, b] = (tau - zeta) / sd
                    s_ext[tt, 1, b] = lam
                    s_ext[tt, 2, b] = 1.0 - nz / r
                    s_ext[tt, 3, b] = yhat if g else tau
                    s_ext[tt, 4, b] = y[r0 + b, t] - yhat if g else 0.0
                    s_ext[tt, 5, b] = pg
                    s_ext[tt, 6, b] = Ree if g else nz
                Ree_b[b] = Ree
                good_b[b] = good
            for i in range(nxi):
                for b in range(nb):
                    K[i, 0, b] = Rxe[i, 0, b] / Ree_b[b] if good_b[b] else 0.0
            # (19), (22): the mean; (20) or App. D (44): the covariance. A run left out has K = 0 and e = 0, so
            # this is the numpy path's arithmetic x + 0 e, P - 0 R_xe^T (the prediction, unchanged)
            for i in range(nxi):
                for b in range(nb):
                    x[i, b] = xp[i, b] + K[i, 0, b] * ee[b]
            _cov_update(Pp, K, Rxe, Hrow, gone, noise, joseph, P, MH, nb)
            _stage_vec(x, s_mean, tt, nb, 0, n)
            _stage_cov(P, s_cov, tt, nb)  # P or its diagonal (outputs=("var",))
            _stage_vec(x, s_am, tt, nb, 0, nxi)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_am, amean, r0, t0, nb, tt + 1)
                _flush(s_apm, apmean, r0, t0, nb, tt + 1)
                _flush(s_ext, ext, r0, t0, nb, tt + 1)
        _store_last(x, P, r0, nb, x_last, P_last)
    for b in range(N):
        for i in range(nxi):
            if not math.isfinite(P_last[b, i, i]):
                return False
    return True
