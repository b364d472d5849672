r"""Compiled (numba) propagate–weight–resample of the particle filter.

An *implementation* of the numpy path of :class:`tobitkf.ParticleFilter` for its linear model
(``_Linear``: :math:`y^* = Cx + v`, one- or two-sided censoring, constant or time-varying limits, missing
readings), both proposals it has there (``"prior"``, the bootstrap filter, and ``"optimal"``, the
locally optimal proposal drawn channel by channel), not a second algorithm: the same equations in
the same order per particle, the same log-sum-exp normalisation of the weights, the same systematic
resampling (Kitagawa 1996) when the effective sample size :math:`1/\sum_iW_i^2` falls below the
threshold. Given the same random numbers, the results equal the numpy path's to rounding (tested to
1e-12 by feeding the numpy path the draws of the compiled loop).

The same loop runs the readings of :mod:`tobitkf.filters._compiled_particle_readings` (a normal latent reading
seen through an interval, as a mixture of modes, over a window of states): random saturation and Rice fading
with Gaussian coefficients under the bootstrap proposal, and a channel whose likelihood is its ``region``'s
(a quantizer) under both; the locally optimal proposal of an interval reading draws its latent reading from the
window, :math:`z = \Phi^{-1}(\Phi(a) + u(\Phi(b) - \Phi(a)))` (one uniform, in the place of a censored
reading's), from the window's two tail masses (one vectorised pass) and AS 241's quantile, and an exact one
conditions on its value. One compiled version serves every model: the readings' model travels as arrays.

**Random numbers.** The compiled loop draws its own numbers, inside the loop, from the filter's
``numpy.random.Generator`` (numba's implementations of numpy's own algorithms, called on the generator's
bit generator, so the stream is numpy's and the generator's state afterwards is the one a pickled state
carries on; called on the bit generator rather than through the Generator's methods, which pass the
reference-counted Generator and pay an atomic increment and decrement per number). Only the
numbers a particle needs are drawn, in this order: for each block of runs, for each step, for each
run of the block, for each particle: (optimal proposal) one uniform per censored reading, in channel
order, then the n standard normals of the state; then, if the run resamples, one uniform. The numpy
path draws the same kinds of numbers, all runs at once (a uniform per channel and particle, the
normals, a uniform per run); so the two paths agree in law, and exactly for the same numbers.

**Memory and layout.** Runs are processed in blocks (outer loop) over time (inner loop, compiled); a
block's particles stay in the cache for its T steps, copied for the call into one row per state component
(``(B, n, N_p)``: a component of a run's particles contiguous), so that every stage of a step is a pass
over the run's particles (propagation, predicted readings, conditioning, noise, weights, moments) that
LLVM vectorises; only the draws and the branches of the censored quantile run particle by particle. The
working memory is the block's copy and one run's scratch (its proposals, numbers and weights, a few
``N_p``-vectors); the particles of every run (the final state, from which a filter can
continue) are the ``(N, N_p, n)`` array of the state, updated in place; nothing grows with T but the
per-step outputs requested (``outputs="last"`` requests none). With several blocks, block ``j`` draws
its numbers after block ``j-1`` has drawn all of its own; a filter continued from its final state
equals one call when the runs fit one block.

**Weights held linear between resamplings.** After a resampling every weight is :math:`1/N_p`; from
there on a run's normalised weights are held as numbers :math:`V_i` (in the log-weights array, flagged
per run), not logarithms, and a step multiplies them by the particle's likelihood: a censored reading
by its mass :math:`\Phi(a)` (no ``log`` and no ``exp``), an interior one by
:math:`e^{\ell_i - \max_j\ell_j}` (the one ``exp`` the log-sum-exp normalisation needs too, in a vectorised
pass: :func:`~tobitkf.filters._compiled_censored._exp_neg`). Nothing
can underflow unnoticed: a particle's product of masses stays above 1e-200 (a smaller mass goes, as its
logarithm, to the exponent: so beyond 35 standard deviations, where it is :func:`log_ndtr` itself), a
normalised weight above 1e-100 (else the run returns to logarithms, formed from the exact parts
:math:`\log V_i + \log(\text{masses}) + \ell_i - \log\text{total}`, until its next resampling), and when
every weight of a run is under 1e-100 they are scaled by a power of 2 (exactly) before the effective
sample size squares them. The log weights of the state are the logarithms of these numbers (formed
once per call). The same arithmetic as the log-sum-exp form up to rounding (the tests hold both to
1e-12 against the numpy path, the hand-over to logarithms included).

**The normal tails** cost what the bootstrap weight and the censored draw need, no more: a censored
weight is :math:`\Phi(a)` from :math:`\Phi(-|a|)`, computed for all particles of a run in one vectorised
pass by the package's compiled censored statistics (:func:`_tail_mass`; relative error about 1e-14 within
8 standard deviations, 2e-13 at 35) (with logarithms: :math:`\log\Phi(a)`, :func:`log_ndtr`; beyond
25√2 ≈ 35.4 standard deviations the asymptotic series of ``erfcx``), and the censored draw
:math:`z = \Phi^{-1}(u\,\Phi(a))` reuses that :math:`\Phi(a)` (:func:`censored_draw`): the quantile by
Wichura's AS 241 (rational functions, relative error about 1e-16: no further ``erfc`` or ``exp``), its
tail from :math:`\sqrt{-\log p}` and the upper tail from :math:`1 - p = (1-u) + u\,\Phi(-a)` (no
cancellation). :func:`ndtri_exp` (the quantile from :math:`\log p`) serves the far tail. The quantiles and
:func:`log_ndtr` agree with ``scipy.special`` to about 1e-15. Functions are compiled on first use and cached on disk
(``cache=True``).

Cost per particle and step (``benchmarks/bench_particle.py`` times it against a plain vectorised numpy
filter and the `particles` and `cuthbert` packages): n normal draws (a call into the bit generator each:
at n = 2 about a third of the time) and vectorised passes for the matrix-vector products, the masses and
the weights; for a censored reading under the optimal proposal a uniform and the quantile's branches (in
the tails of :math:`\Phi^{-1}`, a ``log`` and a ``sqrt``); the resampling in one pass. The fast-math flags
are ``contract`` on AS 241's polynomials (:func:`_poly7`) and ``reassoc`` on the three weighted sums
(:func:`_sums`, :func:`_dev_sum`, :func:`_dev2_sum`: vectorised, their order changes them at rounding
level); everything else is strict IEEE.

References: M. J. Wichura, Algorithm AS 241: the percentage points of the normal distribution, Applied
Statistics 37(3), 1988.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

# numba's own implementations of Generator.random and Generator.standard_normal (numpy's algorithms on the bit
# generator's C functions), called on the bit generator itself: a call through the Generator's method passes
# the reference-counted Generator and pays an atomic increment and decrement per number drawn (measured: a
# third of the loop's time at n = 2). The same functions, so the same stream.
from numba.np.random.distributions import random_standard_normal as _standard_normal
from numba.np.random.generator_core import next_double as _next_double

from .._compiled_linalg import psd_root
from ._compiled_censored import _exp_neg
from ._compiled_particle_readings import _tail_mass, compiled_readings, log_ndtr, reading_log_weights, tail_masses
from ._particle_rng import generator
from ._readings import _INTERIOR, _INTERVAL, _LOWER, _MISSING, _RTOL_LIMIT, _UPPER

__all__ = [
    "log_ndtr",
    "ndtri_exp",
    "censored_draw",
    "pf_block",
    "runs_per_block",
    "filter_blocks",
    "BLOCK_BYTES",
]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)
_LN2 = math.log(2.0)
_INF = math.inf

#: cache budget of one block of runs (bytes): its particles and log-weights stay in the core's L2 cache
BLOCK_BYTES = 1 * 2**20
#: linear weights (see :func:`pf_block`): a particle's product of censored masses stays above this...
_F_MIN = 1e-200
#: ...and its normalised weight above this, else the run's weights return to logarithms
_W_MIN = 1e-100
_LOG_W_MIN = math.log(_W_MIN)


# --------------------------------------------------------------------------- normal tails


# Wichura's AS 241 (PPND16): the normal quantile by rational functions, relative error about 1e-16.
# The central region |p - 1/2| <= 0.425, in r = 0.180625 - (p - 1/2)^2:
_A = (3.3871328727963666080e0, 1.3314166789178437745e2, 1.9715909503065514427e3, 1.3731693765509461125e4,
      4.5921953931549871457e4, 6.7265770927008700853e4, 3.3430575583588128105e4, 2.5090809287301226727e3)  # fmt: skip
_B = (1.0, 4.2313330701600911252e1, 6.8718700749205790830e2, 5.3941960214247511077e3, 2.1213794301586595867e4,
      3.9307895800092710610e4, 2.8729085735721942674e4, 5.2264952788528545610e3)  # fmt: skip
# the tails, in s = sqrt(-log(min(p, 1 - p))): s <= 5 (in s - 1.6) and s > 5 (in s - 5)
_C = (1.42343711074968357734e0, 4.63033784615654529590e0, 5.76949722146069140550e0, 3.64784832476320460504e0,
      1.27045825245236838258e0, 2.41780725177450611770e-1, 2.27238449892691845833e-2, 7.74545014278341407640e-4)  # fmt: skip
_D = (1.0, 2.05319162663775882187e0, 1.67638483018380384940e0, 6.89767334985100004550e-1, 1.48103976427480074590e-1,
      1.51986665636164571966e-2, 5.47593808499534494600e-4, 1.05075007164441684324e-9)  # fmt: skip
_E = (6.65790464350110377720e0, 5.46378491116411436990e0, 1.78482653991729133580e0, 2.96560571828504891230e-1,
      2.65321895265761230930e-2, 1.24266094738807843860e-3, 2.71155556874348757815e-5, 2.01033439929228813265e-7)  # fmt: skip
_F = (1.0, 5.99832206555887937690e-1, 1.36929880922735805310e-1, 1.48753612908506148525e-2, 7.86869131145613259100e-4,
      1.84631831751005468180e-5, 1.42151175831644588870e-7, 2.04426310338993978564e-15)  # fmt: skip
_LOG_P_LOW = math.log(0.075)
_LOG_P_HIGH = math.log(0.925)


@njit(cache=True, error_model="numpy", fastmath={"contract"})
def _poly7(c, x):
    r""":math:`\sum_{i=0}^7 c_i x^i` by Estrin's scheme (three levels of multiply-adds instead of Horner's chain
    of seven: the two polynomials of a quotient and the particles around them overlap). The only fast-math
    flag is ``contract`` (a multiply-add rounded once, as accurate as or more than the two roundings; no
    reassociation), here and nowhere else: these are rational approximations of relative error ~1e-16."""
    x2 = x * x
    x4 = x2 * x2
    return (c[0] + c[1] * x) + x2 * (c[2] + c[3] * x) + x4 * ((c[4] + c[5] * x) + x2 * (c[6] + c[7] * x))


@njit(cache=True, error_model="numpy", inline="always")
def _quantile_center(q):
    """:math:`\\Phi^{-1}(1/2 + q)` for :math:`|q| \\le 0.425` (AS 241)."""
    r = 0.180625 - q * q
    return q * _poly7(_A, r) / _poly7(_B, r)


@njit(cache=True, error_model="numpy", inline="always")
def _quantile_tail(s):
    r""":math:`-\Phi^{-1}(p)` for :math:`p < 0.075` given :math:`s = \sqrt{-\log p}` (AS 241; > 0)."""
    if s <= 5.0:
        s -= 1.6
        return _poly7(_C, s) / _poly7(_D, s)
    s -= 5.0
    return _poly7(_E, s) / _poly7(_F, s)


@njit(cache=True, error_model="numpy")
def _ndtri_exp_far(t):
    """:func:`ndtri_exp` below t = -700 (Phi(z) under 1e-304): Newton steps on log Phi(z) = t from AS 241's tail."""
    z = -_quantile_tail(math.sqrt(-t))
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

    AS 241 (Wichura 1988): the lower tail (:math:`p < 0.075`) from :math:`s = \sqrt{-t}` (no exponential),
    the centre from :math:`p = e^t`, the upper tail from :math:`1 - p = -\mathrm{expm1}(t)` (no
    cancellation); below t = -700 Newton steps on :math:`\log\Phi(z) = t`."""
    if t != t or t > 0.0:
        return math.nan
    if t == -_INF:
        return -_INF
    if t == 0.0:
        return _INF
    if t < -700.0:
        return _ndtri_exp_far(t)
    if t < _LOG_P_LOW:
        return -_quantile_tail(math.sqrt(-t))
    if t > _LOG_P_HIGH:
        return _quantile_tail(math.sqrt(-math.log(-math.expm1(t))))
    return _quantile_center(math.exp(t) - 0.5)


@njit(cache=True, error_model="numpy", inline="always")
def _normal_mass(x, M):
    r"""The mass :math:`\Phi(x)` in the form the weights use, given :math:`M = \Phi(-|x|)`
    (:func:`_tail_mass`): ``(far, lm, M, upper)``.

    For x > 0, ``upper`` (the mass is :math:`1 - M`); down to 25√2 ≈ 35.4 standard deviations below 0, the
    mass is :math:`M`; beyond, ``far`` and :math:`lm = \log\Phi(x)` through :func:`log_ndtr` (the mass itself
    would underflow)."""
    upper = x > 0.0
    if not (upper or abs(x) * _SQRT1_2 < 25.0):
        return True, log_ndtr(x), 0.0, False
    return False, 0.0, M, upper


@njit(cache=True, error_model="numpy", inline="always")
def _censored_core(a, M, u):
    r"""The mass of :math:`(-\infty, a]` (as :func:`_normal_mass`, given :math:`M = \Phi(-|a|)`) and the draw
    :math:`\Phi^{-1}(u\,\Phi(a))`: ``(far, lm, M, upper, z)``; the quantile reuses the mass (no ``erfc`` or
    ``exp``)."""
    far, lm, M, upper = _normal_mass(a, M)
    if far:
        return far, lm, M, upper, ndtri_exp(math.log(u) + lm)
    p = u * ((1.0 - M) if upper else M)
    if p > 0.925:  # (only when upper)
        return far, lm, M, upper, _quantile_tail(math.sqrt(-math.log((1.0 - u) + u * M)))
    if p < 0.075:
        if p == 0.0:
            return far, lm, M, upper, -_INF
        return far, lm, M, upper, -_quantile_tail(math.sqrt(-math.log(p)))
    return far, lm, M, upper, _quantile_center(p - 0.5)


@njit(cache=True, error_model="numpy", inline="always")
def censored_draw(a, u):
    r"""The log-mass and a draw of a standard normal truncated to :math:`(-\infty, a]`:
    :math:`(\log\Phi(a),\ \Phi^{-1}(u\,\Phi(a)))` for a uniform u, the two sharing one mass
    (:func:`_tail_mass`).

    Equal to ``(log_ndtr(a), ndtri_exp(log(u) + log_ndtr(a)))`` (the numpy path's composition) to the mass's
    accuracy (about 1e-14 relative): :math:`p = u\Phi(a)` is formed directly (:math:`\Phi(a) \ge 10^{-274}`
    here, so :math:`\log p` does not underflow), the quantile's upper tail from
    :math:`1 - p = (1 - u) + u\,\Phi(-a)`; beyond 35 standard deviations (:math:`a < -25\sqrt2`) through
    :func:`log_ndtr` and :func:`ndtri_exp`."""
    far, lm, M, upper, z = _censored_core(a, _tail_mass(a), u)
    if far:
        return lm, z
    return (math.log1p(-M) if upper else math.log(M)), z


@njit(cache=True, error_model="numpy")
def interval_draw(a, b, u):
    r"""The log-mass and a draw of a standard normal truncated to :math:`[a, b]` for a uniform u, as the numpy
    path's ``_log_interval`` and ``_interval_z``: mirrored to :math:`a \le 0` (:math:`[-b, -a]` when a > 0),
    :math:`\ell = \log\Phi(b) + \mathrm{log1p}(-e^{\log\Phi(a) - \log\Phi(b)})`,
    :math:`z = \Phi^{-1}(\Phi(a) + u e^\ell)` through :func:`ndtri_exp` of the log-sum (numpy's ``logaddexp``),
    clipped to the window."""
    flip = a > 0.0
    a2 = -b if flip else a
    b2 = -a if flip else b
    la = log_ndtr(a2)
    lb = log_ndtr(b2)
    lm = lb + math.log1p(-math.exp(la - lb))
    t = math.log(u) + lm
    if la == t:
        q = la + _LN2
    elif la > t:
        q = la + math.log1p(math.exp(t - la))
    else:
        q = t + math.log1p(math.exp(la - t))
    z = min(max(ndtri_exp(q), a2), b2)
    return lm, -z if flip else z


@njit(cache=True, error_model="numpy", inline="always")
def _window_core(a, b, Ma, Mb, u):
    r"""The log-mass of the window :math:`[a, b]` (:math:`a \le 0`) and the draw
    :math:`\Phi^{-1}(\Phi(a) + u(\Phi(b) - \Phi(a)))`, from the tail masses :math:`M_a = \Phi(-|a|)`,
    :math:`M_b = \Phi(-|b|)` (:func:`_tail_mass`): the quantile by AS 241 from p, or from
    :math:`1 - p = (1 - \Phi(b)) + (1 - u)(\Phi(b) - \Phi(a))` in the upper tail. NaN (for
    :func:`interval_draw`) where the mass would lose more than two bits to cancellation or b < -35."""
    pa = Ma if a > -_INF else 0.0
    qb = (Mb if b > 0.0 else 1.0 - Mb) if b < _INF else 0.0
    pb = 1.0 - qb if b > 0.0 else Mb
    mass = pb - pa
    if b < -35.0 or not mass * 4.0 >= pb:
        return math.nan, 0.0
    p = pa + u * mass
    if p > 0.925:
        z = _quantile_tail(math.sqrt(-math.log(qb + (1.0 - u) * mass)))
    elif p < 0.075:
        z = -_quantile_tail(math.sqrt(-math.log(p))) if p > 0.0 else -_INF
    else:
        z = _quantile_center(p - 0.5)
    return math.log(mass), min(max(z, a), b)


@njit(cache=True, error_model="numpy", inline="always")
def _mass_factor(far, lm, M, upper, F):
    """A censored channel's weight factor in the linear weights: ``(F', log-part)``. The mass multiplies the
    particle's factor F while the product stays above :data:`_F_MIN`; else (or far in the tail) its
    logarithm goes to the log part (exact, and no underflow)."""
    if far:
        return F, lm
    mass = 1.0 - M if upper else M
    if mass * F < _F_MIN:
        return F, (math.log1p(-M) if upper else math.log(M))
    return F * mass, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _limit_z(Z, lower, lo, hi, isd, Np):
    r"""The particles' standardised distances past a censored reading's limit, in place: ``Z`` (Np,) the latent
    means become :math:`(lo - z_p)/s` at the lower limit (``lower``), :math:`(z_p - hi)/s` at the upper one
    (``isd`` = 1/s), so that the reading's mass is :math:`\Phi(Z_p)` on either side."""
    if lower:
        for p in range(Np):
            Z[p] = (lo - Z[p]) * isd
    else:
        for p in range(Np):
            Z[p] = (Z[p] - hi) * isd


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


# --------------------------------------------------------------------------- passes over a run's particles


@njit(cache=True, error_model="numpy")
def _row_dot(V, c, out):
    r"""``out[p] = sum_j V[j, p] c[j]`` (V: (n, Np)), summed in j's order as the per-particle loops did; the inner
    loop runs over the particles (vectorised)."""
    Np = V.shape[1]
    for p in range(Np):
        out[p] = 0.0
    for j in range(V.shape[0]):
        cj = c[j]
        for p in range(Np):
            out[p] += V[j, p] * cj


# The three weighted sums over a run's particles may be reassociated (the only fast-math flag here): LLVM then
# vectorises them with several accumulators, where a strict left-to-right sum is one chain of dependent adds
# (a few cycles per particle each). The order of a sum of thousands of terms changes it at rounding level.


@njit(cache=True, error_model="numpy", fastmath={"reassoc"})
def _sums(w):
    r""":math:`(\sum_p w_p,\ \sum_p w_p^2)`."""
    tot = 0.0
    sw2 = 0.0
    for p in range(w.shape[0]):
        tot += w[p]
        sw2 += w[p] * w[p]
    return tot, sw2


@njit(cache=True, error_model="numpy", fastmath={"reassoc"})
def _dev_sum(w, x, x0):
    r""":math:`\sum_p w_p (x_p - x_0)`."""
    s = 0.0
    for p in range(w.shape[0]):
        s += w[p] * (x[p] - x0)
    return s


@njit(cache=True, error_model="numpy", fastmath={"reassoc"})
def _dev2_sum(w, x, x0, z, z0):
    r""":math:`\sum_p w_p (x_p - x_0)(z_p - z_0)`."""
    s = 0.0
    for p in range(w.shape[0]):
        s += w[p] * (x[p] - x0) * (z[p] - z0)
    return s


# --------------------------------------------------------------------------- a block of runs over T steps


@njit(cache=True, error_model="numpy", nogil=True)
def pf_block(
    optimal,
    rng,
    X,
    lw,
    ll_acc,
    xm,
    Pm,
    A,
    G,
    Qd,
    C,
    r,
    y,
    LO,
    HI,
    readings,
    thr,
    o_mean,
    o_cov,
    o_var,
    o_pm,
    o_pc,
    o_ext,
    want,
):
    r"""The particle filter for the B runs of a block over T steps, in place, drawing its own numbers.

    Parameters
    ----------
    optimal : bool
        The locally optimal proposal (else the bootstrap one).
    rng : numpy.random.Generator
        The filter's generator (advanced; the order of the draws is the module's).
    X : (B, Np, n)
        The particles at the start; on return those after the last step.
    lw : (B, Np)
        Normalised log weights, updated (inside the call a run's row may hold the weights themselves: see
        "Weights held linear" in the module's docstring; logarithms again on return).
    ll_acc : (B,)
        Running sum of the log-likelihood, updated.
    xm, Pm : (B, n), (B, n, n)
        In: the weighted moments at the start; out: those after the last step.
    A, G, Qd : (n, n), (n, w), (n, n)
        Transition, a root of the process covariance (G G^T = Qd), the process covariance (of a window of
        states: the top block of ``nb`` rows moves, the others are shifted down by A's identity blocks, G is
        zero below the top block).
    C : (m, n) ; r : (m,)
        Readings matrix and noise variances.
    y : (B, T, m) ; LO, HI : (T, m)
        Readings (NaN = missing) and limits.
    readings : tuple
        ``(general, nb, k0, H, gains, modes, ylo, yhi)``: whether the readings are the general ones of
        :mod:`tobitkf.filters._compiled_particle_readings` (bootstrap proposal only; else linear readings with
        censoring, by C, LO, HI), the top block's size, the step before the first reading, and that module's
        rows, gains, modes (m, K, n), (m, K, 2), (m, J, 3) and reading intervals (B, T, m).
    thr : float
        Resample when the effective sample size is below ``thr`` (the threshold times Np).
    o_mean, o_cov, o_var, o_pm, o_pc : (B, T, ...) or placeholders
        Outputs per step: the weighted mean and covariance, the variances, the linear prediction of the
        moments (written where ``want`` says so).
    o_ext : (B, T, 3)
        The effective sample size, whether the run resampled (1.0/0.0) and the step's log-likelihood
        estimate (-inf where no particle explains the reading).
    want : (6,) bool
        Which of mean, cov, var, pred_mean, pred_cov, extras to write.
    """
    B, Np, n = X.shape
    T, m = LO.shape
    general, nb, k0, H, gains, modes, ylo, yhi = readings
    K = H.shape[1]
    TJ = np.empty(modes.shape[1])
    SR = np.empty((4, Np))  # the general readings' scratch
    SR2 = np.empty((2, 2 * Np))  # (and an interval's ends and tail masses)
    BAD = np.empty(Np, dtype=np.bool_)
    bg = rng.bit_generator  # the draws go to it directly (see the imports)
    cls = np.empty(m, dtype=np.int8)
    Sig = np.empty((n, n))
    L = np.empty((n, n))
    g = np.empty((m, n))
    sr = np.empty(m)
    isd = np.empty(m)
    lsd = np.empty(m)
    srp = np.empty(m)  # the bootstrap's noise standard deviations, their inverses and log-normalisers
    isp = np.empty(m)
    lsp = np.empty(m)
    for l in range(m):
        srp[l] = math.sqrt(r[l])
        isp[l] = 1.0 / srp[l]
        lsp[l] = math.log(srp[l]) + _LOG_SQRT_2PI
    e = np.empty(n)
    x0 = np.empty(n)
    d = np.empty(n)
    S1 = np.empty(n)
    S2 = np.empty((n, n))
    # The particles of the block, one row per state component ((B, n, Np): a component of every particle of a
    # run contiguous), and one run-step's scratch in the same layout: every pass below runs over the particles
    # in its inner loop (LLVM vectorises the arithmetic ones); X is read in at the start and written back at
    # the end.
    Xs = np.empty((B, n, Np))
    for b in range(B):
        for p in range(Np):
            for i in range(n):
                Xs[b, i, p] = X[b, p, i]
    MU = np.empty((n, Np))  # the proposals' means (optimal), the propagated particles (bootstrap)
    T1 = np.empty(Np)  # a row of the noise term
    U = np.empty((m, Np))  # one run-step's random numbers: the uniforms of the censored readings...
    E = np.empty((G.shape[1], Np))  # ...and the normals
    MM = np.empty(Np)  # the masses Phi(-|a|) of a censored channel
    Z = np.empty(Np)  # a channel's predicted reading, then its standardised limit, then the draw's offset
    INC = np.empty(Np)  # the log part of the new weights (then with the old log weights: work)
    work = np.empty(Np)  # the cumulative weights (resampling)
    F = np.empty(Np)  # the linear part (products of censored masses) of the new weights
    Wb = np.empty(Np)
    Xn = np.empty((n, Np))  # one run's particles before resampling
    # lin[b]: the run's weights are held linear in lw[b] (normalised), else as logarithms (see the docstring)
    lin = np.empty(B, dtype=np.bool_)
    for b in range(B):
        ok = True
        for p in range(Np):
            if not lw[b, p] >= _LOG_W_MIN:
                ok = False
                break
        lin[b] = ok
        if ok:
            for p in range(Np):
                lw[b, p] = math.exp(lw[b, p])
    for k in range(T):
        for b in range(B):
            Xb = Xs[b]
            # the linear prediction of the weighted moments (core.predict), where it is recorded
            if want[3]:
                for i in range(nb):  # (the outputs: the top block of a window)
                    s = 0.0
                    for j in range(n):
                        s += A[i, j] * xm[b, j]
                    o_pm[b, k, i] = s
            if want[4]:
                for i in range(nb):
                    for j in range(nb):
                        s = 0.0
                        for q in range(n):
                            for h in range(n):
                                s += A[i, q] * Pm[b, q, h] * A[j, h]
                        Sig[i, j] = s + Qd[i, j]
                for i in range(nb):
                    for j in range(nb):
                        o_pc[b, k, i, j] = 0.5 * (Sig[i, j] + Sig[j, i])
            for l in range(m):
                cls[l] = _classify(y[b, k, l], LO[k, l], HI[k, l])
                if general:  # a region's reading: exact (its value) or an interval
                    v = ylo[b, k, l]
                    cls[l] = _MISSING if v != v else (_INTERIOR if v == yhi[b, k, l] else _INTERVAL)
            lb = lin[b]
            for p in range(Np):
                INC[p] = 0.0
                F[p] = 1.0
            if optimal:
                # the Gaussian conditioning of _condition_in_sequence: the same for every particle of the run
                for i in range(n):
                    for j in range(n):
                        Sig[i, j] = Qd[i, j]
                for l in range(m):
                    if cls[l] == _MISSING:
                        continue
                    s2 = 0.0
                    for i in range(n):
                        s = 0.0
                        for j in range(n):
                            s += Sig[i, j] * C[l, j]
                        e[i] = s
                        s2 += s * C[l, i]
                    s2 += r[l]
                    den = s2 if s2 > 0.0 else 1.0
                    for i in range(n):
                        g[l, i] = e[i] / den
                    sr[l] = math.sqrt(s2)
                    isd[l] = 1.0 / sr[l]
                    lsd[l] = math.log(sr[l]) + _LOG_SQRT_2PI
                    for i in range(n):
                        for j in range(n):
                            Sig[i, j] = Sig[i, j] - s2 * g[l, i] * g[l, j]
                    for i in range(n):
                        for j in range(i + 1, n):
                            v = 0.5 * (Sig[i, j] + Sig[j, i])
                            Sig[i, j] = v
                            Sig[j, i] = v
                psd_root(Sig, L)
                # the run's numbers first, in the documented order (then the arithmetic runs without calls)
                for p in range(Np):
                    for l in range(m):
                        if cls[l] == _LOWER or cls[l] == _UPPER or cls[l] == _INTERVAL:
                            U[l, p] = _next_double(bg)
                    for j in range(n):
                        E[j, p] = _standard_normal(bg)
                # the proposal's mean: A x, then conditioned on the channels in turn
                for i in range(n):
                    for p in range(Np):
                        MU[i, p] = 0.0
                    for j in range(n):
                        aij = A[i, j]
                        for p in range(Np):
                            MU[i, p] += Xb[j, p] * aij
                for l in range(m):
                    c = cls[l]
                    if c == _MISSING:
                        continue
                    _row_dot(MU, C[l], Z)
                    sd = sr[l]
                    isl = isd[l]
                    if c == _INTERIOR:
                        yl = ylo[b, k, l] if general else y[b, k, l]
                        ls = lsd[l]
                        for p in range(Np):
                            dv = yl - Z[p]
                            zz = dv * isl
                            INC[p] += -0.5 * zz * zz - ls
                            Z[p] = dv
                    elif c == _INTERVAL:  # a draw from the window the reading says the latent reading is in
                        lo, hi = ylo[b, k, l], yhi[b, k, l]
                        TA, TM = SR2[0], SR2[1]
                        for p in range(Np):  # its ends, mirrored to a <= 0 (as the numpy path)
                            a = (lo - Z[p]) / sd
                            bb = (hi - Z[p]) / sd
                            flip = a > 0.0
                            TA[p] = -bb if flip else a
                            TA[Np + p] = -a if flip else bb
                        tail_masses(TA, TM, 2 * Np)  # their tail masses
                        for p in range(Np):
                            lm, z = _window_core(TA[p], TA[Np + p], TM[p], TM[Np + p], U[l, p])
                            if lm != lm:  # far in the tails or a cancelling mass: logarithms throughout
                                lm, z = interval_draw((lo - Z[p]) / sd, (hi - Z[p]) / sd, U[l, p])
                            elif (lo - Z[p]) / sd > 0.0:
                                z = -z
                            INC[p] += lm
                            Z[p] = sd * z
                    else:
                        _limit_z(Z, c == _LOWER, LO[k, l], HI[k, l], isl, Np)
                        sgn = sd if c == _LOWER else -sd
                        tail_masses(Z, MM, Np)  # the masses
                        for p in range(Np):  # the draws: branches, and a log in the quantile's tails
                            far, lm, M, upper, z = _censored_core(Z[p], MM[p], U[l, p])
                            if lb:
                                F[p], lm = _mass_factor(far, lm, M, upper, F[p])
                            elif not far:
                                lm = math.log1p(-M) if upper else math.log(M)
                            INC[p] += lm
                            Z[p] = z * sgn
                    for i in range(n):
                        gi = g[l, i]
                        for p in range(Np):
                            MU[i, p] += Z[p] * gi
                # the particles: the mean plus L times the normals
                for i in range(n):
                    _row_dot(E, L[i], T1)
                    for p in range(Np):
                        Xb[i, p] = MU[i, p] + T1[p]
            else:
                for p in range(Np):
                    for j in range(E.shape[0]):
                        E[j, p] = _standard_normal(bg)
                for i in range(nb):
                    _row_dot(Xb, A[i], MU[i])
                    _row_dot(E, G[i], T1)
                    for p in range(Np):
                        MU[i, p] += T1[p]
                for i in range(nb, n):  # a window's older blocks: shifted down
                    for p in range(Np):
                        MU[i, p] = Xb[i - nb, p]
                for i in range(n):
                    for p in range(Np):
                        Xb[i, p] = MU[i, p]
                for l in range(m):
                    c = cls[l]
                    if general:
                        lo = ylo[b, k, l]
                        if lo == lo:  # (NaN: missing)
                            present = min(K, k0 + k + 2)  # term s reads the state s steps back
                            reading_log_weights(Xb, H[l], gains[l], modes[l], present, lo, yhi[b, k, l], r[l], INC, SR,
                                                SR2, BAD, TJ)  # fmt: skip
                        continue
                    if c == _MISSING:
                        continue
                    _row_dot(MU, C[l], Z)
                    isl = isp[l]
                    if c == _INTERIOR:
                        yl = y[b, k, l]
                        ls = lsp[l]
                        for p in range(Np):
                            zz = (yl - Z[p]) * isl
                            INC[p] += -0.5 * zz * zz - ls
                    else:
                        _limit_z(Z, c == _LOWER, LO[k, l], HI[k, l], isl, Np)
                        if lb:
                            tail_masses(Z, MM, Np)  # the masses
                            for p in range(Np):
                                far, lm, M, upper = _normal_mass(Z[p], MM[p])
                                F[p], lm = _mass_factor(far, lm, M, upper, F[p])
                                INC[p] += lm
                        else:
                            for p in range(Np):
                                INC[p] += log_ndtr(Z[p])
            # the largest log part and whether any log part is not 0 (else the linear weights need no exp)
            top = -_INF
            nz = False
            for p in range(Np):
                inc = INC[p]
                nz = nz or inc != 0.0
                w = inc if lb else inc + lw[b, p]
                INC[p] = w
                if w > top:
                    top = w
            # the new weights, unnormalised: exp(log weight - top) (logarithms), or
            # weight x mass factor x exp(log part - top) (linear; the exp only where a log part is not 0)
            if lb and not nz:
                top = 0.0
            dead = not (top > -_INF and top < _INF)
            if dead:  # no particle explains the reading: keep the weights, report -inf
                top = -_INF
                for p in range(Np):
                    if lb:
                        Wb[p] = lw[b, p]
                    else:
                        INC[p] = lw[b, p]
                        if INC[p] > top:
                            top = INC[p]
                if lb:
                    top = 0.0
                else:
                    for p in range(Np):
                        Wb[p] = math.exp(INC[p] - top)
            elif lb:
                if nz:
                    for p in range(Np):
                        Wb[p] = lw[b, p] * F[p] * _exp_neg(INC[p] - top)
                else:
                    for p in range(Np):
                        Wb[p] = lw[b, p] * F[p]
                wmax = 0.0
                for p in range(Np):
                    wmax = max(wmax, Wb[p])
                if wmax < _W_MIN:
                    # every weight small (masses far in the tails): scaled by a power of 2 (exactly) so the
                    # largest is in [1/2, 1), else their squares (the effective sample size) underflow
                    ex = math.frexp(wmax)[1]
                    sc = math.ldexp(1.0, -ex)
                    for p in range(Np):
                        Wb[p] *= sc
                    top += ex * _LN2
            else:
                for p in range(Np):
                    Wb[p] = _exp_neg(INC[p] - top)
            # the weighted moments: sums of the deviations from the run's first particle (no cancellation when
            # the mean is far from 0), normalised once
            full = want[1] or want[2] or want[4] or k == T - 1  # the covariance is needed (else the mean only)
            tot, sw2 = _sums(Wb)
            wmin = _INF
            for p in range(Np):
                wmin = min(wmin, Wb[p])
            for i in range(n):
                x0[i] = Xb[i, 0]
                S1[i] = _dev_sum(Wb, Xb[i], x0[i])
            if full:
                for i in range(n):
                    for j in range(i, n):
                        S2[i, j] = _dev2_sum(Wb, Xb[i], x0[i], Xb[j], x0[j])
            lnorm = math.log(tot) + top
            ll = -_INF if dead else lnorm
            ll_acc[b] += ll
            for i in range(n):
                d[i] = S1[i] / tot
                xm[b, i] = x0[i] + d[i]
            if full:
                for i in range(n):
                    for j in range(i, n):
                        v = S2[i, j] / tot - d[i] * d[j]
                        Pm[b, i, j] = v
                        Pm[b, j, i] = v
            ess = 1.0 / (sw2 / (tot * tot))
            res = ess < thr
            if res:
                # systematic resampling (the comparisons of systematic_resample, one run)
                u0 = _next_double(bg)
                cum = 0.0
                for p in range(Np):
                    cum += Wb[p] / tot
                    work[p] = cum
                work[Np - 1] = 1.0
                for i in range(n):
                    for p in range(Np):
                        Xn[i, p] = Xb[i, p]
                j = 0
                for p in range(Np):
                    v = (u0 + p) / Np
                    while j < Np and work[j] <= v:
                        j += 1
                    src = j if j < Np else Np - 1
                    for i in range(n):
                        Xb[i, p] = Xn[i, src]
                # equal weights: held linear from here on
                lin[b] = True
                for p in range(Np):
                    lw[b, p] = 1.0 / Np
            elif not lb:
                for p in range(Np):
                    lw[b, p] = INC[p] - lnorm
            elif dead or not wmin < _W_MIN * tot:
                it = 1.0 / tot
                for p in range(Np):
                    lw[b, p] = Wb[p] * it
            else:
                # a normalised weight would fall below _W_MIN: back to logarithms, from the exact parts
                lin[b] = False
                lt = math.log(tot) + top
                for p in range(Np):
                    lw[b, p] = math.log(lw[b, p]) + math.log(F[p]) + INC[p] - lt
            if want[0]:
                for i in range(nb):
                    o_mean[b, k, i] = xm[b, i]
            if want[1]:
                for i in range(nb):
                    for j in range(nb):
                        o_cov[b, k, i, j] = Pm[b, i, j]
            if want[2]:
                for i in range(nb):
                    o_var[b, k, i] = Pm[b, i, i]
            if want[5]:
                o_ext[b, k, 0] = ess
                o_ext[b, k, 1] = 1.0 if res else 0.0
                o_ext[b, k, 2] = ll
    # the particles back in the state's layout; the carry holds logarithms
    for b in range(B):
        for p in range(Np):
            for i in range(n):
                X[b, p, i] = Xs[b, i, p]
        if lin[b]:
            for p in range(Np):
                lw[b, p] = math.log(lw[b, p])


# --------------------------------------------------------------------------- the driver


def runs_per_block(particles: int, n: int, budget: int = BLOCK_BYTES) -> int:
    """Runs per block so that the block's particles and log weights fit ``budget`` bytes (at least one run)."""
    return max(1, budget // (8 * particles * (n + 1)))


def filter_blocks(pf: Any, y2: np.ndarray, state: Any, want: frozenset[str], batch: tuple[int, ...], block=None):
    """The particle filter's loop over the readings ``y2`` (N, T, m) from ``state``, compiled, in blocks of runs.

    ``pf`` is a :class:`~tobitkf.ParticleFilter` whose model the loop covers (time-invariant system, no input:
    ``ParticleFilter._compiled_gap``);
    ``block`` overrides the runs per block (:func:`runs_per_block`). Returns the
    :class:`~tobitkf.filters.core.FilterResult` its numpy loop returns: the outputs in ``want`` per step,
    the final state (particles, log weights, generator, running log-likelihood)."""
    from .core import FilterResult, FilterState

    model, system = pf.model, pf.system
    N, T, m = y2.shape
    n, Np, ns = model.nx, pf.particles, pf.n  # the particles' state (a window for fading), the system's
    optimal = pf.proposal == "optimal"
    k0 = int(state.k)
    C = np.ascontiguousarray(system.measurement(k0 + 1), dtype=float)
    d = np.diagonal(system.measurement_cov(k0 + 1)).astype(float)
    r = np.ascontiguousarray(np.sqrt(d) ** 2 if optimal else d)  # as the numpy path forms them
    LO, HI = np.empty((T, m)), np.empty((T, m))  # the limits per step: m numbers each, nothing per particle
    for i in range(T):
        LO[i], HI[i] = model.limits(k0 + 1 + i)
    rd = compiled_readings(model, system, y2, k0, LO, HI)  # the dynamics (of a window of states) and the readings
    A, G, Qd, general = rd["A"], rd["G"], rd["Qd"], rd["general"]
    carry = state.carry
    X = np.array(carry["particles"], dtype=float, order="C")  # (N, Np, n): the final particles, in place
    lw = np.array(carry["log_weights"], dtype=float, order="C")
    ll_acc = np.array(carry["log_likelihood"], dtype=float)
    xm = np.array(state.x, dtype=float).reshape(N, n)
    Pm = np.array(np.broadcast_to(state.P, (N, n, n)), dtype=float)
    rng = generator(carry["rng"])  # the filter's generator, restored from the state
    names = ("mean", "cov", "var", "pred_mean", "pred_cov", "extras")
    flags = np.array([key in want for key in names])
    shapes = {"mean": (ns,), "cov": (ns, ns), "var": (ns,), "pred_mean": (ns,), "pred_cov": (ns, ns)}
    outs = {key: np.empty((N, T) + shp) if key in want else np.empty((1, 1) + shp) for key, shp in shapes.items()}
    ext = np.empty((N, T, 3)) if flags[5] else np.empty((1, 1, 3))
    Bmax = min(N, int(block) if block else runs_per_block(Np, n))
    yc = np.ascontiguousarray(y2, dtype=float)
    for r0 in range(0, N, Bmax):
        r1 = min(N, r0 + Bmax)
        blk = {key: (a[r0:r1] if key in want else a) for key, a in outs.items()}
        reads = (general, rd["nb"], k0, rd["H"], rd["gains"], rd["modes"], rd["ylo"][r0:r1] if general else rd["ylo"],
                 rd["yhi"][r0:r1] if general else rd["yhi"])  # fmt: skip
        pf_block(optimal, rng, X[r0:r1], lw[r0:r1], ll_acc[r0:r1], xm[r0:r1], Pm[r0:r1], A, G, Qd, C, r,
                 yc[r0:r1], LO, HI, reads, pf.resample_threshold * Np, blk["mean"], blk["cov"], blk["var"],
                 blk["pred_mean"], blk["pred_cov"], ext[r0:r1] if flags[5] else ext, flags)  # fmt: skip
    new_carry = {"particles": X, "log_weights": lw, "rng": rng.bit_generator.state, "log_likelihood": ll_acc}
    final = FilterState(k=k0 + T, batch_shape=batch, x=xm, P=Pm, n=ns, S=None, carry=new_carry)

    def shaped(key):
        return outs[key].reshape(batch + outs[key].shape[1:]) if key in want else None

    extras = {}
    if flags[5]:
        extras = {"ess": ext[..., 0].copy(), "resampled": ext[..., 1] > 0.5, "log_likelihood": ext[..., 2].copy()}
        extras = {key: v.reshape(batch + v.shape[1:]) for key, v in extras.items()}
    return FilterResult(
        mean=shaped("mean"),
        cov=shaped("cov"),
        pred_mean=shaped("pred_mean"),
        pred_cov=shaped("pred_cov"),
        extras=extras,
        times=np.arange(k0 + 1, k0 + T + 1),
        var=shaped("var"),
        final=final,
    )
