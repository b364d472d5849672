r"""The one compiled time loop of the Gaussian-update families: the Kalman filter, the Tobit Kalman filter (every
noise term, both covariance forms, the multi-region TKF as stacked channels), the fading, protocol and steady-state
Tobit Kalman filters and every assumed-density family.

:func:`compiled_loop` is written once: the runs in blocks (runs on the last axis, vectorised), per step the predict
(:func:`~tobitkf.filters._compiled_block._predict`, or the block shift of an augmented state,
:func:`~tobitkf.filters._compiled_fading.shift_predict_block`), the input term :math:`B^uu_k`, the family's
update, the outputs staged for a chunk of steps and written run by run (:mod:`tobitkf.filters._compiled_block`),
carved from the output pool (:func:`~tobitkf.filters.kalman.output_arrays`). Its scratch is sized to the family
(an array the family's update does not use gets no room, :func:`_loop_scratch`). The update is chosen by a code, and
each family compiles its own version of the loop that holds its update alone:

* :data:`KALMAN`: :math:`K = \bar PC^T(C\bar PC^T + R)^{-1}` over the channels that take part (a NaN reading
  does not), Miller (2015) (2.3)–(2.6); with one prior covariance for all runs and nothing missing the
  covariance and the gains are computed once and the means of every run with those gains;
* :data:`TOBIT`: the Tobit update of all channels at the prior (Miller (3.37)–(3.41)): the channel statistics of
  :func:`~tobitkf.filters._compiled_tobit.tobit_stats_block` (called, not inlined: its arrays arrive borrowed),
  then the moments, the masked gain and the covariance update written in the loop beside the Kalman filter's and
  the fading TKF's (what :func:`~tobitkf.filters._compiled_tobit.tobit_update_block` does for the closed loop of
  :mod:`tobitkf.control`);
* :data:`FADING`: the fading TKF's update of its augmented state (Geng et al. 2017, Table 1), the same Tobit
  update at the step's rows ``H[t]`` (:math:`H_k = \bar\theta_k\mathcal C_k`) with the inverse Mills ratios
  among the outputs, written in the loop itself beside the Kalman filter's update (whose masked gain and covariance
  update it shares; the one-sided statistics of a block from
  :func:`~tobitkf.filters._compiled_fading.fading_lower_block`): an array handed per step to a function inlined
  by numba, or a view made per step, costs an atomic increment and decrement of its reference count, some 40 per
  step and block as a function taking the block's scratch (the means-only filter ~7 % slower);
* an assumed-density family (:data:`~tobitkf.filters._compiled_moments.FAMILIES`, or a channel's own block,
  :data:`~tobitkf.filters._compiled_moments.BLOCK`): channel by channel, a
  rank-one change along :math:`\bar Ph^T` (:mod:`tobitkf.filters._compiled_moments`),

  .. math::

      \hat x = \bar x + \alpha\,\bar Ph_l^T,\quad P = \bar P - \beta\,\bar Ph_l^T h_l\bar P,

  with :math:`(\alpha, \beta)` per run from the family's block function
  (:func:`~tobitkf.filters._compiled_moments.family_block`), the channel rows :math:`h_l` per step and a
  multiplicative-noise term (the fading variance :math:`\sum_q f_q\bar Pf_q^T + (f_q\bar x)^2`);
* :data:`PROTOCOL_TKF`: the protocol Tobit Kalman filter (Geng et al. (19)–(24)) on the augmented state, the
  scheduled sensor's row per step, its moments from
  :func:`~tobitkf.filters._compiled_moments.protocol_tkf_block` (:func:`_protocol_tkf_update`), the step's
  scalars and the augmented means into ``comp``;
* :data:`FIXED_GAIN`: the steady-state Tobit Kalman filter, whose gain and covariances are constants: its means
  alone, :math:`\hat x = \bar x + K_\infty(y - E[y])` (Miller (3.56)–(3.58), :func:`_fixed_gain_means`).

A code, not a function argument: numba types a compiled function given as an argument by the object, a type that
does not survive the process, so a loop taking the update as an argument would be compiled again in every process
(a channel's own block travels as a handle whose type is named by the hash of the block's code instead,
:func:`~tobitkf.filters._compiled_moments.block_kind`, and its version of the loop is cached like the package's
families'). The code travels as a kind
(:func:`~tobitkf.filters._compiled_moments.kind`, the tuple of ``code`` Nones): numba reads the length of a tuple
argument as a constant before typing and prunes the branches of the other families, so that the Kalman filter's
version does not compile the assumed-density moments, nor theirs the Tobit update (compared as a run-time integer,
every family's update was typed and lowered into every version).

What an assumed-density family gives the loop (:class:`~tobitkf.filters._loop_specs.CompiledSpec`, built by the
``*_spec`` functions of :mod:`tobitkf.filters._loop_specs` from an estimator and a record;
:func:`~tobitkf.filters._loop_specs.channel_spec` for any channel of the measurement contract that names its
compiled block, so that the generic :class:`~tobitkf.AssumedDensityFilter` of such a channel needs no spec of its
own): its code, the rows ``H`` (TH, m, n_x), the fading rows ``F`` (TF, m, Q, n_x), the noise variances ``r``
(TR, m), the limits ``lo``/``hi`` (TL, m), its parameters ``par`` (TP, m, K), the number of mixture components
``J`` whose posterior weights are returned; per-step arrays are indexed by ``min(t, len - 1)`` (one row:
constant). The KF and the TKF enter through :mod:`tobitkf.filters._compiled_entries`.
Covered: time-invariant system matrices (control inputs through constant ``Bu``/``D``); for the censored
assumed-density filter also matrices per step and per run (a :class:`~tobitkf.LinearSystem` with ``batch_ndim``:
``A``, ``Qd`` (runs or 1, steps or 1, n, n), ``r`` and the limits (runs or 1, steps or 1, m), indexed by run and
step, 0 where shared; :func:`_predict_runs` takes each lane's own transition), C shared by the runs; the KF and
the TKF in the standard and Joseph forms, the assumed-density filters in the standard form and the channel-order
update; anything else (the square-root form, other families' time-varying matrices, per-step limits given to
``step``) runs the numpy path (``backend="auto"``) or is refused (``backend="numba"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_block import (
    _block_dims,
    _cov_update,
    _flush,
    _gain,
    _gain_block,
    _innovation_moments,
    _mean_scratch,
    _mirror,
    _predict,
    _stage,
    _stage_mean,
    _stage_rows,
    _stage_shape,
    _store_last,
    _take_part,
    _update_scratch,
    mean_predict,
    runs_per_block,
)
from ._compiled_censored import censored_stats, noise_term
from ._compiled_fading import AUG_BLOCK, fading_lower_block, shift_predict_block
from ._compiled_moments import (
    BLOCK,
    FAMILIES,
    INTERIOR,
    MISSING,
    PROTOCOL_TKF_EXTRAS,
    classify,
    family_block,
    kind,
    protocol_tkf_block,
)
from ._compiled_tobit import _INF, GL_W, GL_X, tobit_stats_block

__all__ = [
    "compiled_loop",
    "KALMAN",
    "TOBIT",
    "PROTOCOL_TKF",
    "FIXED_GAIN",
    "FADING",
    "CODES",
    "kind",
]


#: update codes of :func:`compiled_loop` beyond the assumed-density families of
#: :data:`~tobitkf.filters._compiled_moments.FAMILIES` (codes below :data:`KALMAN`): the Kalman filter and the Tobit
#: Kalman filter (a joint update of all channels, not channel by channel)
KALMAN, TOBIT = 16, 17
#: update codes of the protocol Tobit Kalman filter (Geng et al. (21)-(24), a joint update of its one scheduled
#: channel, :func:`_protocol_tkf_update`) and of the fixed-gain (steady-state) Tobit Kalman filter (Miller (3.58),
#: means only, :func:`_fixed_gain_means`)
PROTOCOL_TKF, FIXED_GAIN = 18, 19
#: update code of the fading Tobit Kalman filter (Geng et al. 2017): the Tobit update of the augmented state at the
#: step's rows :math:`H_k`, with the inverse Mills ratio among its outputs (written in the loop, beside the Kalman
#: filter's update, whose gain and covariance update it shares;
#: :func:`~tobitkf.filters._compiled_fading.fading_lower_block`)
FADING = 20
#: every update code of :func:`compiled_loop`
CODES = (*FAMILIES.values(), BLOCK, KALMAN, TOBIT, PROTOCOL_TKF, FIXED_GAIN, FADING)
#: the loop's update codes as types (:func:`~tobitkf.filters._compiled_moments.kind`: a tuple of ``code`` Nones),
#: what its callers pass as ``family``
KALMAN_KIND, TOBIT_KIND, PROTOCOL_TKF_KIND, FADING_KIND = kind(KALMAN), kind(TOBIT), kind(PROTOCOL_TKF), kind(FADING)
FIXED_GAIN_KIND = kind(FIXED_GAIN)


@njit(cache=True, error_model="numpy", inline="always")
def _kalman_moments(C, R, Pp, xp, y, r0, t, e, CP, Rxe, Ree, ok, nb):
    r"""The Kalman filter's innovation moments of a block (Miller (2.4)–(2.5)): :math:`R_{ee} = C\bar PC^T + R`,
    :math:`R_{xe} = \bar PC^T`, :math:`e = y - C\bar x`; a channel whose reading is NaN or whose innovation
    variance is not positive does not take part (its innovation set to 0)."""
    m, n = C.shape
    for l in range(m):
        for j in range(n):
            for b in range(nb):
                CP[l, j, b] = 0.0
            for k in range(n):
                c = C[l, k]
                for b in range(nb):
                    CP[l, j, b] += c * Pp[k, j, b]
    for l in range(m):
        for j in range(n):
            for b in range(nb):
                Rxe[j, l, b] = CP[l, j, b]
        for q in range(m):
            for b in range(nb):
                Ree[l, q, b] = 0.0
            for k in range(n):
                c = C[q, k]
                for b in range(nb):
                    Ree[l, q, b] += CP[l, k, b] * c
            rq = R[l, q]
            for b in range(nb):
                Ree[l, q, b] += rq
        for b in range(nb):
            s = 0.0
            for j in range(n):
                s += xp[j, b] * C[l, j]
            e[l, b] = y[r0 + b, t, l] - s
    _take_part(Ree, e, ok, m, nb)


@njit(cache=True, error_model="numpy")
def _channel_updates(family, npass, y, cls, has_cls, H, F, r, lo, hi, par, du, r0, t, xp, Pp, scratch, nb):
    r"""The assumed-density update of a block, channel by channel (module docstring): for each channel its row
    ``H[t]``, the noise variance ``r`` and the limits ``lo``/``hi`` (runs or 1, steps, m) of each run, the prior
    moments :math:`h\bar x + d`, :math:`h\bar Ph^T`, the noise variance plus the fading
    variance :math:`\sum_q f_q\bar Pf_q^T + (f_q\bar x)^2`, the family's :math:`(\alpha, \beta)` from
    :func:`~tobitkf.filters._compiled_moments.family_block`, and the rank-one change along :math:`\bar Ph^T`
    of ``xp``, ``Pp`` in place. ``family`` the family as a kind (:func:`~tobitkf.filters._compiled_moments.kind`:
    each family compiles its own version, holding its block function alone). ``npass = 2``: the readings inside
    their limits first, then the others.
    ``scratch`` = ``(Pc, scr, alpha, beta, llb, pt, compt, pub, compb, member, cv, buf)`` (:func:`_adf_scratch`):
    adds each channel's log-likelihood to ``llb`` (B,); ``pub`` (m, B), ``compb`` (m, J, B) its probability of
    an uncensored reading (of the pass that updated the run) and its components' posterior weights (of the last
    pass); the rest scratch."""
    Pc, scr, alpha, beta, llb, pt, compt, pub, compb, member, cv, buf = scratch
    m = y.shape[2]
    nx = xp.shape[0]
    Q = F.shape[2]
    hx, hph, rb, yv, lov, hiv = scr[0], scr[1], scr[2], scr[3], scr[4], scr[5]
    has_du = du.shape[1] > 0
    glx, glw = GL_X, GL_W
    th, tf, tr = min(t, H.shape[0] - 1), min(t, F.shape[0] - 1), min(t, r.shape[1] - 1)
    tl, tp = min(t, lo.shape[1] - 1), min(t, par.shape[0] - 1)
    nr, nl = r.shape[0] > 1, lo.shape[0] > 1  # noise / limits per run: run r0 + b of the block reads its own
    for b in range(nb):
        llb[b] = 0.0
    for pl in range(npass * m):
        ps, l = pl // m, pl % m
        h = H[th, l]
        # P h^T, h x + d, h P h^T
        for i in range(nx):
            for b in range(nb):
                Pc[i, b] = 0.0
        for k in range(nx):
            c = h[k]
            if c != 0.0:
                for i in range(nx):
                    for b in range(nb):
                        Pc[i, b] += Pp[k, i, b] * c
        for b in range(nb):
            s = 0.0
            q = 0.0
            for k in range(nx):
                s += h[k] * xp[k, b]
                q += h[k] * Pc[k, b]
            hx[b] = s + du[r0 + b, t, l] if has_du else s
            hph[b] = q
            rb[b] = r[r0 + b if nr else 0, tr, l]
        # the fading variance: sum_q f_q P f_q^T + (f_q x)^2
        for qq in range(Q):
            f = F[tf, l, qq]
            for k in range(nx):
                fk = f[k]
                if fk != 0.0:
                    for b in range(nb):
                        acc = 0.0
                        for j in range(nx):
                            acc += Pp[k, j, b] * f[j]
                        rb[b] += fk * acc
            for b in range(nb):
                s = 0.0
                for k in range(nx):
                    s += f[k] * xp[k, b]
                rb[b] += s * s
        for b in range(nb):
            yb = y[r0 + b, t, l]
            yv[b] = yb
            lo_l, hi_l = lo[r0 + b if nl else 0, tl, l], hi[r0 + b if nl else 0, tl, l]
            lov[b] = lo_l
            hiv[b] = hi_l
            c = cls[r0 + b, t, l] if has_cls else classify(yb, lo_l, hi_l)
            member[b] = npass == 1 or ((c == INTERIOR) == (ps == 0))
            cv[b] = c if member[b] else MISSING
        family_block(family, nb, yv, cv, hx, hph, rb, lov, hiv, par[tp, l], alpha, beta, llb, pt, compt, glx, glw, buf)
        # the rank-one update along P h^T
        for i in range(nx):
            for b in range(nb):
                xp[i, b] += alpha[b] * Pc[i, b]
        for i in range(nx):
            for j in range(i, nx):
                for b in range(nb):
                    Pp[i, j, b] -= beta[b] * Pc[i, b] * Pc[j, b]
        _mirror(Pp, nb)
        for b in range(nb):
            if member[b]:
                pub[l, b] = pt[b]
        for j in range(compt.shape[0]):
            for b in range(nb):
                compb[l, j, b] = compt[j, b]


@njit(cache=True, error_model="numpy", inline="always")
def _predict_runs(A, Qd, r0, t, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A_i\hat x`, :math:`\bar P = A_iPA_i^T + Q_i` of a block whose runs each have their own
    ``A`` / ``Qd`` (runs or 1, steps, n, n) (run ``r0 + b`` in lane b; index 0 where shared, step ``min(t, len -
    1)``); ``AP`` (n, n) scratch. :math:`\bar P` from its upper triangle with the symmetric part of Q, mirrored."""
    n = x.shape[0]
    ta, tq = min(t, A.shape[1] - 1), min(t, Qd.shape[1] - 1)
    na, nq = A.shape[0] > 1, Qd.shape[0] > 1
    for b in range(nb):
        Ab = A[r0 + b if na else 0, ta]
        Qb = Qd[r0 + b if nq else 0, tq]
        for i in range(n):  # zero entries of A skipped (a diagonal A costs n^2, not n^3)
            s = 0.0
            for j in range(n):
                s += Ab[i, j] * x[j, b]
            xp[i, b] = s
            for j in range(n):
                AP[i, j] = 0.0
            for k in range(n):
                a = Ab[i, k]
                if a != 0.0:
                    for j in range(n):
                        AP[i, j] += a * P[k, j, b]
        for i in range(n):
            for j in range(i, n):
                s = 0.0
                for k in range(n):
                    a = Ab[j, k]
                    if a != 0.0:
                        s += AP[i, k] * a
                v = s + 0.5 * (Qb[i, j] + Qb[j, i])
                Pp[i, j, b] = v
                Pp[j, i, b] = v


