r"""The joint update of m = 2 or 3 channels in the runs-vectorised step (:mod:`tobitkf.filters._compiled_soa`),
the KF's and the TKF's, each operation as the compiled loop's and in its order (so that the two agree to
rounding); the step of one run ``b`` of a block, inlined into the loops over the block's runs of
:func:`~tobitkf.filters._compiled_soa._step` (the scratch layout of
:func:`~tobitkf.filters._compiled_soa_step._offsets`).

* Kalman filter: the rows :math:`C` (m, n) and :math:`R` (m, m) constant, :math:`R_{xe} = \bar PC^T`,
  :math:`R_{ee} = C\bar PC^T + R`, :math:`e = y - C\bar x`, a channel whose reading is NaN (or whose variance is
  not above the smallest normal number) left out (innovation 0, gain column 0), :math:`K` from the unit-diagonal
  :math:`(DR_{ee}D)Z = DR_{xe}^T`, :math:`D = \mathrm{diag}(R_{ee})^{-1/2}`, by elimination without pivoting
  (:func:`_kalman_joint_gain`, :func:`_joint_solve`; a run with a pivot not positive again with partial
  pivoting, :func:`_kalman_fallback`), then :math:`\hat x = \bar x + Ke`, :math:`P = \bar P - KR_{xe}^T` or
  Joseph's :math:`P = M - (MC^T - KR)K^T` (:func:`_kalman_joint_update`), in three loops over the block's runs.
* Tobit Kalman filter (all channels' statistics at the prior,
  :func:`~tobitkf.filters._compiled_tobit.tobit_update_block`): the prediction, :math:`h_l = \bar Pc_l^T`,
  :math:`C\bar PC^T` and the latent means :math:`\mu_l = c_l\bar x + (Du_k)_l` (:func:`_tkf_joint_moments`);
  each channel's statistics :math:`(\gamma_l, E(y_l), R_{uu,l})` at its own limits of the step and its own
  :math:`\sigma_l` (in :func:`~tobitkf.filters._compiled_soa._step`, the routes of one channel);
  :math:`R_{ee} = \Gamma C\bar PC^T\Gamma + \mathrm{diag}(R_{uu})`, :math:`R_{xe} = \bar PC^T\Gamma`,
  :math:`e = y - E(y)` (a channel whose reading is NaN, or whose variance is not above the smallest normal
  number, left out) and the KF's elimination (:func:`_tkf_joint_gain`, :func:`_joint_solve`, the fallback
  :func:`_kalman_fallback`); then :math:`\hat x = \bar x + Ke`, :math:`P = \bar P - KR_{xe}^T` or Joseph's
  :math:`P = M - (M C^T\Gamma - K\,\mathrm{diag}(R_{uu}))K^T` (:func:`_kalman_joint_update`): five loops over the
  block's runs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_block import _solve_gain
from ._compiled_soa_step import _TINY, SOA_BLOCK, _offsets, _predict_state

__all__: list[str] = []


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_joint_gain(W, cst, b, n, m):
    r"""The Kalman filter's prediction, innovation moments and joint gain of run ``b`` with ``m`` channels, each
    operation as the compiled loop's (:func:`~tobitkf.filters._compiled_loop._kalman_moments`,
    :func:`~tobitkf.filters._compiled_block._gain_block`), in its order: :math:`h_l = \bar Pc_l^T` (the column
    :math:`l` of :math:`R_{xe}`), :math:`R_{ee} = C\bar PC^T + R`, :math:`e = y - C\bar x` (0 for a channel
    whose reading is NaN or whose variance is not above the smallest normal number: it does not take part, its
    gain column is 0), and with :math:`D = \mathrm{diag}(R_{ee})^{-1/2}` the unit-diagonal system
    :math:`(DR_{ee}D)Z = DR_{xe}^T` by Gaussian elimination without pivoting, :math:`K = (DZ)^T`. A pivot not
    positive flags the run (row ``oBAD``) for :func:`_kalman_fallback`."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    nn = n * n
    oc, orr = 2 * nn, 2 * nn + m * n  # the rows C, then R, in the constants
    _predict_state(W, cst, b, n, m)
    for l in range(m):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += cst[oc + l * n + k] * W[(oPp + k * n + j) * BK + b]
            W[(oH + l * n + j) * BK + b] = acc
    for l in range(m):
        for q in range(m):
            acc = 0.0
            for k in range(n):
                acc += W[(oH + l * n + k) * BK + b] * cst[oc + q * n + k]
            W[(oS + l * m + q) * BK + b] = acc + cst[orr + l * m + q]
        acc = 0.0
        for j in range(n):
            acc += W[(oXP + j) * BK + b] * cst[oc + l * n + j]
        e = W[(oY + l) * BK + b] - acc
        good = W[(oS + l * m + l) * BK + b] > _TINY and not math.isnan(e)
        W[(oOK + l) * BK + b] = 1.0 if good else 0.0
        W[(oMU + l) * BK + b] = e if good else 0.0
    _joint_solve(W, b, n, m)


