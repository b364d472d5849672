r"""The censored-normal statistics of the compiled path (numba): the one implementation every compiled caller uses.

The compiled form of :func:`tobitkf.censored.censored_moments`, which stays the high-precision numpy reference
(tested against it on a grid out to ±40σ, one- and two-sided, and against 60-digit values). Everything is
built on one routine for a single finite limit, :func:`_one_sided_at`, written without a libm call or a
branch per run so that a loop over the runs of a block vectorises (AVX2/AVX-512: 4 or 8 runs per
instruction):

* :func:`one_sided_block`: a channel whose one finite limit the runs of a block share (the common Tobit case;
  an upper limit by mirroring), the TKF's statistics for all runs at once (:func:`lower_stats_block`: the form
  the fading and protocol kernels read);
* :func:`censored_stats`: one run with any limits (runs with their own limits, windows): one finite limit is
  :func:`_one_sided_at`, two are :func:`_window_stats` (the reference's routes: direct formulas with
  :math:`\Phi` from :func:`_one_sided_at`, a one-sided route when the far limit is negligible, Gauss–Legendre
  quadrature for a narrow window or a two-sided one in a tail);
* :func:`beyond`: the log-probability and truncated moments beyond one limit (the assumed-density updates and
  the steady-state fit's log-likelihood), finite however far in the tail.

Routes, in the standardized limit :math:`a = (\ell - \mu)/\sigma` of a lower limit :math:`\ell`:

* :math:`-4 \le a \le 2`: with :math:`x = |a|/\sqrt 2` and the scaled complementary error function
  :math:`E = \mathrm{erfcx}(x) = e^{x^2}\mathrm{erfc}(x)`, :math:`\Phi(-|a|) = \tfrac12 E e^{-x^2}`;
  for :math:`a > 0`, :math:`\gamma = \Phi(-a)` and the inverse Mills ratio
  :math:`\lambda = \varphi(a)/\gamma = \sqrt{2/\pi}/E`; for :math:`a \le 0`, :math:`\gamma = 1 - \Phi(a)`
  and :math:`\lambda = \varphi(a)/\gamma`; :math:`\mathrm{Var}[Z \mid Z > a] = 1 + a\lambda - \lambda^2`
  (the reference's direct formulas);
* :math:`a < -4`: the same, :math:`E` from a second fit in :math:`w = x_0/x`;
* :math:`a > 2`: Laplace's continued fraction, :math:`s = 2/(a + 3/(a + \dots))`, :math:`t = 1/(a + s)`,
  :math:`\lambda = a + t`, :math:`\mathrm{Var} = t(s - t)`, through fits of the smooth functions
  :math:`a\,t` and :math:`a^2 t(s - t)` of :math:`u = 2/a \in (0, 1)`, and :math:`\gamma = \varphi(a)/\lambda`.
  The reference takes the direct formulas up to :math:`a = 4` and the fraction beyond; between 2
  and 4 its :math:`1 + a\lambda - \lambda^2` cancels (its error reaches ~1e-12 relative near
  :math:`a = 4`), which the fitted fraction does not (within 2e-14 of the converged fraction: tested).

Each of the four functions (erfcx on :math:`[0, x_0]`, :math:`x_0 = 4/\sqrt 2`; :math:`\sqrt\pi\,x\,
\mathrm{erfcx}(x)` in :math:`w = x_0/x \in (0, 1]`; :math:`a t` and :math:`a^2 t (s - t)` in
:math:`u`) is the polynomial interpolating it at Chebyshev points (degree 24, 20, 28, 28), built at import
from :func:`scipy.special.erfcx` and from the continued fraction evaluated with 600 terms (converged to
rounding for :math:`a \ge 2`); interpolation errors are below 4e-15 relative (measured on dense grids).
The polynomials are evaluated as power series in four Horner chains (short dependency chains), and
:math:`e^{z}` as a polynomial with a table of powers of two instead of libm's ``exp``. The results agree
with the reference to 1e-13 relative where it is accurate (and through a filter with the numpy path to
1e-12); tested, also against 60-digit values, in ``tests/filters/test_kernels_censored.py`` and
``tests/filters/test_kernels.py``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, types
from numba.extending import intrinsic
from numpy.polynomial import chebyshev as _cheb
from scipy.special import erfcx as _erfcx

from ..censored import _CF_FROM, _FAR, _GL_W, _GL_X, _NARROW

__all__ = [
    "censored_stats",
    "window_direct",
    "beyond",
    "one_sided_block",
    "lower_stats_block",
    "censored_moments_array",
    "one_sided_array",
    "lower_stats_array",
    "GL_X",
    "GL_W",
    "X0",
    "A_TAIL",
]

# The quadrature of censored_moments (passed to the kernels), read-only: numba freezes a module-level array read-only
# in compiled code, so a kernel handed these from Python is compiled for the argument types the compiled loops give it
# (writable, every function that takes them, and its callees, was compiled a second time).
GL_X, GL_W = _GL_X.view(), _GL_W.view()
GL_X.flags.writeable = GL_W.flags.writeable = False

X0 = _CF_FROM * math.sqrt(0.5)  # erfcx argument at |a| = 4, the far side's edge
A_TAIL = 2.0  # a > A_TAIL: the tail fits (no cancellation in the variance), else erfcx
_NC = 32  # coefficients of every polynomial, zero-padded (four Horner chains of 8)
_CF_NODES = 600  # continued-fraction terms at the tail fits' nodes (converged to rounding at a >= 2)


def _interpolant(f, degree: int) -> np.ndarray:
    """Power-series coefficients (in t on [-1, 1], zero-padded to ``_NC``) of the polynomial of ``degree``
    interpolating ``f(t)`` at the Chebyshev points of the first kind."""
    t = np.cos(np.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))
    c = _cheb.cheb2poly(_cheb.chebfit(t, f(t), degree))
    out = np.zeros(_NC)
    out[: c.size] = c
    return np.ascontiguousarray(out)


def _far(t: np.ndarray) -> np.ndarray:
    w = 0.5 * (t + 1.0)  # w = X0 / x in (0, 1]; the Chebyshev points avoid w = 0
    x = X0 / w
    return math.sqrt(math.pi) * x * _erfcx(x)


def _tail(t: np.ndarray, which: int) -> np.ndarray:
    """``a t(a)`` (``which`` 0) or ``a^2 Var[Z | Z > a]`` (1) at ``a = A_TAIL / u``, ``u = (t + 1) / 2``, from
    Laplace's continued fraction evaluated backwards with ``_CF_NODES`` terms."""
    a = A_TAIL / (0.5 * (t + 1.0))
    s = np.zeros_like(a)
    for k in range(_CF_NODES, 1, -1):
        s = k / (a + s)
    tt = 1.0 / (a + s)
    return a * tt if which == 0 else a * a * (tt * (s - tt))


