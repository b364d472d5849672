r"""Fading readings of a :class:`~tobitkf.NonlinearSystem`: the extended, sigma-point, Tobit and assumed-density
filters of :math:`y^*_k = \vartheta_k\odot h(x_k, k) + v_k`.

The channel is Rice fading of order 0 (Geng et al. 2017, (2) with :math:`L = 0`; docs/sources/geng2017-fading.md):
a random gain :math:`\vartheta_k(l)` per channel and step, independent over channels and time and of the state
and the noise, of mean :math:`\bar\vartheta_l` and variance :math:`\tilde\vartheta_l` (Assumption 2; any law of
:mod:`tobitkf.channels.laws`: the filters use its mean and variance), given as a
:class:`~tobitkf.RiceFading` of order 0. With a :class:`~tobitkf.Censoring` the faded reading is then censored
((3) of the source). A :class:`~tobitkf.RiceFading` of order L > 0, :math:`y^*_k = \sum_{s\le\min(L,k)}
\vartheta_k(s)\odot h(x_{k-s}, k-s) + v_k`, is read by every filter here through the window of past states
:math:`[x_k; \dots; x_{k-L}]` (:mod:`tobitkf.filters.nonlinear_fading_window`, with its equations; the numpy path
only); the rest of this docstring is order 0.

Every filter here is its unfaded counterpart of :mod:`tobitkf.filters.nonlinear` with the measurement moments of
:math:`h` under the prediction (:math:`\hat y`, :math:`P_{xy}`, :math:`P_{yy}`, by linearisation or sigma
points) replaced by those of the faded function :math:`\vartheta\odot h(x)`
(:mod:`tobitkf.filters._compiled_fading_moments`, the one definition both paths call):

.. math::

    \hat y_l \to \bar\vartheta_l\hat y_l, \qquad P_{xy,\cdot l} \to \bar\vartheta_lP_{xy,\cdot l}, \qquad
    P_{yy,ab} \to \bar\vartheta_a\bar\vartheta_bP_{yy,ab} + \delta_{ab}\tilde\vartheta_a(P_{yy,aa} + \hat y_a^2),

the source's :math:`H_k = \bar\theta_k\mathcal C_k` ((7)–(10); (21), (24)) applied to the linearised moments, plus
the fading variance in :math:`\Sigma_{\tilde y\tilde y}` ((25)–(26)). The update is then the unfaded filter's:

* :class:`FadingExtendedKalmanFilter`, :class:`FadingUnscentedKalmanFilter`: :math:`K = P_{xy}(P_{yy} + R)^{-1}`;
* :class:`FadingTobitExtendedKalmanFilter`, :class:`FadingTobitUnscentedKalmanFilter`: the Tobit update with the
  censored-normal statistics at :math:`\hat\chi = \bar\vartheta\odot\hat y` and :math:`\sigma_l = \sqrt{R_{ll}}`
  (Lemma 1, (6), (21)), the gain scale :math:`\bar\Upsilon`, the noise term of the Tobit filter plus
  :math:`\bar\gamma_l^2` times the fading variance: the TKF-FM of the source ((19)–(26)) on the linearised
  moments;
* :class:`FadingNonlinearAssumedDensityFilter`: channel by channel, the latent reading
  :math:`y^*_l \sim N(\bar\vartheta_l\hat y_l, \bar\vartheta_l^2P_{yy,ll} + \tilde\vartheta_l(P_{yy,ll} +
  \hat y_l^2) + R_{ll})` with covariance :math:`\bar\vartheta_lP_{xy,\cdot l}` with x, and the channel's exact
  moments of the latent reading given the reading (:class:`~tobitkf.FadingAssumedDensityFilter`'s update).

For a linear :math:`h = Cx` these are the linear fading filters exactly (tested): the extended and unscented
Kalman filters (m = 1) and the assumed-density filter are :class:`~tobitkf.FadingAssumedDensityFilter`
without and with censoring, the Tobit forms with ``fading_variance_term=False`` are
:class:`~tobitkf.FadingTobitKalmanFilter`. With :math:`\tilde\vartheta = 0` and :math:`\bar\vartheta = 1` each
is its unfaded filter.

**The fading variance** (``fading_variance_term``, default True): the source's filter leaves out
:math:`\tilde\vartheta` (docs/sources GF-04, over-confident); here the exact second moment under the prediction is
kept by default, as the fading assumed-density filter keeps it; ``False`` is the source's means-only form. (The
linear :class:`~tobitkf.FadingTobitKalmanFilter`'s option of that name takes the unconditional second moment
:math:`E[x_kx_k^T]` instead.) Only the standard covariance form (the Joseph form and the square-root form would
need the fading variance as a noise of their own).

Missing readings (NaN) take no part in the update. Time convention as every filter: :math:`y_1` at index 0,
result row k-1 holds :math:`\hat x_{k|k}`. With ``f`` and ``h`` numba-compiled the filters run in the compiled
nonlinear loop (:mod:`tobitkf.filters._compiled_nonlinear`), equal to the numpy path to rounding.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError, check_bool, check_instance
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading
from ..models.nonlinear import NonlinearSystem
from .nonlinear import (
    ExtendedKalmanFilter,
    TobitExtendedKalmanFilter,
    TobitUnscentedKalmanFilter,
    UnscentedKalmanFilter,
    _form,
)
from .nonlinear_adf import NonlinearAssumedDensityFilter
from .nonlinear_fading_window import FadingWindow

__all__ = [
    "FadingExtendedKalmanFilter",
    "FadingUnscentedKalmanFilter",
    "FadingTobitExtendedKalmanFilter",
    "FadingTobitUnscentedKalmanFilter",
    "FadingNonlinearAssumedDensityFilter",
    "fading_gains",
]


def fading_gains(system: Any, fading: Any, fading_variance_term: Any = True) -> np.ndarray:
    r"""The ``(2, m)`` array :math:`[\bar\vartheta; \tilde\vartheta]` of an order-0 :class:`~tobitkf.RiceFading`
    read by the filters of a :class:`~tobitkf.NonlinearSystem` (the variances zeroed without the fading
    variance term).

    Raises
    ------
    ValidationError
        ``fading`` not a RiceFading, of an order other than 0, or ``fading_variance_term`` not a bool.
    ShapeError
        A law whose channels do not match the system's m outputs.
    """
    check_instance(system, NonlinearSystem, "system")
    check_instance(fading, RiceFading, "fading")
    if fading.order != 0:
        raise ValidationError(
            f"fading: expected a RiceFading of order 0 for the gains of theta h(x_k) + v, got order L={fading.order} "
            "(the filters read a higher order through their window: tobitkf.filters.nonlinear_fading_window)"
        )
    fading.check(system.m)
    use_var = check_bool(fading_variance_term, "fading_variance_term")
    gm, gv = fading.mean_gains(system.m)[0], fading.var_gains(system.m)[0]
    if not (np.isfinite(gm).all() and np.isfinite(gv).all() and (gv >= 0).all()):  # a law of our own may slip
        raise ValidationError(f"fading: expected finite coefficient means and variances >= 0, got {gm}, {gv}")
    return np.ascontiguousarray(np.stack([gm, gv if use_var else np.zeros_like(gv)]))


def _fading_setup(est: Any, system: Any, fading: Any, fading_variance_term: Any) -> None:
    """The fading of a filter: the order-0 gains ``_fade`` (read by the compiled loop too) or, for an order
    L > 0, the window (:mod:`tobitkf.filters.nonlinear_fading_window`)."""
    check_instance(system, NonlinearSystem, "system")
    check_instance(fading, RiceFading, "fading")
    use_var = check_bool(fading_variance_term, "fading_variance_term")
    if fading.order == 0:
        est._fade = fading_gains(system, fading, use_var)
    else:
        fading.check(system.m)
    est._window_setup(system, fading, use_var)
    est.fading = fading
    est.fading_variance_term = use_var


def _faded_moments(fade: np.ndarray, yhat: Any, Pxy: Any, Pyy: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moments of the faded reading from those of ``h(x)`` (``yhat`` (N, r), ``Pxy`` (N, n, r), ``Pyy``
    (N, r, r); copies) and the gains' means and variances ``fade`` (2, r) (module docstring)."""
    yhat, Pxy, Pyy = (np.array(a, dtype=float, order="C") for a in (yhat, Pxy, Pyy))
    from ._compiled_fading_moments import fading_moments_batch  # numba is imported on first use

    fading_moments_batch(fade[0], fade[1], yhat, Pxy, Pyy)
    return yhat, Pxy, Pyy


