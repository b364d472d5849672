r"""Steady-state Tobit Kalman filter with a controlled censoring limit.

Source: Miller (2015), §3.4.2, (3.51)–(3.58) (spec 001a §3.7, 001b §0.3).

If the sensor's censoring limit is set from the a-priori estimate (3.56),

.. math::

    T_k = C\bar x_k + D u_k + \sigma\,\Phi^{-1}(\Xi) \quad\text{(right censoring)}, \qquad
    T_k = C\bar x_k + D u_k - \sigma\,\Phi^{-1}(\Xi) \quad\text{(left censoring)},

the probability of an uncensored reading evaluated at the prior is the constant
:math:`\Xi` (``xi_uncensored``), and the Tobit statistics are constant:
:math:`\alpha = \Phi^{-1}(\Xi)`, :math:`\hat\lambda = \phi(\alpha)/\Xi`,
:math:`\upsilon = \sigma^2(1 - \alpha\hat\lambda - \hat\lambda^2)`. The TKF becomes a Kalman
filter for the modified pair :math:`(A, \tilde C = \Xi C)` with noise :math:`\Upsilon`
(3.57):

.. math::

    \bar\Psi_\infty &= A\bar\Psi_\infty A^T - A\bar\Psi_\infty\tilde C^T(\tilde C\bar\Psi_\infty\tilde C^T
        + \Upsilon)^{-1}\tilde C\bar\Psi_\infty A^T + Q \\
    K_\infty &= \bar\Psi_\infty\tilde C^T(\tilde C\bar\Psi_\infty\tilde C^T + \Upsilon)^{-1}, \qquad
    \Psi_\infty = (I - K_\infty\tilde C)\bar\Psi_\infty \\
    \hat x_k &= \bar x_k + K_\infty(y_k - E[y_k]), \qquad
    E[y_k] = C\bar x_k + Du_k \mp \sigma[\phi(\alpha) - (1-\Xi)\alpha] \quad (3.58)

(upper sign: right censoring). The modified DARE is solved with
``scipy.linalg.solve_discrete_are``.

Deviations from the source
--------------------------
* (3.57) prints :math:`K = \bar\Psi(\Xi C)^T\bar\Psi(\cdots)^{-1}` with a spurious second
  :math:`\bar\Psi`; it is dropped (spec A-3.4, an unavoidable repair: the printed form does
  not conform).
* (3.61)/(5.68) write the limit with :math:`C\hat x_k`; the a-priori :math:`C\bar x_k` is used,
  as (3.56) states, since the limit must be set before the measurement arrives (spec A-3.10).
* (3.54) is garbled (pdf for cdf, no T term); (3.58) and the corrected (3.54) agree (spec A-3.3).

Time convention: x_0 ~ N(x0, P0) prior; y_1 at index 0; output index k-1 holds x̂_{k|k}.
Symbols: ``xi_uncensored`` = Ξ (probability of *not* being censored; 1 − Ξ is the
censored fraction, spec A-3.11), ``upsilon`` = υ, ``inverse_mills`` = λ̂, ``gain`` = K∞,
``prior_cov`` = Ψ̄∞, ``cov`` = Ψ∞.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from scipy.linalg import solve_discrete_are
from scipy.special import ndtri

from .._validation import ShapeError, ValidationError, as_float_array, check_instance, check_option
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._common import FilterResult, prepare_inputs, prepare_measurements
from .tobit import _sigma_of

__all__ = ["SteadyStateTobitKalmanFilter", "controlled_limit_statistics", "tobit_kalman_filter_controlled"]


def controlled_limit_statistics(xi_uncensored: Any, sigma: Any):
    r"""Constant Tobit statistics under the controlled limit (3.56)–(3.57).

    Parameters
    ----------
    xi_uncensored : float or (m,) array_like in (0, 1)
    sigma : float or (m,) array_like, > 0
        Measurement-noise standard deviations.

    Returns
    -------
    alpha : :math:`\Phi^{-1}(\Xi)`
    inverse_mills : :math:`\hat\lambda = \phi(\alpha)/\Xi` (the right-censoring IMR of (3.54))
    upsilon : :math:`\sigma^2(1 - \alpha\hat\lambda - \hat\lambda^2)`
    offset : :math:`\sigma[\phi(\alpha) - (1-\Xi)\alpha]`, so that
        :math:`E[y] = C\bar x \mp \text{offset}` (3.58)

    Raises
    ------
    ValidationError
        If some Ξ is outside (0, 1) or σ <= 0.
    """
    xi = as_float_array(xi_uncensored, "xi_uncensored")
    if np.any((xi <= 0) | (xi >= 1)):
        raise ValidationError(f"xi_uncensored: expected probabilities in the open interval (0, 1), got {xi}")
    sig = as_float_array(sigma, "sigma")
    if np.any(sig <= 0):
        raise ValidationError(f"sigma: expected standard deviations > 0, got {sig}")
    alpha = ndtri(xi)
    phi = np.exp(-0.5 * alpha**2) / np.sqrt(2 * np.pi)
    lam = phi / xi
    upsilon = sig**2 * (1.0 - alpha * lam - lam**2)
    offset = sig * (phi - (1.0 - xi) * alpha)
    return alpha, lam, upsilon, offset


def _xi_per_channel(xi_uncensored: Any, m: int) -> np.ndarray:
    """Ξ as an (m,) array; a scalar applies to every channel."""
    xi = as_float_array(xi_uncensored, "xi_uncensored")
    if xi.ndim > 1 or xi.size not in (1, m):
        raise ShapeError(f"xi_uncensored: expected a scalar or shape ({m},) (one per channel), got shape {xi.shape}")
    return np.broadcast_to(xi.reshape(-1), (m,)).copy()


def _no_missing(y2: np.ndarray, name: str) -> None:
    # the gain and the reported covariance are the constant steady-state ones: a skipped
    # (missing) sample would make the reported covariance wrong, so NaN is refused
    if np.isnan(y2).any():
        raise ValidationError(f"{name}: the steady-state TKF has a fixed gain and cannot skip missing samples "
                              "(NaN found); use TobitKalmanFilter for records with gaps")


def _initial_mean(system: LinearSystem, x0: Any, runs: int, batch: tuple[int, ...]) -> np.ndarray:
    n = system.n
    x = system.x0 if x0 is None else as_float_array(x0, "x0")
    for shape in ((runs, n), tuple(batch) + (n,)):
        try:
            return np.broadcast_to(x, shape).reshape(runs, n).copy()
        except ValueError:
            pass
    raise ShapeError(f"x0: expected ({n},) or the batch shape of y + ({n},), got {x.shape}")


def _warn_if_diverged(means: np.ndarray, name: str) -> None:
    # the fixed-gain Tobit observer is not globally stable (e.g. A = -1, Xi < 0.5, small sigma: the
    # error grows geometrically and overflows); say so instead of returning NaN silently
    bad = ~np.isfinite(means).all(axis=-1)
    if bad.any():
        run, step = (int(i) for i in np.argwhere(bad)[0])
        warnings.warn(f"{name}: the estimate diverged (overflowed to inf/NaN) in run {run} at step k={step + 1}; "
                      "the fixed-gain Tobit observer is not globally stable for this model and Xi "
                      "(docs/reliability.md)", RuntimeWarning, stacklevel=3)


class SteadyStateTobitKalmanFilter:
    r"""Fixed-gain Tobit Kalman filter whose sensor limit is steered from the prior (Miller §3.4.2).

    Parameters
    ----------
    system : LinearSystem
        Time-invariant model; R diagonal; (A, √Q) stabilizable and (A, C) detectable.
    xi_uncensored : float or (m,) array_like in (0, 1)
        Target probability Ξ of an *uncensored* reading per channel.
    side : {"upper", "lower"}, default "upper"
        Right censoring (the source's §3.4) or left censoring (spec A-3.11, [non-source]).

    Attributes
    ----------
    gain : (n, m) ndarray
        :math:`K_\infty`.
    prior_cov, cov : (n, n) ndarray
        :math:`\bar\Psi_\infty` and :math:`\Psi_\infty`.
    upsilon, inverse_mills, alpha : (m,) ndarray
        Constant Tobit statistics.

    Raises
    ------
    ValidationError
        Ξ outside (0, 1), a time-varying or non-diagonal model, or a modified DARE
        without a stabilizing solution (the message says so).

    Examples
    --------
    The Ξ = 0.5 noise term is :math:`\sigma^2(1 - 2/\pi)` (spec 001a §3.7 table):

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    >>> f = tk.SteadyStateTobitKalmanFilter(sys, 0.5)
    >>> bool(np.isclose(f.upsilon[0], 0.1 * (1 - 2 / np.pi)))
    True
    """

    def __init__(self, system: LinearSystem, xi_uncensored: Any, *, side: str = "upper"):
        check_instance(system, LinearSystem, "system")
        check_option(side, "side", ("upper", "lower"))
        if not system.time_invariant:
            raise ValidationError("system: the steady-state TKF needs a time-invariant model (constant A, C, Q, R)")
        m = system.m
        sigma = _sigma_of(system.measurement_cov(1))
        xi = _xi_per_channel(xi_uncensored, m)
        self.alpha, self.inverse_mills, self.upsilon, self._offset = controlled_limit_statistics(xi, sigma)
        self.system, self.side, self.xi_uncensored, self.sigma = system, side, xi, sigma
        A, C, Q = system.transition(0), system.measurement(1), system.process_cov(0)
        Ct = xi[:, None] * C
        Ups = np.diag(self.upsilon)
        try:
            Pbar = solve_discrete_are(A.T, Ct.T, Q, Ups)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise ValidationError(
                "modified DARE (3.57) for (A, Xi C, Q, upsilon) has no stabilizing solution: "
                f"check that (A, sqrt(Q)) is stabilizable and (A, C) detectable ({exc})") from None
        if not np.all(np.isfinite(Pbar)):
            raise ValidationError("modified DARE (3.57) returned a non-finite solution")
        S = Ct @ Pbar @ Ct.T + Ups
        self.prior_cov = 0.5 * (Pbar + Pbar.T)
        self.gain = np.linalg.solve(S, Ct @ Pbar).T
        cov = (np.eye(system.n) - self.gain @ Ct) @ Pbar
        self.cov = 0.5 * (cov + cov.T)
        self.modified_C = Ct

    def limit(self, prior_measurement: np.ndarray) -> np.ndarray:
        r"""Censoring limit (3.56) for the prior measurement mean :math:`C\bar x_k + Du_k` (..., m)."""
        shift = self.sigma * self.alpha
        return prior_measurement + shift if self.side == "upper" else prior_measurement - shift

    def expected_measurement(self, prior_measurement: np.ndarray) -> np.ndarray:
        """E[y_k] of (3.58) under the controlled limit."""
        return prior_measurement - self._offset if self.side == "upper" else prior_measurement + self._offset

    def censoring(self, limits: np.ndarray) -> Censoring:
        """The :class:`Censoring` of one run's record of limits ``(T, m)`` (e.g. ``extras["limits"][i]``)."""
        return Censoring(upper=limits) if self.side == "upper" else Censoring(lower=limits)

    def filter(self, y: Any, *, u: Any = None, x0: Any = None) -> FilterResult:
        r"""Fixed-gain update of measurements censored at the controlled limits.

        ``y`` (..., T, m) must have been censored at the limits :meth:`limit` gives for
        this filter's own priors (e.g. by :meth:`filter_controlled`); the filter
        itself only needs :math:`E[y_k]`, which (3.58) gives without the limits.
        Covariances are the constant :math:`\Psi_\infty`, :math:`\bar\Psi_\infty`
        (read-only broadcast views).
        NaN (a missing sample) is refused with a :class:`ValidationError`: a fixed gain
        cannot skip a sample without making the reported covariance wrong.
        """
        y2, batch = prepare_measurements(y, self.system.m)
        _no_missing(y2, "y")
        return self._run(y2, batch, u, x0, latent=False)

    def filter_controlled(self, y_latent: Any, *, u: Any = None, x0: Any = None) -> FilterResult:
        """Close the loop between sensor and filter: at each step the limit (3.56) is set
        from the filter's prior and the latent reading is censored there (by
        the sensor), then the fixed-gain update runs.

        Returns the usual result with extras ``limits`` and ``y`` (..., T, m): the limits
        used and the censored readings the filter received.
        """
        y2, batch = prepare_measurements(y_latent, self.system.m, "y_latent")
        _no_missing(y2, "y_latent")
        return self._run(y2, batch, u, x0, latent=True)

    def _run(self, y2, batch, u, x0, *, latent: bool) -> FilterResult:
        sys = self.system
        N, T, m = y2.shape
        n = sys.n
        u2 = prepare_inputs(sys, u, N, T)
        x = _initial_mean(sys, x0, N, batch)
        A, C, K = sys.transition(0), sys.measurement(1), self.gain
        means = np.empty((N, T, n))
        pmeans = np.empty((N, T, n))
        limits = np.empty((N, T, m)) if latent else None
        ys = np.empty((N, T, m)) if latent else None
        for k in range(1, T + 1):
            uk = None if u2 is None else u2[:, k - 1]
            bx, dy = sys.input_effect(k, uk)
            x = x @ A.T + bx
            pmeans[:, k - 1] = x
            ybar = x @ C.T + dy
            yk = y2[:, k - 1]
            if latent:
                lim = self.limit(ybar)
                # the sensor clips its reading at the limit the filter set
                yk = np.minimum(yk, lim) if self.side == "upper" else np.maximum(yk, lim)
                limits[:, k - 1], ys[:, k - 1] = lim, yk
            x = x + (yk - self.expected_measurement(ybar)) @ K.T
            means[:, k - 1] = x
        _warn_if_diverged(means, "SteadyStateTobitKalmanFilter")
        extras = {} if not latent else {"limits": limits.reshape(batch + (T, m)), "y": ys.reshape(batch + (T, m))}
        return FilterResult(mean=means.reshape(batch + (T, n)),
                            cov=np.broadcast_to(self.cov, batch + (T, n, n)),
                            pred_mean=pmeans.reshape(batch + (T, n)),
                            pred_cov=np.broadcast_to(self.prior_cov, batch + (T, n, n)), extras=extras)


def tobit_kalman_filter_controlled(system: LinearSystem, xi_uncensored: Any, y_latent: Any, *,
                                   side: str = "upper", u: Any = None) -> FilterResult:
    r"""The full TKF (3.55) whose sensor limit is steered by (3.56) from the TKF's own prior.

    At each step the limit :math:`T_k = C\bar x_k + Du_k \pm \sigma\Phi^{-1}(\Xi)` is set, the
    latent reading is clipped there by the sensor, and the ordinary Tobit update
    (:func:`~tobitkf.filters.tobit.tobit_update`) runs. Then :math:`E(\mathbf p_k) \equiv \Xi`
    at every step and the covariance converges to the modified-DARE posterior
    :math:`\Psi_\infty` of :class:`SteadyStateTobitKalmanFilter` (spec 001a §6 item 4).

    Returns the usual result with extras ``limits``, ``y`` and ``p_uncensored`` (..., T, m).
    """
    from ._common import check_prior, predict
    from .tobit import tobit_update

    check_instance(system, LinearSystem, "system")
    check_option(side, "side", ("upper", "lower"))
    y2, batch = prepare_measurements(y_latent, system.m, "y_latent")
    N, T, m = y2.shape
    n = system.n
    sigma = _sigma_of(system.measurement_cov(1))
    alpha, _, _, _ = controlled_limit_statistics(_xi_per_channel(xi_uncensored, m), sigma)
    u2 = prepare_inputs(system, u, N, T)
    x, P = check_prior(system, None, None, N)
    out = {name: np.empty((N, T) + shape) for name, shape in
           (("mean", (n,)), ("cov", (n, n)), ("pred_mean", (n,)), ("pred_cov", (n, n)),
            ("limits", (m,)), ("y", (m,)), ("p_uncensored", (m,)))}
    inf = np.full((N, m), np.inf)
    for k in range(1, T + 1):
        uk = None if u2 is None else u2[:, k - 1]
        bx, dy = system.input_effect(k, uk)
        x, P = predict(x, P, system.transition(k - 1), system.process_cov(k - 1), bx)
        out["pred_mean"][:, k - 1], out["pred_cov"][:, k - 1] = x, P
        C = system.measurement(k)
        ybar = x @ C.T + dy
        if side == "upper":
            lim = ybar + sigma * alpha
            yk = np.minimum(y2[:, k - 1], lim)
            lower, upper = -inf, lim
        else:
            lim = ybar - sigma * alpha
            yk = np.maximum(y2[:, k - 1], lim)
            lower, upper = lim, inf
        x, P, st = tobit_update(x, P, yk, C, sigma, lower, upper, dy=dy)
        out["mean"][:, k - 1], out["cov"][:, k - 1] = x, P
        out["limits"][:, k - 1], out["y"][:, k - 1], out["p_uncensored"][:, k - 1] = lim, yk, st.p_uncensored
    shaped = {k: v.reshape(batch + v.shape[1:]) for k, v in out.items()}
    return FilterResult(mean=shaped.pop("mean"), cov=shaped.pop("cov"), pred_mean=shaped.pop("pred_mean"),
                        pred_cov=shaped.pop("pred_cov"), extras=shaped)


