r"""Probability laws of random channel coefficients (fading gains, delays, failures).

Small reusable classes, one per law, shared by the channel pieces of several
sources: the Rice fading channel of Geng et al. 2017 ((2) of the source, Gaussian
coefficients; its Conclusion, uniform coefficients, GF-15), and the probability-mass-function
fading of the time-delay source (Li, Li & Wang 2018, Assumption 1).

Every law has a *core shape*: its parameters broadcast together to one array
shape (for example ``(L+1, m)``, one coefficient per delay ``s`` and channel
``m``), and each entry of that shape is an independent scalar random variable.

=================  ====================================  ==========================================
class              parameters                            moments
=================  ====================================  ==========================================
:class:`Gaussian`  ``mean`` :math:`\bar\vartheta`,       mean, variance as given
                   ``variance`` :math:`\tilde\vartheta`
:class:`Uniform`   ``low`` a, ``high`` b                 :math:`(a+b)/2`, :math:`(b-a)^2/12`
:class:`PMF`       ``values`` :math:`\gamma_l`,           :math:`\sum_l p_l\gamma_l`,
                   ``probs`` :math:`p_l` (last axis)     :math:`\sum_l p_l(\gamma_l-\bar\gamma)^2`
=================  ====================================  ==========================================

All expose ``.shape`` (the core shape), ``.mean``, ``.variance``,
``.second_moment`` (arrays of the core shape) and ``.sample(rng, shape=())``
returning ``shape + core_shape`` draws. ``rng`` is a ``numpy.random.Generator``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array

__all__ = ["CoefficientLaw", "Gaussian", "Uniform", "PMF", "Constant", "as_law"]

_PROB_TOL = 1e-9


def _shape_tuple(shape: Any) -> tuple[int, ...]:
    if shape is None:
        return ()
    if isinstance(shape, (int, np.integer)):
        if shape < 0:
            raise ValidationError(f"shape: expected a non-negative size, got {shape}")
        return (int(shape),)
    try:
        out = tuple(int(s) for s in shape)
    except TypeError:
        raise ValidationError(f"shape: expected an int or a tuple of ints, got {shape!r}") from None
    if any(s < 0 for s in out):
        raise ValidationError(f"shape: expected non-negative sizes, got {out}")
    return out


def _check_rng(rng: Any) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValidationError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    return rng


class CoefficientLaw:
    """Base class: a batch of independent scalar random variables of core shape ``.shape``."""

    shape: tuple[int, ...]

    @property
    def mean(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def variance(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def second_moment(self) -> np.ndarray:
        r""":math:`E[\vartheta^2] = \mathrm{Var}[\vartheta] + E[\vartheta]^2`, core shape."""
        return self.variance + self.mean**2

    def sample(self, rng: np.random.Generator, shape: Any = ()) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def __getitem__(self, index: Any) -> CoefficientLaw:  # pragma: no cover - overridden
        raise NotImplementedError


class Gaussian(CoefficientLaw):
    r"""Independent Gaussian coefficients :math:`\vartheta \sim N(\bar\vartheta, \tilde\vartheta)`.

    The law of the Rice fading coefficients in Geng et al. 2017, Assumption 2: mean and **variance**
    (not standard deviation, docs/sources GF-08). No clipping
    to [0, 1] is done.

    Parameters
    ----------
    mean : array_like
        Means, any shape.
    variance : array_like
        Variances (>= 0), broadcasting with ``mean``; 0 gives a deterministic coefficient.

    Raises
    ------
    ValidationError
        If an entry is not finite or a variance is negative.
    ShapeError
        If ``mean`` and ``variance`` do not broadcast.

    Examples
    --------
    >>> law = Gaussian([0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    >>> law.shape, law.sample(np.random.default_rng(0), (4,)).shape
    ((3,), (4, 3))
    """

    def __init__(self, mean: Any, variance: Any = 0.0):
        mu = as_float_array(mean, "mean")
        var = as_float_array(variance, "variance")
        if (var < 0).any():
            raise ValidationError(f"variance: expected variances >= 0, got {var[var < 0].ravel()[:3]}")
        try:
            mu, var = np.broadcast_arrays(mu, var)
        except ValueError:
            raise ShapeError(f"mean/variance: shapes {mu.shape} and {var.shape} do not broadcast") from None
        self._mean, self._var = np.array(mu), np.array(var)
        self.shape = self._mean.shape

    @property
    def mean(self) -> np.ndarray:
        return self._mean

    @property
    def variance(self) -> np.ndarray:
        return self._var

    def sample(self, rng: np.random.Generator, shape: Any = ()) -> np.ndarray:
        """Draw ``shape + self.shape`` independent coefficients."""
        rng = _check_rng(rng)
        z = rng.standard_normal(_shape_tuple(shape) + self.shape)
        return self._mean + np.sqrt(self._var) * z

    def __getitem__(self, index: Any) -> Gaussian:
        return Gaussian(self._mean[index], self._var[index])

    def __repr__(self) -> str:
        return f"Gaussian(mean={self._mean.tolist()}, variance={self._var.tolist()})"


class Uniform(CoefficientLaw):
    r"""Independent coefficients uniform on :math:`[a, b]`.

    Geng et al. 2017, Conclusion (docs/sources GF-15): mean :math:`(a+b)/2`,
    variance :math:`(b-a)^2/12`.

    Parameters
    ----------
    low, high : array_like
        Interval ends, broadcasting together, ``low <= high`` (equal ends give a constant).

    Raises
    ------
    ValidationError
        If an entry is not finite or ``low > high``.
    ShapeError
        If ``low`` and ``high`` do not broadcast.

    Examples
    --------
    >>> float(Uniform(0.2, 0.8).mean), round(float(Uniform(0.2, 0.8).variance), 4)
    (0.5, 0.03)
    """

    def __init__(self, low: Any, high: Any):
        lo = as_float_array(low, "low")
        hi = as_float_array(high, "high")
        try:
            lo, hi = np.broadcast_arrays(lo, hi)
        except ValueError:
            raise ShapeError(f"low/high: shapes {lo.shape} and {hi.shape} do not broadcast") from None
        if (lo > hi).any():
            raise ValidationError(
                f"low/high: expected low <= high, got low={lo[lo > hi].ravel()[:3]} > high={hi[lo > hi].ravel()[:3]}"
            )
        self.low, self.high = np.array(lo), np.array(hi)
        self.shape = self.low.shape

    @property
    def mean(self) -> np.ndarray:
        return 0.5 * (self.low + self.high)

    @property
    def variance(self) -> np.ndarray:
        return (self.high - self.low) ** 2 / 12.0

    def sample(self, rng: np.random.Generator, shape: Any = ()) -> np.ndarray:
        """Draw ``shape + self.shape`` independent coefficients."""
        rng = _check_rng(rng)
        u = rng.random(_shape_tuple(shape) + self.shape)
        return self.low + (self.high - self.low) * u

    def __getitem__(self, index: Any) -> Uniform:
        return Uniform(self.low[index], self.high[index])

    def __repr__(self) -> str:
        return f"Uniform(low={self.low.tolist()}, high={self.high.tolist()})"


class PMF(CoefficientLaw):
    r"""Coefficients taking finitely many values: :math:`P(\gamma = \gamma_l) = p_l`.

    Li, Li & Wang 2018, Assumption 1: :math:`\bar\gamma = \sum_l p_l\gamma_l`,
    :math:`E[\gamma^2] = \sum_l p_l\gamma_l^2`, :math:`\sigma^2 = \sum_l p_l(\gamma_l-\bar\gamma)^2`.
    The support lies on the **last** axis; leading axes (if any) form the core
    shape, so one PMF object can hold a different law per delay or channel.

    Parameters
    ----------
    values : (..., K) array_like
        Support points :math:`\gamma_l`.
    probs : (..., K) array_like
        Probabilities :math:`p_l >= 0`, summing to 1 (to 1e-9) along the last axis;
        broadcasts with ``values``.

    Raises
    ------
    ShapeError
        If ``values`` or ``probs`` is a scalar, or their last axes differ in length
        (or the leading axes do not broadcast).
    ValidationError
        If an entry is not finite, a probability is negative or the probabilities
        do not sum to 1.

    Examples
    --------
    >>> law = PMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8])
    >>> round(float(law.mean), 4), law.shape
    (0.9945, ())
    """

    def __init__(self, values: Any, probs: Any):
        val = as_float_array(values, "values")
        p = as_float_array(probs, "probs")
        if val.ndim == 0:
            raise ShapeError("values: expected an array (..., K) of support points, got a scalar")
        if p.ndim == 0:
            raise ShapeError("probs: expected an array (..., K) of probabilities, got a scalar")
        if val.shape[-1] != p.shape[-1]:
            raise ShapeError(
                f"probs: expected the same length K={val.shape[-1]} as values on the last axis, got {p.shape[-1]}"
            )
        if (p < 0).any():
            raise ValidationError(f"probs: expected probabilities >= 0, got {p[p < 0].ravel()[:3]}")
        total = p.sum(-1)
        if (np.abs(total - 1.0) > _PROB_TOL).any():
            raise ValidationError(
                f"probs: expected probabilities summing to 1 along the last axis, got sums {np.ravel(total)[:3]}"
            )
        try:
            val, p = np.broadcast_arrays(val, p)
        except ValueError:
            raise ShapeError(f"values/probs: shapes {val.shape} and {p.shape} do not broadcast") from None
        self.values, self.probs = np.array(val), np.array(p)
        self.shape = self.values.shape[:-1]
        self._cdf = np.cumsum(self.probs, axis=-1)

    @property
    def mean(self) -> np.ndarray:
        return (self.probs * self.values).sum(-1)

    @property
    def variance(self) -> np.ndarray:
        return (self.probs * (self.values - self.mean[..., None]) ** 2).sum(-1)

    def sample(self, rng: np.random.Generator, shape: Any = ()) -> np.ndarray:
        """Draw ``shape + self.shape`` independent coefficients by inverting the cdf."""
        rng = _check_rng(rng)
        u = rng.random(_shape_tuple(shape) + self.shape)
        idx = (u[..., None] >= self._cdf).sum(-1)
        idx = np.minimum(idx, self.values.shape[-1] - 1)  # u within rounding of 1
        vals = np.broadcast_to(self.values, u.shape + self.values.shape[-1:])
        return np.take_along_axis(vals, idx[..., None], axis=-1)[..., 0]

    def __getitem__(self, index: Any) -> PMF:
        if not isinstance(index, tuple):
            index = (index,)
        return PMF(self.values[index + (slice(None),)], self.probs[index + (slice(None),)])

    def __repr__(self) -> str:
        return f"PMF(values={self.values.tolist()}, probs={self.probs.tolist()})"


def Constant(value: Any) -> Gaussian:
    """A deterministic coefficient (a :class:`Gaussian` with zero variance)."""
    return Gaussian(value, 0.0)


def as_law(law: Any, name: str = "law") -> CoefficientLaw:
    """Return ``law`` if it is a :class:`CoefficientLaw`, else treat it as constant values."""
    if isinstance(law, CoefficientLaw):
        return law
    if isinstance(law, (str, bytes)) or law is None:
        raise ValidationError(f"{name}: expected a CoefficientLaw (Gaussian, Uniform, PMF) or numbers, got {law!r}")
    return Gaussian(as_float_array(law, name), 0.0)
