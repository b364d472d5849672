r"""Maximum (assumed-density) likelihood for the parameters of a :class:`~tobitkf.NonlinearSystem`.

The model is a map :math:`\theta \mapsto` ``NonlinearSystem`` (the parameters may sit in f, h, Q, R or the
prior); the readings pass through a channel (censoring, a quantizer, ... or none). The log-likelihood is the
nonlinear assumed-density filter's (:meth:`~tobitkf.NonlinearAssumedDensityFilter.log_likelihood`),

.. math:: \ell(\theta) = \sum_{r}\sum_k \sum_l \log p(y_{r,k,l} \mid \text{the Gaussian prediction of its
   latent reading}),

each term the channel's exact probability (density, or mass of a censored reading) of the reading under the
filter's Gaussian, statistically linearised, prediction of the latent reading; summed over independent records
``r`` when ``y`` has leading axes. It is exact for a linear model and an approximation otherwise (as the
filter's moments are). It is maximised by the quasi-Newton search of every fit in the package
(:func:`~tobitkf.inference._optimize.maximize`: BFGS, finite-difference gradients, the Newton-decrement
stopping rule), and the standard errors are those of the observed information, the inverse of minus the
central-difference Hessian of :math:`\ell` at the optimum (:class:`~tobitkf.FitResult`).

**Bias.** With censored readings of a nonlinear h the approximation biases the estimates by an amount that does
not shrink with the data: the filter takes the latent reading :math:`h(x_k) + v_k` as Gaussian, and the probability
of a censored reading depends on the tail of its actual (skewed) distribution. Finer sigma-point rules, more
``iterations`` and the square-root form refine the same Gaussian approximation and do not remove the bias (measured in
``tests/inference/test_nonlinear_fit_montecarlo.py``); without censoring, or with a linear h, there is none.
``tk.fit(..., update="quadrature")`` removes the part that comes from the latent reading: the filter's likelihood is
then the evidence of the exact one-step posterior, each reading's likelihood integrated over the Gaussian prediction
of x, at about 16 times the cost per evaluation. What is left comes from carrying one Gaussian for x (and its
prediction through f by the rule), and it depends on the records: on the model of that test, over 12 data sets each
(mean estimate minus the truth, ± its Monte Carlo error), with records of 100 readings (64 per data set) the linearised update gives a -0.0076 ± 0.0025, c +0.041 ±
0.004 and the quadrature a +0.0051 ± 0.0023, c -0.0070 ± 0.0037 (within about 2 Monte Carlo errors of the truth);
with records of 50 readings (128 per data set) the linearised a -0.0043 ± 0.0026, c +0.028 ± 0.005 and the quadrature
a +0.0085 ± 0.0027, c -0.020 ± 0.005 (3.2 and 4.4 Monte Carlo errors: the bias reversed, not removed). So the
quadrature update is not an unbiased fit in general. ``tk.fit(..., bias_correction="bootstrap")`` removes the bias,
whatever its source, to first order by a parametric bootstrap (:mod:`tobitkf.inference._bias_correction`), with
either update: the option to use for a fit unbiased within its Monte Carlo error (tested with the linearised
update on the records of 50 readings).

Reached through :func:`tobitkf.fit` with a callable model that returns a ``NonlinearSystem`` at ``theta0``.
"""

from __future__ import annotations

import time
import warnings
from typing import Any, Callable

import numpy as np

from .._validation import ValidationError, as_float_array, check_bool
from ..channels.censoring import Censoring
from ..models.nonlinear import NonlinearSystem
from ._direct import checked_map, fit_map, start_values
from ._optimize import check_iterations, check_tolerance
from ._results import FitResult, _progress_callback

__all__ = ["NonlinearModel", "builds_nonlinear", "fit_nonlinear"]


