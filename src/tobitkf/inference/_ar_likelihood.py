r"""Exact likelihood and posterior of a censored regression with autoregressive errors: the data, the
quadrature plan and the forward-backward recursion behind :class:`tobitkf.inference.censored_ar.CensoredAR`.

Model (the censored regression with AR(p) errors of ARCensReg and carx; Schumacher, Lachos & Dey
2017; Wang & Chan 2017), for t = 1..T:

.. math::

    y^*_t = x_t^T\beta + \xi_t, \qquad \xi_t = \phi_1\xi_{t-1} + \dots + \phi_p\xi_{t-p} + e_t, \qquad
    e_t \sim N(0, \sigma^2),

:math:`\xi` stationary from the start; the reading is :math:`y_t = y^*_t` when uncensored (observed
exactly: a state-space model with R = 0), the limit when censored (:math:`y^*_t \le l_t` left,
:math:`y^*_t \ge h_t` right), or missing.

Exact likelihood by a quadrature (point-mass) recursion. With :math:`S_t` the set the data allow for
:math:`\xi_t` (a point :math:`y_t - x_t^T\beta`, a half-line at the limit, or the line when missing),

.. math::

    L = \int \prod_{t=1}^T p(\xi_t \mid \xi_{t-1}, \dots, \xi_{t-p})\,\mathbf 1\{\xi_t \in S_t\}\,d\mu_t(\xi_t),

:math:`\mu_t` the counting measure at a point and Lebesgue measure otherwise;
:math:`p(\xi_t \mid \cdot) = N(\sum_i a_{t,i}\xi_{t-i}, v_t)` with :math:`a_t = \phi`,
:math:`v_t = \sigma^2` for t > p and the stationary (Durbin–Levinson) predictors for t <= p. The
forward recursion over the joint of the last p values,

.. math::

    \alpha_t(\xi_t, \dots, \xi_{t-p+1}) = \mathbf 1\{\xi_t \in S_t\}\int p(\xi_t \mid \xi_{t-1..t-p})\,
      \alpha_{t-1}(\xi_{t-1}, \dots, \xi_{t-p})\,d\xi_{t-p}, \qquad L = \int\alpha_T,

is evaluated with composite Gauss–Legendre rules on each censored or missing :math:`S_t` (panels no
wider than the innovation standard deviation, ``nodes`` per panel) cut to
[anchors - K sd, anchors + K sd], the anchors being the exactly observed neighbours of the run, 0 and
the limit, sd the stationary standard deviation and K = ``span``: exact to the quadrature's
accuracy (the log-likelihood of the real data sets converges to 1e-9 as the rule is refined, tested).
Cost O(T M^{p+1}) for M nodes per censored step; an exactly observed step costs O(M^p).

Within one maximisation the number of panels of each step is held fixed (the :class:`GridPlan`), so
the quadrature nodes move smoothly with the parameters and the computed log-likelihood is a smooth
function of them (finite-difference gradients and Hessians work); the plan is refreshed between
passes until it no longer changes.

The posterior of every :math:`\xi_t` (:func:`posterior_moments`) follows from the backward
recursion on the same nodes (a forward–backward smoother exact to the quadrature).

Parameter names: ``beta`` (l,), ``sigma2`` :math:`\sigma^2`, ``phi`` (p,).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .._compiled import numba_available
from .._progress import plural
from .._validation import ShapeError, ValidationError, as_float_array, check_memory, check_scale
from ._ar_process import ar_autocovariance, ar_predictors, is_stationary
from ._common import LOG_2PI, censoring_sides

__all__ = ["CensoredARData", "GridPlan", "plan_grid", "exact_log_likelihood", "posterior_moments"]


_GL_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}
#: default quadrature: Gauss-Legendre nodes per panel, cut in standard deviations, panel width in sd
NODES, SPAN, PANEL_SD, HERMITE = 8, 8.0, 1.5, 16


def _gauss_hermite(H: int):
    key = -H
    if key not in _GL_CACHE:
        _GL_CACHE[key] = np.polynomial.hermite.hermgauss(H)
    return _GL_CACHE[key]


def _gauss_legendre(G: int):
    if G not in _GL_CACHE:
        _GL_CACHE[G] = np.polynomial.legendre.leggauss(G)
    return _GL_CACHE[G]


# --------------------------------------------------------------------------- data


@dataclass(frozen=True, eq=False)
class CensoredARData:
    r"""Validated data of a censored regression with AR errors.

    Parameters
    ----------
    y : (T,) array_like
        Readings; censored ones hold their limit; NaN = missing.
    X : (T, l) array_like, optional
        Regressors (default: a column of ones, the mean).
    lower, upper : float or (T,) array_like, optional
        Limits (default none: -inf / +inf).
    censored : (T,) bool array_like, optional
        The recorded indicator (default: the limit rule).

    Raises
    ------
    ShapeError
        Lengths do not agree.
    ValidationError
        Non-finite regressors, a reading outside its limits, an inconsistent indicator.
    """

    y: np.ndarray
    X: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    side: np.ndarray

    @classmethod
    def build(
        cls, y: Any, X: Any = None, lower: Any = -np.inf, upper: Any = np.inf, censored: Any = None, rtol: float = 1e-12
    ) -> CensoredARData:
        y = as_float_array(y, "y", ndim=1, allow_nan=True)
        check_scale(y, "y")  # a reading whose square overflows is refused by name, as the filters do
        T = y.size
        if T < 1:
            raise ShapeError("y: expected at least one reading")
        X = np.ones((T, 1)) if X is None else as_float_array(X, "X", ndim=(1, 2))
        if X.ndim == 1:
            X = X[:, None]
        if X.shape[0] != T:
            raise ShapeError(f"X: expected {T} rows (one per reading), got shape {X.shape}")
        lo = (
            np.broadcast_to(as_float_array(lower, "lower", ndim=(0, 1), allow_inf=True), (T,)).copy()
            if np.ndim(lower) == 0 or np.shape(lower) == (T,)
            else None
        )
        hi = (
            np.broadcast_to(as_float_array(upper, "upper", ndim=(0, 1), allow_inf=True), (T,)).copy()
            if np.ndim(upper) == 0 or np.shape(upper) == (T,)
            else None
        )
        if lo is None or hi is None:
            raise ShapeError(
                f"lower/upper: expected scalars or ({T},) arrays, got {np.shape(lower)} and {np.shape(upper)}"
            )
        if not (lo < hi).all():
            raise ValidationError("lower/upper: expected lower < upper for every reading")
        with np.errstate(invalid="ignore"):
            bad = (y < lo - 1e-9 * np.maximum(1, np.abs(np.where(np.isfinite(lo), lo, 0)))) | (
                y > hi + 1e-9 * np.maximum(1, np.abs(np.where(np.isfinite(hi), hi, 0)))
            )
        if bad.any():
            i = int(np.argmax(bad))
            raise ValidationError(
                f"y: reading {y[i]:.6g} at index {i} lies outside its limits [{lo[i]:.6g}, {hi[i]:.6g}]"
            )
        flags = (
            None if censored is None else np.asarray(censored).reshape(-1, 1) if np.size(censored) == T else censored
        )
        if flags is not None and np.size(flags) == T:
            with np.errstate(invalid="ignore"):
                inside = np.asarray(flags, dtype=bool).reshape(-1) & (y > lo) & (y < hi) & np.isfinite(lo + hi)
            if inside.any():
                i = int(np.flatnonzero(inside)[0])
                raise ValidationError(
                    f"censored: reading {i} is an interval reading (flagged, inside [{lo[i]:.6g}, {hi[i]:.6g}]), which "
                    "the censored AR model's exact likelihood does not take; fit a state-space model (tk.fit with "
                    "a LinearSystem template or a map theta -> LinearSystem) for interval readings"
                )
        side = censoring_sides(y[:, None], lo[:, None], hi[:, None], flags, rtol=rtol)[:, 0]
        return cls(y=y, X=X, lower=lo, upper=hi, side=side)

    @property
    def T(self) -> int:
        return int(self.y.size)

    @property
    def observed(self) -> np.ndarray:
        """(T,) bool: readings observed exactly (present and not censored)."""
        return (self.side == 0) & ~np.isnan(self.y)


# --------------------------------------------------------------------------- the grid


@dataclass(frozen=True)
class GridPlan:
    """The quadrature of every step: ``panels[t]`` Gauss-Legendre panels of ``nodes`` nodes (0: an
    exactly observed step, one node; -1: ``hermite`` Gauss-Hermite nodes), the cut ``span``."""

    panels: tuple[int, ...]
    nodes: int
    span: float
    hermite: int = 0

    def counts(self) -> np.ndarray:
        """(T,) number of nodes of each step."""
        p = np.array(self.panels, dtype=np.int64)
        return np.where(p > 0, p * self.nodes, np.where(p < 0, self.hermite, 1)).astype(np.int64)

    def total_nodes(self) -> int:
        return int(self.counts().sum())


def _runs(data: CensoredARData) -> list[tuple[int, int]]:
    """Maximal runs [s, e) of steps that are not observed exactly (vectorised: O(T) numpy, no Python loop
    over the steps)."""
    s, e = _run_bounds(data.observed)
    return list(zip(s.tolist(), e.tolist()))


def _run_bounds(observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starts and ends (exclusive) of the maximal runs of False in ``observed``."""
    edge = np.diff(np.concatenate([[1], observed.astype(np.int8), [1]]))
    return np.flatnonzero(edge == -1), np.flatnonzero(edge == 1)