class _FadingMoments(FadingWindow):
    """The faded measurement moments (module docstring) on top of a nonlinear filter's own."""

    _forms: tuple[str, ...] = ("standard",)  # the Joseph and square-root forms are refused
    _fade: np.ndarray  # (2, m): the coefficients' means and variances, read by the compiled loop too
    fading: RiceFading
    fading_variance_term: bool

    def _measurement_moments(self, k: int, xp: np.ndarray, Pp: np.ndarray, u: np.ndarray | None = None):
        if self._lags:
            return self._window_measurement(k, xp, Pp)
        yhat, Pxy, Pyy, H = super()._measurement_moments(k, xp, Pp, u)  # type: ignore[misc]
        yhat, Pxy, Pyy = _faded_moments(self._fade, yhat, Pxy, Pyy)
        return yhat, Pxy, Pyy, None if H is None else H * self._fade[0][:, None]

    def _fading_repr(self) -> str:
        return f"{self.fading!r}" + ("" if self.fading_variance_term else ", fading_variance_term=False")


class FadingExtendedKalmanFilter(_FadingMoments, ExtendedKalmanFilter):
    r"""The extended Kalman filter of fading readings :math:`y^* = \vartheta\odot h(x) + v` (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
    fading : RiceFading
        The law of the gains :math:`\vartheta` (its mean and variance per channel); of order L > 0 the filter
        carries the window :math:`[x_k; \dots; x_{k-L}]` (:mod:`tobitkf.filters.nonlinear_fading_window`; the
        numpy path, an ``h(x, k)`` without input, no smoother), and the state's ``aug_mean`` holds the
        fixed-lag estimates :math:`\hat x_{k-s|k}`.
    fading_variance_term : bool, default True
        Keep :math:`\tilde\vartheta(P_{yy} + \hat y^2)` in the innovation variance (False: the means only, as
        the source's filter).
    backend : {"auto", "numba", "numpy"}, default "auto"

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, ``fading`` not a RiceFading, an unknown option; an ``h(x, k, u)`` with
        fading of order L > 0; ``backend="numba"`` with order L > 0.
    ShapeError
        A fading law whose channels do not match the system.

    Examples
    --------
    A constant gain 0.5 halves the reading: the Kalman filter of C = 2 * 0.5.

    >>> import tobitkf as tk
    >>> sys = tk.NonlinearSystem(lambda x, k: x, lambda x, k: 2.0 * x, Q=[[0.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> out = tk.FadingExtendedKalmanFilter(sys, tk.RiceFading(0, [0.5])).filter([[2.0]])
    >>> round(float(out.mean[0, 0]), 12), round(float(out.cov[0, 0, 0]), 12)
    (1.0, 0.5)
    """

    _name = "FadingExtendedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        fading: RiceFading,
        *,
        fading_variance_term: bool = True,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        _fading_setup(self, system, fading, fading_variance_term)
        super().__init__(system, covariance_update=covariance_update, backend=backend)

    def __repr__(self) -> str:
        return f"FadingExtendedKalmanFilter({self.system!r}, {self._fading_repr()})"


