r"""Fixed-interval (Rauch–Tung–Striebel) and fixed-lag smoothing on the estimation core.

Model: the package's :class:`~tobitkf.LinearSystem`, readings :math:`y_1..y_T` (row k-1). The
Rauch–Tung–Striebel backward pass over a Gaussian filter's filtered and predicted moments, with its
equations, is :func:`~tobitkf.filters.smoothing.rts_smooth`, defined with the filters that take it
(their ``smooth`` method); this module runs it for a model (:func:`smooth`) and online
(:class:`FixedLagSmoother`).

Which smoother goes with which filter (:func:`smooth`):

* ``"kalman"``: the KF's moments: the exact posterior of the linear Gaussian model (missing readings
  skipped); equal to the brute-force stacked Gaussian posterior (tested);
* ``"dropping"``: the KF that drops censored readings;
* ``"tobit"``: the TKF's linearisation :math:`H = E(\mathbf p)C` (Miller (3.39)–(3.40)): the TKF's
  filtered and predicted moments in the same backward pass;
* ``"adf"``: the assumed-density filter's exact-moment projection (:class:`~tobitkf.AssumedDensityTobitFilter`,
  the uncensored readings of a step first, :func:`~tobitkf.filters.assumed_density.assumed_density_filter`) with
  the Gaussian backward pass, the "ADF-RTS" (assumed-density) smoother (Deisenroth & Ohlsson 2011's
  Gaussian smoother with exact moments). For a censored regression with AR errors the exact posterior
  is :func:`tobitkf.inference.censored_ar.posterior_moments`.

Output: the :class:`~tobitkf.FilterResult` of :func:`~tobitkf.filters.smoothing.rts_smooth` (smoothed moments,
``extras`` with the lag-one ``cross_cov``, ``initial_mean``/``initial_cov``, ``filtered_mean``/``filtered_cov``
and the gains ``gain``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..channels.censoring import Censoring
from ..filters.assumed_density import assumed_density_filter
from ..filters.core import FilterResult, FilterState, prepare_measurements
from ..filters.kalman import DroppingKalmanFilter, KalmanFilter, dropping_with_indicator
from ..filters.smoothing import rts_smooth, rts_step
from ..filters.tobit import TobitKalmanFilter, check_tobit_indicator
from ..models.linear import LinearSystem

__all__ = [
    "rts_smooth",
    "smooth",
    "SMOOTHERS",
    "FixedLagSmoother",
    "FixedLagState",
    "dropping_with_indicator",
    "check_tobit_indicator",
]

SMOOTHERS = ("kalman", "dropping", "tobit", "adf")


def _filter_for(system: LinearSystem, method: str, censoring: Censoring | None):
    if method == "kalman":
        return KalmanFilter(system, backend="numpy")
    if censoring is None:
        raise ValidationError(f"censoring: method {method!r} needs the censoring limits")
    if method == "dropping":
        return DroppingKalmanFilter(system, censoring, backend="numpy")
    if method == "tobit":
        return TobitKalmanFilter(system, censoring, backend="numpy")
    return assumed_density_filter(system, censoring)


def smooth(
    system: LinearSystem,
    y: Any,
    *,
    censoring: Censoring | None = None,
    censored: Any = None,
    method: str = "auto",
    u: Any = None,
    x0: Any = None,
    P0: Any = None,
    times: Any = None,
    grid: Any = None,
    start: Any = None,
) -> FilterResult:
    r"""Fixed-interval smoothing of readings ``y`` (..., T, m): :math:`\hat x_{k|T}`, :math:`P_{k|T}` and the
    lag-one cross-covariances.

    Parameters
    ----------
    system : LinearSystem
        The model.
    y : (..., T, m) array_like
        Readings; NaN = missing; censored readings hold their limit.
    censoring : Censoring, optional
        The limits (needed by every method but ``"kalman"``).
    censored : (..., T, m) bool array_like, optional
        The recorded censoring indicator (``"dropping"`` and ``"adf"``; the TKF's update does
        not depend on it, a flagged reading is checked to lie at its limit); default the limit rule.
    method : {"auto", "kalman", "dropping", "tobit", "adf"}, default "auto"
        The filter whose smoother runs (module docstring); ``"auto"``: ``"kalman"`` without
        ``censoring``, else ``"adf"``.
    u : (..., T, p) array_like, optional
        Known inputs.
    x0, P0 : array_like, optional
        Override the system's prior.
    times : (T,) array_like, optional
        Sample times (floats or dates) for a :class:`~tobitkf.ContinuousLinearSystem`: each gap
        discretised exactly, the prior at ``start`` (default: the first sample or grid time).
    grid : (G,) array_like, optional
        With ``times``: the times at which the state is returned (merged into the sample times as
        missing readings; ``u`` then given on the grid). See
        :func:`~tobitkf.filters._times.smooth_on_grid`.

    Returns
    -------
    FilterResult
        See the module docstring (with ``grid``: the rows of the grid); for ``"adf"`` also the filter's ``extras["log_likelihood"]`` (..., T)
        and ``extras["side"]`` (..., T, m).

    Raises
    ------
    ValidationError
        Unknown method, a censored method without ``censoring``, and the filters' own input errors.

    Examples
    --------
    Without censoring the smoother at the last reading is the filter:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[1.0]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.3], [np.nan], [1.2]])
    >>> sm = tk.smooth(sys, y)
    >>> bool(np.isclose(sm.mean[-1, 0], tk.KalmanFilter(sys).filter(y).mean[-1, 0]))
    True
    """
    check_instance(system, LinearSystem, "system")
    if method == "auto":
        method = "kalman" if censoring is None else "adf"
    if method not in SMOOTHERS:
        raise ValidationError(f"method: expected one of {', '.join(('auto',) + SMOOTHERS)}, got {method!r}")
    if censoring is not None:
        check_instance(censoring, Censoring, "censoring")
    est = _filter_for(system, method, censoring)
    if times is not None or grid is not None or start is not None:
        if method == "tobit" and censored is not None:
            assert censoring is not None, "_filter_for refuses the tobit method without censoring"
            check_tobit_indicator(censoring, y, censored)
        recorded = censored if method in ("adf", "dropping") else None
        return est.smooth(y, u=u, censored=recorded, x0=x0, P0=P0, times=times, grid=grid, start=start)
    if method == "adf":
        res = est.filter(y, u=u, censored=censored, x0=x0, P0=P0)
    elif method == "dropping" and censored is not None:
        res = dropping_with_indicator(est, y, censored, u=u, x0=x0, P0=P0)
    else:
        if method == "tobit" and censored is not None:
            assert censoring is not None, "_filter_for refuses the tobit method without censoring"
            check_tobit_indicator(censoring, y, censored)
        res = est.filter(y, u=u, x0=x0, P0=P0)
    return rts_smooth(res, system, x0=x0, P0=P0)


# --------------------------------------------------------------------------- fixed lag (online)


@dataclass(frozen=True, eq=False)
class FixedLagState:
    r"""State of a :class:`FixedLagSmoother`: the filter's state and the window of the last ``lag`` steps.

    Attributes
    ----------
    filter_state : FilterState
        The underlying filter's state after the last reading.
    window : tuple
        Per step of the window, oldest first: ``(k, x_{k|k}, P_{k|k}, x̄_{k|k-1}, P̄_{k|k-1})``.
    """

    filter_state: FilterState
    window: tuple = field(default_factory=tuple)

    @property
    def k(self) -> int:
        """Time index of the last reading."""
        return self.filter_state.k


class FixedLagSmoother:
    r"""Fixed-lag smoother on the online API: after reading :math:`y_K`, the estimate :math:`\hat x_{K-L|K}`.

    Runs the estimator's ``predict`` and ``step`` (any Gaussian filter on a
    :class:`~tobitkf.LinearSystem`: KF, TKF, dropping KF, the ADF) one reading at a time and keeps the
    last L+1 filtered and predicted moments; :meth:`estimate` runs the RTS backward pass over that
    window (O(L n³) per reading), which is exactly the fixed-interval smoother of :math:`y_{1:K}` at
    lag L (Särkkä 2013, §8.6: fixed-lag smoothing as a windowed RTS).

    Parameters
    ----------
    estimator : GaussianFilter
        A filter with ``system``, ``init``, ``predict`` and ``step``.
    lag : int
        L >= 0 (0 is the filter).

    Raises
    ------
    ValidationError
        An estimator without that API, a negative or non-integer lag.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.inference import FixedLagSmoother
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[1.0]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> fl = FixedLagSmoother(tk.KalmanFilter(sys), lag=2)
    >>> st = fl.init()
    >>> for r in ([0.3], [0.1], [1.2]):
    ...     st = fl.step(st, r)
    >>> k, mean, cov = fl.estimate(st)                 # x_{1|3}
    >>> bool(np.isclose(mean[0], tk.smooth(sys, [[0.3], [0.1], [1.2]]).mean[0, 0])), k
    (True, 1)
    """

    def __init__(self, estimator: Any, lag: int):
        if not all(hasattr(estimator, a) for a in ("system", "init", "predict", "step")):
            raise ValidationError("estimator: expected a Gaussian filter on a LinearSystem (KF, TKF, dropping KF, ADF)")
        if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
            raise ValidationError(f"lag: expected an integer >= 0, got {lag!r}")
        self.estimator, self.lag = estimator, int(lag)

    def init(self, batch_shape: Any = (), **kw: Any) -> FixedLagState:
        """The prior (the estimator's ``init``); the window starts with the prior as step 0."""
        st = self.estimator.init(batch_shape, **kw)
        return FixedLagState(filter_state=st, window=((st.k, st.x, st.P, None, None),))

    def step(self, state: FixedLagState, y: Any, *, u: Any = None, **options: Any) -> FixedLagState:
        """One reading: the filter's prediction and step, the window advanced (``options`` go to the step)."""
        if not isinstance(state, FixedLagState):
            raise ValidationError(
                f"state: expected a FixedLagState (from init() or step()), got {type(state).__name__}"
            )
        pred = self.estimator.predict(state.filter_state, u=u)
        new = self.estimator.step(state.filter_state, y, u=u, **options)
        window = state.window + ((new.k, new.x, new.P, pred.x, pred.P),)
        return FixedLagState(filter_state=new, window=window[-(self.lag + 1) :])

    def _window_pass(self, win: tuple) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """RTS over the window: ``(k, x_{k|K}, P_{k|K})`` for every step of it, newest first."""
        x, P = win[-1][1], win[-1][2]
        out = [(win[-1][0], x, P)]
        A_of = self.estimator.system.transition
        for j in range(len(win) - 2, -1, -1):
            kj, xf, Pf = win[j][0], win[j][1], win[j][2]
            x, P, _ = rts_step(A_of(kj), xf, Pf, win[j + 1][3], win[j + 1][4], x, P)
            out.append((kj, x, P))
        return out

    def _shape(self, st: FilterState, x: np.ndarray, P: np.ndarray):
        n, b = st.n, st.batch_shape
        P = np.broadcast_to(P, (st.runs,) + P.shape[1:])
        return x[:, :n].reshape(b + (n,)), P[:, :n, :n].reshape(b + (n, n))

    def estimate(self, state: FixedLagState):
        r"""``(k, mean, cov)``: :math:`\hat x_{k|K}`, :math:`P_{k|K}` for k = K - L (or the oldest step of the
        window), K the last reading; shapes ``batch_shape + (n,)`` and ``batch_shape + (n, n)``."""
        k, x, P = self._window_pass(state.window)[-1]
        return (k,) + self._shape(state.filter_state, x, P)

    def run(self, y: Any, *, u: Any = None) -> FilterResult:
        r"""All readings ``y`` (T, m) of one run: ``mean``/``cov`` row k-1 holds :math:`\hat x_{k|\min(k+L, T)}`
        (the lagged estimates; the last L steps from the backward pass over the final window)."""
        y2, batch = prepare_measurements(y, self.estimator.m)
        if batch != ():
            raise ValidationError("y: FixedLagSmoother.run takes one run (T, m); use step() for batches")
        T = y2.shape[1]
        st = self.init()
        n = st.filter_state.n
        mean, cov = np.empty((T, n)), np.empty((T, n, n))
        u2 = None if u is None else np.asarray(u, dtype=float)
        for i in range(T):
            st = self.step(st, y2[0, i], u=None if u2 is None else u2[i])
            k, mk, Pk = self.estimate(st)
            if k >= 1:
                mean[k - 1], cov[k - 1] = mk, Pk
        for k, x, P in self._window_pass(st.window):
            if k >= 1:
                mean[k - 1], cov[k - 1] = self._shape(st.filter_state, x, P)
        return FilterResult(
            mean=mean,
            cov=cov,
            pred_mean=None,
            pred_cov=None,
            extras={"lag": self.lag},
            times=np.arange(1, T + 1),
            final=st.filter_state,
        )