C_CENTRAL = _interpolant(lambda t: _erfcx(0.5 * (t + 1.0) * X0), 24)  # erfcx(x), x = (t + 1) X0 / 2
C_FAR = _interpolant(_far, 20)  # sqrt(pi) x erfcx(x), x = X0 / w, w = (t + 1) / 2
C_TAIL_T = _interpolant(lambda t: _tail(t, 0), 28)  # a t(a), a = A_TAIL / u, u = (t + 1) / 2
C_TAIL_V = _interpolant(lambda t: _tail(t, 1), 28)  # a^2 Var[Z | Z > a]

# exp(z) without libm (so that the loop vectorises): z = k ln2 + r, |r| <= ln(2)/2, exp(r) by its
# degree-12 Taylor polynomial (truncation < 2e-16 relative), 2^k from a table spanning the subnormals
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # fdlibm's split of ln 2: k * _LN2_HI is exact
_LN2_LO = 1.90821492927058770002e-10
_POW2_MIN = -1074
_POW2 = np.ldexp(1.0, np.arange(_POW2_MIN, 1))
_EXP_UNDER = -745.2  # exp(z) rounds to 0 below this (the smallest subnormal is e^-744.44)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_SQRT_2_PI = math.sqrt(2.0 / math.pi)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_TINY = float(np.finfo(np.float64).tiny)
_INF = math.inf