class FadingUnscentedKalmanFilter(_FadingMoments, UnscentedKalmanFilter):
    r"""The sigma-point (unscented, cubature, Gauss–Hermite) Kalman filter of fading readings (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
    fading : RiceFading
        As :class:`FadingExtendedKalmanFilter` (any order L).
    rule, alpha, beta, kappa, order
        The sigma-point rule, as :class:`~tobitkf.UnscentedKalmanFilter`.
    fading_variance_term : bool, default True
        As :class:`FadingExtendedKalmanFilter`.
    backend : {"auto", "numba", "numpy"}, default "auto"

    Raises
    ------
    ValidationError, ShapeError
        As :class:`FadingExtendedKalmanFilter`, and an unknown rule or a bad parameter.
    """

    _name = "FadingUnscentedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        fading: RiceFading,
        *,
        rule: Any = "unscented",
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        fading_variance_term: bool = True,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        _fading_setup(self, system, fading, fading_variance_term)
        super().__init__(
            system, rule=rule, alpha=alpha, beta=beta, kappa=kappa, order=order,
            covariance_update=covariance_update, backend=backend,
        )  # fmt: skip

    def __repr__(self) -> str:
        return f"FadingUnscentedKalmanFilter({self.system!r}, {self._fading_repr()}, rule={self.rule!r})"


