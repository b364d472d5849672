r"""Optimal linear filter, predictor and smoothers for pure-delay systems with fading measurements.

Source: Y. Li, J. Li, X. Wang (2018), "Optimal linear estimators for time-delay systems with
fading measurements and correlated noises" (seed 002; spec ``002_timedelay_fading.md`` §2).
Model (1)–(3) in :mod:`tobitkf.models.delay`. All estimators are the affine LMMSE
(projection on span{1, y(0..t)}) for the equivalent second-order model (spec §1.6):

.. math::

    x(t+1) = A x(t-d) + u(t), \quad y(t) = \bar\gamma(t) H x(t-d) + e(t), \quad
    E[uu^T] = Q_u(t),\ E[ee^T] = R(t) = Q_v + \sigma^2(t) H\Lambda(t-d)H^T,\ E[ue^T] = \Gamma S.

Three exact algorithms (they agree to rounding; tests check it):

* **C, chain-decoupled** (:func:`chain_lmmse`, default). With an uncorrelated initial history
  the states split into d+1 interleaved chains; y(t) updates only the chain of x(t-d). Cost per
  step O(n³ + n²m + m³), independent of d.
* **A, augmented** (:func:`augmented_lmmse`). Dense LMMSE on X(t) = [x(t); ...; x(t-W)], any
  joint prior, any lag structure; cost O(n³(W+1)³) per step. The reference.
* **D, reorganized innovation** (:func:`reorganized_lmmse`). The source's Lemmas 1–3 and
  Theorems 1–3 with errata E3–E7 corrected (spec §2.5), any prior, O(d²) per step.

What a new measurement y(t) changes (d >= 1, uncorrelated history): only the estimate of its
chain, x̂(t-d|t) and the smoothed estimates of older elements of that chain. The source's
"filter" x̂(t|t) then equals the one-step prediction x̂(t|t-1) (gain K(t) ≡ 0) and its
fixed-lag-(d-1) smoother x̂(t-d+1|t) equals x̂(t-d+1|t-d) (spec §0). This is a property of
the printed model, not a bug.

Time convention (the source's): y(0) is the first measurement, at index 0, and measures x(-d).
Output index t holds x̂(t|t) (``mean``), x̂(t+1|t) (``pred_mean``) and x̂(t-d|t)
(``measured_mean``). Covariances do not depend on the data (no censoring), so they are
computed once and broadcast over the runs as read-only views.

Code names -> paper symbols: ``mean``/``cov`` x̂(t|t), P(t|t) (Theorem 1); ``pred_mean``/``pred_cov``
x̂(t+1|t), P(t+1|t) (Theorem 2, (50)–(52)); ``measured_mean`` x̂(t-d|t) (Lemma 1, i = 0);
``lagged[L]`` x̂(t-L|t) (Theorem 3 is L = d-1); ``innovation`` ε(t) (14); ``innovation_cov``
Q_ε(t) (15); ``second_moment`` Λ(t) (10, corrected E2); ``decorrelation`` J (8).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array, check_instance
from ..models.delay import DelayFadingSystem, HistoryPrior
from ._common import check_keywords, symmetrize

__all__ = ["DelayEstimates", "IntervalSmoothing", "chain_lmmse", "augmented_lmmse", "reorganized_lmmse",
           "smooth_interval", "smooth_point", "second_moments", "ChainLMMSE", "AugmentedLMMSE",
           "ReorganizedInnovationLMMSE"]

_DECORRELATION = ("optimal", "paper")
_ERRATA = ("E5", "E6", "E7")


@dataclass(frozen=True)
class DelayEstimates:
    """Estimates of the delay system, index t = measurement time (y(0) at index 0).

    Truth alignment with :func:`~tobitkf.simulate.delay.simulate_delay` output: ``mean`` lines up
    with ``data.x[:, :T]`` (x(t)), ``pred_mean`` with ``data.x[:, 1:]`` (x(t+1), which is what
    :func:`tobitkf.metrics.summarize` does with a (N, T+1, n) truth), ``measured_mean`` with
    ``full_states(data)[:, :T]`` (x(t-d)).

    Attributes
    ----------
    mean, cov : (..., T, n), (..., T, n, n)
        Filter x̂(t|t), P(t|t) (Theorem 1). For d >= 1 and an uncorrelated history it equals
        the one-step prediction x̂(t|t-1); y(t) does not change it.
    pred_mean, pred_cov : (..., T, n), (..., T, n, n)
        One-step predictor x̂(t+1|t), P(t+1|t) (Theorem 2); changed by y(t).
    measured_mean, measured_cov : (..., T, n), (..., T, n, n)
        Delayed filter x̂(t-d|t), P(t-d|t): the element y(t) measures; changed by y(t).
    innovation : (..., T, m)
        ε(t) = y(t) - γ̄(t) H x̂(t-d|t-1).
    innovation_cov : (..., T, m, m)
        Q_ε(t).
    second_moment : (T+1, n, n)
        Λ(t) = E[x(t)x(t)^T], t = 0..T.
    lagged : dict {L: (mean, cov)}
        Fixed-lag smoother x̂(t-L|t) (NaN where t-L < -d). Changed by y(t) only when
        L = d or t-L is in the chain of x(t-d) (L ≡ d mod d+1).
    ahead : dict {k: (mean, cov)}
        k-step predictor x̂(t+k|t); changed by y(t) only through x̂(t+1|t) and x̂(t-d|t).
    point : dict or None
        Fixed-point smoother ``{"j": j0, "mean", "cov"}``: x̂(j0|t) (NaN while x(j0) does not
        exist yet, t + 1 < j0); changed only at t = j0 + d + k(d+1).
    extras : dict
        Algorithm-specific quantities (e.g. ``smoother`` for Algorithm D: x̂(t-d+1|t)).
    """

    mean: np.ndarray
    cov: np.ndarray
    pred_mean: np.ndarray
    pred_cov: np.ndarray
    measured_mean: np.ndarray
    measured_cov: np.ndarray
    innovation: np.ndarray
    innovation_cov: np.ndarray
    second_moment: np.ndarray
    lagged: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    ahead: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    point: dict[str, Any] | None = None
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class IntervalSmoothing:
    """Fixed-interval (RTS) smoother output x̂(j|T-1), j = -d..T (index j + d).

    Attributes
    ----------
    times : (T+d+1,) int array
        The element times j = -d..T.
    mean : (..., T+d+1, n)
    cov : (..., T+d+1, n, n)
    """

    times: np.ndarray
    mean: np.ndarray
    cov: np.ndarray


# --------------------------------------------------------------------------- shared pieces

def _prepare(system: Any, prior: Any, y: Any) -> tuple[np.ndarray, tuple[int, ...]]:
    check_instance(system, DelayFadingSystem, "system")
    system.check_prior(prior)
    arr = as_float_array(y, "y")
    if arr.ndim < 2 or arr.shape[-1] != system.m:
        raise ShapeError(f"y: expected (..., T, {system.m}), got shape {arr.shape}")
    if arr.shape[-2] < 1:
        raise ShapeError(f"y: expected at least one time step, got shape {arr.shape}")
    return arr.reshape((-1,) + arr.shape[-2:]), arr.shape[:-2]


def _check_lags(lags: Any, name: str, minimum: int) -> tuple[int, ...]:
    out = []
    for L in tuple(lags):
        if isinstance(L, bool) or not isinstance(L, (int, np.integer)) or L < minimum:
            raise ValidationError(f"{name}: expected integers >= {minimum}, got {L!r}")
        out.append(int(L))
    return tuple(sorted(set(out)))


def second_moments(system: DelayFadingSystem, prior: HistoryPrior, last: int) -> dict[int, np.ndarray]:
    r"""Λ(j) = E[x(j)x(j)^T] for j = -d..``last`` (corrected recursion, erratum E2).

    .. math:: \Lambda(t+1) = A\Lambda(t-d)A^T + \sum_i Q_{\zeta_i}(t)A_i\Lambda(t-d)A_i^T + \Gamma Q_w\Gamma^T,
       \qquad \Lambda(-k) = P(-k) + \bar x(-k)\bar x(-k)^T.

    The source's (10) uses the random sample y(t)y(t)^T and drops cross terms; it is not offered.
    Only for the pure-delay model (Algorithm A tracks the joint second moment itself).
    """
    d = system.d
    lam = {}
    for k in range(d + 1):
        mu = prior.block_mean(k)
        lam[-k] = prior.block_cov(k) + np.outer(mu, mu)
    for t in range(0, last):
        L = lam[t - d]
        lam[t + 1] = symmetrize(system.A @ L @ system.A.T + system.process_cov(t, L))
    return lam


def _decorrelation(system: DelayFadingSystem, s: int, Lam_meas: np.ndarray, mode: str):
    r"""J(s), Ā(s), Σ(s) of the J-form predictor (spec §1.5).

    ``"optimal"`` (corrected, E3): :math:`R = Q_v + \sigma^2 H\Lambda H^T`, :math:`J = \Gamma S R^{-1}`,
    :math:`\Sigma = \sum_i Q_{\zeta_i} A_i\Lambda A_i^T + \Gamma(Q_w - SR^{-1}S^T)\Gamma^T`.
    ``"paper"`` ((8), (9), (11)): :math:`J = \Gamma S Q_v^{-1}`,
    :math:`\Sigma = \sum_i Q_{\zeta_i} A_i\Lambda A_i^T + \Gamma(Q_w - SQ_v^{-1}S^T)\Gamma^T + \sigma^2 J H\Lambda H^T J^T`.
    Both use Ā = A - γ̄ J H.
    """
    gb, s2 = system.gamma_mean(s), system.gamma_var(s)
    HLH = system.H @ Lam_meas @ system.H.T
    mult = system.mult_cov(s, Lam_meas)
    if mode == "optimal":
        R = system.Qv + s2 * HLH
        SRinv = np.linalg.solve(R, system.S.T).T
        J = system.Gamma @ SRinv
        Sigma = mult + system.Gamma @ (system.Qw - SRinv @ system.S.T) @ system.Gamma.T
    else:
        J = system.Gamma @ system.S_Qv_inv
        Sigma = mult + system.Gamma @ system.eta_cov @ system.Gamma.T + s2 * (J @ HLH @ J.T)
    Abar = system.A - gb * (J @ system.H)
    return J, Abar, symmetrize(Sigma)


def _ro(arr: np.ndarray, batch: tuple[int, ...]) -> np.ndarray:
    """Broadcast a shared (T, ...) covariance array over the batch shape, read-only."""
    out = np.broadcast_to(arr, batch + arr.shape)
    return out


def _shape_mean(arr: np.ndarray, batch: tuple[int, ...]) -> np.ndarray:
    return arr.reshape(batch + arr.shape[1:])


def _mult_sum(q: np.ndarray, Ai: np.ndarray, Lam: np.ndarray) -> np.ndarray:
    """Σ_i q_i A_i Λ A_i^T with matmuls (einsum over four indices would be O(N^4))."""
    return np.sum(q[:, None, None] * (Ai @ Lam @ np.swapaxes(Ai, -1, -2)), axis=0)


def _gain(D: np.ndarray, HtQi: np.ndarray, gb: float) -> np.ndarray:
    return gb * (D @ HtQi)


# --------------------------------------------------------------------------- Algorithm C

def _chain_core(system: DelayFadingSystem, prior: HistoryPrior, y: np.ndarray, *, decorrelation: str,
                lags: tuple[int, ...], horizons: tuple[int, ...], point: int | None, keep_rts: bool):
    N, T, m = y.shape
    n, d = system.n, system.d
    A, H, GS = system.A, system.H, system.GS
    kmax = max((1,) + horizons)
    lam = second_moments(system, prior, T + kmax - 1)
    xb: dict[int, np.ndarray] = {}
    Pb: dict[int, np.ndarray] = {}
    D: dict[int, np.ndarray] = {}
    rts: dict[str, dict[int, np.ndarray]] = {k: {} for k in ("xupd", "Pupd", "Cx", "xpred", "Ppred")}
    for k in range(d + 1):
        xb[-k] = np.broadcast_to(prior.block_mean(k), (N, n)).copy()
        Pb[-k] = prior.block_cov(k).copy()
        D[-k] = Pb[-k]
        if keep_rts:
            rts["xpred"][-k], rts["Ppred"][-k] = xb[-k], Pb[-k]
    keep = max((d,) + lags)
    nan_m, nan_P = np.full((N, n), np.nan), np.full((n, n), np.nan)
    out = {k: [] for k in ("x", "P", "xp", "Pp", "xm", "Pm", "eps", "Qe")}
    lag_out = {L: ([], []) for L in lags}
    ahead_out = {k: ([], []) for k in horizons}
    point_out = ([], [])
    for t in range(T):
        e = t - d
        gb = system.gamma_mean(t)
        xm, Pm, Le = xb[e], Pb[e], lam[e]
        R = system.fading_noise_cov(t, Le)                      # step 2: R = Q_v + σ² H Λ H^T
        Qe = symmetrize(gb * gb * (H @ Pm @ H.T) + R)           # step 3 / (15)
        eps = y[:, t] - gb * (xm @ H.T)                         # step 4 / (14)
        HtQi = np.linalg.solve(Qe, H).T                         # H^T Q_ε^{-1}
        Ke = _gain(Pm, HtQi, gb)                                # step 5 / (46), (51)
        for a in [a for a in D if a <= e and (e - a) % (d + 1) == 0]:
            Ka = Ke if a == e else _gain(D[a], HtQi, gb)       # rule (M): K(a|t) = γ̄ Φ(a, t-d) H^T Q_ε^{-1}
            xb[a] = xb[a] + eps @ Ka.T
            Pb[a] = symmetrize(Pb[a] - Ka @ Qe @ Ka.T)
            # rules (M), (T): Φ_t(a, t+1) = [Φ_{t-1}(a, e) - K_a Q_ε K_e^T] A^T - K_a S^T Γ^T
            D[a] = (D[a] - Ka @ Qe @ Ke.T) @ A.T - Ka @ GS.T
        if keep_rts:
            rts["xupd"][e], rts["Pupd"][e], rts["Cx"][e] = xb[e], Pb[e], D[e]
        if decorrelation == "optimal":
            Lg = gb * (A @ Pm @ H.T) + GS                       # step 8
            LQi = np.linalg.solve(Qe, Lg.T).T
            xn = xm @ A.T + eps @ LQi.T                         # step 9
            Pn = A @ Pm @ A.T + system.process_cov(t, Le) - LQi @ Lg.T   # step 10
        else:
            # Source (50), (52) with the constant J = Γ S Q_v^{-1} of (8): not orthogonal to y(t)
            # when σ² > 0 and S ≠ 0 (erratum E3), so suboptimal and its P is not the true error covariance.
            J, Abar, Sigma = _decorrelation(system, t, Le, "paper")
            xn = xb[e] @ Abar.T + y[:, t] @ J.T
            Pn = Abar @ Pb[e] @ Abar.T + Sigma
        xb[t + 1], Pb[t + 1] = xn, symmetrize(Pn)
        D[t + 1] = Pb[t + 1]
        if keep_rts:
            rts["xpred"][t + 1], rts["Ppred"][t + 1] = xb[t + 1], Pb[t + 1]
        out["x"].append(xb[t]); out["P"].append(Pb[t])
        out["xp"].append(xb[t + 1]); out["Pp"].append(Pb[t + 1])
        out["xm"].append(xb[e]); out["Pm"].append(Pb[e])
        out["eps"].append(eps); out["Qe"].append(Qe)
        for L in lags:
            j = t - L
            lag_out[L][0].append(xb[j] if j >= -d else nan_m)
            lag_out[L][1].append(Pb[j] if j >= -d else nan_P)
        if horizons:
            tmp: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            for k in range(2, kmax + 1):
                j = t + k
                src = j - d - 1
                xs, Ps = (xb[src], Pb[src]) if src <= t + 1 else tmp[src]
                # k-step predictor: no ΓS term for k >= 2 (spec §2.3)
                tmp[j] = (xs @ A.T, symmetrize(A @ Ps @ A.T + system.process_cov(j - 1, lam[src])))
            for k in horizons:
                xk, Pk = (xb[t + 1], Pb[t + 1]) if k == 1 else tmp[t + k]
                ahead_out[k][0].append(xk); ahead_out[k][1].append(Pk)
        if point is not None:
            point_out[0].append(xb[point] if point in xb else nan_m)
            point_out[1].append(Pb[point] if point in Pb else nan_P)
        for j in [j for j in xb if j < t + 1 - keep and j != point]:
            del xb[j], Pb[j], D[j]
    return out, lag_out, ahead_out, point_out, lam, rts, xb, Pb


def _assemble(out, lag_out, ahead_out, point_out, point, lam, T, batch, extras=None) -> DelayEstimates:
    def means(lst):
        return _shape_mean(np.stack(lst, axis=1), batch)

    def covs(lst):
        return _ro(np.stack(lst, axis=0), batch)

    return DelayEstimates(
        mean=means(out["x"]), cov=covs(out["P"]), pred_mean=means(out["xp"]), pred_cov=covs(out["Pp"]),
        measured_mean=means(out["xm"]), measured_cov=covs(out["Pm"]), innovation=means(out["eps"]),
        innovation_cov=covs(out["Qe"]), second_moment=np.stack([lam[t] for t in range(T + 1)]),
        lagged={L: (means(v[0]), covs(v[1])) for L, v in lag_out.items()},
        ahead={k: (means(v[0]), covs(v[1])) for k, v in ahead_out.items()},
        point=None if point is None else {"j": point, "mean": means(point_out[0]), "cov": covs(point_out[1])},
        extras=extras or {})


def chain_lmmse(system: DelayFadingSystem, prior: HistoryPrior, y: Any, *, decorrelation: str = "optimal",
                lags: Any = (), horizons: Any = (), fixed_point: int | None = None) -> DelayEstimates:
    r"""Algorithm C: chain-decoupled exact LMMSE filter, predictors and smoothers (spec §2.3).

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
    DelayEstimates

    Raises
    ------
    ValidationError
        A prior correlated across lags (``prior``; use Algorithm A or D), a model with extra
        lags (``system``), an unknown option, ``lags``/``horizons``/``fixed_point`` out of range,
        or smoothing beyond lag 2d with ``decorrelation="paper"``.

    Notes
    -----
    Deviation from the source: ``decorrelation="optimal"`` replaces the constant J of (8) by
    J(t) = ΓS[Q_v + σ²(t)HΛ(t-d)H^T]^{-1} (erratum E3; the source's J leaves Ω(t) correlated
    with y(t) when σ² > 0 and S ≠ 0). With S = 0 or σ² = 0 both modes coincide. The state
    second moment uses the corrected recursion (E2) in both modes.
    """
    check_keywords({"decorrelation": decorrelation}, {"decorrelation": _DECORRELATION})
    y2, batch = _prepare(system, prior, y)
    _require_chain(system, prior)
    lags = _check_lags(lags, "lags", 0)
    horizons = _check_lags(horizons, "horizons", 1)
    d = system.d
    if fixed_point is not None:
        if isinstance(fixed_point, bool) or not isinstance(fixed_point, (int, np.integer)) or fixed_point < -d:
            raise ValidationError(f"fixed_point: expected an integer element time >= -d = {-d}, got {fixed_point!r}")
        fixed_point = int(fixed_point)
    if decorrelation == "paper" and (fixed_point is not None or any(L > 2 * d for L in lags)):
        raise ValidationError("decorrelation: smoothing beyond lag 2d (lags > 2d, fixed_point) needs "
                              "decorrelation='optimal'; the constant-J covariances are not error covariances")
    res = _chain_core(system, prior, y2, decorrelation=decorrelation, lags=lags, horizons=horizons,
                      point=fixed_point, keep_rts=False)
    out, lag_out, ahead_out, point_out, lam = res[:5]
    return _assemble(out, lag_out, ahead_out, point_out, fixed_point, lam, y2.shape[1], batch)


def _require_chain(system: DelayFadingSystem, prior: HistoryPrior) -> None:
    if not system.is_pure_delay:
        raise ValidationError("system: Algorithm C needs the pure-delay model (no extra_lags); use augmented_lmmse")
    if not prior.is_uncorrelated:
        raise ValidationError("prior: Algorithm C needs mutually uncorrelated x(0), ..., x(-d) (the chains must be "
                              "independent); use augmented_lmmse or reorganized_lmmse for a correlated prior")


def smooth_interval(system: DelayFadingSystem, prior: HistoryPrior, y: Any) -> IntervalSmoothing:
    r"""Fixed-interval smoother x̂(j|T-1), j = -d..T: chain RTS in decorrelated form (spec §2.3).

    .. math::

        G(j) &= P(j|j+d)\bar A(j+d)^T P(j+d+1|j+d)^{-1}, \\
        \hat x(j|N) &= \hat x(j|j+d) + G(j)[\hat x(j+d+1|N) - \hat x(j+d+1|j+d)], \\
        P(j|N) &= P(j|j+d) + G(j)[P(j+d+1|N) - P(j+d+1|j+d)]G(j)^T,

    for j = N-d, ..., -d (N = T-1); the elements j > N-d are not measured yet and keep their
    filter values. Not in the source (its only smoother is the fixed lag d-1 of Theorem 3).
    Same requirements as :func:`chain_lmmse`. ``P(j+d+1|j+d)`` is solved against; if it is
    singular the pseudo-inverse is used.
    """
    y2, batch = _prepare(system, prior, y)
    _require_chain(system, prior)
    N, T, _ = y2.shape
    d = system.d
    res = _chain_core(system, prior, y2, decorrelation="optimal", lags=(), horizons=(), point=None, keep_rts=True)
    rts, xb, Pb = res[5], res[6], res[7]
    xs: dict[int, np.ndarray] = {}
    Ps: dict[int, np.ndarray] = {}
    for j in range(max(T - d, -d), T + 1):
        xs[j], Ps[j] = xb[j], Pb[j]
    for j in range(T - 1 - d, -d - 1, -1):
        nxt = j + d + 1
        Pp = rts["Ppred"][nxt]
        try:
            G = np.linalg.solve(Pp.T, rts["Cx"][j].T).T
        except np.linalg.LinAlgError:
            G = rts["Cx"][j] @ np.linalg.pinv(Pp)
        xs[j] = rts["xupd"][j] + (xs[nxt] - rts["xpred"][nxt]) @ G.T
        Ps[j] = symmetrize(rts["Pupd"][j] + G @ (Ps[nxt] - Pp) @ G.T)
    times = np.arange(-d, T + 1)
    mean = np.stack([xs[j] for j in times], axis=1)
    cov = np.stack([Ps[j] for j in times], axis=0)
    return IntervalSmoothing(times=times, mean=_shape_mean(mean, batch), cov=_ro(cov, batch))


def smooth_point(system: DelayFadingSystem, prior: HistoryPrior, y: Any, j0: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-point smoother x̂(j0|t), P(j0|t) for t = 0..T-1 (spec §2.3); see :func:`chain_lmmse`.

    Returns ``(mean (..., T, n), cov (..., T, n, n))``, NaN while t + 1 < j0.
    """
    res = chain_lmmse(system, prior, y, fixed_point=j0)
    return res.point["mean"], res.point["cov"]