class NonlinearModel:
    """The fitted model of a nonlinear fit (:class:`~tobitkf.FitResult`'s ``model``): the map, the channel and
    the filter's options. ``system(theta)`` rebuilds the system at ``theta``; a fit read back from JSON has no
    map (the code of f and h is not saved), so it holds the estimates only."""

    kind = "nonlinear"

    def __init__(
        self,
        build: Callable[[np.ndarray], Any] | None,
        channel: Any,
        rule: str,
        iterations: int,
        update: str = "linearised",
    ):
        self.build, self.channel, self.rule, self.iterations = build, channel, rule, iterations
        self.update = update

    def __repr__(self) -> str:
        up = "" if self.update == "linearised" else f", update={self.update!r}"
        return f"NonlinearModel(channel={self.channel!r}, rule={self.rule!r}, iterations={self.iterations}{up})"

    def system(self, theta: Any = None, l: int = 0) -> NonlinearSystem:
        if self.build is None:
            raise ValidationError("model: a nonlinear fit read from a file has no map theta -> system; rebuild it")
        return self.build(np.asarray(theta, dtype=float))

    def to_spec(self) -> dict[str, Any]:
        return {"kind": self.kind, "rule": self.rule, "iterations": self.iterations, "update": self.update}

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> NonlinearModel:
        rule, iterations = str(spec.get("rule", "unscented")), int(spec.get("iterations", 1))
        return cls(None, None, rule, iterations, str(spec.get("update", "linearised")))

    def _unavailable(self, what: str):
        raise ValidationError(
            f"model: {what} of a nonlinear fit is not available here; run "
            "tk.NonlinearAssumedDensityFilter(res.system(), channel) on the readings"
        )

    def smooth(self, res: Any):
        self._unavailable("smooth()")

    def forecast(self, res: Any, steps: int, **kw: Any):
        self._unavailable("forecast()")

    def residuals(self, res: Any, seed: int = 0):
        self._unavailable("residuals()")


def builds_nonlinear(model: Any, theta0: Any) -> bool:
    """Whether the callable ``model`` returns a :class:`~tobitkf.NonlinearSystem` at ``theta0``."""
    try:
        th0 = np.asarray(theta0, dtype=float)
    except (TypeError, ValueError):
        return False
    return isinstance(model(th0), NonlinearSystem)


