r"""Assumed-density filter for randomly occurring sensor saturation with missing readings (ROSS).

Not in the source. Channel of Wang, Shen & Liu ((2)–(3), Remark 2; :class:`~tobitkf.RandomSaturation`),
on linear Gaussian dynamics: sensor i reads

.. math::

    y^i_k = \alpha^i_k\,\sigma(C_ix_k) + (1-\alpha^i_k)\beta^i_k\,C_ix_k + v^i_k, \qquad
    \sigma(c) = \mathrm{sign}(c)\min\{u_i, |c|\},

saturated with probability :math:`\mu_i`, linear with :math:`(1-\mu_i)\nu_i`, noise only with
:math:`(1-\mu_i)(1-\nu_i)`; :math:`v^i \sim N(0, R_{ii})`. The source designs a fixed-gain H∞
filter for deterministic disturbances; with Gaussian noises the Bayes filter keeps the mode as a
discrete variable. Given the Gaussian prior, with :math:`c = C_ix \sim N(\mu_c, s^2)`,
:math:`s^2 = C_i\bar PC_i^T`, the exact posterior is a mixture over the three modes with
weights :math:`\propto \pi_jL_j` and, in each, the moments of x follow from those of c
(:math:`x \mid c` is Gaussian: :math:`\hat x = \bar x + K(E[c\mid y] - \mu_c)`,
:math:`P = \bar P - K(s^2 - \mathrm{Var}[c\mid y])K^T`, :math:`K = \bar PC_i^T/s^2`):

* noise only: :math:`L = N(y; 0, r)`, the prior unchanged;
* linear: :math:`L = N(y; \mu_c, s^2 + r)`, the Kalman update;
* saturated: :math:`p(y \mid c) = N(y; \sigma(c), r)` splits c into three pieces,

  .. math::

      c \le -u&: \ M_1 = \Phi\big(\tfrac{-u-\mu_c}{s}\big)N(y; -u, r), \quad c \sim TN(\mu_c, s^2; (-\infty, -u]) \\
      |c| < u&: \ M_2 = N(y; \mu_c, s^2 + r)\,P_{(-u, u)}(m', v'), \quad c \sim TN(m', v'; (-u, u)),
        \ m' = \mu_c + \tfrac{s^2}{s^2+r}(y - \mu_c),\ v' = \tfrac{s^2r}{s^2+r} \\
      c \ge u&: \ M_3 = \Phi\big(\tfrac{\mu_c-u}{s}\big)N(y; u, r), \quad c \sim TN(\mu_c, s^2; [u, \infty))

  with :math:`L = M_1 + M_2 + M_3` and the moments of c those of the three-piece mixture
  (truncated moments from :func:`tobitkf.censored_moments`).

The three are merged by moment matching (:func:`~tobitkf.filters.assumed_density.merge_gaussians`),
sensors in sequence (diagonal R). NaN = missing reading (no update; distinct from the noise-only mode).

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)`, :math:`y_1` at index 0, result row
k-1 holds :math:`\hat x_{k|k}`.
"""

from __future__ import annotations

import numpy as np
from scipy.special import log_ndtr

from .._validation import ValidationError, check_instance
from ..censored import censored_moments
from ..channels.saturation import RandomSaturation
from ..models.linear import LinearSystem
from ._outputs import loop_input
from .assumed_density import ADF_OPTIONS, AssumedDensityFamily, merge_gaussians
from .core import MeasurementPrediction, measurement_update
from .kalman import LinearGaussianFamily
from .registry import family_entry, register

__all__ = ["SaturationAssumedDensityFilter", "saturated_reading_moments"]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_TINY = np.finfo(np.float64).tiny


def _lognorm(y, m, var):
    return -0.5 * (y - m) ** 2 / var - 0.5 * np.log(var) - _LOG_SQRT_2PI