# --------------------------------------------------------------------------- Algorithm A

def _augmented_matrices(system: DelayFadingSystem, W: int):
    n, m, p, h, d = system.n, system.m, system.p, system.h, system.d
    B = W + 1
    NN = n * B
    AA = np.zeros((NN, NN))
    for lag, mat in system.lags.items():
        AA[:n, lag * n:(lag + 1) * n] += mat
    for k in range(W):
        AA[(k + 1) * n:(k + 2) * n, k * n:(k + 1) * n] = np.eye(n)
    Ai = np.zeros((h, NN, NN))
    Ai[:, :n, d * n:(d + 1) * n] = system.A_mult
    G = np.zeros((NN, p))
    G[:n] = system.Gamma
    HH = np.zeros((m, NN))
    HH[:, d * n:(d + 1) * n] = system.H
    return AA, Ai, G, HH


def _augmented_core(system: DelayFadingSystem, prior: HistoryPrior, y: np.ndarray, W: int, record: bool = False):
    N, T, m = y.shape
    n, d = system.n, system.d
    AA, Ai, G, HH = _augmented_matrices(system, W)
    NN = n * (W + 1)
    m0 = np.zeros(NN)
    m0[:n * (d + 1)] = prior.mean.reshape(-1)
    P = np.zeros((NN, NN))
    P[:n * (d + 1), :n * (d + 1)] = prior.cov          # blocks beyond d: x(-k), k > d, do not exist (held at 0)
    LamX = P + np.outer(m0, m0)
    X = np.broadcast_to(m0, (N, NN)).copy()
    GQG, GS = G @ system.Qw @ G.T, G @ system.S
    rec = []
    for t in range(T):
        gb, s2 = system.gamma_mean(t), system.gamma_var(t)
        Qe = symmetrize(gb * gb * (HH @ P @ HH.T) + s2 * (HH @ LamX @ HH.T) + system.Qv)
        eps = y[:, t] - gb * (X @ HH.T)
        HtQi = np.linalg.solve(Qe, HH).T
        K = gb * (P @ HtQi)
        Xf = X + eps @ K.T
        Pf = symmetrize(P - K @ Qe @ K.T)
        q = system.q_mult(t)
        Qu = GQG + (_mult_sum(q, Ai, LamX) if q.size else 0.0)
        Lg = gb * (AA @ P @ HH.T) + GS
        LQi = np.linalg.solve(Qe, Lg.T).T
        Xp = X @ AA.T + eps @ LQi.T
        Pp = symmetrize(AA @ P @ AA.T + Qu - LQi @ Lg.T)
        rec.append((Xf, Pf, Xp, Pp, K, eps, Qe, P) if record else (Xf, Pf, Xp, Pp, eps, Qe))
        LamX = symmetrize(AA @ LamX @ AA.T + Qu)
        X, P = Xp, Pp
    return rec, LamX


