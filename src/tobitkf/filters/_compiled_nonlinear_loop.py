r"""The compiled time loop of the nonlinear filters, for a :class:`~tobitkf.NonlinearSystem` whose ``f`` and ``h``
(and ``F``, ``H`` when given) are ``numba.njit`` functions: one loop for both covariance forms.

:func:`nonlinear_loop` is the numpy path of :mod:`tobitkf.filters.nonlinear` (whose module docstring states the
equations) run by numba over blocks of :data:`~tobitkf.filters._compiled_nonlinear.NL_BLOCK` runs and steps: the
user's functions are called from compiled code once per block and step on the stacked points of the block's runs,
``f(X, k)`` with ``X`` (nb * L, n) (the L sigma points of each run, or the one mean and the 2n central-difference
points of the extended form) and ``h(X, k)`` likewise, as the batched numpy path calls them, so a function written
for it serves here unchanged. Per step, the **prediction** (extended or by the sigma-point rule), then the
**update** by a code: :data:`~tobitkf.filters._compiled_nonlinear.KALMAN` (over the channels with a reading,
standard or Joseph), :data:`~tobitkf.filters._compiled_nonlinear.TOBIT` (the Tobit update at the predicted
measurement) or :data:`~tobitkf.filters._compiled_nonlinear.ADF` (channel by channel, iterated). The per-run
algebra is in block steps cached on disk: those of the covariance form and the ones both forms share in
:mod:`tobitkf.filters._compiled_nonlinear`, those of the square-root form (a factor :math:`S`, :math:`P = SS^T`,
carried instead of P) in :mod:`tobitkf.filters._compiled_nonlinear_sqrt`.

The user's functions are arguments, so numba specialises the loop for each (f, h, F, H): compiled once per
process and combination (a function specialised on another is not cached on disk). That specialised loop is kept
thin (the loops over blocks, steps, channels and linearisations, and the calls of f, h). The form is chosen by the
type of an argument (the roots of R, or None), so numba compiles only that form's branch. Covered: the standard
(and Joseph for the extended Kalman filter) and square-root forms, inputs ``f(x, k, u)``, time-varying Q (and R
for the uncensored filters), censoring and any channel with compiled moments (a quantizer, a channel's own
``compiled_block``) for the assumed-density filter, censoring for the Tobit filters, fading readings
:math:`\vartheta\odot h(x) + v` for every filter in the covariance form (``fade``: the moments of
:mod:`~tobitkf.filters._compiled_fading_moments`) and random saturation for the assumed-density filter (a family
that gives its block's arrays itself, ``_compiled_channel``); other channels run the numpy path.

Measured (``benchmarks/bench_nonlinear.py``: two coupled pendulums, n = 4, m = 2, unscented rule, 10^4 runs x
100 steps, 25 % of readings clipped; two runs on a 2-core machine under a load average of 10-16): the
assumed-density filter 3.57x and 3.24x the compiled linear assumed-density filter per run-step in wall time
(1.07 and 1.05 against 0.29 and 0.26 µs of CPU time), the calls of f and h alone 1.70x and 1.66x; the
uncensored UKF 4.22x and 4.18x. Before the block steps stopped allocating and had their state loops unrolled:
5.9x (2,000 runs, the same load), with about 0.8 µs per run-step outside f and h.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numba import njit

from . import _compiled_nonlinear_sqrt as sq
from ._compiled_inputs import _model_inputs, active_inputs
from ._compiled_moments import CENSORED, kind
from ._compiled_nonlinear import (
    ADF,
    KALMAN,
    NL_BLOCK,
    SIZES,
    TOBIT,
    _adf_channel_start,
    _adf_project,
    _adf_scratch,
    _block_copy,
    _block_differences,
    _block_end,
    _block_inputs,
    _block_jacobians,
    _block_points,
    _block_rows,
    _block_start,
    _call,
    _input_scratch,
    _predict_extended,
    _predict_sigma,
    _record,
    _record_ll,
    _scratch,
    _update_joint,
    point_columns,
)

_NO_FADING = np.zeros((0, 1))  # the loop's ``fade`` of an unfaded reading

__all__ = ["nonlinear_loop", "channel_arrays", "channel_gap", "compiled_run", "Run", "run_arrays", "run_result"]


@njit(error_model="numpy")
def nonlinear_loop(
    size, f, h, F, H, code, xi, xcol, wm, wc, y, u, uh, Qs, Rs, Rroots, k0, x0, P0,
    family, lo, hi, par, noise_code, iterations, joseph,
    means, covs, pmeans, pcovs, ey, slope, ll, x_last, P_last, fade,
):  # fmt: skip
    r"""The filter of every nonlinear family over the runs of ``y`` (N, T, m) from the prior ``x0`` (N, n),
    ``P0`` (N or 1, n, n) at time ``k0``, in either covariance form.

    ``size`` the state size as a type (:data:`~tobitkf.filters._compiled_nonlinear.SIZES`, or ``()``); ``f``,
    ``h``, ``F``, ``H``: the model's compiled functions (``F``/``H`` None: central differences); ``u`` (N, T, p)
    the inputs of an ``f(x, k, u)`` or None, ``uh`` those of an ``h(x, k, u)`` or None; ``xi`` (L, n), ``wm``,
    ``wc`` (L,) the sigma-point rule (L = 0: the extended form), ``xcol`` (L,) its
    :func:`~tobitkf.filters._compiled_nonlinear.point_columns`; ``Qs`` (TQ, n, n) :math:`Q_{k-1}` and ``Rs``
    (TR, m, m) :math:`R_k` per step (one row: constant); ``Rroots`` None: the covariance form; else the
    square-root form, with ``Rroots`` (TR, m, m) the roots of ``Rs``, ``Qs`` (TQ, n, q) the roots of Q and
    ``P0``, ``P_last`` factors :math:`S` (:math:`P = SS^T`). ``code`` ``KALMAN``, ``TOBIT`` or ``ADF`` as a kind
    (:func:`~tobitkf.filters._compiled_moments.kind`: its length is read as a constant and the other updates'
    branches are pruned before typing, so that the Kalman filters' versions do not compile the assumed-density
    update nor the ADF's the joint one);
    ``family``, ``lo``/``hi`` (TL, m), ``par`` (TP, m, K) the channel of the ADF (a family of
    :mod:`~tobitkf.filters._compiled_moments` as a kind, :func:`~tobitkf.filters._compiled_moments.kind`: its
    moments alone are compiled) and the limits of the Tobit update, ``noise_code`` its noise
    term; ``iterations`` the ADF's linearisations; ``joseph`` the Joseph form of the Kalman update. Writes
    ``means``/``pmeans`` (N, T or 0, n), ``covs`` (N, T or 0, n, n or 1: the diagonals), ``pcovs``, the Tobit
    extras ``ey``/``slope`` (N, T or 0, m), the ADF's ``ll`` (N, T or 0), and the last state
    ``x_last``/``P_last``; ``fade`` (2, m) the means and variances of the fading gains :math:`\vartheta` of a
    reading :math:`\vartheta\odot h(x) + v` ((0, m): none; the covariance form only).

    The runs go in blocks; each call of f, h (F, H) takes the stacked points of a block (``_block_points``:
    (nb * L, n); the extended form: the nb means, or the nb * 2n central-difference points), the assumed-density
    update only those of the runs still taking part. Only this function is specialised on the user's functions
    (and compiled in every process); ``Rroots is None`` is decided by its type, so only one form's branches are
    compiled.
    """
    upd = len(code)  # a constant: numba rewrites the length of a tuple argument before typing
    N, T, m = y.shape
    n = x0.shape[1]
    L = xi.shape[0]
    TQ, TR, TL, TP = Qs.shape[0], Rs.shape[0], lo.shape[0], par.shape[0]
    B = min(NL_BLOCK, N)
    rows = L if L > 0 else 2 * n  # points per run of one call
    factors = Rroots is not None
    xs, Ps, xps, Pps, xms, Pms, X, X1, deltas, J, Hj, every, act, lsum = _scratch(B, n, m, rows)
    root, dv = np.empty((n, n)), np.empty(n)
    ws = _adf_scratch(B, n)
    U = _input_scratch(u if uh is None else uh, B * rows)
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _block_start(x0, P0, r0, nb, xs, Ps)
        for t in range(T):
            k = k0 + t + 1
            Q, R = Qs[min(t, TQ - 1)], Rs[min(t, TR - 1)]
            lo_t, hi_t = lo[min(t, TL - 1)], hi[min(t, TL - 1)]
            # ---- the prediction: extended or by the rule
            if L == 0:
                _block_rows(xs, X1, nb)
                Y1 = _call(f, X1[:nb], k - 1, _block_inputs(u, r0, nb, t, 1, U))
                if F is None:
                    _block_differences(xs, X, deltas, nb)
                    V = _call(f, X[: nb * rows], k - 1, _block_inputs(u, r0, nb, t, rows, U))
                    _block_jacobians(V, deltas, J, nb)
                    Jf = J
                else:
                    Jf = _call(F, X1[:nb], k - 1, _block_inputs(u, r0, nb, t, 1, U))
                if Rroots is None:
                    _predict_extended(Y1, Jf, Ps, Q, xps, Pps, root, nb)
                else:
                    sq.predict(False, Y1, Jf, Ps, wm, wc, Q, xps, Pps, nb)
            else:
                _block_points(size, xs, Ps, xi, xcol, root, X, nb, every, factors)
                Y = _call(f, X[: nb * L], k - 1, _block_inputs(u, r0, nb, t, L, U))
                if Rroots is None:
                    _predict_sigma(size, Y, wm, wc, Q, xps, Pps, dv, nb)
                else:
                    sq.predict(True, Y, J, Ps, wm, wc, Q, xps, Pps, nb)
            if Rroots is None:
                _record(size, xps, Pps, r0, t, nb, pmeans, pcovs)
            else:
                sq.record(xps, Pps, r0, t, nb, pmeans, pcovs)
            # ---- the update
            if upd == ADF:  # channel by channel, each linearised `iterations` times
                _block_copy(size, xps, Pps, xs, Ps, nb)
                lsum[:] = 0.0
                for ch in range(m):
                    if _adf_channel_start(size, y, r0, t, ch, xs, Ps, xms, Pms, act, nb) == 0:
                        continue
                    for it in range(iterations):
                        q = _block_points(size, xms, Pms, xi, xcol, root, X, nb, act, factors)
                        if q == 0:
                            break
                        Yh = _call(h, X[: q * L], k, active_inputs(uh, r0, nb, t, L, U, act))
                        if Rroots is None:
                            _adf_project(
                                size, it, ch, X, Yh, wm, wc, y, r0, t, xs, Ps, xms, Pms, act, R[ch, ch],
                                family, lo_t[ch], hi_t[ch], par[min(t, TP - 1), ch], lsum, nb, ws, fade,
                            )  # fmt: skip
                        else:
                            sq.adf_channel(it, ch, Yh, xi, wm, wc, y, r0, t, xs, Ps, xms, Pms, act, R[ch, ch],
                                           family, lo_t[ch], hi_t[ch], par[min(t, TP - 1), ch], lsum, nb)  # fmt: skip
                    _block_copy(size, xms, Pms, xs, Ps, nb)
                _record_ll(lsum, r0, t, nb, ll)
            else:
                if L == 0:  # the extended measurement: h(x̄) and its Jacobian
                    _block_rows(xps, X1, nb)
                    Yh = _call(h, X1[:nb], k, _block_inputs(uh, r0, nb, t, 1, U))
                    if H is None:
                        _block_differences(xps, X, deltas, nb)
                        Yd = _call(h, X[: nb * rows], k, _block_inputs(uh, r0, nb, t, rows, U))
                        _block_jacobians(Yd, deltas, Hj, nb)
                        Jh = Hj
                    else:
                        Jh = _call(H, X1[:nb], k, _block_inputs(uh, r0, nb, t, 1, U))
                else:  # at the points
                    _block_points(size, xps, Pps, xi, xcol, root, X, nb, every, factors)
                    Yh = _call(h, X[: nb * L], k, _block_inputs(uh, r0, nb, t, L, U))
                    Jh = Hj
                if Rroots is None:
                    _update_joint(upd, L > 0, X, Yh, Jh, wm, wc, xps, Pps, y, r0, t, R, lo_t, hi_t, noise_code,
                                  joseph, xs, Ps, Hj, ey, slope, nb, fade)  # fmt: skip
                else:
                    sq.joint(upd, L > 0, Yh, Jh, xi, wm, wc, xps, Pps, y, r0, t, R, Rroots[min(t, TR - 1)], lo_t,
                             hi_t, noise_code, xs, Ps, ey, slope, nb)  # fmt: skip
            if Rroots is None:
                _record(size, xs, Ps, r0, t, nb, means, covs)
            else:
                sq.record(xs, Ps, r0, t, nb, means, covs)
        _block_end(xs, Ps, r0, nb, x_last, P_last)


# --------------------------------------------------------------------------- the Python side


def _c(a) -> np.ndarray:
    """``a`` as a C-contiguous, writable float64 array (a read-only one would specialise the loop once more)."""
    return np.require(a, dtype=float, requirements=("C", "W"))


def channel_arrays(est, k0: int, T: int):
    """``(family, lo, hi, par, noise_code)`` of the estimator's channel for the steps k0+1..k0+T, or a string
    saying why the compiled loop does not cover it (the numpy path runs). ``family`` a kind
    (:func:`~tobitkf.filters._compiled_moments.kind`, or of a channel's own block,
    :func:`~tobitkf.filters._compiled_moments.channel_kind`: the loop's assumed-density update compiles that
    family's moments alone)."""
    from ..channels.censoring import Censoring
    from ._compiled_moments import channel_kind
    from ._compiled_tobit import NOISE_CODES

    m = est.m
    inf = np.full((1, m), np.inf)
    none = np.zeros((1, m, 0))
    code = est._compiled_code
    if code == KALMAN:
        return kind(CENSORED), -inf, inf, none, 0
    channel = est.channel
    if getattr(est, "_sigma" if code == TOBIT else "_r", None) is None:
        return "a measurement covariance R given per step"
    if code == ADF and hasattr(est, "_compiled_channel"):  # a family that gives its block's arrays itself
        return est._compiled_channel(k0, T)
    if isinstance(channel, Censoring):
        lo, hi = channel.all_limits(T, m, start=k0 + 1, check=False)
        noise = NOISE_CODES[est.noise_term] if code == TOBIT else 0
        return kind(CENSORED), _c(lo), _c(hi), none, noise
    family = channel_kind(channel) if code == ADF else None
    if family is not None:  # a channel with compiled moments (its own compiled_block: a quantizer, ...)
        par = _c(channel.compiled_parameters(k0 + 1, T, m))
        return family, -inf, inf, par, 0
    return (
        f"the channel {type(channel).__name__} (the compiled path covers censoring and, for the ADF, channels "
        "with compiled moments)"
    )


def channel_gap(est) -> str | None:
    """Why the compiled loop does not cover the estimator's channel and noise (None: it does)."""
    gap = channel_arrays(est, 0, 1)
    return gap if isinstance(gap, str) else None


class Run(NamedTuple):
    """The arguments of one compiled run that the standard and the square-root form share (:func:`run_arrays`)."""

    head: tuple[Any, ...]
    """The loop's leading arguments: ``size, f, h, F, H, code, xi, xcol, wm, wc, y, u, uh`` (``code`` a kind)."""
    channel: tuple[Any, ...]
    """``family, lo, hi, par, noise_code, iterations``."""
    outputs: tuple[np.ndarray, ...]
    """``means, covs, pmeans, pcovs, ey, slope, ll``."""
    code: int
    extras: bool
    """Whether the family's extras are recorded."""
    steps: int


def run_arrays(est, y2: np.ndarray, u2, state, want, *, online: bool = False) -> Run | None:
    """The arrays of a compiled run of a nonlinear estimator on ``y2`` (N, T, m) from ``state``, in either
    covariance form: the rule's points, the channel, the outputs ``want`` asks for (``online``: the one step
    and its prediction) and the inputs; None when the channel is not covered (:func:`channel_arrays`)."""
    from ._outputs import _empty, output_arrays, state_specs

    N, T, m = y2.shape
    n = est.n
    sys_ = est.system
    arrays = channel_arrays(est, state.k, T)
    if isinstance(arrays, str):
        return None
    rule = est.rule
    if rule is None:
        xi, wm, wc = np.empty((0, n)), np.empty(0), np.empty(0)
    else:
        xi, wm, wc = (_c(a) for a in rule.unit(n))
    code = est._compiled_code
    ext = online or "extras" in want
    if online:  # the prediction too, for the consistency check of the step
        outputs: tuple[np.ndarray, ...] = (_empty((N, 0, n)), _empty((N, 0, n, n)), np.empty((N, 1, n)),
                                           np.empty((N, 1, n, n)))  # fmt: skip
        outputs += (np.empty((N, 1, m)), np.empty((N, 1, m)), np.empty((N, 0))) if code == TOBIT else (
            _empty((N, 0, m)), _empty((N, 0, m)), np.empty((N, 1)) if code == ADF else _empty((N, 0)))  # fmt: skip
    else:
        outputs = tuple(output_arrays(
            N, T, *state_specs(want, n), (ext and code == TOBIT, (m,)), (ext and code == TOBIT, (m,)),
            (ext and code == ADF, ()),
        ))  # fmt: skip
    uf, uh = _model_inputs(sys_, u2, N, T)
    head = (SIZES.get(n, ()), sys_.f, sys_.h, sys_.F, sys_.H, kind(code), xi, point_columns(xi), wm, wc, _c(y2), uf, uh)
    channel = (*arrays, est.iterations if code == ADF else 1)
    return Run(head, channel, outputs, code, ext, T)


def run_result(run: Run, want, batch, state, x_last, P_last, S_last=None, *, online: bool = False):
    """The :class:`~tobitkf.FilterResult` of a compiled run (``online``: the new state and the step's prediction
    ``(state, x̄, P̄)``) from its last means ``x_last``, covariances ``P_last`` (and factors ``S_last`` of the
    square-root form)."""
    from ._outputs import compiled_result
    from .core import FilterState, step_state

    means, covs, pmeans, pcovs, ey, slope, ll = run.outputs
    n = x_last.shape[1]
    T = run.steps
    extras = {}
    if run.extras and run.code == TOBIT:
        extras = {"expected_y": ey, "slope": slope}
    elif run.extras and run.code == ADF:
        extras = {"log_likelihood": ll}
    if online:
        new = step_state(state.k + 1, state.batch_shape, x_last, P_last, n, S_last, state.carry,
                         {key: v[:, 0] for key, v in extras.items()} or None)  # fmt: skip
        return new, pmeans[:, 0], pcovs[:, 0]
    extras = {key: v.reshape(batch + v.shape[1:]) for key, v in extras.items()}
    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=P_last, n=n, S=S_last, carry=state.carry)
    return compiled_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)


