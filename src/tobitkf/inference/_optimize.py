r"""Numerical maximisation helpers of the fits: finite-difference gradients and Hessians, a BFGS driver
with a scale-free stopping rule, a convergence trace and a progress callback.

The log-likelihoods maximised here are smooth to rounding (the exact censored-AR likelihood holds its
quadrature plan fixed within a pass, :mod:`tobitkf.inference.censored_ar`), so central differences
with a step :math:`h_i = h\max(1, |u_i|)` give gradients accurate to :math:`O(h^2)` and rounding
:math:`O(\epsilon|\ell|/h)`; with h = 1e-5 both are below 1e-6 for log-likelihoods of order 10^3.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .._progress import plural
from .._validation import ValidationError

__all__ = [
    "central_gradient",
    "forward_gradient",
    "central_hessian",
    "forward_hessian",
    "maximize",
    "Outcome",
    "check_tolerance",
    "check_iterations",
    "Ticker",
    "maximize_map",
    "maximize_closing",
    "observed_information",
]


def central_gradient(f: Callable[[np.ndarray], float], x: np.ndarray, step: float = 1e-5) -> np.ndarray:
    r""":math:`\partial f/\partial x_i \approx (f(x + h_ie_i) - f(x - h_ie_i))/(2h_i)`, :math:`h_i = h\max(1, |x_i|)`."""
    x = np.asarray(x, dtype=float)
    g = np.empty_like(x)
    for i in range(x.size):
        h = step * max(1.0, abs(x[i]))
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def forward_gradient(f: Callable[[np.ndarray], float], x: np.ndarray, fx: float, step: float = 1e-6) -> np.ndarray:
    r""":math:`\partial f/\partial x_i \approx (f(x + h_ie_i) - f(x))/h_i`, :math:`h_i = h\max(1, |x_i|)`, with the
    value ``fx`` = f(x) already known: d evaluations, error :math:`O(h)` plus :math:`O(\epsilon|f|/h)`."""
    x = np.asarray(x, dtype=float)
    g = np.empty_like(x)
    for i in range(x.size):
        hi = step * max(1.0, abs(x[i]))
        e = np.zeros_like(x)
        e[i] = hi
        g[i] = (f(x + e) - fx) / hi
    return g


def central_hessian(
    f: Callable[[np.ndarray], float], x: np.ndarray, step: float = 1e-4, f0: float | None = None
) -> np.ndarray:
    r"""Central-difference Hessian: :math:`(f(x+h_i) - 2f(x) + f(x-h_i))/h_i^2` on the diagonal and the
    four-point rule off it; :math:`1 + 2d + 2d(d-1)` evaluations, error :math:`O(h^2)`."""
    x = np.asarray(x, dtype=float)
    d = x.size
    h = step * np.maximum(1.0, np.abs(x))
    fx = f(x) if f0 is None else f0
    H = np.empty((d, d))
    fp = np.empty(d)
    fm = np.empty(d)
    for i in range(d):
        e = np.zeros(d)
        e[i] = h[i]
        fp[i], fm[i] = f(x + e), f(x - e)
        H[i, i] = (fp[i] - 2 * fx + fm[i]) / h[i] ** 2
    for i in range(d):
        for j in range(i + 1, d):
            ei = np.zeros(d)
            ej = np.zeros(d)
            ei[i], ej[j] = h[i], h[j]
            v = (f(x + ei + ej) - f(x + ei - ej) - f(x - ei + ej) + f(x - ei - ej)) / (4 * h[i] * h[j])
            H[i, j] = H[j, i] = v
    return H


def forward_hessian(
    f: Callable[[np.ndarray], float], x: np.ndarray, step: float = 1e-4, f0: float | None = None
) -> np.ndarray:
    r"""Forward-difference Hessian, :math:`H_{ij} \approx (f(x + h_ie_i + h_je_j) - f(x + h_ie_i) - f(x + h_je_j)
    + f(x))/(h_ih_j)`: :math:`1 + d + d(d+1)/2` evaluations (21 for d = 5, against 51 for
    :func:`central_hessian`), error :math:`O(h)` plus rounding :math:`O(\epsilon|f|/h^2)`; with
    h = 1e-4 and a log-likelihood smooth to 1e-12 both are about 1e-4 relative."""
    x = np.asarray(x, dtype=float)
    d = x.size
    h = step * np.maximum(1.0, np.abs(x))
    fx = f(x) if f0 is None else f0
    E = np.diag(h)
    fi = np.array([f(x + E[i]) for i in range(d)])
    H = np.empty((d, d))
    for i in range(d):
        for j in range(i, d):
            v = (f(x + E[i] + E[j]) - fi[i] - fi[j] + fx) / (h[i] * h[j])
            H[i, j] = H[j, i] = v
    return H


def check_tolerance(value: Any, name: str) -> float:
    """A tolerance: a finite positive real number (booleans and text refused), naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValidationError(f"{name}: expected a positive finite number, got {value!r} ({type(value).__name__})")
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValidationError(f"{name}: expected a positive finite number, got {value!r}")
    return v


