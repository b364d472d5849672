r"""Batched Monte Carlo simulation of truth and measurements.

Draws ``runs`` independent realisations of a :class:`~tobitkf.LinearSystem`
at once (Miller (3.18)):

.. math::

    x_0 \sim N(\bar x_0, P_0), \quad x_k = A_{k-1}x_{k-1} + B^u u_k + B_{k-1} w_{k-1}, \quad
    y^*_k = C_k x_k + D u_k + v_k, \quad y_k = \mathrm{clip}(y^*_k, l_k, h_k)

Array layout (DESIGN.md): ``x`` is ``(N, T+1, n)`` holding x_0..x_T; ``y`` and
``y_latent`` are ``(N, T, m)`` holding y_1..y_T. All randomness comes from one
``numpy.random.Generator`` built from ``seed``, drawn in a fixed order (x_0, w, v,
then the measurement model's own draws), so the same seed gives the same numbers.

A measurement model other than ``C x + D u + v`` (Rice fading, integral
measurements, ...) is passed as ``measurement``: any object with a method
``draw(rng, x, system, noise, inputs) -> (y_latent, extras)`` where ``x`` is
``(N, T+1, n)``, ``noise`` is the ``(N, T, m)`` draw of :math:`v_k` and ``extras``
a dict of the model's own random variables (kept in ``SimulationData.extras``).
Pieces that act after censoring (packet loss, scheduling) are passed as
``post``: objects with ``apply(rng, y, extras) -> y``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._linalg import eigh_sqrt as psd_sqrt
from .._progress import plural
from .._validation import (
    ShapeError,
    ValidationError,
    as_float_array,
    as_generator,
    check_count,
    check_instance,
    check_memory,
)
from ..channels.base import Channel
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ..models.nonlinear import NonlinearSystem

__all__ = ["SimulationData", "simulate", "as_generator", "psd_sqrt"]


@dataclass(frozen=True)
class SimulationData:
    """Truth and measurements of a batch of runs.

    Attributes
    ----------
    x : (N, T+1, n) ndarray
        True states x_0..x_T.
    y : (N, T, m) ndarray
        Measurements y_1..y_T as the estimator receives them (censored).
    y_latent : (N, T, m) ndarray
        Latent (uncensored) measurements y*_1..y*_T.
    u : (N, T, p) ndarray or None
        Control inputs u_1..u_T, if any.
    extras : dict
        Random variables drawn by channel pieces (fading coefficients, failure gains...).
    """

    x: np.ndarray
    y: np.ndarray
    y_latent: np.ndarray
    u: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def runs(self) -> int:
        return self.x.shape[0]

    @property
    def steps(self) -> int:
        return self.y.shape[1]


def simulate(
    system: LinearSystem | NonlinearSystem,
    steps: int,
    runs: int = 1,
    *,
    channel: Channel | Sequence[Channel] | None = None,
    censoring: Censoring | None = None,
    measurement: Any = None,
    post: Sequence[Any] = (),
    inputs: Any = None,
    seed: Any = 0,
) -> SimulationData:
    r"""Draw truth and censored measurements for many runs at once.

    Parameters
    ----------
    system : LinearSystem or NonlinearSystem
        The model (a :class:`~tobitkf.NonlinearSystem` draws :math:`x_k = f(x_{k-1}, k-1) + w_{k-1}`,
        :math:`y^*_k = h(x_k, k) + v_k`, with an input :math:`f(x_{k-1}, k-1, u_k)` and :math:`h(x_k, k, u_k)`;
        no channel piece may draw its reading from ``C``; a :class:`~tobitkf.RiceFading` of order 0 draws
        :math:`\vartheta_k h(x_k, k) + v_k`, a :class:`~tobitkf.RandomSaturation` its three modes at
        :math:`h(x_k, k)`).
    steps : int
        Horizon T (number of measurements).
    runs : int, default 1
        Number of independent Monte Carlo runs N.
    channel : Channel or sequence of Channel, optional
        The channel pieces between sensor and estimator (:class:`~tobitkf.channels.base.Channel`:
        :class:`~tobitkf.Censoring`, :class:`~tobitkf.RiceFading`, :class:`~tobitkf.ProtocolChannel`,
        :class:`~tobitkf.RandomSaturation`), applied stage by stage: the one piece that draws the
        reading (at most one), then every piece's censoring, then every piece's post-censoring step,
        each in the order given. ``censoring``, ``measurement`` and ``post`` below are the same
        stages named one by one; they run before the ``channel`` pieces of the same stage.
    censoring : Censoring, optional
        Limits applied to the latent measurements; default: none.
    measurement : object, optional
        Measurement model replacing ``C x + D u + v`` (see module docstring).
    post : sequence of objects, optional
        Channel pieces applied after censoring (see module docstring).
    inputs : (T, p) or (N, T, p) array_like, optional
        Control inputs u_1..u_T (index k-1 holds u_k).
    seed : int, SeedSequence or Generator, default 0
        Source of all randomness.

    Returns
    -------
    SimulationData
        ``x`` (N, T+1, n), ``y`` and ``y_latent`` (N, T, m).

    Raises
    ------
    ValidationError
        If ``steps`` or ``runs`` is not a positive integer or ``seed`` is invalid.
    ShapeError
        If inputs or time-varying matrices do not cover the horizon.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-14]], R=[[0.01]], x0=[-0.1], P0=[[0.0]])
    >>> data = tk.simulate(sys, steps=5, runs=3, censoring=tk.Censoring(lower=0.0), seed=1)
    >>> data.x.shape, data.y.shape, bool((data.y >= 0).all())
    ((3, 6, 1), (3, 5, 1), True)
    """
    nonlinear = isinstance(system, NonlinearSystem)
    if not nonlinear:
        check_instance(system, LinearSystem, "system")
    steps = check_count(steps, "steps")
    runs = check_count(runs, "runs")
    # refused before anything is allocated (or a callable evaluated over a huge horizon)
    check_memory(
        8 * runs * (steps + 1) * (2 * system.n + system.q + 3 * system.m + (system.p or 0)),
        "runs/steps",
        f"{plural(runs, 'run')} x {plural(steps, 'step')} (n = {system.n}, m = {system.m}: states, noises, readings)",
    )
    system.check_horizon(steps)  # also validates callables over the horizon
    if censoring is not None:
        check_instance(censoring, Censoring, "censoring")
        censoring.check(system.m, steps)
    if measurement is not None and not callable(getattr(measurement, "draw", None)):
        raise ValidationError(
            f"measurement: expected an object with a draw(rng, x, system, noise, inputs) method, "
            f"got {type(measurement).__name__}"
        )
    if isinstance(post, (str, bytes)) or not hasattr(post, "__iter__"):
        raise ValidationError(f"post: expected a sequence of channel pieces, got {type(post).__name__}")
    post = tuple(post)
    for i, piece in enumerate(post):
        if not callable(getattr(piece, "apply", None)):
            raise ValidationError(
                f"post[{i}]: expected an object with an apply(rng, y, extras) method, got {type(piece).__name__}"
            )
    pieces = () if channel is None else (tuple(channel) if isinstance(channel, (list, tuple)) else (channel,))
    for i, piece in enumerate(pieces):
        check_instance(piece, Channel, f"channel[{i}]" if len(pieces) > 1 else "channel")
        piece.check(system, steps)
    drawers = [p for p in pieces if p.measures]
    if len(drawers) + (measurement is not None) > 1:
        raise ValidationError(
            "channel: at most one piece may draw the reading (measurement=, or one channel "
            f"with a draw stage), got {len(drawers) + (measurement is not None)}"
        )
    if drawers:
        measurement = drawers[0]
    if nonlinear and measurement is not None and not getattr(measurement, "draws_nonlinear", False):
        raise ValidationError(
            "channel: a NonlinearSystem's reading is h(x, k) + v; a piece that draws its own reading from C "
            f"({type(measurement).__name__}) does not apply"
        )
    u = system.check_inputs(inputs, steps, "inputs")
    if u is not None:
        assert system.p is not None, "check_inputs returns inputs only for a system with an input matrix"
        u = np.broadcast_to(u, (runs, steps, system.p)) if u.ndim == 2 else u
        if u.shape[0] != runs:
            raise ShapeError(f"inputs: expected (T, p) or ({runs}, T, p), got {u.shape}")
    rng = as_generator(seed)
    n, m, q = system.n, system.m, system.q

    x = np.empty((runs, steps + 1, n))
    x[:, 0] = system.x0 + rng.standard_normal((runs, n)) @ psd_sqrt(system.P0).T
    w = rng.standard_normal((runs, steps, q))
    v = rng.standard_normal((runs, steps, m))

    const_noise = not (system.Q.varying or (system.B is not None and system.B.varying))
    if const_noise:
        G = psd_sqrt(system.Q.at(0))
        if system.B is not None:
            G = system.B.at(0) @ G
        w = w @ G.T
    if not system.R.varying:
        v = v @ psd_sqrt(system.R.at(1)).T
    for k in range(1, steps + 1):
        noise = w[:, k - 1]
        if not const_noise:
            G = psd_sqrt(system.Q.at(k - 1))
            if system.B is not None:
                G = system.B.at(k - 1) @ G
            noise = noise @ G.T
        if isinstance(system, NonlinearSystem):
            x[:, k] = system.transition_map(x[:, k - 1], k - 1, None if u is None else u[:, k - 1]) + noise
        else:
            x[:, k] = x[:, k - 1] @ system.transition(k - 1).T + noise
        if u is not None and system.Bu is not None:
            x[:, k] += u[:, k - 1] @ system.Bu.at(k).T
        if system.R.varying:
            v[:, k - 1] = v[:, k - 1] @ psd_sqrt(system.R.at(k)).T

    extras: dict[str, Any] = {}
    if measurement is None:
        if isinstance(system, NonlinearSystem):
            # an h(x, k, u) reads the input u_k of its own step (row k - 1)
            uk = [None if u is None else u[:, k - 1] for k in range(1, steps + 1)]
            y_latent = np.stack([system.measurement_map(x[:, k], k, uk[k - 1]) for k in range(1, steps + 1)], 1) + v
        elif system.C.varying:
            y_latent = np.stack([x[:, k] @ system.measurement(k).T for k in range(1, steps + 1)], axis=1) + v
        else:
            y_latent = x[:, 1:] @ system.measurement(1).T + v
        if u is not None and system.D is not None:
            y_latent += np.stack([u[:, k - 1] @ system.D.at(k).T for k in range(1, steps + 1)], axis=1)
    else:
        drawn = measurement.draw(rng, x, system, v, u)
        hook = "channel" if drawers else "measurement"
        if not (isinstance(drawn, tuple) and len(drawn) == 2):
            raise ValidationError(f"{hook}: draw() must return (y_latent, extras), got {type(drawn).__name__}")
        y_latent = _hook_output(drawn[0], f"{hook}: draw()", (runs, steps, m), exact=True)
        try:
            extras = dict(drawn[1])
        except (TypeError, ValueError):
            raise ValidationError(
                f"{hook}: draw() must return a dict of extras, got {type(drawn[1]).__name__}"
            ) from None
    y = y_latent if censoring is None else censoring.clip(y_latent)
    for i, piece in enumerate(pieces):
        y = _hook_output(piece.censor(y), f"{_label(pieces, i)}: censor()", (runs, steps, m))
    for i, piece in enumerate(post):
        y = _hook_output(piece.apply(rng, y, extras), f"post[{i}]: apply()", (runs, steps, m))
    for i, piece in enumerate(pieces):
        y = _hook_output(piece.apply(rng, y, extras), f"{_label(pieces, i)}: apply()", (runs, steps, m))
    return SimulationData(x=x, y=y, y_latent=y_latent, u=u, extras=extras)


def _label(pieces: tuple, i: int) -> str:
    return f"channel[{i}]" if len(pieces) > 1 else "channel"


def _hook_output(value: Any, name: str, shape: tuple[int, ...], *, exact: bool = False) -> np.ndarray:
    """What a channel piece or hook returned: real numbers (NaN = a missing reading) of shape
    ``(runs, steps, channels)``; the channel count may change after the reading is drawn (a
    scheduler forwards one sensor), unless ``exact``."""
    arr = as_float_array(value, name, allow_nan=True)
    if arr.ndim != 3 or arr.shape[:2] != shape[:2] or arr.shape[2] < 1 or (exact and arr.shape != shape):
        want = str(shape) if exact else f"({shape[0]}, {shape[1]}, channels)"
        raise ShapeError(f"{name} returned shape {arr.shape}, expected {want} (runs, steps, channels)")
    return arr