@njit(cache=True, error_model="numpy")
def _protocol_tkf_update(y, cls, H, F, r, lo, par, mode, joseph, r0, t, xp, Pp, x, P, blk, PC, mom, buf, nb):
    r"""The protocol Tobit Kalman filter's update of a block (Geng et al. (19)–(24)): the scheduled sensor's row
    :math:`\mathbf H = \bar\Lambda_h\mathcal C_h` ``H[t]`` (1, n_ξ), its :math:`\mathcal C_h` ``F[t, 0, 0]``, its
    noise variance ``r[0, t, 0]``, the threshold ``lo[0, 0, 0]``, ``par[t, 0]`` = (:math:`\bar\Lambda_h`,
    :math:`\check\Lambda_h`, the failure term of ``"lmmse_unconditional"``), the failure term's ``mode``
    (:func:`~tobitkf.filters._compiled_moments.protocol_tkf_block`), γ = ``cls == INTERIOR``; the moments of
    :func:`~tobitkf.filters._compiled_moments.protocol_tkf_block` into ``mom``, then
    :math:`K = P^-\mathbf H^T/R_{ee}` (0 for a run that does not take part), :math:`\hat\xi = \hat\xi^- + Ke`
    and the covariance in the standard or Joseph form (App. D (44)) of the shared update
    (:func:`~tobitkf.filters._compiled_block._cov_update`). ``PC`` (n_ξ, B) scratch."""
    P_, Pp_, AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    nx = xp.shape[0]
    th, tf, tp, tr = min(t, H.shape[0] - 1), min(t, F.shape[0] - 1), min(t, par.shape[0] - 1), min(t, r.shape[1] - 1)
    h, c = H[th, 0], F[tf, 0, 0]
    rv = r[0, tr, 0]
    # R_xe = P H^T, and P C^T for the failure term
    for i in range(nx):
        for b in range(nb):
            Rxe[i, 0, b] = 0.0
            PC[i, b] = 0.0
        for k in range(nx):
            hk = h[k]
            ck = c[k]
            for b in range(nb):
                Rxe[i, 0, b] += Pp[i, k, b] * hk
                PC[i, b] += Pp[i, k, b] * ck
    for j in range(4):
        for b in range(nb):
            mom[j, b] = 0.0
    for j in range(nx):
        hj = h[j]
        cj = c[j]
        for b in range(nb):
            mom[0, b] += xp[j, b] * hj
            mom[1, b] += Rxe[j, 0, b] * hj
            mom[2, b] += PC[j, b] * cj
            mom[3, b] += xp[j, b] * cj
    for b in range(nb):
        mom[14, b] = y[r0 + b, t, 0]
        ok[0, b] = cls[r0 + b, t, 0] == INTERIOR
        gam[0, b] = 1.0
    lm, lv, fixed = par[tp, 0, 0], par[tp, 0, 1], par[tp, 0, 2]
    protocol_tkf_block(nb, mom, ok[0], math.sqrt(rv), rv, lo[0, 0, 0], lm, lv, fixed, mode, GL_X, GL_W, buf)
    for b in range(nb):
        noise[0, 0, b] = mom[11, b]
    for i in range(nx):
        for b in range(nb):
            K[i, 0, b] = Rxe[i, 0, b] / mom[12, b] if ok[0, b] else 0.0
    # (19), (22): the mean; (20) or App. D (44): the covariance. A run left out has K = 0 and e = 0: its
    # prediction, unchanged
    for i in range(nx):
        for b in range(nb):
            x[i, b] = xp[i, b] + K[i, 0, b] * mom[13, b]
    _cov_update(Pp, K, Rxe, H[th], gam, noise, joseph, P, MH, nb)


