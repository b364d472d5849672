r"""Algorithm C of the delay family: the chain-decoupled LMMSE filter, predictor and smoothers.

With an uncorrelated initial history the states of x(t+1) = A x(t-d) + u(t) split into d+1
interleaved chains, and y(t) updates only the chain of x(t-d): :class:`ChainLMMSE` /
:func:`chain_lmmse` (the default delay estimator, cost per step independent of d) and the
fixed-interval / fixed-point smoothers :func:`smooth_interval`, :func:`smooth_point`.
The model, the time convention and the code names of every delay estimator:
:mod:`tobitkf.filters.delay` (which also holds the pieces the three algorithms share).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import ValidationError
from ..models.delay import DelayFadingSystem, HistoryPrior
from . import delay as _shared  # _WHOLE_STEP_MAX_RUNS read at call time: one knob for C and D
from ._backend import BACKENDS, use_compiled
from .core import (
    FilterResult,
    FilterState,
    MeasurementPrediction,
    Transition,
    check_keywords,
    measurement_update,
    step_state,
    symmetrize,
    time_update,
)
from .delay import (
    _DECORRELATION,
    _NO_LAYOUTS,
    IntervalSmoothing,
    _blockdiag,
    _cached_layout,
    _check_lags,
    _compiled_gap,
    _compiled_moment_args,
    _DelayEstimator,
    _extend_second_moments,
    _flat_views,
    _moments_at,
    _packed_moment_args,
    _solve_small,
    _stack_blocks,
    register_delay,
)

__all__ = [
    "ChainLMMSE",
    "chain_lmmse",
    "smooth_interval",
    "smooth_point",
]


# --------------------------------------------------------------------------- Algorithm C


class ChainLMMSE(_DelayEstimator):
    r"""Algorithm C, the chain-decoupled exact LMMSE (see :func:`chain_lmmse`), as an estimator.

    Validates once; ``filter(y, lags=..., horizons=..., fixed_point=...)``, ``smooth``, ``smooth_point``;
    online ``init()``/``step(state, y_t)`` (one reading y(t) per step, ``state.k`` = t). The state's
    ``mean``/``cov`` are x̂(t|t), P(t|t); its internal vector stacks the window x̂(t|t), ..., x̂(t-d|t).

    Parameters
    ----------
    system, prior, decorrelation
        The pure-delay model, the uncorrelated prior of its history and the predictor's decorrelation
        (default ``"optimal"``), as in :func:`chain_lmmse`.
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``"auto"`` forms the moments of Λ(t-d) (R(t), J(t), Ā(t), Σ(t), Λ(t+1)) compiled
        (:func:`tobitkf.filters._compiled_delay.delay_moments`, the reorganized LMMSE's code) and runs the
        shared update and predict compiled when numba imports and the fading and multiplicative-noise
        laws do not change with t (else the moments stay on numpy); equal to the numpy path to rounding
        (tested to 1e-12). ``"numpy"`` the reference path; ``"numba"`` raises
        :class:`~tobitkf.ValidationError` for laws that change with t.
    """

    _name = "ChainLMMSE"
    _step_options = ("lags", "horizons", "point", "keep_rts")

    def __init__(
        self, system: DelayFadingSystem, prior: HistoryPrior, *, decorrelation: str = "optimal", backend: str = "auto"
    ):
        check_keywords(
            {"decorrelation": decorrelation, "backend": backend}, {"decorrelation": _DECORRELATION, "backend": BACKENDS}
        )
        self._setup(system, prior)
        _require_chain(system, self.prior)
        self.decorrelation = decorrelation
        self.backend = backend
        self._GS = system.GS
        self._moments = None  # the compiled moments of Λ(t-d) and their constant arguments
        self._whole = None  # the compiled plain step (:func:`~tobitkf.filters._compiled_delay.chain_step`)
        if use_compiled(backend, _compiled_gap(system), "the chain LMMSE's moments"):
            from ._compiled_delay import chain_step, delay_moments

            self._moments = (delay_moments, _compiled_moment_args(system, decorrelation))
            self._whole = (chain_step, _packed_moment_args(system, decorrelation, system.d))

    def _state_dim(self) -> int:
        return self.n * (self.system.d + 1)

    def _initial(self, N, prior, P0, batch):
        _require_chain(self.system, prior)
        d, n = self.system.d, self.n
        xb, Pb, D, lam = {}, {}, {}, {}
        for k in range(d + 1):
            xb[-k] = np.broadcast_to(prior.block_mean(k), (N, n)).copy()
            Pb[-k] = prior.block_cov(k)[None].copy()
            D[-k] = Pb[-k]
            mu = prior.block_mean(k)
            lam[-k] = prior.block_cov(k) + np.outer(mu, mu)
        x = _stack_blocks([xb[-k] for k in range(d + 1)])
        P = _blockdiag([Pb[-k][0] for k in range(d + 1)])
        return x, P, {"xb": xb, "Pb": Pb, "D": D, "lam": lam}

    def _step_arrays(self, t, x, P, S, carry, y, u, options=None):
        options = options or {}
        sys_ = self.system
        d, n = sys_.d, self.n
        lags, horizons = options.get("lags", ()), options.get("horizons", ())
        point, keep_rts = options.get("point"), options.get("keep_rts", False)
        # the compiled plain step reads the window before y(t) off the last one, x̂(t-1-k|t-1): from t = 1 on
        # (the prior's window is x(0), ..., x(-d) itself)
        plain = not (lags or horizons or keep_rts) and point is None and t > 0
        if self._whole is not None and plain and P.shape[0] == 1 and x.shape[0] <= _shared._WHOLE_STEP_MAX_RUNS:
            return self._plain_step(t, x, P, carry, y)
        xb, Pb, D = dict(carry["xb"]), dict(carry["Pb"]), dict(carry["D"])
        e = t - d
        # what time t needs of Λ(t-d), each formed once: R(t) = Q_v + σ² H Λ H^T, J(t), Ā(t), Σ(t) and Λ(t+1)
        lam = dict(carry["lam"])
        if self._moments is not None:
            moments, margs = self._moments
            R, J, Abar, Sigma, lam[t + 1] = moments(lam[e], *margs)
        else:
            R, (J, Abar, Sigma), lam[t + 1] = _moments_at(sys_, t, lam[e], self.decorrelation)
        if horizons and max(horizons) > 1:
            lam = _extend_second_moments(sys_, lam, t + max(horizons))
        gb = sys_.gamma_mean(t)
        H, A, GS = sys_.H, sys_.A, self._GS
        # the update of the measured element x(t-d): the shared update with H_eff = γ̄H, noise R(t) (14)-(15), (46)
        mp = MeasurementPrediction(expected=gb * xb[e].dot(H.T), H0=gb * H, noise=R[None])
        fast = self._compiled_core()  # one run: the compiled shared step (a shared covariance stays on numpy)
        xe, Pe, _, Ke, Qe = measurement_update(xb[e], Pb[e], None, y, mp, "standard", compiled=fast)
        eps = y - mp.expected
        # rule (M): older elements a of the same chain, K(a|t) = γ̄ Φ(a, t-d) H^T Q_ε^{-1} (kept only for
        # lags > d or a fixed point: the plain step has none)
        older = [a for a in D if a < e and (e - a) % (d + 1) == 0]
        HtQi = _solve_small(Qe[0], H).T if older else None  # H^T Q_ε^{-1}
        for a in older:
            Ka = gb * (D[a][0] @ HtQi)
            xb[a] = xb[a] + eps @ Ka.T
            Pb[a] = symmetrize(Pb[a] - Ka @ Qe @ Ka.T)
            # rules (M), (T): Φ_t(a, t+1) = [Φ_{t-1}(a, e) - K_a Q_ε K_e^T] A^T - K_a S^T Γ^T
            D[a] = (D[a] - Ka @ Qe @ Ke[0].T) @ A.T - Ka @ GS.T
        if Ke.shape[0] == 1:  # one gain (the covariances are shared by the runs): 2-D products, the same numbers
            K0 = Ke[0]
            D[e] = ((D[e][0] - K0.dot(Qe[0]).dot(K0.T)).dot(A.T) - K0.dot(GS.T))[None]
        else:
            D[e] = (D[e] - Ke @ Qe @ np.swapaxes(Ke, -1, -2)) @ A.T - Ke @ GS.T
        xb[e], Pb[e] = xe, Pe
        # the one-step prediction x̂(t+1|t) by the shared predict, decorrelated: Ā(t) x̂(t-d|t) + J(t) y(t),
        # Ā P Ā^T + Σ(t) (corrected (52); "paper": the source's constant J of (8))
        xn, Pn, _ = time_update(xe, Pe, None, Transition(A=Abar, Qd=Sigma, b=y.dot(J.T)), "standard", compiled=fast)
        xb[t + 1], Pb[t + 1], D[t + 1] = xn, Pn, Pn
        N = x.shape[0]
        extras = {
            "measured_mean": xe,
            "measured_cov": Pe,
            "next_mean": xn,
            "next_cov": Pn,
            "innovation": eps,
            "innovation_cov": Qe,
            "_lam": lam[t][None],
        }
        if keep_rts:
            extras.update(rts_xupd=xe, rts_Pupd=Pe, rts_Cx=D[e], rts_xpred=xn, rts_Ppred=Pn)
        if lags or point is not None:  # the NaN rows of elements before x(-d)
            nan_m, nan_P = np.full((N, n), np.nan), np.full((1, n, n), np.nan)
        for L in lags:
            j = t - L
            extras[f"lag{L}_mean"] = xb[j] if j >= -d else nan_m
            extras[f"lag{L}_cov"] = Pb[j] if j >= -d else nan_P
        if horizons:
            tmp: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            for kk in range(2, max(horizons) + 1):
                j = t + kk
                src = j - d - 1
                xs, Ps = (xb[src], Pb[src]) if src <= t + 1 else tmp[src]
                # k-step predictor: no ΓS term for k >= 2
                tmp[j] = (xs @ A.T, symmetrize(A @ Ps @ A.T + sys_.process_cov(j - 1, lam[src])))
            for kk in horizons:
                xk, Pk = (xn, Pn) if kk == 1 else tmp[t + kk]
                extras[f"ahead{kk}_mean"], extras[f"ahead{kk}_cov"] = xk, Pk
        if point is not None:
            extras["point_mean"] = xb[point] if point in xb else nan_m
            extras["point_cov"] = Pb[point] if point in Pb else nan_P
        # the window before this reading, x̂(t|t-1), x̂(t-1|t-1), ..., x̂(t-d|t-1), and after it: only the
        # measured element's block (the last) has changed
        xp = _stack_blocks([carry["xb"][t - k] for k in range(d + 1)])
        Pp = _blockdiag([carry["Pb"][t - k][0] for k in range(d + 1)])
        x_new, P_new = xp.copy(), Pp.copy()
        x_new[:, d * n :] = xe
        P_new[0, d * n :, d * n :] = Pe[0]
        new = _chain_prune(t, d, lags, point, xb, Pb, D, lam)
        return x_new, P_new, None, new, xp, Pp, extras

    def _plain_compiled_step(self, t, x, P, carry, y):
        """The compiled plain step (:func:`~tobitkf.filters._compiled_delay.chain_step`) at t >= 1: its flat output
        (the trace of the new window's covariance last) and the layout of its arrays."""
        step, args = self._whole
        N, nw = x.shape
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: self._plain_shapes(N, nw)
        )
        size, lay = lay
        buf = np.empty(size)
        # y contiguous whether a row of a record or one reading: numba types a strided array apart (one compile more)
        y = np.ascontiguousarray(y)
        step(x, P[0], carry["xb"][t], carry["Pb"][t][0], carry["lam"][t - self.system.d], y, *args, buf)
        return buf, lay

    def _plain_shapes(self, N, nw):
        n, m = self.n, self.m
        return ((N, nw), (N, nw), (N, n), (N, m), (1, nw, nw), (1, nw, nw), (1, n, n), (1, m, m), (n, n))

    def _plain_carry(self, t, carry, xn, Pn, lam_next):
        """The plain step's new carry: the measured element x(t-d) leaves it (the window keeps it; its Φ is not
        formed), x̂(t+1|t) and Λ(t+1) join it. In the steady state of plain steps (the carry holds exactly the
        window x(t-d..t) and Λ(t-2d-1..t)) the dicts are copied and their one stale entry deleted; else
        :func:`_chain_prune` (the same entries, by a scan)."""
        d = self.system.d
        xb, Pb, D, lam = carry["xb"], carry["Pb"], carry["D"], carry["lam"]
        e, e_lam = t - d, t - 2 * d - 1
        if len(xb) == d + 1 and e in xb and t in xb and len(lam) == 2 * d + 2 and e_lam in lam and t in lam:
            new = {"xb": xb.copy(), "Pb": Pb.copy(), "D": D.copy(), "lam": lam.copy()}
            del new["xb"][e], new["Pb"][e], new["D"][e], new["lam"][e_lam]
        else:
            new = _chain_prune(t, d, (), None, xb, Pb, D, lam)
        new["xb"][t + 1], new["Pb"][t + 1], new["D"][t + 1] = xn, Pn, Pn
        new["lam"][t + 1] = lam_next
        return new

    def _plain_step(self, t, x, P, carry, y):
        """:meth:`_step_arrays` at t >= 1 without lags, horizons or a fixed point, as one compiled call
        (:func:`~tobitkf.filters._compiled_delay.chain_step`; the same carry and extras, equal to rounding)."""
        buf, lay = self._plain_compiled_step(t, x, P, carry, y)
        x_new, xp, xn, eps, P_new, Pp, Pn, Qe, lam_next = _flat_views(buf, lay)
        new = self._plain_carry(t, carry, xn, Pn, lam_next)
        return x_new, P_new, None, new, xp, Pp, self._plain_extras(t, carry, x_new, P_new, xn, Pn, eps, Qe)

    def _plain_extras(self, t, carry, x_new, P_new, xn, Pn, eps, Qe):
        dn = self.system.d * self.n
        return {
            "measured_mean": x_new[:, dn:],
            "measured_cov": P_new[:, dn:, dn:],
            "next_mean": xn,
            "next_cov": Pn,
            "innovation": eps,
            "innovation_cov": Qe,
            "_lam": carry["lam"][t][None],
        }

    def _whole_online(self, state, y):
        """:meth:`_plain_step` as the online step: the views of the window before the reading, which the state
        does not keep, are not cut."""
        t, carry, x = state.k + 1, state.carry, state.x
        buf, lay = self._plain_compiled_step(t, x, state.P, carry, y)
        if not math.isfinite(buf[-1]):
            return None
        (o0, z0, s0), _, (o2, z2, s2), (o3, z3, s3), (o4, z4, s4), _, (o6, z6, s6), (o7, z7, s7), (o8, z8, s8) = lay
        x_new, xn, eps = buf[o0 : o0 + z0].reshape(s0), buf[o2 : o2 + z2].reshape(s2), buf[o3 : o3 + z3].reshape(s3)
        P_new, Pn = buf[o4 : o4 + z4].reshape(s4), buf[o6 : o6 + z6].reshape(s6)
        Qe, lam_next = buf[o7 : o7 + z7].reshape(s7), buf[o8 : o8 + z8].reshape(s8)
        new = self._plain_carry(t, carry, xn, Pn, lam_next)
        extras = self._plain_extras(t, carry, x_new, P_new, xn, Pn, eps, Qe)
        return step_state(t, state.batch_shape, x_new, P_new, self.n, None, new, extras)

    def _checked_options(self, lags, horizons, fixed_point):
        lags = _check_lags(lags, "lags", 0)
        horizons = _check_lags(horizons, "horizons", 1)
        d = self.system.d
        if fixed_point is not None:
            if isinstance(fixed_point, bool) or not isinstance(fixed_point, (int, np.integer)) or fixed_point < -d:
                raise ValidationError(
                    f"fixed_point: expected an integer element time >= -d = {-d}, got {fixed_point!r}"
                )
            fixed_point = int(fixed_point)
        if self.decorrelation == "paper" and (fixed_point is not None or any(L > 2 * d for L in lags)):
            raise ValidationError(
                "decorrelation: smoothing beyond lag 2d (lags > 2d, fixed_point) needs "
                "decorrelation='optimal'; the constant-J covariances are not error covariances"
            )
        return {"lags": lags, "horizons": horizons, "point": fixed_point}

    def _whole_takes(self, state, options):
        plain = not (options.get("lags") or options.get("horizons") or options.get("keep_rts"))
        return (
            self._whole is not None
            and plain
            and options.get("point") is None
            and state.k >= 0
            and state.P.shape[0] == 1
            and state.x.shape[0] <= _shared._WHOLE_STEP_MAX_RUNS
        )

    def _prepare_step_options(self, state, options):
        if not options:  # the plain online step: nothing to check
            return {"lags": (), "horizons": (), "point": None}
        return self._checked_options(options.get("lags", ()), options.get("horizons", ()), options.get("point"))

    def filter(  # type: ignore[override]  # the delay family: a prior of its own and lag options
        self,
        y: Any,
        *,
        lags: Any = (),
        horizons: Any = (),
        fixed_point: int | None = None,
        prior: Any = None,
        outputs: Any = "all",
        state: FilterState | None = None,
    ) -> FilterResult:
        """Run Algorithm C over ``y`` (..., T, m); see :func:`chain_lmmse`."""
        return self._run_delay(y, prior, state, outputs, self._checked_options(lags, horizons, fixed_point))

    def smooth(self, y: Any) -> IntervalSmoothing:
        """Fixed-interval smoother; see :func:`smooth_interval`."""
        return smooth_interval(self.system, self.prior, y)

    def smooth_point(self, y: Any, j0: int):
        """Fixed-point smoother; see :func:`smooth_point`."""
        return smooth_point(self.system, self.prior, y, j0)


def _chain_prune(t: int, d: int, lags: tuple, point: int | None, xb, Pb, D, lam) -> dict[str, Any]:
    """The chain LMMSE's new carry after step t: new dicts without the elements x(j), j < t + 1 - max(d, lags)
    (but the fixed point), and the Λ(j) no longer read."""
    lo = t + 1 - max((d,) + tuple(lags))
    kept = [j for j in xb if j >= lo or j == point]
    lo_lam = lo - d - 1
    new: dict[str, Any] = {
        "xb": {j: xb[j] for j in kept},
        "Pb": {j: Pb[j] for j in kept},
        "D": {j: D[j] for j in kept},
        "lam": {j: v for j, v in lam.items() if j >= lo_lam},
    }
    if point is not None:
        new["point"] = point
    return new


def chain_lmmse(
    system: DelayFadingSystem,
    prior: HistoryPrior,
    y: Any,
    *,
    decorrelation: str = "optimal",
    lags: Any = (),
    horizons: Any = (),
    fixed_point: int | None = None,
) -> FilterResult:
    r"""Algorithm C: chain-decoupled exact LMMSE filter, predictors and smoothers (chain decoupling, ours; LD-02).

    For each measurement y(t), with j = t - d (the measured element):

    .. math::

        \varepsilon(t) &= y(t) - \bar\gamma(t)H\hat x(j|t-1), \quad
        Q_\varepsilon(t) = \bar\gamma^2 H P(j|t-1) H^T + \sigma^2 H\Lambda(j)H^T + Q_v \quad (14), (15) \\
        K(j|t) &= \bar\gamma P(j|t-1)H^TQ_\varepsilon^{-1}, \quad \hat x(j|t) = \hat x(j|t-1) + K\varepsilon \quad (13), (46) \\
        \hat x(t+1|t) &= A\hat x(j|t-1) + LQ_\varepsilon^{-1}\varepsilon, \quad L = \bar\gamma AP(j|t-1)H^T + \Gamma S \\
        P(t+1|t) &= AP(j|t-1)A^T + Q_u(t) - LQ_\varepsilon^{-1}L^T
            \;(= \bar A(t)P(j|t)\bar A(t)^T + \Sigma(t), \text{ corrected (52)})

    and the generic rule (M) updates older elements of the same chain (fixed-lag and
    fixed-point smoothing). Exact when x(0), ..., x(-d) are mutually uncorrelated; cost per
    step independent of d (plus one update per kept element of the chain for ``lags`` > 2d).

    Parameters
    ----------
    system : DelayFadingSystem
        Pure-delay model (no ``extra_lags``).
    prior : HistoryPrior
        Uncorrelated prior of x(0), ..., x(-d).
    y : (..., T, m) array_like
        Measurements y(0)..y(T-1) (leading axes = runs).
    decorrelation : {"optimal", "paper"}
        ``"optimal"`` (default): the exact predictor (corrected J(t) = ΓS R(t)^{-1}).
        ``"paper"``: the source's constant J = ΓS Q_v^{-1} in (50)–(52) (comparison only).
    lags : iterable of int >= 0
        Fixed lags L for which x̂(t-L|t) is returned in ``lagged``.
    horizons : iterable of int >= 1
        Steps k for which x̂(t+k|t) is returned in ``ahead``.
    fixed_point : int >= -d, optional
        Element j0 for the fixed-point smoother x̂(j0|t).

    Returns
    -------
    FilterResult

    Raises
    ------
    ValidationError
        A prior correlated across lags (``prior``; use Algorithm A or D), a model with extra
        lags (``system``), an unknown option, ``lags``/``horizons``/``fixed_point`` out of range,
        or smoothing beyond lag 2d with ``decorrelation="paper"``.

    Notes
    -----
    Deviation from the source: ``decorrelation="optimal"`` replaces the constant J of (8) by
    J(t) = ΓS[Q_v + σ²(t)HΛ(t-d)H^T]^{-1} (docs/sources LD-E3; the source's J leaves Ω(t) correlated
    with y(t) when σ² > 0 and S ≠ 0). With S = 0 or σ² = 0 both modes coincide. The state
    second moment uses the corrected recursion (LD-E2) in both modes.
    """
    est = ChainLMMSE(system, prior, decorrelation=decorrelation)
    return est.filter(y, lags=lags, horizons=horizons, fixed_point=fixed_point)


def _require_chain(system: DelayFadingSystem, prior: HistoryPrior) -> None:
    if not system.is_pure_delay:
        raise ValidationError("system: Algorithm C needs the pure-delay model (no extra_lags); use augmented_lmmse")
    if not prior.is_uncorrelated:
        raise ValidationError(
            "prior: Algorithm C needs mutually uncorrelated x(0), ..., x(-d) (the chains must be "
            "independent); use augmented_lmmse or reorganized_lmmse for a correlated prior"
        )


def smooth_interval(system: DelayFadingSystem, prior: HistoryPrior, y: Any) -> IntervalSmoothing:
    r"""Fixed-interval smoother x̂(j|T-1), j = -d..T: chain RTS in decorrelated form (chain decoupling, ours; LD-02).

    .. math::

        G(j) &= P(j|j+d)\bar A(j+d)^T P(j+d+1|j+d)^{-1}, \\
        \hat x(j|N) &= \hat x(j|j+d) + G(j)[\hat x(j+d+1|N) - \hat x(j+d+1|j+d)], \\
        P(j|N) &= P(j|j+d) + G(j)[P(j+d+1|N) - P(j+d+1|j+d)]G(j)^T,

    for j = N-d, ..., -d (N = T-1); the elements j > N-d are not measured yet and keep their
    filter values. Not in the source (its only smoother is the fixed lag d-1 of Theorem 3).
    Same requirements as :func:`chain_lmmse`. ``P(j+d+1|j+d)`` is solved against; if it is
    singular the pseudo-inverse is used.
    """
    est = ChainLMMSE(system, prior)
    res = est._run(y, outputs=("extras",), state=est.init(np.shape(y)[:-2]), step_options={"keep_rts": True})
    ex = res.extras
    assert res.final is not None, "the estimation loop records the final state"
    final = res.final.carry
    batch = np.shape(y)[:-2]
    N = int(np.prod(batch, dtype=int))
    T, d = np.shape(y)[-2], system.d

    def runs(a):  # batch + (T, ...) -> (N, T, ...)
        return np.asarray(a).reshape((N,) + np.shape(a)[len(batch) :])

    xupd, Pupd, Cx = runs(ex["rts_xupd"]), np.asarray(ex["rts_Pupd"]), np.asarray(ex["rts_Cx"])
    xpred, Ppred = runs(ex["rts_xpred"]), np.asarray(ex["rts_Ppred"])
    Pupd, Cx, Ppred = (a.reshape((-1,) + a.shape[-3:])[0] if a.ndim > 3 else a for a in (Pupd, Cx, Ppred))
    # element j is measured at t = j + d (index j + d), and x(j+d+1) is predicted at that step
    xs: dict[int, np.ndarray] = {}
    Ps: dict[int, np.ndarray] = {}
    for j in range(max(T - d, -d), T + 1):
        xs[j], Ps[j] = final["xb"][j], final["Pb"][j][0]
    for j in range(T - 1 - d, -d - 1, -1):
        t = j + d
        nxt = j + d + 1
        Pp = Ppred[t]
        try:
            G = np.linalg.solve(Pp.T, Cx[t].T).T
        except np.linalg.LinAlgError:
            G = Cx[t] @ np.linalg.pinv(Pp)
        xs[j] = xupd[:, t] + (xs[nxt] - xpred[:, t]) @ G.T
        Ps[j] = symmetrize(Pupd[t] + G @ (Ps[nxt] - Pp) @ G.T)
    times = np.arange(-d, T + 1)
    mean = np.stack([xs[j] for j in times], axis=1)
    cov = np.stack([Ps[j] for j in times], axis=0)
    return IntervalSmoothing(
        times=times, mean=mean.reshape(batch + mean.shape[1:]), cov=np.broadcast_to(cov, batch + cov.shape)
    )


def smooth_point(system: DelayFadingSystem, prior: HistoryPrior, y: Any, j0: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-point smoother x̂(j0|t), P(j0|t) for t = 0..T-1; see :func:`chain_lmmse`.

    Returns ``(mean (..., T, n), cov (..., T, n, n))``, NaN while t + 1 < j0.
    """
    res = chain_lmmse(system, prior, y, fixed_point=j0)
    return res.extras["point"]["mean"], res.extras["point"]["cov"]


register_delay(
    ChainLMMSE,
    "exact LMMSE of a pure-delay system with fading, chain-decoupled (Li, Li & Wang 2018)",
    {"decorrelation": _DECORRELATION, "backend": BACKENDS},
)
