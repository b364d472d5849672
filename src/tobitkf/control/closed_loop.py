r"""Closed-loop simulation: plant + censored sensor + (Tobit) Kalman observer + LQR, batched over runs.

Source: Miller (2015) §6.2 (the TKF as observer in LQG, (6.14)–(6.21)), §6.4 (output feedback with
the steady-state TKF and a moving limit, (6.45)); our deviations: docs/sources/miller2015-ch5-7.md.

Loop, for k = 1..T (package time convention: x_0 ~ N(x0, P0), y_1 at index 0):

.. math::

    u_k &= \bar N r_k - K\hat x_{k-1|k-1} \qquad (6.22), (6.45) \\
    x_k &= Ax_{k-1} + B^u u_k + w_{k-1}, \qquad y^*_k = Cx_k + Du_k + v_k \\
    \bar x_k &= A\hat x_{k-1|k-1} + B^u u_k \quad\text{(the input applied over (k-1, k], Miller (3.51))} \\
    y_k &= \mathrm{clip}(y^*_k, l_k, h_k), \qquad \hat x_{k|k} = \text{observer update}(\bar x_k, y_k)

Observers (``observer=``), each an estimator driven through its public online API
(``predict(state, u=u_k)``, then ``update(pred, y_k, ...)``), as a user would drive it:

==============  ===============================================================================
``"kf"``        :class:`~tobitkf.KalmanFilter`, treating censored readings as ordinary ones (the
                text's KF-LQG)
``"tkf"``       :class:`~tobitkf.TobitKalmanFilter` (3.55) at the fixed limits of ``censoring``
``"tkf-moving"`` the same TKF, with the sensor limit set from its prior by (3.56) (γ̂ ≡ Ξ), passed to
                ``update(..., lower=, upper=)``
``"sstkf"``     :class:`~tobitkf.filters.steady_state.SteadyStateTobitKalmanFilter` (fixed gain K∞ of the
                modified DARE, moving limit (3.56))
==============  ===============================================================================

Two implementations of the loop (``backend=``): the numpy loop below, the reference, which drives the
observer through its online API step by step, and a compiled loop (:mod:`tobitkf.control._compiled_closed`,
the default when numba imports) that runs plant, sensor, observer and control law of a block of runs per
step in one kernel, built from the TKF kernel's predict and update blocks; the two agree to rounding
(tested to 1e-12 in ``tests/control/test_closed_loop_compiled.py``) and see the same random draws.

The random draws (x_0, then w, then v) come from one generator in a fixed order, so the same seed
gives the same noise to every observer: with infinite limits ``"kf"`` and ``"tkf"`` produce
identical trajectories (tested in
``tests/control/test_closed_loop.py::test_t4_infinite_limit_kf_and_tkf_loops_are_identical``).

Deviation from the source: (6.45) writes the idealised observer
:math:`\hat x_{k+1} = (A - L\gamma C)\hat x_k + Bu_k + L\gamma Cx_k`, which uses the true state and
cannot be run; the implementable filter form above is used (ours, not in the source; docs/sources MB-16,
MB-23). (6.15) prints the left-censoring expectation for a right-censored sensor; the expectation always
matches the sensor's censoring side here (docs/sources MB-22).

Divergence: a run whose state or estimate leaves ``divergence_bound`` is frozen at its last value
and flagged in ``diverged`` / ``diverged_step`` (never a silent NaN or overflow).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._linalg import eigh_sqrt as psd_sqrt
from .._progress import plural
from .._validation import (
    ShapeError,
    ValidationError,
    as_float,
    as_float_array,
    as_generator,
    check_count,
    check_instance,
    check_memory,
    check_option,
    diagonal_sigma,
)
from ..channels.censoring import Censoring
from ..filters._backend import BACKENDS, use_compiled
from ..filters.kalman import KalmanFilter
from ..filters.steady_state import SteadyStateTobitKalmanFilter
from ..filters.tobit import NOISE_TERMS, TobitKalmanFilter
from ..models.linear import LinearSystem
from .lqg import controlled_noise, reference_gain

__all__ = ["ClosedLoopResult", "simulate_closed_loop", "OBSERVERS", "quadratic_cost"]

OBSERVERS = ("kf", "tkf", "tkf-moving", "sstkf")


@dataclass(frozen=True)
class ClosedLoopResult:
    """Trajectories of a batch of closed-loop runs.

    Attributes
    ----------
    x : (N, T+1, n)   true states x_0..x_T
    estimate : (N, T, n)   x̂_{k|k} (index k-1)
    pred_estimate : (N, T, n)   x̄_k
    cov : (N, T, n, n)   observer covariance Ψ_{k|k} (constant Ψ∞ for ``"sstkf"``)
    u : (N, T, p)   inputs u_k (index k-1)
    y, y_latent : (N, T, m)   censored and latent readings
    lower, upper : (N, T, m)   the limits the sensor used
    p_uncensored : (N, T, m)   γ̂ at the prior (1 for ``"kf"``, Ξ for the moving limit)
    reference : (T, r)   r_k
    diverged : (N,) bool ; diverged_step : (N,) int (-1 if not)
    """

    x: np.ndarray
    estimate: np.ndarray
    pred_estimate: np.ndarray
    cov: np.ndarray
    u: np.ndarray
    y: np.ndarray
    y_latent: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    p_uncensored: np.ndarray
    reference: np.ndarray
    diverged: np.ndarray
    diverged_step: np.ndarray


def _reference(reference: Any, steps: int, nr: int) -> np.ndarray:
    r = as_float_array(reference, "reference")
    if r.ndim == 0:
        r = np.full((steps, nr), float(r))
    elif r.ndim == 1 and r.shape[0] == nr:
        r = np.broadcast_to(r, (steps, nr)).copy()
    elif r.ndim == 1 and nr == 1 and r.shape[0] >= steps:
        r = r[:steps, None]
    elif r.ndim == 2 and r.shape[1] == nr and r.shape[0] >= steps:
        r = r[:steps]
    else:
        raise ShapeError(f"reference: expected a scalar, ({nr},) or (T>={steps}, {nr}), got {r.shape}")
    return r


def simulate_closed_loop(
    plant: LinearSystem,
    K: Any,
    steps: int,
    runs: int = 1,
    *,
    observer: str = "tkf",
    censoring: Censoring | None = None,
    xi_uncensored: Any = None,
    side: str = "upper",
    reference: Any = 0.0,
    Nbar: Any = None,
    Cz: Any = None,
    seed: Any = 0,
    x0_estimate: Any = None,
    P0_estimate: Any = None,
    noise_term: str = "dissertation",
    divergence_bound: float = 1e8,
    noise: dict | None = None,
    backend: str = "auto",
) -> ClosedLoopResult:
    r"""Simulate the LQG loop with a (Tobit) Kalman observer over many runs at once.

    Parameters
    ----------
    plant : LinearSystem
        Time-invariant DT plant with a control input ``Bu``; R diagonal for the Tobit observers.
    K : (p, n) array_like
        State-feedback gain (e.g. :func:`~tobitkf.control.lqg.dlqr`).
    steps, runs : int
        Horizon T and number of runs N.
    observer : {"kf", "tkf", "tkf-moving", "sstkf"}, default "tkf"
        See the module docstring.
    censoring : Censoring, optional
        Fixed sensor limits for ``"kf"`` and ``"tkf"`` (default: none).
    xi_uncensored : float or (m,) in (0, 1)
        Target probability Ξ of an uncensored reading, required by ``"tkf-moving"`` and ``"sstkf"``.
    side : {"upper", "lower"}, default "upper"
        Censoring side of the moving limit.
    reference : scalar, (r,) or (T, r) array_like, default 0
        Setpoint r_k of the tracked output z = C_z x.
    Nbar : (p, r) array_like, optional
        Reference gain; default :func:`~tobitkf.control.lqg.reference_gain` for unit DC gain
        (only computed when the reference is not identically zero).
    Cz : (r, n) array_like, optional
        Tracked output; default the measured C.
    seed : int or Generator
    x0_estimate, P0_estimate : array_like, optional
        Observer prior (default the plant's x0, P0); the truth draws x_0 ~ N(x0, P0).
    noise_term : str
        Tobit noise term of the TKF observers (see :class:`~tobitkf.TobitKalmanFilter`).
    divergence_bound : float, default 1e8
        Runs whose |x| or |x̂| exceed it are frozen and flagged.
    noise : dict, optional
        Pre-drawn randomness ``{"x0": (N, n), "w": (N, T, n), "v": (N, T, m)}`` (initial state, process
        noise as added to the state, measurement noise); overrides ``seed`` (common random numbers
        across designs, or one run of a batch re-run alone).
    backend : {"auto", "numpy", "numba"}, default "auto"
        The time loop: ``"numpy"`` the loop below, driving the observer through its online API (the
        reference); ``"numba"`` the compiled loop of :mod:`tobitkf.control._compiled_closed` (plant, observer
        and control law per step, batched over runs; the same noises, equal to the numpy loop to rounding,
        tested to 1e-12), which covers every observer, with a diagonal R for ``"kf"``; ``"auto"`` the
        compiled loop when numba imports and the case is covered, else numpy.

    Returns
    -------
    ClosedLoopResult

    Raises
    ------
    ValidationError
        Unknown observer, missing or invalid Ξ (outside (0, 1)), a plant without input, a
        time-varying plant, non-diagonal R for a Tobit observer, an untrackable reference, an unknown
        ``backend`` or ``backend="numba"`` for the KF observer with a non-diagonal R.
    ImportError
        ``backend="numba"`` without numba installed.
    ShapeError
        Non-conforming K, Nbar, Cz or reference.
    """
    try:
        divergence_bound = as_float(divergence_bound, "divergence_bound", low=0.0, low_open=True)
    except ValidationError:
        raise ValidationError(f"divergence_bound: expected a positive number, got {divergence_bound!r:.40}") from None
    check_option(observer, "observer", OBSERVERS)
    check_option(side, "side", ("upper", "lower"))
    check_option(noise_term, "noise_term", NOISE_TERMS)
    check_option(backend, "backend", BACKENDS)
    check_instance(plant, LinearSystem, "plant")
    if plant.Bu is None:
        raise ValidationError("plant: the closed loop needs a control input matrix Bu")
    if not plant.time_invariant or plant.Bu.varying:
        raise ValidationError("plant: simulate_closed_loop needs a time-invariant plant")
    steps, runs = check_count(steps, "steps"), check_count(runs, "runs")
    n, m, p = plant.n, plant.m, plant.p
    assert p is not None, "a plant with an input matrix (plant.Bu is read above)"
    check_memory(
        8 * runs * (steps + 1) * (4 * n + n * n + 3 * m + p),
        "runs/steps",
        f"{plural(runs, 'run')} x {plural(steps, 'step')} (n = {n}, m = {m}: states, estimates, covariances, readings)",
    )
    A, C, Bu = plant.transition(0), plant.measurement(1), plant.Bu.at(1)
    D = None if plant.D is None else plant.D.at(1)
    R = plant.measurement_cov(1)
    K = np.atleast_2d(as_float_array(K, "K"))
    if K.shape != (p, n):
        raise ShapeError(f"K: expected ({p}, {n}), got {K.shape}")
    Cz = C if Cz is None else np.atleast_2d(as_float_array(Cz, "Cz"))
    if Cz.shape[1] != n:
        raise ShapeError(f"Cz: expected (r, {n}), got {Cz.shape}")
    r = _reference(reference, steps, Cz.shape[0])
    if Nbar is None:
        Nbar = np.zeros((p, Cz.shape[0])) if not np.any(r) else reference_gain(A, Bu, Cz, K, domain="dt")
    Nbar = np.atleast_2d(as_float_array(Nbar, "Nbar"))
    if Nbar.shape != (p, Cz.shape[0]):
        raise ShapeError(f"Nbar: expected ({p}, {Cz.shape[0]}), got {Nbar.shape}")

    tobit = observer != "kf"
    sigma = diagonal_sigma(R) if tobit else np.sqrt(np.diagonal(R))
    moving = observer in ("tkf-moving", "sstkf")
    shift = None
    if moving:
        if xi_uncensored is None:
            raise ValidationError(
                f"xi_uncensored: observer {observer!r} needs the target probability of an uncensored reading, in (0, 1)"
            )
        xi = as_float_array(xi_uncensored, "xi_uncensored")
        if xi.size not in (1, m):
            raise ShapeError(f"xi_uncensored: expected a scalar or ({m},), got shape {xi.shape}")
        xi = np.broadcast_to(xi.reshape(-1), (m,)).copy()
        controlled_noise(xi, sigma)  # raises for xi outside (0, 1)
        from scipy.special import ndtri

        shift = sigma * ndtri(xi) * (1.0 if side == "upper" else -1.0)
    elif xi_uncensored is not None:
        raise ValidationError(f"xi_uncensored: only used by the moving-limit observers, not {observer!r}")
    if moving and censoring is not None:
        raise ValidationError(f"censoring: observer {observer!r} sets its own moving limit; do not pass fixed limits")
    cens = Censoring() if censoring is None else censoring
    if not isinstance(cens, Censoring):
        raise ValidationError(f"censoring: expected a Censoring, got {type(censoring).__name__}")
    cens.check(m, steps)
    obs: KalmanFilter | SteadyStateTobitKalmanFilter | TobitKalmanFilter
    if observer == "kf":
        obs = KalmanFilter(plant, backend="numpy")
    elif observer == "sstkf":
        obs = SteadyStateTobitKalmanFilter(plant, xi, side=side)
    else:
        obs = TobitKalmanFilter(
            plant, Censoring() if moving else cens, noise_term=noise_term, backend="numpy", check_limits=False
        )

    x = np.empty((runs, steps + 1, n))
    if noise is None:
        rng = as_generator(seed)
        x[:, 0] = plant.x0 + rng.standard_normal((runs, n)) @ psd_sqrt(plant.P0).T
        w = rng.standard_normal((runs, steps, plant.q))
        v = rng.standard_normal((runs, steps, m)) @ psd_sqrt(R).T
        G = psd_sqrt(plant.Q.at(0))
        if plant.B is not None:
            G = plant.B.at(0) @ G
        w = w @ G.T
    else:
        missing = [k for k in ("x0", "w", "v") if k not in noise] if isinstance(noise, dict) else ["x0", "w", "v"]
        if missing:
            raise ValidationError(f"noise: expected keys 'x0', 'w', 'v' (a dict), missing {', '.join(missing)}")
        try:
            x[:, 0], w, v = (
                np.broadcast_to(as_float_array(noise[key], f"noise[{key!r}]"), shape)
                for key, shape in (("x0", (runs, n)), ("w", (runs, steps, n)), ("v", (runs, steps, m)))
            )
        except KeyError as exc:
            raise ValidationError(f"noise: expected keys 'x0', 'w', 'v', missing {exc}") from None
        except ValidationError:  # NaN, inf or text in noise['w'] ...: named by as_float_array
            raise
        except ValueError:
            raise ShapeError(
                f"noise: expected x0 ({runs}, {n}), w ({runs}, {steps}, {n}), v ({runs}, {steps}, {m}), got "
                f"{[np.shape(noise[k]) for k in ('x0', 'w', 'v')]}"
            ) from None

    if observer == "sstkf":
        if P0_estimate is not None:
            raise ValidationError("P0_estimate: the steady-state observer has the constant covariance Psi_inf")
        state = obs.init((runs,), x0=x0_estimate)
    else:
        state = obs.init((runs,), x0=x0_estimate, P0=P0_estimate)
    gap = "the KF observer with a non-diagonal R" if observer == "kf" and np.any(R != np.diag(np.diagonal(R))) else None
    if use_compiled(backend, gap, "the closed loop"):
        run = _compiled_loop(
            plant, obs, observer, state, x, w, v, K, Nbar, r, cens, sigma, noise_term, divergence_bound, shift, side
        )
        run["x"], run["reference"] = x, r
        return _result(run)
    out = _outputs(runs, steps, n, p, m)
    alive = np.ones(runs, dtype=bool)
    diverged_step = np.full(runs, -1)
    inf = np.full((runs, m), np.inf)
    for k in range(1, steps + 1):
        xh = state.mean
        uk = r[k - 1] @ Nbar.T - xh @ K.T
        xk = x[:, k - 1] @ A.T + uk @ Bu.T + w[:, k - 1]
        dy = 0.0 if D is None else uk @ D.T
        ylat = xk @ C.T + dy + v[:, k - 1]
        pred = obs.predict(state, u=uk)  # x̄_k = A x̂_{k-1|k-1} + B^u u_k
        xbar = pred.mean
        if moving:
            lim = xbar @ C.T + dy + shift
            lo, hi = (-inf, lim) if side == "upper" else (lim, inf)
        else:
            l0, h0 = cens.limits(k)
            lo, hi = np.broadcast_to(l0, (runs, m)), np.broadcast_to(h0, (runs, m))
        yk = np.minimum(np.maximum(ylat, lo), hi)  # the sensor
        if observer == "kf":
            new = obs.update(pred, yk)
            gam = np.ones((runs, m))
        elif observer == "sstkf":
            new = obs.update(pred, yk)
            gam = np.broadcast_to(xi, (runs, m))
        else:
            new = obs.update(pred, yk, lower=lo, upper=hi)
            gam = new.extras["p_uncensored"]
        xnew = new.mean
        bad = alive & ~(np.all(np.abs(xk) < divergence_bound, axis=1) & np.all(np.abs(xnew) < divergence_bound, axis=1))
        if bad.any():
            diverged_step[bad] = k
            alive &= ~bad
        keep = alive[:, None]
        x[:, k] = np.where(keep, xk, x[:, k - 1])
        if keep.all():
            state = new
        else:  # a diverged run is frozen at its last estimate
            assert new.P is not None and state.P is not None, "the observers carry their covariance"
            P_new = new.P if new.P.shape[0] == runs else np.broadcast_to(new.P, (runs,) + new.P.shape[1:])
            P_old = state.P if state.P.shape[0] == runs else np.broadcast_to(state.P, (runs,) + state.P.shape[1:])
            state = new.replace(
                x=np.where(keep, new.x, state.x),
                P=P_new if observer == "sstkf" else np.where(keep[:, :, None], P_new, P_old),
            )
        out["estimate"][:, k - 1], out["pred"][:, k - 1] = state.mean, np.where(keep, xbar, state.mean)
        out["cov"][:, k - 1] = state.cov
        out["u"][:, k - 1] = np.where(keep, uk, 0.0)
        out["y"][:, k - 1], out["ylat"][:, k - 1] = yk, ylat
        out["lower"][:, k - 1], out["upper"][:, k - 1], out["gamma"][:, k - 1] = lo, hi, gam
    out["x"], out["reference"], out["dstep"] = x, r, diverged_step
    return _result(out)


def _outputs(runs: int, steps: int, n: int, p: int, m: int) -> dict[str, np.ndarray]:
    """The per-step output arrays (N, T, ...) of both loops, by the numpy loop's names."""
    shapes = {"estimate": (n,), "pred": (n,), "cov": (n, n), "u": (p,), "y": (m,), "ylat": (m,)}
    shapes.update({"lower": (m,), "upper": (m,), "gamma": (m,)})
    return {name: np.empty((runs, steps) + shape) for name, shape in shapes.items()}


def _result(out: dict[str, np.ndarray]) -> ClosedLoopResult:
    return ClosedLoopResult(
        x=out["x"],
        estimate=out["estimate"],
        pred_estimate=out["pred"],
        cov=out["cov"],
        u=out["u"],
        y=out["y"],
        y_latent=out["ylat"],
        lower=out["lower"],
        upper=out["upper"],
        p_uncensored=out["gamma"],
        reference=out["reference"],
        diverged=out["dstep"] >= 0,
        diverged_step=out["dstep"],
    )


def _compiled_loop(plant, obs, observer, state, x, w, v, K, Nbar, r, cens, sigma, noise_term, bound, shift, side):
    """The loop of :func:`simulate_closed_loop` by :func:`tobitkf.control._compiled_closed.compiled_closed_loop`
    (same noises, same observer matrices, read from the observer's public attributes); fills ``x`` (N, T+1, n)
    from its row 0 and returns the other outputs by the numpy loop's names."""
    from ..filters._compiled_tobit import NOISE_CODES
    from . import _compiled_closed as kc

    runs, steps, n = w.shape
    m, p = plant.m, Nbar.shape[0]

    def f64(a, dtype=float):  # C-contiguous and writable: numba types read-only arrays apart, one compile more each
        return np.require(a, dtype, ("C", "W"))

    A, C, Bu = (f64(mat, dtype=float) for mat in (plant.transition(0), plant.measurement(1), plant.Bu.at(1)))
    D = np.zeros((0, p)) if plant.D is None else f64(plant.D.at(1), dtype=float)
    steady = observer == "sstkf"
    if steady:
        Kss, Pss = f64(obs.gain, dtype=float), f64(obs.cov, dtype=float)
        offset = f64(obs.expected_measurement(np.zeros(m)), dtype=float)  # E[y] - C xbar - D u of (3.58)
        xi = f64(obs.xi_uncensored, dtype=float)
        P0 = np.zeros((runs, n, n))
    else:
        Kss, Pss, offset, xi = np.zeros((n, m)), np.zeros((n, n)), np.zeros(m), np.zeros(m)
        P0 = f64(np.broadcast_to(state.P, (runs, n, n)), dtype=float)
    shift = np.zeros(m) if shift is None else shift
    lo, hi = cens.all_limits(steps, m, check=False)
    out = _outputs(runs, steps, n, p, m)
    dstep = np.empty(runs, dtype=np.int64)
    kc.compiled_closed_loop(
        kc.OBSERVER_CODES[observer],
        A,
        Bu,
        C,
        D,
        f64(plant.process_cov(0), dtype=float),
        f64(sigma, dtype=float),
        f64(K, dtype=float),
        f64(Nbar, dtype=float),
        f64(r, dtype=float),
        lo,
        hi,
        f64(shift, dtype=float),
        side == "upper",
        Kss,
        offset,
        Pss,
        xi,
        f64(w, dtype=float),
        f64(v, dtype=float),
        f64(state.x, dtype=float),
        P0,
        NOISE_CODES[noise_term],
        float(bound),
        x,
        out["estimate"],
        out["pred"],
        out["cov"],
        out["u"],
        out["y"],
        out["ylat"],
        out["lower"],
        out["upper"],
        out["gamma"],
        dstep,
    )
    out["dstep"] = dstep
    return out


def quadratic_cost(
    result: ClosedLoopResult, Q: Any, R: Any, x_ref: Any = None, u_ref: Any = None, *, skip: int = 0
) -> np.ndarray:
    r"""Average LQ cost per run, :math:`\frac1{T'}\sum_k (x_k - x_{ref})^TQ(x_k - x_{ref}) + (u_k - u_{ref})^TR(u_k - u_{ref})`.

    ``x_ref`` (n,) / (T, n) and ``u_ref`` (p,) / (T, p) default to 0; ``skip`` drops the first steps.
    Returns ``(N,)``; diverged runs give ``inf``.
    """
    Q = np.atleast_2d(as_float_array(Q, "Q"))
    R = np.atleast_2d(as_float_array(R, "R"))
    n, p = result.x.shape[-1], result.u.shape[-1]
    if Q.shape != (n, n) or R.shape != (p, p):
        raise ShapeError(f"Q, R: expected ({n}, {n}) and ({p}, {p}), got {Q.shape} and {R.shape}")
    dx = result.x[:, 1:] - (0.0 if x_ref is None else np.asarray(x_ref, dtype=float))
    du = result.u - (0.0 if u_ref is None else np.asarray(u_ref, dtype=float))
    c = np.einsum("ntj,jk,ntk->nt", dx, Q, dx) + np.einsum("ntj,jk,ntk->nt", du, R, du)
    cost = c[:, skip:].mean(axis=1)
    return np.where(result.diverged, np.inf, cost)
