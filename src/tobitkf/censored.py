r"""Moments of a censored normal variable, numerically safe far into the tails.

For a latent :math:`y^* \sim N(\mu, \sigma^2)` observed through the clip
:math:`y = \min(\max(y^*, l), h)` (``lower`` = l, ``upper`` = h, either may be
infinite) let :math:`a = (l-\mu)/\sigma`, :math:`b = (h-\mu)/\sigma`. Then
(Miller 2015, (3.7)–(3.12) for left censoring, (3.54) for right censoring,
and the general two-sided form of Miller §6.6; docs/sources MA-20):

.. math::

    p_{lower} &= \Phi(a), \qquad p_{upper} = \Phi(-b), \qquad
    \gamma = p_{uncensored} = \Phi(b) - \Phi(a) \\
    \lambda &= \frac{\phi(a) - \phi(b)}{\gamma} \quad\text{(inverse Mills ratio)} \\
    E[y^* \mid l<y^*<h] &= \mu + \sigma\lambda \\
    \operatorname{Var}[y^* \mid l<y^*<h] &= \sigma^2\Big[1 + \frac{a\phi(a) - b\phi(b)}{\gamma} - \lambda^2\Big] \\
    E[y] &= p_{lower}\, l + \gamma\,(\mu + \sigma\lambda) + p_{upper}\, h

Sign convention: with only a lower limit, :math:`\lambda = \phi(a)/(1-\Phi(a))`,
the dissertation's λ of (3.7). With only an upper limit, :math:`\lambda = -\phi(b)/\Phi(b)`,
i.e. **minus** the right-censoring "IMR" of (3.54) and (5.4); the truncated mean is
:math:`\mu + \sigma\lambda` in both cases.

Numerics. Direct formulas suffer cancellation or 0/0 when the uncensored window
lies far in a tail (|a| or |b| beyond a few units) or is narrow. The window is first
mirrored to the upper tail (:math:`[a', b'] = [-b, -a]` when :math:`a < -b`, λ changing
sign). Three routes:

* **one-sided tail** (:math:`b' = \infty`, or the far limit negligible:
  :math:`b'^2 - a'^2 > 100`, i.e. :math:`\phi(b')/\phi(a') < e^{-50}`) with :math:`a' > 4`:
  Laplace's continued fraction for the Mills ratio :math:`R(x) = Q(x)/\phi(x)
  = 1/(x + 1/(x + 2/(x + 3/(x + \dots))))`, evaluated backwards over the levels
  ``int(140/x) + 6`` down to 2 (relative error of the tail :math:`s` and of the variance
  below 4e-16 for x >= 4, checked against a 40-digit evaluation on a dense grid).
  With :math:`s = 2/(x + 3/(x + \dots))` and :math:`t = 1/(x + s)`: :math:`\lambda = x + t`
  and :math:`\mathrm{Var}[Z \mid Z > x] = 1 - \lambda(\lambda - x) = t(s - t)` (no
  cancellation), :math:`\gamma = \phi(x)/\lambda` as one ``exp`` (underflows to 0 only
  when the true value does). Accurate out to any distance (1000σ and beyond).
* **narrow or two-sided in a tail** (:math:`b - a < 1`, or :math:`a' > 4` with the far limit
  not negligible): shifted coordinates :math:`u = z - a'`, where the density is proportional to
  :math:`e^{-a' u - u^2/2}` on :math:`[0, \min(w, u_{max})]`, by 64-node Gauss–Legendre
  quadrature with a two-pass variance, and the uncensored probability as
  :math:`\phi(a')` times the quadrature sum;
* otherwise the direct formulas above (:math:`a' \le 4`; their cancellation in the variance
  costs up to a few hundred ulp near the switch).

:mod:`tobitkf.filters._compiled_censored` is the compiled implementation (the same routes, tested against
these numbers).
Tail probabilities use ``scipy.special.ndtr`` on the side where they are
small, so limits 40 (or 1000) standard deviations away give finite, accurate numbers
(checked against 60-digit values in ``shared/vectors``).
"""

from __future__ import annotations

import itertools
import math
from typing import Any, NamedTuple

import numpy as np
from scipy.special import log_ndtr, ndtr

__all__ = ["CensoredMoments", "censored_fisher_information", "censored_moments", "standardized_limits"]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_TAIL = 4.0  # beyond this many sigma the window is treated by quadrature
_NARROW = 1.0  # windows narrower than this (in sigma) too
_GL_X, _GL_W = np.polynomial.legendre.leggauss(64)
_CF_FROM = 4.0  # one-sided windows beyond this many sigma: the continued fraction
_FAR = 100.0  # b'^2 - a'^2 above this: the far limit is negligible (phi ratio < e^-50)
_CF_TERMS = 140.0  # int(_CF_TERMS / x) + 6 terms of the continued fraction at x
_SMALL = 4  # at most this many entries: the route of each is taken on Python floats (_small_moments)