def _blk(M: np.ndarray, i: int, j: int | None, n: int) -> np.ndarray:
    if j is None:
        return M[..., i * n:(i + 1) * n]
    return M[..., i * n:(i + 1) * n, j * n:(j + 1) * n]


def augmented_lmmse(system: DelayFadingSystem, prior: HistoryPrior, y: Any, *, window: int | None = None,
                    lags: Any = ()) -> DelayEstimates:
    r"""Algorithm A: dense LMMSE on the augmented state X(t) = [x(t); ...; x(t-W)] (spec §2.4).

    .. math::

        X(t+1) = (\mathfrak A + \textstyle\sum_i\zeta_i(t)\mathfrak A_i)X(t) + \mathfrak G w(t), \qquad
        y(t) = \gamma(t)\mathfrak H X(t) + v(t),

    with the LMMSE for same-time correlated noises (gain :math:`\bar\gamma\mathcal P\mathfrak H^TQ_\varepsilon^{-1}`,
    predictor gain :math:`(\bar\gamma\mathfrak A\mathcal P\mathfrak H^T + \mathfrak G S)Q_\varepsilon^{-1}`).
    Exact for any joint prior and any lag structure (``extra_lags``). Not the source's method
    (it avoids augmentation); the reference every other algorithm is tested against.
    Cost O(n³(W+1)³) per step.

    Parameters
    ----------
    system : DelayFadingSystem
    prior : HistoryPrior
        Any joint prior of x(0), ..., x(-d).
    y : (..., T, m) array_like
    window : int >= d, optional
        W; default d. Larger windows give fixed-lag smoothing up to lag W.
    lags : iterable of int in [0, W]
        Fixed lags returned in ``lagged``.

    Returns
    -------
    DelayEstimates
        ``extras["final_mean"]`` (..., n(W+1)) and ``extras["final_cov"]`` (n(W+1), n(W+1)):
        X̂(T|T-1), i.e. x̂(T-k|T-1) for k = 0..W. With W = T + d this is the fixed-interval
        smoother of every element x(-d)..x(T) (the oracle for :func:`smooth_interval`).

    Raises
    ------
    ValidationError
        ``window`` < d or a lag outside [0, W].
    """
    y2, batch = _prepare(system, prior, y)
    d, n = system.d, system.n
    W = d if window is None else window
    if isinstance(W, bool) or not isinstance(W, (int, np.integer)) or W < d:
        raise ValidationError(f"window: expected an integer >= d = {d}, got {window!r}")
    lags = _check_lags(lags, "lags", 0)
    if any(L > W for L in lags):
        raise ValidationError(f"lags: expected lags <= window W = {W}, got {max(lags)}")
    rec, _ = _augmented_core(system, prior, y2, int(W))
    T = y2.shape[1]
    lam = _augmented_second_moments(system, prior, T)
    out = {"x": [_blk(r[0], 0, None, n) for r in rec], "P": [_blk(r[1], 0, 0, n) for r in rec],
           "xp": [_blk(r[2], 0, None, n) for r in rec], "Pp": [_blk(r[3], 0, 0, n) for r in rec],
           "xm": [_blk(r[0], d, None, n) for r in rec], "Pm": [_blk(r[1], d, d, n) for r in rec],
           "eps": [r[4] for r in rec], "Qe": [r[5] for r in rec]}
    nan_m, nan_P = np.full((y2.shape[0], n), np.nan), np.full((n, n), np.nan)
    lag_out = {L: ([_blk(r[0], L, None, n) if t - L >= -d else nan_m for t, r in enumerate(rec)],
                   [_blk(r[1], L, L, n) if t - L >= -d else nan_P for t, r in enumerate(rec)]) for L in lags}
    extras = {"final_mean": _shape_mean(rec[-1][2], batch), "final_cov": rec[-1][3], "window": int(W)}
    return _assemble(out, lag_out, {}, ([], []), None, lam, T, batch, extras)


