r"""Algorithm A of the delay family: the dense LMMSE on the augmented state X(t) = [x(t); ...; x(t-W)].

:class:`AugmentedLMMSE` / :func:`augmented_lmmse` take any joint prior and any lag structure at a
cost O(n³(W+1)³) per step; they are the reference the other two algorithms are tested against.
The model, the time convention and the code names of every delay estimator:
:mod:`tobitkf.filters.delay` (which also holds the pieces the three algorithms share).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import ValidationError
from ..models.delay import DelayFadingSystem, HistoryPrior
from ._backend import BACKENDS, use_compiled
from .core import (
    COVARIANCE_FORMS,
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
    _NO_LAYOUTS,
    _cached_layout,
    _check_lags,
    _compiled_gap,
    _DelayEstimator,
    _flat_views,
    _mult_sum,
    _solve_small,
    register_delay,
    second_moments,
)

__all__ = [
    "AugmentedLMMSE",
    "augmented_lmmse",
]


# --------------------------------------------------------------------------- Algorithm A


def _augmented_matrices(system: DelayFadingSystem, W: int):
    n, m, p, h, d = system.n, system.m, system.p, system.h, system.d
    B = W + 1
    NN = n * B
    AA = np.zeros((NN, NN))
    for lag, mat in system.lags.items():
        AA[:n, lag * n : (lag + 1) * n] += mat
    for k in range(W):
        AA[(k + 1) * n : (k + 2) * n, k * n : (k + 1) * n] = np.eye(n)
    Ai = np.zeros((h, NN, NN))
    Ai[:, :n, d * n : (d + 1) * n] = system.A_mult
    G = np.zeros((NN, p))
    G[:n] = system.Gamma
    HH = np.zeros((m, NN))
    HH[:, d * n : (d + 1) * n] = system.H
    # the constants of every step of _aug_step: 𝔊 Q_w 𝔊^T and (𝔊 S)^T (formed as it forms them)
    return AA, Ai, G, HH, G @ system.Qw @ G.T, (G @ system.S).T


def _aug_step(
    system: DelayFadingSystem, mats, X, P, LamX, y, t, form: str = "standard", S=None, compiled: bool = False
):
    """One reading of Algorithm A: the shared update of X(t|t-1) with y(t) and the decorrelated prediction.

    Update: H_eff = γ̄𝔥, noise R = σ²𝔥Λ_X𝔥^T + Q_v (the shared :func:`measurement_update`). Prediction:
    X(t+1|t) = Ā X(t|t) + J y(t), Ā = 𝔄 - γ̄J𝔥, J = 𝔊S R^{-1}, covariance Ā P Ā^T + Q_u - J R J^T, which
    equals the textbook predictor with same-time correlated noises (gain (γ̄𝔄P𝔥^T + 𝔊S)Q_ε^{-1}).
    ``form`` is the covariance form of the shared update and predict (with the factor ``S`` for
    ``"square_root"``); ``compiled`` runs them compiled where covered (one covariance per run). Returns ``(X(t|t), P(t|t), X(t+1|t), P(t+1|t), K, ε, Q_ε, Λ_X(t+1), S(t|t), S(t+1|t))``.
    """
    AA, Ai, G, HH, GQG, GS_T = mats
    gb, s2 = system.gamma_mean(t), system.gamma_var(t)
    # the model's products are of 2-D matrices (Λ_X, 𝔄, 𝔥, J, R): ndarray.dot, bitwise the products of @
    # at a fraction of its call overhead (the online step of one run forms about ten of them)
    R = symmetrize(s2 * HH.dot(LamX).dot(HH.T) + system.Qv)
    mp = MeasurementPrediction(expected=gb * (X @ HH.T), H0=gb * HH, noise=R[None])
    Xf, Pf, Sf, K, Qe = measurement_update(X, P, S, y, mp, form, compiled=compiled)
    if Qe is None:  # the square-root form does not form Q_ε
        Qe = symmetrize(gb * gb * (HH @ P @ HH.T) + R)
    eps = y - mp.expected
    q = system.q_mult(t)
    Qu = GQG + (_mult_sum(q, Ai, LamX) if q.size else 0.0)
    J = _solve_small(R, GS_T).T  # 𝔊 S R^{-1} (R symmetric)
    Abar = AA - gb * J.dot(HH)
    tr = Transition(A=Abar, Qd=symmetrize(Qu - J.dot(R).dot(J.T)), b=y @ J.T)
    Xp, Pp, Sp = time_update(Xf, Pf, Sf, tr, form, compiled=compiled)
    LamX = symmetrize(AA.dot(LamX).dot(AA.T) + Qu)
    return Xf, Pf, Xp, Pp, K, eps, Qe, LamX, Sf, Sp


def _blk(M: np.ndarray, i: int, j: int | None, n: int) -> np.ndarray:
    if j is None:
        return M[..., i * n : (i + 1) * n]
    return M[..., i * n : (i + 1) * n, j * n : (j + 1) * n]


class AugmentedLMMSE(_DelayEstimator):
    """Algorithm A, the dense augmented LMMSE (see :func:`augmented_lmmse`), as an estimator.

    Online ``init()``/``step(state, y_t)``; the state's internal vector is X̂(t|t) = x̂(t..t-W|t).

    Parameters
    ----------
    system : DelayFadingSystem
    prior : HistoryPrior
        Any joint prior of x(0), ..., x(-d).
    window : int >= d, optional
        W; default d.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        The covariance form of the shared update and predict; ``"square_root"`` carries a factor of the
        augmented covariance (not in the source; the chain and reorganized algorithms have their own
        covariance recursions for the older elements and keep the standard form).
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``"auto"`` runs a step of one covariance shared by the runs (every step from the prior) as one compiled
        call (:func:`tobitkf.filters._compiled_delay.aug_step`: the update, the decorrelated predict and
        Λ_X(t+1)) when numba imports, the form is ``"standard"`` and the fading and multiplicative-noise laws
        do not change with t; else the shared update and predict run compiled around the numpy moments. Equal
        to the numpy path to rounding (tested to 1e-12). ``"numpy"`` the reference path; ``"numba"`` raises
        :class:`~tobitkf.ValidationError` for the cases the whole-step kernel does not cover.
    """

    _name = "AugmentedLMMSE"
    _step_options = ("lags",)

    def __init__(
        self,
        system: DelayFadingSystem,
        prior: HistoryPrior,
        *,
        window: int | None = None,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        check_keywords(
            {"covariance_update": covariance_update, "backend": backend},
            {"covariance_update": ("standard", "joseph", "square_root"), "backend": BACKENDS},
        )
        self.covariance_update = covariance_update
        self.backend = backend
        self._setup(system, prior)
        d = system.d
        W = d if window is None else window
        if isinstance(W, bool) or not isinstance(W, (int, np.integer)) or W < d:
            raise ValidationError(f"window: expected an integer >= d = {d}, got {window!r}")
        self.window = int(W)
        self._mats = _augmented_matrices(system, self.window)
        gap = _compiled_gap(system)
        if gap is None and covariance_update != "standard":
            gap = f"covariance_update={covariance_update!r} (the whole-step kernel runs the standard form)"
        self._whole = None  # the compiled whole step and its constant arguments after (X, P, Λ_X, y)
        if use_compiled(backend, gap, "the augmented LMMSE's step"):
            from ._compiled_delay import aug_step

            AA, Ai, _, HH, GQG, GS_T = self._mats
            q = system.q_mult(0) if system.h else np.zeros(0)
            c = np.ascontiguousarray
            consts = (c(AA), c(Ai), c(q, dtype=float), c(HH), c(GQG), c(GS_T), c(system.Qv))
            self._whole = (aug_step, consts + (float(system.gamma_mean(0)), float(system.gamma_var(0))))

    def _state_dim(self) -> int:
        return self.n * (self.window + 1)

    def _initial(self, N, prior, P0, batch):
        n, d, W = self.n, self.system.d, self.window
        NN = n * (W + 1)
        m0 = np.zeros(NN)
        m0[: n * (d + 1)] = prior.mean.reshape(-1)
        P = np.zeros((NN, NN))
        P[: n * (d + 1), : n * (d + 1)] = prior.cov  # blocks beyond d: x(-k), k > d, do not exist (held at 0)
        return np.broadcast_to(m0, (N, NN)).copy(), P[None], {"LamX": P + np.outer(m0, m0)}

    def _step_arrays(self, t, x, P, S, carry, y, u, options=None):
        lags = (options or {}).get("lags", ())
        n, d = self.n, self.system.d
        if "next" in carry:
            Xpr, Ppr, Spr = carry["next"]
        else:
            Xpr, Ppr, Spr = x, P, S
        if self._whole is not None and Ppr.shape[0] == 1:  # one compiled call (a covariance shared by the runs)
            Xf, Xp, eps, Pf, Pp, Qe, LamX = _flat_views(*self._whole_compiled_step(Xpr, Ppr, carry, y))
            Sf = Sp = None
        else:
            form, fast = self.covariance_update, self._compiled_core()
            Xf, Pf, Xp, Pp, _, eps, Qe, LamX, Sf, Sp = _aug_step(
                self.system, self._mats, Xpr, Ppr, carry["LamX"], y, t, form, Spr, fast
            )
        N = x.shape[0]
        extras = self._aug_extras(carry, Xf, Pf, Xp, Pp, eps, Qe)
        if lags:  # the NaN rows of elements before x(-d)
            nan_m, nan_P = np.full((N, n), np.nan), np.full((1, n, n), np.nan)
        for L in lags:
            extras[f"lag{L}_mean"] = _blk(Xf, L, None, n) if t - L >= -d else nan_m
            extras[f"lag{L}_cov"] = _blk(Pf, L, L, n) if t - L >= -d else nan_P
        new = {"LamX": LamX, "next": (Xp, Pp, Sp), "lam": {t + 1: LamX[:n, :n]}}
        return Xf, Pf, Sf, new, Xpr, Ppr, extras

    def _aug_extras(self, carry, Xf, Pf, Xp, Pp, eps, Qe):
        n, d = self.n, self.system.d
        return {
            "measured_mean": _blk(Xf, d, None, n),
            "measured_cov": _blk(Pf, d, d, n),
            "next_mean": _blk(Xp, 0, None, n),
            "next_cov": _blk(Pp, 0, 0, n),
            "innovation": eps,
            "innovation_cov": Qe,
            "_lam": carry["LamX"][:n, :n][None],
        }

    def _whole_compiled_step(self, Xpr, Ppr, carry, y):
        """The compiled whole step (:func:`~tobitkf.filters._compiled_delay.aug_step`) from the prediction
        ``Xpr``, ``Ppr``: its flat output (the trace of P(t|t) last) and the layout of its arrays."""
        step, consts = self._whole
        N, nx = Xpr.shape
        m = self.m
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: ((N, nx), (N, nx), (N, m), (1, nx, nx), (1, nx, nx), (1, m, m), (nx, nx))
        )
        size, lay = lay
        buf = np.empty(size)
        # y contiguous whether a row of a record or one reading: numba types a strided array apart (one compile more)
        step(Xpr, Ppr[0], carry["LamX"], np.ascontiguousarray(y), *consts, buf)
        return buf, lay

    def _whole_online(self, state, y):
        """:meth:`_step_arrays`' compiled branch as the online step (no lags)."""
        t, carry = state.k + 1, state.carry
        Xpr, Ppr, _ = carry["next"] if "next" in carry else (state.x, state.P, None)
        buf, lay = self._whole_compiled_step(Xpr, Ppr, carry, y)
        if not math.isfinite(buf[-1]):
            return None
        Xf, Xp, eps, Pf, Pp, Qe, LamX = _flat_views(buf, lay)
        n = self.n
        new = {"LamX": LamX, "next": (Xp, Pp, None), "lam": {t + 1: LamX[:n, :n]}}
        extras = self._aug_extras(carry, Xf, Pf, Xp, Pp, eps, Qe)
        return step_state(t, state.batch_shape, Xf, Pf, n, None, new, extras)

    def _whole_takes(self, state, options):
        P = state.carry["next"][1] if "next" in state.carry else state.P
        return self._whole is not None and P.shape[0] == 1 and not options.get("lags")

    def _prepare_step_options(self, state, options):
        if not options:  # the plain online step: nothing to check
            return {"lags": ()}
        lags = _check_lags(options.get("lags", ()), "lags", 0)
        if any(L > self.window for L in lags):
            raise ValidationError(f"lags: expected lags <= window W = {self.window}, got {max(lags)}")
        return {"lags": lags}

    def filter(  # type: ignore[override]  # the delay family: a prior of its own and lag options
        self, y: Any, *, lags: Any = (), prior: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        """Run Algorithm A over ``y`` (..., T, m); see :func:`augmented_lmmse`."""
        res = self._run_delay(y, prior, state, outputs, self._prepare_step_options(None, {"lags": lags}))
        Xp, Pp, _ = res.final.carry["next"]
        batch = np.shape(y)[:-2]
        res.extras["final_mean"] = Xp.reshape(batch + Xp.shape[1:])
        res.extras["final_cov"] = Pp[0]
        res.extras["window"] = self.window
        return res


def augmented_lmmse(
    system: DelayFadingSystem, prior: HistoryPrior, y: Any, *, window: int | None = None, lags: Any = ()
) -> FilterResult:
    r"""Algorithm A: dense LMMSE on the augmented state X(t) = [x(t); ...; x(t-W)] (state augmentation, ours).

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
    FilterResult
        ``extras["final_mean"]`` (..., n(W+1)) and ``extras["final_cov"]`` (n(W+1), n(W+1)):
        X̂(T|T-1), i.e. x̂(T-k|T-1) for k = 0..W. With W = T + d this is the fixed-interval
        smoother of every element x(-d)..x(T) (the oracle for :func:`smooth_interval`).

    Raises
    ------
    ValidationError
        ``window`` < d or a lag outside [0, W].
    """
    return AugmentedLMMSE(system, prior, window=window).filter(y, lags=lags)


def _augmented_second_moments(system: DelayFadingSystem, prior: HistoryPrior, T: int) -> dict[int, np.ndarray]:
    if system.is_pure_delay:
        return second_moments(system, prior, T)
    # generic lags: propagate the joint second moment of [x(t); ...; x(t-d)]
    n, d = system.n, system.d
    AA, Ai, G, *_ = _augmented_matrices(system, d)
    m0 = prior.mean.reshape(-1)
    LamX = prior.cov + np.outer(m0, m0)
    lam = {0: LamX[:n, :n]}
    for t in range(T):
        q = system.q_mult(t)
        Qu = G @ system.Qw @ G.T + (_mult_sum(q, Ai, LamX) if q.size else 0.0)
        LamX = symmetrize(AA @ LamX @ AA.T + Qu)
        lam[t + 1] = LamX[:n, :n]
    return lam


register_delay(
    AugmentedLMMSE,
    "exact LMMSE on the augmented delay state (Li, Li & Wang 2018)",
    {"window": int, "covariance_update": COVARIANCE_FORMS},
)