def compiled_run(est, y2: np.ndarray, u2, state, want, batch, *, online: bool = False):
    """The compiled ``filter`` (or, ``online``, one step) of a nonlinear estimator whose gap is None, in its
    covariance form: a :class:`~tobitkf.FilterResult` (for a step the new state and the step's prediction
    ``(state, x̄, P̄)``; the square-root form's final state carries the factor), or None when the covariance (or
    factor) stopped being finite (the numpy path reruns the call and reports where) or the channel is not
    covered."""
    from .._linalg import psd_sqrt

    run = run_arrays(est, y2, u2, state, want, online=online)
    if run is None:
        return None
    sys_ = est.system
    N, T, _ = y2.shape
    n = est.n
    k0 = state.k
    x_last, P_last = np.empty((N, n)), np.empty((N, n, n))
    loop: Any = nonlinear_loop  # called with the run's tuples: the typed signature is numba's, not the loop's
    if est.covariance_update == "square_root":
        steps = range(T) if (sys_.Q.varying or sys_.R.varying) else range(1)
        Qroots = _c(np.stack([est._qroot(k0 + t) for t in steps]))
        Rs = _c(np.stack([sys_.measurement_cov(k0 + t + 1) for t in steps]))
        S0 = state.S if state.S is not None else psd_sqrt(state.P)
        loop(*run.head, Qroots, Rs, _c(psd_sqrt(Rs)), k0, _c(state.x), _c(S0), *run.channel, False, *run.outputs,
             x_last, P_last, getattr(est, "_fade", _NO_FADING))  # fmt: skip
        if not np.isfinite(P_last).all():
            return None
        S_last = P_last
        P_last = S_last @ np.swapaxes(S_last, -1, -2)
        P_last = 0.5 * (P_last + np.swapaxes(P_last, -1, -2))
        return run_result(run, want, batch, state, x_last, P_last, S_last, online=online)
    Qs = _c(np.stack([sys_.process_cov(k0 + t) for t in range(T)]) if sys_.Q.varying else sys_.process_cov(0)[None])
    Rs = _c(np.stack([sys_.measurement_cov(k0 + t + 1) for t in range(T)]) if sys_.R.varying else
            sys_.measurement_cov(1)[None])  # fmt: skip
    loop(*run.head, Qs, Rs, None, k0, _c(state.x), _c(state.P), *run.channel, est.covariance_update == "joseph",
         *run.outputs, x_last, P_last, getattr(est, "_fade", _NO_FADING))  # fmt: skip
    if not np.isfinite(np.diagonal(P_last, axis1=-2, axis2=-1)).all():
        return None
    return run_result(run, want, batch, state, x_last, P_last, online=online)
