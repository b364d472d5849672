r"""Compiled (numba) propagate–weight–resample of the particle filter for linear readings with censoring.

An *implementation* of the numpy path of :class:`tobitkf.ParticleFilter` for its linear model
(``_Linear``: :math:`y^* = Cx + v`, one- or two-sided censoring, constant or time-varying limits, missing
readings), both proposals it has there (``"prior"``, the bootstrap filter, and ``"optimal"``, the
locally optimal proposal drawn channel by channel), not a second algorithm: the same equations in
the same order per particle, the same log-sum-exp normalisation of the weights, the same systematic
resampling (Kitagawa 1996) when the effective sample size :math:`1/\sum_iW_i^2` falls below the
threshold, and **the same random numbers**: the driver draws, per step, exactly the arrays the numpy
path draws, with the same ``numpy.random.Generator`` calls in the same order (into buffers allocated
once, ``out=``), and hands them to the compiled step. With all runs in one block the results equal the
numpy path's to rounding (tested to 1e-12).

Runs are processed in blocks (outer loop) over time (inner loop); the working buffers (the proposed
particles, the random numbers) are those of one block, allocated once, so the working memory does not
grow with the run count or with T. The particles of every run (the final state, from which a filter
can continue) are one ``(N, N_p, n)`` array updated in place. With several blocks a block consumes the
generator for all its steps before the next one starts (the draws of block ``j`` are those the numpy
path draws for those runs alone, continuing the generator where block ``j-1`` left it; tested).

The normal tails: :math:`\log\Phi` (:func:`log_ndtr`) through ``erfc`` and, beyond 25√2 ≈ 35.4 standard
deviations, the asymptotic series of ``erfcx``; its inverse (:func:`ndtri_exp`) from Acklam's rational
start refined by a Halley step (agree with ``scipy.special`` to ~1e-15).
Functions are compiled on first use and cached on disk (``cache=True``).

Cost per particle and step: the numpy normal draws (shared with the numpy path, so that both give the
same numbers) and, for a censored reading, one :func:`log_ndtr` and, under the optimal proposal, one
:func:`ndtri_exp` (scalar libm calls: erfc, log, exp); the rest (propagation, weights, moments,
resampling) is a few passes over the block's particles without temporaries
(``benchmarks/bench_particle.py`` (c) times it against the numpy path and a plain numpy filter).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from ._readings import _INTERIOR, _LOWER, _MISSING, _RTOL_LIMIT, _UPPER

__all__ = ["log_ndtr", "ndtri_exp", "pf_step", "runs_per_block", "filter_blocks", "BLOCK_BYTES"]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)
_SQRT_PI = math.sqrt(math.pi)
_SQRT_2PI = math.sqrt(2.0 * math.pi)
_INF = math.inf

#: working-memory budget of one block of runs (bytes): the proposed particles and the random numbers
BLOCK_BYTES = 4 * 2**20


# --------------------------------------------------------------------------- normal tails


@njit(cache=True, error_model="numpy")
def log_ndtr(x):
    r""":math:`\log\Phi(x)`, accurate in both tails: :math:`\mathrm{log1p}(-\tfrac12\mathrm{erfc}(x/\sqrt2))`
    for x > 0, :math:`\log(\tfrac12\mathrm{erfc}(t))`, :math:`t = -x/\sqrt2`, down to t = 25, and below
    :math:`-x^2/2 + \log(\tfrac12\mathrm{erfcx}(t))` with the asymptotic series of erfcx (8 terms,
    truncation < 1e-16 for t > 25)."""
    if x != x:
        return x
    if x == _INF:
        return 0.0
    if x == -_INF:
        return -_INF
    if x > 0.0:
        return math.log1p(-0.5 * math.erfc(x * _SQRT1_2))
    t = -x * _SQRT1_2
    if t < 25.0:
        return math.log(0.5 * math.erfc(t))
    q = 1.0 / (2.0 * t * t)
    term = 1.0
    s = 1.0
    for k in range(1, 9):
        term *= -(2.0 * k - 1.0) * q
        s += term
    return -0.5 * x * x + math.log(0.5 * s / (t * _SQRT_PI))


# Acklam's rational approximation of the normal quantile (relative error < 1.2e-9): the start
_A = (-3.969683028665376e01, 2.209460984245205e02, -2.759285104469687e02, 1.383577518672690e02,
      -3.066479806614716e01, 2.506628277459239e00)  # fmt: skip
_B = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02, 6.680131188771972e01,
      -1.328068155288572e01)  # fmt: skip
_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e00, -2.549732539343734e00,
      4.374664141464968e00, 2.938163982698783e00)  # fmt: skip
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00, 3.754408661907416e00)
_P_LOW = 0.02425
_LOG_P_LOW = math.log(_P_LOW)
_LOG_P_HIGH = math.log1p(-_P_LOW)


@njit(cache=True, error_model="numpy")
def _tail_start(q):
    c0, c1, c2, c3, c4, c5 = _C
    d0, d1, d2, d3 = _D
    return (((((c0 * q + c1) * q + c2) * q + c3) * q + c4) * q + c5) / ((((d0 * q + d1) * q + d2) * q + d3) * q + 1.0)


@njit(cache=True, error_model="numpy", inline="always")
def _halley(z, p):
    r"""One Halley step towards :math:`\Phi(z) = p` from Acklam's start (relative error 1.2e-9 -> rounding)."""
    e = 0.5 * math.erfc(-z * _SQRT1_2) - p
    u = e * _SQRT_2PI * math.exp(0.5 * z * z)
    return z - u / (1.0 + 0.5 * z * u)


