r"""Compiled (numba) time loops of the Kalman filter and the Tobit Kalman filter.

These kernels are an *implementation* of the numpy reference paths in
:mod:`tobitkf.filters.kalman` and :mod:`tobitkf.filters.tobit`, not a second
algorithm: same equations (Miller (2015) (2.3)–(2.6); (3.20)–(3.22), (3.32),
(3.37)–(3.41), (3.55)), same channel masking as
:func:`tobitkf.filters.core.gain_update` (missing or degenerate channels get a
zero gain column), same symmetrization after each predict and update, and the same
censored-normal statistics as :func:`tobitkf.censored.censored_moments` (direct
formulas in the central region; 64-node Gauss–Legendre quadrature in shifted
coordinates when the uncensored window lies beyond 4σ in a tail or is narrower than
1σ); a channel with one finite limit shared by the runs of a block (the common Tobit case) takes the
vectorised statistics of :mod:`tobitkf.filters._kernels_censored` for all runs of the block at once.
Results agree with the numpy path to rounding (tested to 1e-12).

Covered cases (the dispatchers in ``kalman.py`` / ``tobit.py`` decide, with
:func:`tobitkf.filters._backend.system_gap`): time-invariant A, C, Q, R (and B); for the TKF also
control inputs through constant B^u and D (the KF kernel takes none); any censoring limits (constant or
``(T, m)``, one- or two-sided, so the multi-region TKF of :func:`tobitkf.multi_region`, whose sensors
are stacked channels, runs here), NaN (missing) measurements, every ``noise_term`` and both
``covariance_update`` forms. Everything else runs on numpy.

Runs are processed in blocks of :func:`runs_per_block` runs (outer loop) over time (inner loop), the
block's state in structure-of-arrays scratch (innermost loops over the runs of the
block, which are independent: one run alone is a latency-bound chain), and the outputs
staged for :data:`CHUNK` steps before they are written run by run into the
preallocated ``(N, T, ...)`` arrays. Functions are compiled on first use and cached on
disk (``cache=True``). The kernels release the GIL (``nogil=True``), so threads (e.g. a
threaded Dask scheduler) can run several filters at once.

Symbols: ``gam`` = E(p) = γ (P(uncensored)), ``lam`` = inverse Mills ratio λ,
``Ruu`` = the noise term :math:`R_{uu}` of (3.40), ``Rxe``/``Ree`` of (3.39)/(3.40).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..censored import _CF_FROM, _CF_TERMS, _FAR, _GL_W, _GL_X, _NARROW, _TAIL
from ._kernels_block import (
    _block_dims,
    _cov_update,
    _flush,
    _gain,
    _gain_block,
    _innovation_moments,
    _load,
    _mean_scratch,
    _predict,
    _stage,
    _stage_shape,
    _store_last,
    _update_scratch,
    runs_per_block,
)
from ._kernels_censored import one_sided_block

__all__ = [
    "censored_stats",
    "censored_moments_array",
    "tkf_kernel",
    "kf_kernel",
    "tobit_update_block",
    "NOISE_CODES",
    "GL_X",
    "GL_W",
]

NOISE_CODES = {"dissertation": 0, "total_variance": 1, "exact_pv": 2}
GL_X, GL_W = _GL_X, _GL_W  # the quadrature of censored_moments (passed to the kernels)

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)
_INF = math.inf
_TINY = float(np.finfo(np.float64).tiny)  # R_ee diagonals not above this count as 0 (as gain_update)


@njit(cache=True, error_model="numpy")
def _ndtr_pair(x):
    """``(Phi(x), Phi(-x))`` from one erf/erfc call, by the cephes algorithm of scipy.special.ndtr
    (``0.5 + 0.5 erf(x/sqrt2)`` in the centre, ``0.5 erfc(|x|/sqrt2)`` in the tails, accurate in both)."""
    if x == _INF:
        return 1.0, 0.0
    if x == -_INF:
        return 0.0, 1.0
    z = x * _SQRT1_2
    if abs(z) < _SQRT1_2:
        h = 0.5 * math.erf(z)
        return 0.5 + h, 0.5 - h
    y = 0.5 * math.erfc(abs(z))
    if z > 0:
        return 1.0 - y, y
    return y, 1.0 - y


# exp on the quadrature exponents without a libm call per node, so that the 64-node loop
# vectorises: exp(z) = 2^k exp(r), k = round(z / ln 2), |r| <= ln(2)/2, exp(r) by its
# degree-12 Taylor polynomial (truncation < 2e-16 relative), 2^k from a table. The
# exponents -a2 u - u^2/2 lie in [-40.2, 0.125] (a2 >= -1/2 and the cut at density e^-40),
# so k in [-59, 0]; the table spans [-64, 1] and the index is clamped.
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # fdlibm's split of ln 2: k * _LN2_HI is exact
_LN2_LO = 1.90821492927058770002e-10
_POW2_OFF = 64
_POW2 = 2.0 ** np.arange(-_POW2_OFF, 2, dtype=np.float64)


@njit(cache=True, error_model="numpy")
def _quadrature_moments(a2, b2, glx, glw, buf):
    """``(E[Z | window], Var[Z | window], P(window))`` of Z ~ N(0, 1) on [a2, b2] (mirrored to the upper
    tail): 64-node Gauss-Legendre in shifted coordinates u = z - a2, density exp(-a2 u - u^2/2) on
    [0, min(w, umax)]. Kept out of :func:`censored_stats` so that the common routes stay small."""
    umax = 80.0 / (a2 + math.hypot(a2, math.sqrt(80.0)))  # -a2 + sqrt(a2^2 + 80), no cancellation
    half = 0.5 * min(b2 - a2, umax)
    pow2 = _POW2
    top2 = pow2.shape[0] - 1
    for j in range(glx.shape[0]):
        u = half * (glx[j] + 1.0)
        z = -a2 * u - 0.5 * u * u
        # exp(z), vectorisable (see _POW2)
        k = math.floor(z * _LOG2E + 0.5)
        r = (z - k * _LN2_HI) - k * _LN2_LO
        e = 1.0 + r * (
            1.0
            + r
            * (
                1.0 / 2
                + r
                * (
                    1.0 / 6
                    + r
                    * (
                        1.0 / 24
                        + r
                        * (
                            1.0 / 120
                            + r
                            * (
                                1.0 / 720
                                + r
                                * (
                                    1.0 / 5040
                                    + r
                                    * (
                                        1.0 / 40320
                                        + r
                                        * (
                                            1.0 / 362880
                                            + r * (1.0 / 3628800 + r * (1.0 / 39916800 + r * (1.0 / 479001600)))
                                        )
                                    )
                                )
                            )
                        )
                    )
                )
            )
        )
        e *= pow2[min(max(int(k) + _POW2_OFF, 0), top2)]
        buf[0, j] = u
        buf[1, j] = glw[j] * half * e
    i0 = 0.0
    i1 = 0.0
    for j in range(glx.shape[0]):
        i0 += buf[1, j]
        i1 += buf[1, j] * buf[0, j]
    umean = i1 / i0
    i2 = 0.0
    for j in range(glx.shape[0]):
        d = buf[0, j] - umean
        i2 += buf[1, j] * d * d
    zvar = i2 / i0
    zm = a2 + umean
    gam = math.exp(-0.5 * a2 * a2 - _LOG_SQRT_2PI + math.log(i0))
    return zm, zvar, gam


@njit(cache=True, error_model="numpy")
def _lower_only(mu, sd, lo):
    """:func:`censored_stats` for a lower limit alone (the common TKF case): the same routes and the same
    arithmetic as the general code with ``hi = inf`` (direct formulas, or the continued fraction beyond
    4 sigma), without the upper limit's terms and branches."""
    a = (lo - mu) / sd
    s = 0.0
    if a > _CF_FROM:
        for k in range(int(_CF_TERMS / a) + 6, 1, -1):
            s = k / (a + s)
    return _lower_stats(mu, sd, lo, s)