class _RunGroup(NamedTuple):
    """Runs of non-observed steps that share their length, their anchors' offsets and purity: the
    Gaussian conditional of their values given the anchors has the same weights for all of them."""

    length: int
    anchors: np.ndarray  # (a,) offsets of the anchors from the run's start (negative: before it)
    pure: bool
    starts: np.ndarray  # (k,) the runs' first steps


def _structure(data: CensoredARData, p: int) -> list[_RunGroup]:
    """The runs of non-observed steps grouped by (length, anchor offsets, pure), computed once per data
    set and order. The anchors of a run are the exactly observed steps within p of it. Memory O(T):
    nothing is stored per pair of steps of a run, so one censored run as long as the record costs no
    more than T scattered ones."""
    cache = data.__dict__.setdefault("_structure_cache", {})
    if p not in cache:
        obs = data.observed
        T = data.T
        starts, ends = _run_bounds(obs)
        cens = np.concatenate([[0], np.cumsum(data.side != 0)])
        pure = (cens[ends] - cens[starts]) == 0
        keys: dict[tuple, list[int]] = {}
        for s, e, pu in zip(starts.tolist(), ends.tolist(), pure.tolist()):
            before = tuple(t - s for t in range(max(0, s - p), s) if obs[t])
            after = tuple(t - s for t in range(e, min(T, e + p)) if obs[t])
            keys.setdefault((e - s, before + after, pu), []).append(s)
        cache[p] = [
            _RunGroup(L, np.array(off, dtype=np.int64), bool(pu), np.array(st, dtype=np.int64))
            for (L, off, pu), st in keys.items()
        ]
    return cache[p]