@njit(cache=True, error_model="numpy")
def _ndtri_exp_far(t):
    """:func:`ndtri_exp` below t = -700 (Phi(z) under 1e-304): Newton steps on log Phi(z) = t from Acklam's start."""
    z = _tail_start(math.sqrt(-2.0 * t))
    for _ in range(12):
        lp = log_ndtr(z)
        step = (lp - t) * math.exp(lp + 0.5 * z * z + _LOG_SQRT_2PI)
        z -= step
        if not abs(step) > 1e-15 * max(1.0, abs(z)):
            break
    return z


@njit(cache=True, error_model="numpy")
def ndtri_exp(t):
    r"""The z with :math:`\log\Phi(z) = t` (:math:`t \le 0`; :math:`-\infty` at :math:`-\infty`, :math:`+\infty` at 0).

    Acklam's rational start (the lower tail from :math:`q = \sqrt{-2t}`; the upper tail mirrored, from
    :math:`1 - p = -\mathrm{expm1}(t)`, so no cancellation), then one Halley step on :math:`\Phi(z) = p`
    through ``erfc`` (on :math:`\Phi(-z) = 1 - p` in the upper tail); below t = -700 Newton steps on
    :math:`\log\Phi(z) = t`."""
    if t != t or t > 0.0:
        return math.nan
    if t == -_INF:
        return -_INF
    if t == 0.0:
        return _INF
    if t < -700.0:
        return _ndtri_exp_far(t)
    if t < _LOG_P_LOW:
        return _halley(_tail_start(math.sqrt(-2.0 * t)), math.exp(t))
    if t > _LOG_P_HIGH:
        q = -math.expm1(t)
        return -_halley(_tail_start(math.sqrt(-2.0 * math.log(q))), q)
    a0, a1, a2, a3, a4, a5 = _A
    b0, b1, b2, b3, b4 = _B
    p = math.exp(t)
    q = p - 0.5
    r = q * q
    z = (((((a0 * r + a1) * r + a2) * r + a3) * r + a4) * r + a5) * q
    z /= ((((b0 * r + b1) * r + b2) * r + b3) * r + b4) * r + 1.0
    return _halley(z, p)


# --------------------------------------------------------------------------- small linear algebra


