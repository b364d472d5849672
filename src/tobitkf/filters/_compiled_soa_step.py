r"""The scratch layout of the runs-vectorised step (:mod:`tobitkf.filters._compiled_soa`) and its pieces for one
channel: the prediction, the reading's moments, the TKF's statistics of a channel and the KF/TKF gain update,
each the step of *one* run ``b`` of a block (inlined into the loops over the block's runs of
:func:`~tobitkf.filters._compiled_soa._step`, where LLVM vectorises them).

Layout: a block of :data:`SOA_BLOCK` runs in one scratch array ``W``, row ``r`` of run ``b`` at
``W[r * SOA_BLOCK + b]`` (the rows of :func:`_offsets`): means ``x[i, b]`` (n, B), covariances ``P[i, j, b]``
(n, n, B) (symmetric, both triangles stored: the output staging of :mod:`tobitkf.filters._compiled_block` reads
them); the constants in ``cst``: A (n x n), sym(Q) (n x n), the rows C (m x n), then the KF's R (m x m) or the
TKF's standard deviations (m). The step of run b, with one channel (m = 1), row :math:`c` (the measurement
matrix),

.. math::

    \bar x = A\hat x + B^uu_k,\quad \bar P = A P A^T + Q,\quad h = \bar P c^T,\quad s = c\bar Pc^T,
    \quad \mu = c\bar x + Du_k,

* Kalman filter (Miller (2015) (2.3)–(2.6)): :math:`e = y - \mu`, :math:`R_{ee} = s + R`, :math:`R_{xe} = h`
  (:func:`_kalman_step`);
* Tobit Kalman filter (Miller (3.37)–(3.41), all statistics at the prior): the censored-normal statistics of
  :math:`\mu` and :math:`\sigma` at the step's limits, :math:`(\gamma, E(y), R_{uu})` (computed in
  :func:`~tobitkf.filters._compiled_soa._step`);
  :math:`e = y - E(y)`, :math:`R_{ee} = \gamma^2 s + R_{uu}`, :math:`R_{xe} = \gamma h` (:func:`_update_of`);

then :math:`K = R_{xe}/R_{ee}`, :math:`\hat x = \bar x + Ke`, :math:`P = \bar P - KR_{xe}^T` (standard form) or the
Joseph form :math:`P = M - (MH^T - KR)K^T`, :math:`M = \bar P - KR_{xe}^T`, :math:`H = \gamma c` (as
:func:`~tobitkf.filters._compiled_block._cov_update`), :func:`_gain_update`. A reading that is NaN, or an
innovation variance not above the smallest normal number, leaves the run's prediction unchanged (the compiled
loop's rule). Every sum is taken in the compiled loop's order, so that the two agree to rounding (and the
reading's mean, which picks the route of the window statistics, to the bit).

The rows are a plain tuple of numbers unpacked in each piece (``oX, oP, ... = _offsets(n, m)``): numba folds them
to constants at every inlined call.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_censored import _one_sided_at, noise_term

__all__ = ["SOA_BLOCK", "SOA_MAX_N", "SIZES", "SOA_MAX_M", "CHANS", "KALMAN", "CENSORED_ADF", "CENSORED_ADF_STATS",
           "TOBIT_ANY", "KINDS"]  # fmt: skip

SOA_BLOCK = 128  # runs per block: a multiple of the vector width (8 doubles with AVX-512)
SOA_MAX_N = 4  # largest state covered: every state loop is unrolled (n^3 products per step in straight-line code)
#: the state size n as a type: a tuple of n zeros, whose length numba folds to a constant (one specialisation of
#: :func:`~tobitkf.filters._compiled_soa.soa_loop` per n, found by the ordinary dispatch on the argument types at
#: every call)
SIZES = {n: (0,) * n for n in range(1, SOA_MAX_N + 1)}
SOA_MAX_M = 3  # most channels of the joint updates (one channel for the assumed-density filter)
#: the number of channels m as a type, likewise (a tuple of m zeros: one specialisation per m)
CHANS = {m: (0,) * m for m in range(1, SOA_MAX_M + 1)}
#: the updates of :func:`~tobitkf.filters._compiled_soa.soa_loop`: the KF, the censored assumed-density filter
#: without or with its log-likelihood and P(uncensored), the TKF (any limits)
KALMAN, CENSORED_ADF, CENSORED_ADF_STATS, TOBIT_ANY = 0, 2, 3, 4
#: the update as a type, likewise: a tuple of ``update`` zeros (one specialisation per update). The step
#: branches on ``len(kind) == update`` directly: numba rewrites the length of a tuple argument as a constant and
#: prunes the branches of the other updates before typing, so that each specialisation holds only its update's
#: code (compared through a variable, every update's code was compiled into every version: the KF's at n = 2 took
#: 127 s to compile on a loaded machine, pruned 20 s)
KINDS = {k: (0,) * k for k in (KALMAN, CENSORED_ADF, CENSORED_ADF_STATS, TOBIT_ANY)}
_TINY = float(np.finfo(np.float64).tiny)
_INF = math.inf


@njit(cache=True, error_model="numpy", inline="always")
def _offsets(n, m):
    """The rows of the scratch ``W`` of :func:`~tobitkf.filters._compiled_soa.soa_loop` (each :data:`SOA_BLOCK`
    numbers) for state size ``n`` and ``m`` channels: state, prediction, scratch, the step's inputs and statistics
    (a row per channel, ``h`` and the gain ``n`` rows per channel, channel ``l``'s at ``oH + l * n``), the joint
    gain's elimination (``m > 1``: :math:`DR_{ee}D` by rows, the right-hand sides, the scaling, the channels that
    take part and a run's flag for the pivoting fallback); the last is the number of rows."""
    nn = n * n
    oX, oP = 0, n
    oXP = oP + nn
    oPp = oXP + n
    oAP = oPp + nn
    oH = oAP + nn
    oK = oH + n * m
    oY = oK + n * m
    oBU = oY + m
    oDU = oBU + n
    oG = oDU + m
    oEY = oG + m
    oCL = oEY + m
    oLL = oCL + m
    oMU = oLL + 1  # the split step (TOBIT_ANY): the moments mu, s and the noise term between its loops
    oS = oMU + m
    oV = oS + m * m
    oSL = oV + m  # 1: the run's window statistics take another route than the direct formulas (a row per channel)
    oRW = oSL + m  # the joint gain (m > 1): D R_ee D (m x m), the right-hand sides D R_xe^T (m x n), D (m)
    oRH = oRW + m * m
    oD = oRH + m * n
    oOK = oD + m  # 1.0: the channel takes part
    oBAD = oOK + m  # 1.0: a pivot not positive, the run's gain again with partial pivoting
    return (
        oX,
        oP,
        oXP,
        oPp,
        oAP,
        oH,
        oK,
        oY,
        oBU,
        oDU,
        oG,
        oEY,
        oCL,
        oLL,
        oMU,
        oS,
        oV,
        oSL,
        oRW,
        oRH,
        oD,
        oOK,
        oBAD,
        oBAD + 1,
    )


@njit(cache=True, error_model="numpy", inline="always")
def _predict_state(W, cst, b, n, m):
    r"""The prediction of run ``b`` of the block, :math:`\bar x = A\hat x + B^uu_k`, :math:`\bar P = APA^T + Q`
    (upper triangle, mirrored), into ``W`` (the layout of ``m`` channels)."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    BK = SOA_BLOCK
    nn = n * n
    # every sum in the compiled loop's order (its terms from 0, the inputs and Q added last): the same rounding,
    # so that the reading's mean, which picks the route of the window statistics, is the loop's to the bit
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += cst[i * n + k] * W[(oX + k) * BK + b]
        W[(oXP + i) * BK + b] = acc + W[(oBU + i) * BK + b]  # 0 without inputs (W starts zeroed)
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += cst[i * n + k] * W[(oP + k * n + j) * BK + b]
            W[(oAP + i * n + j) * BK + b] = acc
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(n):
                acc += W[(oAP + i * n + k) * BK + b] * cst[j * n + k]
            acc += cst[nn + i * n + j]
            W[(oPp + i * n + j) * BK + b] = acc
            W[(oPp + j * n + i) * BK + b] = acc


@njit(cache=True, error_model="numpy", inline="always")
def _predict_moments(W, cst, b, n):
    r"""The prediction of run ``b`` of the block (:func:`_predict_state`, one channel) and the moments of its
    reading: :math:`h = \bar Pc^T` into ``W``, returns :math:`(\mu, s) = (c\bar x + Du_k, c\bar Pc^T)`."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, 1)
    )
    BK = SOA_BLOCK
    nn = n * n
    _predict_state(W, cst, b, n, 1)
    mu = 0.0
    for i in range(n):
        mu += W[(oXP + i) * BK + b] * cst[2 * nn + i]
    mu += W[oDU * BK + b]
    sv = 0.0
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += W[(oPp + i * n + k) * BK + b] * cst[2 * nn + k]
        W[(oH + i) * BK + b] = acc
        sv += cst[2 * nn + i] * acc
    return mu, sv


