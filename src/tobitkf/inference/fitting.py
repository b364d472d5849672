r"""Learning from censored data: :func:`fit` and the :class:`FitResult` a fit returns.

Three kinds of model (what ``model`` is):

* a :class:`~tobitkf.inference.censored_ar.CensoredAR` template, the censored regression with AR(p)
  errors (R = 0: exact readings when uncensored): exact maximum likelihood by direct maximisation of
  the quadrature likelihood of :mod:`tobitkf.inference.censored_ar`;
* a :class:`~tobitkf.LinearSystem` (the starting values) with ``estimate`` naming the matrices to learn,
  any subset of ``A, C, Q, R, Bu, D, x0, P0`` (``P0="stationary"`` ties the prior to A and Q): by
  default direct quasi-Newton maximisation of the Kalman (no censoring) or assumed-density
  log-likelihood over the estimated entries (covariances through their log-Cholesky factors), each
  evaluation a compiled pass of the filter's recursion (:mod:`tobitkf.inference._compiled_ss`);
  ``method="em"``: expectation-maximisation with the closed-form M-steps of the linear Gaussian model
  (Shumway & Stoffer 1982; Ghahramani & Hinton 1996), the E-step of the KF/RTS smoother (exact) or, for
  censored readings, of the assumed-density smoother of each reading's latent value. EM takes small
  steps near the optimum (hundreds of iterations on a 300-reading series, and the likelihood change it
  stops on can be small while the optimum is still standard errors away), so it is the named option;
* a callable ``theta -> LinearSystem`` (a structured model) with ``theta0``: direct maximisation of the
  same log-likelihood;
* a callable ``theta -> NonlinearSystem`` with ``theta0``: direct maximisation of the nonlinear
  assumed-density filter's log-likelihood (:mod:`tobitkf.inference.nonlinear_fit`; options ``channel``,
  ``rule``, ``iterations``, ``update``, ``names``).

**Bias correction** (a callable model): ``bias_correction="bootstrap"`` corrects the estimates by a parametric
bootstrap, :math:`2\hat\theta - \bar\theta^*` over ``bootstrap_samples`` refits of data simulated at
:math:`\hat\theta` (:mod:`tobitkf.inference._bias_correction`), for an approximate likelihood whose maximiser is
biased (the assumed-density likelihood of censored readings of a nonlinear h).

**Stopping rule and convergence** (every kind): the quasi-Newton search stops when its Newton decrement
:math:`\sqrt{g^TH^{-1}g}` is below ``gtol`` (1e-3 by default): the remaining step is shorter than ``gtol``
standard errors, whatever the record's length (:func:`~tobitkf.inference._optimize.maximize`).
``converged`` is True only when, at the estimates, the Newton step with the observed information,
:math:`I^{-1}g`, is below ``gtol`` standard errors in every parameter and the information is positive
definite (without standard errors: when the search's rule was met); ``message`` says which rule
decided and, when not converged, how far off the estimates are. Gradients are finite differences of
the log-likelihood (forward, relative step 1e-6, during the search; central for the check).

**What is refused** (a ``ValidationError`` naming the argument): no reading present; for the censored
AR model no exactly observed reading (the likelihood of censored-only readings has no maximum) or, with
nothing censored, readings the regressors fit without error; text or boolean readings; tolerances that
are not positive finite numbers; iteration counts that are not integers >= 1; a singular starting value
of an estimated covariance; estimates that run away during the search (the quadrature's size is checked
before anything is allocated).

Every fit returns a :class:`FitResult`: estimates, standard errors from the observed information
(the inverse of minus the Hessian of the log-likelihood at the optimum, in the natural parameters),
log-likelihood, AIC :math:`= -2\ell + 2k`, BIC :math:`= -2\ell + k\log n` (n the number of readings
present), the convergence trace, and what a user does next: forecasts with intervals, standardised
(quantile) residuals with diagnostics, saving and loading as plain JSON.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ._results import _FORMAT, _VERSION, FitResult, residual_diagnostics

__all__ = ["FitResult", "fit", "load_fit", "residual_diagnostics"]


def load_fit(path: str | os.PathLike, *, data: Any = None) -> FitResult:
    """Read a fit written by :meth:`FitResult.save`; ``data`` (optional) re-attaches the data it was fitted to.

    Raises
    ------
    ValidationError
        Not a tobitkf fit file, an unknown version or model kind.
    """
    try:
        rec = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValidationError(f"path: cannot read a fit from {path} ({exc})") from None
    if not isinstance(rec, dict) or rec.get("format") != _FORMAT:
        raise ValidationError(f"path: {path} is not a tobitkf fit file")
    if rec.get("version") != _VERSION:
        raise ValidationError(f"path: unknown fit-file version {rec.get('version')!r} (expected {_VERSION})")
    model = _model_from_spec(rec["model"])
    names = list(rec["names"])
    theta = np.array([rec["estimates"][n] for n in names], dtype=float)
    cov = (
        None
        if rec.get("cov") is None
        else np.array([[np.nan if v is None else v for v in row] for row in rec["cov"]], dtype=float)
    )
    if data is not None and model.kind == "censored_ar":
        from .censored_ar import CensoredARData

        if not isinstance(data, CensoredARData):
            raise ValidationError("data: expected the CensoredARData the model was fitted to")
    return FitResult(
        model=model,
        names=names,
        theta=theta,
        cov=cov,
        loglik=float(rec["loglik"]),
        n_obs=int(rec["n_obs"]),
        n_params=int(rec["n_params"]),
        method=rec["method"],
        likelihood=rec["likelihood"],
        converged=bool(rec["converged"]),
        message=rec.get("message", ""),
        trace=rec.get("trace", []),
        fit_seconds=float(rec.get("fit_seconds", 0.0)),
        evaluations=int(rec.get("evaluations", 0)),
        data=data,
        extra=rec.get("extra", {}),
    )


def _model_from_spec(spec: dict[str, Any]):
    kind = spec.get("kind") if isinstance(spec, dict) else None
    if kind == "censored_ar":
        from .censored_ar import CensoredAR

        return CensoredAR(
            int(spec["p"]),
            nodes=int(spec["nodes"]),
            span=float(spec["span"]),
            panel_sd=float(spec["panel_sd"]),
            hermite=int(spec["hermite"]),
        )
    if kind == "state_space":
        from .state_space import StateSpaceModel

        return StateSpaceModel.from_spec(spec)
    if kind == "continuous_panel":
        from .panel import PanelModel

        return PanelModel.from_spec(spec)
    if kind == "nonlinear":
        from .nonlinear_fit import NonlinearModel

        return NonlinearModel.from_spec(spec)
    raise ValidationError(f"model: unknown model kind {kind!r} in the fit file")


def fit(
    model: Any,
    y: Any,
    *,
    X: Any = None,
    u: Any = None,
    censoring: Any = None,
    censored: Any = None,
    lower: Any = None,
    upper: Any = None,
    estimate: Any = None,
    theta0: Any = None,
    method: str = "auto",
    likelihood: str = "auto",
    progress: Any = None,
    times: Any = None,
    bias_correction: str | None = None,
    bootstrap_samples: int | None = None,
    seed: Any = None,
    **options: Any,
) -> FitResult:
    r"""Fit a model to (censored) readings: exact ML, EM or direct maximisation (module docstring).

    Parameters
    ----------
    model : CensoredAR, LinearSystem or callable
        The template (see the module docstring); a callable maps a parameter vector to a
        :class:`~tobitkf.LinearSystem` or a :class:`~tobitkf.NonlinearSystem`.
    y : (T,) or (T, m) array_like
        Readings; censored ones hold their limit; NaN = missing.
    X : (T, l) array_like, optional
        Regressors of a :class:`CensoredAR` (default: the intercept).
    u : (T, p) array_like, optional
        Known inputs of a state-space model (the input matrices Bu, D multiply them; a NonlinearSystem's
        ``f(x, k, u)`` takes them).
    censoring : Censoring, optional
        Limits; or give ``lower``/``upper`` (scalars or per reading).
    censored : bool array_like, optional
        The recorded censoring indicator (default: the limit rule).
    estimate : sequence of str, optional
        For a LinearSystem template: the matrices to learn (default ``("A", "C", "Q", "R")``).
    theta0 : array_like
        Starting parameter vector for a callable model.
    method : {"auto", "em", "direct"}
        ``"auto"``: exact ML for CensoredAR, direct quasi-Newton maximisation for a LinearSystem template
        and for a callable; ``"em"``: expectation-maximisation (a LinearSystem template only).
    likelihood : {"auto", "kalman", "adf"}
        For state-space models: the Kalman likelihood (no censoring) or the assumed-density one.
    progress : None, False, True or callable
        None: a progress line on stderr every 10 s once a fit has run 10 s; False: silent; True: progress
        from the start; a callable: called with each iteration's trace entry.
    times : (T,) array_like, optional
        Sample times of ``y`` for a callable ``theta -> ContinuousLinearSystem`` (each gap discretised
        exactly). A :class:`~tobitkf.Panel` as ``y`` (many subjects, own times) is fitted jointly the same
        way: :func:`~tobitkf.inference.panel.fit_panel` (options ``align``, ``start``, ``names``).
    bias_correction : {None, "bootstrap"}, default None
        ``"bootstrap"`` (a callable model ``theta -> LinearSystem`` or ``NonlinearSystem``): the estimates
        corrected for their bias by a parametric bootstrap, :math:`\hat\theta_{bc} = 2\hat\theta -
        \bar\theta^*`, :math:`\bar\theta^*` the mean of the refits of ``bootstrap_samples`` data sets simulated
        at :math:`\hat\theta` with the data's shape, channel, inputs and missing readings
        (:mod:`tobitkf.inference._bias_correction`; it costs about ``bootstrap_samples`` further fits). The
        standard errors, log-likelihood and criteria stay those of the maximum; ``res.extra["bias_correction"]``
        holds the uncorrected estimates, the estimated bias, its Monte Carlo error and the bootstrap spread.
    bootstrap_samples : int >= 2, optional
        B, the bootstrap data sets of ``bias_correction="bootstrap"`` (default 50).
    seed : int or SeedSequence, optional
        Source of the bootstrap data sets (default 0; the same seed gives the same correction).
    **options
        Passed to the fitter (``maxiter``, ``gtol``, EM's ``tol``, ``standard_errors``, ...).

    Returns
    -------
    FitResult

    Raises
    ------
    ValidationError
        An unknown model kind or method, missing ``theta0`` for a callable, data without information,
        invalid tolerances (module docstring), and the fitters' own errors; for ``bias_correction``: an unknown
        value, a model that is not a callable map, ``bootstrap_samples`` below 2, a bad ``seed``, corrected
        estimates the model refuses, or ``bootstrap_samples``/``seed`` given without it.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.data import load_phosphorus
    >>> d = load_phosphorus()
    >>> res = tk.fit(tk.CensoredAR(1), d.y, X=d.design("lQ"), lower=d.lower, censored=d.censored)
    >>> res.converged, sorted(res.params)
    (True, ['beta0', 'beta1', 'phi1', 'sigma2'])
    """
    from ..models.linear import LinearSystem
    from .censored_ar import CensoredAR

    if method not in ("auto", "em", "direct"):
        raise ValidationError(f"method: expected 'auto', 'em' or 'direct', got {method!r}")
    if bias_correction is None and (bootstrap_samples is not None or seed is not None):
        raise ValidationError("bootstrap_samples/seed: options of bias_correction='bootstrap', which is not set")
    if bias_correction is not None:
        return _bootstrap_corrected(
            model,
            y,
            X=X,
            u=u,
            censoring=censoring,
            censored=censored,
            lower=lower,
            upper=upper,
            estimate=estimate,
            theta0=theta0,
            method=method,
            likelihood=likelihood,
            progress=progress,
            times=times,
            bias_correction=bias_correction,
            samples=50 if bootstrap_samples is None else bootstrap_samples,
            seed=0 if seed is None else seed,
            options=options,
        )
    from .panel import Panel, fit_panel, single_series_panel

    if times is not None or isinstance(y, Panel):  # a continuous-time model at sample times
        if not isinstance(y, Panel):
            y = single_series_panel(y, times, u=u, censoring=censoring, censored=censored, lower=lower, upper=upper)
        elif times is not None or u is not None or censoring is not None or censored is not None:
            raise ValidationError("times/u/censoring/censored: a Panel carries its own; give them to the Panel")
        return fit_panel(model, y, theta0=theta0, method=method, likelihood=likelihood, progress=progress, **options)
    if isinstance(model, CensoredAR):
        if method == "em":
            raise ValidationError("method: the censored AR model is fitted by direct exact maximisation ('direct')")
        lo, hi = _limits_1d(censoring, lower, upper)
        y1 = as_float_array(y, "y", ndim=(1, 2), allow_nan=True)
        if y1.ndim == 2:
            if y1.shape[1] != 1:
                raise ShapeError(f"y: the censored AR model takes one series, (T,) or (T, 1); got shape {y1.shape}")
            y1 = y1[:, 0]
        c1 = None if censored is None else np.asarray(censored).reshape(-1)
        return model.fit(y1, X, lower=lo, upper=hi, censored=c1, progress=progress, **options)
    from .state_space import fit_state_space

    if callable(model) and not isinstance(model, LinearSystem) and theta0 is not None:
        from .nonlinear_fit import builds_nonlinear, fit_nonlinear

        if builds_nonlinear(model, theta0):  # a map theta -> NonlinearSystem: the assumed-density likelihood
            if censored is not None or estimate is not None or X is not None:
                raise ValidationError("censored/estimate/X: not options of a nonlinear model's fit")
            return fit_nonlinear(
                model,
                y,
                theta0=theta0,
                u=u,
                censoring=censoring,
                lower=lower,
                upper=upper,
                method=method,
                likelihood=likelihood,
                progress=progress,
                **options,
            )
    if isinstance(model, LinearSystem) or callable(model):
        return fit_state_space(
            model,
            y,
            u=u,
            censoring=censoring,
            censored=censored,
            lower=lower,
            upper=upper,
            estimate=estimate,
            theta0=theta0,
            method=method,
            likelihood=likelihood,
            progress=progress,
            **options,
        )
    raise ValidationError(
        f"model: expected a CensoredAR, a LinearSystem or a callable theta -> LinearSystem, got {type(model).__name__}"
    )


def _bootstrap_corrected(model, y, *, bias_correction, samples, seed, options, **kw) -> FitResult:
    """:func:`fit` with ``bias_correction``: the plain fit, then the parametric-bootstrap correction
    (:func:`~tobitkf.inference._bias_correction.bootstrap_bias_correction`) of a callable model's estimates."""
    import copy

    from ._bias_correction import bootstrap_bias_correction, check_bootstrap, simulated_like

    if bias_correction != "bootstrap":
        raise ValidationError(f"bias_correction: expected None or 'bootstrap', got {bias_correction!r}")
    check_bootstrap(samples, seed)  # refused before the first fit
    if not callable(model) or kw["theta0"] is None or kw["times"] is not None or kw["censored"] is not None:
        raise ValidationError(
            "bias_correction: 'bootstrap' corrects a callable model theta -> LinearSystem or NonlinearSystem "
            "fitted with theta0 (no times or Panel, no censored indicator: the bootstrap simulates the readings)"
        )
    from .panel import Panel

    if isinstance(y, Panel):
        raise ValidationError("bias_correction: 'bootstrap' is not available for a Panel")
    res = fit(model, y, **kw, **options)
    if not res.extra.get("theta_map"):
        raise ValidationError("bias_correction: 'bootstrap' corrects a callable model's parameter vector")
    channel = getattr(res.model, "channel", None) if res.model.kind == "nonlinear" else res.model.censoring
    arr = as_float_array(y, "y", allow_nan=True)
    u = kw["u"]
    refit_kw = {**kw, "progress": False}
    refit_options = {**options, "standard_errors": False}

    def draw(theta, ss):
        return simulated_like(model(theta), arr, channel=channel, u=u, seed=ss)

    def refit(ystar, start):
        return fit(model, ystar, **{**refit_kw, "theta0": start}, **refit_options)

    def model_of(theta):
        try:
            system = model(theta)
        except ValueError as exc:  # the correction crossed a bound of the model (a variance below zero ...)
            raise ValidationError(
                f"bias_correction: the corrected estimates {np.round(theta, 6).tolist()} are refused by the model "
                f"({exc}); the plain estimates are {np.round(res.theta, 6).tolist()}: fit without the correction, "
                "or reparametrise (e.g. a log-variance)"
            ) from None
        if res.model.kind == "nonlinear":
            return res.model
        out = copy.copy(res.model)  # a linear map's fitted model holds the system at the estimates
        out.fitted = system
        return out

    return bootstrap_bias_correction(
        res, draw=draw, refit=refit, model_of=model_of, samples=samples, seed=seed, progress=kw["progress"]
    )


def _limits_1d(censoring, lower, upper):
    if censoring is not None:
        if lower is not None or upper is not None:
            raise ValidationError("censoring: give either censoring or lower/upper, not both")
        lo, hi = censoring.lower, censoring.upper
        lo = lo[:, 0] if lo.ndim == 2 else lo.reshape(()) if lo.ndim == 1 and lo.size == 1 else lo
        hi = hi[:, 0] if hi.ndim == 2 else hi.reshape(()) if hi.ndim == 1 and hi.size == 1 else hi
        return lo, hi
    return (-np.inf if lower is None else lower), (np.inf if upper is None else upper)