def _intervals(data: CensoredARData, beta, sigma2, phi, span: float):
    r"""Per step: the Gaussian conditional :math:`N(m_t, s_t^2)` of :math:`\xi_t` given the exactly observed
    values within p steps of its run (censoring ignored) and the quadrature interval ``[lo, hi]``.

    The interval is ``span`` standard deviations :math:`s_t` either side of :math:`m_t`, cut at the limit
    (a censored posterior is that Gaussian truncated to the censored box, so its mass outside is at
    most :math:`2\Phi(-K)/P(\text{box})`). ``width`` is the panel width scale: the smaller of
    :math:`s_t` and :math:`\sigma/\max(1, |\phi|)`, the scale on which the transition kernel varies.
    Exactly observed steps get NaN. ``pure`` marks the steps of runs without a censored reading (only
    missing ones), whose posterior given the neighbours is Gaussian.

    The conditional weights depend only on the lags, so runs of the same shape (:class:`_RunGroup`)
    share one solve: the cost is one small solve per shape plus O(T) arithmetic.

    Returns
    -------
    m, s, lo, hi, width : (T,) ndarrays ; pure : (T,) bool
    """
    p = len(phi)
    mu = data.X @ beta
    xi = data.y - mu
    kern = float(np.sqrt(sigma2)) / max(1.0, float(np.max(np.abs(phi), initial=0.0)))
    T = data.T
    m = np.full(T, np.nan)
    sd = np.full(T, np.nan)
    pure = np.zeros(T, dtype=bool)
    groups = _structure(data, p)
    longest = max((gr.length for gr in groups), default=0)
    g = ar_autocovariance(phi, sigma2, longest + 2 * p + 1)
    for L, anc, is_pure, starts in groups:
        ro = np.arange(L)
        idx = (starts[:, None] + ro[None, :]).ravel()
        if anc.size:
            Gra = g[np.abs(ro[:, None] - anc[None, :])]
            W = np.linalg.solve(g[np.abs(anc[:, None] - anc[None, :])], Gra.T).T  # (L, a)
            m[idx] = (xi[starts[:, None] + anc[None, :]] @ W.T).ravel()
            v = g[0] - np.einsum("ij,ij->i", W, Gra)
        else:
            m[idx] = 0.0
            v = np.full(L, g[0])
        sd[idx] = np.tile(np.sqrt(np.maximum(v, 1e-300)), starts.size)
        pure[idx] = is_pure
    side = data.side
    lower = np.where(side < 0, data.lower - mu, np.nan)
    upper = np.where(side > 0, data.upper - mu, np.nan)
    lo = np.where(side < 0, np.fmin(m, lower) - span * sd, np.where(side > 0, upper, m - span * sd))
    hi = np.where(side < 0, lower, np.where(side > 0, np.fmax(m, upper) + span * sd, m + span * sd))
    width = np.minimum(sd, kern)
    return m, sd, lo, hi, width, pure