def _augmented_second_moments(system: DelayFadingSystem, prior: HistoryPrior, T: int) -> dict[int, np.ndarray]:
    if system.is_pure_delay:
        return second_moments(system, prior, T)
    # generic lags: propagate the joint second moment of [x(t); ...; x(t-d)]
    n, d = system.n, system.d
    AA, Ai, G, _ = _augmented_matrices(system, d)
    m0 = prior.mean.reshape(-1)
    LamX = prior.cov + np.outer(m0, m0)
    lam = {0: LamX[:n, :n]}
    for t in range(T):
        q = system.q_mult(t)
        Qu = G @ system.Qw @ G.T + (_mult_sum(q, Ai, LamX) if q.size else 0.0)
        LamX = symmetrize(AA @ LamX @ AA.T + Qu)
        lam[t + 1] = LamX[:n, :n]
    return lam


# --------------------------------------------------------------------------- Algorithm D

def reorganized_lmmse(system: DelayFadingSystem, prior: HistoryPrior, y: Any, *, decorrelation: str = "optimal",
                      warmup: int | None = None, reinsert_errata: Any = ()) -> DelayEstimates:
    r"""Algorithm D: the source's reorganized-innovation estimator, errata corrected (spec §2.5).

    Streaming order at time t (Ψ_i(t) := Φ_{t-i}(t-d-i+1, t-d+1), i = 1..d):

    (a) ε(t), Q_ε(t) from x̂(t-d|t-1) (14), (15);
    (b) filter (35)–(38): K(t|t) = γ̄ Ψ_d(t+d-1)^T H^T Q_ε^{-1}, P(t|t) = P(t|t-1) - γ̄ K H Ψ_d(t+d-1);
    (c) Ψ_i(t), i = d-1..1, by the corrected (58):

    .. math::

        \Psi_i(t) = [\Psi_{d-i+1}(t-i)^T - \bar\gamma K(a|t-d)HP(t-2d|t-d-1)]\bar A(t-d)^T
          - \bar\gamma K(a|t-d+1)H\Psi_d(t) - \sum_{j=0}^{d-2-i}\bar\gamma K(a|t-i-j)H\Psi_{i+j+1}(t),
          \quad a = t-d-i+1;

    (d) fixed-lag-(d-1) smoother (55)–(57) for a = t-d+1;
    (e) K(t-d|t) (51), x̂(t-d|t), predictor (50), (52) with Ā(t), J(t), Σ(t);
    (f) Ψ_d(t+d) = {Ā(t)[Ψ_1(t) - γ̄ K(t-d|t) H Ψ_1(t)]}^T (39);
    (g) Λ(t+1) by the corrected recursion (E2).

    Initialization (the source's list is garbled, spec §4 item 12): with a prior uncorrelated
    across lags, D starts at t = 0 with every Ψ and every gain K(a|s), s ≠ a+d, equal to zero
    (exact). Otherwise the steps t < ``warmup`` (default 2d+1, the source's "ε(i) = 0,
    i = 1..2d+1" range) are computed by Algorithm A, from which every stored Ψ, gain and
    covariance is read (spec §2.5). For d = 0 this is Algorithm C.

    Parameters
    ----------
    system, prior, y
        As :func:`augmented_lmmse` (pure-delay model, any joint prior).
    decorrelation : {"optimal", "paper"}
        J(t) of the corrected E3 or the source's constant J = ΓS Q_v^{-1} (everywhere Ā appears).
    warmup : int, optional
        First step done by the reorganized recursions; >= 2d+1 for a correlated prior
        (default 2d+1), >= 0 for an uncorrelated one (default 0). The steps before it are
        exact (Algorithm A) in both ``decorrelation`` modes.
    reinsert_errata : iterable of {"E5", "E6", "E7"}
        For regression tests only: put back the source's printed (30)/(58): ``"E5"`` uses
        K(t-d-i|t-d) for K(t-d-i+1|t-d), ``"E6"`` the transposed Ψ_d(t)^T, ``"E7"`` the upper
        summation limit d-1-i (double counts the update at t-d+1). Each breaks optimality.

    Returns
    -------
    DelayEstimates
        ``lagged[d-1]`` is Theorem 3's smoother x̂(t-d+1|t) (d >= 1).

    Raises
    ------
    ValidationError
        Extra lags, an unknown option or erratum, ``warmup`` too small for a correlated prior.

    Notes
    -----
    Deviations from the source (each an erratum of spec §2.2): γ̄, σ² indexed by the measurement's
    own time (E4); Ψ_d(t) untransposed (E6); K(t-d-i+1|t-d) (E5); summation limit d-2-i (E7);
    J(t) corrected (E3) unless ``decorrelation="paper"``; streaming order (a)–(g) (spec §4 item 13).
    The cost is O(d²) per step, not independent of d as the source claims.
    """
    check_keywords({"decorrelation": decorrelation}, {"decorrelation": _DECORRELATION})
    errata = frozenset(reinsert_errata)
    bad = errata - set(_ERRATA)
    if bad:
        raise ValidationError(f"reinsert_errata: expected a subset of {_ERRATA}, got {sorted(bad)}")
    y2, batch = _prepare(system, prior, y)
    if not system.is_pure_delay:
        raise ValidationError("system: Algorithm D needs the pure-delay model (no extra_lags); use augmented_lmmse")
    d, n = system.d, system.n
    if d == 0:
        if not prior.is_uncorrelated:  # pragma: no cover - a single block is always uncorrelated
            raise ValidationError("prior: unexpected correlated prior for d = 0")
        return chain_lmmse(system, prior, y, decorrelation=decorrelation, lags=(max(d - 1, 0),))
    zero_init = prior.is_uncorrelated
    t0 = (0 if zero_init else 2 * d + 1) if warmup is None else warmup
    lowest = 0 if zero_init else 2 * d + 1
    if isinstance(t0, bool) or not isinstance(t0, (int, np.integer)) or t0 < lowest:
        raise ValidationError(f"warmup: expected an integer >= {lowest} ({'uncorrelated' if zero_init else 'correlated'} "
                              f"prior; 2d+1 = {2 * d + 1}), got {warmup!r}")
    N, T, m = y2.shape
    H = system.H
    lam = second_moments(system, prior, T)
    t_init = min(t0, T)
    rec, _ = _augmented_core(system, prior, y2[:, :t_init], d, record=True) if t_init > 0 else ([], None)

    xf, Pf, xsm, Psm, xm, Pmeas, xp, Pp = {}, {}, {}, {}, {}, {}, {}, {}
    Psi: dict[tuple[int, int], np.ndarray] = {}
    K: dict[tuple[int, int], np.ndarray] = {}
    eps, Qe, Pm = {}, {}, {}
    zero_nn, zero_nm = np.zeros((n, n)), np.zeros((n, m))
    # Exact initialization from an uncorrelated prior (spec §2.5): every Ψ and every gain
    # K(a|s), s ≠ a+d, is zero; the elements x(-k) keep their prior until measured.
    for k in range(d + 1):
        mu = np.broadcast_to(prior.block_mean(k), (N, n)).copy()
        xf[-k], Pf[-k] = mu, prior.block_cov(k)            # x̂(-k|-k) = prior (no data before t = 0)
    xp[0], Pp[0] = xf[0], Pf[0]
    xsm[-1], Psm[-1] = xf[-d], Pf[-d]                      # x̂(-d|-1)
    for t, (Xf, PfA, Xp, PpA, KA, e_t, Q_t, Pprior) in enumerate(rec):
        xf[t], Pf[t] = _blk(Xf, 0, None, n), _blk(PfA, 0, 0, n)
        xsm[t], Psm[t] = _blk(Xf, d - 1, None, n), _blk(PfA, d - 1, d - 1, n)
        xm[t], Pmeas[t] = _blk(Xf, d, None, n), _blk(PfA, d, d, n)
        xp[t + 1], Pp[t + 1] = _blk(Xp, 0, None, n), _blk(PpA, 0, 0, n)
        Pm[t] = _blk(Pprior, d, d, n)                       # P(t-d|t-1)
        for k in range(d + 1):
            K[(t - k, t)] = _blk(KA.T, k, None, n).T        # K(t-k|t): rows of block k
        eps[t], Qe[t] = e_t, Q_t
        # Ψ_i(t') = block (d, d-i) of P(j|j-1) with j = t'-i+1
        for j, Pj in ((t, Pprior), (t + 1, PpA)):
            for i in range(1, d + 1):
                Psi[(i, j + i - 1)] = _blk(Pj, d, d - i, n)

    gbar = system.gamma_mean
    Jc: dict[int, tuple] = {}

    def gk(s: int) -> float:          # γ̄(s); no measurement (and a zero gain) before s = 0
        return gbar(s) if s >= 0 else 0.0

    def decor(s: int):
        if s not in Jc:
            Jc[s] = _decorrelation(system, s, lam[s - d], decorrelation)
        return Jc[s]

    for t in range(t_init, T):
        gb = gbar(t)
        # (a) innovation (14), (15); x̂(t-d|t-1) is last step's smoother output x̂(t-d+1|t) shifted
        xmp, Pmp = xsm[t - 1], Psm[t - 1]
        Pm[t] = Pmp
        Q = symmetrize(gb * gb * (H @ Pmp @ H.T) + system.fading_noise_cov(t, lam[t - d]))
        e_t = y2[:, t] - gb * (xmp @ H.T)
        eps[t], Qe[t] = e_t, Q
        HtQi = np.linalg.solve(Q, H).T
        # (b) filter, (35)-(38) shifted by one
        Psd = Psi.get((d, t + d - 1), zero_nn)
        Kf = gb * (Psd.T @ HtQi)
        K[(t, t)] = Kf
        xf[t] = xp[t] + e_t @ Kf.T
        Pf[t] = symmetrize(Pp[t] - gb * (Kf @ H @ Psd))
        # (c) Ψ_i(t), i = d-1..1, corrected (58)
        # Before t = d (zero initialization only) the terms below are all zero: Ψ and the
        # gains of not-yet-measured elements vanish; times < 0 carry no measurement.
        Abar_td = decor(t - d)[1] if t - d >= 0 else system.A
        for i in range(d - 1, 0, -1):
            a = t - d - i + 1
            a5 = a - 1 if "E5" in errata else a          # source (30)/(58) print K(t-d-i|t-d) (E5)
            psi_dt = Psi.get((d, t), zero_nn)
            psi_d = psi_dt.T if "E6" in errata else psi_dt   # source prints Ψ_d(t)^T (E6)
            val = (Psi.get((d - i + 1, t - i), zero_nn).T
                   - gk(t - d) * (K.get((a5, t - d), zero_nm) @ H @ Pm.get(t - d, zero_nn))) @ Abar_td.T
            val = val - gk(t - d + 1) * (K.get((a, t - d + 1), zero_nm) @ H @ psi_d)
            top = d - 1 - i if "E7" in errata else d - 2 - i  # source's limit d-1-i double counts (E7)
            for j in range(0, top + 1):
                s = t - i - j
                val = val - gk(s) * (K.get((a, s), zero_nm) @ H @ Psi.get((i + j + 1, t), zero_nn))
            Psi[(i, t)] = val
        # (d) fixed-lag d-1 smoother (55)-(57), a = t-d+1
        a = t - d + 1
        xs_, Ps_ = xf[a], Pf[a]
        for i in range(1, d):
            s = t - i + 1
            if s < 0:
                continue
            Ks = gbar(s) * (Psi[(i, t)].T @ np.linalg.solve(Qe[s], H).T)
            K[(a, s)] = Ks
            xs_ = xs_ + eps[s] @ Ks.T
            Ps_ = Ps_ - gbar(s) * (Ks @ H @ Psi[(i, t)])
        xsm[t], Psm[t] = xs_, symmetrize(Ps_)
        # (e) delayed filter and predictor (50)-(52)
        Ke = gb * (Pmp @ HtQi)
        K[(t - d, t)] = Ke
        xm[t] = xmp + e_t @ Ke.T
        Pmeas[t] = symmetrize(Pmp - gb * (Ke @ H @ Pmp))
        J, Abar, Sigma = decor(t)
        xp[t + 1] = xm[t] @ Abar.T + y2[:, t] @ J.T
        Pp[t + 1] = symmetrize(Abar @ Pmeas[t] @ Abar.T + Sigma)
        # (f) corrected (39)
        psi1 = Psi.get((1, t), zero_nn)
        Psi[(d, t + d)] = (Abar @ (psi1 - gb * (Ke @ H @ psi1))).T
        # drop what is no longer needed
        for key in [k for k in Psi if k[1] < t - 2 * d - 1]:
            del Psi[key]
        for key in [k for k in K if k[1] < t - 2 * d - 1]:
            del K[key]

    out = {"x": [xf[t] for t in range(T)], "P": [Pf[t] for t in range(T)],
           "xp": [xp[t + 1] for t in range(T)], "Pp": [Pp[t + 1] for t in range(T)],
           "xm": [xm[t] for t in range(T)], "Pm": [Pmeas[t] for t in range(T)],
           "eps": [eps[t] for t in range(T)], "Qe": [Qe[t] for t in range(T)]}
    lag_out = {d - 1: ([xsm[t] for t in range(T)], [Psm[t] for t in range(T)])}
    return _assemble(out, lag_out, {}, ([], []), None, lam, T, batch, {"warmup": int(t0)})