def _censoring(censoring: Any) -> Censoring:
    if censoring is None:
        return Censoring()
    check_instance(censoring, Censoring, "censoring")
    return censoring


class FadingTobitExtendedKalmanFilter(_FadingMoments, TobitExtendedKalmanFilter):
    r"""The Tobit extended Kalman filter of censored fading readings: the TKF-FM of Geng et al. 2017 on the
    linearised moments (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal with positive entries.
    fading : RiceFading
        As :class:`FadingExtendedKalmanFilter` (any order L).
    censoring : Censoring, optional
        The limits of the faded reading; default none.
    noise_term : {"dissertation", "total_variance", "exact_pv"}, default "dissertation"
        As :class:`~tobitkf.TobitExtendedKalmanFilter` (the default is the truncated variance (12) of the
        source).
    fading_variance_term : bool, default True
        As :class:`FadingExtendedKalmanFilter`; False is the source's filter.
    backend : {"auto", "numba", "numpy"}, default "auto"

    Raises
    ------
    ValidationError
        As :class:`FadingExtendedKalmanFilter`, ``censoring`` not a Censoring, R not diagonal or a variance not
        positive.

    Notes
    -----
    Extras: ``expected_y`` (..., T, m), the reading's mean :math:`\hat y_{k|k-1}` (21), and ``slope``
    (..., T, m), the probability :math:`\bar\gamma` of an uncensored reading (6).
    """

    _name = "FadingTobitExtendedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        fading: RiceFading,
        censoring: Censoring | None = None,
        *,
        noise_term: str | None = None,
        fading_variance_term: bool = True,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        _fading_setup(self, system, fading, fading_variance_term)
        super().__init__(
            system, _censoring(censoring), noise_term=noise_term, covariance_update=covariance_update, backend=backend
        )

    def __repr__(self) -> str:
        return (
            f"FadingTobitExtendedKalmanFilter({self.system!r}, {self._fading_repr()}, {self.channel!r}, "
            f"noise_term={self.noise_term!r})"
        )