def _bitcast(name: str, source: Any, target: Any, doc: str) -> Any:
    """The intrinsic ``name`` that reads the bits of a ``source`` value as a ``target`` (an LLVM bitcast:
    vectorisable, unlike ``math.frexp``); ``source`` and ``target`` numba types of one size."""

    def cast(typingctx, value):
        if value != source:
            return None

        def codegen(context, builder, signature, args):
            return builder.bitcast(args[0], context.get_value_type(target))

        return target(source), codegen

    cast.__name__ = cast.__qualname__ = name
    cast.__doc__ = doc
    return intrinsic(cast)


_f64_bits = _bitcast("_f64_bits", types.float64, types.int64, "The bits of a float64 as an int64.")
_bits_f64 = _bitcast(
    "_bits_f64", types.int64, types.float64, "The float64 of the bits (int64): the inverse of _f64_bits."
)


# log(x) without libm (so that the loop vectorises): x = 2^k m, m in [sqrt(1/2), sqrt(2)), from the bits;
# log(m) = 2 atanh(f), f = (m - 1)/(m + 1), |f| < 0.172, by its series to f^21 (truncation < 3e-17 relative)
_LOG_SERIES = tuple(1.0 / (2 * j + 1) for j in range(1, 11))
_MANT = (1 << 52) - 1
_ONE_BITS = 1023 << 52


@njit(cache=True, error_model="numpy", inline="always")
def _log_pos(x):
    r""":math:`\log x` for :math:`x` from the smallest normal number to +inf, without a libm call (within 2 ulp
    of ``math.log``; tested)."""
    ix = _f64_bits(x)
    k = (ix >> 52) - 1023
    m = _bits_f64((ix & _MANT) | _ONE_BITS)  # [1, 2)
    big = m > _SQRT2
    m = 0.5 * m if big else m
    kf = float(k + 1 if big else k)
    f = (m - 1.0) / (m + 1.0)
    f2 = f * f
    c = _LOG_SERIES
    p = c[9]
    for j in range(8, -1, -1):
        p = p * f2 + c[j]
    lm = 2.0 * f + (2.0 * f) * (f2 * p)
    v = kf * _LN2_HI + (kf * _LN2_LO + lm)
    return v if x < _INF else x


@njit(cache=True, error_model="numpy", inline="always")
def _exp_neg(z):
    r""":math:`e^z` for :math:`z \le \ln(2)/2` (0 below the subnormals), without a libm call."""
    zc = max(z, _EXP_UNDER)
    k = math.floor(zc * _LOG2E + 0.5)
    r = (zc - k * _LN2_HI) - k * _LN2_LO
    r2 = r * r
    lo = 1.0 + r * (1.0 + r * (1.0 / 2 + r * (1.0 / 6 + r * (1.0 / 24 + r * (1.0 / 120 + r * (1.0 / 720))))))
    hi = 1.0 / 5040 + r * (
        1.0 / 40320 + r * (1.0 / 362880 + r * (1.0 / 3628800 + r * (1.0 / 39916800 + r * (1.0 / 479001600))))
    )
    e = lo + (r2 * r2 * r2 * r) * hi
    v = e * _POW2[min(max(int(k) - _POW2_MIN, 0), -_POW2_MIN)]
    return v if z > _EXP_UNDER else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _coef(j, central, far):
    return C_CENTRAL[j] if central else (C_FAR[j] if far else C_TAIL_T[j])


