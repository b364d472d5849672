r"""Pure-delay systems with multiplicative noise, fading measurements and correlated noises.

Source: Y. Li, J. Li, X. Wang, "Optimal linear estimators for time-delay systems with
fading measurements and correlated noises", J. Electrical and Computer Engineering
(Hindawi), 2018 (our deviations: docs/sources/li2018-delay.md). The model, eqs. (1)–(3):

.. math::

    x(t+1) &= \Big[A + \sum_{i=1}^h A_i\,\zeta_i(t)\Big]\,x(t-d) + \Gamma w(t), \\
    y(t)   &= \gamma(t)\,H\,x(t-d) + v(t), \qquad
    E\begin{bmatrix} w(t)\\ v(t)\end{bmatrix}\begin{bmatrix} w(j)^T & v(j)^T\end{bmatrix}
      = \begin{bmatrix} Q_w & S\\ S^T & Q_v\end{bmatrix}\delta_{tj}.

Assumptions made explicit (LD-01, LD-09): the multiplicative noises
:math:`\zeta_i(t) \sim N(0, Q_{\zeta_i}(t))` and the fading coefficient :math:`\gamma(t)`
are independent of each other, of (w, v), of the initial history and over time; the
estimator knows only the fading mean :math:`\bar\gamma(t)` and variance
:math:`\sigma^2(t)`; the prior covers the whole initial history
:math:`x(0), x(-1), \dots, x(-d)` (:class:`HistoryPrior`).

Time convention (the paper's, differs from :class:`~tobitkf.LinearSystem`; the simulator is
:func:`tobitkf.simulate.delay.simulate_delay`): time starts at
t = 0 with the first measurement y(0), which measures x(-d). Array index t of ``y``
holds y(t); ``SimulationData.x[:, t]`` holds x(t) for t = 0..T; the history
x(-d)..x(-1) is in ``extras["history"]`` (oldest first).

Lag structure: the transition is stored as ``{lag: matrix}`` (:attr:`DelayFadingSystem.lags`),
x(t+1) = sum_k A^(k) x(t-k) + multiplicative part + noise. The printed model is
``{d: A}``; ``extra_lags`` adds terms such as A_0 x(t), which only the augmented estimator
(Algorithm A) accepts.

Code names -> paper symbols: ``A`` A, ``A_mult`` A_i, ``q_mult`` Q_{ζ_i}, ``H`` H,
``Gamma`` Γ, ``Qw`` Q_w, ``Qv`` Q_v, ``S`` S, ``d`` d, ``fading`` the law of γ(t)
(``mean`` γ̄, ``variance`` σ²), ``HistoryPrior`` x̄(-k), P(-k) (LD-01).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import (
    ShapeError,
    ValidationError,
    as_float_array,
    check_instance,
    check_memory,
    check_probability,
    check_psd,
)
from ..channels.laws import PMF

__all__ = [
    "FadingPMF",
    "FadingMoments",
    "HistoryPrior",
    "DelayFadingSystem",
    "paper_example",
    "paper_prior",
    "paper_fading",
]


# --------------------------------------------------------------------------- fading laws


class FadingPMF(PMF):
    r"""A scalar fading coefficient with a probability mass function (Assumption 1 of the source).

    :math:`P(\gamma = \gamma_l) = p_l`, :math:`\bar\gamma = \sum_l p_l\gamma_l`,
    :math:`\sigma^2 = \sum_l p_l(\gamma_l - \bar\gamma)^2`.

    The :class:`~tobitkf.channels.laws.PMF` law restricted to one scalar coefficient with
    values in [0, 1] (the source's [α, β] ⊂ [0, 1]). Any law with ``mean``, ``variance`` and
    ``sample(rng, shape)`` (scalar core shape) can be passed as ``fading`` instead.

    Parameters
    ----------
    values : (L,) array_like
        The values :math:`\gamma_l`, in [0, 1].
    probs : (L,) array_like
        Their probabilities, each in [0, 1], summing to 1.

    Raises
    ------
    ValidationError
        If a probability lies outside [0, 1], they do not sum to 1, or a value lies outside [0, 1].
    ShapeError
        If the arrays are not one-dimensional of equal length.

    Examples
    --------
    >>> law = FadingPMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8])
    >>> round(float(law.mean), 4), round(float(law.variance), 8)
    (0.9945, 0.00015475)
    """

    def __init__(self, values: Any, probs: Any):
        v = as_float_array(values, "values", ndim=1)
        p = as_float_array(probs, "probs", ndim=1)
        if v.shape != p.shape or v.size == 0:
            raise ShapeError(
                f"values/probs: expected two non-empty (L,) arrays of equal length, got {v.shape} and {p.shape}"
            )
        check_probability(p, "probs")
        if ((v < 0) | (v > 1)).any():
            raise ValidationError(f"values: expected fading values in [0, 1], got {v[(v < 0) | (v > 1)][:3]}")
        super().__init__(v, p)

    @classmethod
    def bernoulli(cls, p_received: float) -> "FadingPMF":
        """γ ∈ {0, 1} with P(γ = 1) = ``p_received`` (missing measurements)."""
        p = float(check_probability(p_received, "p_received"))
        return cls([0.0, 1.0], [1.0 - p, p])


class FadingMoments:
    r"""A fading coefficient given only by its mean :math:`\bar\gamma(t)` and variance :math:`\sigma^2(t)`.

    Each of ``mean`` and ``variance`` is a scalar, a ``(T,)`` array indexed by the
    measurement time t, or a callable of t. The estimators use only these two moments.
    The simulator draws :math:`\gamma(t) = \bar\gamma(t) \pm \sigma(t)` with probability 1/2
    each (a two-point law with the same moments; not a source choice).
    """

    def __init__(self, mean: Any, variance: Any):
        self._mean = _scalar_schedule(mean, "mean")
        self._var = _scalar_schedule(variance, "variance")
        if self._var(0) < 0:
            raise ValidationError(f"variance: expected a non-negative fading variance, got {self._var(0)} at t=0")

    def mean_at(self, t: int) -> float:
        return self._mean(t)

    def variance_at(self, t: int) -> float:
        v = self._var(t)
        if v < 0:
            raise ValidationError(f"variance: expected a non-negative fading variance, got {v} at t={t}")
        return v

    def sample_at(self, rng: np.random.Generator, t: int, shape: Any) -> np.ndarray:
        sign = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
        return self.mean_at(t) + sign * np.sqrt(self.variance_at(t))


def _scalar_schedule(value: Any, name: str) -> Callable[[int], float]:
    if callable(value):
        return lambda t: float(as_float_array(value(t), f"{name}({t})", ndim=0))
    arr = as_float_array(value, name, ndim=(0, 1))
    if arr.ndim == 0:
        c = float(arr)
        return lambda t: c

    def at(t: int) -> float:
        if not 0 <= t < arr.shape[0]:
            raise ShapeError(f"{name}: time-indexed array has {plural(arr.shape[0], 'step')}, t={t} requested")
        return float(arr[t])

    return at


class _FadingSchedule:
    """Normalizes the ``fading`` argument to mean_at(t), variance_at(t), sample_at(rng, t, shape)."""

    def __init__(self, fading: Any):
        self.source = fading
        self._law: Callable[[Any], Any] | None
        if fading is None:
            self._law = lambda t: _NO_FADING
        elif isinstance(fading, FadingMoments):
            self._law = None
        elif _is_law(fading):
            self._law = lambda t: fading
        elif callable(fading):
            first = fading(0)
            if not _is_law(first):
                raise ValidationError(
                    "fading: a callable must return a law with mean, variance and sample(rng, shape) "
                    f"for each t, got {type(first).__name__}"
                )
            self._law = fading
        else:
            raise ValidationError(
                "fading: expected None, a law (mean, variance, sample), a callable t -> law or "
                f"FadingMoments, got {type(fading).__name__}"
            )
        # a law that does not change with t (none, or one law object): its two moments validated once here,
        # not at every step of an estimator (the online step of one run asks for them at every reading)
        self._const: tuple[float, float] | None = None
        if fading is None or (not isinstance(fading, FadingMoments) and _is_law(fading)):
            self._const = (self._checked_mean(0), self._checked_variance(0))

    @property
    def varying(self) -> bool:
        return isinstance(self.source, FadingMoments) or (callable(self.source) and not _is_law(self.source))

    def mean_at(self, t: int) -> float:
        if self._const is not None:
            return self._const[0]
        return self._checked_mean(t)

    def variance_at(self, t: int) -> float:
        if self._const is not None:
            return self._const[1]
        return self._checked_variance(t)

    def _checked_mean(self, t: int) -> float:
        if self._law is None:
            return self.source.mean_at(t)
        return float(as_float_array(self._law_at(t).mean, f"fading({t}).mean", ndim=0))

    def _checked_variance(self, t: int) -> float:
        if self._law is None:
            return self.source.variance_at(t)
        v = float(as_float_array(self._law_at(t).variance, f"fading({t}).variance", ndim=0))
        if v < 0:
            raise ValidationError(f"fading({t}).variance: expected a non-negative fading variance, got {v}")
        return v

    def _law_at(self, t: int) -> Any:
        assert self._law is not None, "moments-only fading (FadingMoments) never asks for a law"
        law = self._law(t)
        if not _is_law(law):
            raise ValidationError(
                f"fading({t}): a callable must return a law with mean, variance and "
                f"sample(rng, shape) for each t, got {type(law).__name__}"
            )
        return law

    def sample_at(self, rng: np.random.Generator, t: int, shape: Any) -> np.ndarray:
        if self._law is None:
            return self.source.sample_at(rng, t, shape)
        return as_float_array(self._law_at(t).sample(rng, shape), f"fading({t}).sample")


def _is_law(obj: Any) -> bool:
    if not all(hasattr(obj, a) for a in ("mean", "variance", "sample")) or callable(getattr(obj, "mean")):
        return False
    if np.shape(obj.mean) != ():
        raise ValidationError(
            f"fading: expected a scalar law (one coefficient γ(t)), got core shape {np.shape(obj.mean)}"
        )
    return True


class _NoFading:
    mean = 1.0
    variance = 0.0

    @staticmethod
    def sample(rng: np.random.Generator, shape: Any) -> np.ndarray:
        return np.ones(shape)


_NO_FADING = _NoFading()


# --------------------------------------------------------------------------- prior


class HistoryPrior:
    r"""Prior of the initial history X(0) = [x(0); x(-1); ...; x(-d)] (LD-01).

    Stored as a joint mean ``mean`` (d+1, n) (row k is :math:`\bar x(-k)`) and a joint
    covariance ``cov`` (n(d+1), n(d+1)) in the same block order. Build it with
    :meth:`uncorrelated` (the default reading: one independent prior per lag),
    :meth:`joint` or :meth:`constant` (x(-k) ≡ x(0), fully correlated); built directly, the
    same checks apply.

    Raises
    ------
    ValidationError
        NaN, inf or text in ``mean``/``cov``, or ``cov`` not symmetric PSD.
    ShapeError
        ``mean`` not (d+1, n), or ``cov`` not (n(d+1), n(d+1)).
    """

    def __init__(self, mean: Any, cov: Any):
        mu = as_float_array(mean, "mean", ndim=2)
        P = as_float_array(cov, "cov", ndim=2)
        if mu.shape[0] < 1 or mu.shape[1] < 1:
            raise ShapeError(f"mean: expected (d+1, n) with d >= 0 and n >= 1, got shape {mu.shape}")
        if P.shape != (mu.size, mu.size):
            raise ShapeError(f"cov: expected shape {(mu.size, mu.size)} for a mean of shape {mu.shape}, got {P.shape}")
        check_psd(P, "cov")
        self.mean = mu.copy()
        self.cov = P.copy()

    @property
    def d(self) -> int:
        return self.mean.shape[0] - 1

    @property
    def n(self) -> int:
        return self.mean.shape[1]

    @classmethod
    def uncorrelated(cls, means: Any, covs: Any) -> "HistoryPrior":
        """Mutually uncorrelated x(-k), k = 0..d: ``means`` (d+1, n), ``covs`` (d+1, n, n), row k for x(-k)."""
        mu = as_float_array(means, "means", ndim=2)
        P = as_float_array(covs, "covs", ndim=3)
        if P.shape != (mu.shape[0], mu.shape[1], mu.shape[1]):
            raise ShapeError(
                f"covs: expected shape {(mu.shape[0], mu.shape[1], mu.shape[1])} to match means {mu.shape}, got {P.shape}"
            )
        check_psd(P, "covs")
        n, b = mu.shape[1], mu.shape[0]
        big = np.zeros((n * b, n * b))
        for k in range(b):
            big[k * n : (k + 1) * n, k * n : (k + 1) * n] = P[k]
        return cls(mu.copy(), big)

    @classmethod
    def repeated(cls, mean: Any, cov: Any, d: int) -> "HistoryPrior":
        """Uncorrelated history with every x(-k) ~ (``mean``, ``cov``) (the paper example's reading)."""
        d = _check_delay(d)
        mu = as_float_array(mean, "mean", ndim=1)
        P = as_float_array(cov, "cov", ndim=2)
        return cls.uncorrelated(np.tile(mu, (d + 1, 1)), np.tile(P, (d + 1, 1, 1)))

    @classmethod
    def joint(cls, mean: Any, cov: Any) -> "HistoryPrior":
        """Joint prior: ``mean`` (d+1, n), ``cov`` (n(d+1), n(d+1)) in the order x(0), x(-1), ..., x(-d)."""
        mu = as_float_array(mean, "mean", ndim=2)
        P = as_float_array(cov, "cov", ndim=2)
        size = mu.size
        if P.shape != (size, size):
            raise ShapeError(f"cov: expected shape {(size, size)} for a mean of shape {mu.shape}, got {P.shape}")
        check_psd(P, "cov")
        return cls(mu.copy(), 0.5 * (P + P.T))

    @classmethod
    def constant(cls, mean: Any, cov: Any, d: int, *, jitter: Any = 0.0) -> "HistoryPrior":
        """Constant history x(-k) = x(0) + e_k, x(0) ~ (``mean``, ``cov``), e_k ~ (0, ``jitter``) independent."""
        d = _check_delay(d)
        mu = as_float_array(mean, "mean", ndim=1)
        P = as_float_array(cov, "cov", ndim=2)
        J = (
            np.broadcast_to(as_float_array(jitter, "jitter"), P.shape)
            if np.ndim(jitter) < 2
            else as_float_array(jitter, "jitter", ndim=2)
        )
        big = np.kron(np.ones((d + 1, d + 1)), P) + np.kron(np.eye(d + 1), J)
        return cls.joint(np.tile(mu, (d + 1, 1)), big)

    def block_mean(self, k: int) -> np.ndarray:
        """Mean of x(-k)."""
        return self.mean[k]

    def block_cov(self, k: int, l: int | None = None) -> np.ndarray:
        """Cov(x(-k), x(-l)) (l defaults to k)."""
        n = self.n
        l = k if l is None else l
        return self.cov[k * n : (k + 1) * n, l * n : (l + 1) * n]

    @property
    def is_uncorrelated(self) -> bool:
        """True if every off-diagonal block of ``cov`` is zero."""
        mask = np.kron(1 - np.eye(self.d + 1), np.ones((self.n, self.n))).astype(bool)
        return not np.any(self.cov[mask] != 0.0)


def _check_delay(d: Any) -> int:
    if isinstance(d, bool) or not isinstance(d, (int, np.integer)):
        raise ValidationError(f"d: expected a non-negative integer delay, got {d!r}")
    if d < 0:
        raise ValidationError(f"d: expected a non-negative integer delay, got {d}")
    return int(d)


# --------------------------------------------------------------------------- system


class DelayFadingSystem:
    r"""The pure-delay system (1)–(3) with multiplicative noise, fading and correlated noises.

    Parameters
    ----------
    A : (n, n) array_like
        Transition matrix acting on x(t-d).
    H : (m, n) array_like
        Measurement matrix.
    Gamma : (n, p) array_like
        Noise input Γ.
    Qw : (p, p) array_like
        Covariance of w(t) (PSD).
    Qv : (m, m) array_like
        Covariance of v(t) (positive definite; the paper inverts it).
    S : (p, m) array_like
        Cross-covariance E[w(t) v(t)^T]. The joint covariance [[Qw, S], [S^T, Qv]] must be
        PSD; S = sqrt(Qw Qv) (w ≡ v up to scale) is allowed.
    d : int
        Delay, >= 0.
    A_mult : (h, n, n) array_like, optional
        Matrices A_i of the multiplicative noise (default: none).
    q_mult : (h,) or (T, h) array_like or callable of t, optional
        Variances Q_{ζ_i}(t) (required when ``A_mult`` is given).
    fading : law, callable t -> law, FadingMoments or None
        Law of γ(t); None means γ ≡ 1.
    extra_lags : dict {lag: (n, n)}, optional
        Extra transition terms A^(lag) x(t - lag), 0 <= lag <= d (not in the source;
        only Algorithm A handles them).

    Raises
    ------
    ValidationError
        ``d`` < 0; a covariance that is not PSD (``Qv`` not PD); ``S`` making the joint
        noise covariance indefinite; negative ``q_mult``; a lag outside [0, d].
    ShapeError
        On non-conforming shapes.
    """

    def __init__(
        self,
        A: Any,
        H: Any,
        Gamma: Any,
        Qw: Any,
        Qv: Any,
        S: Any,
        d: int,
        *,
        A_mult: Any = None,
        q_mult: Any = None,
        fading: Any = None,
        extra_lags: dict | None = None,
    ):
        self.d = _check_delay(d)
        self.A = as_float_array(A, "A", ndim=2)
        n = self.A.shape[0]
        if self.A.shape != (n, n):
            raise ShapeError(f"A: expected a square (n, n) matrix, got {self.A.shape}")
        self.H = as_float_array(H, "H", ndim=2)
        if self.H.shape[1] != n:
            raise ShapeError(f"H: expected (m, {n}), got {self.H.shape}")
        m = self.H.shape[0]
        self.Gamma = as_float_array(Gamma, "Gamma", ndim=(1, 2))
        if self.Gamma.ndim == 1:
            self.Gamma = self.Gamma[:, None]
        if self.Gamma.shape[0] != n:
            raise ShapeError(f"Gamma: expected ({n}, p), got {self.Gamma.shape}")
        p = self.Gamma.shape[1]
        self.Qw = np.atleast_2d(as_float_array(Qw, "Qw", ndim=(0, 2)))
        self.Qv = np.atleast_2d(as_float_array(Qv, "Qv", ndim=(0, 2)))
        self.S = np.atleast_2d(as_float_array(S, "S", ndim=(0, 2)))
        if self.Qw.shape != (p, p):
            raise ShapeError(f"Qw: expected ({p}, {p}), got {self.Qw.shape}")
        if self.Qv.shape != (m, m):
            raise ShapeError(f"Qv: expected ({m}, {m}), got {self.Qv.shape}")
        if self.S.shape != (p, m):
            raise ShapeError(f"S: expected ({p}, {m}) (p x m), got {self.S.shape}")
        check_psd(self.Qw, "Qw")
        check_psd(self.Qv, "Qv", strict=True)
        self.S_Qv_inv = np.linalg.solve(self.Qv, self.S.T).T  # S Qv^{-1}  (p, m)
        eta = self.Qw - self.S_Qv_inv @ self.S.T  # Qw - S Qv^{-1} S^T
        eta = 0.5 * (eta + eta.T)
        scale = max(float(np.abs(self.Qw).max()), float(np.abs(self.Qv).max()), np.finfo(float).tiny)
        lo = float(np.linalg.eigvalsh(eta).min())
        if lo < -1e-9 * scale:
            raise ValidationError(
                f"S: the joint noise covariance [[Qw, S], [S^T, Qv]] is indefinite "
                f"(Qw - S Qv^-1 S^T has eigenvalue {lo:.3g}); need |S| <= sqrt(Qw Qv)"
            )
        self.eta_cov = eta
        if A_mult is None:
            self.A_mult = np.zeros((0, n, n))
        else:
            self.A_mult = as_float_array(A_mult, "A_mult", ndim=(2, 3))
            if self.A_mult.ndim == 2:
                self.A_mult = self.A_mult[None]
            if self.A_mult.shape[1:] != (n, n):
                raise ShapeError(f"A_mult: expected (h, {n}, {n}), got {self.A_mult.shape}")
        h = self.A_mult.shape[0]
        if h and q_mult is None:
            raise ValidationError("q_mult: expected the variances Q_zeta_i of the multiplicative noises, got None")
        self._q_mult = self._q_schedule(q_mult, h)
        #: Q_ζ does not change with t (no multiplicative noise, or one variance per A_i)
        self.q_constant = h == 0 or (not callable(q_mult) and np.ndim(q_mult) <= 1)
        self.fading = _FadingSchedule(fading)
        self.lags = {self.d: self.A}
        for lag, mat in (extra_lags or {}).items():
            if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or not 0 <= lag <= self.d:
                raise ValidationError(f"extra_lags: expected integer lags in [0, d={self.d}], got {lag!r}")
            mat = as_float_array(mat, f"extra_lags[{lag}]", ndim=2)
            if mat.shape != (n, n):
                raise ShapeError(f"extra_lags[{lag}]: expected ({n}, {n}), got {mat.shape}")
            self.lags[int(lag)] = self.lags.get(int(lag), 0.0) + mat
        self.n, self.m, self.p, self.h = n, m, p, h
        self.GS = self.Gamma @ self.S  # Γ S   (n, m)
        self.GQG = self.Gamma @ self.Qw @ self.Gamma.T  # Γ Q_w Γ^T
        self._init_args = dict(
            A=A,
            H=H,
            Gamma=Gamma,
            Qw=Qw,
            Qv=Qv,
            S=S,
            d=d,
            A_mult=A_mult,
            q_mult=q_mult,
            fading=fading,
            extra_lags=extra_lags,
        )

    @staticmethod
    def _q_schedule(q: Any, h: int) -> Callable[[int], np.ndarray]:
        if h == 0:
            return lambda t: np.zeros(0)
        if callable(q):

            def at(t: int) -> np.ndarray:
                val = as_float_array(q(t), f"q_mult({t})").reshape(-1)  # NaN, inf, text: refused by name
                if val.shape != (h,) or (val < 0).any():
                    raise ValidationError(f"q_mult({t}): expected {h} non-negative variances, got {val}")
                return val

            at(0)
            return at
        arr = as_float_array(q, "q_mult", ndim=(0, 1, 2))
        if (arr < 0).any():
            raise ValidationError(f"q_mult: expected non-negative variances, got {arr[arr < 0][:3]}")
        if arr.ndim <= 1:
            c = np.broadcast_to(arr, (h,)).copy() if arr.size in (1, h) else None
            if c is None:
                raise ShapeError(f"q_mult: expected ({h},) or (T, {h}), got {arr.shape}")
            return lambda t: c
        if arr.shape[1] != h:
            raise ShapeError(f"q_mult: expected (T, {h}), got {arr.shape}")

        def at2(t: int) -> np.ndarray:
            if not 0 <= t < arr.shape[0]:
                raise ShapeError(f"q_mult: time-indexed array has {plural(arr.shape[0], 'step')}, t={t} requested")
            return arr[t]

        return at2

    # ----- accessors (all by the paper's time t of the noise / measurement)
    def q_mult(self, t: int) -> np.ndarray:
        """Q_{ζ_i}(t), shape (h,)."""
        return self._q_mult(t)

    def gamma_mean(self, t: int) -> float:
        """γ̄(t)."""
        return self.fading.mean_at(t)

    def gamma_var(self, t: int) -> float:
        """σ²(t)."""
        return self.fading.variance_at(t)

    def mult_cov(self, t: int, Lam: np.ndarray) -> np.ndarray:
        r""":math:`\sum_i Q_{\zeta_i}(t) A_i \Lambda A_i^T` for a second moment Λ of x(t-d)."""
        q = self.q_mult(t)
        if q.size == 0:
            return np.zeros_like(Lam)
        if q.size == 1:  # one multiplicative noise (the paper's example): the sum of one term, unbatched
            Ai = self.A_mult[0]
            if Lam.ndim == 2:  # ndarray.dot: bitwise the products of @, at a fraction of its call overhead
                return q[0] * Ai.dot(Lam).dot(Ai.T)
            return q[0] * (Ai @ Lam @ Ai.T)
        return np.sum(q[:, None, None] * (self.A_mult @ Lam @ np.swapaxes(self.A_mult, -1, -2)), axis=0)

    def process_cov(self, t: int, Lam: np.ndarray) -> np.ndarray:
        r"""Q_u(t) = Σ_i Q_{ζ_i}(t) A_i Λ(t-d) A_i^T + Γ Q_w Γ^T (the equivalent second-order model of (1)–(3))."""
        return self.mult_cov(t, Lam) + self.GQG

    def fading_noise_cov(self, t: int, Lam: np.ndarray) -> np.ndarray:
        r"""R(t) = Q_v + σ²(t) H Λ(t-d) H^T (the decorrelation corrected, LD-E3)."""
        H = self.H
        if Lam.ndim == 2:  # ndarray.dot: bitwise the products of @, at a fraction of its call overhead
            return self.Qv + self.gamma_var(t) * H.dot(Lam).dot(H.T)
        return self.Qv + self.gamma_var(t) * (H @ Lam @ H.T)

    @property
    def is_pure_delay(self) -> bool:
        """True for the printed model (only the lag-d transition)."""
        return list(self.lags) == [self.d]

    def replace(self, **changes: Any) -> "DelayFadingSystem":
        """A copy with some constructor arguments changed (e.g. ``S=0``, ``fading=None``)."""
        args = dict(self._init_args)
        unknown = set(changes) - set(args)
        if unknown:
            raise TypeError(f"unexpected keyword argument(s) {sorted(unknown)}")
        args.update(changes)
        d = args.pop("d")
        return DelayFadingSystem(d=d, **args)

    def check_prior(self, prior: Any) -> HistoryPrior:
        """Raise unless ``prior`` is a HistoryPrior for this n and d (d+1 lags)."""
        check_instance(prior, HistoryPrior, "prior")
        if prior.n != self.n:
            raise ShapeError(f"prior: expected states of dimension n={self.n}, got {prior.n}")
        if prior.d != self.d:
            raise ValidationError(
                f"prior: expected a history of d+1={self.d + 1} lags x(0)..x(-{self.d}), got {prior.d + 1}"
            )
        return prior


# --------------------------------------------------------------------------- paper example


def paper_fading(q: float = 1.0) -> FadingPMF:
    """The example's pmf {0.95: 0.05, 0.98: 0.15, q: 0.8} (§5 and Fig. 2; LD-11)."""
    return FadingPMF([0.95, 0.98, q], [0.05, 0.15, 0.8])


def paper_example(S: float = 0.3, *, q: float = 1.0, d: int = 3) -> DelayFadingSystem:
    """The numerical example of §5.

    ``S`` is not stated in the source; 0.3 = sqrt(Q_w Q_v) is inferred from Tables 1–2
    (LD-03). ``q`` is the Fig. 2 pmf variant (q = 1 is the base case).
    """
    return DelayFadingSystem(
        A=[[0.4, 0.7], [0.2, 0.6]],
        H=[[0.5, 1.0]],
        Gamma=[[1.0], [1.0]],
        Qw=0.3,
        Qv=0.3,
        S=S,
        d=d,
        A_mult=[[[0.1, 0.2], [0.2, -0.1]]],
        q_mult=[0.16],
        fading=paper_fading(q),
    )


def paper_prior(d: int = 3, cov: float = 0.01) -> HistoryPrior:
    """x(-k) ~ (0, 0.01 I) uncorrelated, k = 0..d (LD-01; P(0|0) = 0.01 I in the source)."""
    d = _check_delay(d)
    check_memory(8 * (2 * (d + 1)) ** 2, "d", f"a history of {d + 1} lags (its joint covariance)")
    return HistoryPrior.repeated(np.zeros(2), as_float_array(cov, "cov", ndim=0) * np.eye(2), d)