@njit(cache=True, error_model="numpy")
def _fixed_gain_means(y, A, C, par, code, x0, means, pmeans, comp, x_last):
    r"""The steady-state Tobit Kalman filter's means over N runs x T steps (Miller (3.56)–(3.58); its covariances
    are the constants of the modified DARE, not computed here):

    .. math::

        \bar x_k = A\hat x_{k-1}, \quad \bar y_k = C\bar x_k, \quad
        \hat x_k = \bar x_k + K_\infty\big(y_k - (\bar y_k + o)\big),

    ``par`` (m, 2 + n): per channel the signed offset :math:`o = \mp\sigma[\phi(\alpha) - (1 - \Xi)\alpha]` of
    (3.58), the signed shift :math:`\pm\sigma\Phi^{-1}(\Xi)` of the limit (3.56) and the gain's column
    :math:`K_\infty[:, l]`; ``code`` bit 0: right censoring (upper), bit 1: latent readings, which the sensor
    clips at the limit :math:`T_k = \bar y_k + \text{shift}` (``min`` for right censoring, ``max`` for left)
    before the update, the limits and the clipped readings going to ``comp`` (N, T, m, 2). Runs in blocks,
    every inner loop over the block and branch-free (the side and latent tests hoisted out of it)."""
    N, T, m = y.shape
    n = A.shape[0]
    upper, latent = (code & 1) == 1, (code & 2) == 2
    B, S = _block_dims(N, T, 0, runs_per_block(n))
    x, xp, e, ybar = _mean_scratch(n, m, B)
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_comp = np.empty(_stage_shape(comp, B, S))
    want_x = comp.shape[1] > 0
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        for b in range(nb):
            for i in range(n):
                x[i, b] = x0[r0 + b, i]
        for t in range(T):
            tt = t % S
            mean_predict(A, x, xp, nb)  # x_bar = A x
            for l in range(m):
                for b in range(nb):
                    ybar[l, b] = 0.0
                for j in range(n):
                    cl = C[l, j]
                    for b in range(nb):
                        ybar[l, b] += cl * xp[j, b]
                for b in range(nb):
                    e[l, b] = y[r0 + b, t, l]
                if latent:  # the sensor's clip at the limit (3.56)
                    sh = par[l, 1]
                    if upper:
                        for b in range(nb):
                            e[l, b] = min(e[l, b], ybar[l, b] + sh)
                    else:
                        for b in range(nb):
                            e[l, b] = max(e[l, b], ybar[l, b] + sh)
                    if want_x:
                        for b in range(nb):
                            s_comp[tt, l, 0, b] = ybar[l, b] + sh
                            s_comp[tt, l, 1, b] = e[l, b]
                off = par[l, 0]
                for b in range(nb):
                    e[l, b] = e[l, b] - (ybar[l, b] + off)  # y - E[y] (3.58)
            for i in range(n):  # x = x_bar + K e
                for b in range(nb):
                    x[i, b] = xp[i, b]
                for l in range(m):
                    k = par[l, 2 + i]
                    for b in range(nb):
                        x[i, b] += k * e[l, b]
            _stage_mean(xp, s_pmean, tt, nb)
            _stage_mean(x, s_mean, tt, nb)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_comp, comp, r0, t0, nb, tt + 1)
        for b in range(nb):
            for i in range(n):
                x_last[r0 + b, i] = x[i, b]