def _cf_terms(x: np.ndarray) -> np.ndarray:
    """Number of continued-fraction terms at ``x`` (>= _CF_FROM): relative error < 4e-16."""
    return (_CF_TERMS / x).astype(np.int64) + 6


def _one_sided_tail(x: np.ndarray):
    r"""Moments of Z ~ N(0,1) given Z > x, for x > _CF_FROM, by Laplace's continued fraction.

    Returns ``(log_gamma, zmean, zvar)``: :math:`\log Q(x)`, :math:`E[Z \mid Z > x] = \lambda`,
    :math:`\mathrm{Var}[Z \mid Z > x]`. The fraction is evaluated backwards with exactly the
    arithmetic of the compiled kernel, so both give the same numbers.
    """
    nterms = _cf_terms(x)
    s = np.zeros_like(x)
    for k in range(int(nterms.max(initial=2)), 1, -1):
        s = np.where(nterms >= k, k / (x + s), s)
    t = 1.0 / (x + s)
    lam = x + t
    zvar = t * (s - t)
    with np.errstate(over="ignore"):
        log_gamma = -0.5 * x * x - _LOG_SQRT_2PI - np.log(lam)
    return log_gamma, lam, zvar


class CensoredMoments(NamedTuple):
    """Statistics of ``y = clip(y*, lower, upper)``, ``y* ~ N(mean, std**2)``; all broadcast shapes."""

    p_lower: np.ndarray
    """P(y* <= lower): probability of reading the lower limit."""
    p_upper: np.ndarray
    """P(y* >= upper): probability of reading the upper limit."""
    p_uncensored: np.ndarray
    """P(lower < y* < upper); the sources' γ (or E(p_k))."""
    inverse_mills: np.ndarray
    """(φ(a) − φ(b)) / p_uncensored; truncated mean = mean + std * inverse_mills. One sign for both sides:
    positive with only a lower limit (+0.798 at the mean), **negative** with only an upper limit
    (−0.798 at the mean), where the dissertation's right-censoring λ̂ of (3.54) is its magnitude."""
    truncated_mean: np.ndarray
    """E[y* | uncensored]."""
    truncated_var: np.ndarray
    """Var[y* | uncensored]; the dissertation's noise term (3.11)."""
    censored_mean: np.ndarray
    """E[y] (Miller (3.8) in general two-sided form)."""
    censored_var: np.ndarray
    """Var[y] (law of total variance)."""


