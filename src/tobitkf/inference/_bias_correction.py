r"""Parametric-bootstrap bias correction of a fit of a map :math:`\theta \mapsto` system (``tk.fit(...,
bias_correction="bootstrap")``).

An estimator :math:`\hat\theta` whose expectation is :math:`\theta + b(\theta)` (the assumed-density likelihood of a
nonlinear or censored model is an approximation of the exact one, and its maximiser carries a bias that does not
vanish with the data; any maximum-likelihood estimate carries a finite-sample one) is corrected by estimating
:math:`b` at the estimate itself (Efron & Tibshirani 1993, §10.6):

.. math::

    y^{*(b)} \sim p(\,\cdot \mid \hat\theta), \quad \hat\theta^{*(b)} = \arg\max_\theta \ell(\theta; y^{*(b)})
    \ (b = 1..B), \qquad \hat b = \bar\theta^* - \hat\theta, \qquad
    \hat\theta_{bc} = \hat\theta - \hat b = 2\hat\theta - \bar\theta^*,

each :math:`y^{*(b)}` simulated from the fitted model (:func:`tobitkf.simulate`) with the shape, the channel, the
inputs and the missing readings of the data, and refitted from :math:`\hat\theta` with the same likelihood. When
:math:`b(\theta)` varies slowly near the truth, :math:`\hat b \approx b(\theta)` and the corrected estimate is
unbiased to first order whatever the source of the bias. The correction adds the Monte Carlo error of
:math:`\bar\theta^*`, :math:`\mathrm{sd}(\hat\theta^*)/\sqrt B`, reported as ``bias_se``.

Cost: ``B`` further fits without standard errors, each starting at :math:`\hat\theta` (so a few quasi-Newton
iterations each), i.e. roughly ``B`` times the search of the first fit.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any, Callable

import numpy as np

from .._validation import ValidationError, check_int
from ._results import FitResult, _progress_callback

__all__ = ["bootstrap_bias_correction", "check_bootstrap", "simulated_like"]


def simulated_like(system: Any, y: np.ndarray, *, channel: Any, u: Any, seed: Any) -> np.ndarray:
    """Readings simulated from ``system`` shaped as ``y`` ((T,), (T, m) or (..., T, m)) through ``channel``, with the
    inputs ``u`` ((T, p) or (..., T, p)) and NaN wherever ``y`` has one (a missing reading stays missing)."""
    from ..simulate import simulate

    y2 = y[:, None] if y.ndim == 1 else y
    T, m = y2.shape[-2:]
    lead = y2.shape[:-2]
    runs = int(np.prod(lead)) if lead else 1
    inputs = None
    if u is not None:
        ua = np.asarray(u, dtype=float)
        inputs = ua if ua.ndim == 2 else ua.reshape((runs,) + ua.shape[-2:])
    d = simulate(system, T, runs, channel=channel, inputs=inputs, seed=seed)
    out = np.asarray(d.y, dtype=float).reshape(lead + (T, m))
    out[np.isnan(y2)] = np.nan
    return out.reshape(y.shape)


def check_bootstrap(samples: Any, seed: Any) -> tuple[int, np.random.SeedSequence]:
    """``(B, SeedSequence)`` of the options ``bootstrap_samples`` and ``seed``.

    Raises
    ------
    ValidationError
        ``samples`` not an integer in [2, 100000]; ``seed`` not a non-negative integer or a SeedSequence.
    """
    B = check_int(samples, "bootstrap_samples", minimum=2, maximum=100_000)
    if isinstance(seed, np.random.SeedSequence):
        return B, seed
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, (bool, np.bool_)) and int(seed) >= 0:
        return B, np.random.SeedSequence(int(seed))
    raise ValidationError(f"seed: expected a non-negative integer or a numpy SeedSequence, got {seed!r}")


def bootstrap_bias_correction(
    res: FitResult,
    *,
    draw: Callable[[np.ndarray, np.random.SeedSequence], np.ndarray],
    refit: Callable[[np.ndarray, np.ndarray], FitResult],
    model_of: Callable[[np.ndarray], Any],
    samples: Any,
    seed: Any,
    progress: Any,
) -> FitResult:
    r"""``res`` with its estimates replaced by :math:`2\hat\theta - \bar\theta^*` (module docstring).

    Parameters
    ----------
    res : FitResult
        The plain fit (:math:`\hat\theta` = ``res.theta``).
    draw : callable
        ``draw(theta, seed_sequence)``: readings simulated at ``theta`` shaped as ``y``.
    refit : callable
        ``refit(y_star, theta_start)``: the same fit of ``y_star`` from ``theta_start``.
    model_of : callable
        ``model_of(theta)``: the result's ``model`` at the corrected estimates.
    samples : int >= 2
        B, the bootstrap data sets.
    seed : int or SeedSequence
        Source of the B data sets (data set ``b`` from the ``b``-th child of ``SeedSequence(seed)``).
    progress
        As :func:`tobitkf.fit`'s (one entry per refit for a callable).

    Returns
    -------
    FitResult
        Estimates corrected; ``cov`` (the standard errors), ``loglik`` and the criteria those of the plain fit
        (the maximum); ``extra["bias_correction"]``: ``method``, ``samples``, ``used`` (refits that converged),
        ``seed``, ``uncorrected``, ``bias`` (:math:`\bar\theta^* - \hat\theta`), ``bias_se``
        (:math:`\mathrm{sd}/\sqrt{\text{used}}`), ``bootstrap_sd`` (the spread of :math:`\hat\theta^*`), each by
        parameter name.

    Raises
    ------
    ValidationError
        ``samples`` not an integer >= 2, a seed that is not an integer or SeedSequence, or fewer than two
        refits converged.
    """
    B, ss = check_bootstrap(samples, seed)
    t0 = time.perf_counter()
    cb, close, ticker = _progress_callback(progress, "bootstrap bias correction")
    theta_hat = np.asarray(res.theta, dtype=float)
    draws: list[np.ndarray] = []
    failed = 0
    try:
        for b, child in enumerate(ss.spawn(B)):
            ystar = draw(theta_hat, child)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # a refit's own convergence warnings: counted below
                    rb = refit(ystar, theta_hat)
            except (ValueError, np.linalg.LinAlgError):
                rb = None
            if rb is not None and rb.converged and np.all(np.isfinite(rb.theta)):
                draws.append(np.asarray(rb.theta, dtype=float))
            else:
                failed += 1
            status = f"refit {b + 1} of {B} ({failed} failed)"
            ticker.tick(status)
            if cb is not None:
                cb(
                    {
                        "iteration": b + 1,
                        "loglik": float("nan") if rb is None else rb.loglik,
                        "params": None if rb is None else rb.params,
                        "seconds": time.perf_counter() - t0,
                    }
                )
    finally:
        close()
    if len(draws) < 2:
        raise ValidationError(
            f"bootstrap_samples: only {len(draws)} of {B} bootstrap refits converged; the bias cannot be estimated"
        )
    th = np.array(draws)
    mean, sd = th.mean(axis=0), th.std(axis=0, ddof=1)
    corrected = 2.0 * theta_hat - mean
    by_name = lambda v: {n: float(x) for n, x in zip(res.names, v)}  # noqa: E731 - a local formatter
    extra = dict(res.extra)
    extra["bias_correction"] = {
        "method": "bootstrap",
        "samples": B,
        "used": len(draws),
        "seed": int(seed) if not isinstance(seed, np.random.SeedSequence) else str(seed.entropy),
        "uncorrected": by_name(theta_hat),
        "bias": by_name(mean - theta_hat),
        "bias_se": by_name(sd / np.sqrt(len(draws))),
        "bootstrap_sd": by_name(sd),
        "seconds": time.perf_counter() - t0,
    }
    note = f"; estimates bias-corrected by a parametric bootstrap of {len(draws)} refits"
    if failed:
        note += f" ({failed} of {B} did not converge and were left out)"
        warnings.warn(f"bias correction: {failed} of {B} bootstrap refits did not converge", stacklevel=3)
    return dataclasses.replace(
        res,
        theta=corrected,
        model=model_of(corrected),
        message=res.message + note,
        fit_seconds=res.fit_seconds + (time.perf_counter() - t0),
        extra=extra,
    )