@njit(cache=True, error_model="numpy", inline="always")
def _lower_stats(mu, sd, lo, s):
    """:func:`_lower_only` given its continued fraction ``s`` (unused when ``a`` is not beyond the tail
    bound)."""
    a = (lo - mu) / sd
    p_lo, q_a = _ndtr_pair(a)
    if a > _CF_FROM:
        t = 1.0 / (a + s)
        lam = a + t
        zvar = t * (s - t)
        gam = math.exp(-0.5 * a * a - _LOG_SQRT_2PI - math.log(lam))
    else:
        gam = q_a if a > 0 else 1.0 - p_lo
        phi_a = math.exp(-0.5 * a * a - _LOG_SQRT_2PI)
        lam = phi_a / gam
        zvar = 1.0 + (a * phi_a) / gam - lam * lam
    gam = min(max(gam, 0.0), 1.0)
    zvar = max(zvar, 0.0)
    tmean = mu + sd * lam
    tvar = sd * sd * zvar
    cmean = gam * tmean
    if p_lo > 0:
        cmean = p_lo * lo + cmean
    cvar = gam * (tvar + (tmean - cmean) ** 2)
    if p_lo > 0:
        cvar += p_lo * (lo - cmean) ** 2
    return p_lo, 0.0, gam, lam, tmean, tvar, cmean, cvar