@njit(cache=True, error_model="numpy", inline="always")
def _joint_solve(W, b, n, m):
    r"""The joint gain of run ``b`` from :math:`R_{ee}` (rows ``oS``), :math:`R_{xe}` (column :math:`l` in rows
    ``oH + l n``) and the channels that take part (``oOK``), as the compiled loop's
    :func:`~tobitkf.filters._compiled_block._gain_block` in its order: :math:`D = \mathrm{diag}(R_{ee})^{-1/2}`
    over the channels that take part, the unit-diagonal :math:`(DR_{ee}D)Z = DR_{xe}^T` (the others' rows and
    columns those of the identity, their right-hand sides 0) by Gaussian elimination without pivoting,
    :math:`K = (DZ)^T` into ``oK``; a pivot not positive flags the run (``oBAD``) for :func:`_kalman_fallback`."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    for i in range(m):
        v = W[(oS + i * m + i) * BK + b]
        W[(oD + i) * BK + b] = 1.0 / math.sqrt(v) if (W[(oOK + i) * BK + b] != 0.0 and v > 0.0) else 1.0
    for i in range(m):
        oki = W[(oOK + i) * BK + b] != 0.0
        di = W[(oD + i) * BK + b]
        for j in range(m):
            both = oki and W[(oOK + j) * BK + b] != 0.0
            W[(oRW + i * m + j) * BK + b] = (
                W[(oS + i * m + j) * BK + b] * di * W[(oD + j) * BK + b] if both else (1.0 if i == j else 0.0)
            )
        for k in range(n):
            W[(oRH + i * n + k) * BK + b] = W[(oH + i * n + k) * BK + b] * di if oki else 0.0
    bad = False
    for c in range(m):
        piv = W[(oRW + c * m + c) * BK + b]
        ok_piv = piv > 0.0  # (False for NaN too)
        bad = bad or not ok_piv
        piv = piv if ok_piv else 1.0  # keeps the arithmetic finite; the run is redone
        W[(oRW + c * m + c) * BK + b] = piv
        for q in range(c + 1, m):
            f = W[(oRW + q * m + c) * BK + b] / piv
            W[(oRW + q * m + c) * BK + b] = f
            for j in range(c + 1, m):
                W[(oRW + q * m + j) * BK + b] -= f * W[(oRW + c * m + j) * BK + b]
            for k in range(n):
                W[(oRH + q * n + k) * BK + b] -= f * W[(oRH + c * n + k) * BK + b]
    for c in range(m - 1, -1, -1):
        for j in range(c + 1, m):
            for k in range(n):
                W[(oRH + c * n + k) * BK + b] -= W[(oRW + c * m + j) * BK + b] * W[(oRH + j * n + k) * BK + b]
        for k in range(n):
            W[(oRH + c * n + k) * BK + b] = W[(oRH + c * n + k) * BK + b] / W[(oRW + c * m + c) * BK + b]
    for i in range(n):
        for j in range(m):
            W[(oK + j * n + i) * BK + b] = W[(oRH + j * n + i) * BK + b] * W[(oD + j) * BK + b]
    W[oBAD * BK + b] = 1.0 if bad else 0.0


@njit(cache=True, error_model="numpy")
def _kalman_fallback(W, nb, n, m):
    """The gains of the block's runs flagged by :func:`_kalman_joint_gain` (a pivot not positive: a singular or
    non-finite :math:`R_{ee}`) again by :func:`~tobitkf.filters._compiled_block._solve_gain` (partial pivoting,
    raising like ``numpy.linalg.solve``), as the compiled loop does; its scratch made only when a run needs it."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    for b in range(nb):
        if W[oBAD * BK + b] != 0.0:
            Rs, Rxs, Ks = np.empty((m, m)), np.empty((n, m)), np.empty((n, m))
            Ws, ds, oks = np.empty((m, n)), np.empty(m), np.empty(m, dtype=np.bool_)
            for i in range(m):
                oks[i] = W[(oOK + i) * BK + b] != 0.0
                for j in range(m):
                    Rs[i, j] = W[(oS + i * m + j) * BK + b]
                for k in range(n):
                    Rxs[k, i] = W[(oH + i * n + k) * BK + b]
            _solve_gain(Rs, Rxs, oks, Ks, Ws, ds)
            for i in range(n):
                for j in range(m):
                    W[(oK + j * n + i) * BK + b] = Ks[i, j]


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_joint_update(W, cst, b, n, m, joseph, tobit):
    r"""The update of run ``b`` from its joint gain (:func:`_kalman_joint_gain`, :func:`_tkf_joint_gain`), as the
    compiled loop's (:func:`~tobitkf.filters._compiled_block._mean_update`,
    :func:`~tobitkf.filters._compiled_block._cov_update`) in its order: :math:`\hat x = \bar x + Ke`,
    :math:`M = \bar P - KR_{xe}^T` (the channel sums four terms at a time), and in the Joseph form
    :math:`P = M - (MH^T - KN)K^T`: for the Kalman filter (``tobit`` False) :math:`H = C`, :math:`N = R`; for the
    TKF :math:`H = \Gamma C`, :math:`\Gamma = \mathrm{diag}(\gamma)`, and :math:`N = \mathrm{diag}(R_{uu})`
    (rows ``oG``, ``oV``)."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    nn = n * n
    oc, orr = 2 * nn, 2 * nn + m * n
    m4 = m - m % 4
    for i in range(n):
        acc = W[(oXP + i) * BK + b]
        for l in range(m):
            acc += W[(oK + l * n + i) * BK + b] * W[(oMU + l) * BK + b]
        W[(oX + i) * BK + b] = acc
    for i in range(n):
        for j in range(i, n):
            acc = W[(oPp + i * n + j) * BK + b]
            for l in range(0, m4, 4):
                acc -= (
                    W[(oK + l * n + i) * BK + b] * W[(oH + l * n + j) * BK + b]
                    + W[(oK + (l + 1) * n + i) * BK + b] * W[(oH + (l + 1) * n + j) * BK + b]
                ) + (
                    W[(oK + (l + 2) * n + i) * BK + b] * W[(oH + (l + 2) * n + j) * BK + b]
                    + W[(oK + (l + 3) * n + i) * BK + b] * W[(oH + (l + 3) * n + j) * BK + b]
                )
            for l in range(m4, m):
                acc -= W[(oK + l * n + i) * BK + b] * W[(oH + l * n + j) * BK + b]
            W[(oP + i * n + j) * BK + b] = acc
            W[(oP + j * n + i) * BK + b] = acc
    if joseph:  # MH = M C^T - K R into the elimination's right-hand sides (free now), then P = M - MH K^T
        for i in range(n):
            for l in range(m):
                acc = 0.0
                for k in range(n):
                    acc += W[(oP + i * n + k) * BK + b] * cst[oc + l * n + k]
                if tobit:  # (M c_l^T) gamma_l - K_l R_uu,l: the off-diagonal noise terms are 0 (subtracted as
                    # exact zeros by the compiled loop: the same number)
                    acc = acc * W[(oG + l) * BK + b] - W[(oK + l * n + i) * BK + b] * W[(oV + l) * BK + b]
                else:
                    for q in range(m):
                        acc -= W[(oK + q * n + i) * BK + b] * cst[orr + q * m + l]
                W[(oRH + i * m + l) * BK + b] = acc
        for i in range(n):
            for j in range(i, n):
                acc = W[(oP + i * n + j) * BK + b]
                for l in range(m):
                    acc -= W[(oRH + i * m + l) * BK + b] * W[(oK + l * n + j) * BK + b]
                W[(oP + i * n + j) * BK + b] = acc
                W[(oP + j * n + i) * BK + b] = acc


@njit(cache=True, error_model="numpy", inline="always")
def _tkf_joint_moments(W, cst, b, n, m):
    r"""The TKF's prediction of run ``b`` with ``m`` channels and the moments its statistics need, as the
    compiled loop's (:func:`~tobitkf.filters._compiled_tobit.tobit_update_block`,
    :func:`~tobitkf.filters._compiled_block._innovation_moments`) in its order: :math:`h_l = \bar Pc_l^T`
    (rows ``oH + l n``), the unscaled :math:`C\bar PC^T` (rows ``oS``) and the latent readings' means
    :math:`\mu_l = c_l\bar x + (Du_k)_l` (rows ``oMU``)."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    oc = 2 * n * n
    _predict_state(W, cst, b, n, m)
    for l in range(m):
        acc = 0.0
        for j in range(n):
            acc += W[(oXP + j) * BK + b] * cst[oc + l * n + j]
        W[(oMU + l) * BK + b] = acc + W[(oDU + l) * BK + b]  # 0 without inputs (W starts zeroed)
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += cst[oc + l * n + k] * W[(oPp + k * n + j) * BK + b]
            W[(oH + l * n + j) * BK + b] = acc
    for l in range(m):
        for q in range(m):
            acc = 0.0
            for k in range(n):
                acc += W[(oH + l * n + k) * BK + b] * cst[oc + q * n + k]
            W[(oS + l * m + q) * BK + b] = acc