def fit_nonlinear(
    model: Callable[[np.ndarray], NonlinearSystem],
    y: Any,
    *,
    theta0: Any,
    u: Any = None,
    censoring: Any = None,
    lower: Any = None,
    upper: Any = None,
    channel: Any = None,
    method: str = "auto",
    likelihood: str = "auto",
    progress: Any = None,
    rule: str = "unscented",
    iterations: int | None = None,
    update: str = "linearised",
    names: Any = None,
    gtol: float = 1e-3,
    maxiter: int = 200,
    standard_errors: bool = True,
) -> FitResult:
    r"""Fit the parameters of a map ``theta -> NonlinearSystem`` by maximum assumed-density likelihood.

    Parameters
    ----------
    model : callable
        ``model(theta)`` returns the :class:`~tobitkf.NonlinearSystem` at the parameter vector ``theta`` (d,).
    y : (T,), (T, m) or (..., T, m) array_like
        Readings (censored ones hold their limit; NaN = missing); leading axes are independent records
        of the same model.
    theta0 : (d,) array_like
        Starting values.
    u : (T, p) or (..., T, p) array_like, optional
        Known inputs of an ``f(x, k, u)``.
    censoring, lower, upper, channel
        The channel the readings passed through: a :class:`~tobitkf.Censoring` (or its ``lower``/``upper``),
        or any contract ``channel`` (one of them); none: plain Gaussian readings.
    method : {"auto", "direct"}
        Direct quasi-Newton maximisation (the only method for a nonlinear model).
    likelihood : {"auto", "adf"}
        The assumed-density likelihood (the only one).
    progress
        As :func:`tobitkf.fit`'s.
    rule : str, default "unscented"
        The sigma-point rule of the filter (``"unscented"``, ``"cubature"``, ``"gauss_hermite"``).
    iterations : int, optional
        The filter's posterior-linearisation iterations per channel (default 1), or with ``update="quadrature"``
        its quadratures per step (default 2).
    update : {"linearised", "quadrature"}, default "linearised"
        The filter's update (:class:`~tobitkf.NonlinearAssumedDensityFilter`): ``"quadrature"`` maximises the
        evidence of the exact one-step posterior instead, the likelihood of each reading integrated over the
        Gaussian prediction of x (the default tensor Gauss–Hermite rule; about 40 times the cost per
        evaluation for n = 1), which removes the part of the bias below that comes from the latent reading, not
        the part that comes from carrying one Gaussian for x (``bias_correction="bootstrap"`` removes both).
    names : sequence of str, optional
        Parameter names (default ``theta0``, ``theta1``, ...).
    gtol, maxiter, standard_errors
        The search's tolerance (standard errors), its iteration cap, and whether to compute the observed
        information (the standard errors and the convergence check).

    Returns
    -------
    FitResult
        ``likelihood="adf"``, ``method="direct"``; ``res.system()`` the fitted system.

    Raises
    ------
    ValidationError
        The map does not return a NonlinearSystem, the log-likelihood is not finite at ``theta0``, no
        reading present, both ``channel`` and ``censoring``/``lower``/``upper``, an unknown method or
        likelihood, bad tolerances.
    ShapeError
        ``theta0`` not a vector, ``names`` of the wrong length, ``y`` or ``u`` malformed.
    """
    from ..filters.nonlinear_adf import NonlinearAssumedDensityFilter

    t0 = time.perf_counter()
    gtol = check_tolerance(gtol, "gtol")
    maxiter = check_iterations(maxiter, "maxiter")
    standard_errors = check_bool(standard_errors, "standard_errors")
    if method not in ("auto", "direct"):
        raise ValidationError(f"method: a nonlinear model is fitted by direct maximisation ('direct'), got {method!r}")
    if likelihood not in ("auto", "adf"):
        raise ValidationError(
            f"likelihood: a nonlinear model has the assumed-density likelihood ('adf'), got {likelihood!r}"
        )
    th0, names = start_values(theta0, None if names is None else [str(v) for v in names])
    arr = as_float_array(y, "y", allow_nan=True)
    y2 = arr[:, None] if arr.ndim == 1 else arr
    if y2.ndim < 2 or y2.size == 0 or np.isnan(y2).all():
        raise ValidationError(f"y: expected readings (T, m) with at least one present, got shape {arr.shape}")
    if channel is not None and (censoring is not None or lower is not None or upper is not None):
        raise ValidationError("channel: give either a channel or censoring/lower/upper, not both")
    if channel is None:
        if censoring is None:
            censoring = Censoring(lower=-np.inf if lower is None else lower, upper=np.inf if upper is None else upper)
        elif lower is not None or upper is not None:
            raise ValidationError("censoring: give either censoring or lower/upper, not both")
        channel = censoring

    sys_of = checked_map(model, NonlinearSystem)
    first = NonlinearAssumedDensityFilter(sys_of(th0), channel, rule=rule, iterations=iterations, update=update)
    first.log_likelihood(y2, u=u)  # the readings, inputs and channel checked once, with their own errors
    iterations = first.iterations

    def ll_of(th: np.ndarray) -> float:
        try:
            est = NonlinearAssumedDensityFilter(sys_of(th), channel, rule=rule, iterations=iterations, update=update)
        except ValueError as exc:  # a parameter the map or the system refuses (a negative variance ...)
            if "the map returned" in str(exc):
                raise
            return -np.inf
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")  # a trial step of the search may diverge: it scores -inf
            try:
                return float(np.sum(est.log_likelihood(y2, u=u)))
            except (ValueError, np.linalg.LinAlgError):
                return -np.inf

    return fit_map(
        ll_of,
        th0,
        names,
        gtol=gtol,
        maxiter=maxiter,
        progress=_progress_callback(progress, "fit nonlinear model"),
        standard_errors=standard_errors,
        started=t0,
        model_of=lambda th: NonlinearModel(model, channel, rule, iterations, update),
        n_obs=int((~np.isnan(y2)).sum()),
        likelihood="adf",
        data={"y": y2, "u": u},
        extra={"theta_map": True, "nonlinear": True},
    )
