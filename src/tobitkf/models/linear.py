r"""Linear (time-varying) Gaussian state-space models.

The model, with the package-wide time convention (Miller 2015, (2.2) and (3.18)):

.. math::

    x_k &= A_{k-1} x_{k-1} + B^u_k u_k + B_{k-1} w_{k-1}, \qquad w_{k-1} \sim N(0, Q_{k-1}) \\
    y^*_k &= C_k x_k + D_k u_k + v_k, \qquad v_k \sim N(0, R_k), \qquad x_0 \sim N(\bar x_0, P_0)

for :math:`k = 1, \dots, T`. ``x_0`` is the prior; the first measurement is
:math:`y_1`, stored at array index 0. The control input :math:`u_k` is the
input applied over the interval (k-1, k] (Miller (3.51)) and is
stored at index k-1 like :math:`y_k`.

Each matrix may be a constant array, an array with a leading time axis, or a
callable of the paper's time index ``k``; with ``batch_ndim = b > 0`` the arrays of A, B, C, Q and R
may also carry ``b`` leading run axes (one model per run: ``(*batch, n, n)`` or ``(*batch, T, n, n)``,
an axis of size 1 shared), broadcast against the readings' batch shape by every filter:

=========  ==========================  ==================================
argument   array index of time k       callable called with
=========  ==========================  ==================================
A, B, Q    ``A[k]`` (k = 0..T-1)        ``A(k)``, k = 0..T-1
Bu         ``Bu[k-1]`` (k = 1..T)       ``Bu(k)``, k = 1..T
C, D, R    ``C[k-1]`` (k = 1..T)        ``C(k)``, k = 1..T
=========  ==========================  ==================================
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, TimeSequence, as_float_array, check_int, check_psd

__all__ = ["LinearSystem"]


class LinearSystem:
    r"""A linear Gaussian state-space model with optional control input.

    Parameters
    ----------
    A : (n, n) or (T, n, n) array_like or callable
        State transition :math:`A_k`.
    C : (m, n) or (T, m, n) array_like or callable
        Measurement matrix :math:`C_k`.
    Q : (q, q) or (T, q, q) array_like or callable
        Process-noise covariance (symmetric PSD). ``q = n`` unless ``B`` is given.
    R : (m, m) or (T, m, m) array_like or callable
        Measurement-noise covariance (symmetric PSD).
    x0 : (n,) array_like
        Prior mean of :math:`x_0`.
    P0 : (n, n) array_like
        Prior covariance of :math:`x_0` (symmetric PSD).
    B : (n, q) or (T, n, q) array_like or callable, optional
        Noise-input matrix; the process noise enters as :math:`B_k w_k`. Default identity.
    Bu : (n, p) or (T, n, p) array_like or callable, optional
        Control-input matrix :math:`B^u`.
    D : (m, p) or (T, m, p) array_like or callable, optional
        Feed-through of the control input into the measurement.
    batch_ndim : int, default 0
        Number of leading run axes of A, B, C, Q and R: each is then its plain shape (shared by the runs),
        ``(*batch, r, c)`` (one constant matrix per run) or ``(*batch, T, r, c)`` (per run and per step);
        axes of size 1 are shared. ``batch_shape`` is the broadcast of their run axes; a filter of readings
        ``(*batch_y, T, m)`` needs ``batch_shape`` equal to ``batch_y`` or all ones (a
        :class:`~tobitkf.ShapeError` otherwise). Run ``i`` is then filtered with its own
        :math:`A_{i,k}, B_{i,k}, C_{i,k}, Q_{i,k}, R_{i,k}` (the numpy path; the compiled loop covers
        shared matrices only). Bu, D, x0 and P0 stay shared (per-run priors go to ``filter``).

    Raises
    ------
    ShapeError
        If the matrices do not conform, or their run axes do not broadcast.
    ValidationError
        If an entry is NaN or inf, or a covariance is not symmetric PSD.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-4]], R=[[0.01]], x0=[0.0], P0=[[1.0]])
    >>> sys.n, sys.m
    (1, 1)
    """

    def __init__(
        self,
        A: Any,
        C: Any,
        Q: Any,
        R: Any,
        x0: Any,
        P0: Any,
        *,
        B: Any = None,
        Bu: Any = None,
        D: Any = None,
        batch_ndim: Any = 0,  # an int (checked); Any so that a spread of optional matrices type-checks
    ):
        b = check_int(batch_ndim, "batch_ndim", minimum=0)
        self.batch_ndim = b
        self.A = TimeSequence(A, "A", offset=0, batch_ndim=b)
        self.C = TimeSequence(C, "C", offset=1, batch_ndim=b)
        self.Q = TimeSequence(Q, "Q", offset=0, psd=True, batch_ndim=b)
        self.R = TimeSequence(R, "R", offset=1, psd=True, batch_ndim=b)
        n = self.A.core_shape[0]
        if self.A.core_shape != (n, n):
            raise ShapeError(f"A: expected a square (n, n) matrix, got {self.A.core_shape}")
        if self.C.core_shape[1] != n:
            raise ShapeError(f"C: expected (m, {n}) to match A of size n={n}, got {self.C.core_shape}")
        m = self.C.core_shape[0]
        if self.R.core_shape != (m, m):
            raise ShapeError(f"R: expected ({m}, {m}) to match C with m={m} rows, got {self.R.core_shape}")
        self.B = None if B is None else TimeSequence(B, "B", offset=0, batch_ndim=b)
        q = n if self.B is None else self.B.core_shape[1]
        if self.B is not None and self.B.core_shape[0] != n:
            raise ShapeError(f"B: expected ({n}, q), got {self.B.core_shape}")
        if self.Q.core_shape != (q, q):
            raise ShapeError(
                f"Q: expected ({q}, {q}) (q = {'columns of B' if B is not None else 'n'}), got {self.Q.core_shape}"
            )
        self.Bu = None if Bu is None else TimeSequence(Bu, "Bu", offset=1)
        self.D = None if D is None else TimeSequence(D, "D", offset=1)
        p = None
        if self.Bu is not None:
            if self.Bu.core_shape[0] != n:
                raise ShapeError(f"Bu: expected ({n}, p), got {self.Bu.core_shape}")
            p = self.Bu.core_shape[1]
        if self.D is not None:
            if self.D.core_shape[0] != m or (p is not None and self.D.core_shape[1] != p):
                raise ShapeError(f"D: expected ({m}, {p if p is not None else 'p'}), got {self.D.core_shape}")
            p = self.D.core_shape[1]
        self.x0 = as_float_array(x0, "x0", ndim=1)
        if self.x0.shape != (n,):
            raise ShapeError(f"x0: expected shape ({n},), got {self.x0.shape}")
        self.P0 = as_float_array(P0, "P0", ndim=2)
        if self.P0.shape != (n, n):
            raise ShapeError(f"P0: expected shape ({n}, {n}), got {self.P0.shape}")
        check_psd(self.P0, "P0")
        self.n, self.m, self.q, self.p = n, m, q, p
        parts = [(part.name, part.batch_shape) for part in self._batched_parts()]
        try:
            self.batch_shape: tuple[int, ...] = tuple(np.broadcast_shapes(*(shape for _, shape in parts)))
        except ValueError:
            found = ", ".join(f"{name} {shape}" for name, shape in parts)
            raise ShapeError(f"A, B, C, Q, R: the run axes do not broadcast: {found}") from None

    def _batched_parts(self) -> list[TimeSequence]:
        return [self.A, self.C, self.Q, self.R] + ([self.B] if self.B is not None else [])

    @property
    def per_run(self) -> bool:
        """True when a matrix differs between runs (``batch_shape`` has more than one run)."""
        return int(np.prod(self.batch_shape, dtype=int)) > 1

    def _runs(self, part: TimeSequence, mat: np.ndarray) -> np.ndarray:
        """``mat`` (*part.batch_shape, r, c) as (N_sys or 1, r, c) with the runs flattened in the system's
        batch order (or as it is when the system has no run axes)."""
        if not self.batch_shape:
            return mat
        if part.batch_shape == self.batch_shape:
            return mat.reshape((-1,) + mat.shape[-2:])
        if int(np.prod(part.batch_shape, dtype=int)) == 1:
            return mat.reshape((1,) + mat.shape[-2:])
        full = np.broadcast_to(mat, self.batch_shape + mat.shape[-2:])
        return full.reshape((-1,) + mat.shape[-2:])

    def check_runs(self, batch: tuple[int, ...]) -> None:
        """Raise :class:`~tobitkf.ShapeError` unless the system's run axes fit readings of batch shape ``batch``:
        equal to it, or of one run only (shared)."""
        if self.per_run and tuple(batch) != self.batch_shape:
            raise ShapeError(
                f"system: its matrices carry run axes {self.batch_shape} (batch_ndim={self.batch_ndim}), "
                f"the readings' batch shape is {tuple(batch)}; expected the same shape"
            )

    # --- per-step accessors (paper time index k) ---------------------------------
    # With run axes (``batch_shape`` not ()), each accessor returns (N_sys or 1, r, c): the runs flattened.
    def transition(self, k: int) -> np.ndarray:
        """:math:`A_k`, used in :math:`x_{k+1} = A_k x_k + ...`: (n, n), or (N or 1, n, n) with run axes."""
        return self._runs(self.A, self.A.at(k))

    def process_cov(self, k: int) -> np.ndarray:
        r""":math:`B_k Q_k B_k^T`, the covariance of the noise added to :math:`x_{k+1}`."""
        Q = self._runs(self.Q, self.Q.at(k))
        if self.B is None:
            return Q
        B = self._runs(self.B, self.B.at(k))
        return B @ Q @ np.swapaxes(B, -1, -2)

    def measurement(self, k: int) -> np.ndarray:
        """:math:`C_k`, used in :math:`y_k = C_k x_k + v_k` (k >= 1)."""
        return self._runs(self.C, self.C.at(k))

    def measurement_cov(self, k: int) -> np.ndarray:
        """:math:`R_k` (k >= 1)."""
        return self._runs(self.R, self.R.at(k))

    @property
    def time_invariant(self) -> bool:
        """True when A, C, Q, R (and B) are constant and shared by every run."""
        return not self.per_run and not any(p.varying for p in self._batched_parts())

    def check_horizon(self, steps: int) -> None:
        """Raise if a time-indexed matrix is shorter than ``steps`` or a callable misbehaves on it.

        Callables are evaluated once over the horizon (shape, finiteness, PSD for Q and R),
        so a bad value at a late step fails at the public call, not as NaN in the output.
        """
        for part in (self.A, self.C, self.Q, self.R, self.B, self.Bu, self.D):
            if part is not None:
                part.check_horizon(steps)
                part.validate_all(steps)

    def check_inputs(self, u: Any, steps: int, name: str = "u") -> np.ndarray | None:
        """Validate a control sequence ``(..., T, p)``; None when the model has no input."""
        if u is None:
            return None
        if self.p is None:
            raise ShapeError(f"{name}: the system has no control input (give Bu or D)")
        u = as_float_array(u, name)
        if u.ndim < 2 or u.shape[-2:] != (steps, self.p):
            raise ShapeError(f"{name}: expected (..., {steps}, {self.p}), got {u.shape}")
        return u

    def input_effect(self, k: int, u_k: np.ndarray | None) -> tuple[np.ndarray | float, np.ndarray | float]:
        """State and measurement offsets :math:`(B^u_k u_k, D_k u_k)` for input ``u_k`` (..., p)."""
        if u_k is None:
            return 0.0, 0.0
        bx = 0.0 if self.Bu is None else u_k @ self.Bu.at(k).T
        dy = 0.0 if self.D is None else u_k @ self.D.at(k).T
        return bx, dy

    def __repr__(self) -> str:
        kind = "time-invariant" if self.time_invariant else "time-varying"
        runs = f", runs {self.batch_shape}" if self.per_run else ""
        return f"LinearSystem(n={self.n}, m={self.m}, q={self.q}, p={self.p}, {kind}{runs})"