class FadingTobitUnscentedKalmanFilter(_FadingMoments, TobitUnscentedKalmanFilter):
    r"""The Tobit update of censored fading readings on the sigma-point moments (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal with positive entries.
    fading : RiceFading
        As :class:`FadingExtendedKalmanFilter` (any order L).
    censoring : Censoring, optional
        The limits of the faded reading; default none.
    rule, alpha, beta, kappa, order
        The sigma-point rule, as :class:`~tobitkf.UnscentedKalmanFilter`.
    noise_term, fading_variance_term, backend
        As :class:`FadingTobitExtendedKalmanFilter`.

    Raises
    ------
    ValidationError, ShapeError
        As :class:`FadingTobitExtendedKalmanFilter`, and an unknown rule or a bad parameter.
    """

    _name = "FadingTobitUnscentedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        fading: RiceFading,
        censoring: Censoring | None = None,
        *,
        rule: Any = "unscented",
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        noise_term: str | None = None,
        fading_variance_term: bool = True,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        _fading_setup(self, system, fading, fading_variance_term)
        super().__init__(
            system, _censoring(censoring), rule=rule, alpha=alpha, beta=beta, kappa=kappa, order=order,
            noise_term=noise_term, covariance_update=covariance_update, backend=backend,
        )  # fmt: skip

    def __repr__(self) -> str:
        return (
            f"FadingTobitUnscentedKalmanFilter({self.system!r}, {self._fading_repr()}, {self.channel!r}, "
            f"rule={self.rule!r}, noise_term={self.noise_term!r}{_form(self)})"
        )


class FadingNonlinearAssumedDensityFilter(FadingWindow, NonlinearAssumedDensityFilter):
    r"""The assumed-density filter of fading readings of a nonlinear model, through a channel (module docstring).

    Channel by channel, the faded reading's moments under the sigma-point linearisation give the Gaussian latent
    reading, and the channel's exact moments given the reading the projection (for censoring, the linear
    :class:`~tobitkf.FadingAssumedDensityFilter`'s update, which it equals for a linear h). With
    ``iterations > 1`` the linearisation of the faded function is redone about the posterior.

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal, entries >= 0.
    fading : RiceFading
        As :class:`FadingExtendedKalmanFilter` (any order L).
    channel : Channel, optional
        What happens to the faded reading (a :class:`~tobitkf.Censoring`, a :class:`~tobitkf.Quantizer`, a
        channel of your own with ``region`` or ``reading_moments``); default no censoring.
    rule, alpha, beta, kappa, order, iterations, backend
        As :class:`~tobitkf.NonlinearAssumedDensityFilter`.
    fading_variance_term : bool, default True
        As :class:`FadingExtendedKalmanFilter`.

    Raises
    ------
    ValidationError, ShapeError
        As :class:`~tobitkf.NonlinearAssumedDensityFilter` and :class:`FadingExtendedKalmanFilter`.

    Notes
    -----
    Extras: ``log_likelihood`` (..., T), as :class:`~tobitkf.NonlinearAssumedDensityFilter`'s.
    """

    _name = "FadingNonlinearAssumedDensityFilter"
    _forms = ("standard",)
    _fade: np.ndarray  # (2, m), as _FadingMoments'
    fading: RiceFading
    fading_variance_term: bool

    def __init__(
        self,
        system: NonlinearSystem,
        fading: RiceFading,
        channel: Any = None,
        *,
        rule: Any = "unscented",
        iterations: int = 1,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        fading_variance_term: bool = True,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        _fading_setup(self, system, fading, fading_variance_term)
        super().__init__(
            system, Censoring() if channel is None else channel, rule=rule, iterations=iterations, alpha=alpha,
            beta=beta, kappa=kappa, order=order, covariance_update=covariance_update, backend=backend,
        )  # fmt: skip

    def _channel_moments(self, l: int, rule: Any, h_l: Any, xm: np.ndarray, Pm: np.ndarray):
        ybar, Pxy, Pyy = super()._channel_moments(l, rule, h_l, xm, Pm)
        if self._lags:  # h_l is channel l's stacked map over the window
            return self._window_channel(l, ybar, Pxy, Pyy)
        return _faded_moments(np.ascontiguousarray(self._fade[:, l : l + 1]), ybar, Pxy, Pyy)

    def __repr__(self) -> str:
        extra = "" if self.fading_variance_term else ", fading_variance_term=False"
        return (
            f"FadingNonlinearAssumedDensityFilter({self.system!r}, {self.fading!r}, {self.channel!r}, "
            f"rule={self.rule!r}{self._iterations_repr()}{extra})"
        )