@njit(cache=True, error_model="numpy", inline="always")
def censored_stats(mu, sd, lo, hi, glx, glw, buf):
    """Censored-normal statistics of one channel, as :func:`tobitkf.censored.censored_moments`.

    ``buf`` is a (2, len(glx)) scratch array for the quadrature nodes and weights.
    Returns ``(p_lower, p_upper, p_uncensored, inverse_mills, truncated_mean,
    truncated_var, censored_mean, censored_var)``.

    Inlined into the caller (numba ``inline="always"``), so the common case, a lower limit alone, is one
    call of :func:`_lower_only` with scalar arguments: a call that passes the three arrays costs more
    than the statistics (measured: 84 ns per call through it against 36 for :func:`_lower_only`, the
    arrays' reference counting included); everything else is :func:`_general_stats`.
    """
    if hi == _INF and lo != -_INF:
        return _lower_only(mu, sd, lo)
    return _general_stats(mu, sd, lo, hi, glx, glw, buf)


@njit(cache=True, error_model="numpy")
def _general_stats(mu, sd, lo, hi, glx, glw, buf):
    """:func:`censored_stats` for any limits (two-sided, upper only, none)."""
    a = -_INF if lo == -_INF else (lo - mu) / sd
    b = _INF if hi == _INF else (hi - mu) / sd
    p_lo, q_a = _ndtr_pair(a)  # Phi(a), Phi(-a)
    q_b, p_hi = _ndtr_pair(b)  # Phi(b), Phi(-b)
    flip = a < -b  # windows in the lower tail are mirrored to the upper tail
    a2 = -b if flip else a
    b2 = -a if flip else b
    one_sided = b2 == _INF or (b2 - a2) * (b2 + a2) > _FAR
    if one_sided and a2 > _CF_FROM:
        # one-sided tail: Laplace's continued fraction for the Mills ratio, evaluated backwards
        # (s = 2/(x + 3/(x + ...)), t = 1/(x + s), lambda = x + t, Var = t (s - t))
        s = 0.0
        for k in range(int(_CF_TERMS / a2) + 6, 1, -1):
            s = k / (a2 + s)
        t = 1.0 / (a2 + s)
        zm = a2 + t
        zvar = t * (s - t)
        lam = -zm if flip else zm
        gam = math.exp(-0.5 * a2 * a2 - _LOG_SQRT_2PI - math.log(zm))
    elif (a2 > _TAIL and not one_sided) or (b - a < _NARROW):
        # window narrow, or two-sided in a tail: shifted coordinates u = z - a2,
        # density exp(-a2 u - u^2/2) on [0, min(w, umax)], 64-node Gauss-Legendre
        zm, zvar, gam = _quadrature_moments(a2, b2, glx, glw, buf)
        lam = -zm if flip else zm
    else:
        # gamma = Phi(b) - Phi(a), subtracting the small tail probabilities
        if a > 0:
            gam = q_a - p_hi
        elif b < 0:
            gam = q_b - p_lo
        else:
            gam = 1.0 - p_lo - p_hi
        phi_a = 0.0
        aphi_a = 0.0
        if a != -_INF:
            phi_a = math.exp(-0.5 * a * a - _LOG_SQRT_2PI)
            aphi_a = a * phi_a
        phi_b = 0.0
        bphi_b = 0.0
        if b != _INF:
            phi_b = math.exp(-0.5 * b * b - _LOG_SQRT_2PI)
            bphi_b = b * phi_b
        lam = (phi_a - phi_b) / gam
        zvar = 1.0 + (aphi_a - bphi_b) / gam - lam * lam
    gam = min(max(gam, 0.0), 1.0)
    zvar = max(zvar, 0.0)
    tmean = mu + sd * lam
    tvar = sd * sd * zvar
    cmean = gam * tmean
    if p_lo > 0:
        cmean = p_lo * lo + cmean
    if p_hi > 0:
        cmean = cmean + p_hi * hi
    cvar = gam * (tvar + (tmean - cmean) ** 2)
    if p_lo > 0:
        cvar += p_lo * (lo - cmean) ** 2
    if p_hi > 0:
        cvar += p_hi * (hi - cmean) ** 2
    return p_lo, p_hi, gam, lam, tmean, tvar, cmean, cvar