# --------------------------------------------------------------------------- thin classes

class ChainLMMSE:
    """Algorithm C as an object: validates once, then ``filter``, ``smooth``, ``smooth_point``.

    See :func:`chain_lmmse` for the parameters and equations.
    """

    def __init__(self, system: DelayFadingSystem, prior: HistoryPrior, *, decorrelation: str = "optimal"):
        check_keywords({"decorrelation": decorrelation}, {"decorrelation": _DECORRELATION})
        check_instance(system, DelayFadingSystem, "system")
        system.check_prior(prior)
        _require_chain(system, prior)
        self.system, self.prior, self.decorrelation = system, prior, decorrelation

    def filter(self, y: Any, *, lags: Any = (), horizons: Any = (), fixed_point: int | None = None) -> DelayEstimates:
        return chain_lmmse(self.system, self.prior, y, decorrelation=self.decorrelation, lags=lags,
                           horizons=horizons, fixed_point=fixed_point)

    def smooth(self, y: Any) -> IntervalSmoothing:
        return smooth_interval(self.system, self.prior, y)

    def smooth_point(self, y: Any, j0: int):
        return smooth_point(self.system, self.prior, y, j0)


class AugmentedLMMSE:
    """Algorithm A as an object; see :func:`augmented_lmmse`."""

    def __init__(self, system: DelayFadingSystem, prior: HistoryPrior, *, window: int | None = None):
        check_instance(system, DelayFadingSystem, "system")
        system.check_prior(prior)
        self.system, self.prior, self.window = system, prior, window

    def filter(self, y: Any, *, lags: Any = ()) -> DelayEstimates:
        return augmented_lmmse(self.system, self.prior, y, window=self.window, lags=lags)


class ReorganizedInnovationLMMSE:
    """Algorithm D as an object; see :func:`reorganized_lmmse`."""

    def __init__(self, system: DelayFadingSystem, prior: HistoryPrior, *, decorrelation: str = "optimal"):
        check_keywords({"decorrelation": decorrelation}, {"decorrelation": _DECORRELATION})
        check_instance(system, DelayFadingSystem, "system")
        system.check_prior(prior)
        self.system, self.prior, self.decorrelation = system, prior, decorrelation

    def filter(self, y: Any) -> DelayEstimates:
        return reorganized_lmmse(self.system, self.prior, y, decorrelation=self.decorrelation)
