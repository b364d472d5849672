r"""Steady-state Tobit Kalman filter with a controlled censoring limit.

Source: Miller (2015), §3.4.2, (3.51)–(3.58); our deviations: docs/sources/miller2015-ch1-4.md.

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
  :math:`\bar\Psi`; it is dropped (docs/sources MA-11, an unavoidable repair: the printed form does
  not conform).
* (3.61)/(5.68) write the limit with :math:`C\hat x_k`; the a-priori :math:`C\bar x_k` is used,
  as (3.56) states, since the limit must be set before the measurement arrives (docs/sources MA-17).
* (3.54) is garbled (pdf for cdf, no T term); (3.58) and the corrected (3.54) agree (docs/sources MA-10).
* :math:`\Psi_\infty` (``cov``) is what the filter believes with :math:`E(\mathbf p) \equiv \Xi`, not an
  error bound (docs/sources MB-F1).

Time convention: x_0 ~ N(x0, P0) prior; y_1 at index 0; output index k-1 holds x̂_{k|k}.
In the terms of the shared core (:mod:`tobitkf.filters.core`): a fixed gain :math:`K_\infty`,
expected reading (3.58), and the constant covariances :math:`\bar\Psi_\infty`, :math:`\Psi_\infty`;
the mean recursion runs through the shared loop. :func:`tobit_kalman_filter_controlled` is the full
TKF (3.55) whose limit is set from its prior, a :class:`~tobitkf.filters.tobit.TobitKalmanFilter`
whose measurement model first clips the latent reading at (3.56).

Symbols: ``xi_uncensored`` = Ξ (probability of *not* being censored; 1 − Ξ is the
censored fraction, docs/sources MA-18), ``upsilon`` = υ, ``lambda_hat`` = λ̂ = φ(α)/Ξ (the source's
right-censoring inverse Mills ratio, positive), ``inverse_mills`` = the inverse Mills ratio with the
sign of :attr:`tobitkf.CensoredMoments.inverse_mills` (−λ̂ for right censoring, +λ̂ for left),
``gain`` = K∞, ``prior_cov`` = Ψ̄∞, ``cov`` = Ψ∞.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from scipy.linalg import solve_discrete_are
from scipy.special import ndtri

from .._validation import ShapeError, ValidationError, as_float_array, check_instance, check_option, diagonal_sigma
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._backend import BACKENDS, system_gap, use_compiled
from ._outputs import loop_array, loop_input, output_arrays
from .core import FilterResult, FilterState, MeasurementPrediction, step_state
from .kalman import LinearGaussianFamily
from .registry import family_entry, register
from .tobit import NOISE_TERMS, TobitKalmanFilter, tobit_measurement

__all__ = [
    "SteadyStateTobitKalmanFilter",
    "controlled_limit_statistics",
    "tobit_kalman_filter_controlled",
    "ControlledLimitTobitKalmanFilter",
]


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
    lambda_hat : :math:`\hat\lambda = \phi(\alpha)/\Xi` (the right-censoring IMR of (3.54), positive)
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


def _initial_mean(system: LinearSystem, x0: Any, runs: int, batch: tuple[int, ...]) -> np.ndarray:
    n = system.n
    x = system.x0 if x0 is None else as_float_array(x0, "x0")
    for shape in ((runs, n), tuple(batch) + (n,)):
        try:
            return np.broadcast_to(x, shape).reshape(runs, n).copy()
        except ValueError:
            pass
    raise ShapeError(f"x0: expected ({n},) or the batch shape of y + ({n},), got {x.shape}")


def _warn_if_diverged(means: np.ndarray | None, name: str, k0: int = 0, stacklevel: int = 3) -> None:
    # the fixed-gain Tobit observer is not globally stable (e.g. A = -1, Xi < 0.5, small sigma: the
    # error grows geometrically and overflows); say so instead of returning NaN silently
    if means is None or np.isfinite(means.reshape(-1) if means.flags.c_contiguous else means).all():
        return  # the common case, without the (N, T) mask (it cost ~25 ns per run-step at n = 2)
    bad = ~np.isfinite(means).all(axis=-1)
    if bad.any():
        idx = np.argwhere(bad)[0]
        run, step = (tuple(int(i) for i in idx[:-1]) or (0,)), int(idx[-1])
        warnings.warn(
            f"{name}: the estimate diverged (overflowed to inf/NaN) in run {run[0] if len(run) == 1 else run} "
            f"at step k={k0 + step + 1}; the fixed-gain Tobit observer is not globally stable for this "
            "model and Xi (docs/reliability.md)",
            RuntimeWarning,
            stacklevel=stacklevel,
        )


class SteadyStateTobitKalmanFilter(LinearGaussianFamily):
    r"""Fixed-gain Tobit Kalman filter whose sensor limit is steered from the prior (Miller §3.4.2).

    Parameters
    ----------
    system : LinearSystem
        Time-invariant model; R diagonal; (A, √Q) stabilizable and (A, C) detectable.
    xi_uncensored : float or (m,) array_like in (0, 1)
        Target probability Ξ of an *uncensored* reading per channel.
    side : {"upper", "lower"}, default "upper"
        Right censoring (the source's §3.4) or left censoring (ours, not in the source; docs/sources MA-18).
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``filter`` and ``filter_controlled`` through the one compiled time loop
        (:mod:`tobitkf.filters._compiled_loop`, its fixed-gain code, the means only; equal to the numpy path to
        rounding; it covers every case without a control input ``u``) or the numpy reference path. ``"numba"``
        raises for a case the loop does not cover; ``"auto"`` then runs numpy. ``step`` always runs numpy.

    Attributes
    ----------
    gain : (n, m) ndarray
        :math:`K_\infty` (the filter gain: :math:`\hat x = \bar x + K_\infty(y - E[y])`).
    prior_cov, cov : (n, n) ndarray
        :math:`\bar\Psi_\infty` and :math:`\Psi_\infty`; :math:`\Psi_\infty` is not an error bound
        (docs/sources MB-F1).
    upsilon, lambda_hat, alpha : (m,) ndarray
        Constant Tobit statistics; ``lambda_hat`` = :math:`\hat\lambda = \phi(\alpha)/\Xi`.
    inverse_mills : (m,) ndarray
        The inverse Mills ratio at the prior with the sign of :attr:`tobitkf.CensoredMoments.inverse_mills`
        (:math:`-\hat\lambda` for right censoring, :math:`+\hat\lambda` for left).

    Raises
    ------
    ValidationError
        Ξ outside (0, 1), a time-varying or non-diagonal model, or a modified DARE
        without a stabilizing solution (the message says so); ``backend="numba"`` with a control
        input (raised by ``filter``).
    ImportError
        ``backend="numba"`` without numba installed (raised by ``filter``).

    Notes
    -----
    Online use: :meth:`step` takes the reading censored at the limit :meth:`limit` gives for the
    state's prediction (the sensor sets it from the filter's prior); ``step(state, y, latent=True)``
    takes the latent reading and censors it there itself, as :meth:`filter_controlled` does.

    Examples
    --------
    The Ξ = 0.5 noise term is :math:`\sigma^2(1 - 2/\pi)` (Miller §3.4.2):

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    >>> f = tk.SteadyStateTobitKalmanFilter(sys, 0.5)
    >>> bool(np.isclose(f.upsilon[0], 0.1 * (1 - 2 / np.pi)))
    True
    """

    _name = "SteadyStateTobitKalmanFilter"
    _loop_consts: tuple  # the compiled loop's constant arguments, set on its first call (_steady_loop_run)
    _step_options = ("latent",)
    # the gain and the reported covariance are the constant steady-state ones: a skipped (missing) sample
    # would make the reported covariance wrong, so NaN is refused, by the record's one finiteness pass
    _allow_missing = False
    _missing_reason = (
        "the steady-state TKF has a fixed gain and cannot skip missing samples; use TobitKalmanFilter for records "
        "with gaps"
    )

    _filter_doc = r"""Fixed-gain update (Miller §3.4.2, (3.58)) of measurements censored at the controlled limits.

    ``y`` (..., T, m) must have been censored at the limits :meth:`limit` gives for this filter's own priors
    (e.g. by :meth:`filter_controlled`); the filter itself only needs :math:`E[y_k]`, which (3.58) gives without
    the limits. Covariances are the constant :math:`\Psi_\infty`, :math:`\bar\Psi_\infty` (read-only broadcast
    views)."""
    _filter_params = {
        "y": "(..., T, m) array_like\n    The censored readings y_1..y_T; no NaN (see Raises).",
        "x0": "array_like, optional\n"
        "    Override the prior mean of :math:`x_0`, ``(n,)`` or ``(..., n)`` (the covariance is the constant\n"
        "    limit).",
    }
    _filter_raises = (
        "NaN (a missing sample): a fixed gain cannot skip a sample without making the reported covariance wrong"
    )

    def __init__(self, system: LinearSystem, xi_uncensored: Any, *, side: str = "upper", backend: str = "auto"):
        check_instance(system, LinearSystem, "system")
        check_option(side, "side", ("upper", "lower"))
        check_option(backend, "backend", BACKENDS)
        self.backend = backend
        if not system.time_invariant:
            raise ValidationError("system: the steady-state TKF needs a time-invariant model (constant A, C, Q, R)")
        m = system.m
        sigma = diagonal_sigma(system.measurement_cov(1))
        xi = _xi_per_channel(xi_uncensored, m)
        self.alpha, self.lambda_hat, self.upsilon, self._offset = controlled_limit_statistics(xi, sigma)
        self.inverse_mills = -self.lambda_hat if side == "upper" else self.lambda_hat.copy()
        self._setup_system(system)
        self.side, self.xi_uncensored, self.sigma = side, xi, sigma
        A, C, Q = system.transition(0), system.measurement(1), system.process_cov(0)
        Ct = xi[:, None] * C
        Ups = np.diag(self.upsilon)
        try:
            Pbar = solve_discrete_are(A.T, Ct.T, Q, Ups)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise ValidationError(
                "modified DARE (3.57) for (A, Xi C, Q, upsilon) has no stabilizing solution: "
                f"check that (A, sqrt(Q)) is stabilizable and (A, C) detectable ({exc})"
            ) from None
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

    # ---- the family's hooks ------------------------------------------------------------
    def _initial(self, N, x0, P0, batch):
        if P0 is not None:
            raise ValidationError(
                "P0: the steady-state TKF has the constant covariance of the modified DARE; only x0 can be given"
            )
        return _initial_mean(self.system, x0, N, batch), self.cov[None].copy(), {}

    def _transition(self, k, u, carry):
        return self._linear_transition(k, u, P_fixed=self.prior_cov[None])

    def _measurement(self, k, xp, Pp, y, u, carry, latent=False):
        ybar = xp @ self.system.measurement(k).T + self._feedthrough(k, u)
        extras = {}
        obs = None
        if latent:
            lim = self.limit(ybar)
            # the sensor clips its reading at the limit the filter set
            obs = np.minimum(y, lim) if self.side == "upper" else np.maximum(y, lim)
            extras = {"limits": lim, "y": obs}
        mp = MeasurementPrediction(
            expected=self.expected_measurement(ybar),
            H0=self.modified_C,
            noise=np.zeros((1, self.m)),
            observed=obs,
            gain=self.gain,
            posterior_cov=self.cov[None],
            extras=extras,
        )
        return mp, carry

    def _compiled_online_step(self, state, y, u, options):
        r"""The fixed-gain step without the shared update's general machinery (no input ``u``): the same
        numbers as :meth:`_transition` + :meth:`_measurement` + the fixed-gain branch of
        :func:`~tobitkf.filters.core.measurement_update`, in the same order, :math:`\bar x = A\hat x`,
        :math:`\hat x = \bar x + K_\infty(y - E[y])` and :math:`\Psi_\infty`, with the transposed matrices
        cached per estimator. None (the shared step runs) with an input or a NaN innovation (an overflowed
        estimate, whose channels the shared update leaves out)."""
        if u is not None:
            return None
        mats = self.__dict__.get("_step_mats")
        if mats is None:
            sys_ = self.system
            mats = self._step_mats = (sys_.transition(0).T, sys_.measurement(1).T, self.gain.T, self.cov[None])
        At, Ct, Kt, P = mats
        xp = state.x @ At + 0.0  # the shared predict adds the input offset b = 0.0
        ybar = xp @ Ct + 0.0  # and the feedthrough 0.0
        extras = {}
        obs = y
        if options:  # latent=True: the sensor clips its reading at the limit the filter set
            lim = self.limit(ybar)
            obs = np.minimum(y, lim) if self.side == "upper" else np.maximum(y, lim)
            extras = {"limits": lim, "y": obs}
        innov = obs - self.expected_measurement(ybar)
        if innov.size <= 4 and any(v != v for v in innov.ravel().tolist()) or innov.size > 4 and np.isnan(innov).any():
            return None
        return step_state(state.k + 1, state.batch_shape, xp + innov @ Kt, P, self.n, None, state.carry, extras)

    def _prepare_step_options(self, state, options):
        latent = options.get("latent", False)
        if not isinstance(latent, (bool, np.bool_)):
            raise ValidationError(f"latent: expected True or False, got {latent!r}")
        return {"latent": True} if latent else {}

    # ---- the compiled path (batched ``filter``/``filter_controlled`` only; ``step`` runs numpy) ------
    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        if not use_compiled(self.backend, system_gap(self.system, u2), "the steady-state Tobit Kalman filter"):
            return None
        return _steady_loop_run(self, y2, state, want, batch, bool((step_options or {}).get("latent", False)))

    def _fixed_gain_run(self, y: Any, u: Any, x0: Any, outputs: Any, state: FilterState | None, **kw: Any):
        """The one loop (compiled or numpy) of ``filter``/``filter_controlled``, then the divergence warning of
        either path: the means are scanned only when the last one is not finite (an overflow never recovers:
        inf and NaN spread through A and K)."""
        k0 = self.k0 if state is None else state.k
        res = self._run(y, u, x0, None, outputs=outputs, state=state, **kw)
        if res.final is not None and not np.isfinite(res.final.x).all():
            # stack: here, filter or filter_controlled, the caller
            _warn_if_diverged(res.mean, self._name, k0, stacklevel=4)
        return res

    def filter(  # type: ignore[override]  # no P0: the covariances are the constant limits
        self, y: Any, *, u: Any = None, x0: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        return self._fixed_gain_run(y, u, x0, outputs, state)

    def filter_controlled(
        self, y_latent: Any, *, u: Any = None, x0: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        """Close the loop between sensor and filter: at each step the limit (3.56) is set
        from the filter's prior and the latent reading is censored there (by
        the sensor), then the fixed-gain update runs.

        Returns the usual result with extras ``limits`` and ``y`` (..., T, m): the limits
        used and the censored readings the filter received.
        """
        return self._fixed_gain_run(y_latent, u, x0, outputs, state, name="y_latent", step_options={"latent": True})


class ControlledLimitTobitKalmanFilter(TobitKalmanFilter):
    r"""The full TKF (3.55) whose sensor limit is steered by (3.56) from the TKF's own prior.

    At each step the limit :math:`T_k = C\bar x_k + Du_k \pm \sigma\Phi^{-1}(\Xi)` is set, the
    latent reading is clipped there by the sensor, and the ordinary Tobit update runs; ``filter`` and
    ``step`` take *latent* readings. Then :math:`E(\mathbf p_k) \equiv \Xi` at every step and the
    covariance converges to the modified-DARE posterior :math:`\Psi_\infty` of
    :class:`SteadyStateTobitKalmanFilter` (Miller §3.4.2).

    Parameters
    ----------
    system : LinearSystem
        Time-invariant model with diagonal R.
    xi_uncensored : float or (m,) array_like in (0, 1)
    side : {"upper", "lower"}, default "upper"
    """

    _name = "ControlledLimitTobitKalmanFilter"
    _step_options = ()

    def __init__(self, system: LinearSystem, xi_uncensored: Any, *, side: str = "upper", **options: Any):
        check_instance(system, LinearSystem, "system")
        check_option(side, "side", ("upper", "lower"))
        super().__init__(system, Censoring(), check_limits=False, **options)
        sigma = diagonal_sigma(system.measurement_cov(1))
        self.alpha = controlled_limit_statistics(_xi_per_channel(xi_uncensored, system.m), sigma)[0]
        self.side, self.sigma_ = side, sigma

    def _compiled_filter(self, *args):
        # the TKF's compiled loop takes the limits as data; here they are set from the prior inside the loop, so
        # there is no compiled path: numpy under "auto", a refusal under "numba" (not a silent numpy run)
        use_compiled(self.backend, "a limit set from the filter's prior (3.56)", "the controlled-limit TKF")
        return None

    def _compiled_online_step(self, *args):
        return None

    def _measurement(self, k, xp, Pp, y, u, carry, **options):
        C = self.system.measurement(k)
        dy = self._feedthrough(k, u)
        ybar = xp @ C.T + dy
        inf = np.full(ybar.shape, np.inf)
        if self.side == "upper":
            lim = ybar + self.sigma_ * self.alpha
            obs, lower, upper = np.minimum(y, lim), -inf, lim
        else:
            lim = ybar - self.sigma_ * self.alpha
            obs, lower, upper = np.maximum(y, lim), lim, inf
        mp = tobit_measurement(xp, C, self.sigma_, lower, upper, dy=dy, noise_term=self.noise_term)
        mp = MeasurementPrediction(
            expected=mp.expected,
            H0=mp.H0,
            scale=mp.scale,
            noise=mp.noise,
            observed=obs,
            extras={"limits": lim, "y": obs, "p_uncensored": mp.scale},
        )
        return mp, carry


def tobit_kalman_filter_controlled(
    system: LinearSystem, xi_uncensored: Any, y_latent: Any, *, side: str = "upper", u: Any = None
) -> FilterResult:
    r"""The full TKF (3.55) whose sensor limit is steered by (3.56) from the TKF's own prior.

    See :class:`ControlledLimitTobitKalmanFilter`; returns the usual result with extras ``limits``,
    ``y`` and ``p_uncensored`` (..., T, m).
    """
    est = ControlledLimitTobitKalmanFilter(system, xi_uncensored, side=side, backend="numpy")
    return est._run(y_latent, u, name="y_latent")


# --------------------------------------------------------------------------- the compiled path


def _steady_loop_run(est: SteadyStateTobitKalmanFilter, y2, state: FilterState, want, batch, latent: bool):
    """The means through the compiled loop's fixed-gain code from ``state``; the constant covariances and the
    outputs as the numpy path returns them (one covariance shared by N > 1 runs is a read-only broadcast view)."""
    from . import _compiled_loop, _loop_specs

    N, T, m = y2.shape
    n = est.n
    consts = est.__dict__.get("_loop_consts")
    if consts is None:  # A, Qd (unused), C (1, m, n), and per channel the signed offset and shift and K's column
        upper = est.side == "upper"
        sgn = -1.0 if upper else 1.0
        A, Qd = _loop_specs._system_arrays(est.system, 0, 1)
        par = np.concatenate([(sgn * est._offset)[:, None], (-sgn * est.sigma * est.alpha)[:, None], est.gain.T], 1)
        C = np.ascontiguousarray(est.system.measurement(1), dtype=float)[None]
        consts = est._loop_consts = (A, Qd, C, np.ascontiguousarray(par)[None], int(upper))
    A, Qd, C, par, code = consts
    ext = "extras" in want and latent
    means, pmeans, comp = output_arrays(  # one allocation, from the output pool when large
        N, T, ("mean" in want, (n,)), ("pred_mean" in want, (n,)), (ext, (m, 2))
    )
    x_last = np.empty((N, n))
    args = _loop_specs.LoopArguments(
        _compiled_loop.FIXED_GAIN_KIND, loop_input(y2), A=A, Qd=Qd, H=C, par=par, noise_code=code + 2 * latent,
        x0=loop_input(state.x), P0=est.cov[None], means=means, pmeans=pmeans, comp=comp, x_last=x_last,
        P_last=np.empty((N, 0, 0)),  # no covariance is carried
    )  # fmt: skip
    _compiled_loop.compiled_loop(*args.filled())  # the arrays the fixed gain does not use: made by filled()

    def out(a):
        return loop_array(a, batch)

    def const(key, P):
        # the numpy loop stores a covariance shared by the runs once and broadcasts it (a copy for one run)
        if key not in want:
            return None
        one = np.broadcast_to(P, (T,) + P.shape)
        return np.broadcast_to(one, batch + one.shape) if N != 1 else one.copy().reshape(batch + one.shape)

    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=est.cov[None], n=n, carry=state.carry)
    return FilterResult(
        mean=out(means),
        cov=const("cov", est.cov),
        pred_mean=out(pmeans),
        pred_cov=const("pred_cov", est.prior_cov),
        extras={"limits": out(comp[..., 0]), "y": out(comp[..., 1])} if ext else {},
        times=np.arange(state.k + 1, state.k + T + 1),
        var=const("var", np.diagonal(est.cov).copy()),
        final=final,
    )


register(
    family_entry(
        SteadyStateTobitKalmanFilter,
        "fixed-gain TKF whose sensor limit is steered from its prior (Miller §3.4)",
        options={"xi_uncensored": float, "side": ("upper", "lower"), "backend": BACKENDS},  # xi: by keyword
        required=("xi_uncensored",),
        reads="latent",
    ),
    family_entry(
        ControlledLimitTobitKalmanFilter,
        "full TKF with the steered limit of (3.56) (Miller §3.4)",
        options={
            "xi_uncensored": float,
            "side": ("upper", "lower"),
            "noise_term": NOISE_TERMS,
            "backend": BACKENDS,  # no compiled path: "auto" and "numpy" run numpy, "numba" refuses
        },
        required=("xi_uncensored",),
        reads="latent",
    ),
)
