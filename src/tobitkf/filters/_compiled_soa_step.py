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
  :math:`\mu` and :math:`\sigma` at the step's limits, :math:`(\gamma, E(y), R_{uu})` and the inverse Mills ratio
  :math:`\lambda` (:func:`_channel_stats`); :math:`e = y - E(y)`, :math:`R_{ee} = \gamma^2 s + R_{uu}`,
  :math:`R_{xe} = \gamma h` (:func:`_update_of`);

then :math:`K = R_{xe}/R_{ee}`, :math:`\hat x = \bar x + Ke`, :math:`P = \bar P - KR_{xe}^T` (standard form) or the
Joseph form :math:`P = M - (MH^T - KR)K^T`, :math:`M = \bar P - KR_{xe}^T`, :math:`H = \gamma c` (as
:func:`~tobitkf.filters._compiled_block._cov_update`), :func:`_gain_update`. A reading that is NaN, or an
innovation variance not above the smallest normal number, leaves the run's prediction unchanged (the compiled
loop's rule). Every sum is taken in the compiled loop's order, so that the two agree to rounding (and the
reading's mean, which picks the route of the window statistics, to the bit).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from ._compiled_censored import _assemble, _one_sided_at, censored_stats, noise_term, window_direct

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
#: without or with its log-likelihood and P(uncensored), the TKF (any limits; also the fading TKF of order 0)
KALMAN, CENSORED_ADF, CENSORED_ADF_STATS, TOBIT_ANY = 0, 2, 3, 4
#: the update as a type, likewise: a tuple of ``update`` zeros (one specialisation per update). The step
#: branches on ``len(kind) == update`` directly: numba rewrites the length of a tuple argument as a constant and
#: prunes the branches of the other updates before typing, so that each specialisation holds only its update's
#: code (compared through a variable, every update's code was compiled into every version: the KF's at n = 2 took
#: 127 s to compile on a loaded machine, pruned 20 s)
KINDS = {k: (0,) * k for k in (KALMAN, CENSORED_ADF, CENSORED_ADF_STATS, TOBIT_ANY)}
_TINY = float(np.finfo(np.float64).tiny)
_INF = math.inf

#: the first rows of the scratch's parts (:func:`_offsets`), by name
_Rows = namedtuple("_Rows", "X P XP Pp AP H K Y BU DU G EY CL LL MU S V SL RW RH D OK BAD LM rows")


@njit(cache=True, error_model="numpy", inline="always")
def _offsets(n, m):
    """The rows of the scratch ``W`` (each :data:`SOA_BLOCK` numbers) for state size ``n`` and ``m`` channels, a
    :data:`_Rows` of the first row of each part: the state ``X`` (n) and ``P`` (n x n), the prediction ``XP``,
    ``Pp``, the scratch ``AP`` (n x n), per channel ``h`` and the gain (``H``, ``K``: n rows per channel, channel
    ``l``'s at ``H + l * n``), the step's inputs ``Y`` (m), ``BU`` (n), ``DU`` (m) and statistics ``G`` (γ),
    ``EY`` (E(y)), the given classes ``CL`` (m each), the log-likelihood ``LL`` (1), the moments between the
    split step's loops ``MU`` (m), ``S`` (m x m), ``V`` (m, the noise term), ``SL`` (m; 1: the window statistics
    take another route than the direct formulas), the joint gain's elimination (``m > 1``: :math:`DR_{ee}D` by
    rows ``RW``, the right-hand sides ``RH`` (m x n), the scaling ``D`` (m), ``OK`` (m; 1: the channel takes
    part), ``BAD`` (1; a pivot not positive: the run's gain again with partial pivoting)), the inverse Mills
    ratios ``LM`` (m); ``rows`` the number of rows."""
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
    oMU = oLL + 1
    oS = oMU + m
    oV = oS + m * m
    oSL = oV + m
    oRW = oSL + m
    oRH = oRW + m * m
    oD = oRH + m * n
    oOK = oD + m
    oBAD = oOK + m
    oLM = oBAD + 1
    return _Rows(oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK,
                 oBAD, oLM, oLM + m)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def _predict_state(W, cst, b, n, m):
    r"""The prediction of run ``b`` of the block, :math:`\bar x = A\hat x + B^uu_k`, :math:`\bar P = APA^T + Q`
    (upper triangle, mirrored), into ``W`` (the layout of ``m`` channels)."""
    o = _offsets(n, m)
    BK = SOA_BLOCK
    nn = n * n
    # every sum in the compiled loop's order (its terms from 0, the inputs and Q added last): the same rounding,
    # so that the reading's mean, which picks the route of the window statistics, is the loop's to the bit
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += cst[i * n + k] * W[(o.X + k) * BK + b]
        W[(o.XP + i) * BK + b] = acc + W[(o.BU + i) * BK + b]  # 0 without inputs (W starts zeroed)
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += cst[i * n + k] * W[(o.P + k * n + j) * BK + b]
            W[(o.AP + i * n + j) * BK + b] = acc
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(n):
                acc += W[(o.AP + i * n + k) * BK + b] * cst[j * n + k]
            acc += cst[nn + i * n + j]
            W[(o.Pp + i * n + j) * BK + b] = acc
            W[(o.Pp + j * n + i) * BK + b] = acc


@njit(cache=True, error_model="numpy", inline="always")
def _predict_moments(W, cst, b, n):
    r"""The prediction of run ``b`` of the block (:func:`_predict_state`, one channel) and the moments of its
    reading: :math:`h = \bar Pc^T` into ``W``, returns :math:`(\mu, s) = (c\bar x + Du_k, c\bar Pc^T)`."""
    o = _offsets(n, 1)
    BK = SOA_BLOCK
    nn = n * n
    _predict_state(W, cst, b, n, 1)
    mu = 0.0
    for i in range(n):
        mu += W[(o.XP + i) * BK + b] * cst[2 * nn + i]
    mu += W[o.DU * BK + b]
    sv = 0.0
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += W[(o.Pp + i * n + k) * BK + b] * cst[2 * nn + k]
        W[(o.H + i) * BK + b] = acc
        sv += cst[2 * nn + i] * acc
    return mu, sv


@njit(cache=True, error_model="numpy", inline="always")
def _one_sided_tkf(mu, sd, lim, sg, noise_code):
    """The TKF's ``(gamma, R_uu, E(y), lambda)`` of a reading with latent mean ``mu``, standard deviation ``sd`` and one
    finite limit: ``sg`` 1 a lower limit ``lim``, -1 an upper one (``lim`` then the lower limit -hi of -y)."""
    ms = sg * mu
    _plo, g, lam, tmean, tvar, cm, cvar = _one_sided_at(ms, sd, lim)
    return g, noise_term(noise_code, ms, g, tmean, tvar, cvar), sg * cm, sg * lam


@njit(cache=True, error_model="numpy", inline="always")
def _channel_stats(W, l, n, m, nb, sd, lo, hi, noise_code, glx, glw, buf):
    r"""The TKF's statistics of channel ``l`` for the block's ``nb`` runs (loops over the runs, each vectorised),
    from the latent means :math:`\mu` (row ``MU + l`` of :func:`_offsets` (n, m)), the standard deviation ``sd``
    and the step's limits ``lo`` < ``hi``: :math:`\gamma` into row ``G + l``, :math:`E(y)` into ``EY + l``, the
    noise term of ``noise_code`` (:data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`) into ``V + l``, the
    inverse Mills ratio into ``LM + l``. Two finite limits: the direct formulas of
    :func:`~tobitkf.filters._compiled_censored.window_direct` for all runs, then the few runs whose window needs
    another route (narrower than :math:`\sigma`, or in a tail) by
    :func:`~tobitkf.filters._compiled_censored.censored_stats` one by one (the compiled loop's numbers); one
    finite limit by :func:`~tobitkf.filters._compiled_censored._one_sided_at` (an upper limit as the lower limit
    -hi of -y); none: the latent reading's moments."""
    o = _offsets(n, m)
    BK = SOA_BLOCK
    rG, rEY, rMU, rV, rSL, rLM = (
        (o.G + l) * BK,
        (o.EY + l) * BK,
        (o.MU + l) * BK,
        (o.V + l) * BK,
        (o.SL + l) * BK,
        (o.LM + l) * BK,
    )
    if lo != -_INF and hi != _INF:  # two finite limits: the direct formulas, vectorised
        for b in range(nb):
            mu = W[rMU + b]
            other, _a2, _b2, _fl, _os, p_lo, p_hi, gam, lam, zvar = window_direct(mu, sd, lo, hi)
            st = _assemble(mu, sd, lo, hi, p_lo, p_hi, gam, lam, zvar)
            W[rG + b] = st[2]
            W[rV + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
            W[rEY + b] = st[6]
            W[rLM + b] = st[3]
            W[rSL + b] = 1.0 if other else 0.0
        for b in range(nb):  # the runs off the direct route: the compiled loop's statistics
            if W[rSL + b] != 0.0:
                mu = W[rMU + b]
                st = censored_stats(mu, sd, lo, hi, glx, glw, buf)
                W[rG + b] = st[2]
                W[rV + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
                W[rEY + b] = st[6]
                W[rLM + b] = st[3]
    elif lo != -_INF or hi != _INF:
        upper = lo == -_INF
        sg = -1.0 if upper else 1.0
        lim = sg * (hi if upper else lo)
        for b in range(nb):
            g, v, cm, lam = _one_sided_tkf(W[rMU + b], sd, lim, sg, noise_code)
            W[rG + b] = g
            W[rV + b] = v
            W[rEY + b] = cm
            W[rLM + b] = lam
    else:  # no limit: the latent reading's moments
        for b in range(nb):
            W[rG + b] = 1.0
            W[rV + b] = sd * sd
            W[rEY + b] = W[rMU + b]
            W[rLM + b] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _gain_update(W, cst, b, n, yb, g, v, ey, sv, joseph):
    r"""The KF/TKF update of run ``b`` from its prediction and :math:`h` in ``W``: :math:`e = y - E(y)`,
    :math:`R_{ee} = \gamma^2 s + R_{uu}`, :math:`K = \gamma h/R_{ee}`, :math:`\hat x = \bar x + Ke`,
    :math:`P = \bar P - \gamma Kh^T` (standard form) or Joseph's (the module docstring); no change for a NaN
    reading or :math:`R_{ee}` not above the smallest normal number."""
    o = _offsets(n, 1)
    BK = SOA_BLOCK
    nn = n * n
    # the compiled loop's operations in its order (_innovation_moments, _gain): the same rounding
    e = yb - ey
    ree = sv * g * g + v
    good = ree > _TINY and not math.isnan(e)
    e = e if good else 0.0
    r = ree if good else 1.0
    for i in range(n):
        rxe = W[(o.H + i) * BK + b] * g
        kgi = (rxe if good else 0.0) / r
        W[(o.K + i) * BK + b] = kgi
        W[(o.X + i) * BK + b] = W[(o.XP + i) * BK + b] + kgi * e
    for i in range(n):
        for j in range(i, n):
            pij = W[(o.Pp + i * n + j) * BK + b] - W[(o.K + i) * BK + b] * (g * W[(o.H + j) * BK + b])
            W[(o.P + i * n + j) * BK + b] = pij
            W[(o.P + j * n + i) * BK + b] = pij
    if joseph:
        # P = M - (M H^T - K R) K^T, M the standard form's result just computed, H = g c
        for i in range(n):
            acc = 0.0
            for k in range(n):
                acc += W[(o.P + i * n + k) * BK + b] * cst[2 * nn + k]
            W[(o.AP + i) * BK + b] = acc * g - W[(o.K + i) * BK + b] * v
        for i in range(n):
            for j in range(i, n):
                pij = W[(o.P + i * n + j) * BK + b] - W[(o.AP + i) * BK + b] * W[(o.K + j) * BK + b]
                W[(o.P + i * n + j) * BK + b] = pij
                W[(o.P + j * n + i) * BK + b] = pij


@njit(cache=True, error_model="numpy", inline="always")
def _update_of(W, cst, b, n, joseph):
    """The split TKF step's update of run ``b`` from the statistics its second loop left in ``W``."""
    o = _offsets(n, 1)
    BK = SOA_BLOCK
    yb, g, v, ey, sv = W[o.Y * BK + b], W[o.G * BK + b], W[o.V * BK + b], W[o.EY * BK + b], W[o.S * BK + b]
    _gain_update(W, cst, b, n, yb, g, v, ey, sv, joseph)


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_step(W, cst, b, n, rn, joseph):
    """The Kalman filter's whole step of run ``b`` (noise variance ``rn``)."""
    mu, sv = _predict_moments(W, cst, b, n)
    _gain_update(W, cst, b, n, W[_offsets(n, 1).Y * SOA_BLOCK + b], 1.0, rn, mu, sv, joseph)
