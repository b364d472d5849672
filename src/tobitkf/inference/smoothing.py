r"""Fixed-interval (Rauch–Tung–Striebel) and fixed-lag smoothing on the estimation core.

Model: the package's :class:`~tobitkf.LinearSystem`,
:math:`x_k = A_{k-1}x_{k-1} + B^u_ku_k + w_{k-1}`, :math:`w_{k-1} \sim N(0, B Q B^T)`, prior
:math:`x_0 \sim N(\bar x_0, P_0)`, readings :math:`y_1..y_T` (row k-1).

The RTS backward pass (Rauch, Tung & Striebel 1965; Särkkä 2013, Theorem 8.2) runs on any Gaussian
filter's filtered and predicted moments, :math:`\hat x_{k|k}, P_{k|k}` and
:math:`\bar x_{k+1|k}, \bar P_{k+1|k}`:

.. math::

    J_k &= P_{k|k}A_k^T\bar P_{k+1|k}^{-1} \\
    \hat x_{k|T} &= \hat x_{k|k} + J_k(\hat x_{k+1|T} - \bar x_{k+1|k}) \\
    P_{k|T} &= P_{k|k} + J_k(P_{k+1|T} - \bar P_{k+1|k})J_k^T \\
    P_{k+1,k|T} &= \mathrm{Cov}(x_{k+1}, x_k \mid y_{1:T}) = P_{k+1|T}J_k^T

for k = T-1, ..., 0 (k = 0 is the prior: :math:`\hat x_{0|0} = \bar x_0`, :math:`P_{0|0} = P_0`). A
singular :math:`\bar P_{k+1|k}` (a singular Q after an exact reading, R = 0) takes the pseudo-inverse
(:func:`~tobitkf.inference._common.solve_psd`).

Which smoother goes with which filter (:func:`smooth`):

* ``"kalman"``: the KF's moments: the exact posterior of the linear Gaussian model (missing readings
  skipped); equal to the brute-force stacked Gaussian posterior (tested);
* ``"dropping"``: the KF that drops censored readings;
* ``"tobit"``: the TKF's linearisation :math:`H = E(\mathbf p)C` (Miller (3.39)–(3.40)): the TKF's
  filtered and predicted moments in the same backward pass;
* ``"adf"``: the assumed-density filter's exact-moment projection (:class:`~tobitkf.AssumedDensityTobitFilter`,
  the uncensored readings of a step first, :func:`~tobitkf.inference._common.assumed_density_filter`) with
  the Gaussian backward pass, the "ADF-RTS" (assumed-density) smoother (Deisenroth & Ohlsson 2011's
  Gaussian smoother with exact moments). For a censored regression with AR errors the exact posterior
  is :func:`tobitkf.inference.censored_ar.posterior_moments`.

Output: a :class:`~tobitkf.FilterResult` whose ``mean``/``cov`` are :math:`\hat x_{k|T}`,
:math:`P_{k|T}` (row k-1 for k = 1..T), ``pred_mean``/``pred_cov`` the filter's predictions, and
``extras``: ``cross_cov`` (..., T, n, n), row k-1 holding :math:`P_{k,k-1|T}` (row 0:
:math:`\mathrm{Cov}(x_1, x_0 \mid y_{1:T})`); ``initial_mean`` (..., n) and ``initial_cov`` (..., n, n),
:math:`\hat x_{0|T}`, :math:`P_{0|T}`; ``filtered_mean``, ``filtered_cov``; ``gain`` (..., T, n, n),
row k holding :math:`J_k` (row 0: :math:`J_0`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, overload

import numpy as np

from .._validation import ValidationError, check_instance
from ..channels.censoring import Censoring
from ..filters.core import FilterResult, FilterState, check_prior, prepare_measurements
from ..models.linear import LinearSystem
from ._common import solve_psd

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


@overload
def _flat(a: np.ndarray, N: int, tail: int) -> np.ndarray: ...
@overload
def _flat(a: np.ndarray | None, N: int, tail: int) -> np.ndarray | None: ...
def _flat(a: np.ndarray | None, N: int, tail: int) -> np.ndarray | None:
    """(batch..., T, *core) -> (N or 1, T, *core) without copying a broadcast shared covariance."""
    if a is None:
        return None
    a = np.asarray(a)
    core = a.shape[a.ndim - tail :]
    lead = a.shape[: a.ndim - tail]
    if len(lead) == 1:  # one run: (T, ...)
        return a[None]
    strides = a.strides[: len(lead) - 1]
    if N > 1 and all(s == 0 for s in strides):  # one covariance shared by every run
        return a[(0,) * (len(lead) - 1)][None]
    return a.reshape((N,) + lead[-1:] + core)


def rts_smooth(
    filtered: FilterResult,
    transition: Callable[[int], np.ndarray] | LinearSystem,
    *,
    x0: Any = None,
    P0: Any = None,
    k0: int = 0,
) -> FilterResult:
    r"""The RTS backward pass over a Gaussian filter's result (see the module docstring).

    Parameters
    ----------
    filtered : FilterResult
        A filter's result with ``mean``, ``cov``, ``pred_mean`` and ``pred_cov`` recorded
        (``outputs="all"``), (..., T, n) and (..., T, n, n).
    transition : LinearSystem or callable
        :math:`A_k` as a function of k (x_{k+1} = A_k x_k), or the system (its ``transition``); also
        the source of the prior when ``x0``/``P0`` are not given.
    x0, P0 : array_like, optional
        The prior :math:`\bar x_0` (..., n), :math:`P_0` (..., n, n) the filter started from (default:
        the system's).
    k0 : int, default 0
        Time index of the prior (the filter's ``state.k`` before the first reading).

    Returns
    -------
    FilterResult
        ``mean`` :math:`\hat x_{k|T}`, ``cov`` :math:`P_{k|T}`, ``extras`` with ``cross_cov``,
        ``initial_mean``, ``initial_cov``, ``filtered_mean``, ``filtered_cov``, ``gain``; ``times``
        as the filter's.

    Raises
    ------
    ValidationError
        The result lacks the predicted or filtered moments, or no prior is available.
    """
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        if getattr(filtered, name) is None:
            raise ValidationError(f"filtered: the result has no {name!r}; run the filter with outputs='all'")
    assert filtered.pred_mean is not None and filtered.cov is not None and filtered.pred_cov is not None
    system = transition if isinstance(transition, LinearSystem) else None
    A_of = system.transition if system is not None else transition
    if not callable(A_of):
        raise ValidationError("transition: expected a LinearSystem or a callable k -> A_k")
    mean = np.asarray(filtered.mean)
    batch, (T, n) = mean.shape[:-2], mean.shape[-2:]
    N = int(np.prod(batch, dtype=int))
    xf = _flat(mean, N, 1)
    xp = _flat(filtered.pred_mean, N, 1)
    Pf = _flat(filtered.cov, N, 2)
    Pp = _flat(filtered.pred_cov, N, 2)
    if x0 is None or P0 is None:
        if system is None:
            raise ValidationError("x0/P0: give the prior the filter started from (or pass the system)")
    if system is not None:
        xa, Pa = check_prior(system, x0, P0, N, batch)
    else:
        xa = np.broadcast_to(np.asarray(x0, dtype=float), (N, n)).copy()
        Pa = np.broadcast_to(np.asarray(P0, dtype=float), (N, n, n)).copy()
    if np.all(Pa == Pa[:1]):
        Pa = Pa[:1]
    shared = Pf.shape[0] == 1 and Pp.shape[0] == 1 and Pa.shape[0] == 1
    Nc = 1 if shared else N
    xs = np.empty((N, T, n))
    Ps = np.empty((Nc, T, n, n))
    cross = np.empty((Nc, T, n, n))
    gain = np.empty((Nc, T, n, n))
    xs[:, -1] = xf[:, -1]
    Ps[:, -1] = Pf[:, -1]
    for i in range(T - 1, -1, -1):
        A = np.asarray(A_of(k0 + i), dtype=float)  # x_{k0+i+1} = A x_{k0+i}
        if i > 0:
            xfi, Pfi = xf[:, i - 1], Pf[:, i - 1]
        else:
            xfi, Pfi = xa, Pa
        Ppi = Pp[:, i]
        Jt = solve_psd(np.broadcast_to(Ppi, (max(Ppi.shape[0], Pfi.shape[0]),) + Ppi.shape[1:]), A @ Pfi)
        J = np.swapaxes(Jt, -1, -2)  # (Nc, n, n)
        gain[:, i] = J
        xn = xfi + np.einsum("...ij,...j->...i", J, xs[:, i] - xp[:, i])
        Pn = Pfi + J @ (Ps[:, i] - Ppi) @ Jt
        Pn = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
        cross[:, i] = Ps[:, i] @ Jt
        if i > 0:
            xs[:, i - 1] = xn
            Ps[:, i - 1] = Pn
        else:
            x_init, P_init = xn, Pn

    def out(a: np.ndarray, tail: int) -> np.ndarray:
        if a.shape[0] == 1 and N != 1:
            return np.broadcast_to(a[0], batch + a.shape[1:])
        return a.reshape(batch + a.shape[1:])

    extras = dict(filtered.extras)
    extras.update(
        {
            "cross_cov": out(cross, 3),
            "gain": out(gain, 3),
            "initial_mean": out(x_init, 1),
            "initial_cov": out(P_init, 2),
            "filtered_mean": filtered.mean,
            "filtered_cov": filtered.cov,
        }
    )
    return FilterResult(
        mean=out(xs, 2),
        cov=out(Ps, 3),
        pred_mean=filtered.pred_mean,
        pred_cov=filtered.pred_cov,
        extras=extras,
        times=filtered.times,
        final=filtered.final,
    )


def _filter_for(system: LinearSystem, method: str, censoring: Censoring | None):
    from ..filters.kalman import DroppingKalmanFilter, KalmanFilter
    from ..filters.tobit import TobitKalmanFilter
    from ._common import assumed_density_filter

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

    Returns
    -------
    FilterResult
        See the module docstring; for ``"adf"`` also the filter's ``extras["log_likelihood"]`` (..., T)
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


def dropping_with_indicator(est, y, censored, *, u=None, x0=None, P0=None, outputs="all", state=None) -> FilterResult:
    r"""The dropping KF ``est`` with the recorded censoring indicator instead of its limit rule.

    Flagged readings (checked to lie at or beyond a limit, see
    :func:`~tobitkf.inference._common.censoring_sides`) are left out of the update exactly as missing
    ones; an unflagged reading at the limit is used. Runs a :class:`~tobitkf.KalmanFilter` with the
    estimator's options on the readings with the flagged ones set to NaN; ``extras["censored"]`` holds the
    flags. Called by :meth:`tobitkf.DroppingKalmanFilter.filter` when ``censored`` is given.
    """
    from ..filters.kalman import KalmanFilter
    from ._common import censoring_sides

    y2, batch = prepare_measurements(y, est.system.m)
    k0 = 0 if state is None else state.k
    lo, hi = est.censoring.all_limits(y2.shape[1], est.system.m, start=k0 + 1)
    arr = np.asarray(censored)
    try:
        c2 = np.broadcast_to(arr, batch + y2.shape[1:]).reshape(y2.shape)
    except ValueError:
        from .._validation import ShapeError

        raise ShapeError(f"censored: expected the shape of y {batch + y2.shape[1:]}, got {arr.shape}") from None
    side = censoring_sides(y2, lo, hi, c2, rtol=est.rtol)
    ym = np.where(side != 0, np.nan, y2).reshape(batch + y2.shape[1:])
    kf = KalmanFilter(est.system, covariance_update=est.covariance_update, backend=est.backend)
    res = kf.filter(ym, u=u, x0=x0, P0=P0, outputs=outputs, state=state)
    extras = dict(res.extras)
    if res.mean is not None or outputs == "all" or "extras" in (outputs or ()):
        extras["censored"] = (side != 0).reshape(batch + y2.shape[1:])
    return FilterResult(
        mean=res.mean,
        cov=res.cov,
        pred_mean=res.pred_mean,
        pred_cov=res.pred_cov,
        extras=extras,
        times=res.times,
        var=res.var,
        final=res.final,
    )


def check_tobit_indicator(censoring: Censoring, y: Any, censored: Any, *, start: int = 1) -> None:
    r"""Check a recorded indicator against the TKF's readings: a flagged reading must lie at (or beyond) a
    limit. The TKF's update (Miller (3.37)-(3.41)) is linear in the reading and does not branch on it,
    so an unflagged reading at the limit needs nothing else. Called by
    :meth:`tobitkf.TobitKalmanFilter.filter` when ``censored`` is given.

    Raises
    ------
    ShapeError, ValidationError
        See :func:`~tobitkf.inference._common.censoring_sides`.
    """
    from ._common import censoring_sides

    arr = np.asarray(y, dtype=float)
    y2 = arr.reshape((-1,) + arr.shape[-2:])
    lo, hi = censoring.all_limits(y2.shape[1], y2.shape[2], start=start)
    try:
        c2 = np.broadcast_to(np.asarray(censored), arr.shape).reshape(y2.shape)
    except ValueError:
        from .._validation import ShapeError

        raise ShapeError(f"censored: expected the shape of y {arr.shape}, got {np.shape(censored)}") from None
    censoring_sides(y2, lo, hi, c2)


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
            xp, Pp = win[j + 1][3], win[j + 1][4]
            Jt = solve_psd(np.broadcast_to(Pp, (max(Pp.shape[0], Pf.shape[0]),) + Pp.shape[1:]), A_of(kj) @ Pf)
            J = np.swapaxes(Jt, -1, -2)
            x = xf + np.einsum("...ij,...j->...i", J, x - xp)
            P = Pf + J @ (P - Pp) @ Jt
            P = 0.5 * (P + np.swapaxes(P, -1, -2))
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
