r"""Nonlinear Gaussian state-space models with additive noise.

The model, with the package-wide time convention (:mod:`tobitkf.models.linear`):

.. math::

    x_k &= f(x_{k-1}, k-1) + w_{k-1}, \qquad w_{k-1} \sim N(0, Q_{k-1}) \\
    y^*_k &= h(x_k, k) + v_k, \qquad v_k \sim N(0, R_k), \qquad x_0 \sim N(\bar x_0, P_0)

for :math:`k = 1, \dots, T`; :math:`x_0` is the prior and :math:`y_1` sits at array index 0. What reaches
the estimator is :math:`y^*_k` passed through a channel (censoring, a quantizer, lost readings) exactly as
for a :class:`~tobitkf.LinearSystem`.

``f`` and ``h`` are batched over leading axes: ``f(x, k)`` maps ``(..., n)`` to ``(..., n)`` and ``h(x, k)``
``(..., n)`` to ``(..., m)``, with ``k`` a Python int. ``Q`` and ``R`` are constant, given per step or
callables of k, as for :class:`~tobitkf.LinearSystem` (``Q[k]`` / ``Q(k)`` for k = 0..T-1, ``R[k-1]`` /
``R(k)`` for k = 1..T).

**Known inputs.** A transition ``f(x, k, u)`` takes a known input :math:`u_k` (p,), with the linear model's
convention: :math:`u_k` acts over the interval (k-1, k] and is stored at index k-1 like :math:`y_k`,

.. math:: x_k = f(x_{k-1}, k-1, u_k) + w_{k-1},

``u`` batched like ``x`` ((..., p), one row per state). The output map may take the same input,
``h(x, k, u)`` (a feedthrough :math:`Du_k`, or an output that depends on the input), with :math:`u_k` of the same
step as the reading:

.. math:: y^*_k = h(x_k, k, u_k) + v_k,

as the linear model's :math:`y^*_k = C_kx_k + D_ku_k + v_k`. Whether ``f`` or ``h`` takes an input is read from
its signature (a third positional parameter without a default) or, with ``inputs=p`` given, from a third
positional parameter with a default too (an ``f`` whose signature cannot be read takes it, an ``h`` does not);
its length p is always given as ``inputs=p``. The filters, smoothers and :func:`~tobitkf.simulate` then take
``u`` (``inputs`` for the simulator) of shape (..., T, p); no input given means :math:`u_k = 0`.
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

import numpy as np

from .._validation import (
    ShapeError,
    TimeSequence,
    ValidationError,
    as_float_array,
    check_count,
    check_int,
    check_psd,
)

__all__ = ["NonlinearSystem", "augment_parameters", "discretize", "jacobian_fd"]

_EPS = np.finfo(np.float64).eps


def jacobian_fd(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray) -> np.ndarray:
    r"""Central-difference Jacobian of a batched ``fun`` ((N, n) -> (N, r)) at ``x`` (N, n): (N, r, n).

    Column j is :math:`(g(x + \delta_je_j) - g(x - \delta_je_j)) / (2\delta_j)` with the usual step for a
    central difference, :math:`\delta_j = \epsilon^{1/3}\max(1, |x_j|)` (:math:`\epsilon` the machine
    epsilon; the step that balances the :math:`O(\delta^2)` truncation error against the
    :math:`O(\epsilon/\delta)` rounding error), so the error is about :math:`\epsilon^{2/3} \approx 4\cdot10^{-11}`
    relative for a function whose third derivative is of the order of the function. All 2n shifted points
    are evaluated in one call of ``fun``.
    """
    N, n = x.shape
    delta = np.cbrt(_EPS) * np.maximum(1.0, np.abs(x))  # (N, n)
    shifts = np.zeros((2, n, N, n))
    idx = np.arange(n)
    shifts[0, idx, :, idx] = delta.T
    shifts[1, idx, :, idx] = -delta.T
    pts = (x[None, None] + shifts).reshape(2 * n * N, n)
    vals = np.asarray(fun(pts), dtype=float)
    r = vals.shape[-1]
    vals = vals.reshape(2, n, N, r)
    diff = (vals[0] - vals[1]) / (2.0 * delta.T[:, :, None])  # (n, N, r)
    return np.ascontiguousarray(np.transpose(diff, (1, 2, 0)))


def discretize(fc: Callable[..., np.ndarray], dt: float, substeps: int = 1):
    r"""The transition map of an ODE :math:`\dot x = f_c(x, t)` over one sampling interval, by fixed-step RK4.

    Returns ``f(x, k)``: ``substeps`` classical fourth-order Runge-Kutta steps of size
    :math:`h = dt/\text{substeps}` from :math:`t = k\,dt` to :math:`(k+1)\,dt`. ``fc(x, t)`` must be batched
    over the leading axes of ``x`` (..., n), as ``f`` is. The local error per interval is :math:`O(h^5)` per
    substep, the global error of the map :math:`O(h^4)`. When ``fc`` takes an input, ``fc(x, t, u)`` (a
    third positional parameter without a default), the map is ``f(x, k, u)`` with ``u`` held constant over
    the interval (zero-order hold); give the system ``inputs=p``.

    Parameters
    ----------
    fc : callable ``fc(x, t) -> dx/dt`` or ``fc(x, t, u)``
    dt : float > 0
        Sampling interval.
    substeps : int >= 1, default 1

    Raises
    ------
    ValidationError
        ``fc`` not callable, ``dt`` not a positive finite number, ``substeps`` not a positive integer.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> f = tk.discretize(lambda x, t: -x, dt=0.1, substeps=4)
    >>> bool(abs(f(np.array([1.0]), 0)[0] - np.exp(-0.1)) < 1e-9)
    True
    """
    if not callable(fc):
        raise ValidationError(f"fc: expected a callable fc(x, t), got {type(fc).__name__}")
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise ValidationError(f"dt: expected a positive number, got {dt!r}") from None
    if not (np.isfinite(dt) and dt > 0):
        raise ValidationError(f"dt: expected a positive finite number, got {dt!r}")
    substeps = check_count(substeps, "substeps")
    h = dt / substeps

    def integrate(x: np.ndarray, k: int, rate: Callable[..., np.ndarray]) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        t = k * dt
        for _ in range(substeps):
            k1 = rate(x, t)
            k2 = rate(x + 0.5 * h * k1, t + 0.5 * h)
            k3 = rate(x + 0.5 * h * k2, t + 0.5 * h)
            k4 = rate(x + h * k3, t + h)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            t += h
        return x

    if _takes_input(fc) is True:

        def f_u(x: np.ndarray, k: int, u: np.ndarray) -> np.ndarray:
            return integrate(x, k, lambda z, t: fc(z, t, u))

        return f_u

    def f(x: np.ndarray, k: int) -> np.ndarray:
        return integrate(x, k, fc)

    return f


def _takes_input(fn: Any, *, optional: bool = False, position: int = 2) -> bool | None:
    """Whether ``fn(x, k, u)`` takes an input by its signature: a third positional parameter (``position``: its
    index; 3 for an ``f(x, k, theta, u)``) without a default (or, with ``optional``, with one). True, False, or
    None when the signature cannot be read (a compiled or built-in function) or takes ``*args``."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_POSITIONAL for p in sig.parameters.values()):
        return None
    positional = [
        p
        for p in sig.parameters.values()
        if p.kind in (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    ]
    return len(positional) > position and (optional or positional[position].default is inspect.Parameter.empty)


class NonlinearSystem:
    r"""A nonlinear state-space model with additive Gaussian noise (module docstring).

    Parameters
    ----------
    f : callable ``f(x, k) -> (..., n)``
        Transition, batched over the leading axes of ``x`` (..., n); :math:`x_k = f(x_{k-1}, k-1) + w_{k-1}`.
    h : callable ``h(x, k) -> (..., m)`` or ``h(x, k, u)``
        Measurement function, batched likewise; :math:`y^*_k = h(x_k, k) + v_k` (or :math:`h(x_k, k, u_k) + v_k`
        with a known input, module docstring).
    Q : (n, n) or (T, n, n) array_like or callable
        Process-noise covariance :math:`Q_k` (symmetric PSD).
    R : (m, m) or (T, m, m) array_like or callable
        Measurement-noise covariance :math:`R_k` (symmetric PSD).
    x0 : (n,) array_like
        Prior mean. P0 : (n, n) array_like, prior covariance (symmetric PSD).
    F : callable ``F(x, k) -> (..., n, n)``, optional
        Jacobian :math:`\partial f/\partial x`. Default: central differences (:func:`jacobian_fd`, step
        :math:`\epsilon^{1/3}\max(1, |x_j|)`, error about :math:`10^{-10}` relative for a smooth ``f``).
    H : callable ``H(x, k) -> (..., m, n)``, optional
        Jacobian :math:`\partial h/\partial x`; default central differences as for ``F``.
    inputs : int >= 1, optional
        The length p of a known input :math:`u_k` of ``f(x, k, u)`` and/or ``h(x, k, u)`` (module docstring);
        required when either takes one (read from its signature, or declared by giving ``inputs``). ``F`` (``H``)
        then takes ``u`` too when ``f`` (``h``) does.

    Raises
    ------
    ValidationError
        ``f``, ``h`` (or ``F``, ``H``) not callable, a non-finite value of f or h at the prior mean, a
        covariance that is not symmetric PSD, an ``f(x, k, u)`` or ``h(x, k, u)`` without ``inputs``, ``inputs``
        when neither ``f`` nor ``h`` takes an input, or not a positive integer.
    ShapeError
        ``f(x0, 0)`` not of shape (n,), ``f`` or ``h`` not batched ((1, n) in, (1, ...) out), ``Q`` not (n, n),
        ``R`` not (m, m) with m the length of ``h(x0, 1)``, a Jacobian of the wrong shape.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.NonlinearSystem(lambda x, k: np.sin(x), lambda x, k: x**2, Q=[[0.1]], R=[[0.01]],
    ...                          x0=[0.5], P0=[[1.0]])
    >>> sys.n, sys.m
    (1, 1)
    """

    def __init__(
        self,
        f: Any,
        h: Any,
        Q: Any,
        R: Any,
        x0: Any,
        P0: Any,
        *,
        F: Any = None,
        H: Any = None,
        inputs: int | None = None,
    ):
        for name, fn in (("f", f), ("h", h)):
            if not callable(fn):
                raise ValidationError(f"{name}: expected a callable {name}(x, k), got {type(fn).__name__}")
        for name, fn in (("F", F), ("H", H)):
            if fn is not None and not callable(fn):
                raise ValidationError(f"{name}: expected a callable {name}(x, k) or None, got {type(fn).__name__}")
        self.x0 = as_float_array(x0, "x0", ndim=1)
        n = self.x0.shape[0]
        self.P0 = as_float_array(P0, "P0", ndim=2)
        if self.P0.shape != (n, n):
            raise ShapeError(f"P0: expected shape ({n}, {n}) to match x0, got {self.P0.shape}")
        check_psd(self.P0, "P0")
        self.f, self.h, self.F, self.H = f, h, F, H
        if inputs is None:
            for name, fn in (("f", f), ("h", h)):
                if _takes_input(fn):
                    raise ValidationError(
                        f"inputs: {name}(x, k, u) takes a known input u; give its length as inputs=p (or drop the "
                        f"third parameter of {name})"
                    )
            self.p: int | None = None
            self.f_takes_input = self.h_takes_input = False
        else:
            f_in, h_in = _takes_input(f, optional=True), _takes_input(h, optional=True)
            if f_in is False and h_in is not True:
                raise ValidationError(
                    f"inputs: given ({inputs!r}) but neither f nor h takes an input (expected f(x, k, u) or h(x, k, u) "
                    "with a third parameter)"
                )
            self.p = check_int(inputs, "inputs", minimum=1)
            # an f whose signature cannot be read takes the input (as declared); such an h does not
            self.f_takes_input, self.h_takes_input = f_in is not False, h_in is True
        u0 = () if self.p is None else (np.zeros(self.p),)  # unbatched: x0 (n,) with u (p,)
        fx = as_float_array(f(self.x0.copy(), 0, *(u0 if self.f_takes_input else ())), "f(x0, 0)", ndim=1)
        if fx.shape != (n,):
            raise ShapeError(f"f(x0, 0): expected shape ({n},) (f maps (..., n) to (..., n)), got {fx.shape}")
        hx = as_float_array(h(self.x0.copy(), 1, *(u0 if self.h_takes_input else ())), "h(x0, 1)", ndim=1)
        m = hx.shape[0]
        if m < 1:
            raise ShapeError("h(x0, 1): expected at least one output, got shape (0,)")
        self.n, self.m, self.q = n, m, n
        # the noise enters directly and there is no input: the LinearSystem attributes a simulation reads
        self.B = self.Bu = self.D = None
        # batched over leading axes: (1, n) in, (1, n) / (1, m) out
        self.transition_map(self.x0[None], 0)
        self.measurement_map(self.x0[None], 1)
        self.Q = TimeSequence(Q, "Q", offset=0, psd=True)
        self.R = TimeSequence(R, "R", offset=1, psd=True)
        if self.Q.core_shape != (n, n):
            raise ShapeError(f"Q: expected ({n}, {n}) to match x0 of size n={n}, got {self.Q.core_shape}")
        if self.R.core_shape != (m, m):
            raise ShapeError(f"R: expected ({m}, {m}) to match h's {m} outputs, got {self.R.core_shape}")
        if F is not None:
            self.transition_jacobian(self.x0[None], 0)
        if H is not None:
            self.measurement_jacobian(self.x0[None], 1)

    @property
    def takes_input(self) -> bool:
        """Whether the model takes a known input (``f(x, k, u)``, ``h(x, k, u)`` or both; ``inputs=p``)."""
        return self.p is not None

    def _inputs(self, rows: int, u: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """``(u,)`` with ``rows`` rows (zeros when no input is given; ``u`` (N', p) repeated for a multiple N' of
        the rows, run-innermost), or ``()`` for a model without inputs."""
        if self.p is None:
            return ()
        if u is None:
            return (np.zeros((rows, self.p)),)
        reps = rows // u.shape[0]
        return (u if reps == 1 else np.tile(u, (reps, 1)),)

    def _f_args(self, rows: int, u: np.ndarray | None) -> tuple[np.ndarray, ...]:
        return self._inputs(rows, u) if self.f_takes_input else ()

    def _h_args(self, rows: int, u: np.ndarray | None) -> tuple[np.ndarray, ...]:
        return self._inputs(rows, u) if self.h_takes_input else ()

    # --- the maps, batched (N, n) -> (N, .) ------------------------------------------------------------
    def transition_map(self, x: np.ndarray, k: int, u: np.ndarray | None = None) -> np.ndarray:
        """:math:`f(x, k)` (or :math:`f(x, k, u)`) for ``x`` (N, n): (N, n), checked. ``u`` (N', p) holds the
        input of each run, with N a multiple of N' and the rows of ``x`` run-innermost (``x`` (R, N', n)
        flattened); None means :math:`u = 0`."""
        return _checked(self.f(x, k, *self._f_args(x.shape[0], u)), (x.shape[0], self.n), f"f(x, {k})")

    def measurement_map(self, x: np.ndarray, k: int, u: np.ndarray | None = None) -> np.ndarray:
        """:math:`h(x, k)` (or :math:`h(x, k, u)`) for ``x`` (N, n): (N, m), checked; ``u`` as
        :meth:`transition_map`'s (:math:`u_k`, the input of the reading's step)."""
        return _checked(self.h(x, k, *self._h_args(x.shape[0], u)), (x.shape[0], self.m), f"h(x, {k})")

    def transition_jacobian(self, x: np.ndarray, k: int, u: np.ndarray | None = None) -> np.ndarray:
        r""":math:`\partial f/\partial x` at ``x`` (N, n): (N, n, n), from ``F`` or central differences (``u`` as
        :meth:`transition_map`'s)."""
        if self.F is None:
            return jacobian_fd(lambda z: self.transition_map(z, k, u), x)
        return _checked(self.F(x, k, *self._f_args(x.shape[0], u)), (x.shape[0], self.n, self.n), f"F(x, {k})")

    def measurement_jacobian(self, x: np.ndarray, k: int, u: np.ndarray | None = None) -> np.ndarray:
        r""":math:`\partial h/\partial x` at ``x`` (N, n): (N, m, n), from ``H`` or central differences (``u`` as
        :meth:`measurement_map`'s)."""
        if self.H is None:
            return jacobian_fd(lambda z: self.measurement_map(z, k, u), x)
        return _checked(self.H(x, k, *self._h_args(x.shape[0], u)), (x.shape[0], self.m, self.n), f"H(x, {k})")

    # --- per-step accessors, as LinearSystem's -----------------------------------------------------------
    def process_cov(self, k: int) -> np.ndarray:
        """:math:`Q_k`, the covariance of the noise added to :math:`x_{k+1}`."""
        return self.Q.at(k)

    def measurement_cov(self, k: int) -> np.ndarray:
        """:math:`R_k` (k >= 1)."""
        return self.R.at(k)

    @property
    def time_invariant(self) -> bool:
        """True when Q and R are constant (f and h may still depend on k)."""
        return not (self.Q.varying or self.R.varying)

    def check_horizon(self, steps: int) -> None:
        """Raise if Q or R given per step is shorter than ``steps`` or a callable misbehaves on it."""
        for part in (self.Q, self.R):
            part.check_horizon(steps)
            part.validate_all(steps)

    def check_inputs(self, u: Any, steps: int, name: str = "u") -> np.ndarray | None:
        """Validate a known-input sequence ``(..., T, p)`` of an ``f(x, k, u)`` / ``h(x, k, u)``; None when none is
        given.

        Raises
        ------
        ShapeError
            An input for a model whose ``f`` takes none, or not of shape (..., steps, p).
        """
        if u is None:
            return None
        if self.p is None:
            raise ShapeError(
                f"{name}: this NonlinearSystem takes no input (write f(x, k, u) or h(x, k, u), with inputs=p)"
            )
        arr = as_float_array(u, name)
        if arr.ndim < 2 or arr.shape[-2:] != (steps, self.p):
            raise ShapeError(f"{name}: expected (..., {steps}, {self.p}), got {arr.shape}")
        return arr

    def __repr__(self) -> str:
        kind = "constant noise" if self.time_invariant else "time-varying noise"
        inp = "" if self.p is None else f", p={self.p}"
        return f"NonlinearSystem(n={self.n}, m={self.m}{inp}, {kind})"


def _checked(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = value if isinstance(value, np.ndarray) and value.dtype == np.float64 else np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ShapeError(f"{name}: expected shape {shape} for a batch of {shape[0]} states, got {arr.shape}")
    return arr


def augment_parameters(
    f: Any,
    h: Any,
    Q: Any,
    R: Any,
    x0: Any,
    P0: Any,
    *,
    theta0: Any,
    theta_cov: Any,
    theta_noise: Any = 0.0,
    inputs: int | None = None,
) -> NonlinearSystem:
    r"""Joint state-parameter tracking by state augmentation: unknown parameters :math:`\theta` appended to the
    state as a random walk (Arthur, Attarian, Hamilton & Tran 2018, the parameter tracking of their Tobit EKF).

    With ``f(x, k, theta)`` and ``h(x, k, theta)`` batched over the leading axes of ``x`` (..., n) and
    ``theta`` (..., d), the augmented state :math:`z = (x, \theta)` (n + d) follows

    .. math::

        x_k = f(x_{k-1}, k-1, \theta_{k-1}) + w_{k-1}, \qquad \theta_k = \theta_{k-1} + \eta_{k-1},
        \qquad y^*_k = h(x_k, k, \theta_k) + v_k,

    :math:`w \sim N(0, Q)`, :math:`\eta \sim N(0, Q_\theta)` (``theta_noise``; 0 keeps the parameter constant
    and its variance only shrinks), :math:`z_0 \sim N((\bar x_0, \theta_0), \mathrm{diag}(P_0, P_\theta))`. Any
    filter of a :class:`NonlinearSystem` then estimates x and :math:`\theta` together: the last d components of
    its mean are the tracked parameters and the matching block of its covariance their uncertainty.

    Parameters
    ----------
    f : callable ``f(x, k, theta)`` (or ``f(x, k, theta, u)`` with ``inputs``)
    h : callable ``h(x, k, theta)`` (or ``h(x, k, theta, u)`` with ``inputs``: an output with a known input)
    Q : (n, n) or (T, n, n) array_like or callable ; R : as for :class:`NonlinearSystem`
    x0 : (n,) ; P0 : (n, n)
    theta0 : (d,) array_like
        The parameters' prior mean.
    theta_cov : (d,) or (d, d) array_like
        Their prior variances (a vector) or covariance :math:`P_\theta`.
    theta_noise : float, (d,) or (d, d) array_like, default 0
        The random walk's step covariance :math:`Q_\theta` (a scalar or vector: variances).
    inputs : int, optional
        The input length p of an ``f(x, k, theta, u)`` and/or ``h(x, k, theta, u)`` (which of the two takes it: read
        from a fourth positional parameter, as :class:`NonlinearSystem` reads a third; an ``f`` whose signature
        cannot be read takes it, such an ``h`` does not).

    Returns
    -------
    NonlinearSystem
        Of dimension n + d, the parameters last.

    Raises
    ------
    ValidationError, ShapeError
        As :class:`NonlinearSystem` for the augmented model; ``theta_cov`` or ``theta_noise`` not PSD or not
        of size d; ``inputs`` given when neither f nor h has a fourth parameter.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.augment_parameters(lambda x, k, th: th * x, lambda x, k, th: x, [[0.1]], [[0.2]], [1.0],
    ...                             [[1.0]], theta0=[0.5], theta_cov=[0.04])
    >>> sys.n, sys.x0.tolist()
    (2, [1.0, 0.5])
    """
    for name, fn in (("f", f), ("h", h)):
        if not callable(fn):
            raise ValidationError(f"{name}: expected a callable {name}(x, k, theta), got {type(fn).__name__}")
    xa = as_float_array(x0, "x0", ndim=1)
    th = as_float_array(theta0, "theta0", ndim=1)
    n, d = xa.shape[0], th.shape[0]
    P_th = _cov_of(theta_cov, d, "theta_cov")
    Q_th = _cov_of(theta_noise, d, "theta_noise")
    P0a = as_float_array(P0, "P0", ndim=2)
    if P0a.shape != (n, n):
        raise ShapeError(f"P0: expected shape ({n}, {n}) to match x0, got {P0a.shape}")

    if inputs is None:
        for name, fn in (("f", f), ("h", h)):
            if _takes_input(fn, position=3):
                raise ValidationError(
                    f"inputs: {name}(x, k, theta, u) takes a known input u; give its length as inputs=p (or drop the "
                    f"fourth parameter of {name})"
                )
    f_in = inputs is not None and _takes_input(f, optional=True, position=3) is not False
    h_in = inputs is not None and _takes_input(h, optional=True, position=3) is True
    if inputs is not None and not (f_in or h_in):
        raise ValidationError(
            f"inputs: given ({inputs!r}) but neither f nor h takes an input (expected f(x, k, theta, u) or "
            "h(x, k, theta, u) with a fourth parameter)"
        )

    def f_with(z: np.ndarray, k: int, u: tuple[np.ndarray, ...]) -> np.ndarray:
        theta = z[..., n:]
        return np.concatenate([np.asarray(f(z[..., :n], k, theta, *u), dtype=float), theta], axis=-1)

    # the augmented maps take u exactly when f or h does (NonlinearSystem reads that from their signatures)
    def f_aug(z: np.ndarray, k: int) -> np.ndarray:
        return f_with(z, k, ())

    def f_aug_u(z: np.ndarray, k: int, u: np.ndarray) -> np.ndarray:
        return f_with(z, k, (u,))

    def h_aug(z: np.ndarray, k: int) -> np.ndarray:
        return h(z[..., :n], k, z[..., n:])

    def h_aug_u(z: np.ndarray, k: int, u: np.ndarray) -> np.ndarray:
        return h(z[..., :n], k, z[..., n:], u)

    if callable(Q):
        Q_aug: Any = lambda k: _block(np.asarray(Q(k), dtype=float), Q_th)  # noqa: E731
    else:
        Qa = as_float_array(Q, "Q", ndim=(2, 3))
        Q_aug = _block(Qa, Q_th) if Qa.ndim == 2 else np.stack([_block(q, Q_th) for q in Qa])
    return NonlinearSystem(
        f_aug_u if f_in else f_aug,
        h_aug_u if h_in else h_aug,
        Q_aug,
        R,
        np.concatenate([xa, th]),
        _block(P0a, P_th),
        inputs=inputs,
    )


def _cov_of(value: Any, d: int, name: str) -> np.ndarray:
    arr = as_float_array(value, name, ndim=(0, 1, 2))
    if arr.ndim < 2:
        arr = np.diag(np.broadcast_to(arr, (d,)).astype(float)) if arr.size in (1, d) else arr
    if arr.shape != (d, d):
        raise ShapeError(
            f"{name}: expected a scalar, ({d},) variances or a ({d}, {d}) covariance, got {np.shape(value)}"
        )
    check_psd(arr, name)
    return arr


def _block(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    n, d = A.shape[0], B.shape[0]
    out = np.zeros((n + d, n + d))
    out[:n, :n], out[n:, n:] = A, B
    return out
