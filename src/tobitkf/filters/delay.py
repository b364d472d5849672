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
Output index t holds x̂(t|t) (``mean``), x̂(t|t-1) (``pred_mean``, the prediction of x(t) before the
reading y(t), as in every family; the prior's x̂(0|-1) = x̄(0) at t = 0), x̂(t+1|t) (``extras["next_mean"]``,
so ``pred_mean[t+1] == next_mean[t]``) and x̂(t-d|t) (``measured_mean``). Covariances do not depend on the
data (no censoring), so they are computed once and broadcast over the runs as read-only views.

Code names -> paper symbols: ``mean``/``cov`` x̂(t|t), P(t|t) (Theorem 1); ``pred_mean``/``pred_cov``
x̂(t|t-1), P(t|t-1) (Theorem 2, (50)–(52), of the step before); ``next_mean``/``next_cov`` x̂(t+1|t),
P(t+1|t); ``measured_mean`` x̂(t-d|t) (Lemma 1, i = 0);
``lagged[L]`` x̂(t-L|t) (Theorem 3 is L = d-1); ``innovation`` ε(t) (14); ``innovation_cov``
Q_ε(t) (15); ``second_moment`` Λ(t) (10, corrected: LD-E2); ``decorrelation`` J (8).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..models.delay import DelayFadingSystem, HistoryPrior
from .core import (
    Estimator,
    FilterResult,
    FilterState,
    symmetrize,
)

__all__ = [
    "IntervalSmoothing",
    "second_moments",
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
# and the compiled step (:mod:`tobitkf.filters._compiled_delay`) read and write the same layout.
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
    """The size of the flat output of a compiled whole step of :mod:`tobitkf.filters._compiled_delay` whose arrays
    have ``shapes``, one after the other, then the trace of the step's covariance, and the ``(offset, size,
    shape)`` of each array (formed once per estimator and number of runs)."""
    out, o = [], 0
    for sh in shapes:
        z = math.prod(sh)
        out.append((o, z, sh))
        o += z
    return o + 1, tuple(out)


def _flat_views(buf: np.ndarray, layout: tuple[tuple[int, int, tuple[int, ...]], ...]) -> list[np.ndarray]:
    """The arrays of ``layout`` (entries of :func:`_flat_layout`) in the flat ``buf`` the compiled step wrote
    (one array, not a tuple: boxing each output would cost about a microsecond), as views."""
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


#: the most runs the compiled whole steps of Algorithms C and D take (the online case: one run, a few); more runs
#: keep their vectorised numpy means and threaded shared update, which a single-threaded loop over the runs
#: does not beat (D, 10^4 runs: 1.3-1.8x slower; measured 3 Dec 2026)
_WHOLE_STEP_MAX_RUNS = 1024

#: the layouts of an estimator that has formed none yet (:func:`_cached_layout`)
_NO_LAYOUTS: dict = {}

#: a placeholder array for a compiled step's argument that is not read (an innovation of a time before the first
#: reading)
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


def _compiled_gap(system: DelayFadingSystem) -> str | None:
    """What the compiled delay steps (:mod:`tobitkf.filters._compiled_delay`) do not cover in ``system``."""
    if system.fading.varying or not system.q_constant:
        return "fading or multiplicative-noise laws that change with t"
    return None


def _compiled_moment_args(system: DelayFadingSystem, mode: str) -> tuple:
    """The constant arguments of :func:`tobitkf.filters._compiled_delay.delay_moments` after Λ (those of
    ``reorg_cov_step`` after ``d, W``): the model's matrices, Q_ζ (empty without multiplicative noise),
    γ̄, σ² and the decorrelation mode, for laws constant in t."""
    c = np.ascontiguousarray
    q = system.q_mult(0) if system.h else np.zeros(0)
    mats = (system.A, system.H, system.Qv, system.Gamma, system.S, system.Qw, system.GQG, system.A_mult)
    args: tuple = tuple(c(M) for M in mats) + (c(q, dtype=float), c(system.S_Qv_inv), c(system.eta_cov))
    return args + (float(system.gamma_mean(0)), float(system.gamma_var(0)), mode == "optimal")


def _packed_moment_args(system: DelayFadingSystem, mode: str, *ints: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_compiled_moment_args` packed for the compiled whole steps (``_compiled_delay._unpack_moments``): the
    matrices row-major then γ̄, σ² in one float array, and (n, m, p, h, optimal) followed by ``ints``."""
    args = list(_compiled_moment_args(system, mode))
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
        """Whether the family's compiled whole step (one compiled call) takes the step from ``state``."""
        return False

    def _compiled_online_step(
        self, state: FilterState, y: np.ndarray, u: Any, options: dict[str, Any]
    ) -> FilterState | None:
        """The online step by the compiled whole step (the family's :meth:`_whole_online`: its branch of
        :meth:`_step_arrays` without the loop's floating-point context, as the compiled arithmetic warns of nothing,
        and with the divergence check on the compiled step's trace of the one shared covariance); None (the checked step
        runs, which warns and makes the means NaN) when the compiled step does not take this step or a variance is not
        finite."""
        if not self._whole_takes(state, options):
            return None
        return self._whole_online(state, y)

    def _whole_online(self, state: FilterState, y: np.ndarray) -> FilterState | None:
        """The compiled whole step from ``state`` as the online step (the family's own, without the loop's
        per-step outputs the online state does not keep); None when the compiled step's trace of the step's covariance
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
    return dataclasses.replace(res, extras=ex)


def _stack_blocks(blocks: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(blocks, axis=-1)


def _blockdiag(blocks: list[np.ndarray]) -> np.ndarray:
    n = blocks[0].shape[-1]
    k = len(blocks)
    out = np.zeros((1, k * n, k * n))
    for i, B in enumerate(blocks):
        out[0, i * n : (i + 1) * n, i * n : (i + 1) * n] = B
    return out


def register_delay(cls: Any, summary: str, options: dict[str, Any]) -> None:
    """Register the delay-family estimator ``cls`` (:func:`~tobitkf.filters.registry.register`): it takes the
    history prior (the channel piece ``prior``) and a delay model."""
    from .registry import family_entry, register

    register(family_entry(cls, summary, ("prior",), options=options, model="delay"))