def plan_grid(
    data: CensoredARData,
    beta,
    sigma2,
    phi,
    *,
    nodes: int = NODES,
    span: float = SPAN,
    panel_sd: float = PANEL_SD,
    hermite: int = HERMITE,
) -> GridPlan:
    """The quadrature of every step at these parameters: Gauss-Legendre panels no wider than ``panel_sd``
    times the step's width scale (see :func:`_intervals`) for censored steps; ``hermite``
    Gauss-Hermite nodes on the Gaussian conditional for the steps of runs of missing readings only
    (0: Gauss-Legendre for those too)."""
    phi = np.asarray(phi, float)
    _, _, lo, hi, width, pure = _intervals(data, np.asarray(beta, float), float(sigma2), phi, span)
    with np.errstate(invalid="ignore", over="ignore"):
        n = np.ceil((hi - lo) / (panel_sd * width))
    n = np.where(np.isfinite(n) | np.isnan(n), n, 2.0**62)
    panels = np.where(np.isnan(n), 0, np.clip(n, 1, 2**62)).astype(np.int64)
    if hermite:
        panels = np.where(pure, -1, panels)
    counts = np.where(panels > 0, panels * int(nodes), np.where(panels < 0, int(hermite), 1))
    _check_plan_size(counts, phi.size)
    return GridPlan(panels=tuple(panels.tolist()), nodes=int(nodes), span=float(span), hermite=int(hermite))


class _PlanTooLarge(ValidationError):
    """A step's quadrature would need more nodes than the recursion can afford (parameters far from
    the data: a search that runs away)."""


#: most nodes of one step: the recursion costs O(M^(p+1)) per step and holds M^p values
_MAX_STEP_WORK = 2.0**32


def _check_plan_size(counts: np.ndarray, p: int) -> None:
    r"""Refuse, before anything is allocated, a quadrature whose one step costs more than
    :data:`_MAX_STEP_WORK` kernel evaluations, or whose nodes (about 48 bytes each with the
    temporaries of :func:`_node_arrays`) and recursion arrays (:math:`M^{\max(p, 1)}` values, three
    copies) do not fit in memory."""
    if counts.size == 0:
        return
    t = int(np.argmax(counts))
    M = int(counts[t])
    if float(M) ** (max(p, 1) + 1) > _MAX_STEP_WORK:
        raise _PlanTooLarge(
            f"y: the quadrature of reading {t} would need {M} nodes at these parameters (its censored "
            f"interval spans that many kernel widths); the recursion cannot afford it"
        )
    check_memory(48 * int(counts.sum()) + 24 * M ** max(p, 1), "y", "the quadrature nodes of the likelihood")