@njit(cache=True, error_model="numpy", inline="always")
def _one_sided_tkf(mu, sd, lim, sg, noise_code):
    """The TKF's ``(gamma, R_uu, E(y))`` of a reading with latent mean ``mu``, standard deviation ``sd`` and one
    finite limit: ``sg`` 1 a lower limit ``lim``, -1 an upper one (``lim`` then the lower limit -hi of -y)."""
    ms = sg * mu
    _plo, g, _lam, tmean, tvar, cm, cvar = _one_sided_at(ms, sd, lim)
    return g, noise_term(noise_code, ms, g, tmean, tvar, cvar), sg * cm


@njit(cache=True, error_model="numpy", inline="always")
def _gain_update(W, cst, b, n, yb, g, v, ey, sv, joseph):
    r"""The KF/TKF update of run ``b`` from its prediction and :math:`h` in ``W``: :math:`e = y - E(y)`,
    :math:`R_{ee} = \gamma^2 s + R_{uu}`, :math:`K = \gamma h/R_{ee}`, :math:`\hat x = \bar x + Ke`,
    :math:`P = \bar P - \gamma Kh^T` (standard form) or Joseph's (module docstring); no change for a NaN
    reading or :math:`R_{ee}` not above the smallest normal number."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, 1)
    )
    BK = SOA_BLOCK
    nn = n * n
    # the compiled loop's operations in its order (_innovation_moments, _gain): the same rounding
    e = yb - ey
    ree = sv * g * g + v
    good = ree > _TINY and not math.isnan(e)
    e = e if good else 0.0
    r = ree if good else 1.0
    for i in range(n):
        rxe = W[(oH + i) * BK + b] * g
        kgi = (rxe if good else 0.0) / r
        W[(oK + i) * BK + b] = kgi
        W[(oX + i) * BK + b] = W[(oXP + i) * BK + b] + kgi * e
    for i in range(n):
        for j in range(i, n):
            pij = W[(oPp + i * n + j) * BK + b] - W[(oK + i) * BK + b] * (g * W[(oH + j) * BK + b])
            W[(oP + i * n + j) * BK + b] = pij
            W[(oP + j * n + i) * BK + b] = pij
    if joseph:
        # P = M - (M H^T - K R) K^T, M the standard form's result just computed, H = g c
        for i in range(n):
            acc = 0.0
            for k in range(n):
                acc += W[(oP + i * n + k) * BK + b] * cst[2 * nn + k]
            W[(oAP + i) * BK + b] = acc * g - W[(oK + i) * BK + b] * v
        for i in range(n):
            for j in range(i, n):
                pij = W[(oP + i * n + j) * BK + b] - W[(oAP + i) * BK + b] * W[(oK + j) * BK + b]
                W[(oP + i * n + j) * BK + b] = pij
                W[(oP + j * n + i) * BK + b] = pij


@njit(cache=True, error_model="numpy", inline="always")
def _update_of(W, cst, b, n, joseph):
    """The split TKF step's update of run ``b`` from the statistics its second loop left in ``W``."""
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, 1)
    )
    BK = SOA_BLOCK
    yb, g, v, ey, sv = W[oY * BK + b], W[oG * BK + b], W[oV * BK + b], W[oEY * BK + b], W[oS * BK + b]
    _gain_update(W, cst, b, n, yb, g, v, ey, sv, joseph)


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_step(W, cst, b, n, rn, joseph):
    """The Kalman filter's whole step of run ``b`` (noise variance ``rn``)."""
    mu, sv = _predict_moments(W, cst, b, n)
    _gain_update(W, cst, b, n, W[_offsets(n, 1)[7] * SOA_BLOCK + b], 1.0, rn, mu, sv, joseph)
