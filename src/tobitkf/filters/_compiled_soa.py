r"""The Kalman filter and the Tobit Kalman filter with the whole step vectorised over the runs (SIMD over the batch).

:func:`~tobitkf.filters._compiled_loop.compiled_loop` keeps a block's runs on the last axis too, but writes the
step as some tens of short loops over the runs, one per product, each storing its result for the next: at
n = 2, m = 1 most of a step is the loops' set-up and the stores between them. Here the state size n is a
compile-time constant (numba ``literally``: one specialisation per n), so that every loop over the state is
unrolled and the *whole* step of one run, predict, censored statistics, gain and covariance update, is straight-line
code in the body of a single loop over the runs of a block, which LLVM vectorises (AVX2: 4 runs per
instruction, AVX-512: 8). Checked with ``inspect_asm`` on a fresh compile (n = 2, AVX-512 machine): the
step's loop is emitted on 8-lane ``zmm`` registers (157 ``vmulpd``, 118 ``vaddpd``, 4 ``vdivpd``, the exponential's
``vrndscalepd``/``vcvttpd2qq`` and one ``vgatherqpd`` for its table of powers of two), next to the scalar copy LLVM
keeps for the remainder of a block.

Layout: a block of :data:`SOA_BLOCK` runs, means ``x[i, b]`` (n, B), covariances ``P[i, j, b]`` (n, n, B)
(symmetric, both triangles stored: the output staging of :mod:`tobitkf.filters._compiled_block` reads them),
readings (N, T, m) as given. The step of run b, with one channel (m = 1), row :math:`c` (the measurement matrix),

.. math::

    \bar x = A\hat x + B^uu_k,\quad \bar P = A P A^T + Q,\quad h = \bar P c^T,\quad s = c\bar Pc^T,

* Kalman filter (Miller (2015) (2.3)–(2.6)): :math:`e = y - c\bar x`, :math:`R_{ee} = s + R`,
  :math:`R_{xe} = h`;
* Tobit Kalman filter (Miller (3.37)–(3.41), all statistics at the prior): the censored-normal statistics of
  :math:`\mu = c\bar x + Du_k` and :math:`\sigma` at the channel's one finite limit,
  :math:`(\gamma, E(y), R_{uu})`, from :func:`~tobitkf.filters._compiled_censored._one_sided_at` (the
  branch-free routes written for vectorisation, imported: the same numbers as the compiled loop's statistics),
  :math:`e = y - E(y)`, :math:`R_{ee} = \gamma^2 s + R_{uu}`, :math:`R_{xe} = \gamma h`;

then :math:`K = R_{xe}/R_{ee}`, :math:`\hat x = \bar x + Ke`, :math:`P = \bar P - KR_{xe}^T` (standard form) or the
Joseph form :math:`P = M - (MH^T - KR)K^T`, :math:`M = \bar P - KR_{xe}^T`, :math:`H = \gamma c` (as
:func:`~tobitkf.filters._compiled_block._cov_update`). A reading that is NaN, or an innovation variance not above
the smallest normal number, leaves the run's prediction unchanged (the compiled loop's rule).

Covered (:func:`soa_covers`): one channel, n from 1 to :data:`SOA_MAX_N`, the standard and Joseph forms; for the
TKF one finite limit per step (lower or upper; the limits may change with the step), every noise term, the
input terms :math:`B^uu_k`, :math:`Du_k`; for the KF a covariance per run (with one prior covariance shared by
the runs, nothing missing, the compiled loop computes the covariance once and is faster). Anything else runs
:func:`~tobitkf.filters._compiled_loop.compiled_loop`. The entries :func:`soa_kalman_loop` and
:func:`soa_tobit_loop` take the arguments of :mod:`tobitkf.filters._compiled_entries`' ``kalman_loop`` and
``tobit_loop`` and fill the same outputs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import literally, njit

from ._compiled_block import _flush, _stage, _stage_shape, _store_last
from ._compiled_censored import _one_sided_at

__all__ = [
    "SOA_BLOCK",
    "SOA_MAX_N",
    "soa_covers",
    "soa_kalman_loop",
    "soa_tobit_loop",
    "soa_loop",
    "soa_run",
    "tobit_entry",
    "kalman_entry",
]

SOA_BLOCK = 128  # runs per block: a multiple of the vector width (8 doubles with AVX-512)
SOA_MAX_N = 4  # largest state covered: every state loop is unrolled (n^3 products per step in straight-line code)
_CHUNK = 64  # steps staged per flush (as the compiled loop's CHUNK)
_STAGE_BYTES = 1 << 18
_TINY = float(np.finfo(np.float64).tiny)
_INF = math.inf


def soa_covers(kalman: bool, m: int, n: int, P0_rows: int, N: int, lo=None, hi=None) -> bool:
    """Whether :func:`soa_loop` covers a call: one channel (``m == 1``), ``1 <= n <=`` :data:`SOA_MAX_N`; the KF
    with a covariance per run (``P0_rows == N``; one shared covariance runs the compiled loop's shared-gain
    path), the TKF with exactly one finite limit in every row of ``lo``/``hi`` (TL, 1)."""
    if m != 1 or not 1 <= n <= SOA_MAX_N:
        return False
    if kalman:
        return P0_rows == N or N == 1
    if lo is None or hi is None:
        return False
    lo_inf = np.isneginf(np.asarray(lo))
    hi_inf = np.isposinf(np.asarray(hi))
    return bool(np.all(lo_inf != hi_inf)) and not bool(np.isnan(lo).any() or np.isnan(hi).any())


def tobit_entry(default, m: int, n: int, lo, hi):
    """The TKF's whole-record entry: :func:`soa_tobit_loop` when :func:`soa_covers` the call (one channel, n up
    to :data:`SOA_MAX_N`, one finite limit in every row of ``lo``/``hi``), else ``default`` (the compiled
    loop's ``tobit_loop``); both take the same arguments."""
    return soa_tobit_loop if soa_covers(False, m, n, 0, 0, lo, hi) else default


def kalman_entry(default, m: int, n: int, P0_rows: int, N: int):
    """The KF's whole-record entry: :func:`soa_kalman_loop` when :func:`soa_covers` the call, else ``default``
    (the compiled loop's ``kalman_loop``); both take the same arguments."""
    return soa_kalman_loop if soa_covers(True, m, n, P0_rows, N) else default


@njit(cache=True, error_model="numpy", nogil=True)
def soa_loop(
    n,
    tobit,
    y,
    A,
    Qd,
    C,
    rnoise,
    lo,
    hi,
    bu,
    du,
    noise_code,
    joseph,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    r"""The KF (``tobit`` False) or the TKF (True) over N runs x T steps, one channel, state size ``n`` (an int,
    made a compile-time constant: one specialisation per n); fills the outputs (module docstring).

    ``y`` (N, T, 1) readings (NaN: missing); ``A``, ``Qd`` (n, n); ``C`` (1, n); ``rnoise`` the KF's noise
    variance R or the TKF's standard deviation σ; ``lo``, ``hi`` (TL, 1) the TKF's limits, row
    ``min(t, TL - 1)``, one of them finite; ``bu`` (N, T, n), ``du`` (N, T, 1) the input terms (T axis 0: none);
    ``noise_code`` of :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`; ``joseph`` the Joseph form; ``x0`` (N, n),
    ``P0`` (N or 1, n, n). Outputs as :func:`~tobitkf.filters._compiled_loop.compiled_loop` (T axis 0: not
    written): ``means``, ``pmeans`` (N, T, n), ``covs`` (N, T, n, n) or (N, T, n, 1), ``pcovs`` (N, T, n, n),
    ``pu``, ``ey`` (N, T, 1) (the TKF's P(uncensored) and E(y)), ``x_last`` (N, n), ``P_last`` (N, n, n).

    Why one scratch array ``W`` with rows :data:`SOA_BLOCK` apart, indexed ``W[row * SOA_BLOCK + b]``, and the
    constants in another (``cst``): LLVM vectorises a loop only when it can prove that its stores do not
    overlap its loads; between separately allocated numba arrays it cannot, and the run-time overlap checks
    it would need for a dozen arrays exceed its limit (the loop stayed scalar: ~1300 scalar double
    instructions against 35 vector ones). Rows of one array a compile-time constant apart are independent
    by construction. The readings, the input terms and the outputs move between ``W`` and their arrays in
    short loops of their own."""
    literally(n)
    N, T, m = y.shape
    BK = SOA_BLOCK
    S = max(1, min(_CHUNK, max(T, 1), _STAGE_BYTES // (8 * n * n * BK)))
    nn = n * n
    # the rows of W (each BK numbers): state, prediction, scratch, the step's inputs and statistics
    oX, oP = 0, n
    oXP = oP + nn
    oPp = oXP + n
    oAP = oPp + nn
    oH = oAP + nn
    oK = oH + n
    oY = oK + n
    oBU = oY + 1
    oDU = oBU + n
    oG = oDU + 1
    oEY = oG + 1
    W = np.zeros((oEY + 1) * BK)
    # the constants: A (n x n), sym(Q) (n x n), c (n)
    cst = np.empty(2 * nn + n)
    for i in range(n):
        cst[2 * nn + i] = C[0, i]
        for j in range(n):
            cst[i * n + j] = A[i, j]
            cst[nn + i * n + j] = 0.5 * (Qd[i, j] + Qd[j, i])
    Wx = W[oX * BK : (oX + n) * BK].reshape((n, BK))
    WP = W[oP * BK : (oP + nn) * BK].reshape((n, n, BK))
    Wxp = W[oXP * BK : (oXP + n) * BK].reshape((n, BK))
    WPp = W[oPp * BK : (oPp + nn) * BK].reshape((n, n, BK))
    s_mean, s_pmean = np.empty(_stage_shape(means, BK, S)), np.empty(_stage_shape(pmeans, BK, S))
    s_cov, s_pcov = np.empty(_stage_shape(covs, BK, S)), np.empty(_stage_shape(pcovs, BK, S))
    s_pu, s_ey = np.empty(_stage_shape(pu, BK, S)), np.empty(_stage_shape(ey, BK, S))
    w_pu, w_ey = pu.shape[1] > 0, ey.shape[1] > 0
    s_y = np.empty((S, BK))
    has_bu, has_du = bu.shape[1] > 0, du.shape[1] > 0
    one_p = P0.shape[0] == 1
    for r0 in range(0, N, BK):
        nb = min(BK, N - r0)
        for b in range(nb):
            rp = 0 if one_p else r0 + b
            for i in range(n):
                Wx[i, b] = x0[r0 + b, i]
                for j in range(n):
                    WP[i, j, b] = P0[rp, i, j]
        for t in range(T):
            tt = t % S
            tl = min(t, lo.shape[0] - 1)
            upper = lo[tl, 0] == -_INF
            sg = -1.0 if upper else 1.0
            lim = sg * (hi[tl, 0] if upper else lo[tl, 0])
            if tt == 0:  # the readings of the chunk's steps, run by run (contiguous reads), into (S, B)
                cnt = min(S, T - t)
                for b in range(nb):
                    for s in range(cnt):
                        s_y[s, b] = y[r0 + b, t + s, 0]
            for b in range(nb):
                W[oY * BK + b] = s_y[tt, b]
            if has_bu:
                for i in range(n):
                    for b in range(nb):
                        W[(oBU + i) * BK + b] = bu[r0 + b, t, i]
            if has_du:
                for b in range(nb):
                    W[oDU * BK + b] = du[r0 + b, t, 0]
            for b in range(nb):  # the whole step of run b: straight-line code, vectorised over b
                # predict: xbar = A x + B^u u, Pbar = A P A^T + Q (upper triangle, mirrored)
                for i in range(n):
                    acc = W[(oBU + i) * BK + b]  # 0 without inputs (W starts zeroed)
                    for k in range(n):
                        acc += cst[i * n + k] * W[(oX + k) * BK + b]
                    W[(oXP + i) * BK + b] = acc
                for i in range(n):
                    for j in range(n):
                        acc = 0.0
                        for k in range(n):
                            acc += cst[i * n + k] * W[(oP + k * n + j) * BK + b]
                        W[(oAP + i * n + j) * BK + b] = acc
                for i in range(n):
                    for j in range(i, n):
                        acc = cst[nn + i * n + j]
                        for k in range(n):
                            acc += W[(oAP + i * n + k) * BK + b] * cst[j * n + k]
                        W[(oPp + i * n + j) * BK + b] = acc
                        W[(oPp + j * n + i) * BK + b] = acc
                # the moments of the reading: mu = c xbar (+ D u), s = c Pbar c^T, h = Pbar c^T
                mu = W[oDU * BK + b]
                for i in range(n):
                    mu += cst[2 * nn + i] * W[(oXP + i) * BK + b]
                sv = 0.0
                for i in range(n):
                    acc = 0.0
                    for k in range(n):
                        acc += W[(oPp + i * n + k) * BK + b] * cst[2 * nn + k]
                    W[(oH + i) * BK + b] = acc
                    sv += cst[2 * nn + i] * acc
                yb = W[oY * BK + b]
                if tobit:
                    ms = sg * mu
                    _plo, g, _lam, tmean, tvar, cm, cvar = _one_sided_at(ms, rnoise, lim)
                    if noise_code == 0:
                        v = tvar
                    elif noise_code == 1:
                        v = cvar
                    else:
                        dm = tmean - ms
                        v = g * (tvar + dm * dm)
                    cm = sg * cm
                    W[oG * BK + b] = g
                    W[oEY * BK + b] = cm
                    e = yb - cm
                    ree = g * g * sv + v
                else:
                    g = 1.0
                    v = rnoise
                    e = yb - mu
                    ree = sv + rnoise
                good = ree > _TINY and not math.isnan(e)
                e = e if good else 0.0
                f = g / ree if good else 0.0  # K = f h, R_xe = g h
                for i in range(n):
                    kgi = f * W[(oH + i) * BK + b]
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
            _stage(Wxp, WPp, tt, nb, s_pmean, s_pcov)
            _stage(Wx, WP, tt, nb, s_mean, s_cov)
            if w_pu:
                for b in range(nb):
                    s_pu[tt, 0, b] = W[oG * BK + b]
            if w_ey:
                for b in range(nb):
                    s_ey[tt, 0, b] = W[oEY * BK + b]
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_pu, pu, r0, t0, nb, tt + 1)
                _flush(s_ey, ey, r0, t0, nb, tt + 1)
        _store_last(Wx, WP, r0, nb, x_last, P_last)


# One entry per state size, each calling soa_loop with its n as a constant: a call from Python with an int n
# would go through ``literally``'s dispatch (typing the call again, about a second) on every call.
@njit(cache=True, nogil=True)
def _soa1(
    tobit,
    y,
    A,
    Qd,
    C,
    rnoise,
    lo,
    hi,
    bu,
    du,
    noise_code,
    joseph,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    soa_loop(
        1,
        tobit,
        y,
        A,
        Qd,
        C,
        rnoise,
        lo,
        hi,
        bu,
        du,
        noise_code,
        joseph,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        x_last,
        P_last,
    )


@njit(cache=True, nogil=True)
def _soa2(
    tobit,
    y,
    A,
    Qd,
    C,
    rnoise,
    lo,
    hi,
    bu,
    du,
    noise_code,
    joseph,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    soa_loop(
        2,
        tobit,
        y,
        A,
        Qd,
        C,
        rnoise,
        lo,
        hi,
        bu,
        du,
        noise_code,
        joseph,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        x_last,
        P_last,
    )


@njit(cache=True, nogil=True)
def _soa3(
    tobit,
    y,
    A,
    Qd,
    C,
    rnoise,
    lo,
    hi,
    bu,
    du,
    noise_code,
    joseph,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    soa_loop(
        3,
        tobit,
        y,
        A,
        Qd,
        C,
        rnoise,
        lo,
        hi,
        bu,
        du,
        noise_code,
        joseph,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        x_last,
        P_last,
    )


@njit(cache=True, nogil=True)
def _soa4(
    tobit,
    y,
    A,
    Qd,
    C,
    rnoise,
    lo,
    hi,
    bu,
    du,
    noise_code,
    joseph,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    soa_loop(
        4,
        tobit,
        y,
        A,
        Qd,
        C,
        rnoise,
        lo,
        hi,
        bu,
        du,
        noise_code,
        joseph,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        x_last,
        P_last,
    )


_ENTRIES = {1: _soa1, 2: _soa2, 3: _soa3, 4: _soa4}


def soa_run(n: int, *args) -> None:
    """:func:`soa_loop` for state size ``n`` (1 to :data:`SOA_MAX_N`) with the rest of its arguments."""
    _ENTRIES[n](*args)


def soa_kalman_loop(y, A, Qd, H, par, joseph, x0, P0, means, covs, pmeans, pcovs, x_last, P_last) -> None:
    """:func:`soa_loop` for the Kalman filter with the arguments of
    :func:`~tobitkf.filters._compiled_entries.kalman_loop` (``H`` (1, 1, n), ``par`` (1, 1, 1) the noise variance
    R); the caller checked :func:`soa_covers`."""
    N, _, m = y.shape
    n = A.shape[0]
    e = np.empty((1, 1))
    soa_run(
        n,
        False,
        y,
        A,
        Qd,
        H[0],
        float(par[0, 0, 0]),
        e,
        e,
        np.empty((N, 0, n)),
        np.empty((N, 0, m)),
        0,
        bool(joseph),
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        np.empty((N, 0, m)),
        np.empty((N, 0, m)),
        x_last,
        P_last,
    )


def soa_tobit_loop(
    y, A, Qd, H, sigma, lo, hi, bu, du, noise_code, joseph, x0, P0, means, covs, pmeans, pcovs, pu, ey, x_last, P_last
) -> None:
    """:func:`soa_loop` for the Tobit Kalman filter with the arguments of
    :func:`~tobitkf.filters._compiled_entries.tobit_loop` (``H`` (1, 1, n), ``sigma`` (1, 1), ``lo``/``hi``
    (TL, 1)); the caller checked :func:`soa_covers`."""
    soa_run(
        A.shape[0],
        True,
        y,
        A,
        Qd,
        H[0],
        float(sigma[0, 0]),
        lo,
        hi,
        bu,
        du,
        int(noise_code),
        bool(joseph),
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        x_last,
        P_last,
    )