def saturated_reading_moments(y: np.ndarray, mean: np.ndarray, var: np.ndarray, r: float, level: float):
    r"""Log-likelihood and posterior mean and variance of :math:`c \sim N(\mu_c, s^2)` given a saturated reading
    :math:`y = \sigma(c) + v`, :math:`v \sim N(0, r)` (the three pieces of the module docstring), batched.

    Parameters
    ----------
    y, mean, var : (N,) arrays
        Readings, :math:`\mu_c` and :math:`s^2 > 0`.
    r : float
        Noise variance (> 0).
    level : float
        Saturation level u (> 0).

    Returns
    -------
    log_likelihood, post_mean, post_var : (N,) ndarrays
    """
    s = np.sqrt(var)
    u = float(level)
    low = censored_moments(mean, s, -np.inf, -u)  # the piece c <= -u
    high = censored_moments(mean, s, u, np.inf)  # the piece c >= u
    g = var / (var + r)
    mid_m, mid_v = mean + g * (y - mean), var * r / (var + r)
    mid = censored_moments(mid_m, np.sqrt(mid_v), -u, u)  # |c| < u, given the reading
    with np.errstate(divide="ignore"):
        logs = np.stack(
            [
                log_ndtr((-u - mean) / s) + _lognorm(y, -u, r),
                _lognorm(y, mean, var + r) + np.log(mid.p_uncensored),
                log_ndtr((mean - u) / s) + _lognorm(y, u, r),
            ]
        )
    ms = np.stack([low.truncated_mean, mid.truncated_mean, high.truncated_mean])
    vs = np.stack([low.truncated_var, mid.truncated_var, high.truncated_var])
    top = logs.max(0)
    w = np.exp(logs - top)
    tot = w.sum(0)
    w /= tot
    pm = (w * ms).sum(0)
    pv = (w * (vs + (ms - pm) ** 2)).sum(0)
    return np.log(tot) + top, pm, np.maximum(pv, 0.0)


_SATURATED_ONLY = np.array([0.0, -np.inf, -np.inf])  # log prior probabilities: the saturated mode alone


def _saturation_moments(y, missing, mean, var, r, level, logp):
    r"""The compiled loop's block of the saturating sensor
    (:func:`~tobitkf.filters._compiled_moments.saturation_block`) over N runs: ``(w, ll, alpha, beta)``, the
    modes' posterior probabilities (3, N) (their prior ones for a missing reading), the log-likelihood (N,) (0
    for a missing reading) and the merged update's scalars (N,) (:math:`\alpha = (E[c \mid y] - \mu_c)/s^2`,
    :math:`\beta = (s^2 - V)/s^4` with the log prior probabilities ``logp`` (3,) of the saturated, linear
    and noise-only modes)."""
    from ._compiled_moments import INTERIOR, MISSING, SATURATION, family_array, kind

    f = loop_input  # writable, C-contiguous: one argument type (a broadcast view would compile apart)
    cls = np.where(missing, MISSING, INTERIOR).astype(np.int8)
    inf = np.full(y.shape, np.inf)
    par = np.concatenate([[float(level)], logp])
    rb = np.full(y.shape, float(r))
    alpha, beta, ll, _, w = family_array(kind(SATURATION), f(y), cls, f(mean), f(var), rb, -inf, inf, par, 3)
    return w, ll, alpha, beta


