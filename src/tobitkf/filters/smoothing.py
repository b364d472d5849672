r"""The Rauch–Tung–Striebel backward pass over a Gaussian filter's result, and the filters' ``smooth`` /
``log_likelihood`` methods, defined once.

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
(:func:`solve_psd`).

The Gaussian filters of this package (:class:`~tobitkf.KalmanFilter`, :class:`~tobitkf.DroppingKalmanFilter`,
:class:`~tobitkf.TobitKalmanFilter`, :class:`~tobitkf.AssumedDensityTobitFilter`) take :class:`SmoothingMethods`:
``smooth`` runs the filter and this backward pass over its moments, ``log_likelihood`` sums the filter's
per-step terms (:meth:`SmoothingMethods._log_likelihood_terms`, which each filter defines); the dropping KF, the
TKF and the assumed-density filter take their ``filter`` with the recorded indicator from
:class:`IndicatorFilterMethods`. The model-level entry points (:func:`tobitkf.smooth`,
:func:`tobitkf.log_likelihood`) live in :mod:`tobitkf.inference`, which builds on this module: the imports run
one way, the filters below the inference.

Output of :func:`rts_smooth`: a :class:`~tobitkf.FilterResult` whose ``mean``/``cov`` are :math:`\hat x_{k|T}`,
:math:`P_{k|T}` (row k-1 for k = 1..T), ``pred_mean``/``pred_cov`` the filter's predictions, and
``extras``: ``cross_cov`` (..., T, n, n), row k-1 holding :math:`P_{k,k-1|T}` (row 0:
:math:`\mathrm{Cov}(x_1, x_0 \mid y_{1:T})`); ``initial_mean`` (..., n) and ``initial_cov`` (..., n, n),
:math:`\hat x_{0|T}`, :math:`P_{0|T}`; ``filtered_mean``, ``filtered_cov``; ``gain`` (..., T, n, n),
row k holding :math:`J_k` (row 0: :math:`J_0`).
"""

from __future__ import annotations

from typing import Any, Callable, overload

import numpy as np

from .._validation import ValidationError
from ..models.linear import LinearSystem
from ._times import at_times, smooth_on_grid
from .core import FilterResult, FilterState, check_prior

__all__ = ["rts_smooth", "rts_step", "solve_psd", "SmoothingMethods", "IndicatorFilterMethods"]


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
        xn, Pn, Jt = rts_step(A, xfi, Pfi, xp[:, i], Pp[:, i], xs[:, i], Ps[:, i])
        gain[:, i] = np.swapaxes(Jt, -1, -2)  # (Nc, n, n)
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