@njit(cache=True, error_model="numpy", inline="always")
def _loop_scratch(family, n, nx, m, J, B, S, TK, buf, means, covs, pmeans, pcovs, pu, ey, ll, comp):
    """The loop's own scratch beyond the block's (:func:`~tobitkf.filters._compiled_block._update_scratch`),
    sized to the family of code ``family`` (an array it does not use gets no room; a constant where the loop is
    compiled for one family):
    ``APr`` (n, n) of :func:`_predict_runs`; ``Kall`` (TK, n, m) the shared Kalman gains (TK = 0: not shared);
    ``mom`` (20, B) of the protocol TKF (0 rows otherwise); the assumed-density scratch of
    :func:`_channel_updates` ``(Pc, scr, alpha, beta, llb, pt, compt, pub, compb, member, cv, buf)``, its run
    axis of length 0 for a family that does not use it (``Pc`` (nx, B) also the protocol TKF's, ``compb``
    (m, J, B) also the fading TKF's inverse Mills ratios; ``compt``, ``compb`` zeroed; ``buf`` the quadrature
    buffer passed in); and the staging buffers of the eight outputs (``(0, ..., B)`` for one not requested,
    :func:`~tobitkf.filters._compiled_block._stage_shape`), in the order mean, cov, pred. mean, pred. cov,
    pu, ey, ll, comp."""
    adf = family < KALMAN
    Ba = B if adf else 0
    Bq = B if adf or family == PROTOCOL_TKF else 0
    Bc = B if adf or family == FADING else 0
    sAP, sK, smom = (n, n), (TK, n, m), (20 if family == PROTOCOL_TKF else 0, B)
    sPc, sscr, sv, spub, scompt, scompb = (nx, Bq), (6, Ba), (Ba,), (m, Ba), (J, Ba), (m, J, Bc)
    m1, m2, m3, m4 = (
        _stage_shape(means, B, S),
        _stage_shape(covs, B, S),
        _stage_shape(pmeans, B, S),
        _stage_shape(pcovs, B, S),
    )
    o1, o2, o3, o4 = _stage_shape(pu, B, S), _stage_shape(ey, B, S), _stage_shape(ll, B, S), _stage_shape(comp, B, S)
    APr, Kall, mom = np.empty(sAP), np.empty(sK), np.empty(smom)
    Pc, scr, alpha, beta, llb, pt = (
        np.empty(sPc),
        np.empty(sscr),
        np.empty(sv),
        np.empty(sv),
        np.empty(sv),
        np.empty(sv),
    )
    pub, compt, compb = np.empty(spub), np.zeros(scompt), np.zeros(scompb)
    s_mean, s_cov, s_pmean, s_pcov = np.empty(m1), np.empty(m2), np.empty(m3), np.empty(m4)
    s_pu, s_ey, s_ll, s_comp = np.empty(o1), np.empty(o2), np.empty(o3), np.empty(o4)
    member, cv = np.empty(Ba, dtype=np.bool_), np.empty(Ba, dtype=np.int8)
    adfs = (Pc, scr, alpha, beta, llb, pt, compt, pub, compb, member, cv, buf)
    return APr, Kall, mom, adfs, (s_mean, s_cov, s_pmean, s_pcov, s_pu, s_ey, s_ll, s_comp)