#: records longer than this start the search on a subsample (:meth:`CensoredAR.fit`)
_WARM_T = 20_000
#: the search's tolerance (standard errors) when Newton steps on the model's rule follow it
_SEARCH_GTOL = 0.01


def _subsample(data: CensoredARData, pieces: int = 10, length: int = 1000) -> CensoredARData:
    """``pieces`` stretches of ``length`` readings spread evenly over the record, joined by one missing
    reading each (a start for the search on a long record, not a likelihood of the record)."""
    T = data.T
    starts = np.unique(np.linspace(0, T - length, pieces).round().astype(np.int64))
    ys: list[np.ndarray] = []
    Xs: list[np.ndarray] = []
    los: list[np.ndarray] = []
    his: list[np.ndarray] = []
    sides: list[np.ndarray] = []
    for k, s0 in enumerate(starts.tolist()):
        sl = slice(s0, s0 + length)
        if k:
            ys.append(np.full(1, np.nan))
            Xs.append(np.zeros((1, data.X.shape[1])))
            los.append(np.full(1, -np.inf))
            his.append(np.full(1, np.inf))
            sides.append(np.zeros(1, dtype=data.side.dtype))
        ys.append(data.y[sl])
        Xs.append(data.X[sl])
        los.append(data.lower[sl])
        his.append(data.upper[sl])
        sides.append(data.side[sl])
    return CensoredARData(
        y=np.concatenate(ys),
        X=np.concatenate(Xs),
        lower=np.concatenate(los),
        upper=np.concatenate(his),
        side=np.concatenate(sides),
    )


def _check_information(data: CensoredARData) -> None:
    """Refuse data whose likelihood has no maximum: nothing present; no reading observed exactly (with
    only censored readings the likelihood grows without bound as the mean moves past the limits); or,
    without censored readings, exact readings that the regressors fit without error (the likelihood
    grows without bound as the innovation variance goes to zero)."""
    present = ~np.isnan(data.y)
    if not present.any():
        raise ValidationError(
            f"y: {'the one reading is' if data.T == 1 else f'all {data.T} readings are'} missing (NaN): there is nothing to fit"
        )
    obs = data.observed
    n_exact = int(obs.sum())
    n_cens = int((present & (data.side != 0)).sum())
    if n_exact == 0:
        raise ValidationError(
            f"y: no reading is observed exactly (of the {plural(int(present.sum()), 'reading')} present, all are "
            "censored at their limits), so the likelihood has no maximum: it keeps growing as the mean moves past the "
            "limits; the fit needs exactly observed readings"
        )
    if n_cens == 0:
        Xo, yo = data.X[obs], data.y[obs]
        coef = np.linalg.lstsq(Xo, yo, rcond=None)[0]
        scale = max(1.0, float(np.max(np.abs(yo))))
        if float(np.max(np.abs(yo - Xo @ coef))) <= 1e-12 * scale:
            raise ValidationError(
                f"y: the regressors fit the {plural(n_exact, 'exactly observed reading')} without error (for example, readings that "
                "are all equal with an intercept), so the innovation variance has no positive estimate "
                "and the likelihood no maximum"
            )


