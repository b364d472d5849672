r"""Optimal linear filter, predictor and smoothers for pure-delay systems with fading measurements.

Source: Y. Li, J. Li, X. Wang (2018), "Optimal linear estimators for time-delay systems with
fading measurements and correlated noises", J. Electrical and Computer Engineering 2018; our deviations:
docs/sources/li2018-delay.md.
Model (1)–(3) in :mod:`tobitkf.models.delay`. All estimators are the affine LMMSE
(projection on span{1, y(0..t)}) for the equivalent second-order model of (1)–(3) (ours):

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
  Theorems 1–3 with LD-E3 to LD-E7 corrected, any prior, O(d²) per step.

What a new measurement y(t) changes (d >= 1, uncorrelated history): only the estimate of its
chain, x̂(t-d|t) and the smoothed estimates of older elements of that chain. The source's
"filter" x̂(t|t) then equals the one-step prediction x̂(t|t-1) (gain K(t) ≡ 0) and its
fixed-lag-(d-1) smoother x̂(t-d+1|t) equals x̂(t-d+1|t-d) (docs/sources LD-02). This is a property of
the printed model, not a bug.

Time convention (the source's): y(0) is the first measurement, at index 0, and measures x(-d).
Output index t holds x̂(t|t) (``mean``), x̂(t+1|t) (``pred_mean``) and x̂(t-d|t)
(``measured_mean``). Covariances do not depend on the data (no censoring), so they are
computed once and broadcast over the runs as read-only views.

Code names -> paper symbols: ``mean``/``cov`` x̂(t|t), P(t|t) (Theorem 1); ``pred_mean``/``pred_cov``
x̂(t+1|t), P(t+1|t) (Theorem 2, (50)–(52)); ``measured_mean`` x̂(t-d|t) (Lemma 1, i = 0);
``lagged[L]`` x̂(t-L|t) (Theorem 3 is L = d-1); ``innovation`` ε(t) (14); ``innovation_cov``
Q_ε(t) (15); ``second_moment`` Λ(t) (10, corrected: LD-E2); ``decorrelation`` J (8).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..models.delay import DelayFadingSystem, HistoryPrior
from ._backend import BACKENDS, use_kernel
from .core import (
    Estimator,
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

__all__ = [
    "IntervalSmoothing",
    "chain_lmmse",
    "augmented_lmmse",
    "reorganized_lmmse",
    "smooth_interval",
    "smooth_point",
    "second_moments",
    "ChainLMMSE",
    "AugmentedLMMSE",
    "ReorganizedInnovationLMMSE",
]

_DECORRELATION = ("optimal", "paper")
_ERRATA = ("E5", "E6", "E7")
#: the per-time dicts of Algorithm D's carry: the (batched) means; each step copies these and adds to / prunes
#: them (its data-independent quantities are in one ring buffer, :func:`_ring_layout`)
_REORG_DICTS = ("xf", "xsm", "xm", "xp", "eps")

# Algorithm D keeps its data-independent quantities of the last W = 4d+4 times in one flat ring buffer
# (time τ in slot τ mod W), copied once per step: Ψ_i(τ) and K(a|τ)H (by offset τ-a = 0..d), P(τ|τ),
# the smoother's P(τ-d+1|τ), P(τ-d|τ), P(τ|τ-1), P(τ-d|τ-1), Λ(τ), J(τ), Ā(τ), Σ(τ), Q_ε(τ); then the gains
# of the last step, K(t|t), K(t-d+1|t-i+1) (i = 1..d-1) and K(t-d|t), which the means read. The numpy step
# and the compiled step (:mod:`tobitkf.filters._kernels_delay`) read and write the same layout.
_RING_FIELDS = ("psi", "kh", "pf", "psm", "pmeas", "pp", "pm", "lam", "abar", "sig", "j", "qe", "kf", "ks", "ke")


def _ring_layout(d: int, n: int, m: int) -> tuple[int, dict[str, Any]]:
    """Ring size W and the (offset, shape) of every field of the flat buffer (and, under ``"fields"``,
    (name, offset, shape, size) of each)."""
    W = 4 * d + 4
    shapes = {
        "psi": (W, d + 1, n, n),
        "kh": (W, d + 1, n, n),
        "pf": (W, n, n),
        "psm": (W, n, n),
        "pmeas": (W, n, n),
        "pp": (W, n, n),
        "pm": (W, n, n),
        "lam": (W, n, n),
        "abar": (W, n, n),
        "sig": (W, n, n),
        "j": (W, n, m),
        "qe": (W, m, m),
        "kf": (n, m),
        "ks": (max(d - 1, 1), n, m),
        "ke": (n, m),
    }
    out: dict[str, Any] = {}
    off = 0
    for name in _RING_FIELDS:
        size = int(np.prod(shapes[name]))
        out[name] = (off, shapes[name])
        off += size
    out["size"] = (off, ())
    # (name, offset, shape, size) once, for the per-step views
    out["fields"] = tuple((k, o, sh, int(np.prod(sh))) for k, (o, sh) in out.items() if k != "size")
    return W, out


def _ring_views(buf: np.ndarray, layout: dict) -> dict[str, np.ndarray]:
    """The fields of a flat ring buffer as views."""
    return {k: buf[o : o + z].reshape(s) for k, o, s, z in layout["fields"]}


def _flat_layout(shapes: tuple[tuple[int, ...], ...]) -> tuple[int, tuple[tuple[int, int, tuple[int, ...]], ...]]:
    """The size of the flat output of a whole-step kernel of :mod:`tobitkf.filters._kernels_delay` whose arrays
    have ``shapes``, one after the other, then the trace of the step's covariance, and the ``(offset, size,
    shape)`` of each array (formed once per estimator and number of runs)."""
    out, o = [], 0
    for sh in shapes:
        z = math.prod(sh)
        out.append((o, z, sh))
        o += z
    return o + 1, tuple(out)


def _flat_views(buf: np.ndarray, layout: tuple[tuple[int, int, tuple[int, ...]], ...]) -> list[np.ndarray]:
    """The arrays of ``layout`` (entries of :func:`_flat_layout`) in the flat ``buf`` the kernel wrote (one array,
    not a tuple: boxing each output would cost about a microsecond), as views."""
    return [buf[o : o + z].reshape(sh) for o, z, sh in layout]


def _cached_layout(est: Any, key: Any, shapes: Any) -> tuple[int, tuple[tuple[int, int, tuple[int, ...]], ...]]:
    """:func:`_flat_layout` of ``shapes()``, formed once per ``key`` (the number of runs) and kept on ``est`` in
    ``_flat_layouts`` (which the callers read first: a hit costs a dict look-up, not this call)."""
    cache = est.__dict__.get("_flat_layouts")
    if cache is None:
        cache = est._flat_layouts = {}
    lay = cache.get(key)
    if lay is None:
        lay = cache[key] = _flat_layout(shapes())
    return lay


#: the most runs the whole-step kernels of Algorithms C and D take (the online case: one run, a few); more runs
#: keep their vectorised numpy means and threaded shared update, which a single-threaded loop over the runs
#: does not beat (D, 10^4 runs: 1.3-1.8x slower; measured 3 Dec 2026)
_WHOLE_STEP_MAX_RUNS = 1024

#: the layouts of an estimator that has formed none yet (:func:`_cached_layout`)
_NO_LAYOUTS: dict = {}

#: a placeholder array for a kernel argument that is not read (an innovation of a time before the first reading)
_NOTHING = np.zeros((1, 1))


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


def _check_lags(lags: Any, name: str, minimum: int) -> tuple[int, ...]:
    out = []
    for L in tuple(lags):
        if isinstance(L, bool) or not isinstance(L, (int, np.integer)) or L < minimum:
            raise ValidationError(f"{name}: expected integers >= {minimum}, got {L!r}")
        out.append(int(L))
    return tuple(sorted(set(out)))


def second_moments(system: DelayFadingSystem, prior: HistoryPrior, last: int) -> dict[int, np.ndarray]:
    r"""Λ(j) = E[x(j)x(j)^T] for j = -d..``last`` (corrected recursion, docs/sources LD-E2).

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