@njit(cache=True, error_model="numpy", nogil=True)
def compiled_loop(
    family,
    y,
    cls,
    A,
    Qd,
    H,
    F,
    r,
    lo,
    hi,
    par,
    J,
    npass,
    noise_code,
    joseph,
    bu,
    du,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    ll,
    comp,
    x_last,
    P_last,
):
    r"""The one compiled time loop of the Gaussian-update families over N runs x T steps; fills the outputs.

    ``family``: the update, as a kind (:func:`~tobitkf.filters._compiled_moments.kind`, the tuple of ``code``
    Nones) of one of :data:`CODES`: :data:`KALMAN`, :data:`TOBIT` (a joint update of all channels), an
    assumed-density family of :data:`~tobitkf.filters._compiled_moments.FAMILIES` or a channel's own block
    (:func:`~tobitkf.filters._compiled_moments.block_kind`) (channel by channel, module docstring), :data:`PROTOCOL_TKF`, :data:`FIXED_GAIN` or :data:`FADING`. Each family compiles its own version
    of the loop, chosen by numba's ordinary dispatch on the argument types, which holds that family's update alone
    (numba reads the tuple's length as a constant and prunes the branches of the others before typing: compiled
    with a run-time code, the loop held every family's update, and the Kalman filter's version took minutes to
    compile).
    ``y`` (N, T, m) readings (NaN: missing); ``cls`` (N, T, m) int8 their classes, or (N, 0, m): by the limit
    rule (assumed-density families only); ``A``, ``Qd`` (NA, TA, n, n) acting on the top block of the state
    (n_x = ``x0.shape[1]`` > n: the block shift); ``H`` (TH, m, n_x) the rows (KF, TKF: C, one row); ``F`` (TF,
    m, Q, n_x) the fading rows; ``r`` (NR, TR, m) the noise variances (TKF: the standard deviations σ); ``lo``,
    ``hi`` (NL, TL, m) the limits; ``par`` (TP, m, K) the family's parameters (KF: R, one row); per-step arrays
    indexed by ``min(t, len - 1)``, the run axis of ``A``, ``Qd``, ``r``, ``lo``, ``hi`` by the run (0 when
    its length is 1: shared; a transition or noise per run is taken lane by lane, :func:`_predict_runs`, for a
    state without the block shift). ``J`` the mixture components, ``npass`` 1 or 2 (assumed-density: the readings
    inside their limits first); ``noise_code`` the TKF's :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`,
    ``joseph`` the Joseph form (KF, TKF); ``bu`` (N, T, n) / ``du`` (N, T, m) the input terms (T axis 0:
    none); ``x0`` (N, n_x), ``P0`` (N or 1, n_x, n_x). Outputs (T axis 0: not written): ``means``,
    ``pmeans`` (N, T, n), ``covs`` (N, T, n, n) or (N, T, n, 1) (the variances), ``pcovs`` (N, T, n, n),
    ``pu``, ``ey`` (N, T, m) (P(uncensored), the TKF's E(y)), ``ll`` (N, T), ``comp`` (N, T, m, J) (:data:`FADING`:
    J = 1, the inverse Mills ratios); for an augmented state ``means`` may be (N, T, n_x) (every block) or
    (N, T, n + n_x) (the top block, then every block), ``covs`` (N, T, n_x, n) (the n x n diagonal blocks) or
    (N, T, n + n_x, n) (the top block, then the diagonal blocks) (:func:`~tobitkf.filters._compiled_block._stage_mean`,
    :func:`~tobitkf.filters._compiled_block._stage_cov`);
    ``x_last``, ``P_last`` the state after the last step. The Kalman filter with one prior covariance
    (``P0`` (1, n, n), N > 1, nothing missing) runs the covariance and the gains once (``covs``, ``pcovs``,
    ``P_last`` with one run) and the means of every run with those gains."""
    code = len(family)  # a constant: numba rewrites the length of a tuple argument before typing
    if code > FADING:  # (a kind below KALMAN and of no family: family_block raises)
        raise ValueError("compiled_loop: family: expected the kind of an update code of CODES")
    N, T, m = y.shape
    if code == FIXED_GAIN:
        _fixed_gain_means(y, A[0, 0], H[0], par[0], noise_code, x0, means, pmeans, comp, x_last)
        return
    nx = x0.shape[1]
    n = A.shape[2]
    adf = code < KALMAN  # an assumed-density family: channel by channel (_channel_updates)
    # a transition or noise per run (run axis longer than 1): each lane of a block its own (_predict_runs)
    per_run = A.shape[0] > 1 or Qd.shape[0] > 1
    shared = code == KALMAN and P0.shape[0] == 1 and N > 1 and not per_run
    runs = 1 if shared else N
    B, S = _block_dims(runs, T, 0 if code == KALMAN else n * n, AUG_BLOCK if code == FADING else runs_per_block(nx))
    # the scratch sized to the family
    x, xp, e, mu = _mean_scratch(nx, m, B)
    sc = _update_scratch(nx, n, 0 if adf else m, B, 0 if code == KALMAN else GL_X.shape[0])
    blk = sc[0]
    P, Pp, AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    Rs, Ws, Ks, oks, Rxs, ds = sc[1]
    Rw, Wb, db, bad = sc[2]
    buf = sc[3]
    APr, Kall, mom, adfs, stg = _loop_scratch(
        code, n, nx, m, J, B, S, T if shared else 0, sc[3], means, covs, pmeans, pcovs, pu, ey, ll, comp
    )
    s_mean, s_cov, s_pmean, s_pcov, s_pu, s_ey, s_ll, s_comp = stg
    pub, compb = adfs[7], adfs[8]
    llf, compf = adfs[4].reshape((1, adfs[4].shape[0])), compb.reshape((m * J, compb.shape[2]))
    C = H[0]
    if code == KALMAN:
        gam[:, :] = 1.0  # H = C
        for l in range(m):
            for q in range(m):
                noise[l, q, :] = par[0, l, q]
    has_cls, has_bu, has_du = cls.shape[1] > 0, bu.shape[1] > 0, du.shape[1] > 0
    want_comp = comp.shape[1] > 0
    one_p = P0.shape[0] == 1
    # What the time loop reads but does not change is taken here, once: every array view made or tuple item taken
    # inside it costs an atomic increment and decrement of the array's reference count per step and block, and an
    # output not requested gets no call at all. With these and the fading update written out below (no function
    # inlined by numba with the block's arrays as arguments) the fading version's time loop went from 44 to 3
    # reference-count increments in its LLVM IR; the fading TKF (n = 2, L = 2, 5,000 runs x 100 steps, thread CPU
    # time of the loop, fastest of 11 calls, 3 processes each alternated, load ~13): means 79-96 -> 69-73, mean and
    # covariance 83-89 -> 76-77 ns per run-step. The Tobit KF's likewise (its statistics called, tobit_stats_block,
    # instead of the inlined tobit_update_block): 40 -> 3 increments in the time loop (n = 4, m = 2)
    At, Qt = A[0, 0], Qd[0, 0]
    tv_a = A.shape[1] > 1 or Qd.shape[1] > 1
    sig, lo0, hi0, lam = r[0, 0], lo[0], hi[0], compb.reshape((m, compb.shape[1] * compb.shape[2]))
    want_pred, want_post = s_pmean.shape[0] + s_pcov.shape[0] > 0, s_mean.shape[0] + s_cov.shape[0] > 0
    want_x = s_pu.shape[0] + s_ey.shape[0] + s_comp.shape[0] > 0
    for r0 in range(0, runs, B):
        nb = min(B, runs - r0)
        for b in range(nb):
            rp = 0 if one_p else r0 + b
            for i in range(nx):
                x[i, b] = x0[r0 + b, i]
                for j in range(nx):
                    P[i, j, b] = P0[rp, i, j]
        for t in range(T):
            tt = t % S
            if per_run:  # (the augmented state's block shift takes shared matrices only)
                _predict_runs(A, Qd, r0, t, x, P, xp, Pp, APr, nb)
            else:
                if tv_a:
                    At, Qt = A[0, min(t, A.shape[1] - 1)], Qd[0, min(t, Qd.shape[1] - 1)]
                if nx == n:
                    _predict(At, Qt, x, P, xp, Pp, AP, nb)
                else:
                    shift_predict_block(At, Qt, x, P, xp, Pp, AP, nb)
            if has_bu:  # xbar = A x + B^u u_k
                for i in range(n):
                    for b in range(nb):
                        xp[i, b] += bu[r0 + b, t, i]
            if want_pred:
                _stage(xp, Pp, tt, nb, s_pmean, s_pcov)
            if code == PROTOCOL_TKF:
                Pc = adfs[0]
                _protocol_tkf_update(
                    y, cls, H, F, r, lo, par, noise_code, joseph, r0, t, xp, Pp, x, P, blk, Pc, mom, sc[3], nb
                )
                if want_comp:  # the step's scalars, then the augmented posterior and prior means
                    for i in range(len(PROTOCOL_TKF_EXTRAS)):
                        for b in range(nb):
                            s_comp[tt, 0, i, b] = mom[4 + i, b]
                    i0 = len(PROTOCOL_TKF_EXTRAS)
                    for i in range(nx):
                        for b in range(nb):
                            s_comp[tt, 0, i0 + i, b] = x[i, b]
                            s_comp[tt, 0, i0 + nx + i, b] = xp[i, b]
            elif code == KALMAN or code == TOBIT or code == FADING:
                if code == KALMAN:
                    _kalman_moments(C, par[0], Pp, xp, y, r0, t, e, CP, Rxe, Ree, ok, nb)
                elif code == TOBIT:  # the channel statistics at the prior (Miller (3.8), (3.22), (3.32))
                    tl = min(t, lo0.shape[0] - 1)
                    tobit_stats_block(
                        C, sig, lo0, hi0, tl, 0, y, du, r0, t, noise_code, GL_X, GL_W, xp, mu, e, gam, noise, buf, nb
                    )
                else:  # the fading TKF (Geng et al. 2017, Table 1) at the rows H_k of the step
                    if t < H.shape[0]:  # H_min(k, L): the last row from then on
                        C = H[t]
                    tl = min(t, lo0.shape[0] - 1)
                    for l in range(m):  # Lemma 1 at chi = H_k xi + D u; (21), (12) or the censored variance; y - E[y]
                        for b in range(nb):  # chi for the whole block (vectorised; the numpy path's sums in order)
                            mu[l, b] = 0.0
                        for j in range(nx):
                            c = C[l, j]
                            for b in range(nb):
                                mu[l, b] += xp[j, b] * c
                        if has_du:
                            for b in range(nb):
                                mu[l, b] += du[r0 + b, t, l]
                        sd, lo_l, hi_l = sig[l], lo0[tl, l], hi0[tl, l]
                        if hi_l == _INF and lo_l != -_INF:  # a lower limit alone: the block at once, vectorised
                            fading_lower_block(mu, l, sd, lo_l, nb, noise_code, gam, lam, noise)
                        else:
                            for b in range(nb):
                                st = censored_stats(mu[l, b], sd, lo_l, hi_l, GL_X, GL_W, buf)
                                gam[l, b] = st[2]
                                lam[l, b] = st[3]
                                noise[l, l, b] = noise_term(noise_code, mu[l, b], st[2], st[4], st[5], st[7])
                                mu[l, b] = st[6]
                        for b in range(nb):
                            e[l, b] = y[r0 + b, t, l] - mu[l, b]
                if code != KALMAN:  # Rxe = P C^T E(p), Ree = E(p) C P C^T E(p) + Ruu (TKF (3.39), (3.40)); fading:
                    # Sigma_xy = P G^T, Sigma_yy = G P G^T + N_k, G = diag(gamma) H_k (24)-(26)
                    _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
                # the masked gain and the mean ((23), (19)); the covariance, standard or Joseph form ((20'))
                if m > 1:
                    _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, Wb, db, bad, Rs, Ws, Ks, oks, Rxs, ds)
                else:
                    _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)
                if shared:
                    for i in range(n):
                        for l in range(m):
                            Kall[t, i, l] = K[i, l, 0]
                _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb)
                if code != KALMAN and want_x:  # P(uncensored), E[y] (the fading TKF: and the inverse Mills ratios)
                    _stage_rows(gam, s_pu, tt, nb)
                    _stage_rows(mu, s_ey, tt, nb)
                    if code == FADING:
                        _stage_rows(lam, s_comp, tt, nb)
            elif code < KALMAN:  # an assumed-density family
                _channel_updates(family, npass, y, cls, has_cls, H, F, r, lo, hi, par, du, r0, t, xp, Pp, adfs, nb)
                _stage_rows(pub, s_pu, tt, nb)
                _stage_rows(llf, s_ll, tt, nb)
                _stage_rows(compf, s_comp, tt, nb)
                x, xp = xp, x
                P, Pp = Pp, P
            if want_post:
                _stage(x, P, tt, nb, s_mean, s_cov)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_pu, pu, r0, t0, nb, tt + 1)
                _flush(s_ey, ey, r0, t0, nb, tt + 1)
                _flush(s_ll, ll, r0, t0, nb, tt + 1)
                _flush(s_comp, comp, r0, t0, nb, tt + 1)
        _store_last(x, P, r0, nb, x_last, P_last)
    if code == KALMAN and shared:
        _shared_gain_means(A[0, 0], C, Kall, y, x0, means, pmeans, x_last)


@njit(cache=True, error_model="numpy")
def _shared_gain_means(A, C, Kall, y, x0, means, pmeans, x_last):
    """The Kalman filter's means of runs 1..N-1 with the gains ``Kall`` (T, n, m) of run 0 (one covariance shared
    by the runs: it does not depend on the readings)."""
    N, T, m = y.shape
    n = A.shape[0]
    xs = np.empty(n)
    xps = np.empty(n)
    es = np.empty(m)
    for r in range(1, N):
        for i in range(n):
            xs[i] = x0[r, i]
        for t in range(T):
            for i in range(n):
                s = 0.0
                for j in range(n):
                    s += A[i, j] * xs[j]
                xps[i] = s
                if pmeans.shape[1] > 0:
                    pmeans[r, t, i] = s
            for l in range(m):
                s = 0.0
                for j in range(n):
                    s += xps[j] * C[l, j]
                es[l] = y[r, t, l] - s
            for i in range(n):
                s = 0.0
                for l in range(m):
                    s += Kall[t, i, l] * es[l]
                xs[i] = xps[i] + s
                if means.shape[1] > 0:
                    means[r, t, i] = xs[i]
        for i in range(n):
            x_last[r, i] = xs[i]