@njit(cache=True, error_model="numpy")
def _psd_sqrt(M, L):
    """L with L L^T = M (n, n): the lower Cholesky factor when M is positive definite, else the
    eigen-decomposition root of its symmetric part (as :func:`tobitkf._linalg.psd_sqrt`)."""
    n = M.shape[0]
    ok = True
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            ok = False
            break
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = M[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    if ok:
        return
    S = 0.5 * (M + M.T)
    w, V = np.linalg.eigh(S)
    for i in range(n):
        for j in range(n):
            L[i, j] = V[i, j] * math.sqrt(max(w[j], 0.0))


@njit(cache=True, error_model="numpy", inline="always")
def _classify(y, lo, hi):
    """The class of one reading (as :func:`tobitkf.filters._readings.classify_readings`)."""
    if y != y:
        return _MISSING
    if lo > -_INF and y <= lo + _RTOL_LIMIT * max(1.0, abs(lo)):
        return _LOWER
    if hi < _INF and y >= hi - _RTOL_LIMIT * max(1.0, abs(hi)):
        return _UPPER
    return _INTERIOR


# --------------------------------------------------------------------------- one step of a block


@njit(cache=True, error_model="numpy", nogil=True)
def pf_step(
    optimal, X, Xn, lw, eps, U, ur, A, G, Qd, C, r, y, lo, hi, thr, xm, Pm, xp, Pp, ess, res, ll, ll_acc, work, Wb
):
    r"""One step of the particle filter for the B runs of a block, in place.

    Parameters
    ----------
    optimal : bool
        The locally optimal proposal (else the bootstrap one).
    X : (B, Np, n)
        The particles at k-1; on return those at k (resampled where the run resampled).
    Xn : (B, Np, n)
        Scratch for the proposed particles.
    lw : (B, Np)
        Normalised log weights, updated.
    eps : (B, Np, n) ; U : (B, Np, m) ; ur : (B,)
        The step's standard normals, uniforms of the censored draws (optimal proposal) and of resampling.
    A, G, Qd : (n, n)
        Transition, a root of the process covariance (G G^T = Qd), the process covariance.
    C : (m, n) ; r : (m,) ; y : (B, m) ; lo, hi : (m,)
        Readings matrix, noise variances, readings (NaN = missing) and limits at k.
    thr : float
        Resample when the effective sample size is below ``thr`` (the threshold times Np).
    xm, Pm : (B, n), (B, n, n)
        In: the weighted moments at k-1; out: those at k.
    xp, Pp, ess, res, ll : out
        The linear prediction of the moments, the effective sample size, whether the run resampled and
        the step's log-likelihood estimate (-inf where no particle explains the reading).
    ll_acc : (B,)
        Running sum of the log-likelihood, updated.
    work : (Np,) ; Wb : (Np,)
        Scratch (incremental log weights; normalised weights).
    """
    B, Np, n = X.shape
    m = C.shape[0]
    cls = np.empty(m, dtype=np.int8)
    Sig = np.empty((n, n))
    L = np.empty((n, n))
    g = np.empty((m, n))
    sr = np.empty(m)
    lsd = np.empty(m)
    srp = np.empty(m)  # the bootstrap's noise standard deviations and their log-normalisers
    lsp = np.empty(m)
    for l in range(m):
        srp[l] = math.sqrt(r[l])
        lsp[l] = math.log(srp[l]) + _LOG_SQRT_2PI
    mu = np.empty(n)
    Sc = np.empty(n)
    x0 = np.empty(n)
    d = np.empty(n)
    S1 = np.empty(n)
    S2 = np.empty((n, n))
    logNp = math.log(Np)
    rank = 0
    for b in range(B):
        # the linear prediction of the weighted moments (core.predict)
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += A[i, j] * xm[b, j]
            xp[b, i] = s
        for i in range(n):
            for j in range(n):
                s = 0.0
                for k in range(n):
                    for q in range(n):
                        s += A[i, k] * Pm[b, k, q] * A[j, q]
                Sig[i, j] = s + Qd[i, j]
        for i in range(n):
            for j in range(n):
                Pp[b, i, j] = 0.5 * (Sig[i, j] + Sig[j, i])
        for l in range(m):
            cls[l] = _classify(y[b, l], lo[l], hi[l])
        if optimal:
            # the Gaussian conditioning of _condition_in_sequence: the same for every particle of the run
            for i in range(n):
                for j in range(n):
                    Sig[i, j] = Qd[i, j]
            for l in range(m):
                if cls[l] == _MISSING:
                    continue
                for i in range(n):
                    s = 0.0
                    for j in range(n):
                        s += Sig[i, j] * C[l, j]
                    Sc[i] = s
                s2 = r[l]
                s = 0.0
                for i in range(n):
                    s += Sc[i] * C[l, i]
                s2 = s + r[l]
                den = s2 if s2 > 0.0 else 1.0
                for i in range(n):
                    g[l, i] = Sc[i] / den
                sr[l] = math.sqrt(s2)
                lsd[l] = math.log(sr[l]) + _LOG_SQRT_2PI
                for i in range(n):
                    for j in range(n):
                        Sig[i, j] = Sig[i, j] - s2 * g[l, i] * g[l, j]
                for i in range(n):
                    for j in range(i + 1, n):
                        v = 0.5 * (Sig[i, j] + Sig[j, i])
                        Sig[i, j] = v
                        Sig[j, i] = v
            _psd_sqrt(Sig, L)
            for p in range(Np):
                for i in range(n):
                    s = 0.0
                    for j in range(n):
                        s += X[b, p, j] * A[i, j]
                    mu[i] = s
                inc = 0.0
                for l in range(m):
                    c = cls[l]
                    if c == _MISSING:
                        continue
                    pred = 0.0
                    for j in range(n):
                        pred += mu[j] * C[l, j]
                    sd = sr[l]
                    if c == _INTERIOR:
                        val = y[b, l]
                        z = (val - pred) / sd
                        inc += -0.5 * z * z - lsd[l]
                    elif c == _LOWER:
                        lm = log_ndtr((lo[l] - pred) / sd)
                        val = pred + ndtri_exp(math.log(U[b, p, l]) + lm) * sd
                        inc += lm
                    else:
                        lm = log_ndtr((pred - hi[l]) / sd)
                        val = pred - ndtri_exp(math.log(U[b, p, l]) + lm) * sd
                        inc += lm
                    dv = val - pred
                    for i in range(n):
                        mu[i] += dv * g[l, i]
                for i in range(n):
                    s = 0.0
                    for j in range(n):
                        s += eps[b, p, j] * L[i, j]
                    Xn[b, p, i] = mu[i] + s
                work[p] = inc
        else:
            for p in range(Np):
                for i in range(n):
                    s = 0.0
                    for j in range(n):
                        s += X[b, p, j] * A[i, j]
                    t = 0.0
                    for j in range(n):
                        t += eps[b, p, j] * G[i, j]
                    Xn[b, p, i] = s + t
                inc = 0.0
                for l in range(m):
                    c = cls[l]
                    if c == _MISSING:
                        continue
                    mul = 0.0
                    for j in range(n):
                        mul += Xn[b, p, j] * C[l, j]
                    sd = srp[l]
                    if c == _INTERIOR:
                        z = (y[b, l] - mul) / sd
                        inc += -0.5 * z * z - lsp[l]
                    elif c == _LOWER:
                        inc += log_ndtr((lo[l] - mul) / sd)
                    else:
                        inc += log_ndtr((mul - hi[l]) / sd)
                work[p] = inc
        # weights: log-sum-exp normalisation, fused with the weighted moments (one pass; the sums of the
        # deviations from the run's first particle, so no cancellation when the mean is far from 0)
        top = -_INF
        for p in range(Np):
            work[p] += lw[b, p]
            if work[p] > top:
                top = work[p]
        dead = not (top > -_INF and top < _INF)
        if dead:  # no particle explains the reading: keep the weights, report -inf
            top = -_INF
            for p in range(Np):
                work[p] = lw[b, p]
                if work[p] > top:
                    top = work[p]
        for i in range(n):
            x0[i] = Xn[b, 0, i]
            S1[i] = 0.0
            for j in range(n):
                S2[i, j] = 0.0
        tot = 0.0
        sw2 = 0.0
        for p in range(Np):
            w = math.exp(work[p] - top)
            Wb[p] = w
            tot += w
            sw2 += w * w
            for i in range(n):
                d[i] = Xn[b, p, i] - x0[i]
                S1[i] += w * d[i]
            for i in range(n):
                for j in range(i, n):
                    S2[i, j] += w * d[i] * d[j]
        lnorm = math.log(tot) + top
        ll[b] = -_INF if dead else lnorm
        ll_acc[b] += ll[b]
        for i in range(n):
            d[i] = S1[i] / tot
            xm[b, i] = x0[i] + d[i]
        for i in range(n):
            for j in range(i, n):
                v = S2[i, j] / tot - d[i] * d[j]
                Pm[b, i, j] = v
                Pm[b, j, i] = v
        sw2 /= tot * tot
        e = 1.0 / sw2
        ess[b] = e
        if e < thr:
            # systematic resampling, the comparisons of systematic_resample (row offset = rank)
            res[b] = True
            off = float(rank)
            rank += 1
            cum = 0.0
            for p in range(Np):
                cum += Wb[p] / tot
                work[p] = cum
            work[Np - 1] = 1.0
            j = 0
            for p in range(Np):
                v = (ur[b] + p) / Np + off
                while j < Np and work[j] + off <= v:
                    j += 1
                src = j if j < Np else Np - 1
                for i in range(n):
                    X[b, p, i] = Xn[b, src, i]
                lw[b, p] = -logNp
        else:
            res[b] = False
            for p in range(Np):
                for i in range(n):
                    X[b, p, i] = Xn[b, p, i]
                lw[b, p] = work[p] - lnorm


# --------------------------------------------------------------------------- the driver


def runs_per_block(particles: int, n: int, m: int, budget: int = BLOCK_BYTES) -> int:
    """Runs per block so that the block's working buffers (proposed particles, normals, uniforms) fit ``budget``."""
    per_run = 8 * particles * (2 * n + m + 2)
    return max(1, budget // per_run)


def _generator(state: dict) -> np.random.Generator:
    """The generator a particle filter's state carries (its bit generator's state), as the numpy path restores it."""
    bg = getattr(np.random, state["bit_generator"])()
    bg.state = state
    return np.random.Generator(bg)


def filter_blocks(pf: Any, y2: np.ndarray, state: Any, want: frozenset[str], batch: tuple[int, ...], block=None):
    """The particle filter's loop over the readings ``y2`` (N, T, m) from ``state``, compiled, in blocks of runs.

    ``pf`` is a :class:`~tobitkf.ParticleFilter` with a linear model (time-invariant system, no input);
    returns the :class:`~tobitkf.filters.core.FilterResult` its numpy loop returns."""
    from .core import FilterResult, FilterState

    model, system = pf.model, pf.system
    N, T, m = y2.shape
    n, Np = system.n, pf.particles
    optimal = pf.proposal == "optimal"
    k0 = state.k
    A = np.ascontiguousarray(system.transition(k0), dtype=float)
    Qd = np.ascontiguousarray(system.process_cov(k0), dtype=float)
    G = np.ascontiguousarray(model._root(k0), dtype=float)
    C = np.ascontiguousarray(system.measurement(k0 + 1), dtype=float)
    d = np.diagonal(system.measurement_cov(k0 + 1)).astype(float)
    r = np.ascontiguousarray(np.sqrt(d) ** 2 if optimal else d)  # as the numpy path forms them
    lims = [model.limits(k0 + 1 + i) for i in range(T)]
    LO = np.ascontiguousarray([lo for lo, _ in lims], dtype=float).reshape(T, m)
    HI = np.ascontiguousarray([hi for _, hi in lims], dtype=float).reshape(T, m)
    carry = state.carry
    X = np.array(carry["particles"], dtype=float, order="C")  # (N, Np, n): the final particles, in place
    lw = np.array(carry["log_weights"], dtype=float, order="C")
    ll_acc = np.array(carry["log_likelihood"], dtype=float)
    xm = np.array(state.x, dtype=float).reshape(N, n)
    Pm = np.array(np.broadcast_to(state.P, (N, n, n)), dtype=float)
    rng = _generator(carry["rng"])  # the numpy path's generator, restored from the state
    outs: dict[str, np.ndarray] = {}
    for key in ("mean", "pred_mean"):
        if key in want:
            outs[key] = np.empty((N, T, n))
    for key in ("cov", "pred_cov"):
        if key in want:
            outs[key] = np.empty((N, T, n, n))
    if "var" in want:
        outs["var"] = np.empty((N, T, n))
    extras = {}
    if "extras" in want:
        extras = {
            "ess": np.empty((N, T)),
            "resampled": np.empty((N, T), dtype=bool),
            "log_likelihood": np.empty((N, T)),
        }
    Bmax = min(N, int(block) if block else runs_per_block(Np, n, m))
    Xn = np.empty((Bmax, Np, n))
    eps = np.empty((Bmax, Np, n))
    U = np.empty((Bmax, Np, m) if optimal else (1, 1, 1))
    ur = np.empty(Bmax)
    xp, Pp = np.empty((Bmax, n)), np.empty((Bmax, n, n))
    ess, res, ll = np.empty(Bmax), np.empty(Bmax, dtype=bool), np.empty(Bmax)
    work, Wb = np.empty(Np), np.empty(Np)
    thr = pf.resample_threshold * Np
    yc = np.ascontiguousarray(y2, dtype=float)
    for r0 in range(0, N, Bmax):
        r1 = min(N, r0 + Bmax)
        B = r1 - r0
        Xb, lwb, xmb, Pmb, lab = X[r0:r1], lw[r0:r1], xm[r0:r1], Pm[r0:r1], ll_acc[r0:r1]
        Xs, es, Us, us = Xn[:B], eps[:B], U[:B] if optimal else U, ur[:B]
        xps, Pps, esss, ress, lls = xp[:B], Pp[:B], ess[:B], res[:B], ll[:B]
        for i in range(T):
            # the draws of the numpy path, in its order: (U,) eps, then the resampling uniforms
            if optimal:
                rng.random(out=Us)
            rng.standard_normal(out=es)
            rng.random(out=us)
            pf_step(optimal, Xb, Xs, lwb, es, Us, us, A, G, Qd, C, r, yc[r0:r1, i], LO[i], HI[i], thr,
                    xmb, Pmb, xps, Pps, esss, ress, lls, lab, work, Wb)  # fmt: skip
            if "mean" in outs:
                outs["mean"][r0:r1, i] = xmb
            if "cov" in outs:
                outs["cov"][r0:r1, i] = Pmb
            if "var" in outs:
                outs["var"][r0:r1, i] = np.diagonal(Pmb, axis1=1, axis2=2)
            if "pred_mean" in outs:
                outs["pred_mean"][r0:r1, i] = xps
            if "pred_cov" in outs:
                outs["pred_cov"][r0:r1, i] = Pps
            if extras:
                extras["ess"][r0:r1, i] = esss
                extras["resampled"][r0:r1, i] = ress
                extras["log_likelihood"][r0:r1, i] = lls
    new_carry = {"particles": X, "log_weights": lw, "rng": rng.bit_generator.state, "log_likelihood": ll_acc}
    final = FilterState(k=k0 + T, batch_shape=batch, x=xm, P=Pm, n=n, S=None, carry=new_carry)

    def shaped(a):
        return None if a is None else a.reshape(batch + a.shape[1:])

    return FilterResult(
        mean=shaped(outs.get("mean")),
        cov=shaped(outs.get("cov")),
        pred_mean=shaped(outs.get("pred_mean")),
        pred_cov=shaped(outs.get("pred_cov")),
        extras={key: shaped(v) for key, v in extras.items()},
        times=np.arange(k0 + 1, k0 + T + 1),
        var=shaped(outs.get("var")),
        final=final,
    )