def _node_arrays(data: CensoredARData, beta, sigma2, phi, plan: GridPlan):
    r"""Quadrature nodes and log weights of every step, concatenated: ``(z, lw, start, count)``.

    Step t holds ``z[start[t]:start[t] + count[t]]``; an exactly observed step is the one node
    :math:`y_t - x_t^T\beta` with log weight 0; a censored step the composite Gauss-Legendre rule of
    ``plan.panels[t]`` panels of ``plan.nodes`` nodes on its interval; a step of a run of missing
    readings (``panels[t] = -1``) the Gauss-Hermite rule of its Gaussian conditional
    :math:`N(m_t, s_t^2)`, :math:`\int f = \sqrt2 s_t\sum_i w_ie^{x_i^2}f(m_t + \sqrt2 s_tx_i)`.
    """
    m, sd, lo, hi, _, _ = _intervals(data, beta, sigma2, phi, plan.span)
    mu = data.X @ beta
    G = plan.nodes
    x, w = _gauss_legendre(G)
    panels = np.array(plan.panels, dtype=np.int64)
    count = plan.counts()
    start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    z = np.empty(int(count.sum()))
    lw = np.zeros_like(z)
    pts = panels == 0
    z[start[pts]] = (data.y - mu)[pts]
    reg = np.flatnonzero(panels > 0)
    if reg.size and numba_available():
        from . import _compiled_ar as K

        K.fill_legendre(z, lw, start[reg], panels[reg], lo[reg], hi[reg], x, w)
    elif reg.size:
        P = panels[reg]
        h = (hi[reg] - lo[reg]) / P
        step_of_panel = np.repeat(np.arange(reg.size), P)
        idx_in_step = np.arange(P.sum()) - np.repeat(np.cumsum(P) - P, P)
        hp = h[step_of_panel]
        base = lo[reg][step_of_panel] + hp * idx_in_step
        zz = base[:, None] + 0.5 * hp[:, None] * (x + 1.0)[None, :]
        ww = np.log(0.5 * hp[:, None] * w[None, :])
        n = P * G
        pos = np.repeat(start[reg], n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
        z[pos] = zz.ravel()
        lw[pos] = ww.ravel()
    her = np.flatnonzero(panels < 0)
    if her.size:
        xh, wh = _gauss_hermite(plan.hermite)
        H = plan.hermite
        pos = (start[her][:, None] + np.arange(H)[None, :]).ravel()
        z[pos] = (m[her][:, None] + np.sqrt(2.0) * sd[her][:, None] * xh[None, :]).ravel()
        lw[pos] = (np.log(np.sqrt(2.0) * sd[her])[:, None] + (np.log(wh) + xh * xh)[None, :]).ravel()
    return z, lw, start, count


# --------------------------------------------------------------------------- recursion


class Posterior(NamedTuple):
    """Posterior moments of the AR errors (:func:`posterior_moments`)."""

    mean: np.ndarray
    var: np.ndarray
    filtered_mean: np.ndarray
    filtered_var: np.ndarray
    loglik: float


def _lse(a: np.ndarray, axis: int) -> np.ndarray:
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(a - m), axis=axis)) + np.squeeze(m, axis=axis)
    return out


def _check_params(data: CensoredARData, beta, sigma2, phi):
    beta = np.asarray(beta, dtype=float).ravel()
    phi = np.asarray(phi, dtype=float).ravel()
    if beta.size != data.X.shape[1]:
        raise ShapeError(f"beta: expected {data.X.shape[1]} coefficients (columns of X), got {beta.size}")
    if not (np.isfinite(sigma2) and sigma2 > 0):
        raise ValidationError(f"sigma2: expected a positive innovation variance, got {sigma2!r}")
    if not is_stationary(phi):
        raise ValidationError(f"phi: expected stationary AR coefficients, got {phi.tolist()}")
    return beta, float(sigma2), phi