@njit(cache=True, error_model="numpy", inline="always")
def _first_poly(t, central, far):
    """The route's first polynomial at ``t``: four Horner chains of 8 terms (short dependency chains)."""
    h0 = _coef(7, central, far)
    h1 = _coef(15, central, far)
    h2 = _coef(23, central, far)
    h3 = _coef(31, central, far)
    for j in range(6, -1, -1):
        h0 = h0 * t + _coef(j, central, far)
        h1 = h1 * t + _coef(8 + j, central, far)
        h2 = h2 * t + _coef(16 + j, central, far)
        h3 = h3 * t + _coef(24 + j, central, far)
    t8 = t * t
    t8 = t8 * t8
    t8 = t8 * t8
    return (h0 + t8 * h1) + (t8 * t8) * (h2 + t8 * h3)


@njit(cache=True, error_model="numpy", inline="always")
def _tail_var_poly(t):
    r""":math:`a^2\,\mathrm{Var}[Z \mid Z > a]` of the tail route: four Horner chains of 8 terms."""
    c = C_TAIL_V
    h0 = c[7]
    h1 = c[15]
    h2 = c[23]
    h3 = c[31]
    for j in range(6, -1, -1):
        h0 = h0 * t + c[j]
        h1 = h1 * t + c[8 + j]
        h2 = h2 * t + c[16 + j]
        h3 = h3 * t + c[24 + j]
    t8 = t * t
    t8 = t8 * t8
    t8 = t8 * t8
    return (h0 + t8 * h1) + (t8 * t8) * (h2 + t8 * h3)


@njit(cache=True, error_model="numpy", inline="always")
def _one_sided_at(mu, sd, lo):
    """The statistics of one run for a lower limit ``lo`` alone (inlined into the block loops, where it
    vectorises): ``(p_lower, gamma, lambda, truncated mean, truncated variance, censored mean, censored
    variance)``, the quantities of :func:`censored_stats` (module docstring)."""
    a = (lo - mu) / sd
    ab = abs(a)
    rb = 1.0 / ab  # the one reciprocal of the routes (inf at a = 0, then unused)
    tail = a > A_TAIL
    far = a < -_CF_FROM
    central = not (tail or far)
    pos = a > 0.0
    # the route's argument in [-1, 1]: x / X0 = |a| / 4, X0 / x = 4 / |a| or A_TAIL / a, mapped
    u = ab * (1.0 / _CF_FROM) if central else (_CF_FROM * rb if far else A_TAIL * rb)
    t = 2.0 * u - 1.0
    p1 = _first_poly(t, central, far)
    ez = _exp_neg(-0.5 * a * a)  # e^{-x^2}, x = |a| / sqrt(2)
    phi = ez * _INV_SQRT_2PI
    # erfcx(x) (central, far side), h = Phi(-|a|)
    E = p1 if central else p1 * (_INV_SQRT_PI * _SQRT2) * rb
    h = 0.5 * E * ez
    lam_tail = ab + p1 * rb  # a + t
    # one division: lambda (central a > 0: sqrt(2/pi) / E; a <= 0: phi / gamma) or gamma (tail: phi / lambda)
    g_left = 1.0 - h
    num = phi if (tail or not pos) else _SQRT_2_PI
    den = lam_tail if tail else (E if pos else g_left)
    q = num / den
    if tail:
        g = q
        lam = lam_tail
        zvar = _tail_var_poly(t) * rb * rb
    else:
        g = h if pos else g_left
        lam = q
        zvar = 1.0 + a * lam - lam * lam
    plo = 1.0 - g if (tail or pos) else h
    g = min(max(g, 0.0), 1.0)
    zvar = max(zvar, 0.0)
    tmean = mu + sd * lam
    tvar = sd * sd * zvar
    cm = plo * lo + g * tmean
    d1 = tmean - cm
    d2 = lo - cm
    cvar = g * (tvar + d1 * d1) + plo * (d2 * d2)
    return plo, g, lam, tmean, tvar, cm, cvar