@njit(cache=True, error_model="numpy")
def censored_moments_array(mu, sd, lo, hi, glx, glw):
    """:func:`censored_stats` over 1-d arrays of equal length; returns an (8, K) array (testing aid)."""
    out = np.empty((8, mu.shape[0]))
    buf = np.empty((2, glx.shape[0]))
    for i in range(mu.shape[0]):
        st = censored_stats(mu[i], sd[i], lo[i], hi[i], glx, glw, buf)
        for j in range(8):
            out[j, i] = st[j]
    return out


# --- the Tobit Kalman filter -----------------------------------------------------------------


@njit(cache=True, error_model="numpy", inline="always")
def tobit_update_block(
    C,
    sigma,
    lo,
    hi,
    lrow,
    lstep,
    y,
    du,
    r0,
    t,
    noise_code,
    joseph,
    glx,
    glw,
    xp,
    Pp,
    mu,
    e,
    x,
    P,
    blk,
    run,
    solve,
    buf,
    nb,
):
    r"""The Tobit measurement update of a block of ``nb`` runs (Miller (3.37)–(3.41), (3.39)–(3.40), (3.32),
    (3.22), (3.55)), all channel statistics at the prior (Assumption A1, (3.35)): the step of
    :func:`tkf_kernel`, shared with the compiled closed loop of :mod:`tobitkf.control` (which runs the TKF
    as its observer), so that the update exists once.

    ``xp`` (n, B), ``Pp`` (n, n, B) the prediction; run b of the block reads its reading at
    ``y[r0 + b, t]`` (NaN: missing) and its feedthrough :math:`Du_k` at ``du[r0 + b, t]`` (``du`` with no
    steps, ``du.shape[1] == 0``: none); ``lo``/``hi`` (L, m) the limits, run b reading row
    ``lrow + lstep * b`` (``lstep = 0``: one row for the block, the limits of the step; ``lstep = 1``: one
    row per run). ``noise_code`` from :data:`NOISE_CODES`. Writes the posterior ``x`` (n, B), ``P``
    (n, n, B), :math:`E(y)` (3.8) in ``mu`` (m, B), the innovation :math:`y - E(y)` in ``e`` (m, B) (0 for
    a channel left out), and in ``blk`` (from :func:`_update_scratch`) ``gam`` = :math:`E(\mathbf p)` and
    the noise term :math:`R_{uu}` among the rest. A channel whose limits the block shares (``lstep = 0``)
    with one side infinite gets its statistics for all runs at once from
    :func:`~tobitkf.filters._kernels_censored.one_sided_block` (vectorised; 8 against 27 ns per run on the
    central route, 10 against 57 with tails, measured in isolation); any other from :func:`censored_stats`
    run by run. Inlined (numba
    ``inline="always"``): the caller's loop sees the statistics of :func:`censored_stats` inlined as before.
    """
    _P, _Pp, _AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    Rs, Ws, Ks, oks, Rxs, ds = run
    Rw, Wb, db, bad = solve
    m, n = C.shape
    has_du = du.shape[1] > 0
    for l in range(m):
        sd = sigma[l]
        lo_l, hi_l = lo[lrow, l], hi[lrow, l]
        if lstep == 0 and (lo_l == -_INF) != (hi_l == _INF):
            # one finite limit shared by the block (the common Tobit case): the statistics of all runs at
            # once, vectorised (_kernels_censored.one_sided_block); the means C xbar + D u staged in e[l]
            el = e[l]
            for b in range(nb):
                s = 0.0
                for j in range(n):
                    s += xp[j, b] * C[l, j]
                el[b] = s + du[r0 + b, t, l] if has_du else s
            upper = lo_l == -_INF
            one_sided_block(el, sd, hi_l if upper else lo_l, upper, nb, noise_code, gam[l], noise[l, l], mu[l])
            for b in range(nb):
                el[b] = y[r0 + b, t, l] - mu[l, b]
            continue
        for b in range(nb):
            s = 0.0
            for j in range(n):
                s += xp[j, b] * C[l, j]
            mean = s + du[r0 + b, t, l] if has_du else s  # C xbar + D u (the numpy path's x_pred @ C.T + dy)
            r = lrow + lstep * b
            st = censored_stats(mean, sd, lo[r, l], hi[r, l], glx, glw, buf)
            g = st[2]
            gam[l, b] = g
            if noise_code == 0:
                v = st[5]
            elif noise_code == 1:
                v = st[7]
            else:
                v = g * (st[5] + (st[4] - mean) ** 2)
            noise[l, l, b] = v
            e[l, b] = y[r0 + b, t, l] - st[6]
            mu[l, b] = st[6]
    # Rxe = Pbar C^T E(p), Ree = E(p) C Pbar C^T E(p) + Ruu  (3.39), (3.40)
    _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
    if m > 1:
        _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, Wb, db, bad, Rs, Ws, Ks, oks, Rxs, ds)
    else:
        _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)
    _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb)  # H = diag(E(p)) C (3.41)