def _forward(data: CensoredARData, beta, sigma2, phi, plan: GridPlan, keep: bool = False):
    """Forward recursion in the log domain; returns (loglik, per-step records for the backward pass or None).

    ``la`` (log alpha, normalised to max 0) has the axes (t, t-1, ..., t-r+1), r = min(t+1, p) values.
    """
    p = phi.size
    preds = ar_predictors(phi, sigma2) if p > 0 else [(np.zeros(0), float(sigma2))]
    z_all, lw_all, start, count = _node_arrays(data, beta, sigma2, phi, plan)
    la: Any = None  # log alpha once the first step is done
    zs: list[np.ndarray] = []  # nodes of the axes of la, newest first
    total = 0.0
    kept: list[tuple] | None = [] if keep else None
    for t in range(data.T):
        a, v = preds[min(t, p)]
        z, lw = z_all[start[t] : start[t] + count[t]], lw_all[start[t] : start[t] + count[t]]
        q = a.size  # earlier values the transition uses (= axes of la)
        if q == 0:
            lK = -0.5 * (LOG_2PI + np.log(v) + z * z / v)
            new = lw + lK
            la_prev = None
        else:
            lK = None
            if lK is None:
                mean: Any = 0.0
                for i in range(q):
                    shape = [1] * q
                    shape[i] = zs[i].size
                    mean = mean + a[i] * zs[i].reshape(shape)
                d = z.reshape((-1,) + (1,) * q) - mean[None]
                lK = -0.5 * (LOG_2PI + np.log(v) + d * d / v)
            new = lK + la[None]
            if q == p:
                new = _lse(new, axis=-1)  # integrate out xi_{t-p}
            new = new + lw.reshape((-1,) + (1,) * (new.ndim - 1))
            la_prev = la
        c = float(np.max(new))
        if not np.isfinite(c):
            return -np.inf, None
        if p == 0:  # independent errors: nothing carried
            total += c + float(_lse(new - c, axis=0))
            if kept is not None:
                kept.append((lK, None, new - c, lw, [z]))
            la = None
            continue
        la = new - c
        total += c
        zs = ([z] + zs)[:p]
        if kept is not None:
            kept.append((lK, la_prev, la, lw, zs[:]))
    if p == 0:
        return total, kept
    return total + float(_lse(la.ravel(), axis=0)), kept


def _log_likelihood(data, beta, sigma2, phi, plan: GridPlan, backend: str = "auto") -> float:
    """The forward recursion: the compiled kernel for p = 1, 2 (when numba imports), else numpy."""
    p = phi.size
    if backend != "numpy" and p in (1, 2) and numba_available():
        from . import _compiled_ar as K

        z, lw, start, count = _node_arrays(data, beta, sigma2, phi, plan)
        preds = ar_predictors(phi, sigma2)
        T = data.T
        a = np.zeros((T, 2))
        a[:, :p] = phi
        v = np.full(T, float(sigma2))
        for t in range(min(p, T)):
            at, vt = preds[t]
            a[t] = 0.0
            a[t, : at.size] = at
            v[t] = vt
        if p == 1:
            return float(K.forward_ar1(z, lw, start, count, np.ascontiguousarray(a[:, 0]), v))
        return float(
            K.forward_ar2(z, lw, start, count, np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1]), v)
        )
    ll, _ = _forward(data, beta, sigma2, phi, plan)
    return float(ll)


def exact_log_likelihood(
    data: CensoredARData,
    beta: Any,
    sigma2: float,
    phi: Any,
    *,
    plan: GridPlan | None = None,
    nodes: int = NODES,
    span: float = SPAN,
) -> float:
    r"""The exact log-likelihood (to quadrature accuracy) of the censored regression with AR(p) errors.

    Parameters
    ----------
    data : CensoredARData
    beta : (l,) array_like
    sigma2 : float > 0
        Innovation variance :math:`\sigma^2`.
    phi : (p,) array_like
        Stationary AR coefficients (p = 0: independent errors).
    plan : GridPlan, optional
        Fixed panel counts (default: :func:`plan_grid` at these parameters).
    nodes, span : int, float
        Gauss–Legendre nodes per panel and the cut in stationary standard deviations (module docstring).

    Returns
    -------
    float
        With all constants; missing readings integrated out; ``-inf`` when the data have zero probability.

    Raises
    ------
    ShapeError, ValidationError
        Wrong number of coefficients, :math:`\sigma^2 \le 0`, non-stationary ``phi``.

    Examples
    --------
    Without censoring it is the Gaussian log-likelihood of a stationary AR(1):

    >>> import numpy as np
    >>> from tobitkf.inference.censored_ar import CensoredARData, exact_log_likelihood
    >>> y = np.array([0.3, -0.2, 0.5])
    >>> d = CensoredARData.build(y)
    >>> G = 1.0 / (1 - 0.25) * 0.5 ** np.abs(np.subtract.outer(range(3), range(3)))
    >>> ref = -0.5 * (3 * np.log(2 * np.pi) + np.linalg.slogdet(G)[1] + y @ np.linalg.solve(G, y))
    >>> bool(np.isclose(exact_log_likelihood(d, [0.0], 1.0, [0.5]), ref))
    True
    """
    beta, sigma2, phi = _check_params(data, beta, sigma2, phi)
    if plan is None:
        plan = plan_grid(data, beta, sigma2, phi, nodes=nodes, span=span)
    elif len(plan.panels) != data.T:
        raise ShapeError(f"plan: expected panel counts for {data.T} steps, got {len(plan.panels)}")
    return float(_log_likelihood(data, beta, sigma2, phi, plan))