def _solve_small(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with A X = B; for a 1 x 1 A (one measurement channel, the papers' examples) the division it is,
    without LAPACK's call overhead (the online step of one run solves several of these per reading)."""
    if A.shape == (1, 1):
        return B / A[0, 0]
    return np.linalg.solve(A, B)


def _decorrelation(
    system: DelayFadingSystem,
    s: int,
    Lam_meas: np.ndarray,
    mode: str,
    *,
    HLH: np.ndarray | None = None,
    mult: np.ndarray | None = None,
    R: np.ndarray | None = None,
):
    r"""J(s), Ā(s), Σ(s) of the J-form predictor ((4)–(12) of the source; docs/sources LD-E1, LD-E3).

    ``"optimal"`` (corrected, LD-E3): :math:`R = Q_v + \sigma^2 H\Lambda H^T`, :math:`J = \Gamma S R^{-1}`,
    :math:`\Sigma = \sum_i Q_{\zeta_i} A_i\Lambda A_i^T + \Gamma(Q_w - SR^{-1}S^T)\Gamma^T`.
    ``"paper"`` ((8), (9), (11)): :math:`J = \Gamma S Q_v^{-1}`,
    :math:`\Sigma = \sum_i Q_{\zeta_i} A_i\Lambda A_i^T + \Gamma(Q_w - SQ_v^{-1}S^T)\Gamma^T + \sigma^2 J H\Lambda H^T J^T`.
    Both use Ā = A - γ̄ J H. ``HLH`` = :math:`H\Lambda H^T`, ``mult`` = :math:`\sum_i Q_{\zeta_i}(s) A_i\Lambda A_i^T`
    and ``R`` may be passed when the caller has them (:func:`_moments_at`; the same numbers, not recomputed).
    """
    # Λ is one (n, n) block here: ndarray.dot, bitwise the products of @ at a fraction of its call overhead
    gb, s2 = system.gamma_mean(s), system.gamma_var(s)
    H, G = system.H, system.Gamma
    if HLH is None:
        HLH = H.dot(Lam_meas).dot(H.T)
    if mult is None:
        mult = system.mult_cov(s, Lam_meas)
    if mode == "optimal":
        if R is None:
            R = system.Qv + s2 * HLH
        SRinv = _solve_small(R, system.S.T).T
        J = G.dot(SRinv)
        Sigma = mult + G.dot(system.Qw - SRinv.dot(system.S.T)).dot(G.T)
    else:
        J = G.dot(system.S_Qv_inv)
        Sigma = mult + G.dot(system.eta_cov).dot(G.T) + s2 * J.dot(HLH).dot(J.T)
    Abar = system.A - gb * J.dot(H)
    return J, Abar, 0.5 * (Sigma + Sigma.T)


def _moments_at(system: DelayFadingSystem, t: int, Lam: np.ndarray, mode: str):
    r"""What time t needs of the second moment Λ(t-d) = ``Lam`` (shared by Algorithms C and D), each formed once:

    .. math::

        R(t) = Q_v + \sigma^2(t) H\Lambda(t-d)H^T, \qquad
        \Lambda(t+1) = \mathrm{sym}(A\Lambda(t-d)A^T + Q_u(t)) \ \text{(corrected recursion, LD-E2)},

    with :math:`Q_u(t) = \sum_i Q_{\zeta_i}(t)A_i\Lambda(t-d)A_i^T + \Gamma Q_w\Gamma^T` and J(t), Ā(t), Σ(t) of
    :func:`_decorrelation` (whose :math:`H\Lambda H^T` and multiplicative term are the same numbers). The values
    are bitwise those of ``fading_noise_cov``, :func:`_extend_second_moments` and :func:`_decorrelation` called
    separately. Returns ``(R (m, m), (J, Ā, Σ), Λ(t+1) (n, n))``.
    """
    A, H = system.A, system.H
    HLH = H.dot(Lam).dot(H.T)
    R = system.Qv + system.gamma_var(t) * HLH
    mult = system.mult_cov(t, Lam)
    Lq = A.dot(Lam).dot(A.T) + (mult + system.GQG)
    dec = _decorrelation(system, t, Lam, mode, HLH=HLH, mult=mult, R=R)
    return R, dec, 0.5 * (Lq + Lq.T)


def _mult_sum(q: np.ndarray, Ai: np.ndarray, Lam: np.ndarray) -> np.ndarray:
    """Σ_i q_i A_i Λ A_i^T with matmuls (einsum over four indices would be O(N^4))."""
    if q.size == 1:  # the sum of one term, unbatched (ndarray.dot: bitwise @, a fraction of its overhead)
        return q[0] * Ai[0].dot(Lam).dot(Ai[0].T)
    return np.sum(q[:, None, None] * (Ai @ Lam @ np.swapaxes(Ai, -1, -2)), axis=0)


def _extend_second_moments(system: DelayFadingSystem, lam: dict[int, np.ndarray], last: int) -> dict[int, np.ndarray]:
    """Λ(j) up to j = ``last`` from the stored ones (the corrected recursion, LD-E2); a new dict."""
    d = system.d
    top = max(lam)
    if top >= last:
        return lam
    lam = dict(lam)
    A = system.A
    for t in range(top, last):
        L = lam[t - d]
        Lq = A.dot(L).dot(A.T) + system.process_cov(t, L)
        lam[t + 1] = 0.5 * (Lq + Lq.T)
    return lam


def _kernel_gap(system: DelayFadingSystem) -> str | None:
    """What the compiled delay kernels (:mod:`tobitkf.filters._kernels_delay`) do not cover in ``system``."""
    if system.fading.varying or not system.q_constant:
        return "fading or multiplicative-noise laws that change with t"
    return None


def _kernel_moment_args(system: DelayFadingSystem, mode: str) -> tuple:
    """The constant arguments of :func:`tobitkf.filters._kernels_delay.delay_moments` after Λ (those of
    ``reorg_cov_step`` after ``d, W``): the model's matrices, Q_ζ (empty without multiplicative noise),
    γ̄, σ² and the decorrelation mode, for laws constant in t."""
    c = np.ascontiguousarray
    q = system.q_mult(0) if system.h else np.zeros(0)
    mats = (system.A, system.H, system.Qv, system.Gamma, system.S, system.Qw, system.GQG, system.A_mult)
    args: tuple = tuple(c(M) for M in mats) + (c(q, dtype=float), c(system.S_Qv_inv), c(system.eta_cov))
    return args + (float(system.gamma_mean(0)), float(system.gamma_var(0)), mode == "optimal")


def _packed_moment_args(system: DelayFadingSystem, mode: str, *ints: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_kernel_moment_args` packed for the whole-step kernels (``_kernels_delay._unpack_moments``): the
    matrices row-major then γ̄, σ² in one float array, and (n, m, p, h, optimal) followed by ``ints``."""
    args = list(_kernel_moment_args(system, mode))
    h = np.size(args[8])  # Q_ζ: one per multiplicative noise (none: no A_i either)
    args[7] = args[7][:h]
    cb = np.concatenate([np.ravel(a) for a in args[:-3]] + [np.array(args[-3:-1], dtype=float)])
    n, m, p = system.n, system.m, system.Gamma.shape[1]
    ib = np.array((n, m, p, h, int(args[-1])) + ints, dtype=np.int64)
    return cb, ib


class _DelayEstimator(Estimator):
    """What the three delay algorithms share: the source's time index (y(0) first, measuring x(-d); the
    prior is the history x(0), ..., x(-d), ``state.k = -1``), the check of the readings (finite: the
    covariances do not depend on the data, so a reading cannot be skipped), the prior override
    (``prior=``, the family's own prior object) and the assembly of the per-step outputs."""

    k0 = -1
    _allow_missing = False
    _missing_reason = (
        "the LMMSE's covariances are formed from the model alone, before any reading, so a reading cannot be skipped"
    )

    def _setup(self, system: Any, prior: Any) -> None:
        check_instance(system, DelayFadingSystem, "system")
        self.prior = system.check_prior(prior)
        self.system = system
        self.n, self.m = system.n, system.m

    def _whole_takes(self, state: FilterState, options: dict[str, Any]) -> bool:
        """Whether the family's compiled whole step (one kernel call) takes the step from ``state``."""
        return False

    def _fast_step(self, state: FilterState, y: np.ndarray, u: Any, options: dict[str, Any]) -> FilterState | None:
        """The online step by the compiled whole step (the family's :meth:`_whole_online`: its branch of
        :meth:`_step_arrays` without the loop's floating-point context, as the kernel's arithmetic warns of nothing,
        and with the divergence check on the kernel's trace of the one shared covariance); None (the checked step
        runs, which warns and makes the means NaN) when the kernel does not take this step or a variance is not
        finite."""
        if not self._whole_takes(state, options):
            return None
        return self._whole_online(state, y)

    def _whole_online(self, state: FilterState, y: np.ndarray) -> FilterState | None:
        """The compiled whole step from ``state`` as the online step (the family's own, without the loop's
        per-step outputs the online state does not keep); None when the kernel's trace of the step's covariance
        (a sum of the variances of the one shared covariance) is not finite (or, harmlessly, overflows: the
        checked step then runs)."""
        raise NotImplementedError  # pragma: no cover - every family with a whole step implements it

    def _the_prior(self, prior: Any) -> HistoryPrior:
        return self.prior if prior is None else self.system.check_prior(prior)

    def init(self, batch_shape: Any = (), *, prior: Any = None, x0: Any = None, P0: Any = None) -> FilterState:
        """The prior history x(0), ..., x(-d) as a state (``state.k = -1``: no reading yet).

        ``prior`` (a :class:`~tobitkf.models.delay.HistoryPrior`) overrides the estimator's.
        """
        if x0 is not None or P0 is not None:
            raise ValidationError(
                "x0/P0: the delay family's prior is the history x(0), ..., x(-d); pass prior=HistoryPrior(...) instead"
            )
        # the family's prior object travels to _initial in the place of x0
        return Estimator.init(self, batch_shape, x0=self._the_prior(prior))

    def _run_delay(self, y: Any, prior: Any, state: FilterState | None, outputs: Any, options: dict[str, Any]):
        if state is None:
            state = self.init(np.shape(y)[:-2] if np.ndim(y) >= 2 else (), prior=prior)
        elif prior is not None:
            raise ValidationError("state: give either a state to continue from or a prior, not both")
        res = self._run(y, outputs=outputs, state=state, step_options=options)
        return _group_extras(res)


def _group_extras(res: FilterResult) -> FilterResult:
    """Per-step lag/horizon/point outputs (``lag3_mean`` ...) into the dicts ``lagged``, ``ahead``, ``point``."""
    ex = dict(res.extras)
    assert res.final is not None, "the estimation loop records the final state"
    lagged, ahead, point = {}, {}, None
    for key in [k for k in ex if k.startswith("lag") and k.endswith("_mean")]:
        L = int(key[3:-5])
        lagged[L] = (ex.pop(key), ex.pop(f"lag{L}_cov"))
    for key in [k for k in ex if k.startswith("ahead") and k.endswith("_mean")]:
        k = int(key[5:-5])
        ahead[k] = (ex.pop(key), ex.pop(f"ahead{k}_cov"))
    if "point_mean" in ex:
        point = {"j": int(res.final.carry["point"]), "mean": ex.pop("point_mean"), "cov": ex.pop("point_cov")}
    if "_lam" in ex:
        lam = np.asarray(ex.pop("_lam"))
        lam = lam.reshape((-1,) + lam.shape[-3:])[0]  # shared by the runs: (T, n, n)
        ex["second_moment"] = np.concatenate([np.asarray(lam), res.final.carry["lam"][res.final.k + 1][None]])
    if lagged:
        ex["lagged"] = dict(sorted(lagged.items()))
    if ahead:
        ex["ahead"] = dict(sorted(ahead.items()))
    if point is not None:
        ex["point"] = point
    return FilterResult(
        mean=res.mean,
        cov=res.cov,
        pred_mean=res.pred_mean,
        pred_cov=res.pred_cov,
        extras=ex,
        times=res.times,
        var=res.var,
        final=res.final,
    )


def _stack_blocks(blocks: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(blocks, axis=-1)


def _blockdiag(blocks: list[np.ndarray]) -> np.ndarray:
    n = blocks[0].shape[-1]
    k = len(blocks)
    out = np.zeros((1, k * n, k * n))
    for i, B in enumerate(blocks):
        out[0, i * n : (i + 1) * n, i * n : (i + 1) * n] = B
    return out


# --------------------------------------------------------------------------- Algorithm C


class ChainLMMSE(_DelayEstimator):
    r"""Algorithm C, the chain-decoupled exact LMMSE (see :func:`chain_lmmse`), as an estimator.

    Validates once; ``filter(y, lags=..., horizons=..., fixed_point=...)``, ``smooth``, ``smooth_point``;
    online ``init()``/``step(state, y_t)`` (one reading y(t) per step, ``state.k`` = t). The state's
    ``mean``/``cov`` are x̂(t|t), P(t|t); its internal vector stacks the window x̂(t|t), ..., x̂(t-d|t).

    Parameters
    ----------
    system : DelayFadingSystem
        Pure-delay model (no ``extra_lags``).
    prior : HistoryPrior
        Uncorrelated prior of x(0), ..., x(-d).
    decorrelation : {"optimal", "paper"}, default "optimal"
        See :func:`chain_lmmse`.
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``"auto"`` forms the moments of Λ(t-d) (R(t), J(t), Ā(t), Σ(t), Λ(t+1)) compiled
        (:func:`tobitkf.filters._kernels_delay.delay_moments`, the reorganized LMMSE's code) and runs the
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
        self._whole = None  # the compiled plain step (:func:`~tobitkf.filters._kernels_delay.chain_step`)
        if use_kernel(backend, _kernel_gap(system), "the chain LMMSE's moments"):
            from ._kernels_delay import chain_step, delay_moments

            self._moments = (delay_moments, _kernel_moment_args(system, decorrelation))
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
        if self._whole is not None and plain and P.shape[0] == 1 and x.shape[0] <= _WHOLE_STEP_MAX_RUNS:
            return self._plain_step(t, x, P, carry, y)
        xb, Pb, D = dict(carry["xb"]), dict(carry["Pb"]), dict(carry["D"])
        e = t - d
        # what time t needs of Λ(t-d), each formed once: R(t) = Q_v + σ² H Λ H^T, J(t), Ā(t), Σ(t) and Λ(t+1)
        lam = dict(carry["lam"])
        if self._moments is not None:
            kern, margs = self._moments
            R, J, Abar, Sigma, lam[t + 1] = kern(lam[e], *margs)
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

    def _plain_kernel(self, t, x, P, carry, y):
        """The compiled plain step (:func:`~tobitkf.filters._kernels_delay.chain_step`) at t >= 1: its flat output
        (the trace of the new window's covariance last) and the layout of its arrays."""
        kern, args = self._whole
        N, nw = x.shape
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: self._plain_shapes(N, nw)
        )
        size, lay = lay
        buf = np.empty(size)
        kern(x, P[0], carry["xb"][t], carry["Pb"][t][0], carry["lam"][t - self.system.d], y, *args, buf)
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
        (:func:`~tobitkf.filters._kernels_delay.chain_step`; the same carry and extras, equal to rounding)."""
        buf, lay = self._plain_kernel(t, x, P, carry, y)
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
        buf, lay = self._plain_kernel(t, x, state.P, carry, y)
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
            and state.x.shape[0] <= _WHOLE_STEP_MAX_RUNS
        )

    def _prepare_step_options(self, state, options):
        if not options:  # the plain online step: nothing to check
            return {"lags": (), "horizons": (), "point": None}
        return self._checked_options(options.get("lags", ()), options.get("horizons", ()), options.get("point"))

    def filter(
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
        call (:func:`tobitkf.filters._kernels_delay.aug_step`: the update, the decorrelated predict and
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
        gap = _kernel_gap(system)
        if gap is None and covariance_update != "standard":
            gap = f"covariance_update={covariance_update!r} (the whole-step kernel runs the standard form)"
        self._whole = None  # the compiled whole step and its constant arguments after (X, P, Λ_X, y)
        if use_kernel(backend, gap, "the augmented LMMSE's step"):
            from ._kernels_delay import aug_step

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
            Xf, Xp, eps, Pf, Pp, Qe, LamX = _flat_views(*self._whole_kernel(Xpr, Ppr, carry, y))
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

    def _whole_kernel(self, Xpr, Ppr, carry, y):
        """The compiled whole step (:func:`~tobitkf.filters._kernels_delay.aug_step`) from the prediction
        ``Xpr``, ``Ppr``: its flat output (the trace of P(t|t) last) and the layout of its arrays."""
        kern, consts = self._whole
        N, nx = Xpr.shape
        m = self.m
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: ((N, nx), (N, nx), (N, m), (1, nx, nx), (1, nx, nx), (1, m, m), (nx, nx))
        )
        size, lay = lay
        buf = np.empty(size)
        kern(Xpr, Ppr[0], carry["LamX"], y, *consts, buf)
        return buf, lay

    def _whole_online(self, state, y):
        """:meth:`_step_arrays`' compiled branch as the online step (no lags)."""
        t, carry = state.k + 1, state.carry
        Xpr, Ppr, _ = carry["next"] if "next" in carry else (state.x, state.P, None)
        buf, lay = self._whole_kernel(Xpr, Ppr, carry, y)
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

    def filter(
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


# --------------------------------------------------------------------------- Algorithm D


class ReorganizedInnovationLMMSE(_DelayEstimator):
    """Algorithm D, the source's reorganized-innovation estimator (see :func:`reorganized_lmmse`).

    Online ``init()``/``step(state, y_t)``: the state's mean/cov are x̂(t|t), P(t|t); the recursions'
    gains, Ψ and the smoother outputs they need are carried in the state (pruned to the last 2d+2
    times). The steps before ``warmup`` run Algorithm A, as in :func:`reorganized_lmmse`. The
    reorganized recursions are the source's algorithm, kept as its faithful (corrected) reference:
    they are not a Gaussian update of one state, so only its delayed-filter update and predictor
    correspond to the shared core's (Algorithms C and A use it).

    Parameters
    ----------
    system : DelayFadingSystem
    prior : HistoryPrior
    decorrelation : {"optimal", "paper"}, default "optimal"
    warmup : int, optional
    reinsert_errata : iterable of {"E5", "E6", "E7"}
        The printed LD-E5, LD-E6, LD-E7; see :func:`reorganized_lmmse`.
    """

    _name = "ReorganizedInnovationLMMSE"

    def __init__(
        self,
        system: DelayFadingSystem,
        prior: HistoryPrior,
        *,
        decorrelation: str = "optimal",
        warmup: int | None = None,
        reinsert_errata: Any = (),
        backend: str = "auto",
    ):
        check_keywords(
            {"decorrelation": decorrelation, "backend": backend}, {"decorrelation": _DECORRELATION, "backend": BACKENDS}
        )
        errata = frozenset(reinsert_errata)
        bad = errata - set(_ERRATA)
        if bad:
            raise ValidationError(f"reinsert_errata: expected a subset of {_ERRATA}, got {sorted(bad)}")
        self._setup(system, prior)
        if not system.is_pure_delay:
            raise ValidationError("system: Algorithm D needs the pure-delay model (no extra_lags); use augmented_lmmse")
        self.decorrelation, self.errata, self.warmup_arg = decorrelation, errata, warmup
        self._t0(self.prior)
        self._HT = system.H.T
        self.backend = backend
        gap = _kernel_gap(system)
        # the compiled whole step (covariances and means) and its arguments after (ring, t); d = 0 is
        # Algorithm C (its chain's own step)
        self._whole = None
        if system.d and use_kernel(backend, gap, "the reorganized LMMSE's covariance step"):
            self._whole = self._compiled_step()
            self._kernel, self._kernel_args = self._compiled_cov_step()
        self._eps_back = tuple(range(1, system.d - 1))  # the whole step reads ε(t-k), k = 1..d-2
        self._lag_keys = (f"lag{system.d - 1}_mean", f"lag{system.d - 1}_cov")
        if system.d == 0:
            self._chain = ChainLMMSE(system, self.prior, decorrelation=decorrelation, backend=backend)
        # γ̄(s), read about 2d times per step: the law's one mean when it does not change with s
        self._g_const = None if system.fading.varying else system.gamma_mean(0)

    def _whole_takes(self, state, options):
        return self._whole is not None and state.k + 1 >= state.carry["t0"] and state.x.shape[0] <= _WHOLE_STEP_MAX_RUNS

    def _compiled_cov_step(self):
        """The compiled covariance step (:func:`~tobitkf.filters._kernels_delay.reorg_cov_step`) and its
        constant arguments after ``(ring, t)``, for many runs (their means on numpy)."""
        from ._kernels_delay import reorg_cov_step

        sys_ = self.system
        W, layout = _ring_layout(sys_.d, self.n, self.m)
        offs = np.array([layout[k][0] for k in _RING_FIELDS], dtype=np.int64)
        args = (offs, sys_.d, W) + _kernel_moment_args(sys_, self.decorrelation)
        return reorg_cov_step, args + tuple(e in self.errata for e in ("E5", "E6", "E7"))

    def _compiled_step(self):
        """The compiled whole step (:func:`~tobitkf.filters._kernels_delay.reorg_step`: the covariance step
        :func:`~tobitkf.filters._kernels_delay.reorg_cov_step` and the means) and its packed constants
        ``(cb, ib)`` (:func:`_packed_moment_args` with d, W, the errata flags and the ring's offsets)."""
        from ._kernels_delay import reorg_step

        sys_ = self.system
        W, layout = _ring_layout(sys_.d, self.n, self.m)
        offs = tuple(int(layout[k][0]) for k in _RING_FIELDS)
        flags = tuple(int(e in self.errata) for e in ("E5", "E6", "E7"))
        return reorg_step, _packed_moment_args(sys_, self.decorrelation, sys_.d, W, *flags, *offs)

    def _gbar(self, s: int) -> float:
        """γ̄(s) (one call, not two, when the fading law does not change with s)."""
        return self._g_const if self._g_const is not None else self.system.gamma_mean(s)

    def _warmup_matrices(self):
        """The augmented matrices of the warm-up steps (Algorithm A, W = d), formed on first use."""
        mats = self.__dict__.get("_aug_mats")
        if mats is None:
            mats = self._aug_mats = _augmented_matrices(self.system, self.system.d)
        return mats

    def _t0(self, prior: HistoryPrior) -> int:
        d = self.system.d
        zero_init = prior.is_uncorrelated
        t0 = (0 if zero_init else 2 * d + 1) if self.warmup_arg is None else self.warmup_arg
        lowest = 0 if zero_init else 2 * d + 1
        if isinstance(t0, bool) or not isinstance(t0, (int, np.integer)) or t0 < lowest:
            raise ValidationError(
                f"warmup: expected an integer >= {lowest} "
                f"({'uncorrelated' if zero_init else 'correlated'} prior; 2d+1 = {2 * d + 1}), "
                f"got {self.warmup_arg!r}"
            )
        return int(t0)

    def _initial(self, N, prior, P0, batch):
        sys_ = self.system
        d, n = sys_.d, self.n
        if d == 0:
            x, P, carry = self._chain._initial(N, prior, P0, batch)
            return x, P, {"chain": carry}
        t0 = self._t0(prior)
        W, layout = self._layout
        ring = np.zeros(layout["size"][0])
        R = _ring_views(ring, layout)
        xf, xsm = {}, {}
        # Exact initialization from an uncorrelated prior: every Ψ and every gain K(a|s), s ≠ a+d, is zero
        # (the ring's zeros); the elements x(-k) keep their prior until measured.
        for k in range(d + 1):
            xf[-k] = np.broadcast_to(prior.block_mean(k), (N, n)).copy()  # x̂(-k|-k) = prior (no data before t = 0)
            m0 = prior.block_mean(k)
            R["pf"][-k % W] = prior.block_cov(k)
            R["lam"][-k % W] = prior.block_cov(k) + np.outer(m0, m0)
        xsm[-1] = xf[-d]  # x̂(-d|-1)
        R["psm"][-1 % W] = R["pf"][-d % W]
        R["pp"][0] = R["pf"][0]
        carry = {"xf": xf, "xsm": xsm, "xm": {}, "xp": {0: xf[0]}, "eps": {}, "ring": ring, "t0": t0}
        if t0 > 0:
            aug = AugmentedLMMSE(sys_, prior, window=d)
            Xa, Pa, ca = aug._initial(N, prior, None, batch)
            carry["aug"] = (Xa, Pa, ca["LamX"])
        return xf[0], R["pf"][0][None].copy(), carry

    @property
    def _layout(self):
        """(W, field offsets) of the ring buffer (:func:`_ring_layout`), formed once."""
        lay = self.__dict__.get("_ring_lay")
        if lay is None:
            lay = self._ring_lay = _ring_layout(self.system.d, self.n, self.m)
        return lay

    def _state_dim(self) -> int:
        return self.n

    def _step_arrays(self, t, x, P, S, carry, y, u, options=None):
        sys_ = self.system
        d = sys_.d
        if d == 0:
            xn, Pn, Sn, cn, xp, Pp, ex = self._chain._step_arrays(t, x, P, S, carry["chain"], y, u, {"lags": (0,)})
            return xn, Pn, Sn, {"chain": cn}, xp, Pp, ex
        # a new carry: the ring buffer is copied once (the caller's state stays unchanged), the per-time
        # dicts of the (batched) means are copied and grown
        c = dict(carry)
        for key in _REORG_DICTS:
            c[key] = dict(carry[key])
        xf, xsm, xm, xp, eps = c["xf"], c["xsm"], c["xm"], c["xp"], c["eps"]
        W, layout = self._layout
        ring = c["ring"] = carry["ring"].copy()
        if t >= c["t0"] and self._whole is not None and y.shape[0] <= _WHOLE_STEP_MAX_RUNS:
            return self._whole_step(t, y, c, xf, xsm, xm, xp, eps, ring)
        R = _ring_views(ring, layout)
        xpred = xp[t]
        if t < c["t0"]:
            self._warmup_step(t, y, c, R)
        elif self._whole is not None:  # many runs: the compiled covariance step, the numpy means
            self._kernel(ring, t, *self._kernel_args)
            self._means_step(t, y, xf, xsm, xm, xp, eps, R)
        else:
            self._cov_step(t, R)
            self._means_step(t, y, xf, xsm, xm, xp, eps, R)
        s1 = (t + 1) % W
        st = t % W
        extras = {
            "measured_mean": xm[t],
            "measured_cov": R["pmeas"][st][None],
            "next_mean": xp[t + 1],
            "next_cov": R["pp"][s1][None],
            "innovation": eps[t],
            "innovation_cov": R["qe"][st][None],
            f"lag{d - 1}_mean": xsm[t],
            f"lag{d - 1}_cov": R["psm"][st][None],
            "_lam": R["lam"][st][None],
        }
        c["lam"] = {t + 1: R["lam"][s1]}  # Λ(t+1), read by the result assembly (_group_extras)
        # drop what is no longer needed (the recursions read back at most 2d+1 steps): the ring's Ψ_i(old)
        # and K(a|old)H are zeroed (a vanishing Ψ or gain reads as zero), the means of time old - 1 go
        old = t - 2 * d - 2
        R["psi"][old % W] = 0.0
        R["kh"][old % W] = 0.0
        _drop_means(old - 1, xf, xsm, xm, xp, eps)
        return xf[t], R["pf"][st][None], None, c, xpred, R["pp"][st][None], extras

    def _whole_step(self, t, y, c, xf, xsm, xm, xp, eps, ring):
        """:meth:`_step_arrays` at t >= warmup as one compiled call (:func:`~tobitkf.filters._kernels_delay.reorg_step`:
        the covariance step, the means and the ring's pruning) on the step's own copies of the carry."""
        xpred = xp[t]
        buf, lay = self._whole_kernel(t, y, xf, xsm, xp, eps, ring)
        x, P, Pprior, extras = self._whole_assemble(t, buf, lay, c, xf, xsm, xm, xp, eps)
        return x, P, None, c, xpred, Pprior, extras

    def _whole_kernel(self, t, y, xf, xsm, xp, eps, ring):
        """The compiled whole step's flat output (the trace of P(t|t) last) and the layout of its arrays."""
        d, n, m = self.system.d, self.n, self.m
        kern, args = self._whole
        N = y.shape[0]
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: ((4, N, n), (N, m), (7, 1, n, n), (1, m, m))
        )
        size, lay = lay
        # C-ordered arguments (the warm-up's means are column blocks of Algorithm A's, the loop's readings
        # columns of the record): one compiled signature, and a tuple of one array type
        # (the warm-up stores its means C-ordered too)
        back = self._eps_back  # ε(t-1), ..., ε(t-d+2)
        prev = tuple([eps[t - k] if t >= k else _NOTHING for k in back]) if back else (_NOTHING,)
        xf_a = xf[t - d + 1] if d > 1 else xp[t]  # for d = 1 the kernel's own x̂(t|t)
        buf = np.empty(size)
        kern(ring, t, *args, np.ascontiguousarray(y), xp[t], xsm[t - 1], xf_a, prev, buf)  # prev: ε(t-1)..ε(t-d+2)
        return buf, lay

    def _whole_assemble(self, t, buf, lay, c, xf, xsm, xm, xp, eps):
        """The means of the kernel's output into the step's per-time dicts (those of time t-2d-3 dropped: the
        kernel zeroed the ring's Ψ, K H of t-2d-2), Λ(t+1) into ``c``; x̂(t|t), P(t|t), P(t|t-1) and the extras."""
        M, e_t, C, Qe = _flat_views(buf, lay)
        m0, m1, m2, m3 = M[0], M[1], M[2], M[3]  # (indexing: a third of the cost of iterating)
        xf[t], xsm[t], xm[t], xp[t + 1] = m0, m1, m2, m3
        eps[t] = e_t
        lag_mean, lag_cov = self._lag_keys
        extras = {
            "measured_mean": m2,
            "measured_cov": C[2],
            "next_mean": m3,
            "next_cov": C[3],
            "innovation": e_t,
            "innovation_cov": Qe,
            lag_mean: m1,
            lag_cov: C[4],
            "_lam": C[5],
        }
        c["lam"] = {t + 1: C[6, 0]}  # Λ(t+1), read by the result assembly (_group_extras)
        old = t - 2 * self.system.d - 3
        xf.pop(old, None), xsm.pop(old, None), xm.pop(old, None), xp.pop(old, None), eps.pop(old, None)
        return m0, C[0], C[1], extras

    def _whole_online(self, state, y):
        """:meth:`_step_arrays`' compiled branch as the online step: the new carry (the ring copied once, the
        per-time dicts of the means copied and grown), the kernel, and the checked trace of P(t|t)."""
        t, carry = state.k + 1, state.carry
        c = dict(carry)
        xf = c["xf"] = carry["xf"].copy()
        xsm = c["xsm"] = carry["xsm"].copy()
        xm = c["xm"] = carry["xm"].copy()
        xp = c["xp"] = carry["xp"].copy()
        eps = c["eps"] = carry["eps"].copy()
        ring = c["ring"] = carry["ring"].copy()
        # :meth:`_whole_kernel` and :meth:`_whole_assemble` written out (their calls and the list of views are a
        # tenth of this step; the test of the reorganized kernel's step loop holds the two forms equal)
        N = y.shape[0]
        d = self.system.d
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N)
        if lay is None:
            return self._whole_online_first(state, y)
        size, ((_, z0, s0), (o1, z1, s1), (o2, z2, s2), (o3, z3, s3)) = lay
        back = self._eps_back
        prev = tuple([eps[t - k] if t >= k else _NOTHING for k in back]) if back else (_NOTHING,)
        buf = np.empty(size)
        kern, args = self._whole
        kern(ring, t, *args, np.ascontiguousarray(y), xp[t], xsm[t - 1], xf[t - d + 1] if d > 1 else xp[t], prev, buf)
        if not math.isfinite(buf[-1]):
            return None
        M, e_t = buf[:z0].reshape(s0), buf[o1 : o1 + z1].reshape(s1)
        C, Qe = buf[o2 : o2 + z2].reshape(s2), buf[o3 : o3 + z3].reshape(s3)
        m0, m1, m2, m3 = M[0], M[1], M[2], M[3]
        xf[t], xsm[t], xm[t], xp[t + 1], eps[t] = m0, m1, m2, m3, e_t
        lag_mean, lag_cov = self._lag_keys
        extras = {
            "measured_mean": m2,
            "measured_cov": C[2],
            "next_mean": m3,
            "next_cov": C[3],
            "innovation": e_t,
            "innovation_cov": Qe,
            lag_mean: m1,
            lag_cov: C[4],
            "_lam": C[5],
        }
        c["lam"] = {t + 1: C[6, 0]}
        old = t - 2 * d - 3
        xf.pop(old, None), xsm.pop(old, None), xm.pop(old, None), xp.pop(old, None), eps.pop(old, None)
        return step_state(t, state.batch_shape, m0, C[0], self.n, None, c, extras)

    def _whole_online_first(self, state, y):
        """:meth:`_whole_online` by the two methods it writes out, at the first step for a number of runs (which
        forms the layout of the kernel's output)."""
        t, carry = state.k + 1, state.carry
        c = dict(carry)
        for key in _REORG_DICTS:
            c[key] = dict(carry[key])
        ring = c["ring"] = carry["ring"].copy()
        xf, xsm, xm, xp, eps = c["xf"], c["xsm"], c["xm"], c["xp"], c["eps"]
        buf, lay = self._whole_kernel(t, y, xf, xsm, xp, eps, ring)
        if not math.isfinite(buf[-1]):
            return None
        x, P, _, extras = self._whole_assemble(t, buf, lay, c, xf, xsm, xm, xp, eps)
        return step_state(t, state.batch_shape, x, P, self.n, None, c, extras)

    def _warmup_step(self, t, y, c, R):
        """A step t < warmup by Algorithm A, from which every stored Ψ, gain and covariance is read (LD-05)."""
        sys_ = self.system
        d, n = sys_.d, self.n
        W = self._layout[0]
        st = t % W
        _, dec, R["lam"][(t + 1) % W] = _moments_at(sys_, t, R["lam"][(t - d) % W], self.decorrelation)
        R["j"][st], R["abar"][st], R["sig"][st] = dec
        Xa, Pa, LamX = c["aug"]
        Xf, PfA, Xp_, PpA, KA, e_t, Q_t, LamX, _, _ = _aug_step(sys_, self._warmup_matrices(), Xa, Pa, LamX, y, t)
        Pprior = Pa[0]
        PfA, PpA, KA, Q_t = PfA[0], PpA[0], KA[0], Q_t[0]
        # the means C-ordered (copies of the column blocks), as the compiled whole step reads them
        c_ = np.ascontiguousarray
        c["xf"][t], R["pf"][st] = c_(_blk(Xf, 0, None, n)), _blk(PfA, 0, 0, n)
        c["xsm"][t], R["psm"][st] = c_(_blk(Xf, d - 1, None, n)), _blk(PfA, d - 1, d - 1, n)
        c["xm"][t], R["pmeas"][st] = c_(_blk(Xf, d, None, n)), _blk(PfA, d, d, n)
        c["xp"][t + 1], R["pp"][(t + 1) % W] = c_(_blk(Xp_, 0, None, n)), _blk(PpA, 0, 0, n)
        R["pm"][st] = _blk(Pprior, d, d, n)  # P(t-d|t-1)
        for k in range(d + 1):
            R["kh"][st, k] = _blk(KA.T, k, None, n).T.dot(sys_.H)  # K(t-k|t) H: K(t-k|t) the rows of block k
        c["eps"][t], R["qe"][st] = c_(e_t), Q_t
        # Ψ_i(t') = block (d, d-i) of P(j|j-1) with j = t'-i+1
        for j, Pj in ((t, Pprior), (t + 1, PpA)):
            for i in range(1, d + 1):
                R["psi"][(j + i - 1) % W, i] = _blk(Pj, d, d - i, n)
        c["aug"] = (Xp_, PpA[None], LamX)
        if t + 1 == c["t0"]:
            del c["aug"]

    def _cov_step(self, t, R):
        """The data-independent part of a reorganized step t >= warmup on the ring (numpy reference of
        :func:`tobitkf.filters._kernels_delay.reorg_cov_step`): (a)–(f) of :func:`reorganized_lmmse`
        without the means, and Λ(t+1) (LD-E2); the gains the means read go to the ring's ``kf``, ``ks``,
        ``ke``."""
        sys_ = self.system
        d = sys_.d
        W = self._layout[0]
        H, HT, A = sys_.H, self._HT, sys_.A
        gbar = self._gbar
        psi, kh = R["psi"], R["kh"]
        st = t % W
        # what time t needs of Λ(t-d), each formed once: R(t) of (15), J(t), Ā(t), Σ(t) of (50)-(52), Λ(t+1) (LD-E2)
        R_t, dec, R["lam"][(t + 1) % W] = _moments_at(sys_, t, R["lam"][(t - d) % W], self.decorrelation)
        R["j"][st], R["abar"][st], R["sig"][st] = dec
        errata = self.errata
        # ndarray.dot on these 2-D blocks: bitwise the products of @ (checked), at a fraction of its call overhead
        gb = gbar(t)
        # (a) innovation covariance (15); P(t-d|t-1) is last step's smoother covariance P(t-d+1|t) shifted
        Pmp = R["psm"][(t - 1) % W]
        R["pm"][st] = Pmp
        Q = gb * gb * (H.dot(Pmp).dot(HT)) + R_t  # R(t) = Q_v + σ² H Λ(t-d) H^T
        if Q.shape[0] > 1:  # a 1 x 1 Q_ε is its own symmetric part (0.5 (q + q) = q exactly)
            Q = 0.5 * (Q + Q.T)
        R["qe"][st] = Q
        HtQi = _solve_small(Q, H).T  # H^T Q_ε(t)^{-1}
        # (b) filter, (35)-(38) shifted by one
        Psd = psi[(t + d - 1) % W, d]
        Kf = R["kf"][...] = gb * (Psd.T.dot(HtQi))
        kh[st, 0] = KfH = Kf.dot(H)
        Pq = R["pp"][st] - gb * (KfH.dot(Psd))
        R["pf"][st] = 0.5 * (Pq + Pq.T)
        # (c) Ψ_i(t), i = d-1..1, corrected (58)
        # Before t = d (zero initialization only) the terms below are all zero: Ψ and the
        # gains of not-yet-measured elements vanish; times < 0 carry no measurement (γ̄ = 0 there).
        if t - d >= 0:
            AbarT_td = R["abar"][(t - d) % W].T
            g_md = gbar(t - d)
        else:
            AbarT_td, g_md = A.T, 0.0
        g_md1 = gbar(t - d + 1) if t - d + 1 >= 0 else 0.0
        e5, e6, e7 = "E5" in errata, "E6" in errata, "E7" in errata
        psi_dt = psi[st, d]
        psi_d = psi_dt.T if e6 else psi_dt  # source prints Ψ_d(t)^T (LD-E6)
        Pm_td = R["pm"][(t - d) % W]  # zero before t = d (no reading of x(t-2d) yet)
        for i in range(d - 1, 0, -1):
            a = t - d - i + 1
            a5 = a - 1 if e5 else a  # source (30)/(58) print K(t-d-i|t-d) (LD-E5)
            # K(a|s)H sits at offset s - a of time s
            val = (psi[(t - i) % W, d - i + 1].T - g_md * kh[(t - d) % W, t - d - a5].dot(Pm_td)).dot(AbarT_td)
            val = val - g_md1 * kh[(t - d + 1) % W, t - d + 1 - a].dot(psi_d)
            top = d - 1 - i if e7 else d - 2 - i  # source's limit d-1-i double counts (LD-E7)
            for j in range(0, top + 1):
                s = t - i - j
                g_s = gbar(s) if s >= 0 else 0.0
                val = val - g_s * kh[s % W, s - a].dot(psi[st, i + j + 1])
            psi[st, i] = val
        # (d) fixed-lag d-1 smoother (55)-(57), a = t-d+1
        a = t - d + 1
        Ps_ = R["pf"][a % W]
        for i in range(1, d):
            s = t - i + 1
            if s < 0:
                continue
            g_s = gbar(s)
            psi_i = psi[st, i]
            Ks = R["ks"][i - 1] = g_s * (psi_i.T.dot(_solve_small(R["qe"][s % W], H).T))
            kh[s % W, s - a] = KsH = Ks.dot(H)
            Ps_ = Ps_ - g_s * (KsH.dot(psi_i))
        R["psm"][st] = 0.5 * (Ps_ + Ps_.T)
        # (e) delayed filter and predictor (50)-(52)
        Ke = R["ke"][...] = gb * (Pmp.dot(HtQi))
        kh[st, d] = KeH = Ke.dot(H)
        Pq = Pmp - gb * (KeH.dot(Pmp))
        Pmeas = R["pmeas"][st] = 0.5 * (Pq + Pq.T)
        Abar = R["abar"][st]
        Pq = Abar.dot(Pmeas).dot(Abar.T) + R["sig"][st]
        R["pp"][(t + 1) % W] = 0.5 * (Pq + Pq.T)
        # (f) corrected (39)
        psi1 = psi[st, 1]
        psi[(t + d) % W, d] = Abar.dot(psi1 - gb * KeH.dot(psi1)).T

    def _means_step(self, t, y, xf, xsm, xm, xp, eps, R):
        """The means of a reorganized step t >= warmup from the gains of :meth:`_cov_step`: ε(t) (14), the
        filter (35), the fixed-lag smoother (55), the delayed filter (51) and the predictor (50)."""
        d = self.system.d
        W = self._layout[0]
        gb = self._gbar(t)
        xmp = xsm[t - 1]  # x̂(t-d|t-1): last step's smoother output x̂(t-d+1|t) shifted
        e_t = eps[t] = y - gb * (xmp.dot(self._HT))
        xf[t] = xp[t] + e_t.dot(R["kf"].T)
        xs_ = xf[t - d + 1]
        for i in range(1, d):
            s = t - i + 1
            if s >= 0:
                xs_ = xs_ + eps[s].dot(R["ks"][i - 1].T)
        xsm[t] = xs_
        xm[t] = xmp + e_t.dot(R["ke"].T)
        st = t % W
        xp[t + 1] = xm[t].dot(R["abar"][st].T) + y.dot(R["j"][st].T)

    def filter(
        self, y: Any, *, prior: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        """Run Algorithm D over ``y`` (..., T, m); see :func:`reorganized_lmmse`."""
        if self.system.d == 0:
            res = self._chain.filter(y, lags=(0,), prior=prior, outputs=outputs, state=state)
            return res
        res = self._run_delay(y, prior, state, outputs, {})
        res.extras["warmup"] = int(res.final.carry["t0"])
        return res


def _drop_means(j: int, *dicts: dict) -> None:
    """Algorithm D's means of time j, no longer read, out of the step's own copies of the per-time dicts."""
    for dct in dicts:
        dct.pop(j, None)


def reorganized_lmmse(
    system: DelayFadingSystem,
    prior: HistoryPrior,
    y: Any,
    *,
    decorrelation: str = "optimal",
    warmup: int | None = None,
    reinsert_errata: Any = (),
) -> FilterResult:
    r"""Algorithm D: the source's reorganized-innovation estimator (Theorems 1–3), LD-E3 to LD-E7 corrected.

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
    (g) Λ(t+1) by the corrected recursion (LD-E2).

    Initialization (the source's list is garbled, docs/sources LD-05): with a prior uncorrelated
    across lags, D starts at t = 0 with every Ψ and every gain K(a|s), s ≠ a+d, equal to zero
    (exact). Otherwise the steps t < ``warmup`` (default 2d+1, the source's "ε(i) = 0,
    i = 1..2d+1" range) are computed by Algorithm A, from which every stored Ψ, gain and
    covariance is read (LD-05). For d = 0 this is Algorithm C.

    Parameters
    ----------
    system, prior, y
        As :func:`augmented_lmmse` (pure-delay model, any joint prior).
    decorrelation : {"optimal", "paper"}
        J(t) corrected (LD-E3) or the source's constant J = ΓS Q_v^{-1} (everywhere Ā appears).
    warmup : int, optional
        First step done by the reorganized recursions; >= 2d+1 for a correlated prior
        (default 2d+1), >= 0 for an uncorrelated one (default 0). The steps before it are
        exact (Algorithm A) in both ``decorrelation`` modes.
    reinsert_errata : iterable of {"E5", "E6", "E7"}
        For regression tests only: put back the source's printed (30)/(58): ``"E5"`` (LD-E5) uses
        K(t-d-i|t-d) for K(t-d-i+1|t-d), ``"E6"`` (LD-E6) the transposed Ψ_d(t)^T, ``"E7"`` (LD-E7) the upper
        summation limit d-1-i (double counts the update at t-d+1). Each breaks optimality.

    Returns
    -------
    FilterResult
        ``lagged[d-1]`` is Theorem 3's smoother x̂(t-d+1|t) (d >= 1).

    Raises
    ------
    ValidationError
        Extra lags, an unknown option or erratum, ``warmup`` too small for a correlated prior.

    Notes
    -----
    Deviations from the source (each a correction of the source: LD-E3 to LD-E7): γ̄, σ² indexed by the
    measurement's own time (LD-E4); Ψ_d(t) untransposed (LD-E6); K(t-d-i+1|t-d) (LD-E5); summation limit
    d-2-i (LD-E7); J(t) corrected (LD-E3) unless ``decorrelation="paper"``; streaming order (a)–(g) (LD-06).
    The cost is O(d²) per step, not independent of d as the source claims.
    """
    est = ReorganizedInnovationLMMSE(
        system, prior, decorrelation=decorrelation, warmup=warmup, reinsert_errata=reinsert_errata
    )
    return est.filter(y)