@njit(cache=True, error_model="numpy", nogil=True)
def tkf_kernel(
    y,
    A,
    Qd,
    C,
    sigma,
    lo,
    hi,
    bu,
    du,
    x0,
    P0,
    noise_code,
    joseph,
    glx,
    glw,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ey,
    x_last,
    P_last,
):
    """TKF over ``N`` runs of ``T`` steps; fills the ``(N, T, ...)`` output arrays in place.

    ``y`` (N, T, m) (NaN = missing), ``A``/``Qd`` (n, n), ``C`` (m, n), ``sigma`` (m,),
    ``lo``/``hi`` (T, m), ``bu`` (N, T, n) the input offsets :math:`B^uu_k` of the predict and ``du``
    (N, T, m) the feedthrough :math:`Du_k` (each (N, 0, ...) without), ``x0`` (N, n), ``P0`` (N, n, n),
    ``noise_code`` from :data:`NOISE_CODES`. An output of shape ``(N, 0, ...)`` is not written (not
    requested); ``x_last`` (N, n) and ``P_last`` (N, n, n) receive the state after the last step.
    """
    N, T, m = y.shape
    n = A.shape[0]
    B, S = _block_dims(N, T, n * n, runs_per_block(n))
    x, xp, e, mu = _mean_scratch(n, m, B)
    blk, run, solve, buf = _update_scratch(n, n, m, B, glx.shape[0])
    P, Pp, AP, _CP, _Rxe, _Ree, _K, _MH, _noise, gam, _ok = blk
    # staging only for the requested outputs (an output of shape (N, 0, ...) gets a (0, S, ...) buffer)
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_cov, s_pcov = np.empty(_stage_shape(covs, B, S)), np.empty(_stage_shape(pcovs, B, S))
    s_pu, s_ey = np.empty(_stage_shape(pu, B, S)), np.empty(_stage_shape(ey, B, S))
    want_pu, want_ey = pu.shape[1] > 0, ey.shape[1] > 0
    has_bu = bu.shape[1] > 0
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x0, P0, r0, nb, x, P)
        for t in range(T):
            tt = t % S
            _predict(A, Qd, x, P, xp, Pp, AP, nb)
            if has_bu:  # xbar = A x + B^u u_k
                for i in range(n):
                    for b in range(nb):
                        xp[i, b] += bu[r0 + b, t, i]
            _stage(xp, Pp, tt, nb, s_pmean, s_pcov)
            tobit_update_block(
                C,
                sigma,
                lo,
                hi,
                t,
                0,
                y,
                du,
                r0,
                t,
                noise_code,
                joseph,
                glx,
                glw,
                xp,
                Pp,
                mu,
                e,
                x,
                P,
                blk,
                run,
                solve,
                buf,
                nb,
            )
            if want_pu or want_ey:
                for l in range(m):
                    for b in range(nb):
                        if want_pu:
                            s_pu[tt, l, b] = gam[l, b]
                        if want_ey:
                            s_ey[tt, l, b] = mu[l, b]
            _stage(x, P, tt, nb, s_mean, s_cov)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
                _flush(s_pu, pu, r0, t0, nb, tt + 1)
                _flush(s_ey, ey, r0, t0, nb, tt + 1)
        _store_last(x, P, r0, nb, x_last, P_last)