@njit(cache=True, error_model="numpy", inline="always")
def beyond(mu, sd, lim, sign):
    r"""The latent :math:`y^* \sim N(\mu, sd^2)` beyond the finite limit ``lim`` on the side ``sign``
    (+1: :math:`y^* \ge` lim, -1: :math:`y^* \le` lim): ``(p_other, log_p, mean, var)`` = the probability
    of the other side, the log-probability of this one and the truncated mean and variance, from
    :func:`_one_sided_at` (vectorisable). :math:`\log P` is :math:`\log\gamma` where :math:`\gamma \ge 1/2`
    and :math:`-a^2/2 - \log\sqrt{2\pi} - \log\lambda` beyond the mean (:math:`\gamma = \varphi(a)/\lambda`),
    finite however far the limit lies in the tail (also where :math:`\gamma` underflows)."""
    m = sign * mu
    lm = sign * lim
    plo, g, lam, tmean, tvar, _cm, _cv = _one_sided_at(m, sd, lm)
    a = (lm - m) / sd
    centre = a <= 0.0
    lg = _log_pos(max(g if centre else lam, _TINY))  # one logarithm, vectorisable (_log_pos)
    logp = lg if centre else -0.5 * a * a - _LOG_SQRT_2PI - lg
    return plo, logp, sign * tmean, tvar


@njit(cache=True, error_model="numpy")
def _quadrature_moments(a2, b2, glx, glw, buf):
    r"""``(E[Z | window], Var[Z | window], P(window))`` of :math:`Z \sim N(0, 1)` on the window [a2, b2]
    (mirrored so that :math:`a_2 \ge -b_2`), as :func:`tobitkf.censored._tail_moments`: Gauss–Legendre
    quadrature (nodes ``glx``, weights ``glw``) in shifted coordinates :math:`u = z - a_2`, where the
    density is :math:`\varphi(a_2)e^{-a_2u - u^2/2}` on :math:`[0, \min(b_2 - a_2, u_{max})]`
    (:math:`u_{max}`: the density down to :math:`e^{-40}`), with a two-pass variance. The exponents lie in
    [-40.2, 0.125] (:func:`_exp_neg` is exact to 2 ulp there). ``buf`` (2, len(glx)) scratch."""
    umax = 80.0 / (a2 + math.hypot(a2, math.sqrt(80.0)))  # -a2 + sqrt(a2^2 + 80), no cancellation
    half = 0.5 * min(b2 - a2, umax)
    G = glx.shape[0]
    for j in range(G):
        u = half * (glx[j] + 1.0)
        buf[0, j] = u
        buf[1, j] = glw[j] * half * _exp_neg(-a2 * u - 0.5 * u * u)
    i0 = 0.0
    i1 = 0.0
    for j in range(G):
        i0 += buf[1, j]
        i1 += buf[1, j] * buf[0, j]
    umean = i1 / i0
    i2 = 0.0
    for j in range(G):
        d = buf[0, j] - umean
        i2 += buf[1, j] * d * d
    return a2 + umean, i2 / i0, math.exp(-0.5 * a2 * a2 - _LOG_SQRT_2PI + math.log(i0))


@njit(cache=True, error_model="numpy", inline="always")
def _assemble(mu, sd, lo, hi, p_lo, p_hi, gam, lam, zvar):
    """The 8-tuple of :func:`censored_stats` from the standardized statistics (as :mod:`tobitkf.censored`)."""
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


