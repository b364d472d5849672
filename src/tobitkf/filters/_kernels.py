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

from .._linalg_kernels import gauss_solve as _gauss_solve
from ..censored import _CF_FROM, _CF_TERMS, _FAR, _GL_W, _GL_X, _NARROW, _TAIL
from ._kernels_censored import one_sided_block

__all__ = [
    "censored_stats",
    "censored_moments_array",
    "tkf_kernel",
    "kf_kernel",
    "tobit_update_block",
    "predict_block",
    "block_scratch",
    "stage_block",
    "flush_rows",
    "stage_shape",
    "CHUNK",
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


# --- block helpers -------------------------------------------------------------------------
# State of a block of up to runs_per_block(n) runs in structure-of-arrays layout: x[i, b], P[i, j, b].
# Runs are independent, so the innermost loops over b carry no dependency: the CPU
# overlaps the recursions of the runs (one run alone is a long latency chain) and LLVM
# vectorises the dense algebra over b.

BLOCK = 32  # runs per block from n = 13 on (runs_per_block: more at smaller n)
CHUNK = 64
FLUSH_BY_STEP = 32  # numbers per run-step from which _flush goes step by step
BLOCKED_N = 8  # state size from which the block products take the blocked loops (_predict_blocked)
STAGE_BYTES = 1 << 18  # at most this many bytes per staging buffer of tkf_kernel (fewer steps at large n)
# Outputs are staged for CHUNK steps of a block and then written run by run: writing
# every step straight into (N, T, ...) arrays touches B rows T*n*8 bytes apart,
# which for long records alias in the cache and miss the TLB on every store. The staging
# buffers are laid out (S, ..., B), the run innermost as in the block's state, so that the
# per-step copies into them are contiguous, vectorised loops over the block; the transpose
# to the run-major (N, T, ...) layout happens once per chunk in _flush (strided reads from
# the cache-resident buffer, contiguous writes). Measured on the steady-state TKF (n = 2,
# 10^4 runs x 100 steps, outputs preallocated): 15.6 ns per run-step against 21.2 ns with
# (B, S, ...) buffers written run by run at every step, and 17.2 ns writing the outputs directly.
# At large n a chunk of CHUNK steps no longer fits the core's L2 cache (n = 16: 64 steps x 256 numbers x 32
# runs = 4 MB per covariance buffer), and the staged copies went out to L3 and back: tkf_kernel stages
# at most STAGE_BYTES per buffer (n = 16: 4 steps; n = 2 keeps 64). Measured at n = 16, m = 8, all
# outputs into reused arrays (in-process A/B, thread CPU time, load 5.7): 3477 -> 2967 ns per run-step.


# --- the block scratch ---------------------------------------------------------------------
# One allocator of the block scratch for every kernel (here, _kernels_fading, _kernels_steady),
# called once per kernel call (never per block or step) and inlined into the kernel at the numba
# IR level, so that LLVM sees the arrays as fresh and unaliased. Not a workspace made by the
# Python driver and passed in: measured on the TKF, views cut from one passed-in buffer cost more
# to make than the allocations (21-33 ns against 20 ns per array) and made a single run's step
# markedly slower (n = 2, m = 1: 1.0-1.6 us against 0.7-1.2 us per step, CPU time on a loaded
# machine), LLVM no longer knowing that the arrays are distinct; a tuple of arrays passed in is
# unboxed array by array on every call (28 arrays: 7.3 us per call).


@njit(cache=True)
def runs_per_block(n):
    """Runs per block of the Kalman-type kernels (TKF, KF, steady-state, closed loop, the shared step) at
    state size ``n``: 128 up to n = 8, 64 up to n = 12, :data:`BLOCK` (32) beyond, plus 8 where slabs alias
    (below).

    A step of a block is some tens of short loops over its runs; at small n each loop's set-up (the
    vector loop's alias checks and remainder) is paid per loop, not per run, so more runs per block
    amortise it, until the block's arrays (n x n x B numbers each) leave the L1/L2 caches and the staging
    buffers get few steps (:data:`STAGE_BYTES`). Measured (4 Dec 2026, TKF kernel, outputs reused,
    thread CPU time, ns per run-step, B = 32 / 64 / 128): n = 2, m = 1 mean + cov 46.9 / 40.0 / 35.1,
    means 40.4 / 36.0 / 28.2, KF 24.4 / 30.2 / 17.1; n = 4, m = 1 mean + cov 91.6 / 104 / 78.0; n = 6, m = 2
    252-270 / 222-239 / 220-224; n = 8, m = 2 355-468 / 316-318 / 331-346; n = 12, m = 4 897-982 /
    845-870 / 852-858; n = 16, m = 8 mean + cov 2023 / 2186 / 2316 (the blocked slab loops run over all
    of a block's lanes at once already).

    From n = :data:`BLOCKED_N` on, 8 runs more when a slab ``P[k]`` of the block (``n * B * 8`` bytes; n = 16,
    B = 32: 4 KB) is a multiple of 4 KB: the slab products (:func:`_rows_times`) read four slabs and update
    four at once, and slabs 4 KB apart all fall into the same set of the 8-way L1 cache and evict each other.
    Measured at n = 16, m = 8, 10^3 runs x 100 steps (in-process A/B, thread CPU time, outputs reused, load
    1.6): means only 1408 -> 1344, all outputs 2303 -> 2071 ns per run-step with 40 runs per block against 32
    (48: the same as 40); at n = 8 (128 runs: 8 KB slabs) 136 runs against 128, alternated twice (load 1.7):
    n = 8, m = 2 mean + cov 257-270 against 283-306, m = 8 568-572 against 607-750 ns per run-step."""
    B = BLOCK
    if n <= 8:
        B = 128
    elif n <= 12:
        B = 64
    if n >= BLOCKED_N and (n * B * 8) % 4096 == 0:
        B += 8
    return B


@njit(cache=True)
def _block_dims(N, T, d=0, block=BLOCK):
    """``(B, S)``: runs per block and staged steps of a call of ``N`` runs x ``T`` steps (a single run,
    the online step, gets a single column, a single step a single staging slot). ``d`` the largest
    number of staged values per run-step (0: not given): S is cut so that one staging buffer holds at
    most :data:`STAGE_BYTES`; ``block`` the most runs per block (:data:`BLOCK`; the augmented-state loops
    take 64)."""
    B = min(block, max(N, 1))
    S = min(CHUNK, max(T, 1))
    if d > 0:
        S = max(1, min(S, STAGE_BYTES // (8 * d * B)))
    return B, S


@njit(cache=True, inline="always")
def _mean_scratch(dim, m, B):
    """The scratch of the mean recursion of a block: ``x``, ``xp`` (dim, B), ``e``, ``ybar`` (m, B)."""
    return np.empty((dim, B)), np.empty((dim, B)), np.empty((m, B)), np.empty((m, B))


@njit(cache=True, inline="always")
def _update_scratch(dim, ntop, m, B, G):
    """The scratch of the covariance recursion and the masked gain of a block of ``B`` runs.

    ``dim`` the state size, ``ntop`` the size of the block the transition acts on (``dim`` for the TKF
    and the KF, ``n`` for the shifted fading state), ``m`` channels, ``G`` quadrature nodes. Returns
    ``(P, Pp, AP, CP, Rxe, Ree, K, MH, noise, gam, ok)`` (``AP`` (dim, ntop, B), ``MH`` the scratch of
    :func:`_cov_update`, ``noise``
    (m, m, B) zeroed), the per-run solve scratch ``(Rs, Ws, Ks, oks, Rxs, ds)`` of :func:`_gain_of_run`,
    the block solve scratch ``(Rw, Wb, db, bad)`` of :func:`_gain_block` (empty for m = 1) and the
    (2, G) quadrature buffer of :func:`censored_stats`."""
    g = m if m > 1 else 0
    gb = B if m > 1 else 0
    blk = (
        np.empty((dim, dim, B)),  # P
        np.empty((dim, dim, B)),  # Pp
        np.empty((dim, ntop, B)),  # AP
        np.empty((m, dim, B)),  # CP
        np.empty((dim, m, B)),  # Rxe
        np.empty((m, m, B)),  # Ree
        np.empty((dim, m, B)),  # K
        np.empty((dim, m, B)),  # MH
        np.zeros((m, m, B)),  # noise
        np.empty((m, B)),  # gam
        np.empty((m, B), dtype=np.bool_),  # ok
    )
    run = (
        np.empty((m, m)),  # Rs
        np.empty((m, dim)),  # Ws
        np.empty((dim, m)),  # Ks
        np.empty(m, dtype=np.bool_),  # oks
        np.empty((dim, m)),  # Rxs
        np.empty(m),  # ds
    )
    solve = (np.empty((g, g, gb)), np.empty((g, dim if g else 0, gb)), np.empty((g, gb)), np.empty(gb, dtype=np.bool_))
    return blk, run, solve, np.empty((2, G))


@njit(cache=True)
def _stage_shape(out, B, S):
    """Shape of the staging buffer of the output ``out`` (N, T, ...): ``(S, ..., B)`` (chunk step first,
    run last: ``buf[tt, ..., b]``), or ``(0, ..., B)`` when the output is not requested
    (``out.shape[1] == 0``: no staging, not written)."""
    return (S if out.shape[1] > 0 else 0,) + out.shape[2:] + (B,)


@njit(cache=True, error_model="numpy")
def _symmetrize(P, nb):
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            for b in range(nb):
                v = 0.5 * (P[i, j, b] + P[j, i, b])
                P[i, j, b] = v
                P[j, i, b] = v


@njit(cache=True, error_model="numpy")
def _mirror(P, nb):
    """Copy the upper triangle of the block's ``P[i, j, b]`` onto the lower (the products below
    compute only ``j >= i`` of a symmetric result: half the work of the full product and
    :func:`_symmetrize`, equal to it to rounding)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            for b in range(nb):
                P[j, i, b] = P[i, j, b]


@njit(cache=True, error_model="numpy")
def _predict(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)` (Miller (2.3), (3.20)–(3.21)).

    From n = :data:`BLOCKED_N` on by :func:`_predict_blocked`; below, these short loops (the blocked
    ones made the n = 2, m = 1 TKF ~8% slower: 86 against 79 ns per run-step, in-process A/B)."""
    n = A.shape[0]
    if n >= BLOCKED_N:
        _predict_blocked(A, Qd, x, P, xp, Pp, AP, nb)
        return
    mean_predict(A, x, xp, nb)
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                AP[i, j, b] = 0.0
            for k in range(n):
                a = A[i, k]
                for b in range(nb):
                    AP[i, j, b] += a * P[k, j, b]
    for i in range(n):
        for j in range(i, n):
            for b in range(nb):
                Pp[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    Pp[i, j, b] += AP[i, k, b] * a
            q = 0.5 * (Qd[i, j] + Qd[j, i])
            for b in range(nb):
                Pp[i, j, b] += q
    _mirror(Pp, nb)


@njit(cache=True, error_model="numpy")
def _predict_blocked(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)` (Miller (2.3), (3.20)–(3.21)).

    Loop order for speed at larger n: ``AP`` row by row as :math:`(AP)_{i\cdot} = \sum_k A_{ik}P_{k\cdot}` over
    the whole contiguous slabs ``P[k]`` (n B numbers, all lanes of the block: lanes past ``nb`` hold an
    earlier block's values and are never read back) by :func:`_rows_times`, four rows and four terms per pass;
    :math:`\bar P_{ij}` (only ``j >= i``, mirrored) by :func:`_sym_times`, four entries and four terms per
    pass over the runs. Measured at n = 16, B = 32 (in isolation, thread CPU time, load 1.2): 659 -> 427 ns
    per run (one row and one term per pass for ``AP``, one entry and eight terms for :math:`\bar P`: 1040 ->
    ~600 ns before that, against one short loop over the runs per term)."""
    n = A.shape[0]
    W = P.shape[2]
    L = n * W
    mean_predict(A, x, xp, nb)
    _rows_times(AP.reshape((n, L)), A, P.reshape((n, L)), n, L, False)
    _sym_times(Pp, AP, A, Qd, True, n, W, False)
    _mirror(Pp, W)


@njit(cache=True, error_model="numpy")
def _rows_times(out, M, X, nk, L, skip_zero):
    """``out[i, q] = sum_k M[i, k] X[k, q]`` for every row i of ``M`` (``out`` (rows, L), ``X`` (nk, L), 2-d
    contiguous): the block products over the whole slabs of a block's lanes (:func:`_predict_blocked`,
    :func:`_innovation_moments_blocked`), in register tiles of four rows and four terms per pass over ``q``
    (four loads of ``X``, four loads and stores of the accumulators per sixteen products; one row and one
    term per pass loads and stores the accumulator once per product). Measured at n = 16, B = 32 (A P, in
    isolation, thread CPU time, load 1.2): 446 -> 298 ns per run. ``skip_zero``: a term whose coefficient
    is 0 is left out (the augmented measurement matrix of the fading TKF is mostly zeros), so that a tile
    with a zero coefficient takes its terms one at a time."""
    nr = M.shape[0]
    r4 = nr - nr % 4
    for i0 in range(0, r4, 4):
        for r in range(4):
            for q in range(L):
                out[i0 + r, q] = 0.0
        k = 0
        while k < nk:
            tile = k + 4 <= nk
            if tile and skip_zero:
                for r in range(4):
                    for c in range(4):
                        if M[i0 + r, k + c] == 0.0:
                            tile = False
            if tile:
                a00, a01, a02, a03 = M[i0, k], M[i0, k + 1], M[i0, k + 2], M[i0, k + 3]
                a10, a11, a12, a13 = M[i0 + 1, k], M[i0 + 1, k + 1], M[i0 + 1, k + 2], M[i0 + 1, k + 3]
                a20, a21, a22, a23 = M[i0 + 2, k], M[i0 + 2, k + 1], M[i0 + 2, k + 2], M[i0 + 2, k + 3]
                a30, a31, a32, a33 = M[i0 + 3, k], M[i0 + 3, k + 1], M[i0 + 3, k + 2], M[i0 + 3, k + 3]
                for q in range(L):
                    p0, p1, p2, p3 = X[k, q], X[k + 1, q], X[k + 2, q], X[k + 3, q]
                    out[i0, q] += (a00 * p0 + a01 * p1) + (a02 * p2 + a03 * p3)
                    out[i0 + 1, q] += (a10 * p0 + a11 * p1) + (a12 * p2 + a13 * p3)
                    out[i0 + 2, q] += (a20 * p0 + a21 * p1) + (a22 * p2 + a23 * p3)
                    out[i0 + 3, q] += (a30 * p0 + a31 * p1) + (a32 * p2 + a33 * p3)
                k += 4
                continue
            for r in range(4):
                a = M[i0 + r, k]
                if a != 0.0 or not skip_zero:
                    for q in range(L):
                        out[i0 + r, q] += a * X[k, q]
            k += 1
    for i in range(r4, nr):
        for q in range(L):
            out[i, q] = 0.0
        for k in range(nk):
            a = M[i, k]
            if a != 0.0 or not skip_zero:
                for q in range(L):
                    out[i, q] += a * X[k, q]


@njit(cache=True, error_model="numpy")
def _sym_times(out, X, M, Q, with_q, nk, W, skip_zero):
    r"""The upper triangle of ``out[i, j, b] = q_ij + sum_k X[i, k, b] M[j, k]`` (``j >= i``, ``k < nk``,
    ``b < W``; :math:`q_{ij}` the symmetric part of ``Q`` when ``with_q``, else 0): :math:`\bar P = (AP)A^T +
    \mathrm{sym}(Q)` of :func:`_predict_blocked` and :math:`C\bar PC^T` of :func:`_innovation_moments_blocked`,
    four entries ``j`` and four terms ``k`` per pass over the runs (the four loads of ``X[i, k]`` shared by
    the four entries; the last ``n - i`` mod 4 entries of a row one at a time). ``skip_zero``: a tile whose
    sixteen (or four) coefficients are all 0 is left out (the fading TKF's augmented C; a zero coefficient
    inside a tile adds an exact 0 for finite ``X``). Measured at n = 16, B = 32 ((AP)A^T in isolation,
    thread CPU time, load 1.2): 207 -> 149 ns per run against one entry and eight terms per pass (160 against
    320 ns for one term per pass)."""
    nr = out.shape[1]
    for i in range(out.shape[0]):
        j = i
        while j < nr:
            four = j + 4 <= nr
            jn = 4 if four else 1
            for r in range(jn):
                qr = 0.5 * (Q[i, j + r] + Q[j + r, i]) if with_q else 0.0
                for b in range(W):
                    out[i, j + r, b] = qr
            k = 0
            while k < nk:
                kn = 4 if k + 4 <= nk else 1
                if skip_zero:
                    nz = False
                    for r in range(jn):
                        for c in range(kn):
                            if M[j + r, k + c] != 0.0:
                                nz = True
                    if not nz:
                        k += kn
                        continue
                if four and kn == 4:
                    a00, a01, a02, a03 = M[j, k], M[j, k + 1], M[j, k + 2], M[j, k + 3]
                    a10, a11, a12, a13 = M[j + 1, k], M[j + 1, k + 1], M[j + 1, k + 2], M[j + 1, k + 3]
                    a20, a21, a22, a23 = M[j + 2, k], M[j + 2, k + 1], M[j + 2, k + 2], M[j + 2, k + 3]
                    a30, a31, a32, a33 = M[j + 3, k], M[j + 3, k + 1], M[j + 3, k + 2], M[j + 3, k + 3]
                    for b in range(W):
                        p0, p1, p2, p3 = X[i, k, b], X[i, k + 1, b], X[i, k + 2, b], X[i, k + 3, b]
                        out[i, j, b] += (a00 * p0 + a01 * p1) + (a02 * p2 + a03 * p3)
                        out[i, j + 1, b] += (a10 * p0 + a11 * p1) + (a12 * p2 + a13 * p3)
                        out[i, j + 2, b] += (a20 * p0 + a21 * p1) + (a22 * p2 + a23 * p3)
                        out[i, j + 3, b] += (a30 * p0 + a31 * p1) + (a32 * p2 + a33 * p3)
                elif four:
                    a0, a1, a2, a3 = M[j, k], M[j + 1, k], M[j + 2, k], M[j + 3, k]
                    for b in range(W):
                        p = X[i, k, b]
                        out[i, j, b] += a0 * p
                        out[i, j + 1, b] += a1 * p
                        out[i, j + 2, b] += a2 * p
                        out[i, j + 3, b] += a3 * p
                elif kn == 4:
                    a0, a1, a2, a3 = M[j, k], M[j, k + 1], M[j, k + 2], M[j, k + 3]
                    for b in range(W):
                        out[i, j, b] += (X[i, k, b] * a0 + X[i, k + 1, b] * a1) + (
                            X[i, k + 2, b] * a2 + X[i, k + 3, b] * a3
                        )
                else:
                    a = M[j, k]
                    for b in range(W):
                        out[i, j, b] += X[i, k, b] * a
                k += kn
            j += jn


@njit(cache=True, error_model="numpy")
def _solve_gain(Ree, Rxe, ok, K, W, d):
    r"""One run: :math:`K = R_{xe}R_{ee}^{-1}` with channels ``~ok`` removed (zero gain column), as
    :func:`~tobitkf.filters.core.gain_update`. ``Ree`` (m, m) is overwritten; Gaussian
    elimination with partial pivoting, like LAPACK gesv."""
    n, m = Rxe.shape
    for i in range(m):
        for j in range(m):
            if not (ok[i] and ok[j]):
                Ree[i, j] = 1.0 if i == j else 0.0
    for j in range(m):
        for i in range(n):
            W[j, i] = Rxe[i, j] if ok[j] else 0.0
    # scale Ree to unit diagonal (as core._gain): channels whose variances differ by ~1e77
    # otherwise give gain entries wrong by ~1e54 and a Joseph covariance of ~1e33
    # (``d`` (m,) is the caller's scratch: nothing is allocated per call)
    for i in range(m):
        d[i] = 1.0 / np.sqrt(Ree[i, i]) if Ree[i, i] > 0.0 else 1.0
    for i in range(m):
        for j in range(m):
            Ree[i, j] *= d[i] * d[j]
        for k in range(n):
            W[i, k] *= d[i]
    if not _gauss_solve(Ree, W):
        raise np.linalg.LinAlgError("Singular matrix")  # as numpy.linalg.solve
    for i in range(n):
        for j in range(m):
            K[i, j] = W[j, i] * d[j]


@njit(cache=True, error_model="numpy")
def _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds):
    """The masked gain of run ``b`` of a block by :func:`_solve_gain` (partial pivoting), copied out
    into the scratch ``Rs``, ``Rxs``, ``oks`` and back into ``K[:, :, b]``."""
    n, m = Rxe.shape[0], Rxe.shape[1]
    for i in range(m):
        oks[i] = ok[i, b]
        for j in range(m):
            Rs[i, j] = Ree[i, j, b]
    for i in range(n):
        for j in range(m):
            Rxs[i, j] = Rxe[i, j, b]
    _solve_gain(Rs, Rxs, oks, Ks, Ws, ds)
    for i in range(n):
        for j in range(m):
            K[i, j, b] = Ks[i, j]


@njit(cache=True, error_model="numpy")
def _mean_update(K, e, xp, x, nb):
    r""":math:`\hat x = \bar x + K e` for a block of runs (the runs on the last axis)."""
    n, m = K.shape[0], K.shape[1]
    for i in range(n):
        for b in range(nb):
            x[i, b] = xp[i, b]
        for l in range(m):
            for b in range(nb):
                x[i, b] += K[i, l, b] * e[l, b]


@njit(cache=True, error_model="numpy")
def _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds):
    r"""Block gain and mean update: :math:`K = R_{xe}R_{ee}^{-1}` (masked), :math:`\hat x = \bar x + Ke`.

    Masked channels (``ok`` False) get a zero gain column and ``e`` set to 0."""
    n, m = Rxe.shape[0], Rxe.shape[1]
    if m == 1:
        for b in range(nb):
            good = ok[0, b]
            r = Ree[0, 0, b] if good else 1.0
            for i in range(n):
                K[i, 0, b] = (Rxe[i, 0, b] if good else 0.0) / r
    else:
        for b in range(nb):
            _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds)
    _mean_update(K, e, xp, x, nb)


@njit(cache=True, error_model="numpy")
def _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, W, d, bad, Rs, Ws, Ks, oks, Rxs, ds):
    r"""Block gain and mean update for ``m > 1``, vectorised over the runs of the block:
    :math:`K = R_{xe}R_{ee}^{-1}` with channels ``~ok`` removed (zero gain column, ``e`` set to 0),
    :math:`\hat x = \bar x + Ke`; the result of :func:`_gain`, without copying each run out.

    With :math:`D = \mathrm{diag}(R_{ee})^{-1/2}` (as :func:`_solve_gain`), the unit-diagonal
    :math:`S = D R_{ee} D` is symmetric positive definite, so Gaussian elimination *without*
    pivoting is stable on it: :math:`S\,Z = D R_{xe}^T` is solved in place for all runs of the
    block at once (innermost loops over the runs: no dependency, vectorised), and
    :math:`K = (DZ)^T`. ``Ree`` is left unchanged (``Rw`` (m, m, B) holds the elimination,
    ``W`` (m, n, B) the right-hand sides, ``d`` (m, B) the scaling, ``bad`` (B,) the flags). A run
    whose pivot is not positive (a singular or non-finite :math:`R_{ee}`) is solved again by
    :func:`_solve_gain` (partial pivoting, raising like ``numpy.linalg.solve``), so the block path
    changes nothing but the speed. Allocates nothing; ``Rs``, ``Ws``, ``Ks``, ``oks``, ``Rxs``,
    ``ds`` are :func:`_gain`'s per-run scratch for that fallback.
    """
    n, m = Rxe.shape[0], Rxe.shape[1]
    for i in range(m):
        for b in range(nb):
            v = Ree[i, i, b]
            d[i, b] = 1.0 / math.sqrt(v) if (ok[i, b] and v > 0.0) else 1.0
    for i in range(m):
        for j in range(m):
            for b in range(nb):
                if ok[i, b] and ok[j, b]:
                    Rw[i, j, b] = Ree[i, j, b] * d[i, b] * d[j, b]
                else:
                    Rw[i, j, b] = 1.0 if i == j else 0.0
        for k in range(n):
            for b in range(nb):
                W[i, k, b] = Rxe[k, i, b] * d[i, b] if ok[i, b] else 0.0
    for b in range(nb):
        bad[b] = False
    for c in range(m):
        for b in range(nb):
            if not Rw[c, c, b] > 0.0:  # also NaN
                bad[b] = True
                Rw[c, c, b] = 1.0  # keeps the other runs' arithmetic finite; this run is redone
        for q in range(c + 1, m):
            for b in range(nb):
                Rw[q, c, b] = Rw[q, c, b] / Rw[c, c, b]  # the multiplier, stored below the diagonal
            for j in range(c + 1, m):
                for b in range(nb):
                    Rw[q, j, b] -= Rw[q, c, b] * Rw[c, j, b]
            for k in range(n):
                for b in range(nb):
                    W[q, k, b] -= Rw[q, c, b] * W[c, k, b]
    for c in range(m - 1, -1, -1):
        for j in range(c + 1, m):
            for k in range(n):
                for b in range(nb):
                    W[c, k, b] -= Rw[c, j, b] * W[j, k, b]
        for k in range(n):
            for b in range(nb):
                W[c, k, b] = W[c, k, b] / Rw[c, c, b]
    for i in range(n):
        for j in range(m):
            for b in range(nb):
                K[i, j, b] = W[j, i, b] * d[j, b]
    for b in range(nb):
        if bad[b]:
            _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds)
    _mean_update(K, e, xp, x, nb)


@njit(cache=True, error_model="numpy", inline="always")
def _take_part(Ree, e, ok, m, nb):
    """The channels that take part (``ok``): innovation variance above the smallest normal number and
    innovation not NaN; the innovation of one that does not is set to 0 (both forms of
    :func:`_innovation_moments`)."""
    for l in range(m):
        for b in range(nb):
            good = (Ree[l, l, b] > _TINY) and not math.isnan(e[l, b])
            ok[l, b] = good
            if not good:
                e[l, b] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def mean_predict(A, x, xp, nb):
    r""":math:`\bar x = A\hat x` for the top ``A.shape[0]`` rows of a block's means (``x``, ``xp`` (dim, B)):
    the mean of both forms of :func:`_predict`, of the fading kernel's block shift and of the steady-state
    kernel."""
    n = A.shape[0]
    for i in range(n):
        for b in range(nb):
            xp[i, b] = 0.0
        for k in range(n):
            a = A[i, k]
            for b in range(nb):
                xp[i, b] += a * x[k, b]


@njit(cache=True, error_model="numpy")
def _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb):
    r"""The moments of a scaled update for a block of runs (the runs on the last axis):
    :math:`R_{xe} = \bar P C^T \Gamma`, :math:`R_{ee} = \Gamma C \bar P C^T \Gamma + N` with
    :math:`\Gamma = \mathrm{diag}(\gamma)` (for the TKF (3.39), (3.40); for the fading TKF (24)-(26) with
    C the augmented measurement matrix, whose zero entries are skipped). A channel takes part
    (``ok``) when its innovation variance is positive and its innovation ``e`` not NaN; the
    innovation of one that does not is set to 0. Writes ``CP`` (m, dim, nb), ``Rxe``, ``Ree``,
    ``ok``, ``e`` in place. From dim = :data:`BLOCKED_N` on by :func:`_innovation_moments_blocked`."""
    m, dim = C.shape
    if dim >= BLOCKED_N:
        _innovation_moments_blocked(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
        return
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                CP[l, j, b] = 0.0
            for k in range(dim):
                c = C[l, k]
                if c != 0.0:
                    for b in range(nb):
                        CP[l, j, b] += c * Pp[k, j, b]
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                Rxe[j, l, b] = CP[l, j, b] * gam[l, b]
        for q in range(m):
            for b in range(nb):
                Ree[l, q, b] = 0.0
            for k in range(dim):
                c = C[q, k]
                for b in range(nb):
                    Ree[l, q, b] += CP[l, k, b] * c
            for b in range(nb):
                Ree[l, q, b] = Ree[l, q, b] * gam[l, b] * gam[q, b]
        for b in range(nb):
            Ree[l, l, b] += noise[l, l, b]
    _take_part(Ree, e, ok, m, nb)


@njit(cache=True, error_model="numpy")
def _innovation_moments_blocked(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb):
    r""":func:`_innovation_moments` at larger dim: :math:`C\bar P` row by row over the contiguous slabs
    ``Pp[k]`` of all lanes of the block (as :func:`_predict_blocked`; zero entries of C skipped) and
    :math:`R_{ee}` on its upper triangle, mirrored (measured at n = 16, m = 8: 500 -> 310 ns per run), both
    in register tiles (:func:`_rows_times`, :func:`_sym_times`; in isolation, B = 40, thread CPU time, one
    process, load 4.4: 507 ns per run one row and one term per pass, 334 with the tiles of C P, 231 with
    those of R_ee too)."""
    m, dim = C.shape
    W = Pp.shape[2]
    L = dim * W
    Ppf = Pp.reshape((dim, L))
    CPf = CP.reshape((m, L))
    _rows_times(CPf, C, Ppf, dim, L, True)  # CP[l] = sum_k C[l, k] Pp[k] over the slabs (as _predict_blocked)
    _sym_times(Ree, CP, C, C, False, dim, W, True)  # the upper triangle of C Pbar C^T (scaled below)
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                Rxe[j, l, b] = CP[l, j, b] * gam[l, b]
        for q in range(l, m):  # symmetric: q >= l, mirrored (C Pbar C^T by _sym_times above)
            for b in range(nb):
                Ree[l, q, b] = Ree[l, q, b] * gam[l, b] * gam[q, b]
                Ree[q, l, b] = Ree[l, q, b]
        for b in range(nb):
            Ree[l, l, b] += noise[l, l, b]
    _take_part(Ree, e, ok, m, nb)


@njit(cache=True, error_model="numpy")
def _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb):
    r"""The covariance update of a block of runs, the one compiled form of every kernel (TKF, KF, fading,
    protocol, the shared step), as the numpy update of :mod:`tobitkf.filters.core`, with the effective
    measurement matrix :math:`H = \mathrm{diag}(\gamma)C` (``C`` (m, n) shared, ``gam`` (m, B) per run):

    standard form :math:`P = \bar P - KR_{xe}^T`; Joseph form
    :math:`(I-KH)\bar P(I-KH)^T + KNK^T`, applied in rank-m products as
    :math:`P = M - (MH^T - KN)K^T`, :math:`M = \bar P - KR_{xe}^T` (the two are equal for
    any gain K with :math:`R_{xe} = \bar PH^T`; O(n^2 m) instead of O(n^3)). ``noise`` (m, m, B) the
    noise term N; ``MH`` (n, m, B) scratch. :math:`MH^T` is formed from the *computed* M, so M's
    rounding error :math:`\delta M` enters P as :math:`\delta M(I - H^TK^T)`, damped as in the
    Joseph form, not as :math:`\delta M` (the reason for this order: with a flat prior the
    cancellation in M is all of P's error otherwise). M and P are computed on the upper triangle and
    mirrored (M is symmetric in exact arithmetic; the mirrored M is the one both steps use). A masked
    channel has a zero gain column, so its row of H does not matter."""
    n, m = K.shape[0], K.shape[1]
    m4 = m - m % 4
    for i in range(n):  # the sum over the channels four terms per pass over the runs (as _sym_times)
        for j in range(i, n):
            for b in range(nb):
                P[i, j, b] = Pp[i, j, b]
            for l in range(0, m4, 4):
                for b in range(nb):
                    P[i, j, b] -= (K[i, l, b] * Rxe[j, l, b] + K[i, l + 1, b] * Rxe[j, l + 1, b]) + (
                        K[i, l + 2, b] * Rxe[j, l + 2, b] + K[i, l + 3, b] * Rxe[j, l + 3, b]
                    )
            for l in range(m4, m):
                for b in range(nb):
                    P[i, j, b] -= K[i, l, b] * Rxe[j, l, b]
    _mirror(P, nb)
    if not joseph:
        return
    for i in range(n):
        for l in range(m):
            for b in range(nb):
                MH[i, l, b] = 0.0
            for k in range(n):
                c = C[l, k]
                if c != 0.0:
                    for b in range(nb):
                        MH[i, l, b] += P[i, k, b] * c
            for b in range(nb):
                MH[i, l, b] = MH[i, l, b] * gam[l, b]
            for q in range(m):
                for b in range(nb):
                    MH[i, l, b] -= K[i, q, b] * noise[q, l, b]
    for i in range(n):
        for j in range(i, n):
            for l in range(m):
                for b in range(nb):
                    P[i, j, b] -= MH[i, l, b] * K[j, l, b]
    _mirror(P, nb)


@njit(cache=True, error_model="numpy")
def _load(x0, P0, r0, nb, x, P):
    n = x.shape[0]
    for b in range(nb):
        for i in range(n):
            x[i, b] = x0[r0 + b, i]
            for j in range(n):
                P[i, j, b] = P0[r0 + b, i, j]


@njit(cache=True, error_model="numpy")
def _stage(xv, Pv, tt, nb, mbuf, cbuf):
    """Copy a block's x[i, b], P[i, j, b] into the staging buffers at chunk step ``tt``; a buffer with
    no runs (``shape[0] == 0``: that output was not requested) is skipped."""
    n = mbuf.shape[1]
    if mbuf.shape[0] > 0:
        for i in range(n):
            for b in range(nb):
                mbuf[tt, i, b] = xv[i, b]
    _stage_cov(Pv, cbuf, tt, nb)


@njit(cache=True, error_model="numpy")
def _stage_cov(Pv, cbuf, tt, nb):
    """Copy the top-left ``n x n`` block of a block's P[i, j, b] (n = ``cbuf.shape[1]``) into the staging
    buffer ``cbuf`` (S, n, n, B) at chunk step ``tt``, or only its diagonal into ``cbuf`` (S, n, 1, B) (the
    variances, for ``outputs=("var",)``: no (N, T, n, n) array); skipped when ``cbuf`` has no steps."""
    if cbuf.shape[0] == 0:
        return
    n = cbuf.shape[1]
    if cbuf.shape[2] == 1:
        for i in range(n):
            for b in range(nb):
                cbuf[tt, i, 0, b] = Pv[i, i, b]
        return
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                cbuf[tt, i, j, b] = Pv[i, j, b]


@njit(cache=True, error_model="numpy")
def _flush(buf, out, r0, t0, nb, cnt):
    """Write ``cnt`` staged steps of ``nb`` runs, ``buf[tt, ..., b]`` (S, ..., B), to
    ``out[r0 + b, t0:t0 + cnt]`` (the transpose; contiguous writes per run). An output with no time axis
    (``out.shape[1] == 0``) was not requested and is skipped."""
    if out.shape[1] == 0:
        return
    S, B = buf.shape[0], buf.shape[buf.ndim - 1]
    d = buf.size // (S * B)
    src = buf.reshape((S, d, B))
    if d >= FLUSH_BY_STEP:
        # large per-step blocks (n = 16: d = 256, a 4 MB buffer): step by step, so that the strided
        # reads stay in one step's slab (d * B * 8 bytes, in cache) instead of sweeping the whole
        # buffer once per run (measured: n = 16, m = 8, all outputs 8.0-11.5 us against 5.0 us per
        # run-step for the run-major loop order before the (S, ..., B) layout)
        # (then 8 x 8 tiles, below)
        dst = out.reshape((out.shape[0], out.shape[1] * d))
        b8, d8 = nb - nb % 8, d - d % 8
        for s in range(cnt):
            o = (t0 + s) * d
            for b0 in range(0, b8, 8):
                # 8 runs x 8 numbers at a time (measured in isolation at d = 256, B = 32, 200 MB of
                # outputs: 303 -> 185 ns per run-step against one run at a time): the eight strided
                # reads of a run share their cache lines with the tile's other runs, and each run's
                # eight writes fill a whole cache line at once
                for q0 in range(0, d8, 8):
                    for u in range(8):
                        for v in range(8):
                            dst[r0 + b0 + u, o + q0 + v] = src[s, q0 + v, b0 + u]
                for u in range(8):
                    for q in range(d8, d):
                        dst[r0 + b0 + u, o + q] = src[s, q, b0 + u]
            for b in range(b8, nb):
                for q in range(d):
                    dst[r0 + b, o + q] = src[s, q, b]
        return
    for b in range(nb):
        dst = out[r0 + b, t0 : t0 + cnt].reshape(-1)
        for s in range(cnt):
            for q in range(d):
                dst[s * d + q] = src[s, q, b]


@njit(cache=True, error_model="numpy")
def _store_last(xv, Pv, r0, nb, x_last, P_last):
    """The block's state after its last step into ``x_last[r0 + b]``, ``P_last[r0 + b]``."""
    n = xv.shape[0]
    for b in range(nb):
        for i in range(n):
            x_last[r0 + b, i] = xv[i, b]
            for j in range(n):
                P_last[r0 + b, i, j] = Pv[i, j, b]


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


@njit(cache=True, error_model="numpy")
def predict_block(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(APA^T + Q)` of a block of runs (the predict of
    :func:`tkf_kernel` and :func:`kf_kernel`, shared with the compiled closed loop of :mod:`tobitkf.control`);
    ``x`` (n, B), ``P`` (n, n, B) in, ``xp``, ``Pp`` out, ``AP`` (n, n, B) scratch."""
    _predict(A, Qd, x, P, xp, Pp, AP, nb)


# the output staging of the kernels, shared with the compiled closed loop of tobitkf.control: stage_block
# copies a block's (dim, B) [and (n, n, B)] arrays into (S, ..., B) buffers at a chunk step, flush_rows
# writes the staged steps run by run into the (N, T, ...) outputs (see CHUNK)
stage_block = _stage
flush_rows = _flush
stage_shape = _stage_shape


@njit(cache=True, inline="always")
def block_scratch(n, m, B, G):
    """The block scratch of a Kalman-type step of ``B`` runs (state size ``n``, ``m`` channels, ``G``
    quadrature nodes): ``(x, xp, e, ey)`` of :func:`_mean_scratch` and ``(blk, run, solve, buf)`` of
    :func:`_update_scratch`, for a kernel outside this module (the compiled closed loop)."""
    return _mean_scratch(n, m, B), _update_scratch(n, n, m, B, G)


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
