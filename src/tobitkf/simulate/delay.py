r"""Simulator of the pure-delay system with fading measurements (Li, Li & Wang 2018, (1)–(3)).

The model and its time convention are documented in :mod:`tobitkf.models.delay`: y(0) is the
first measurement and measures x(-d); ``SimulationData.x[:, t]`` holds x(t) for t = 0..T and the
history x(-d)..x(-1) is in ``extras["history"]`` (oldest first).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._linalg import eigh_sqrt as psd_sqrt
from .._progress import plural
from .._validation import as_generator, check_count, check_instance, check_memory
from ..models.delay import DelayFadingSystem, HistoryPrior
from .core import SimulationData

__all__ = ["simulate_delay", "full_states"]


def simulate_delay(
    system: DelayFadingSystem, prior: HistoryPrior, steps: int, runs: int = 1, *, seed: Any = 0
) -> SimulationData:
    r"""Draw truth and fading measurements of the delay system for many runs at once.

    The initial history X(0) = [x(0); ...; x(-d)] is Gaussian with the joint prior. For
    t = 0..T-1 (docs/sources LD-03, LD-09): :math:`\gamma(t)` i.i.d. from the fading law,
    :math:`\zeta_i(t) \sim N(0, Q_{\zeta_i}(t))`, :math:`v(t) \sim N(0, Q_v)` and
    :math:`w(t) = S Q_v^{-1} v(t) + \eta(t)`, :math:`\eta(t) \sim N(0, Q_w - S Q_v^{-1} S^T)`
    independent of v, so that Cov(w, v) = S and Var w = Q_w even at the singular
    S = sqrt(Q_w Q_v). Then x(t+1) by (1) and y(t) by (2).

    Parameters
    ----------
    system : DelayFadingSystem
    prior : HistoryPrior
        Law of the true initial history (d+1 lags).
    steps : int
        Number of measurements T (y(0)..y(T-1)).
    runs : int, default 1
    seed : int, SeedSequence or Generator, default 0

    Returns
    -------
    SimulationData
        ``x`` (N, T+1, n) holds x(0)..x(T); ``y`` = ``y_latent`` (N, T, m) holds y(0)..y(T-1);
        ``extras``: ``history`` (N, d, n) x(-d)..x(-1), ``gamma`` (N, T), ``zeta`` (N, T, h),
        ``w`` (N, T, p), ``v`` (N, T, m).

    Raises
    ------
    ValidationError
        Bad ``steps``/``runs``/``seed`` or a prior of the wrong length (argument ``prior``).
    """
    check_instance(system, DelayFadingSystem, "system")
    prior = system.check_prior(prior)
    T = check_count(steps, "steps")
    N = check_count(runs, "runs")
    n, m, p, h, d = system.n, system.m, system.p, system.h, system.d
    check_memory(
        8 * N * (T + d + 1) * (2 * n + 2 * m + p + h + 1),
        "runs/steps",
        f"{plural(N, 'run')} x {plural(T, 'step')} (n = {n}, m = {m}, d = {d}: states, noises, readings)",
    )
    rng = as_generator(seed)
    full = np.empty((N, T + d + 1, n))  # index j + d holds x(j), j = -d..T
    X0 = prior.mean.reshape(-1) + rng.standard_normal((N, n * (d + 1))) @ psd_sqrt(prior.cov).T
    for k in range(d + 1):
        full[:, d - k] = X0[:, k * n : (k + 1) * n]
    v = rng.standard_normal((N, T, m)) @ psd_sqrt(system.Qv).T
    eta = rng.standard_normal((N, T, p)) @ psd_sqrt(system.eta_cov).T
    w = v @ system.S_Qv_inv.T + eta
    zeta = rng.standard_normal((N, T, h))
    gamma = np.empty((N, T))
    y = np.empty((N, T, m))
    for t in range(T):
        gamma[:, t] = system.fading.sample_at(rng, t, (N,))
        zeta[:, t] *= np.sqrt(system.q_mult(t))
        xd = full[:, t]  # x(t-d) at index t-d+d
        y[:, t] = gamma[:, t, None] * (xd @ system.H.T) + v[:, t]
        nxt = w[:, t] @ system.Gamma.T
        for lag, mat in system.lags.items():
            nxt = nxt + full[:, t + d - lag] @ mat.T
        if h:
            Am = np.einsum("ri,ijk->rjk", zeta[:, t], system.A_mult)
            nxt = nxt + np.einsum("rjk,rk->rj", Am, xd)
        full[:, t + d + 1] = nxt
    extras = {"history": full[:, :d].copy(), "gamma": gamma, "zeta": zeta, "w": w, "v": v}
    return SimulationData(x=full[:, d:].copy(), y=y, y_latent=y, extras=extras)


def full_states(data: SimulationData) -> np.ndarray:
    """x(-d)..x(T) as one (N, T+d+1, n) array from :func:`simulate_delay` output."""
    return np.concatenate([data.extras["history"], data.x], axis=1)