def _norm_logpdf(z: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # |z| > 1e154: z*z overflows to inf, log-density -inf is right
        return -0.5 * z * z - _LOG_SQRT_2PI


def standardized_limits(mean, std, lower, upper):
    """Return ``a = (lower - mean)/std`` and ``b = (upper - mean)/std`` with infinities kept."""
    with np.errstate(invalid="ignore"):
        a = np.where(np.isneginf(lower), -np.inf, (lower - mean) / std)
        b = np.where(np.isposinf(upper), np.inf, (upper - mean) / std)
    return a, b


def _tail_moments(a: np.ndarray, b: np.ndarray):
    """Moments of Z ~ N(0,1) restricted to [a, b] (a > -6, window not in the lower tail).

    Returns (log_gamma, zmean, zvar) with zmean = E[Z | window], zvar = Var[Z | window].
    """
    w = b - a
    # a u + u^2/2 = 40 -> density below e^-40 relative; root u = -a + sqrt(a^2 + 80) written
    # without cancellation (and without overflowing a^2) so that a >~ 1e8 does not give umax = 0
    umax = 80.0 / (a + np.hypot(a, np.sqrt(80.0)))
    top = np.minimum(w, umax)
    half = 0.5 * top[..., None]
    u = half * (_GL_X + 1.0)  # (..., 64) nodes on [0, top]
    dens = np.exp(-a[..., None] * u - 0.5 * u * u)  # phi(a+u)/phi(a)
    wt = _GL_W * half * dens
    i0 = wt.sum(-1)
    umean = (wt * u).sum(-1) / i0
    uvar = (wt * (u - umean[..., None]) ** 2).sum(-1) / i0
    log_gamma = _norm_logpdf(a) + np.log(i0)
    return log_gamma, a + umean, uvar


def censored_moments(mean, std, lower, upper) -> CensoredMoments:
    r"""Moments of a censored (clipped) normal variable, stable in the tails.

    Parameters
    ----------
    mean : array_like
        Mean :math:`\mu` of the latent normal.
    std : array_like
        Standard deviation :math:`\sigma > 0` (not the variance; Miller L809 calls it "the variance").
    lower, upper : array_like
        Censoring limits, ``-inf`` / ``+inf`` for none; ``lower < upper`` is required.
        All four arguments broadcast together.

    Returns
    -------
    CensoredMoments
        Named tuple of arrays of the broadcast shape; see the module docstring for
        the equations.

    Raises
    ------
    ValidationError
        If ``mean`` is NaN or infinite, ``std`` is not a finite number > 0, a limit is NaN, some
        ``lower >= upper``, or an argument holds text or booleans.
    ShapeError
        If the arguments do not broadcast.

    Notes
    -----
    Probabilities that underflow double precision are returned as 0.0, and
    the truncated moments stay finite even then (they follow from the shape of
    the density near the limit, not from the underflowed probability).

    Examples
    --------
    Truth -0.1, σ = 0.1, left censoring at 0 (Miller Example 1, §3.3.6.2):

    >>> m = censored_moments(-0.1, 0.1, 0.0, np.inf)
    >>> round(float(m.p_uncensored), 5), round(float(m.censored_mean), 5)
    (0.15866, 0.00833)
    """
    from ._validation import ShapeError, ValidationError, as_float_array

    args = (
        as_float_array(mean, "mean"),
        as_float_array(std, "std", allow_nan=True, allow_inf=True),
        as_float_array(lower, "lower", allow_inf=True),
        as_float_array(upper, "upper", allow_inf=True),
    )
    try:
        mu, sd, lo, hi = np.broadcast_arrays(*args)
    except ValueError:
        raise ShapeError(
            "mean/std/lower/upper: shapes " + ", ".join(str(a.shape) for a in args) + " do not broadcast"
        ) from None
    if np.any(~(sd > 0)):
        raise ValidationError("std: expected standard deviations > 0")
    if np.isinf(sd).any():
        raise ValidationError("std: expected finite standard deviations, found inf")
    if np.any(~(lo < hi)):
        raise ValidationError("lower/upper: expected lower < upper for every channel")
    return unchecked_moments(mu, sd, lo, hi)


def unchecked_moments(mean, std, lower, upper) -> CensoredMoments:
    """:func:`censored_moments` without its input checks, for the filters' inner loop.

    The filters have checked their limits and noise once at the boundary; what reaches them
    per step is a predicted mean and standard deviation, which are NaN exactly when a run's
    covariance has overflowed. The loop then poisons that run and warns once; here NaN
    simply propagates (instead of raising mid-loop and losing the healthy runs).
    """
    args = [np.asarray(v, dtype=float) for v in (mean, std, lower, upper)]
    shape = max((v.shape for v in args), key=len)
    size = math.prod(shape)
    if size <= _SMALL and all(shape[len(shape) - v.ndim :] == v.shape for v in args):
        # every argument's shape a trailing part of the largest: broadcasting repeats its entries
        flat = [v.ravel().tolist() * (size // max(v.size, 1)) for v in args]
        rows = [_small_moments(*vals) for vals in zip(*flat)]
        if all(r is not None for r in rows):
            cols = np.fromiter(itertools.chain.from_iterable(zip(*rows)), float, 8 * size)
            return CensoredMoments(*cols.reshape((8,) + shape))
    mu, sd, lo, hi = np.broadcast_arrays(*args)
    mu, sd, lo, hi = (np.ravel(v) for v in (mu, sd, lo, hi))
    a, b = standardized_limits(mu, sd, lo, hi)

    p_lo = ndtr(a)
    p_hi = ndtr(-b)
    # gamma = Phi(b) - Phi(a), subtracting the small tail probabilities
    gamma = np.where(a > 0, ndtr(-a) - p_hi, np.where(b < 0, ndtr(b) - p_lo, 1.0 - p_lo - p_hi))
    phi_a = np.exp(_norm_logpdf(np.where(np.isfinite(a), a, 0.0))) * np.isfinite(a)
    phi_b = np.exp(_norm_logpdf(np.where(np.isfinite(b), b, 0.0))) * np.isfinite(b)
    aphi_a = np.where(np.isfinite(a), a, 0.0) * phi_a
    bphi_b = np.where(np.isfinite(b), b, 0.0) * phi_b

    flip = a < -b  # mirror windows in the lower tail to the upper tail
    a2 = np.where(flip, -b, a)
    b2 = np.where(flip, -a, b)
    with np.errstate(over="ignore", invalid="ignore"):
        one_sided = np.isposinf(b2) | ((b2 - a2) * (b2 + a2) > _FAR)
    tail = one_sided & (a2 > _CF_FROM)
    hard = ~tail & ((~one_sided & (a2 > _TAIL)) | ((b - a) < _NARROW))
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (phi_a - phi_b) / gamma
        zvar = 1.0 + (aphi_a - bphi_b) / gamma - lam * lam
    if np.any(tail):
        log_g, zm, zv = _one_sided_tail(a2[tail])
        lam[tail] = np.where(flip[tail], -zm, zm)
        zvar[tail] = zv
        gamma[tail] = np.exp(log_g)
    if np.any(hard):
        log_g, zm, zv = _tail_moments(a2[hard], b2[hard])
        lam[hard] = np.where(flip[hard], -zm, zm)
        zvar[hard] = zv
        gamma[hard] = np.exp(log_g)
    gamma = np.clip(gamma, 0.0, 1.0)
    zvar = np.maximum(zvar, 0.0)

    tmean = mu + sd * lam
    tvar = sd * sd * zvar
    lo_term = np.where(p_lo > 0, p_lo * np.where(np.isfinite(lo), lo, 0.0), 0.0)
    hi_term = np.where(p_hi > 0, p_hi * np.where(np.isfinite(hi), hi, 0.0), 0.0)
    cmean = lo_term + gamma * tmean + hi_term
    with np.errstate(invalid="ignore"):
        d_lo = np.where(p_lo > 0, np.where(np.isfinite(lo), lo, 0.0) - cmean, 0.0)
        d_hi = np.where(p_hi > 0, np.where(np.isfinite(hi), hi, 0.0) - cmean, 0.0)
    cvar = gamma * (tvar + (tmean - cmean) ** 2) + p_lo * d_lo**2 + p_hi * d_hi**2
    return CensoredMoments(*(np.reshape(v, shape) for v in (p_lo, p_hi, gamma, lam, tmean, tvar, cmean, cvar)))


def _small_moments(mu: float, sd: float, lo: float, hi: float) -> tuple[float, ...] | None:
    """:func:`unchecked_moments` of one entry on Python floats, or None when it needs the array code.

    The same routes with the same arithmetic as the array code (each entry takes only its own route
    instead of every route being evaluated and masked), for the online step of one run, where the
    array code's fixed cost of some sixty tiny numpy operations is most of the step. Entries with a NaN
    or infinite mean, a standard deviation that is not a finite number > 0, a NaN limit or
    ``lower >= upper`` return None (the array code handles them, propagating NaN). The quadrature route
    (narrow or two-sided windows in a tail) calls the array helper on the one entry. Transcendental
    functions come from :mod:`math` instead of numpy, so results can differ from the array code by an
    ulp or so (tested to 1e-13 relative).
    """
    if not (math.isfinite(mu) and math.isfinite(sd) and sd > 0.0 and lo < hi):
        return None
    a = -math.inf if lo == -math.inf else (lo - mu) / sd
    b = math.inf if hi == math.inf else (hi - mu) / sd
    p_lo = float(ndtr(a))
    p_hi = float(ndtr(-b))
    if a > 0:
        gamma = float(ndtr(-a)) - p_hi
    elif b < 0:
        gamma = float(ndtr(b)) - p_lo
    else:
        gamma = 1.0 - p_lo - p_hi
    fin_a, fin_b = math.isfinite(a), math.isfinite(b)
    phi_a = math.exp(-0.5 * a * a - _LOG_SQRT_2PI) if fin_a else 0.0
    phi_b = math.exp(-0.5 * b * b - _LOG_SQRT_2PI) if fin_b else 0.0
    flip = a < -b
    a2, b2 = (-b, -a) if flip else (a, b)
    one_sided = b2 == math.inf or (b2 - a2) * (b2 + a2) > _FAR
    if one_sided and a2 > _CF_FROM:  # Laplace's continued fraction, as _one_sided_tail
        s = 0.0
        for k in range(int(_CF_TERMS / a2) + 6, 1, -1):
            s = k / (a2 + s)
        t = 1.0 / (a2 + s)
        zm = a2 + t
        zvar = t * (s - t)
        lam = -zm if flip else zm
        gamma = math.exp(-0.5 * a2 * a2 - _LOG_SQRT_2PI - math.log(zm))
    elif (not one_sided and a2 > _TAIL) or (b - a) < _NARROW:  # quadrature, as _tail_moments
        log_g, zm_a, zv_a = _tail_moments(np.array([a2]), np.array([b2]))
        lam = -float(zm_a[0]) if flip else float(zm_a[0])
        zvar = float(zv_a[0])
        gamma = math.exp(float(log_g[0]))
    else:
        if not gamma > 0.0:
            return None
        lam = (phi_a - phi_b) / gamma
        zvar = 1.0 + ((a * phi_a if fin_a else 0.0) - (b * phi_b if fin_b else 0.0)) / gamma - lam * lam
    gamma = min(max(gamma, 0.0), 1.0)
    zvar = max(zvar, 0.0)
    tmean = mu + sd * lam
    tvar = sd * sd * zvar
    lo_f = lo if math.isfinite(lo) else 0.0
    hi_f = hi if math.isfinite(hi) else 0.0
    lo_term = p_lo * lo_f if p_lo > 0 else 0.0
    hi_term = p_hi * hi_f if p_hi > 0 else 0.0
    cmean = lo_term + gamma * tmean + hi_term
    d_lo = lo_f - cmean if p_lo > 0 else 0.0
    d_hi = hi_f - cmean if p_hi > 0 else 0.0
    dm = tmean - cmean
    cvar = gamma * (tvar + dm * dm) + p_lo * d_lo * d_lo + p_hi * d_hi * d_hi
    return p_lo, p_hi, gamma, lam, tmean, tvar, cmean, cvar


_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def _phi_terms(z: np.ndarray):
    """(phi(z), z phi, z^2 phi, z^3 phi), 0 at +-inf."""
    fin = np.isfinite(z)
    zf = np.where(fin, z, 0.0)
    ph = np.where(fin, np.exp(-0.5 * zf * zf - _LOG_SQRT_2PI), 0.0)
    return ph, zf * ph, zf * zf * ph, zf**3 * ph


def censored_fisher_information(mean: Any, std: Any, lower: Any = -np.inf, upper: Any = np.inf):
    r"""Fisher information of a censored normal reading in :math:`(\mu, \sigma)` (its equations in :mod:`tobitkf.design.pcrlb`).

    Parameters
    ----------
    mean, std, lower, upper : array_like
        Broadcasting together; ``std > 0``, ``lower < upper`` (infinite for no limit).

    Returns
    -------
    I_mm, I_ms, I_ss : ndarray
        :math:`I_{\mu\mu}`, :math:`I_{\mu\sigma}`, :math:`I_{\sigma\sigma}`, of the broadcast shape.

    Raises
    ------
    ValidationError
        ``std <= 0`` or ``lower >= upper``.

    Examples
    --------
    Without censoring the normal's :math:`1/\sigma^2, 0, 2/\sigma^2`; censored at the mean, less:

    >>> [round(float(v), 6) for v in censored_fisher_information(0.0, 2.0)]
    [0.25, 0.0, 0.5]
    >>> round(float(censored_fisher_information(0.0, 1.0, lower=0.0)[0]), 4)
    0.8183
    """
    from ._validation import ValidationError

    mu, sd, lo, hi = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (mean, std, lower, upper)))
    if np.any(~(sd > 0)):
        raise ValidationError("std: expected standard deviations > 0")
    if np.any(~(lo < hi)):
        raise ValidationError("lower/upper: expected lower < upper")
    with np.errstate(invalid="ignore"):
        a = np.where(np.isneginf(lo), -np.inf, (lo - mu) / sd)
        b = np.where(np.isposinf(hi), np.inf, (hi - mu) / sd)
    pa, apa, a2pa, a3pa = _phi_terms(a)
    pb, bpb, b2pb, b3pb = _phi_terms(b)
    fa, fb = np.isfinite(a), np.isfinite(b)
    af, bf = np.where(fa, a, 0.0), np.where(fb, b, 0.0)
    Ta = np.where(fa, np.exp(-af * af - 2 * _LOG_SQRT_2PI - log_ndtr(af)), 0.0)
    Tb = np.where(fb, np.exp(-bf * bf - 2 * _LOG_SQRT_2PI - log_ndtr(-bf)), 0.0)
    delta = np.where(a > 0, ndtr(-a) - ndtr(-b), ndtr(b) - ndtr(a))
    I2 = delta + apa - bpb
    var = sd * sd
    I_mm = (Ta + I2 + Tb) / var
    I_ms = (af * Ta + (a2pa + pa) - (b2pb + pb) + bf * Tb) / var
    I_ss = (af * af * Ta + a3pa - b3pb + I2 + delta + bf * bf * Tb) / var
    return I_mm, I_ms, I_ss