def posterior_moments(
    data: CensoredARData,
    beta: Any,
    sigma2: float,
    phi: Any,
    *,
    plan: GridPlan | None = None,
    nodes: int = NODES,
    span: float = SPAN,
):
    r"""Exact (to quadrature) posterior mean and variance of every :math:`\xi_t` given all the data.

    Forward–backward on the quadrature nodes of :func:`exact_log_likelihood`: the backward message
    :math:`\beta_t(\xi_t, \dots, \xi_{t-p+1}) = \int p(\xi_{t+1} \mid \cdot)\,\beta_{t+1}\,d\mu_{t+1}`,
    the marginal :math:`p(\xi_t \mid y_{1:T}) \propto \sum \alpha_t\beta_t`. The latent reading's
    posterior mean is :math:`x_t^T\beta + E[\xi_t \mid y_{1:T}]` (exact readings: the reading itself).

    Returns
    -------
    Posterior
        ``mean``, ``var`` (T,): smoothed :math:`E[\xi_t \mid y_{1:T}]` and variance; ``filtered_mean``,
        ``filtered_var`` (T,): :math:`E[\xi_t \mid y_{1:t}]` and variance (the forward marginals);
        ``loglik``.
    """
    beta, sigma2, phi = _check_params(data, beta, sigma2, phi)
    if plan is None:
        plan = plan_grid(data, beta, sigma2, phi, nodes=nodes, span=span)
    p = phi.size
    ll, kept = _forward(data, beta, sigma2, phi, plan, keep=True)
    T = data.T
    mean, var, fmean, fvar = np.empty(T), np.empty(T), np.empty(T), np.empty(T)
    if not np.isfinite(ll):
        for a in (mean, var, fmean, fvar):
            a[:] = np.nan
        return Posterior(mean, var, fmean, fvar, ll)
    for t in range(T):
        la_t, z = kept[t][2], kept[t][4][0]
        lm = _lse(la_t.reshape(la_t.shape[0], -1), axis=1) if la_t.ndim > 1 else la_t
        w = np.exp(lm - np.max(lm))
        w /= w.sum()
        fmean[t] = w @ z
        fvar[t] = max(w @ (z - fmean[t]) ** 2, 0.0)
    lb = np.zeros_like(kept[-1][2])  # log beta_T over the axes of la_T
    for t in range(T - 1, -1, -1):
        lK_t, la_prev, la_t, lw_t, zs_t = kept[t]
        post = la_t + lb
        # marginal of xi_t: axis 0
        lm = _lse(post.reshape(post.shape[0], -1), axis=1) if post.ndim > 1 else post
        w = np.exp(lm - np.max(lm))
        w /= w.sum()
        z = zs_t[0]
        mean[t] = w @ z
        var[t] = max(w @ (z - mean[t]) ** 2, 0.0)
        if t == 0:
            break
        # backward message to t-1: lb_{t-1}(axes of la_{t-1}) = lse over xi_t of lK + lw + lb_t
        if p == 0:  # independent errors: the steps do not talk to each other
            lb = np.zeros_like(kept[t - 1][2])
            continue
        q = lK_t.ndim - 1
        msg = lb + lw_t.reshape((-1,) + (1,) * (lb.ndim - 1))
        if q == p:
            # lb_t has axes (t, ..., t-p+1); the kernel (t, t-1, ..., t-p); la_prev (t-1, ..., t-p)
            joint = lK_t + msg[..., None]
        else:
            # nothing was integrated out: la_t has the kernel's axes (t, t-1, ..., t-q)
            joint = lK_t + msg
        lb = _lse(joint, axis=0)
        lb = lb - np.max(lb)
    return Posterior(mean, var, fmean, fvar, float(ll))
