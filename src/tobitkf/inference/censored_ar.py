r"""The censored regression with AR(p) errors as a :func:`tobitkf.fit` template: :class:`CensoredAR` (its exact
maximum-likelihood fit, standard errors, smoother, residuals and forecasts).

The model, its exact likelihood and the quadrature are described in :mod:`tobitkf.inference._ar_likelihood`;
the AR process's algebra is in :mod:`tobitkf.inference._ar_process`. This module also hands on their public
names (``from tobitkf.inference.censored_ar import exact_log_likelihood`` keeps working).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import ShapeError, ValidationError, as_float_array, check_bool
from ._ar_likelihood import (
    _SEARCH_GTOL,
    _WARM_T,
    HERMITE,
    NODES,
    PANEL_SD,
    SPAN,
    CensoredARData,
    GridPlan,
    _check_information,
    _forward,
    _log_likelihood,
    _PlanTooLarge,
    _subsample,
    exact_log_likelihood,
    plan_grid,
    posterior_moments,
)
from ._ar_process import (
    ar_autocovariance,
    ar_companion,
    ar_predictors,
    ar_state_space,
    ar_to_pacf,
    is_stationary,
    pacf_to_ar,
)
from ._optimize import _inverse_information, check_iterations, check_tolerance, forward_hessian, maximize
from ._results import FitResult, _progress_callback

__all__ = [
    "CensoredAR",
    "CensoredARData",
    "GridPlan",
    "ar_autocovariance",
    "ar_predictors",
    "pacf_to_ar",
    "ar_to_pacf",
    "is_stationary",
    "exact_log_likelihood",
    "posterior_moments",
    "plan_grid",
    "ar_state_space",
    "HERMITE",
    "NODES",
    "PANEL_SD",
    "SPAN",
]


class CensoredAR:
    r"""Template of the censored regression with AR(p) errors, fitted by exact maximum likelihood.

    :math:`y^*_t = x_t^T\beta + \xi_t`, :math:`\xi_t = \sum_{i\le p}\phi_i\xi_{t-i} + e_t`,
    :math:`e_t \sim N(0, \sigma^2)`, stationary start; readings exact when uncensored (R = 0), at the
    limit when censored, NaN when missing (module docstring). Parameters, named as in the
    metrics: ``beta0``, ``beta1``, ... (the columns of X), ``sigma2``, ``phi1``, ..., ``phip``.

    Parameters
    ----------
    p : int, default 1
        AR order (0: independent errors, the Tobit regression).
    nodes, span, panel_sd, hermite : optional
        Quadrature settings of the exact likelihood (:func:`plan_grid`).

    Raises
    ------
    ValidationError
        A negative order or bad quadrature settings.

    Examples
    --------
    >>> import numpy as np
    >>> from tobitkf.inference.censored_ar import CensoredAR
    >>> rng = np.random.default_rng(0)
    >>> xi = np.zeros(200)
    >>> for t in range(1, 200):
    ...     xi[t] = 0.6 * xi[t - 1] + rng.normal()
    >>> y = np.maximum(1.0 + xi, 0.5)                     # left-censored at 0.5
    >>> fit = CensoredAR(1).fit(y, lower=0.5)
    >>> sorted(fit.params)
    ['beta0', 'phi1', 'sigma2']
    >>> bool(abs(fit.params["phi1"] - 0.6) < 3 * fit.se["phi1"])
    True
    """

    kind = "censored_ar"

    def __init__(
        self, p: int = 1, *, nodes: int = NODES, span: float = SPAN, panel_sd: float = PANEL_SD, hermite: int = HERMITE
    ):
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or p < 0:
            raise ValidationError(f"p: expected an AR order >= 0, got {p!r}")
        for name, val in (("nodes", nodes), ("hermite", hermite)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < (1 if name == "nodes" else 0):
                raise ValidationError(f"{name}: expected a positive integer, got {val!r}")
        for name, num in (("span", span), ("panel_sd", panel_sd)):
            if not (isinstance(num, (int, float, np.floating)) and np.isfinite(num) and num > 0):
                raise ValidationError(f"{name}: expected a positive number, got {num!r}")
        self.p = int(p)
        self.nodes, self.span, self.panel_sd, self.hermite = int(nodes), float(span), float(panel_sd), int(hermite)

    def __repr__(self) -> str:
        return f"CensoredAR(p={self.p})"

    def _coarse(self) -> CensoredAR:
        return CensoredAR(
            self.p,
            nodes=max(4, self.nodes - 2),
            span=self.span,
            panel_sd=self.panel_sd * 4 / 3,
            hermite=max(8, self.hermite - 4),
        )

    # parameters -------------------------------------------------------------------
    def names(self, l: int) -> list[str]:
        """Parameter names for l regressors."""
        return [f"beta{i}" for i in range(l)] + ["sigma2"] + [f"phi{i + 1}" for i in range(self.p)]

    def split(self, theta: np.ndarray, l: int):
        """``(beta, sigma2, phi)`` from the natural parameter vector."""
        theta = np.asarray(theta, dtype=float)
        return theta[:l], float(theta[l]), theta[l + 1 :]

    def _to_free(self, theta, l):
        beta, s2, phi = self.split(theta, l)
        r = ar_to_pacf(phi) if self.p else np.zeros(0)
        return np.concatenate([beta, [np.log(s2)], np.arctanh(r)])

    def _from_free(self, u, l):
        u = np.asarray(u, dtype=float)
        phi = pacf_to_ar(np.tanh(u[l + 1 :])) if self.p else np.zeros(0)
        with np.errstate(over="ignore"):  # a trial step far out: sigma2 = inf, a failed step (-inf likelihood)
            s2 = np.exp(u[l])
        return np.concatenate([u[:l], [s2], phi])

    def start(self, data: CensoredARData) -> np.ndarray:
        """Starting values: least squares on the present readings (censored ones at their limit), then
        Yule-Walker on the residuals (partial autocorrelations clipped to +-0.9)."""
        ok = ~np.isnan(data.y)
        X, y = data.X[ok], data.y[ok]
        beta = np.linalg.lstsq(X, y, rcond=None)[0]
        r = np.full(data.T, np.nan)
        r[ok] = y - X @ beta
        acov = []
        for k in range(self.p + 1):
            a, b = r[k:], r[: data.T - k]
            both = ~np.isnan(a) & ~np.isnan(b)
            acov.append(float(np.mean(a[both] * b[both])) if both.sum() > 1 else 0.0)
        g = np.array(acov)
        g0 = max(g[0], 1e-12)
        if self.p:
            Gm = np.array([[g[abs(i - j)] for j in range(self.p)] for i in range(self.p)])
            try:
                phi = np.linalg.solve(Gm, g[1:])
                phi = pacf_to_ar(np.clip(ar_to_pacf(phi), -0.9, 0.9))
            except (np.linalg.LinAlgError, ValidationError):
                phi = np.zeros(self.p)
            s2 = max(g0 - phi @ g[1:], 1e-3 * g0)
        else:
            phi, s2 = np.zeros(0), g0
        return np.concatenate([beta, [s2], phi])

    # likelihood --------------------------------------------------------------------
    def plan(self, data: CensoredARData, theta) -> GridPlan:
        beta, s2, phi = self.split(theta, data.X.shape[1])
        return plan_grid(
            data, beta, s2, phi, nodes=self.nodes, span=self.span, panel_sd=self.panel_sd, hermite=self.hermite
        )

    def log_likelihood(self, data: CensoredARData, theta, plan: GridPlan | None = None) -> float:
        """Exact log-likelihood at the natural parameters ``theta`` (``-inf`` outside the parameter space)."""
        beta, s2, phi = self.split(theta, data.X.shape[1])
        if not (np.isfinite(s2) and s2 > 0) or not is_stationary(phi):
            return -np.inf
        if plan is None:
            plan = self.plan(data, theta)
        return _log_likelihood(data, beta, s2, phi, plan)

    def fit(
        self,
        y: Any,
        X: Any = None,
        *,
        lower: Any = -np.inf,
        upper: Any = np.inf,
        censored: Any = None,
        start: Any = None,
        maxiter: int = 200,
        gtol: float = 1e-3,
        passes: int = 3,
        standard_errors: bool = True,
        coarse: bool = True,
        progress: Any = None,
        warm_start: Any = "auto",
    ):
        r"""Exact maximum-likelihood fit (direct maximisation, BFGS on unconstrained parameters).

        The free parameters are :math:`\beta`, :math:`\log\sigma^2` and the Fisher transforms of the
        partial autocorrelations (stationarity by construction); the quadrature plan is frozen within a
        pass and refreshed at the pass's optimum (at most ``passes`` passes, until it no longer changes).
        Standard errors from the observed information: the inverse of minus the (forward-difference,
        step 1e-4 relative) Hessian of the log-likelihood in the natural parameters at the optimum.

        **Stopping rule** (scale-free, so that it means the same for 100 readings as for :math:`10^6`):
        the search stops when the Newton decrement :math:`\sqrt{g^TH^{-1}g}` (g the gradient, H minus
        the quasi-Newton Hessian) is below ``gtol`` (:func:`~tobitkf.inference._optimize.maximize`). The
        fit is reported ``converged`` when, on the model's own quadrature rule, the Newton step with the
        observed information, :math:`\delta = I^{-1}g`, is below ``gtol`` standard errors in every
        parameter, :math:`\max_i|\delta_i|/\mathrm{se}_i < \texttt{gtol}`, and the information is
        positive definite (without the information, ``standard_errors=False`` and ``coarse=False``: when
        the search's rule was met). Otherwise ``converged`` is False and ``message`` says why.

        With ``coarse`` the search on the coarse rule stops at 0.01 standard errors (or ``gtol`` if
        larger) and the Newton steps finish it; the information is computed again where they end when
        they moved the estimates by more than 0.01 standard errors and 1e-4 of their size (a smaller
        move changes the standard errors by less than about 1e-4, relative).

        **Long records** (``warm_start="auto"``: more than 20 000 readings and no ``start``): the search
        first runs on ten stretches of 1000 readings spread over the record (joined by one missing
        reading each), and starts the full search from that optimum with its quasi-Newton inverse
        Hessian scaled by the ratio of the readings; the full record then needs a few iterations.

        Parameters
        ----------
        y : (T,) array_like
            Readings (censored ones at their limit, NaN = missing).
        X : (T, l) array_like, optional
            Regressors; default a column of ones.
        lower, upper : float or (T,) array_like
            Censoring limits.
        censored : (T,) bool array_like, optional
            The recorded indicator (default: the limit rule).
        start : (l + 1 + p,) array_like, optional
            Natural starting values (default :meth:`start`).
        maxiter : int >= 1
            BFGS iterations per pass.
        gtol : float > 0
            Tolerance of the stopping rule, in standard errors.
        passes : int >= 1
            Maximum number of quadrature-plan refreshes.
        standard_errors : bool
            Compute the observed-information standard errors.
        coarse : bool, default True
            Search on a coarser quadrature rule (2 nodes fewer per panel, panels 4/3 wider), then polish
            the optimum with Newton steps on the model's own rule.
        progress : None, False, True or callable
            None (default): a progress line on stderr every 10 s once a fit has run 10 s; False: silent;
            True: a status line from the start; a callable is called with each iteration's trace entry.
        warm_start : {"auto", True, False}
            The subsample start for long records (above).

        Returns
        -------
        FitResult

        Raises
        ------
        ValidationError, ShapeError
            Bad data (see :class:`CensoredARData`); data without information (no reading observed
            exactly, or exact readings that the regressors fit without error: the likelihood then has no
            maximum); a start outside the parameter space; ``gtol``/``maxiter``/``passes`` not valid;
            estimates that run away during the search (the same cause: no maximum).
        """
        t0 = time.perf_counter()
        gtol = check_tolerance(gtol, "gtol")
        maxiter = check_iterations(maxiter, "maxiter")
        passes = check_iterations(passes, "passes")
        standard_errors = check_bool(standard_errors, "standard_errors")
        coarse = check_bool(coarse, "coarse")
        if not (warm_start == "auto" or isinstance(warm_start, (bool, np.bool_))):
            raise ValidationError(f"warm_start: expected 'auto', True or False, got {warm_start!r}")
        data = CensoredARData.build(y, X, lower, upper, censored)
        _check_information(data)
        l = data.X.shape[1]
        names = self.names(l)
        theta = self.start(data) if start is None else as_float_array(start, "start", ndim=1)
        if theta.size != len(names):
            raise ShapeError(f"start: expected {len(names)} values ({', '.join(names)}), got {theta.size}")
        if not np.isfinite(self.log_likelihood(data, theta)):
            raise ValidationError(
                "start: the log-likelihood is -inf there (sigma2 <= 0, a non-stationary phi, or "
                "readings of zero probability)"
            )
        cb, close, ticker = _progress_callback(progress, f"fit {self!r} to {plural(data.T, 'reading')}")
        trace: list[dict[str, Any]] = []
        evals = 0
        u = self._to_free(theta, l)
        hinv = None
        warm = (start is None and data.T > _WARM_T) if warm_start == "auto" else bool(warm_start)
        try:
            if warm:
                candidate = _subsample(data)
                sub: CensoredARData | None = candidate
                try:
                    _check_information(candidate)
                except ValidationError:  # a subsample without exact readings: start from the full record
                    sub = None
                if sub is not None:
                    ticker.tick("searching on a subsample")
                    try:
                        u_sub, _, n_ev, h_sub = self._search(
                            sub, u, max(gtol, _SEARCH_GTOL), maxiter, passes, coarse, None, ticker, None, []
                        )
                    except ValidationError:  # the subsample's estimates ran away: start from the full record
                        u_sub, n_ev, h_sub = u, 0, None
                    evals += n_ev
                    if h_sub is not None and np.isfinite(self.log_likelihood(data, self._from_free(u_sub, l))):
                        u = u_sub
                        n_full = int((~np.isnan(data.y)).sum())
                        hinv = h_sub * (int((~np.isnan(sub.y)).sum()) / max(n_full, 1))
            ticker.tick("searching")
            # with the coarse rule the Newton steps below finish the search (quadratically), so the search
            # itself stops within a hundredth of a standard error
            search_tol = max(gtol, _SEARCH_GTOL) if coarse else gtol
            u, (converged, message), n_ev, _ = self._search(
                data, u, search_tol, maxiter, passes, coarse, cb, ticker, hinv, trace
            )
            evals += n_ev
            theta = self._from_free(u, l)
            plan = self._checked_plan(data, theta)

            def f(th, plan=plan):
                ticker.tick()
                return self.log_likelihood(data, th, plan)

            ll = f(theta)
            evals += 1
            cov = None
            if standard_errors or coarse:
                ticker.tick("observed information")
                H = forward_hessian(f, theta, f0=ll)
                evals += 1 + theta.size + theta.size * (theta.size + 1) // 2
                cov = info = _inverse_information(H)
                theta_info = theta.copy()
                converged, message = False, message + "; the observed information is not positive definite"
                for _ in range(4):  # Newton steps on the model's own rule; the last one decides convergence
                    if info is None or not np.all(np.isfinite(info)):
                        break
                    ticker.tick("Newton steps on the model's rule")
                    hs = 1e-7 * np.maximum(1.0, np.abs(theta))
                    g = np.array([(f(theta + e) - ll) / hs[i] for i, e in enumerate(np.diag(hs))])
                    evals += theta.size
                    step = info @ g
                    se_ = np.sqrt(np.maximum(np.diagonal(info), 1e-300))
                    size = float(np.max(np.abs(step) / se_))
                    new_theta, new_ll = theta + step, -np.inf
                    for _ in range(8):
                        new_ll = f(new_theta)
                        evals += 1
                        if np.isfinite(new_ll) and new_ll >= ll - 1e-9 * max(1.0, abs(ll)):
                            break
                        step = step / 2
                        new_theta = theta + step
                    if size < gtol:
                        converged = True
                        message = (
                            f"the Newton step on the model's rule is {size:.2g} standard errors (below gtol = {gtol:g})"
                        )
                    else:
                        converged = False
                        message = (
                            f"the last Newton step on the model's rule is {size:.2g} standard errors (gtol = {gtol:g})"
                        )
                    if not (np.isfinite(new_ll) and new_ll >= ll - 1e-9 * max(1.0, abs(ll))):
                        break
                    theta, ll = new_theta, new_ll
                    trace.append(
                        {
                            "iteration": len(trace) + 1,
                            "loglik": float(ll),
                            "params": dict(zip(names, theta.tolist())),
                            "polish": True,
                            "seconds": round(time.perf_counter() - t0, 4),
                        }
                    )
                    if converged:
                        break
                # the information where the estimates ended, not where the Newton steps began, when the steps
                # moved them by more than 0.01 s.e. and 1e-4 of their size: the information changes by
                # O(|step|) relative, so a smaller move (long records: s.e. of 1e-3) leaves the s.e. to 1e-4
                shift = np.abs(theta - theta_info)
                moved = bool(
                    info is not None
                    and np.all(np.isfinite(info))
                    and np.max(shift / np.sqrt(np.maximum(np.diagonal(info), 1e-300))) > 0.01
                    and np.max(shift / np.maximum(1.0, np.abs(theta))) > 1e-4
                )
                if standard_errors and moved:
                    ticker.tick("observed information at the optimum")
                    cov = _inverse_information(forward_hessian(f, theta, f0=ll))
                    evals += 1 + theta.size + theta.size * (theta.size + 1) // 2
                if not standard_errors:
                    cov = None
        finally:
            close()
        k = len(names)
        n = int((~np.isnan(data.y)).sum())
        return FitResult(
            model=self,
            names=names,
            theta=theta,
            cov=cov,
            loglik=ll,
            n_obs=n,
            n_params=k,
            method="direct",
            likelihood="exact",
            converged=converged,
            message=message,
            trace=trace,
            fit_seconds=time.perf_counter() - t0,
            evaluations=evals,
            data=data,
        )

    def _checked_plan(self, data: CensoredARData, theta) -> GridPlan:
        """:meth:`plan`, with a run-away search named as such (the plan's size check raises)."""
        try:
            return self.plan(data, theta)
        except _PlanTooLarge as exc:
            raise ValidationError(
                f"y: the estimates ran away during the fit ({exc}); the likelihood of these readings "
                "appears to have no maximum (too few exactly observed readings, or a variance that goes "
                "to zero); check the data or give a start"
            ) from None

    def _search(self, data, u, gtol, maxiter, passes, coarse, cb, ticker, hinv, trace):
        """BFGS passes on the (coarse) rule, the plan frozen within a pass; returns
        ``(u, (converged, message), evaluations, inverse Hessian)``."""
        l = data.X.shape[1]
        names = self.names(l)
        search = self._coarse() if coarse else self
        converged, message, evals = False, "", 0
        for _ in range(passes):
            plan = search._checked_plan(data, self._from_free(u, l))
            out = maximize(
                lambda v, plan=plan: search.log_likelihood(data, self._from_free(v, l), plan),
                u,
                gtol=gtol,
                maxiter=maxiter,
                progress=cb,
                label=lambda v: dict(zip(names, self._from_free(v, l).tolist())),
                iteration0=len(trace),
                hess_inv0=hinv,
                ticker=ticker,
            )
            trace += out.trace
            evals += out.evaluations
            u, hinv = out.x, out.hess_inv
            converged, message = out.converged, out.message
            th = self._from_free(u, l)
            new_plan = search._checked_plan(data, th)
            evals += 1
            if new_plan == plan or abs(search.log_likelihood(data, th, new_plan) - out.value) < 1e-7 * max(
                1.0, abs(out.value) / 1e3
            ):
                break
        return u, (converged, message), evals, hinv

    # what a user does after a fit -----------------------------------------------------
    def system(self, theta, l: int):
        """The fitted model as a :class:`~tobitkf.LinearSystem` (:func:`ar_state_space`)."""
        beta, s2, phi = self.split(theta, l)
        return ar_state_space(beta, s2, phi)

    def to_spec(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "p": self.p,
            "nodes": self.nodes,
            "span": self.span,
            "panel_sd": self.panel_sd,
            "hermite": self.hermite,
        }


def _predictive_mixtures(data: CensoredARData, beta, sigma2, phi, plan: GridPlan):
    """Per step t: the one-step predictive of :math:`\\xi_t` given :math:`y_{1:t-1}` as a Gaussian mixture
    ``(weights, means, var)`` over the nodes of the previous p steps; and the final joint of the last p
    values ``(weights, nodes tuple)``."""
    p = phi.size
    preds = ar_predictors(phi, sigma2) if p > 0 else [(np.zeros(0), float(sigma2))]
    ll, kept = _forward(data, beta, sigma2, phi, plan, keep=True)
    if not np.isfinite(ll):
        raise ValidationError("theta: the data have zero probability under these parameters")
    out = []
    for t in range(data.T):
        a, v = preds[min(t, p)]
        if t == 0 or a.size == 0:
            out.append((np.ones(1), np.zeros(1), v))
            continue
        la_prev, zs_prev = kept[t - 1][2], kept[t - 1][4]
        w = np.exp(la_prev - la_prev.max())
        mean = np.zeros(la_prev.shape)
        for i in range(a.size):
            shape = [1] * la_prev.ndim
            shape[i] = zs_prev[i].size
            mean = mean + a[i] * zs_prev[i].reshape(shape)
        out.append(((w / w.sum()).ravel(), mean.ravel(), v))
    la_T, zs_T = kept[-1][2], kept[-1][4]
    wT = np.exp(la_T - la_T.max())
    return out, (wT / wT.sum(), zs_T)


def _mixture_cdf(x, w, m, v):
    from scipy.special import ndtr

    return float(np.sum(w * ndtr((x - m) / np.sqrt(v))))


def _mixture_quantile(q, w, m, v):
    from scipy.optimize import brentq

    sd = np.sqrt(v)
    lo, hi = float(np.min(m) - 12 * sd), float(np.max(m) + 12 * sd)
    return brentq(lambda x: _mixture_cdf(x, w, m, v) - q, lo, hi, xtol=1e-12)


def _ar_smooth(self, res):
    data = res.data
    beta, s2, phi = self.split(res.theta, data.X.shape[1])
    post = posterior_moments(data, beta, s2, phi, plan=self.plan(data, res.theta))
    return data.X @ beta + post.mean, post.var


def _ar_residuals(self, res, seed: int = 0):
    from scipy.special import ndtri

    data = res.data
    beta, s2, phi = self.split(res.theta, data.X.shape[1])
    mix, _ = _predictive_mixtures(data, beta, s2, phi, self.plan(data, res.theta))
    rng = np.random.default_rng(seed)
    mu = data.X @ beta
    r = np.full(data.T, np.nan)
    for t in range(data.T):
        w, m, v = mix[t]
        if np.isnan(data.y[t]):
            continue
        if data.side[t] == 0:
            uu = _mixture_cdf(data.y[t] - mu[t], w, m, v)
        elif data.side[t] < 0:
            uu = rng.uniform(0.0, _mixture_cdf(data.lower[t] - mu[t], w, m, v))
        else:
            uu = rng.uniform(_mixture_cdf(data.upper[t] - mu[t], w, m, v), 1.0)
        r[t] = float(ndtri(min(max(uu, 1e-300), 1 - 1e-16)))
    return r


def _ar_forecast(self, res, steps: int, *, X=None, level: float = 0.95, lower=None, upper=None):
    r"""Forecasts of :math:`y^*_{T+h}`, h = 1..steps, from the exact joint posterior of the last p values:
    a Gaussian mixture over its quadrature nodes, :math:`\xi_{T+h} \mid s_T \sim N(e_1^TA^hs_T, v_h)`,
    :math:`v_h = \sigma^2\sum_{j<h}(e_1^TA^je_1)^2`; central intervals from the mixture's quantiles."""
    data = res.data
    l = data.X.shape[1]
    beta, s2, phi = self.split(res.theta, l)
    if X is None:
        if l != 1:
            raise ValidationError(f"X: expected the future regressors ({steps}, {l}) for the forecast")
        Xf = np.ones((steps, 1))
    else:
        Xf = as_float_array(X, "X", ndim=(1, 2))
        Xf = Xf[:, None] if Xf.ndim == 1 else Xf
        if Xf.shape != (steps, l):
            raise ShapeError(f"X: expected the future regressors of shape ({steps}, {l}), got {Xf.shape}")
    A = ar_companion(phi)
    p = A.shape[0]
    _, (wT, zsT) = _predictive_mixtures(data, beta, s2, phi, self.plan(data, res.theta))
    if phi.size == 0:
        states = np.zeros((1, p))
        w = np.ones(1)
    else:
        grids = np.meshgrid(*zsT, indexing="ij")
        states = np.stack([g.ravel() for g in grids], axis=-1)  # (K, q) newest first
        if states.shape[1] < p:
            states = np.concatenate([states, np.zeros((states.shape[0], p - states.shape[1]))], axis=1)
        w = wT.ravel()
    keep = w > 1e-14 * w.max()
    states, w = states[keep], w[keep] / w[keep].sum()
    lo_lim = data.lower[-1] if lower is None else lower
    hi_lim = data.upper[-1] if upper is None else upper
    lo_lim = np.broadcast_to(np.asarray(lo_lim, dtype=float), (steps,))
    hi_lim = np.broadcast_to(np.asarray(hi_lim, dtype=float), (steps,))
    out: dict[str, Any] = {
        k: np.empty(steps)
        for k in ("mean", "sd", "lower", "upper", "censored_mean", "censored_lower", "censored_upper")
    }
    Ah = np.eye(p)
    vh = 0.0
    from ..censored import censored_moments

    for h in range(steps):
        vh = vh + s2 * (Ah[0, 0] ** 2)  # sum_{j<h+1} (e1' A^j e1)^2 sigma^2
        Ah = A @ Ah
        m = states @ Ah[0] + Xf[h] @ beta
        mean = float(w @ m)
        var = float(w @ (m - mean) ** 2 + vh)
        out["mean"][h], out["sd"][h] = mean, np.sqrt(var)
        a = (1 - level) / 2
        ql, qu = _mixture_quantile(a, w, m, vh), _mixture_quantile(1 - a, w, m, vh)
        out["lower"][h], out["upper"][h] = ql, qu
        st = censored_moments(m, np.sqrt(vh), lo_lim[h], hi_lim[h])
        out["censored_mean"][h] = float(w @ st.censored_mean)
        out["censored_lower"][h] = min(max(ql, lo_lim[h]), hi_lim[h])
        out["censored_upper"][h] = min(max(qu, lo_lim[h]), hi_lim[h])
    out["level"] = level
    return out


CensoredAR.smooth = _ar_smooth  # type: ignore[attr-defined]  # defined after the class: they use its fit results
CensoredAR.residuals = _ar_residuals  # type: ignore[attr-defined]  # (as above)
CensoredAR.forecast = _ar_forecast  # type: ignore[attr-defined]  # (as above)