def rts_step(
    A: np.ndarray,
    x_filt: np.ndarray,
    P_filt: np.ndarray,
    x_pred: np.ndarray,
    P_pred: np.ndarray,
    x_next: np.ndarray,
    P_next: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""One step of the RTS backward pass (the module docstring's equations), batched over runs.

    Parameters
    ----------
    A : (n, n) :math:`A_k` ; x_filt : (N, n) :math:`\hat x_{k|k}` ; P_filt : (N or 1, n, n) :math:`P_{k|k}`
    x_pred : (N, n) :math:`\bar x_{k+1|k}` ; P_pred : (N or 1, n, n) :math:`\bar P_{k+1|k}`
    x_next : (N, n) :math:`\hat x_{k+1|T}` ; P_next : (N or 1, n, n) :math:`P_{k+1|T}`

    Returns
    -------
    x : (N, n) :math:`\hat x_{k|T}` ; P : (N or 1, n, n) :math:`P_{k|T}` (symmetrised) ;
    Jt : (N or 1, n, n) :math:`J_k^T` (the cross-covariance is :math:`P_{k+1|T}J_k^T`)
    """
    Jt = solve_psd(np.broadcast_to(P_pred, (max(P_pred.shape[0], P_filt.shape[0]),) + P_pred.shape[1:]), A @ P_filt)
    J = np.swapaxes(Jt, -1, -2)
    x = x_filt + np.einsum("...ij,...j->...i", J, x_next - x_pred)
    P = P_filt + J @ (P_next - P_pred) @ Jt
    return x, 0.5 * (P + np.swapaxes(P, -1, -2)), Jt


def solve_psd(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    r""":math:`S^{-1}B` for symmetric PSD ``S`` (..., n, n), ``B`` (..., n, r), batched.

    A Cholesky factorization certifies a positive definite ``S`` (then an LU solve); a singular
    ``S`` (a predicted covariance :math:`AP A^T + Q` with a singular Q after an exact reading) takes
    the pseudo-inverse, which is what the RTS gain needs: the range of :math:`A P` lies in the range
    of :math:`APA^T + Q`.
    """
    try:
        np.linalg.cholesky(S)
        return np.linalg.solve(S, B)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, -1, -2)))
        cut = 1e-12 * np.maximum(np.abs(w).max(axis=-1, keepdims=True), np.finfo(float).tiny)
        inv_w = np.where(w > cut, 1.0 / np.where(w > cut, w, 1.0), 0.0)
        return V @ (inv_w[..., :, None] * (np.swapaxes(V, -1, -2) @ B))


class SmoothingMethods:
    """``smooth`` and ``log_likelihood`` of a Gaussian filter, written once for every filter that takes it.

    The filter supplies ``system``, ``filter(y, *, u, x0, P0, [censored], ...)`` and
    :meth:`_log_likelihood_terms`; ``censored`` (the recorded indicator) is passed on only when given,
    so a filter whose ``filter`` takes none refuses it with a ``TypeError`` as before.
    """

    system: LinearSystem
    filter: Callable[..., FilterResult]

    def smooth(
        self,
        y: Any,
        *,
        u: Any = None,
        censored: Any = None,
        x0: Any = None,
        P0: Any = None,
        times: Any = None,
        grid: Any = None,
        start: Any = None,
    ) -> FilterResult:
        r"""Fixed-interval (RTS) smoother of ``y`` (..., T, m) over this filter's moments, with lag-one
        cross-covariances: :func:`rts_smooth` over ``self.filter(y, ...)`` (for the TKF its linearisation
        :math:`H = E(\mathbf p)C`; for the dropping KF the censored readings dropped; for the assumed-density
        filter with ``order="uncensored_first"`` it is ``tk.smooth(..., method="adf")``).

        Parameters
        ----------
        y : (..., T, m) array_like
        u : (..., T, p) array_like, optional
        censored : (..., T, m) bool array_like, optional
            The recorded censoring indicator, for the filters whose ``filter`` takes one.
        x0, P0 : array_like, optional
            Override the system's prior.
        times : (T,) array_like, optional
            Sample times of the readings (floats or dates), for a :class:`~tobitkf.ContinuousLinearSystem`:
            each gap discretised exactly, the prior at ``start`` (default the first sample or grid time).
        grid : (G,) array_like, optional
            With ``times``: return the state at these times instead
            (:func:`~tobitkf.filters._times.smooth_on_grid`; ``u`` is then given on the grid).

        Returns
        -------
        FilterResult
            See :func:`rts_smooth`; with ``grid`` the rows of the grid.

        Raises
        ------
        ValidationError, ShapeError
            As the filter's ``filter``; ``times`` for a discrete-time system, duplicate sample times.
        """
        if times is not None:
            if grid is not None:
                return smooth_on_grid(self, y, times, grid, u=u, censored=censored, x0=x0, P0=P0, start=start)
            return at_times(self, times, y, start=start).smooth(y, u=u, censored=censored, x0=x0, P0=P0)
        if grid is not None or start is not None:
            raise ValidationError("grid/start: give the sample times (times=) of a continuous-time model")
        res = self.filter(y, u=u, x0=x0, P0=P0, **_recorded(censored))
        return rts_smooth(res, self.system, x0=x0, P0=P0)

    def log_likelihood(
        self,
        y: Any,
        *,
        u: Any = None,
        censored: Any = None,
        x0: Any = None,
        P0: Any = None,
        per_step: bool = False,
        times: Any = None,
    ) -> np.ndarray:
        r"""Log-likelihood :math:`\sum_k \ell_k` of ``y`` (..., T, m): (...), or the terms (..., T) with ``per_step``.

        The Kalman filters (plain and dropping): the exact prediction-error likelihood of the linear Gaussian
        model, NaN readings skipped (:func:`tobitkf.inference.kalman_log_likelihood`). The assumed-density
        filter: its ``log_likelihood`` extras (see its Notes); with ``order="uncensored_first"`` it is
        :func:`tobitkf.inference.adf_log_likelihood`. The TKF's update defines none: it gives the
        assumed-density likelihood of its model (system and censoring). ``times`` (T,): sample times for a
        :class:`~tobitkf.ContinuousLinearSystem` (each gap discretised exactly).

        Raises
        ------
        ValidationError, ShapeError
            As the filter's ``filter``.
        """
        if times is not None:
            est = at_times(self, times, y)
            return est.log_likelihood(y, u=u, censored=censored, x0=x0, P0=P0, per_step=per_step)
        terms = self._log_likelihood_terms(y, u=u, x0=x0, P0=P0, **_recorded(censored))
        return terms if per_step else terms.sum(-1)

    def _log_likelihood_terms(self, y: Any, *, u: Any, x0: Any, P0: Any, **recorded: Any) -> np.ndarray:
        """The per-step log-likelihood terms (..., T) of ``y``; each filter that takes the mixin defines it."""
        raise NotImplementedError


class IndicatorFilterMethods:
    """``filter`` of the linear filters that take the recorded censoring indicator ``censored`` (the dropping KF,
    the TKF, the assumed-density filter), written once: sample times (``times``, a
    :class:`~tobitkf.ContinuousLinearSystem`) run the filter on the exact discretisation
    (:func:`~tobitkf.filters._times.at_times`); without a record beside the readings the shared loop runs; with one
    the family's :meth:`_filter_indicated` decides what it means. A family with record keywords of its own (the
    assumed-density filter's ``lower``/``upper``) writes a ``filter`` taking them that hands them, those given, to
    :meth:`_filter_record`."""

    _run: Callable[..., FilterResult]

    def filter(
        self,
        y: Any,
        *,
        u: Any = None,
        censored: Any = None,
        x0: Any = None,
        P0: Any = None,
        outputs: Any = "all",
        state: FilterState | None = None,
        times: Any = None,
    ) -> FilterResult:
        # the docstring is the shared text completed by the family's fragments (``_filter_doc``)
        return self._filter_record(y, u, censored, x0, P0, outputs, state, times)

    def _filter_record(
        self, y: Any, u: Any, censored: Any, x0: Any, P0: Any, outputs: Any, state: Any, times: Any, **record: Any
    ) -> FilterResult:
        """:meth:`filter` with ``record``: the family's own record keywords that were given (not None)."""
        if times is not None:
            est = at_times(self, times, y)
            return est.filter(y, u=u, censored=censored, x0=x0, P0=P0, outputs=outputs, state=state, **record)
        if censored is None and not record:
            return self._run(y, u, x0, P0, outputs=outputs, state=state)
        return self._filter_indicated(y, censored, u=u, x0=x0, P0=P0, outputs=outputs, state=state, **record)

    def _filter_indicated(self, y: Any, censored: Any, *, u: Any, x0: Any, P0: Any, outputs: Any, state: Any):
        """``filter`` of ``y`` with what was recorded beside it: the indicator ``censored`` (None when only the
        family's own record keywords were given, which it then takes too); each family defines it."""
        raise NotImplementedError


def _recorded(censored: Any) -> dict[str, Any]:
    return {} if censored is None else {"censored": censored}