class SaturationAssumedDensityFilter(AssumedDensityFamily, LinearGaussianFamily):
    r"""Assumed-density filter for random saturation with missing readings (see the module docstring).

    Parameters
    ----------
    system : LinearSystem
        The model; diagonal R with positive entries.
    channel : RandomSaturation
        Saturation and arrival probabilities and the levels.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        Covariance form of each mode's update (the square root merges factors).
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``"auto"``: :meth:`filter` through the compiled loop (:mod:`tobitkf.filters._compiled_loop`) when numba
        is installed and the options are covered (the standard covariance form, time-invariant system matrices), else the numpy loop; ``"numba"``
        insists on it; ``"numpy"`` never uses it (the same numbers, tested to 1e-12). The numpy loop takes the
        modes' probabilities, the log-likelihood and the saturated mode's moments from the compiled loop's block
        (:func:`~tobitkf.filters._compiled_moments.saturation_block`), on every backend.

    Raises
    ------
    ValidationError
        A non-diagonal or non-positive R, bad option or argument type; (when filtering) a control input
        ``u`` with a system that has a feedthrough D (the saturated reading (2) has none: u enters through Bu).
    ShapeError
        A channel whose sensor count differs from the system's m.

    Notes
    -----
    Extras: ``mode_posterior`` (..., T, m, 3), the posterior probabilities of the saturated, linear
    and noise-only modes of each sensor; ``log_likelihood`` (..., T).

    Examples
    --------
    Never saturated, always arriving: the Kalman filter.

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.3], [-0.4], [1.2]])
    >>> ch = tk.RandomSaturation(mu=[0.0], nu=[1.0])
    >>> a = tk.SaturationAssumedDensityFilter(sys, ch).filter(y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True
    """

    _name = "SaturationAssumedDensityFilter"

    def __init__(
        self,
        system: LinearSystem,
        channel: RandomSaturation,
        *,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        self._configure(system, covariance_update, backend)
        check_instance(channel, RandomSaturation, "channel")
        channel.check(system)
        self.channel = channel
        with np.errstate(divide="ignore"):
            mu, nu = channel.mu, channel.nu
            self._logp = np.stack([np.log(mu), np.log((1 - mu) * nu), np.log((1 - mu) * (1 - nu))], axis=-1)

    _compiled_spec = "saturation_spec"
    _positive_noise = "the saturation filter"
    _variances = AssumedDensityFamily._noise_at  # the name the compiled loop's arrays read

    def _project(self, k, xp, Pp, Sp, y, u=None):
        if u is not None and self.system.D is not None:
            raise ValidationError(
                "u: the saturation filter's reading (2) has no feedthrough D u (it would be ambiguous whether "
                "D u is saturated); give the system no D (a control input enters through Bu only)"
            )
        C, r = self.system.measurement(k), self._noise_at(k)
        N, m = y.shape
        x, P, S = xp, Pp, Sp
        post = np.zeros((N, m, 3))
        ll = np.zeros(N)
        form = self.covariance_update
        for i in range(m):
            c, yi, ri = C[i], y[:, i], float(r[i])
            miss = np.isnan(yi)
            yz = np.where(miss, 0.0, yi)
            mu_c = x @ c
            var = np.broadcast_to(np.einsum("rij,i,j->r", P, c, c), (N,))
            ok = var > _TINY
            # the modes' posterior probabilities and the log-likelihood, then the saturated mode's posterior
            # moments alone (its prior probability 1), from the compiled loop's block (saturation_block)
            w, ll_i = _saturation_moments(yz, miss, mu_c, var, ri, self.channel.level[i], self._logp[i])[:2]
            csat, dsat = _saturation_moments(yz, miss, mu_c, var, ri, self.channel.level[i], _SATURATED_ONLY)[2:]
            pm, pv = mu_c + csat * var, var - dsat * var * var
            sat = MeasurementPrediction(
                expected=mu_c[:, None],
                H0=c[None],
                noise=np.zeros((1, 1)),
                observed=np.where(ok & ~miss, pm, np.nan)[:, None],
                retained=pv[:, None],
            )
            x1, P1, S1, _, _ = measurement_update(x, P, S, yz[:, None], sat, form)
            # linear mode: the Kalman update
            lin = MeasurementPrediction(
                expected=mu_c[:, None], H0=c[None], noise=np.full((1, 1), ri), valid=~miss[:, None]
            )
            x2, P2, S2, _, _ = measurement_update(x, P, S, yz[:, None], lin, form)
            Ns = (N,) + P.shape[1:]
            covs = np.stack([np.broadcast_to(P1, Ns), np.broadcast_to(P2, Ns), np.broadcast_to(P, Ns)])
            facs = (
                None
                if S is None
                else np.stack([np.broadcast_to(S1, Ns), np.broadcast_to(S2, Ns), np.broadcast_to(S, Ns)])
            )
            xm, Pm, Sm = merge_gaussians(w, np.stack([x1, x2, x]), covs, facs)
            if miss.any():
                xm = np.where(miss[:, None], x, xm)
                Pm = np.where(miss[:, None, None], np.broadcast_to(P, Ns), Pm)
                if Sm is not None:
                    Sm = np.where(miss[:, None, None], np.broadcast_to(S, Ns), Sm)
            x, P, S = xm, Pm, Sm
            post[:, i] = w.T
            ll += ll_i
        return x, P, S, {"mode_posterior": post, "log_likelihood": ll}

    def __repr__(self) -> str:
        return f"SaturationAssumedDensityFilter({self.channel!r}, covariance_update={self.covariance_update!r})"


register(
    family_entry(
        SaturationAssumedDensityFilter,
        "assumed-density filter for random saturation with missing readings (beyond the sources)",
        ("saturation",),
        options=ADF_OPTIONS,
    )
)
