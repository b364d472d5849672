r"""Simulator of the plant (1) with ROSS sensors (2) of the regional H∞ problem (Wang, Shen & Liu).

The disturbances are deterministic l_2 sequences (as in the paper); the randomness is the 2m
Bernoulli variables per step. Model: :mod:`tobitkf.models.ross`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import ShapeError, ValidationError, as_float_array, as_generator, check_instance, check_memory
from ..models.ross import RossModel

__all__ = ["RossSimulation", "simulate_ross", "wang2010_disturbances"]


@dataclass(frozen=True)
class RossSimulation:
    """Truth and measurements of a batch of runs of (1)–(2).

    Attributes
    ----------
    x : (N, T+1, n) ndarray
        States x_0..x_T.
    y : (N, T, m) ndarray
        Measurements ỹ_0..ỹ_{T-1} (ỹ_k from x_k; the filter (5) uses ỹ_k to form x̂_{k+1}).
    z : (N, T+1, r) ndarray
        z_k = M x_k.
    alpha, beta : (N, T, m) ndarray
        The Bernoulli draws α_k^i, β_k^i (0/1).
    w : (N, T, p) ndarray
        Process disturbance w_0..w_{T-1}.
    v : (N, T, m) ndarray
        Measurement noise ṽ_0..ṽ_{T-1} (before D_v).
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    w: np.ndarray
    v: np.ndarray

    @property
    def disturbance_energy(self) -> np.ndarray:
        """Σ_k ‖w̄_k‖² per run, (N,)."""
        return (self.w**2).sum(axis=(1, 2)) + (self.v**2).sum(axis=(1, 2))


def _sequence(value: Any, name: str, runs: int, steps: int, dim: int) -> np.ndarray:
    if callable(value):
        rows = [as_float_array(value(k), f"{name}({k})") for k in range(steps)]
        for k, row in enumerate(rows):
            if row.size != dim:
                raise ShapeError(f"{name}({k}): expected {dim} value(s), got shape {row.shape}")
        arr = np.array([row.reshape(dim) for row in rows])
    else:
        arr = as_float_array(value, name, ndim=(2, 3))
    if arr.shape[-2:] != (steps, dim) or (arr.ndim == 3 and arr.shape[0] != runs):
        raise ShapeError(f"{name}: expected ({steps}, {dim}) or ({runs}, {steps}, {dim}), got {arr.shape}")
    return np.broadcast_to(arr, (runs, steps, dim)).copy()


def simulate_ross(
    model: RossModel, steps: int, runs: int = 1, *, x0: Any = None, w: Any = None, v: Any = None, seed: Any = None
) -> RossSimulation:
    r"""Simulate the plant (1) and the ROSS sensors (2) for many runs at once.

    The disturbances are deterministic l_2 sequences (as in the paper); the randomness is
    the 2m Bernoulli variables per step, drawn independently from ``seed`` (α then β at
    each step, docs/sources WH-05).

    Parameters
    ----------
    model : RossModel
        Must carry ``f``.
    steps : int
        T, number of transitions.
    runs : int
        N.
    x0 : (n,) or (N, n) array_like, optional
        Initial state (zeros by default).
    w : (T, p), (N, T, p) array_like or callable k -> (p,), optional
        Process disturbance w_0..w_{T-1} (zeros by default).
    v : (T, m), (N, T, m) array_like or callable k -> (m,), optional
        Measurement noise ṽ_0..ṽ_{T-1} (zeros by default).
    seed : int, SeedSequence or Generator
        Required (an explicit seed, as in :func:`tobitkf.simulate`).

    Returns
    -------
    RossSimulation

    Raises
    ------
    ValidationError, ShapeError
    """
    check_instance(model, RossModel, "model")
    if model.f is None:
        raise ValidationError("model.f: expected the plant nonlinearity to simulate, got None")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValidationError(f"steps: expected a positive integer, got {steps!r}")
    if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or runs < 1:
        raise ValidationError(f"runs: expected a positive integer, got {runs!r}")
    n, m, p = model.n, model.m, model.p
    check_memory(
        8 * runs * (steps + 1) * (2 * n + 5 * m + p),
        "runs/steps",
        f"{plural(runs, 'run')} x {plural(steps, 'step')} (n = {n}, m = {m}: states, readings, disturbances, modes)",
    )
    x0a = np.zeros(n) if x0 is None else as_float_array(x0, "x0", ndim=(1, 2))
    if x0a.shape[-1] != n or (x0a.ndim == 2 and x0a.shape[0] != runs):
        raise ShapeError(f"x0: expected ({n},) or ({runs}, {n}), got {x0a.shape}")
    ws = np.zeros((runs, steps, p)) if w is None else _sequence(w, "w", runs, steps, p)
    vs = np.zeros((runs, steps, m)) if v is None else _sequence(v, "v", runs, steps, m)
    rng = as_generator(seed)
    x = np.empty((runs, steps + 1, n))
    y = np.empty((runs, steps, m))
    alpha = np.empty((runs, steps, m))
    beta = np.empty((runs, steps, m))
    x[:, 0] = x0a
    ch = model.channel
    for k in range(steps):
        a, b = ch.draw_modes(rng, (runs,))
        alpha[:, k], beta[:, k] = a, b
        y[:, k] = ch.measure(x[:, k] @ model.C.T, a, b, vs[:, k] * model.D)  # (2)
        x[:, k + 1] = model.f(x[:, k]) + ws[:, k] @ model.B.T  # (1)
    return RossSimulation(x=x, y=y, z=x @ model.M.T, alpha=alpha, beta=beta, w=ws, v=vs)


def wang2010_disturbances(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """w_k = 8 sin(0.5k)/(k+1), v_k^1 = v_k^2 = 2 cos(0.3k)/(5(k+1)) for k = 0..steps-1 (Section 4)."""
    k = np.arange(steps, dtype=float)
    w = (8 * np.sin(0.5 * k) / (k + 1))[:, None]
    v1 = 2 * np.cos(0.3 * k) / (5 * (k + 1))
    return w, np.stack([v1, v1], axis=-1)