@njit(cache=True, error_model="numpy", inline="always")
def window_direct(mu, sd, lo, hi):
    r"""The direct formulas of :func:`_window_stats` for two finite limits lo < hi, without a branch or a libm
    call per run (a loop over runs that inlines it vectorises), and whether the run needs one of the other
    routes instead: ``(other, a2, b2, flip, one_sided, p_lo, p_hi, gam, lam, zvar)``; ``gam``, ``lam``,
    ``zvar`` are the direct route's (meaningless where ``other``), :math:`[a_2, b_2]` the standardized window
    mirrored to the upper tail (``flip``). :math:`\Phi(a)`, :math:`1 - \Phi(a)`, :math:`\Phi(-b)`,
    :math:`\Phi(b)` by :func:`_one_sided_at` at :math:`a` and :math:`-b`; :math:`\gamma` subtracts the small
    tail probabilities, :math:`\lambda = (\varphi(a) - \varphi(b))/\gamma`, :math:`\mathrm{Var} = 1 +
    (a\varphi(a) - b\varphi(b))/\gamma - \lambda^2`."""
    a = (lo - mu) / sd
    b = (hi - mu) / sd
    # Phi(a), Phi(-a) and Phi(-b), Phi(b), by the same route at a and at -b (a symmetric window: p_lo = p_hi)
    p_lo, q_a, _l, _m, _v, _c, _w = _one_sided_at(0.0, 1.0, a)
    p_hi, q_b, _l, _m, _v, _c, _w = _one_sided_at(0.0, 1.0, -b)
    flip = a < -b
    a2 = -b if flip else a
    b2 = -a if flip else b
    one_sided = (b2 - a2) * (b2 + a2) > _FAR
    other = (one_sided and a2 > A_TAIL) or (a2 > _CF_FROM and not one_sided) or (b - a < _NARROW)
    gam = q_a - p_hi if a > 0 else (q_b - p_lo if b < 0 else 1.0 - p_lo - p_hi)
    phi_a = _exp_neg(-0.5 * a * a) * _INV_SQRT_2PI
    phi_b = _exp_neg(-0.5 * b * b) * _INV_SQRT_2PI
    lam = (phi_a - phi_b) / gam
    zvar = 1.0 + (a * phi_a - b * phi_b) / gam - lam * lam
    return other, a2, b2, flip, one_sided, p_lo, p_hi, gam, lam, zvar


@njit(cache=True, error_model="numpy")
def _window_stats(mu, sd, lo, hi, glx, glw, buf):
    r""":func:`censored_stats` for two finite limits lo < hi: the routes of :mod:`tobitkf.censored` with the
    window mirrored to the upper tail (:math:`[a_2, b_2] = [-b, -a]` when :math:`a < -b`): the far limit
    negligible (:math:`b_2^2 - a_2^2 > 100`) beyond :data:`A_TAIL`: the one-sided statistics at
    :math:`a_2`; a window narrower than 1σ, or two-sided beyond 4σ: :func:`_quadrature_moments`;
    otherwise the direct formulas of :func:`window_direct`."""
    other, a2, b2, flip, one_sided, p_lo, p_hi, gam, lam, zvar = window_direct(mu, sd, lo, hi)
    if other:
        if one_sided and a2 > A_TAIL:
            _p, gam, zm, _m, zvar, _c, _w = _one_sided_at(0.0, 1.0, a2)
        else:
            zm, zvar, gam = _quadrature_moments(a2, b2, glx, glw, buf)
        lam = -zm if flip else zm
    return _assemble(mu, sd, lo, hi, p_lo, p_hi, gam, lam, zvar)


@njit(cache=True, error_model="numpy", inline="always")
def censored_stats(mu, sd, lo, hi, glx, glw, buf):
    r"""The censored-normal statistics of one run, as :func:`tobitkf.censored.censored_moments` (its
    high-precision reference, tested against it): ``(p_lower, p_upper, p_uncensored, inverse_mills,
    truncated_mean, truncated_var, censored_mean, censored_var)`` of :math:`y^* \sim N(\mu, sd^2)` clipped
    to [lo, hi] (either infinite, lo < hi). One finite limit: :func:`_one_sided_at` (an upper limit as the
    lower limit :math:`-h` of :math:`-y^*`); two: :func:`_window_stats` (quadrature nodes ``glx``, weights
    ``glw``, scratch ``buf`` (2, len(glx))); none: the latent's own moments. Inlined (numba
    ``inline="always"``), so that the one-sided route is inlined into the caller's loop over the runs."""
    if lo != -_INF and hi == _INF:
        plo, g, lam, tmean, tvar, cm, cv = _one_sided_at(mu, sd, lo)
        return plo, 0.0, g, lam, tmean, tvar, cm, cv
    if lo == -_INF and hi != _INF:
        phi, g, lam, tmean, tvar, cm, cv = _one_sided_at(-mu, sd, -hi)
        return 0.0, phi, g, -lam, -tmean, tvar, -cm, cv
    if lo == -_INF:
        v = sd * sd
        return 0.0, 0.0, 1.0, 0.0, mu, v, mu, v
    return _window_stats(mu, sd, lo, hi, glx, glw, buf)


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