def check_iterations(value: Any, name: str) -> int:
    """An iteration count: an integer >= 1 (booleans, floats and text refused), naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValidationError(f"{name}: expected an integer >= 1, got {value!r} ({type(value).__name__})")
    return int(value)


class Ticker:
    """Rate-limited progress lines on stderr for long fits: silent for the first ``after`` seconds, then
    one line at most every ``every`` seconds (plain text, so it shows in logs and CI as on a terminal).
    ``tick(text)`` is cheap enough to call on every likelihood evaluation."""

    def __init__(self, title: str, *, enabled: bool = True, after: float = 10.0, every: float = 10.0):
        self.title, self.enabled, self.every = title, enabled, every
        self.t0 = time.perf_counter()
        self.next = self.t0 + after
        self.status = "starting"

    def tick(self, status: str | None = None) -> None:
        if status is not None:
            self.status = status
        if not self.enabled:
            return
        now = time.perf_counter()
        if now >= self.next:
            import sys

            print(f"{self.title}: {self.status} ({now - self.t0:.0f} s elapsed)", file=sys.stderr, flush=True)
            self.next = now + self.every


@dataclass
class Outcome:
    r"""Result of :func:`maximize`: the maximiser, the value, the trace and the counts; ``hess_inv`` the
    final quasi-Newton approximation of :math:`(-\nabla^2 f)^{-1}` and ``decrement`` the last
    :math:`\sqrt{g^TH^{-1}g}`."""

    x: np.ndarray
    value: float
    converged: bool
    message: str
    iterations: int
    evaluations: int
    trace: list[dict[str, Any]] = field(default_factory=list)
    hess_inv: np.ndarray | None = None
    decrement: float = np.nan


def maximize(
    f: Callable[[np.ndarray], float],
    x0: np.ndarray,
    *,
    gtol: float = 1e-3,
    maxiter: int = 200,
    step: float | None = None,
    difference: str = "forward",
    progress: Callable[[dict[str, Any]], None] | None = None,
    label: Callable[[np.ndarray], dict[str, Any]] | None = None,
    iteration0: int = 0,
    hess_inv0: np.ndarray | None = None,
    ticker: Ticker | None = None,
) -> Outcome:
    r"""Maximise ``f`` by BFGS with finite-difference gradients, a backtracking (Armijo) line search and a
    scale-free stopping rule.

    **Stopping rule.** With :math:`g` the gradient and :math:`H^{-1}` the quasi-Newton approximation of
    the inverse of minus the Hessian (for a log-likelihood: the covariance of the estimates), stop when
    the Newton decrement

    .. math:: \lambda = \sqrt{g^TH^{-1}g} < \texttt{gtol},

    i.e. when the remaining quasi-Newton step is shorter than ``gtol`` standard errors (in the metric of
    the information) and the log-likelihood can still gain about :math:`\lambda^2/2`. Unlike a bound on
    the gradient itself, this does not tighten as the record grows (the gradient of a log-likelihood of
    :math:`10^6` readings is large where the estimates are already within a small fraction of a standard
    error). It is checked only once :math:`H^{-1}` rests on at least one curvature update (or on
    ``hess_inv0``). ``converged`` is True only when the rule was met; a line search that finds no
    increase ends the search with ``converged=False`` and the reason.

    Forward differences (d evaluations per gradient, the value at x reused, relative step 1e-6) are the
    default: their O(h) error moves the quasi-Newton step by about h in the parameters, far below a
    standard error. ``difference="central"`` (2d evaluations, h = 1e-5) for objectives that need more.

    Parameters
    ----------
    f : callable
        The objective (a log-likelihood) of the unconstrained vector; ``-inf`` or NaN count as a failed step.
    x0 : (d,) ndarray
    gtol : float
        Tolerance of the Newton decrement (in standard errors).
    maxiter : int
    step : float, optional
        Relative finite-difference step (default 1e-6 forward, 1e-5 central).
    difference : {"forward", "central"}
    progress : callable, optional
        Called after every iteration with its trace entry.
    label : callable, optional
        Maps x to the named parameters recorded in the trace.
    iteration0 : int
        Number of the first iteration in the trace (passes continue the count).
    hess_inv0 : (d, d) ndarray, optional
        Starting inverse Hessian (positive definite); default the identity, with a first step of length
        at most 1.
    ticker : Ticker, optional
        Told of every evaluation (progress lines on long fits).

    Returns
    -------
    Outcome

    Raises
    ------
    ValidationError
        ``gtol`` not a positive finite number, ``maxiter`` not an integer >= 1, an unknown ``difference``,
        a non-finite ``f(x0)``.
    """
    gtol = check_tolerance(gtol, "gtol")
    maxiter = check_iterations(maxiter, "maxiter")
    if difference not in ("forward", "central"):
        raise ValidationError(f"difference: expected 'forward' or 'central', got {difference!r}")
    if step is None:
        step = 1e-6 if difference == "forward" else 1e-5
    count = [0]
    t0 = time.perf_counter()

    def val(x: np.ndarray) -> float:
        count[0] += 1
        v = float(f(x))
        if ticker is not None:
            ticker.tick()
        return v if np.isfinite(v) else -np.inf

    def grad(x: np.ndarray, fx: float) -> np.ndarray:
        if difference == "central":
            return central_gradient(val, x, step)
        return forward_gradient(val, x, fx, step)

    x = np.array(x0, dtype=float)
    d = x.size
    fx = val(x)
    if not np.isfinite(fx):
        raise ValidationError("x0: the objective is not finite at the starting point")
    trace: list[dict[str, Any]] = []
    if d == 0:
        return Outcome(x, fx, True, "nothing to estimate", 0, count[0], trace, np.zeros((0, 0)), 0.0)
    g = grad(x, fx)
    have_curvature = hess_inv0 is not None
    # without a start, the identity (as scipy's BFGS): its first step is cut to length 1 below, and
    # each update corrects the curvature along its step only, keeping long steps in flat directions
    Hinv = np.eye(d) if hess_inv0 is None else np.array(hess_inv0, dtype=float)
    converged, message, dec = False, f"stopped after {plural(maxiter, 'iteration')}", np.nan
    for _ in range(maxiter):
        if not np.all(np.isfinite(g)):
            message = "the gradient is not finite"
            break
        direction = Hinv @ g
        dec2 = float(g @ direction)
        if not dec2 > 0:  # lost positive definiteness: restart from the identity
            Hinv = np.eye(d)
            have_curvature = False
            direction = Hinv @ g
            dec2 = float(g @ direction)
        dec = float(np.sqrt(max(dec2, 0.0)))
        if have_curvature and dec < gtol:
            converged, message = True, f"Newton decrement {dec:.2g} below gtol = {gtol:g} (standard errors)"
            break
        # a first trial step of length at most 1 until the curvature is known
        alpha, fnew, xnew = (1.0 if have_curvature else min(1.0, 1.0 / float(np.linalg.norm(direction)))), -np.inf, x
        for _ in range(40):  # backtracking: Armijo's sufficient increase
            xnew = x + alpha * direction
            fnew = val(xnew)
            if np.isfinite(fnew) and fnew >= fx + 1e-4 * alpha * dec2:
                break
            alpha *= 0.5
        else:
            if have_curvature and dec < 10 * gtol:
                converged = True
                message = f"Newton decrement {dec:.2g} below 10 gtol and no further increase within rounding"
            else:
                message = f"the line search found no increase (Newton decrement {dec:.2g} standard errors)"
            break
        gnew = grad(xnew, fnew)
        s_, y_ = xnew - x, g - gnew  # y_ = change of the gradient of -f
        sy = float(s_ @ y_)
        if sy > 1e-12 * float(np.linalg.norm(s_) * np.linalg.norm(y_)) and np.all(np.isfinite(gnew)):
            rho = 1.0 / sy
            V = np.eye(d) - rho * np.outer(s_, y_)
            Hinv = V @ Hinv @ V.T + rho * np.outer(s_, s_)
            have_curvature = True
        x, fx, g = xnew, fnew, gnew
        entry = {
            "iteration": iteration0 + len(trace) + 1,
            "loglik": float(fx),
            "params": label(x) if label is not None else x.tolist(),
            "seconds": round(time.perf_counter() - t0, 4),
        }
        trace.append(entry)
        if ticker is not None:
            ticker.tick(f"iteration {entry['iteration']}, log-likelihood {fx:.6f}")
        if progress is not None:
            progress(entry)
    return Outcome(
        x=x,
        value=float(fx),
        converged=converged,
        message=message,
        iterations=len(trace),
        evaluations=count[0],
        trace=trace,
        hess_inv=Hinv,
        decrement=dec,
    )


def maximize_map(
    ll_of: Callable[[np.ndarray], float],
    th0: np.ndarray,
    names: list[str],
    *,
    gtol: float,
    maxiter: int,
    progress: tuple[Any, Callable[[], None], Ticker],
    standard_errors: bool = True,
    check_always: bool = False,
) -> tuple[Outcome, np.ndarray, float, np.ndarray | None]:
    r"""The direct fit of a user map's parameters, shared by every kind of model: the log-likelihood checked at
    ``th0``, :func:`maximize`, then the observed information (inverse of minus the central-difference Hessian) and
    the Newton-step convergence check (:func:`_newton_check`; with ``check_always`` also when no standard errors
    are wanted). ``progress`` is the ``(callback, close, ticker)`` of the fit's progress option.

    Returns ``(outcome, theta, loglik, cov)`` with the outcome's ``converged``/``message`` those of the check,
    ``cov`` None without standard errors.

    Raises
    ------
    ValidationError
        The log-likelihood is not finite at ``th0``.
    """
    if not np.isfinite(ll_of(th0)):
        raise ValidationError("theta0: the log-likelihood is -inf (or the map fails) at the starting values")
    out = maximize_closing(
        ll_of, th0, progress, gtol=gtol, maxiter=maxiter, label=lambda v: dict(zip(names, v.tolist()))
    )
    th = out.x
    ll = ll_of(th)
    cov = None
    if standard_errors or check_always:
        cov, out.converged, out.message, _ = observed_information(ll_of, th, ll, gtol, out.message)
    return out, th, ll, (cov if standard_errors else None)


def _inverse_information(H: np.ndarray) -> np.ndarray | None:
    """The inverse of the observed information -H, or an all-NaN matrix when -H is not positive definite."""
    info = -0.5 * (H + H.T)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        return np.full(info.shape, np.nan)
    return np.linalg.inv(info)


def _newton_check(f, v, cov, gtol: float, optimizer_message: str) -> tuple[bool, str, int]:
    r"""Whether ``v`` is an optimum to ``gtol`` standard errors: the Newton step :math:`\delta = I^{-1}g`
    with the observed information (``cov`` = :math:`I^{-1}`) and a central-difference gradient g must be
    below ``gtol`` standard errors in every parameter. Returns ``(converged, message, evaluations)``."""
    if cov is None or not np.all(np.isfinite(cov)):
        return False, optimizer_message + "; the observed information is not positive definite there", 0
    g = central_gradient(f, v)
    if not np.all(np.isfinite(g)):
        return False, optimizer_message + "; the gradient is not finite there", 2 * v.size
    se = np.sqrt(np.maximum(np.diagonal(cov), 1e-300))
    size = float(np.max(np.abs(cov @ g) / se, initial=0.0))
    if size < gtol:
        return True, f"{optimizer_message}; Newton step {size:.2g} standard errors (below gtol = {gtol:g})", 2 * v.size
    return (
        False,
        f"{optimizer_message}; but the Newton step to the optimum is still {size:.2g} standard errors "
        f"(gtol = {gtol:g})",
        2 * v.size,
    )


def maximize_closing(
    f: Callable[[np.ndarray], float],
    x0: np.ndarray,
    progress: tuple[Any, Callable[[], None], Ticker],
    *,
    gtol: float,
    maxiter: int,
    label: Callable[[np.ndarray], Any] | None = None,
) -> Outcome:
    """:func:`maximize` of ``f`` from ``x0`` reporting to ``progress`` (the ``(callback, close, ticker)`` of a fit's
    ``progress`` option), closed whatever happens: the direct maximisation of every fit."""
    cb, close, ticker = progress
    try:
        return maximize(f, x0, gtol=gtol, maxiter=maxiter, progress=cb, label=label, ticker=ticker)
    finally:
        close()


def observed_information(
    f: Callable[[np.ndarray], float], v: np.ndarray, f0: float, gtol: float, optimizer_message: str
) -> tuple[np.ndarray | None, bool, str, int]:
    r"""The standard errors and the convergence verdict of a fit at ``v`` (``f0`` = f(v)): the covariance
    :math:`I^{-1}` from the central-difference Hessian (all NaN where the observed information is not positive
    definite) and :func:`_newton_check` with it. Returns ``(cov, converged, message, evaluations of the check)``.
    """
    cov = _inverse_information(central_hessian(f, v, f0=f0))
    converged, message, evaluations = _newton_check(f, v, cov, gtol, optimizer_message)
    return cov, converged, message, evaluations
