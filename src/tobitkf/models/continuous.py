r"""Linear Gaussian models in continuous time, discretised exactly over each gap between readings.

The model (a linear stochastic differential equation observed at times :math:`t_1 < \dots < t_T`):

.. math::

    dx(t) = (A_c x(t) + B_c u(t))\,dt + dw(t), \qquad E[dw\,dw^T] = Q_c\,dt, \qquad
    y_k = C x(t_k) + D u_k + v_k, \quad v_k \sim N(0, R),

with the prior :math:`x(t_0) \sim N(\bar x_0, P_0)` at a start time :math:`t_0 \le t_1` (by default
:math:`t_0 = t_1`: the prior is the state at the first reading). Over a gap :math:`\Delta_k = t_k -
t_{k-1}` with the input held at :math:`u_k` (zero-order hold on :math:`(t_{k-1}, t_k]`, the package's
convention that :math:`u_k` acts over the interval ending at reading k) the exact transition is

.. math::

    x(t_k) = A(\Delta_k)x(t_{k-1}) + B(\Delta_k)u_k + w_k, \qquad w_k \sim N(0, Q(\Delta_k)),

    A(\Delta) = e^{A_c\Delta}, \qquad B(\Delta) = \int_0^\Delta e^{A_cs}\,ds\,B_c, \qquad
    Q(\Delta) = \int_0^\Delta e^{A_cs}Q_ce^{A_c^Ts}\,ds,

computed by block matrix exponentials (:func:`expm_batch`): :math:`Q` by Van Loan's method
(Van Loan 1978, "Computing integrals involving the matrix exponential"),

.. math::

    \exp\left(\begin{bmatrix} -A_c & Q_c \\ 0 & A_c^T \end{bmatrix}\Delta\right)
    = \begin{bmatrix} \cdot & F_{12} \\ 0 & F_{22} \end{bmatrix}, \qquad
    A(\Delta) = F_{22}^T, \qquad Q(\Delta) = F_{22}^TF_{12},

and :math:`B` from :math:`\exp\left(\begin{bmatrix} A_c & B_c \\ 0 & 0\end{bmatrix}\Delta\right)`, whose
top-right block is :math:`B(\Delta)`. A scalar Ornstein-Uhlenbeck process :math:`A_c = -\theta`,
:math:`Q_c = \sigma^2` gives :math:`A = e^{-\theta\Delta}`, :math:`Q = \sigma^2(1 - e^{-2\theta\Delta})/(2\theta)`.

Irregular sampling is thus a time-varying discrete system (:meth:`ContinuousLinearSystem.at_times`): one
:math:`(A_k, Q_k, B_k)` per gap, which every filter, smoother, likelihood and fit of the package runs as
it is. Times are floats in the model's time unit or dates (numpy ``datetime64``, pandas timestamps,
ISO strings) converted to that unit (:func:`time_values`); two readings at the same time are refused
(give them as two channels of one reading instead).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array, check_psd
from .linear import LinearSystem

__all__ = ["ContinuousLinearSystem", "time_values", "expm_batch", "TIME_UNITS"]

#: length of each time unit in nanoseconds (a year is 365.25 days)
TIME_UNITS = {
    "s": 1e9,
    "min": 60e9,
    "h": 3600e9,
    "D": 86400e9,
    "W": 7 * 86400e9,
    "Y": 365.25 * 86400e9,
}
_ALIASES = {"second": "s", "minute": "min", "hour": "h", "day": "D", "days": "D", "week": "W", "year": "Y"}


_TAYLOR_DEGREE = 14


def expm_batch(M: np.ndarray) -> np.ndarray:
    r"""Matrix exponentials of a stack ``M`` (K, r, r), batched: scaling and squaring with a Taylor series
    (Moler & Van Loan 2003, "Nineteen dubious ways...", methods 1 and 3).

    Each matrix is scaled by :math:`2^{-s}` to a 1-norm at most 1/2, its exponential summed to degree 14
    (truncation error below :math:`0.5^{15}/15! \approx 2\times10^{-17}` relative), then squared s times.
    Equal to ``scipy.linalg.expm`` to about 1e-12 relative for norms up to a few hundred (tested); used
    instead of it because its batched form costs tens of milliseconds per call for a few small matrices,
    which a fit pays at every likelihood evaluation.
    """
    M = np.asarray(M, dtype=float)
    r = M.shape[-1]
    norm = np.abs(M).sum(axis=-2).max(axis=-1, initial=0.0)
    s = np.maximum(0, np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.5))).astype(int)
    X = M * np.ldexp(1.0, -s)[..., None, None]
    eye = np.broadcast_to(np.eye(r), M.shape)
    E = eye + X / _TAYLOR_DEGREE
    for k in range(_TAYLOR_DEGREE - 1, 0, -1):  # Horner: I + X/1 (I + X/2 (I + ...))
        E = eye + (X @ E) / k
    for j in range(int(s.max(initial=0))):
        E = np.where((j < s)[..., None, None], E @ E, E)
    return E


def _unit(unit: Any) -> str:
    key = _ALIASES.get(unit, unit) if isinstance(unit, str) else unit
    if key not in TIME_UNITS:
        raise ValidationError(f"unit: expected one of {', '.join(TIME_UNITS)} (or day, year, ...), got {unit!r}")
    return key


def _as_dates(times: Any) -> np.ndarray | None:
    """``times`` as datetime64[ns] when they are dates (datetime64, pandas timestamps, date objects, ISO
    strings), else None."""
    arr = np.asarray(times)
    if arr.dtype.kind == "M":
        return arr.astype("datetime64[ns]")
    if arr.dtype.kind in "OUS":
        try:
            return np.asarray(times, dtype="datetime64[ns]")
        except (TypeError, ValueError):
            raise ValidationError(
                "times: expected numbers or dates (datetime64, pandas timestamps, ISO strings), "
                f"got values such as {arr.ravel()[:1].tolist()!r}"
            ) from None
    return None


def time_values(times: Any, *, unit: str = "D", origin: Any = None, name: str = "times") -> np.ndarray:
    """Times as floats in the model's ``unit``: numbers as they are, dates as ``(t - origin) / unit``.

    Parameters
    ----------
    times : (T,) array_like
        Numbers, or dates (numpy ``datetime64``, pandas ``DatetimeIndex``, ``datetime`` objects, ISO strings).
    unit : {"s", "min", "h", "D", "W", "Y"} (or "second", "day", "year", ...), default "D"
        The time unit of the model's rates; only used for dates (a year is 365.25 days).
    origin : date, optional
        The date that becomes 0 (default: the earliest of ``times``); only for dates.
    name : str
        The argument name used in errors.

    Returns
    -------
    (T,) float ndarray

    Raises
    ------
    ValidationError
        Times that are neither numbers nor dates, NaN / NaT, or an unknown unit.
    """
    key = _unit(unit)
    dates = _as_dates(times)
    if dates is None:
        vals = as_float_array(times, name, ndim=1)
        return vals
    if dates.ndim != 1:
        raise ShapeError(f"{name}: expected a 1-D sequence of times, got shape {dates.shape}")
    if np.isnat(dates).any():
        raise ValidationError(f"{name}: missing date (NaT) at index {int(np.argmax(np.isnat(dates)))}")
    if origin is None:
        ref = dates.min() if dates.size else np.datetime64(0, "ns")
    else:
        ref = _as_dates([origin])
        if ref is None:
            raise ValidationError(f"origin: expected a date for dated {name}, got {origin!r}")
        ref = ref[0]
    return (dates - ref).astype(np.int64) / TIME_UNITS[key]


def check_increasing(t: np.ndarray, name: str = "times") -> None:
    """Raise :class:`ValidationError` unless ``t`` is strictly increasing (a duplicate or a step back named)."""
    d = np.diff(t)
    if (d > 0).all():
        return
    i = int(np.argmax(~(d > 0)))
    what = "a duplicate time" if d[i] == 0 else "times out of order"
    raise ValidationError(
        f"{name}: expected strictly increasing times, got {what} at index {i + 1} ({t[i + 1]!r} after {t[i]!r}); "
        "two readings at one time go in as two channels of one reading"
    )


class ContinuousLinearSystem(LinearSystem):
    r"""A linear Gaussian model in continuous time (module docstring), read at arbitrary times.

    As a :class:`~tobitkf.LinearSystem` it is the discretisation over one time unit
    (:math:`A = e^{A_c}`, ...): readings one unit apart. Give the sample times to any filter, smoother,
    likelihood or fit (``times=``), or call :meth:`at_times`, for irregular readings.

    Parameters
    ----------
    Ac : (n, n) array_like
        Drift matrix :math:`A_c` (rates per ``unit``).
    Qc : (n, n) array_like
        Diffusion (spectral density) :math:`Q_c`, symmetric PSD.
    C : (m, n) array_like
    R : (m, m) array_like
        Measurement-noise covariance (symmetric PSD).
    x0 : (n,) array_like
    P0 : (n, n) array_like
        The prior of the state at the start time.
    Bc : (n, p) array_like, optional
        Input matrix: :math:`B_cu(t)` enters the drift, ``u`` held over each gap (zero-order hold).
    D : (m, p) array_like, optional
        Feed-through of the input into the reading.
    unit : str, default "D"
        The time unit of the rates, used to convert dated times (:func:`time_values`); float times are
        taken in this unit as they are.

    Raises
    ------
    ShapeError, ValidationError
        As :class:`~tobitkf.LinearSystem`, and for a non-square ``Ac`` or an asymmetric / indefinite ``Qc``.

    Examples
    --------
    An Ornstein-Uhlenbeck state (rate 0.5, diffusion 2) read at three irregular times:

    >>> import numpy as np, tobitkf as tk
    >>> ou = tk.ContinuousLinearSystem([[-0.5]], [[2.0]], [[1.0]], [[0.1]], [0.0], [[2.0]])
    >>> sys = ou.at_times([0.0, 1.0, 3.0])
    >>> np.round(sys.A.array[:, 0, 0], 4).tolist()   # e^{-0.5 * gap}; the prior is at the first time
    [1.0, 0.6065, 0.3679]
    """

    def __init__(
        self, Ac: Any, Qc: Any, C: Any, R: Any, x0: Any, P0: Any, *, Bc: Any = None, D: Any = None, unit: str = "D"
    ):
        self.Ac = as_float_array(Ac, "Ac", ndim=2)
        n = self.Ac.shape[0]
        if self.Ac.shape != (n, n):
            raise ShapeError(f"Ac: expected a square (n, n) matrix, got {self.Ac.shape}")
        self.Qc = as_float_array(Qc, "Qc", ndim=2)
        if self.Qc.shape != (n, n):
            raise ShapeError(f"Qc: expected ({n}, {n}) to match Ac, got {self.Qc.shape}")
        check_psd(self.Qc, "Qc")
        self.Bc = None if Bc is None else as_float_array(Bc, "Bc", ndim=2)
        if self.Bc is not None and self.Bc.shape[0] != n:
            raise ShapeError(f"Bc: expected ({n}, p), got {self.Bc.shape}")
        self.unit = _unit(unit)
        self._C, self._R, self._D = C, R, D
        A1, Q1, B1 = self.discretize(1.0)
        super().__init__(A=A1, C=C, Q=Q1, R=R, x0=x0, P0=P0, Bu=B1, D=D)

    def discretize(self, dt: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        r"""The exact transition over gaps ``dt``: :math:`A(\Delta)`, :math:`Q(\Delta)` (Van Loan) and the
        zero-order-hold input matrix :math:`B(\Delta)` (None without ``Bc``).

        Parameters
        ----------
        dt : float or (K,) array_like
            Gaps, >= 0 (0 gives A = I, Q = 0, B = 0).

        Returns
        -------
        A, Q : (n, n) or (K, n, n) ndarray
        B : (n, p) or (K, n, p) ndarray or None

        Raises
        ------
        ValidationError
            A negative or non-finite gap.
        """
        d = as_float_array(dt, "dt", ndim=(0, 1))
        if (d < 0).any():
            raise ValidationError(f"dt: expected gaps >= 0, got {float(d[d < 0].ravel()[0])!r}")
        gaps, inverse = np.unique(d.ravel(), return_inverse=True)  # a regular grid: one exponential
        n = self.Ac.shape[0]
        M = np.zeros((gaps.size, 2 * n, 2 * n))
        M[:, :n, :n] = -self.Ac
        M[:, :n, n:] = self.Qc
        M[:, n:, n:] = self.Ac.T
        E = expm_batch(M * gaps[:, None, None])
        A = np.swapaxes(E[:, n:, n:], -1, -2)
        Q = A @ E[:, :n, n:]
        Q = 0.5 * (Q + np.swapaxes(Q, -1, -2))
        B = None
        if self.Bc is not None:
            p = self.Bc.shape[1]
            Mb = np.zeros((gaps.size, n + p, n + p))
            Mb[:, :n, :n] = self.Ac
            Mb[:, :n, n:] = self.Bc
            B = expm_batch(Mb * gaps[:, None, None])[:, :n, n:][inverse].reshape(d.shape + (n, p))
        return A[inverse].reshape(d.shape + (n, n)), Q[inverse].reshape(d.shape + (n, n)), B

    def time_values(self, times: Any, *, origin: Any = None, name: str = "times") -> np.ndarray:
        """``times`` as floats in the model's unit (:func:`time_values` with this model's ``unit``)."""
        return time_values(times, unit=self.unit, origin=origin, name=name)

    def at_times(self, times: Any, *, start: Any = None) -> LinearSystem:
        r"""The discrete system of readings at ``times``: :math:`A_k = A(t_k - t_{k-1})`, :math:`Q_k`,
        :math:`B^u_k` per gap (leading time axis), C, R, D as given, the prior at ``start``.

        Parameters
        ----------
        times : (T,) array_like
            Strictly increasing sample times: floats in the model's unit, or dates.
        start : float or date, optional
            The time of the prior :math:`x(t_0)`, at or before the first reading (default: the first
            reading's time, so the prior is the state at :math:`t_1`).

        Returns
        -------
        LinearSystem
            Time-varying over T steps (``A[k-1]`` the transition into reading k).

        Raises
        ------
        ValidationError
            Duplicate or decreasing times, a start after the first reading, dates mixed with numbers.
        """
        t = self._values_with_start(times, start)
        return self._system_on(t[1:], t[0])

    def _values_with_start(self, times: Any, start: Any) -> np.ndarray:
        """``[t_0, t_1, ..., t_T]`` as floats (the start first), checked."""
        if start is None:
            t = self.time_values(times)
            if t.size == 0:
                raise ValidationError("times: expected at least one sample time")
            t = np.concatenate([t[:1], t])
        else:
            dates = _as_dates(times)
            if dates is not None:
                s = _as_dates([start])
                if s is None:
                    raise ValidationError(f"start: expected a date for dated times, got {start!r}")
                t = self.time_values(np.concatenate([s, dates]))
            else:
                t = np.concatenate([[float(as_float_array(start, "start", ndim=0))], self.time_values(times)])
            if t.size > 1 and t[0] > t[1]:
                raise ValidationError("start: the prior's time must be at or before the first reading")
        check_increasing(t[1:])
        return t

    def _system_on(self, t: np.ndarray, t0: float) -> LinearSystem:
        gaps = np.diff(np.concatenate([[t0], t]))
        A, Q, B = self.discretize(gaps)
        return LinearSystem(A=A, C=self._C, Q=Q, R=self._R, x0=self.x0, P0=self.P0, Bu=B, D=self._D)

    def __repr__(self) -> str:
        return f"ContinuousLinearSystem(n={self.n}, m={self.m}, p={self.p}, unit={self.unit!r})"