@njit(cache=True, error_model="numpy", inline="always")
def one_sided_block(ym, sd, lim, upper, nb, noise_code, gam, noise, cmean):
    r"""Censored-normal statistics of the runs ``b < nb`` of a block for one channel with one finite limit,
    as the TKF update needs them.

    ``ym`` (B,) the means :math:`\mu_b` of the latent reading, ``sd`` its standard deviation (> 0, shared),
    ``lim`` the finite limit: a lower limit, or an upper one when ``upper`` (the other side infinite).
    Writes :math:`\gamma_b = P(\text{uncensored})` into ``gam``, the censored mean :math:`E(y)` (Miller
    (3.8)) into ``cmean`` and the noise term of ``noise_code`` (:data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`:
    0 the truncated variance, 1 the censored variance, 2 :math:`\gamma(\mathrm{Var}_t + (E_t - \mu)^2)`)
    into ``noise``; the numbers of :func:`censored_stats`.
    An upper limit is the lower limit :math:`-\ell` of :math:`-y`: the same statistics with the means'
    signs flipped."""
    sg = -1.0 if upper else 1.0
    lo = sg * lim
    for b in range(nb):
        mu = sg * ym[b]
        _plo, g, _lam, tmean, tvar, cm, cvar = _one_sided_at(mu, sd, lo)
        gam[b] = g
        noise[b] = noise_term(noise_code, mu, g, tmean, tvar, cvar)
        cmean[b] = sg * cm


@njit(cache=True, error_model="numpy", inline="always")
def noise_term(noise_code, mu, g, tmean, tvar, cvar):
    r"""The TKF's noise term :math:`R_{uu}` of ``noise_code`` (:data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`)
    from a channel's statistics: 0 the truncated variance, 1 the censored variance, 2
    :math:`\gamma(\mathrm{Var}_t + (E_t - \mu)^2)` (the mean :math:`\mu` of the latent reading)."""
    if noise_code == 0:
        return tvar
    if noise_code == 1:
        return cvar
    d = tmean - mu
    return g * (tvar + d * d)


@njit(cache=True, error_model="numpy", inline="always")
def lower_stats_block(ym, sd, lo, nb, gam, lam, tvar, cmean, cvar):
    r"""The statistics of the runs ``b < nb`` of a block for a lower limit ``lo`` alone (the form the fading
    and protocol kernels read): :math:`\gamma` into ``gam``, the inverse Mills ratio into ``lam``, the
    truncated variance into ``tvar``, the censored mean and variance into ``cmean``, ``cvar`` (each (B,));
    the numbers of :func:`censored_stats`."""
    for b in range(nb):
        _plo, g, lm, _tmean, tv, cm, cv = _one_sided_at(ym[b], sd, lo)
        gam[b] = g
        lam[b] = lm
        tvar[b] = tv
        cmean[b] = cm
        cvar[b] = cv


@njit(cache=True, error_model="numpy")
def one_sided_array(ym, sd, lim, upper, noise_code):
    """:func:`one_sided_block` over a 1-d array of means (a testing aid); returns ``(gam, noise, cmean)``."""
    n = ym.shape[0]
    gam, noise, cmean = np.empty(n), np.empty(n), np.empty(n)
    one_sided_block(ym, sd, lim, upper, n, noise_code, gam, noise, cmean)
    return gam, noise, cmean


@njit(cache=True, error_model="numpy")
def lower_stats_array(ym, sd, lo):
    """:func:`lower_stats_block` over a 1-d array of means (a testing aid); returns ``(gam, lam, tvar, cmean,
    cvar)``."""
    n = ym.shape[0]
    out = np.empty((5, n))
    lower_stats_block(ym, sd, lo, n, out[0], out[1], out[2], out[3], out[4])
    return out
