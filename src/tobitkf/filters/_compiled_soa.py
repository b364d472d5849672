r"""The Kalman filter, the Tobit Kalman filter and the censored assumed-density filter with the whole step
vectorised over the runs (SIMD over the batch).

:func:`~tobitkf.filters._compiled_loop.compiled_loop` keeps a block's runs on the last axis too, but writes the
step as some tens of short loops over the runs, one per product, each storing its result for the next: at
n = 2, m = 1 most of a step is the loops' set-up and the stores between them. Here the state size n is a
compile-time constant (the length of the tuple ``size``, :data:`SIZES`: one specialisation per n, chosen by
numba's ordinary dispatch on the argument's type), so that every loop over the state is unrolled and the
*whole* step of one run, predict, gain and covariance update, is straight-line code in the body of a loop over the
runs of a block, which LLVM vectorises (AVX2: 4 runs per instruction, AVX-512: 8). Three things keep it so, each of
which, lost, left the step scalar (0 packed multiplications in its code; counted for every update by the tests,
:func:`_step`): the loops over the runs have a trip count bounded by :data:`SOA_BLOCK` (numba's wraparound of
negative indices is then proven dead; unbounded, the addresses are not affine in the run); the step runs in a
function of its own taking the scratch as an argument, the covariance form chosen outside the loops over the runs
(no reference-count calls left in them); and the TKF's step runs as three loops (prediction and moments;
statistics; update), each vectorised: fused into one loop, LLVM left it scalar without a reason it reports (48.7 ns
per run-step against the three loops' 18.1, n = 2, one-sided limits). The censored assumed-density filter's loop
without its log-likelihood and P(uncensored) stays scalar (with them it vectorises, but computing them always was
no faster).

The pieces: the scratch layout (a block of :data:`SOA_BLOCK` runs, means ``x[i, b]`` (n, B), covariances
``P[i, j, b]`` (n, n, B), readings (N, T, m) as given) and the step of one run with one channel, the Kalman
filter's (:data:`KALMAN`) and the Tobit Kalman filter's update (:data:`TOBIT_ANY`), in
:mod:`tobitkf.filters._compiled_soa_step`; the joint update of m = 2 or 3 channels, the KF's and the TKF's, in
:mod:`tobitkf.filters._compiled_soa_joint`; here the time loop (:func:`soa_loop`), the step of a block
(:func:`_step`: which update, its loops over the runs, the TKF's censored statistics at the prior), what is
covered and the entries. Each is the compiled loop's arithmetic in its order, so that the two agree to rounding; a
reading that is NaN, or an innovation variance not above the smallest normal number, leaves the run's prediction
unchanged (the compiled loop's rule).

The censored assumed-density filter's update (:data:`CENSORED_ADF`, :mod:`tobitkf.filters.assumed_density`),
in :func:`_step`: the reading's class (missing, inside its limits, at the lower or the upper limit: given, or by
the limit rule of :func:`~tobitkf.filters._compiled_moments.classify`) and the latent :math:`N(\mu, s + r)` give
:math:`(\alpha, \beta)`, the log-likelihood and P(uncensored) from
:func:`~tobitkf.filters._compiled_moments._censored_one` (the compiled loop's function, imported; its logarithms
and exponential without a libm call, so that they vectorise too), and :math:`\hat x = \bar x + \alpha h`,
:math:`P = \bar P - \beta hh^T`. With one channel both of its orders (``"channels"``, ``"uncensored_first"``) are
this one update.

Covered (:func:`soa_covers`, :func:`censored_covers`): one channel, n from 1 to :data:`SOA_MAX_N`; for the TKF
limits without NaN, ``lo < hi`` (one finite limit, two or none; the limits may change with the step), every noise term, the
standard and Joseph forms, the input terms :math:`B^uu_k`, :math:`Du_k`; for the KF a covariance per run (with
one prior covariance shared by the runs, nothing missing, the compiled loop computes the covariance once and is
faster), both forms; for the censored assumed-density filter a time-invariant system (A, Q and C shared by the
runs and the steps), the noise variance and the limits shared by the runs (either may change with the step;
no limit, one or two finite ones), the input terms, the standard form, with or without the log-likelihood and
P(uncensored) (:func:`censored_entry`; given interval readings run the loop); the joint updates of m = 2, 3
channels (n up to :data:`SOA_MAX_N`), the KF's and the TKF's (each channel its own limits, which may change with
the step, and its own :math:`\sigma_l`; every noise term, both forms, the input terms), are tested equal to the
loop, and routed for the measured (m, n) of :data:`KF_JOINT_ROUTED` and :data:`TKF_JOINT_ROUTED`. Anything else runs
:func:`~tobitkf.filters._compiled_loop.compiled_loop`.

Measured (n = 2, m = 1, 2 x 10^4 runs x 100 steps, readings max(N(0.1, 0.5^2), 0), lower limit 0, outputs
allocated and touched before, thread CPU time per run-step, medians of 5 alternating calls in one process, one
thread, a 2-core AVX-512 machine under a load average of 8-10): TKF 18.1 against the compiled loop's 30.3 ns
(means only), 25.7 against 41.1 (means and covariances); KF 10.2 against 25.8 and 18.2 against 28.8; censored
assumed-density filter 63.9 and 65.2 (its loop scalar), with its log-likelihood and P(uncensored) 68.7 and 71.9
(vectorised). Two finite limits (n = 2, 2 x 10^4 runs x 100 steps, readings clipped to [-0.5, 0.5], means only
plus the extras, medians of 5 alternating calls, load average 8-12): TKF 82.7 against the loop's 108.2 ns;
censored assumed-density filter with its log-likelihood and P(uncensored) 59.8 against 171.0. The KF with two channels (n = 2, C = I,
R = diag(0.1, 0.2), 2 x 10^4 runs x 100 steps, medians of 7 alternating calls, load average 10.7): 22.2 against the
loop's 30.9 ns (means only), 27.6 against 37.0 (means and covariances). The entries :func:`soa_kalman_loop`,
:func:`soa_tobit_loop` and :func:`soa_censored_loop` take the arguments of
:mod:`tobitkf.filters._compiled_entries`' ``kalman_loop`` and ``tobit_loop`` and of ``compiled_loop`` and fill
the same outputs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import _compiled_loop
from ._compiled_block import _flush, _stage, _stage_shape, _store_last
from ._compiled_censored import GL_W, GL_X, _assemble, censored_stats, noise_term, window_direct
from ._compiled_moments import CENSORED, INTERVAL, classify
from ._compiled_moments import _censored_one as _adf_update
from ._compiled_soa_joint import (
    _kalman_fallback,
    _kalman_joint_gain,
    _kalman_joint_update,
    _tkf_joint_gain,
    _tkf_joint_moments,
)
from ._compiled_soa_step import (
    CENSORED_ADF,
    CENSORED_ADF_STATS,
    CHANS,
    KALMAN,
    KINDS,
    SIZES,
    SOA_BLOCK,
    SOA_MAX_M,
    SOA_MAX_N,
    TOBIT_ANY,
    _kalman_step,
    _offsets,
    _one_sided_tkf,
    _predict_moments,
    _update_of,
)

__all__ = [
    "SOA_BLOCK",
    "SOA_MAX_N",
    "SIZES",
    "CHANS",
    "SOA_MAX_M",
    "KF_JOINT_ROUTED",
    "TKF_JOINT_ROUTED",
    "KALMAN",
    "TOBIT_ANY",
    "CENSORED_ADF",
    "CENSORED_ADF_STATS",
    "KINDS",
    "soa_covers",
    "censored_covers",
    "soa_kalman_loop",
    "soa_tobit_loop",
    "soa_censored_loop",
    "soa_loop",
    "tobit_entry",
    "kalman_entry",
    "censored_entry",
]

#: the (m, n) of the KF's joint update (m > 1) that :func:`kalman_entry` routes to :func:`soa_loop`: those measured
#: faster than the compiled loop. n = 2, m = 2 (C = I, R = diag(0.1, 0.2), 2 x 10^4 runs x 100 steps, thread CPU time
#: per run-step, medians of 7 alternating calls in one process, load average 10.7 on 2 cores): 22.2 against 30.9 ns
#: means only, 27.6 against 37.0 with covariances. The others (``bench_simd.py --which kfm``: channel l reads state
#: l mod n, the same sizes, load average 7-10), means only / with covariances: (m, n) = (2, 1) 14.7 / 16.6 against
#: 20.8 / 22.6, (3, 1) 21.5 / 23.2 against 29.9 / 31.5, (3, 2) 28.0 / 35.1 against 39.3 / 46.4, (2, 3) 31.3 / 44.6
#: against 40.7 / 54.2; slower, not routed: (3, 3) 302 / 317 against 54.8 / 68.1, (2, 4) 227 / 252 against 62.8 /
#: 93.6, (3, 4) 381 / 406 against 82.3 / 111 (the straight-line step of a run no longer vectorises well). Every m up
#: to :data:`SOA_MAX_M` and n up to :data:`SOA_MAX_N` is tested equal to the loop. Routed for now only at (2, 2), the largest gain measured: each routed (m, n) is a compiled
#: version of its own (about 20 s of compiling on the first call at that size, and in the test run), and the other
#: gains (8-30 %) come from one run on a loaded machine, to be confirmed on an idle one before they are routed
KF_JOINT_ROUTED = frozenset({(2, 2)})
#: the (m, n) of the TKF's joint update (m > 1) that :func:`tobit_entry` routes to :func:`soa_loop`: those measured
#: faster than the compiled loop (``bench_simd.py --which tkfm,tkfmw``: every channel left-censored at 0, channel l
#: reading state l mod n, 2 x 10^4 runs x 100 steps, thread CPU time per run-step, medians of 7 alternating calls in
#: one process, load average 6-10 on 2 cores), means only / with covariances: (m, n) = (2, 1) 36.4 / 38.4 against
#: the loop's 40.1 / 42.2 (every channel in the window [-0.5, 0.5]: 144 / 145 against 205 / 206), (3, 1) 53.5 / 56.4
#: against 59.2 / 63.8 (window: 218 / 218 against 301 / 298), (2, 2) 44.0 / 55.1 against 55.7 / 66.0, (3, 2) 59.1 /
#: 65.7 against 69.2 / 76.1, (2, 3) 48.9 / 61.8 against 60.2 / 73.9, (3, 3) 73.0 / 87.0 against 86.7 / 100.3; slower,
#: not routed: (2, 4) 183 / 210 against 79.3 / 109, (3, 4) 445 / 470 against 105 / 131. Every m up to
#: :data:`SOA_MAX_M` and n up to :data:`SOA_MAX_N` is tested equal to the loop
#: Routed for now only at (2, 2), the largest gain measured, for the reason given at :data:`KF_JOINT_ROUTED`
TKF_JOINT_ROUTED = frozenset({(2, 2)})
_CHUNK = 64  # steps staged per flush (as the compiled loop's CHUNK)
_STAGE_BYTES = 1 << 18
_INF = math.inf


def soa_covers(kalman: bool, m: int, n: int, P0_rows: int, N: int, lo=None, hi=None) -> bool:
    """Whether :func:`soa_loop` covers a KF or TKF call: one channel (``m == 1``), ``1 <= n <=``
    :data:`SOA_MAX_N`, or for a joint update of several channels the (m, n) of :data:`KF_JOINT_ROUTED` (KF) and
    :data:`TKF_JOINT_ROUTED` (TKF); the KF with a covariance per run (``P0_rows == N``; one shared covariance runs
    the compiled loop's shared-gain path), the TKF with limits ``lo``/``hi`` (TL, m) without NaN and ``lo < hi``
    in every entry (per channel one finite limit, two or none)."""
    if kalman and (m, n) in KF_JOINT_ROUTED:
        return P0_rows == N or N == 1
    if not 1 <= n <= SOA_MAX_N or (m != 1 and (kalman or (m, n) not in TKF_JOINT_ROUTED)):
        return False
    if kalman:
        return P0_rows == N or N == 1
    if lo is None or hi is None:
        return False
    lo, hi = np.asarray(lo), np.asarray(hi)
    return bool(np.all(lo < hi))  # False for a NaN limit too


def censored_covers(family: int, A, Qd, H, F, r, lo, hi, x0) -> bool:
    """Whether :func:`soa_loop` covers a call of the compiled loop for an assumed-density family (the arguments
    of :func:`~tobitkf.filters._compiled_loop.compiled_loop`): the censored family, one channel, a state of 1 to
    :data:`SOA_MAX_N` without augmentation or fading rows, ``A``, ``Qd`` and the rows ``H`` shared by the runs
    and the steps, the noise variances ``r`` and the limits ``lo``/``hi`` (runs or 1, steps or 1, 1) shared by
    the runs, no NaN limit."""
    n = x0.shape[1]
    return (
        family == CENSORED
        and H.shape[0] == 1
        and H.shape[1] == 1
        and 1 <= n <= SOA_MAX_N
        and A.shape == (1, 1, n, n)
        and Qd.shape == (1, 1, n, n)
        and F.shape[2] == 0
        and r.shape[0] == 1
        and lo.shape[0] == 1
        and hi.shape[0] == 1
        and not bool(np.isnan(lo).any() or np.isnan(hi).any())
    )


def tobit_entry(default, m: int, n: int, lo, hi):
    """The TKF's whole-record entry: :func:`soa_tobit_loop` when :func:`soa_covers` the call (one channel, n up
    to :data:`SOA_MAX_N`, limits without NaN, ``lo < hi``), else ``default`` (the compiled loop's ``tobit_loop``);
    both take the same arguments."""
    return soa_tobit_loop if soa_covers(False, m, n, 0, 0, lo, hi) else default


def kalman_entry(default, m: int, n: int, P0_rows: int, N: int):
    """The KF's whole-record entry: :func:`soa_kalman_loop` when :func:`soa_covers` the call, else ``default``
    (the compiled loop's ``kalman_loop``); both take the same arguments."""
    return soa_kalman_loop if soa_covers(True, m, n, P0_rows, N) else default


def censored_entry(default, family: int, A, Qd, H, F, r, lo, hi, x0, stats: bool):
    """An assumed-density family's whole-record entry: :func:`soa_censored_loop` when :func:`censored_covers` the
    call, else ``default`` (:func:`~tobitkf.filters._compiled_loop.compiled_loop`); both take the same arguments.
    With the log-likelihood and P(uncensored) too (``stats``; unused since their logarithms vectorise: n = 2,
    two-sided limits, 2 x 10^4 runs x 100 steps, thread CPU time, load average 8-12: 60 against the loop's 171 ns
    per run-step)."""
    return soa_censored_loop if censored_covers(family, A, Qd, H, F, r, lo, hi, x0) else default


@njit(cache=True, error_model="numpy", nogil=True)
def _step(
    size, chans, kind, W, cst, nb, rn, lo_t, hi_t, lim, sg, lo_r, hi_r, noise_code, joseph, has_cls, glx, glw, buf
):
    """The update ``kind`` of one step for the ``nb`` runs of a block, from and into the scratch ``W`` of
    :func:`soa_loop` (its docstring). A function of its own, not inlined into the time loop: ``W`` and ``cst``
    are arguments here (borrowed references), so that the helpers inlined into the loop over the runs take them
    without reference counting; inlined into :func:`soa_loop`, whose own arrays they are, each run's step made an
    ``NRT_incref``/``NRT_decref`` call pair that numba's reference-count pruning did not remove, and LLVM does not
    vectorise a loop with a call in it (the whole step stayed scalar)."""
    n = len(size)
    BK = SOA_BLOCK
    # the runs' loops' trip count bounded (0 to SOA_BLOCK), so that LLVM proves every index W[row * BK + b]
    # non-negative and drops numba's wraparound of negative indices: with it the addresses are not affine in b
    # and no loop over the runs vectorised
    nb = max(0, min(nb, BK))
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, 1)
    )
    lo_fin, hi_fin = lo_t != -_INF, hi_t != _INF
    # The TKF's statistics are written out in both of its branches below (one channel, several), not as one helper
    # inlined into both: as a helper (taking the limits, or the limits and sg, lim as arguments) the TKF's step at
    # n = 1, m = 1 took 44-46 s of CPU to compile against 30-32 s written out (fresh cache, the same machine and
    # load, measured in parallel), for the same numbers
    if len(kind) == TOBIT_ANY and len(chans) > 1:  # several channels: moments; statistics; gain; fallback; update
        m = len(chans)
        om = _offsets(n, m)
        jG, jEY, jMU, jV, jSL = om[10], om[11], om[14], om[16], om[17]
        osd = 2 * n * n + m * n  # the channels' standard deviations among the constants
        for b in range(nb):
            _tkf_joint_moments(W, cst, b, n, m)
        for l in range(m):  # each channel's statistics at its limits of the step, the routes of the one channel's
            lo_l, hi_l, sd = lo_r[l], hi_r[l], cst[osd + l]
            rG, rEY, rMU, rV, rSL = (jG + l) * BK, (jEY + l) * BK, (jMU + l) * BK, (jV + l) * BK, (jSL + l) * BK
            if lo_l != -_INF and hi_l != _INF:
                for b in range(nb):
                    mu = W[rMU + b]
                    other, _a2, _b2, _fl, _os, p_lo, p_hi, gam, lam, zvar = window_direct(mu, sd, lo_l, hi_l)
                    st = _assemble(mu, sd, lo_l, hi_l, p_lo, p_hi, gam, lam, zvar)
                    W[rG + b] = st[2]
                    W[rV + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
                    W[rEY + b] = st[6]
                    W[rSL + b] = 1.0 if other else 0.0
                for b in range(nb):
                    if W[rSL + b] != 0.0:
                        mu = W[rMU + b]
                        st = censored_stats(mu, sd, lo_l, hi_l, glx, glw, buf)
                        W[rG + b] = st[2]
                        W[rV + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
                        W[rEY + b] = st[6]
            elif lo_l != -_INF or hi_l != _INF:
                up_l = lo_l == -_INF
                sg_l = -1.0 if up_l else 1.0
                lim_l = sg_l * (hi_l if up_l else lo_l)
                for b in range(nb):
                    g, v, cm = _one_sided_tkf(W[rMU + b], sd, lim_l, sg_l, noise_code)
                    W[rG + b] = g
                    W[rV + b] = v
                    W[rEY + b] = cm
            else:
                for b in range(nb):
                    W[rG + b] = 1.0
                    W[rV + b] = sd * sd
                    W[rEY + b] = W[rMU + b]
        for b in range(nb):
            _tkf_joint_gain(W, cst, b, n, m)
        _kalman_fallback(W, nb, n, m)
        if joseph:
            for b in range(nb):
                _kalman_joint_update(W, cst, b, n, m, True, True)
        else:
            for b in range(nb):
                _kalman_joint_update(W, cst, b, n, m, False, True)
    elif len(kind) == TOBIT_ANY:  # (len(kind): a constant, the other updates' branches pruned)
        for b in range(nb):  # prediction and moments
            mu, sv = _predict_moments(W, cst, b, n)
            W[oMU * BK + b] = mu
            W[oS * BK + b] = sv
        if lo_fin and hi_fin:  # two finite limits: the direct formulas, vectorised
            for b in range(nb):
                mu = W[oMU * BK + b]
                other, _a2, _b2, _fl, _os, p_lo, p_hi, gam, lam, zvar = window_direct(mu, rn, lo_t, hi_t)
                st = _assemble(mu, rn, lo_t, hi_t, p_lo, p_hi, gam, lam, zvar)
                W[oG * BK + b] = st[2]
                W[oV * BK + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
                W[oEY * BK + b] = st[6]
                W[oSL * BK + b] = 1.0 if other else 0.0
            for b in range(nb):  # the runs off the direct route: the compiled loop's statistics
                if W[oSL * BK + b] != 0.0:
                    mu = W[oMU * BK + b]
                    st = censored_stats(mu, rn, lo_t, hi_t, glx, glw, buf)
                    W[oG * BK + b] = st[2]
                    W[oV * BK + b] = noise_term(noise_code, mu, st[2], st[4], st[5], st[7])
                    W[oEY * BK + b] = st[6]
        elif lo_fin or hi_fin:
            for b in range(nb):
                g, v, cm = _one_sided_tkf(W[oMU * BK + b], rn, lim, sg, noise_code)
                W[oG * BK + b] = g
                W[oV * BK + b] = v
                W[oEY * BK + b] = cm
        else:  # no limit: the latent reading's moments
            for b in range(nb):
                W[oG * BK + b] = 1.0
                W[oV * BK + b] = rn * rn
                W[oEY * BK + b] = W[oMU * BK + b]
        # the update; the Joseph form chosen outside the loops over the runs, a constant inside: a branch on it
        # within a run's step kept a reference-count call pair in the loop (not vectorised)
        if joseph:
            for b in range(nb):
                _update_of(W, cst, b, n, True)
        else:
            for b in range(nb):
                _update_of(W, cst, b, n, False)
    elif len(kind) == KALMAN and len(chans) > 1:  # the joint update of m channels: gain; fallback; update
        m = len(chans)
        for b in range(nb):
            _kalman_joint_gain(W, cst, b, n, m)
        _kalman_fallback(W, nb, n, m)
        if joseph:
            for b in range(nb):
                _kalman_joint_update(W, cst, b, n, m, True, False)
        else:
            for b in range(nb):
                _kalman_joint_update(W, cst, b, n, m, False, False)
    elif len(kind) == KALMAN:
        if joseph:
            for b in range(nb):
                _kalman_step(W, cst, b, n, rn, True)
        else:
            for b in range(nb):
                _kalman_step(W, cst, b, n, rn, False)
    else:
        for b in range(nb):  # the censored assumed-density filter: x = xbar + alpha h, P = Pbar - beta h h^T
            mu, sv = _predict_moments(W, cst, b, n)
            yb = W[oY * BK + b]
            cl = W[oCL * BK + b] if has_cls else float(classify(yb, lo_t, hi_t))
            al, be, lb, p = _adf_update(yb, cl, mu, sv + rn, lo_t, hi_t)
            if len(kind) == CENSORED_ADF_STATS:  # without, they are not computed
                W[oG * BK + b] = p
                W[oLL * BK + b] = lb
            for i in range(n):
                hv = W[(oH + i) * BK + b]
                W[(oX + i) * BK + b] = W[(oXP + i) * BK + b] + al * hv
                W[(oK + i) * BK + b] = be * hv
            for i in range(n):
                for j in range(i, n):
                    pij = W[(oPp + i * n + j) * BK + b] - W[(oK + i) * BK + b] * W[(oH + j) * BK + b]
                    W[(oP + i * n + j) * BK + b] = pij
                    W[(oP + j * n + i) * BK + b] = pij


@njit(cache=True, error_model="numpy", nogil=True)
def soa_loop(
    size,
    chans,
    kind,
    y,
    A,
    Qd,
    C,
    rv,
    lo,
    hi,
    bu,
    du,
    cls,
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
    ll,
    x_last,
    P_last,
):
    r"""The KF, the TKF or the censored assumed-density filter (``kind`` :data:`KALMAN`,
    :data:`TOBIT_ANY`, :data:`CENSORED_ADF`, :data:`CENSORED_ADF_STATS` as :data:`KINDS`) over N runs x T steps,
    m channels, state size ``n = len(size)`` (a tuple of n zeros, :data:`SIZES`: a compile-time constant);
    fills the outputs (module docstring).

    ``chans`` a tuple of m zeros (:data:`CHANS`; m > 1 the KF and the TKF); ``y`` (N, T, m) readings (NaN:
    missing); ``A``, ``Qd`` (n, n); ``C`` (m, n); ``rv`` (TR,) per step (row ``min(t, TR - 1)``) the KF's noise
    variance R, the TKF's standard deviation σ or the assumed-density filter's noise variance r (m > 1,
    constant: the KF's R (m, m) flattened, the TKF's σ (m,)); ``lo``, ``hi`` (TL, m) the limits, row
    ``min(t, TL - 1)``; ``bu`` (N, T, n), ``du`` (N, T, m) the input terms (T axis 0: none); ``cls`` (N, T, 1) int8 the
    assumed-density filter's reading classes (T axis 0: by the limit rule); ``noise_code`` of
    :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`; ``joseph`` the Joseph form (KF, TKF); ``x0`` (N, n),
    ``P0`` (N or 1, n, n). Outputs as :func:`~tobitkf.filters._compiled_loop.compiled_loop` (T axis 0: not
    written): ``means``, ``pmeans`` (N, T, n), ``covs`` (N, T, n, n) or (N, T, n, 1), ``pcovs`` (N, T, n, n),
    ``pu`` (N, T, m) P(uncensored), ``ey`` (N, T, m) the TKF's E(y), ``ll`` (N, T) the assumed-density filter's
    log-likelihood, ``x_last`` (N, n), ``P_last`` (N, n, n).

    Why one scratch array ``W`` with rows :data:`SOA_BLOCK` apart, indexed ``W[row * SOA_BLOCK + b]``, and the
    constants in another (``cst``): LLVM vectorises a loop only when it can prove that its stores do not
    overlap its loads; between separately allocated numba arrays it cannot, and the run-time overlap checks
    it would need for a dozen arrays exceed its limit (the loop stayed scalar: ~1300 scalar double
    instructions against 35 vector ones). Rows of one array a compile-time constant apart are independent
    by construction. The readings, the input terms and the outputs move between ``W`` and their arrays in
    short loops of their own.

    :data:`TOBIT_ANY` (the TKF) splits the step into three loops over the block's runs: the prediction and the moments
    (vectorised), the step's statistics (vectorised: one-sided, none, or two finite limits by
    :func:`~tobitkf.filters._compiled_censored.window_direct`, whose runs off the direct route, a narrow window
    or one in a tail, then take :func:`~tobitkf.filters._compiled_censored.censored_stats` one at a time: the
    compiled loop's numbers), and the update (vectorised)."""
    n, m = len(size), len(chans)
    N, T = y.shape[0], y.shape[1]
    BK = SOA_BLOCK
    S = max(1, min(_CHUNK, max(T, 1), _STAGE_BYTES // (8 * n * n * BK)))
    nn = n * n
    oX, oP, oXP, oPp, oAP, oH, oK, oY, oBU, oDU, oG, oEY, oCL, oLL, oMU, oS, oV, oSL, oRW, oRH, oD, oOK, oBAD, rows = (
        _offsets(n, m)
    )
    W = np.zeros(rows * BK)
    glx, glw = GL_X, GL_W
    buf = np.empty((2, glx.shape[0]))
    # the constants: A (n x n), sym(Q) (n x n), the rows C (m x n), with m > 1 the KF's R (m x m) from rv
    cst = np.zeros(2 * nn + m * n + m * m)
    for l in range(m):
        for i in range(n):
            cst[2 * nn + l * n + i] = C[l, i]
    if m > 1:  # the KF's R (m x m), the TKF's standard deviations (m)
        for i in range(min(m * m, rv.shape[0])):
            cst[2 * nn + m * n + i] = rv[i]
    for i in range(n):
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
    s_ll = np.empty(_stage_shape(ll, BK, S))
    w_pu, w_ey, w_ll = pu.shape[1] > 0, ey.shape[1] > 0, ll.shape[1] > 0
    s_y = np.empty((S, m, BK))
    has_bu, has_du, has_cls = bu.shape[1] > 0, du.shape[1] > 0, cls.shape[1] > 0
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
            lo_t, hi_t = lo[tl, 0], hi[tl, 0]
            rn = rv[min(t, rv.shape[0] - 1)]  # (m > 1: unused)
            upper = lo_t == -_INF  # one finite limit: an upper one is the lower limit -hi of -y
            sg = -1.0 if upper else 1.0
            lim = sg * (hi_t if upper else lo_t)
            if tt == 0:  # the readings of the chunk's steps, run by run (contiguous reads), into (S, B)
                cnt = min(S, T - t)
                for b in range(nb):
                    for s in range(cnt):
                        for l in range(m):
                            s_y[s, l, b] = y[r0 + b, t + s, l]
            for l in range(m):
                for b in range(nb):
                    W[(oY + l) * BK + b] = s_y[tt, l, b]
            if has_bu:
                for i in range(n):
                    for b in range(nb):
                        W[(oBU + i) * BK + b] = bu[r0 + b, t, i]
            if has_du:
                for l in range(m):
                    for b in range(nb):
                        W[(oDU + l) * BK + b] = du[r0 + b, t, l]
            if has_cls:
                for l in range(m):
                    for b in range(nb):
                        W[(oCL + l) * BK + b] = cls[r0 + b, t, l]
            _step(
                size, chans, kind, W, cst, nb, rn, lo_t, hi_t, lim, sg, lo[tl], hi[tl], noise_code, joseph, has_cls,
                glx, glw, buf,
            )  # fmt: skip
            _stage(Wxp, WPp, tt, nb, s_pmean, s_pcov)
            _stage(Wx, WP, tt, nb, s_mean, s_cov)
            if w_pu:
                for l in range(m):
                    for b in range(nb):
                        s_pu[tt, l, b] = W[(oG + l) * BK + b]
            if w_ey:
                for l in range(m):
                    for b in range(nb):
                        s_ey[tt, l, b] = W[(oEY + l) * BK + b]
            if w_ll:
                for b in range(nb):
                    s_ll[tt, b] = W[oLL * BK + b]
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_pu, pu, r0, t0, nb, tt + 1)
                _flush(s_ey, ey, r0, t0, nb, tt + 1)
                _flush(s_ll, ll, r0, t0, nb, tt + 1)
        _store_last(Wx, WP, r0, nb, x_last, P_last)


def _none(N: int, *shape: int) -> np.ndarray:
    """An output or input that is not there: (N, 0, ...)."""
    return np.empty((N, 0) + shape)


def soa_kalman_loop(y, A, Qd, H, par, joseph, x0, P0, means, covs, pmeans, pcovs, x_last, P_last) -> None:
    """:func:`soa_loop` for the Kalman filter with the arguments of
    :func:`~tobitkf.filters._compiled_entries.kalman_loop` (``H`` (1, m, n) the rows C, ``par`` (1, m, m) the
    noise covariance R; m from 1 to :data:`SOA_MAX_M`); the caller checked :func:`soa_covers`."""
    N, _, m = y.shape
    n = A.shape[0]
    e = np.empty((1, 1))
    soa_loop(
        SIZES[n],
        CHANS[m],
        KINDS[KALMAN],
        y,
        A,
        Qd,
        H[0],
        np.ascontiguousarray(par.reshape(m * m)),
        e,
        e,
        _none(N, n),
        _none(N, m),
        np.empty((N, 0, m), dtype=np.int8),
        0,
        bool(joseph),
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        _none(N, m),
        _none(N, m),
        _none(N),
        x_last,
        P_last,
    )


def soa_tobit_loop(
    y, A, Qd, H, sigma, lo, hi, bu, du, noise_code, joseph, x0, P0, means, covs, pmeans, pcovs, pu, ey, x_last, P_last
) -> None:
    """:func:`soa_loop` for the Tobit Kalman filter with the arguments of
    :func:`~tobitkf.filters._compiled_entries.tobit_loop` (``H`` (1, m, n), ``sigma`` (1, m), ``lo``/``hi``
    (TL, m); m from 1 to :data:`SOA_MAX_M`); the caller checked :func:`soa_covers`. Every kind of limits takes the
    split step (:data:`TOBIT_ANY`, three vectorised loops per step, with m > 1 the joint update's gain and
    update after them: the module docstring)."""
    N, _, m = y.shape
    soa_loop(
        SIZES[A.shape[0]],
        CHANS[m],
        KINDS[TOBIT_ANY],
        y,
        A,
        Qd,
        H[0],
        np.ascontiguousarray(sigma.reshape(m)),
        lo,
        hi,
        bu,
        du,
        np.empty((N, 0, m), dtype=np.int8),
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
        _none(N),
        x_last,
        P_last,
    )


def soa_censored_loop(*args) -> None:
    """:func:`soa_loop` for the censored assumed-density filter with the 29 arguments of
    :func:`~tobitkf.filters._compiled_loop.compiled_loop` (``A``, ``Qd`` (1, 1, n, n), ``H`` (1, 1, n), ``r``,
    ``lo``, ``hi`` (1, steps or 1, 1); ``F``, ``par``, ``J``, ``npass``, ``noise_code``, ``joseph``, ``ey`` and
    ``comp`` unused: no fading rows, no mixture, one channel, the standard form); the caller checked
    :func:`censored_covers`. Given classes with an interval reading (:data:`~tobitkf.filters._readings.INTERVAL`:
    flagged censored inside its limits, whose update takes quadrature) run the compiled loop itself."""
    (_family, y, cls, A, Qd, H, _F, r, lo, hi, _par, _J, _npass, _noise_code, _joseph, bu, du, x0, P0, means, covs,
     pmeans, pcovs, pu, _ey, ll, _comp, x_last, P_last) = args  # fmt: skip
    if cls.shape[1] > 0 and bool((cls == INTERVAL).any()):
        _compiled_loop.compiled_loop(*args)
        return
    soa_loop(
        SIZES[x0.shape[1]],
        CHANS[1],
        KINDS[CENSORED_ADF_STATS if pu.shape[1] > 0 or ll.shape[1] > 0 else CENSORED_ADF],
        y,
        A[0, 0],
        Qd[0, 0],
        H[0],
        np.ascontiguousarray(r.reshape(-1)),
        lo[0],
        hi[0],
        bu,
        du,
        cls,
        0,
        False,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        _none(y.shape[0], 1),
        ll,
        x_last,
        P_last,
    )