# --- the Kalman filter ---------------------------------------------------------------------


@njit(cache=True, error_model="numpy", nogil=True)
def kf_kernel(y, skip, A, Qd, C, R, x0, P0, joseph, means, covs, pmeans, pcovs, x_last, P_last):
    """KF over ``N`` runs; fills the outputs in place (an output of shape ``(N, 0, ...)`` is not
    written); ``x_last`` (N, n) and ``P_last`` (N or 1, n, n) receive the state after the last step.

    ``skip`` (N, T, m) bool marks channels left out (with NaN in ``y``). When ``covs``
    has one run and ``N > 1`` (shared covariance: no channel skipped, common prior) the
    covariance recursion and gains are computed once and only the means run per run;
    otherwise each run has its own covariance. ``x0`` (N, n), ``P0`` (N or 1, n, n).
    """
    N, T, m = y.shape
    n = A.shape[0]
    shared = covs.shape[0] == 1 and N > 1
    B, S = _block_dims(N, T, 0, runs_per_block(n))
    x, xp, e, _yb = _mean_scratch(n, m, B)
    blk, run, solve, _buf = _update_scratch(n, n, m, B, 0)
    P, Pp, AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    gam[:, :] = 1.0  # H = C
    Rs, Ws, Ks, oks, Rxs, ds = run
    Rw, Wb, db, bad = solve
    for l in range(m):
        for q in range(m):
            noise[l, q, :] = R[l, q]
    Kall = np.empty((T if shared else 0, n, m))
    runs = 1 if shared else N
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_cov, s_pcov = np.empty(_stage_shape(covs, B, S)), np.empty(_stage_shape(pcovs, B, S))
    for r0 in range(0, runs, B):
        nb = min(B, runs - r0)
        _load(x0, P0, r0, nb, x, P)
        for t in range(T):
            tt = t % S
            _predict(A, Qd, x, P, xp, Pp, AP, nb)
            _stage(xp, Pp, tt, nb, s_pmean, s_pcov)
            # Ree = C Pbar C^T + R, Rxe = Pbar C^T, e = y - C xbar  (2.4)–(2.5)
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
            for l in range(m):
                for b in range(nb):
                    good = (Ree[l, l, b] > _TINY) and not skip[r0 + b, t, l]
                    ok[l, b] = good
                    if not good:
                        e[l, b] = 0.0
            if m > 1:
                _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, Wb, db, bad, Rs, Ws, Ks, oks, Rxs, ds)
            else:
                _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)
            if shared:
                for i in range(n):
                    for l in range(m):
                        Kall[t, i, l] = K[i, l, 0]
            _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb)
            _stage(x, P, tt, nb, s_mean, s_cov)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_cov, covs, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_pcov, pcovs, r0, t0, nb, tt + 1)
        _store_last(x, P, r0, nb, x_last, P_last)
    if shared:
        # means of the other runs with the shared gains (the covariance does not depend on y)
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