@njit(cache=True, error_model="numpy", inline="always")
def _tkf_joint_gain(W, cst, b, n, m):
    r"""The TKF's joint gain of run ``b`` from its moments (:func:`_tkf_joint_moments`) and its channels'
    statistics (rows ``oG`` :math:`\gamma_l`, ``oV`` :math:`R_{uu,l}`, ``oEY`` :math:`E(y_l)`), as the compiled
    loop's (:func:`~tobitkf.filters._compiled_block._innovation_moments`, ``_take_part``, ``_gain_block``) in its
    order (Miller (3.39)–(3.40)): :math:`R_{ee,lq} = (C\bar PC^T)_{lq}\gamma_l\gamma_q + \delta_{lq}R_{uu,l}`
    (rows ``oS``), :math:`R_{xe} = \bar PC^T\Gamma` (rows ``oH``), :math:`e_l = y_l - E(y_l)` (rows ``oMU``; 0
    for a channel that does not take part: a NaN reading, or a variance not above the smallest normal number),
    then :func:`_joint_solve`."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    for l in range(m):
        gl = W[(oG + l) * BK + b]
        for q in range(m):
            W[(oS + l * m + q) * BK + b] = W[(oS + l * m + q) * BK + b] * gl * W[(oG + q) * BK + b]
        W[(oS + l * m + l) * BK + b] += W[(oV + l) * BK + b]
        for j in range(n):
            W[(oH + l * n + j) * BK + b] = W[(oH + l * n + j) * BK + b] * gl
        e = W[(oY + l) * BK + b] - W[(oEY + l) * BK + b]
        good = W[(oS + l * m + l) * BK + b] > _TINY and not math.isnan(e)
        W[(oOK + l) * BK + b] = 1.0 if good else 0.0
        W[(oMU + l) * BK + b] = e if good else 0.0
    _joint_solve(W, b, n, m)
