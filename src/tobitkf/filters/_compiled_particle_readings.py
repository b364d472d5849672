r"""The readings of the compiled particle filter beyond censoring: their likelihood and what each model supplies.

The compiled loop (:func:`tobitkf.filters._compiled_particle.pf_block`) runs the bootstrap proposal for every
model whose reading of channel l, given a particle :math:`\xi`, is a normal latent reading seen through an
interval, possibly as a mixture over discrete modes j (and the locally optimal proposal of those with one term
and one mode: the region channels; there an interval reading draws its latent reading from the window):

.. math::

    c_l(\xi) = \sum_{s} \bar g_{ls}\,(h_{ls}\xi), \qquad
    s_l^2(\xi) = \sum_{s} \tilde g_{ls}\,(h_{ls}\xi)^2 + r_l, \qquad
    \mu_{lj}(\xi) = g_{lj}\,\mathrm{clip}(c_l(\xi), -u_{lj}, u_{lj}),

    \log p(y_l \mid \xi) = \log\sum_j \pi_{lj} \begin{cases}
        \phi\big((y - \mu_{lj})/s_l\big)/s_l & \text{an exact reading } y \\
        \Phi\big((b - \mu_{lj})/s_l\big) - \Phi\big((a - \mu_{lj})/s_l\big) & \text{a reading that says } y^* \in [a, b]
    \end{cases}

(term s reads the state s steps back, present from step s on; a NaN reading contributes nothing). The models:

* censoring (:class:`~tobitkf.Censoring`, the loop's own path; here only as a special case): one term
  :math:`h = C_l`, one mode; a reading at a limit is the interval :math:`(-\infty, l]` or :math:`[h, \infty)`;
* random saturation (:class:`~tobitkf.RandomSaturation`, with or without a Censoring): three modes,
  saturated (:math:`g = 1`, :math:`u` the level, :math:`\pi = \mu_i`), linear (:math:`u = \infty`,
  :math:`(1-\mu_i)\nu_i`) and noise only (:math:`g = 0`, :math:`(1-\mu_i)(1-\nu_i)`);
* Rice fading of order L with Gaussian coefficients (:class:`~tobitkf.RiceFading`, with or without a
  Censoring): L + 1 terms :math:`h_{ls} = C_l` on block s of the window, :math:`\bar g = \bar\vartheta(s)`,
  :math:`\tilde g = \tilde\vartheta(s)`, one mode;
* a channel of the measurement contract whose likelihood is its ``region``'s (:class:`~tobitkf.Quantizer`,
  a dead band, a channel of your own): one term, one mode, the reading's region :math:`[a, b]` (exact where
  :math:`a = b`).

These are the equations of the numpy path (``_Model.log_likelihood``,
:func:`tobitkf.channels.base.interval_log_likelihood`), in the same order per particle: the interval mass
as :func:`tobitkf.channels.base.log_interval_mass` forms it (:math:`\log\Phi(b') + \mathrm{log1p}(-e^{\log\Phi(a')
- \log\Phi(b')})` on the side of the lower tail), the modes by log-sum-exp.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from ._compiled_censored import _exp_neg, _log_pos, _one_sided_at
from ._readings import _INTERIOR, _LOWER, _UPPER
from ._readings import classify_readings as _classify_readings

__all__ = ["log_ndtr", "log_interval", "reading_log_weights", "compiled_readings"]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)
_SQRT_PI = math.sqrt(math.pi)
_INF = math.inf


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


@njit(cache=True, error_model="numpy", inline="always")
def log_interval(a, b):
    r""":math:`\log(\Phi(b) - \Phi(a))` for :math:`a \le b` (infinite ends allowed), as
    :func:`tobitkf.channels.base.log_interval_mass`: mirrored to :math:`[-b, -a]` when :math:`a + b > 0`, then
    :math:`\log\Phi(b) + \mathrm{log1p}(-e^{\log\Phi(a) - \log\Phi(b)})` (:math:`\log\Phi(b)` where
    :math:`\Phi(a) = 0`)."""
    if a + b > 0.0:
        a, b = -b, -a
    la = log_ndtr(a)
    lb = log_ndtr(b)
    if la == -_INF:
        return lb
    return lb + math.log1p(-math.exp(la - lb))


@njit(cache=True, error_model="numpy", inline="always")
def _tail_mass(x):
    r""":math:`\Phi(-|x|)` by the package's compiled censored statistics (``_compiled_censored._one_sided_at``:
    polynomial fits of erfcx and an exp without libm; relative error about 1e-14 within 8 standard deviations,
    2e-13 at 35), which a loop over particles vectorises: the censored weights take their masses from one such
    pass, where a library ``erfc`` is a call per particle."""
    return _one_sided_at(0.0, 1.0, abs(x))[1]


@njit(cache=True, error_model="numpy")
def tail_masses(x, out, count):
    r"""``out[i] =`` :math:`\Phi(-|x_i|)` for the first ``count`` entries, in one vectorised pass (one compiled
    copy of :func:`_tail_mass` for every pass of the particle filter's loop)."""
    for i in range(count):
        out[i] = _tail_mass(x[i])


@njit(cache=True, error_model="numpy")
def _log_weight(c, sd, ls, modes, lo, hi, TJ):
    r"""The log-likelihood of one particle (latent mean ``c``, standard deviation ``sd``, ``ls`` = log sd) in
    logarithms throughout: the modes' log-densities or :func:`log_interval` and their log-sum-exp (the numpy
    path's order)."""
    top = -_INF
    used = 0
    for j in range(modes.shape[0]):
        lp = modes[j, 2]
        if lp == -_INF:
            continue
        u = modes[j, 1]
        mu = modes[j, 0] * min(max(c, -u), u)
        if lo == hi:
            z = (lo - mu) / sd
            t = -0.5 * z * z - ls - _LOG_SQRT_2PI
        else:
            a = (lo - mu) / sd if lo > -_INF else -_INF
            b = (hi - mu) / sd if hi < _INF else _INF
            t = log_interval(a, b)
        t += lp
        TJ[used] = t
        used += 1
        top = max(top, t)
    if used == 1:
        return TJ[0]
    if not (top > -_INF and top < _INF):
        top = 0.0
    s = 0.0
    for j in range(used):
        s += math.exp(TJ[j] - top)
    return math.log(s) + top


@njit(cache=True, error_model="numpy")
def reading_log_weights(Xb, H, gains, modes, terms, lo, hi, r, INC, S, S2, BAD, TJ):
    r"""Add the log-likelihood of one reading of one channel to each particle's ``INC`` (Np,) (the module's
    equations).

    In vectorised passes over the particles: the latent mean and standard deviation, then per mode its
    probability times the density :math:`\phi(z)/s` (an exp without libm) or the interval's mass
    :math:`\Phi(\beta) - \Phi(\alpha)` (the package's compiled normal tails, on the side of the lower tail),
    summed over the modes, and one log without libm; one exact reading of one mode needs no exp or log (its
    log-density directly). A particle beyond 35 standard deviations of a limit or of the reading, whose interval
    mass loses more than two bits to cancellation, or whose likelihood is under 1e-290, is weighted instead in
    logarithms throughout (:func:`_log_weight`, the numpy path's formulas). The same numbers as the numpy path
    to about 1e-13 (relative, in the likelihood).

    Parameters
    ----------
    Xb : (n_x, Np)
        The run's particles, one row per state component.
    H : (K, n_x) ; gains : (K, 2) ; terms : int
        The rows :math:`h_s`, the gains :math:`(\bar g_s, \tilde g_s)` and how many terms are present (<= K).
    modes : (J, 3)
        Per mode :math:`(g_j, u_j, \log\pi_j)` (a mode of probability 0 is skipped).
    lo, hi : float
        The reading's interval (equal: an exact reading).
    r : float
        The noise variance :math:`R_{ll}`.
    S : (4, Np) ; S2 : (2, 2 Np) ; BAD : (Np,) bool ; TJ : (J,)
        Scratch: the latent means, variances, inverse standard deviations and likelihoods; an interval's ends
        and their tail masses; the particles weighted in logarithms; one particle's modes.
    """
    n, Np = Xb.shape
    Z, V, IS, ACC = S[0], S[1], S[2], S[3]
    TA, TM = S2[0], S2[1]
    varying = False
    for s in range(terms):
        varying = varying or gains[s, 1] != 0.0
    for p in range(Np):
        Z[p] = 0.0
        V[p] = 0.0
    for s in range(terms):  # the latent mean (and variance)
        gm = gains[s, 0]
        gv = gains[s, 1]
        for p in range(Np):
            c = 0.0
            for j in range(n):
                c += Xb[j, p] * H[s, j]
            Z[p] += gm * c
            V[p] += c * c * gv
    sr = math.sqrt(r)
    ls0 = math.log(sr)
    r2 = sr * sr
    for p in range(Np):
        IS[p] = 1.0 / math.sqrt(V[p] + r2) if varying else 1.0 / sr
    exact = lo == hi
    J = modes.shape[0]
    active = 0
    g, u, lp = 0.0, 0.0, 0.0
    for j in range(J):
        if modes[j, 2] > -_INF:
            active += 1
            g, u, lp = modes[j, 0], modes[j, 1], modes[j, 2]
    single = exact and active == 1
    if single:  # the log-density directly (its -log s by the log pass below where s varies)
        for p in range(Np):
            z = (lo - g * min(max(Z[p], -u), u)) * IS[p]
            INC[p] += (-0.5 * z * z - (0.0 if varying else ls0) - _LOG_SQRT_2PI) + lp
            ACC[p] = IS[p]
            BAD[p] = False
        if not varying:
            return
        J = 0
    else:
        for p in range(Np):
            ACC[p] = 0.0
            BAD[p] = False
    whole = lo == -_INF and hi == _INF
    for j in range(J):  # the modes' likelihoods, summed (vectorised passes)
        g, u, lp = modes[j, 0], modes[j, 1], modes[j, 2]
        if lp == -_INF:
            continue
        w = math.exp(lp)
        if exact:
            w *= 1.0 / math.sqrt(2.0 * math.pi)
            for p in range(Np):
                z = (lo - g * min(max(Z[p], -u), u)) * IS[p]
                e = -0.5 * z * z
                ACC[p] += w * IS[p] * _exp_neg(e)
                BAD[p] = BAD[p] or e < -600.0
        elif whole:
            for p in range(Np):
                ACC[p] += w
        else:  # an interval, mirrored to the side of the lower tail: its ends' tail masses in one pass of 2 Np
            for p in range(Np):
                mu = g * min(max(Z[p], -u), u)
                a = (lo - mu) * IS[p] if lo > -_INF else -_INF
                b = (hi - mu) * IS[p] if hi < _INF else _INF
                flip = a + b > 0.0
                TA[p] = -b if flip else a
                TA[Np + p] = -a if flip else b
            tail_masses(TA, TM, 2 * Np)
            for p in range(Np):
                b2 = TA[Np + p]
                pb = 1.0 - TM[Np + p] if b2 > 0.0 else TM[Np + p]
                mass = pb - (TM[p] if TA[p] > -_INF else 0.0)
                ACC[p] += w * mass
                BAD[p] = BAD[p] or b2 < -35.0 or mass * 4.0 < pb
    for p in range(Np):  # one log (vectorised)
        v = ACC[p]
        bad = BAD[p] or not v > 1e-290
        BAD[p] = bad
        INC[p] += _log_pos(v if not bad else 1.0)
    if single:
        return
    for p in range(Np):  # the particles far in the tails: in logarithms throughout
        if BAD[p]:
            sd = math.sqrt(V[p] + r2) if varying else sr
            INC[p] += _log_weight(Z[p], sd, math.log(sd) if varying else ls0, modes, lo, hi, TJ)


# --------------------------------------------------------------------------- what each model supplies


def _limit_intervals(y2: np.ndarray, LO: np.ndarray, HI: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The intervals (N, T, m) of censored readings: the reading itself (interior), (-inf, lo] or [hi, inf) at a
    limit, NaN where missing (the classes of :func:`tobitkf.filters._readings.classify_readings`)."""
    cls = _classify_readings(y2, LO[None], HI[None])
    lo = np.where(cls == _INTERIOR, y2, np.where(cls == _LOWER, -np.inf, np.where(cls == _UPPER, HI[None], np.nan)))
    hi = np.where(cls == _INTERIOR, y2, np.where(cls == _LOWER, LO[None], np.where(cls == _UPPER, np.inf, np.nan)))
    return np.ascontiguousarray(lo), np.ascontiguousarray(hi)


def compiled_readings(model: Any, system: Any, y2: np.ndarray, k0: int, LO: np.ndarray, HI: np.ndarray) -> dict:
    """The arrays the compiled loop takes for ``model`` (time-invariant ``system``, readings ``y2`` (N, T, m) from
    step ``k0 + 1``, censoring limits ``LO``, ``HI`` (T, m)): the augmented dynamics ``A``, ``Qd`` (n_x, n_x),
    ``G`` (n_x, n) (noise in the top block), ``nb`` (the top block's size), and for the general readings
    (``general``) ``H`` (m, K, n_x), ``gains`` (m, K, 2), ``modes`` (m, J, 3), the intervals ``ylo``, ``yhi``
    (N, T, m); placeholders for linear readings with censoring."""
    from ._particle_models import _Contract, _Fading, _Saturation

    n, m = system.n, system.m
    A = np.asarray(system.transition(k0), dtype=float)
    Qd = np.asarray(system.process_cov(k0), dtype=float)
    G = np.asarray(model._root(k0), dtype=float)
    C = np.asarray(system.measurement(k0 + 1), dtype=float)
    nx = model.nx
    one = np.ones((m, 1, 2))
    one[..., 1] = 0.0
    plain = np.tile(np.array([1.0, np.inf, 0.0]), (m, 1, 1))
    out = {"nb": n, "general": True, "H": C[:, None, :], "gains": one, "modes": plain}
    if isinstance(model, _Saturation):
        lp = model.logp
        lev = np.asarray(model.channel.level, dtype=float)
        out["modes"] = np.stack(
            [np.stack([np.ones(m), lev, lp[0]], -1), np.stack([np.ones(m), np.full(m, np.inf), lp[1]], -1),
             np.stack([np.zeros(m), np.full(m, np.inf), lp[2]], -1)], axis=1)  # fmt: skip
    elif isinstance(model, _Fading):
        L = model.L
        Aa, Qa, Ga = np.zeros((nx, nx)), np.zeros((nx, nx)), np.zeros((nx, n))
        Aa[:n, :n], Qa[:n, :n], Ga[:n] = A, Qd, G
        Aa[n:, : nx - n] = np.eye(nx - n)
        A, Qd, G = Aa, Qa, Ga
        H = np.zeros((m, L + 1, nx))
        for s in range(L + 1):
            H[:, s, s * n : (s + 1) * n] = C
        out["H"] = H
        out["gains"] = np.stack([model.mean_g.T, model.var_g.T], axis=-1)
    if isinstance(model, _Contract):
        N, T, _ = y2.shape
        ylo, yhi = np.full(y2.shape, np.nan), np.full(y2.shape, np.nan)
        for k in range(T):
            for l in range(m):
                rows = ~np.isnan(y2[:, k, l])
                if rows.any():
                    ylo[rows, k, l], yhi[rows, k, l] = model.channel.region(y2[rows, k, l], k0 + 1 + k, l)
    elif isinstance(model, (_Saturation, _Fading)):
        ylo, yhi = _limit_intervals(y2, LO, HI)
    else:  # linear readings with censoring: the loop's own path
        out.update(general=False, H=np.zeros((1, 1, 1)), gains=np.zeros((1, 1, 2)), modes=np.zeros((1, 1, 3)))
        ylo = yhi = np.zeros((1, 1, 1))
    out.update(A=A, Qd=Qd, G=G, ylo=ylo, yhi=yhi)
    return {key: np.ascontiguousarray(v, dtype=float) if isinstance(v, np.ndarray) else v for key, v in out.items()}
