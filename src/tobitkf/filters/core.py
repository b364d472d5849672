r"""The estimation core: one state, one result, one predict, one measurement update, one time loop.

Every Gaussian-update family (Kalman, dropping Kalman, Tobit and multi-region, steady-state Tobit,
fading Tobit, protocol Tobit, the delay LMMSE) is a *measurement model*: given the prediction it
returns the moments of its update (Stone Soup's measurement prediction),

.. math::

    \hat y = E[y_k \mid \text{prior}], \qquad H = \mathrm{diag}(s)\,H_0, \qquad
    R_{xe} = \bar P H^T, \qquad R_{ee} = H\bar PH^T + N,

with a common :math:`H_0` (m, n_x), a per-run channel scale :math:`s` (N, m) (the Tobit
:math:`E(\mathbf p)`, the fading :math:`\bar\gamma`, the failure mean :math:`\bar\Lambda`), a noise
term :math:`N` (diagonal or full) and the channels that take part. :func:`measurement_update`
applies them in every covariance form with one masking rule,

.. math::

    K = R_{xe}R_{ee}^{-1}, \qquad \hat x = \bar x + K(y - \hat y), \qquad
    P = \begin{cases} \bar P - KR_{xe}^T & \text{standard} \\
    (I - KH)\bar P(I - KH)^T + KNK^T & \text{Joseph} \\
    SS^T \text{ from a QR of } \begin{bmatrix} N^{1/2\,T} & 0 \\ \bar S^TH^T & \bar S^T\end{bmatrix}
      & \text{square root,} \end{cases}

and :func:`time_update` the one predict :math:`\bar x = A\hat x + b`, :math:`\bar P = APA^T + Q`,
with the block-shift structure of an augmented state (fading, protocol, delay) and the square-root
form. Channels that do not take part (missing readings, dropped or censored readings, a family's own
rule, or :math:`R_{ee,ll}` not above the smallest normal number) are removed exactly: zero gain
column, the other channels updated as in the reduced model.

On top of these, :class:`GaussianFilter` gives every family the same online API and one loop::

    state = est.init(batch_shape=(N,))        # the prior
    state = est.step(state, y_k, u=u_k)       # one predict + update; NaN reading = predict only
    result = est.filter(y)                    # the loop over the same step, same numbers

Time convention of the package families (the delay and H∞ families keep their papers' indices, and
:attr:`FilterResult.times` says which): :math:`x_0 \sim N(\bar x_0, P_0)` is the prior
(``state.k = 0``), the first reading is :math:`y_1` at index 0, and result row ``k-1`` holds
:math:`\hat x_{k|k}`, :math:`P_{k|k}` and the prediction :math:`\hat x_{k|k-1}`, :math:`P_{k|k-1}`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Mapping, cast

import numpy as np

from .._linalg import psd_sqrt, symmetrize
from .._progress import plural
from .._validation import (
    _F64,
    ShapeError,
    ValidationError,
    as_float_array,
    check_memory,
    check_option,
    check_psd,
    check_scale,
    reading_in_scale,
)
from . import _backend, _online_check
from ._online_check import (
    CORRECTION_CAP,
    CORRECTION_WINDOW,
    _caller_level,
    _correction_remedy,
    correction_threshold,
)

__all__ = [
    "FilterResult",
    "FilterState",
    "Transition",
    "MeasurementPrediction",
    "predict",
    "shift_predict",
    "sqrt_predict",
    "time_update",
    "gain_update",
    "sqrt_update",
    "measurement_update",
    "GaussianFilter",
    "COVARIANCE_FORMS",
    "OUTPUTS",
    "parse_outputs",
    "prepare_measurements",
    "prepare_inputs",
    "check_prior",
    "check_keywords",
    "process_roots",
    "psd_sqrt",
    "symmetrize",
]

COVARIANCE_FORMS = ("standard", "joseph", "square_root")
OUTPUTS = ("mean", "cov", "var", "pred_mean", "pred_cov", "extras")
_TINY = np.finfo(np.float64).tiny


# --------------------------------------------------------------------------- state and result


@dataclass(frozen=True, eq=False)
class FilterState:
    r"""The state of an estimator between two readings: a frozen record of arrays, picklable.

    Estimators return a new state from :meth:`~GaussianFilter.init` and every
    :meth:`~GaussianFilter.step`; a state can be pickled mid-run and the run resumed from it with
    identical results.

    Attributes
    ----------
    k : int
        Time index of the last update (the prior: 0 for the package families, the family's own
        start index for the delay and H∞ families).
    batch_shape : tuple of int
        Leading (run) shape; ``()`` for one run.
    x : (N, n_x) ndarray
        Internal mean, N = prod(batch_shape) (1 for one run). For augmented families (fading,
        protocol, delay) n_x > n and the first n components are :math:`\hat x_k`.
    P : (N or 1, n_x, n_x) ndarray or None
        Internal covariance; a leading axis of 1 means one covariance shared by every run (a Kalman
        filter whose runs all took the same channels). None for estimators without a covariance.
    S : (N or 1, n_x, n_x) ndarray or None
        Square-root factor, :math:`P = SS^T`, when the filter runs the square-root form.
    n : int
        Dimension of the reported state (the first n components of ``x``).
    carry : mapping
        Family-specific arrays carried from step to step (stale predictions, second moments,
        pending inputs, a generator's state); read-only by convention.
    extras : mapping
        The per-step quantities of the last step (what ``filter`` records in ``extras``, for the
        runs in the flat layout (N, ...)), e.g. ``p_uncensored``; empty for a prior.
    """

    k: int
    batch_shape: tuple[int, ...]
    x: np.ndarray
    P: np.ndarray | None
    n: int
    S: np.ndarray | None = None
    carry: Mapping[str, Any] = field(default_factory=dict)
    extras: Mapping[str, Any] = field(default_factory=dict)

    @property
    def mean(self) -> np.ndarray:
        """:math:`\\hat x_{k|k}`, shape ``batch_shape + (n,)``."""
        return self.x[:, : self.n].reshape(self.batch_shape + (self.n,))

    @property
    def cov(self) -> np.ndarray | None:
        """:math:`P_{k|k}`, shape ``batch_shape + (n, n)`` (a read-only broadcast view when shared)."""
        if self.P is None:
            return None
        P = self.P[:, : self.n, : self.n]
        if P.shape[0] == 1 and self.runs != 1:
            return np.broadcast_to(P[0], self.batch_shape + (self.n, self.n))
        return P.reshape(self.batch_shape + (self.n, self.n))

    @property
    def runs(self) -> int:
        """Number of runs N = prod(batch_shape)."""
        return math.prod(self.batch_shape)

    @property
    def aug_mean(self) -> np.ndarray:
        """The whole internal mean, ``batch_shape + (n_x,)``."""
        return self.x.reshape(self.batch_shape + self.x.shape[-1:])

    @property
    def aug_cov(self) -> np.ndarray | None:
        """The whole internal covariance, ``batch_shape + (n_x, n_x)``."""
        if self.P is None:
            return None
        if self.P.shape[0] == 1 and self.runs != 1:
            return np.broadcast_to(self.P[0], self.batch_shape + self.P.shape[-2:])
        return self.P.reshape(self.batch_shape + self.P.shape[-2:])

    def replace(self, **changes: Any) -> FilterState:
        """A copy with some fields changed (checked in full when it next enters an estimator)."""
        from dataclasses import replace as _replace

        return _replace(self, **changes)

    def __getstate__(self) -> dict[str, Any]:
        # the mark of the estimator that made the state (:func:`mark_trusted`) does not travel: an unpickled
        # (or copied) state is checked in full when it next enters an estimator
        d = self.__dict__
        return {key: val for key, val in d.items() if key != _ORIGIN} if _ORIGIN in d else dict(d)


def step_state(
    k: int,
    batch_shape: tuple[int, ...],
    x: np.ndarray,
    P: np.ndarray | None,
    n: int,
    S: np.ndarray | None = None,
    carry: Mapping[str, Any] | None = None,
    extras: Mapping[str, Any] | None = None,
) -> FilterState:
    """``FilterState(k=k, ..., extras=extras)`` without the frozen dataclass's ``__init__`` (one
    ``object.__setattr__`` per field, about 1 µs of an online step of ~15 µs): the same object, fields set in
    its ``__dict__``; ``carry``/``extras`` None are a new empty dict each, as the defaults. No checks, as
    the dataclass's constructor has none; for the estimators' steps."""
    st = _new_object(FilterState)
    d = st.__dict__
    d["k"] = k
    d["batch_shape"] = batch_shape
    d["x"] = x
    d["P"] = P
    d["n"] = n
    d["S"] = S
    d["carry"] = {} if carry is None else carry
    d["extras"] = {} if extras is None else extras
    return st


_new_object = object.__new__

#: key, in a state's ``__dict__``, of the token of the estimator that made it (not a field: ``replace``,
#: pickling and copying drop it)
_ORIGIN = "_origin"
_UNTRUSTED = object()


def _token(est: Any) -> object:
    """The estimator's private token, made at its first state."""
    tok = est.__dict__.get("_state_token")
    if tok is None:
        tok = est.__dict__["_state_token"] = object()
    return tok


def mark_trusted(est: Any, state: FilterState) -> FilterState:
    """Mark ``state`` as made (or checked in full) by ``est``: it then enters ``est``'s ``step``, ``predict``
    and ``update`` without the full check of :meth:`Estimator._check_state`. Returns ``state``."""
    state.__dict__[_ORIGIN] = _token(est)
    return state


def is_trusted(est: Any, state: Any) -> bool:
    """Whether ``state`` is a :class:`FilterState` that ``est`` made (or checked) and nobody replaced, copied
    or unpickled since: one type test and two dictionary look-ups."""
    return type(state) is FilterState and state.__dict__.get(_ORIGIN, _UNTRUSTED) is est.__dict__.get("_state_token")


@dataclass(frozen=True)
class FilterResult:
    r"""Output of every estimator's ``filter``: one row per reading, with the source's time index.

    Row ``i`` holds the estimate after the reading of row ``i`` of ``y``; ``times[i]`` is the
    source's time index of that row (1..T for the package families, whose prior is
    :math:`x_0`; 0..T-1 for the delay family, whose first reading is y(0); 1..T for the H∞ filter,
    whose row i is :math:`\hat x_{i+1}` from :math:`\tilde y_0..\tilde y_i`). Metrics align the
    truth by ``times`` (:func:`tobitkf.metrics.summarize`).

    Attributes
    ----------
    mean : (..., T, n) ndarray or None
        Filtered means :math:`\hat x_{k|k}` (None when not requested in ``outputs``).
    cov : (..., T, n, n) ndarray or None
        Filtered covariances :math:`P_{k|k}` (None when not requested or not defined).
    pred_mean : (..., T, n) ndarray or None
        Predicted means :math:`\hat x_{k|k-1}` (before the reading of the same row).
    pred_cov : (..., T, n, n) ndarray or None
        Predicted covariances :math:`P_{k|k-1}`.
    extras : dict
        Estimator-specific per-step quantities (e.g. ``p_uncensored`` (..., T, m)).
    times : (T,) int ndarray
        The source's time index of each row.
    var : (..., T, n) ndarray or None
        Diagonals of ``cov`` (filled when ``outputs`` asks for ``"var"`` instead of ``"cov"``).
    final : FilterState or None
        The state after the last reading: pass it to ``step`` or to ``filter(..., state=...)`` to
        continue the run.
    """

    mean: np.ndarray | None
    cov: np.ndarray | None
    pred_mean: np.ndarray | None
    pred_cov: np.ndarray | None
    extras: dict[str, Any] = field(default_factory=dict)
    times: np.ndarray | None = None
    var: np.ndarray | None = None
    final: FilterState | None = None


# --------------------------------------------------------------------------- what a family contributes


@dataclass(frozen=True, eq=False)
class Transition:
    r"""One time update :math:`\bar x = A\hat x + b`, :math:`\bar P = APA^T + Q_d`.

    ``A`` (n_x, n_x) dense, or (n, n) acting on block ``source`` of an augmented state when ``shift``
    (the block-shift transition :math:`\xi' = [A\xi_{source} + b;\ \xi_0;\ \dots;\ \xi_{L-1}]` of the
    fading, protocol and delay families); ``Qd`` the noise covariance (of the top block when
    ``shift``); ``b`` (N, n) or 0 an input offset; ``G`` a root of ``Qd`` (``G G^T = Qd``) for the
    square-root form (computed from ``Qd`` when None). ``P_fixed`` replaces the covariance
    recursion by a constant (fixed-gain filters).
    """

    A: np.ndarray
    Qd: np.ndarray
    b: Any = 0.0
    shift: bool = False
    source: int = 0
    G: np.ndarray | None = None
    P_fixed: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class MeasurementPrediction:
    r"""The moments a family hands to :func:`measurement_update` (see the module docstring).

    Attributes
    ----------
    expected : (N, m) ndarray
        :math:`\hat y = E[y_k \mid \text{prior}]`; the innovation is :math:`y_k - \hat y`.
    H0 : (m, n_x) ndarray
        The common part of the effective measurement matrix.
    scale : (N, m) ndarray or None
        Per-run channel scale, :math:`H = \mathrm{diag}(s)H_0`; None means 1.
    noise : (N or 1, m) or (N or 1, m, m) ndarray
        The noise term N of :math:`R_{ee} = H\bar PH^T + N`: its diagonal, or the full matrix.
    valid : (N, m) bool ndarray or None
        Channels that take part (a missing reading, NaN, never does).
    observed : (N, m) ndarray or None
        The reading to use instead of the one passed to the step (a sensor in the loop that clips
        at a limit set from the prior).
    gain : (n_x, m) ndarray or None
        A fixed gain (steady-state filters): :math:`\hat x = \bar x + K(y - \hat y)` and the
        covariance is the transition's fixed one.
    posterior_cov : (N or 1, n_x, n_x) ndarray or None
        With a fixed ``gain``: the (constant) covariance after the update.
    retained : (N, m) ndarray or None
        Diagonal variance :math:`V` the reading leaves in the channel (an assumed-density update of a
        censored reading: the variance of the latent reading given that it was censored). The
        posterior covariance gains :math:`KVK^T` in every form: :math:`P = \bar P - K(R_{ee} - V)K^T`.
        None means 0 (the reading removes the whole innovation variance).
    extras : dict
        Per-step quantities the family reports (N, ...).
    """

    expected: np.ndarray
    H0: np.ndarray
    noise: np.ndarray
    scale: np.ndarray | None = None
    valid: np.ndarray | None = None
    observed: np.ndarray | None = None
    gain: np.ndarray | None = None
    posterior_cov: np.ndarray | None = None
    retained: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- the one predict


def predict(x: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0):
    r"""Time update :math:`\bar x = A\hat x + B^u u`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)`
    (Miller (2.3), (3.20)–(3.21)), batched.

    ``x`` (N, n), ``P`` (N or 1, n, n); ``A`` (n, n); ``Qd`` (n, n) the noise covariance
    :math:`BQB^T`; ``bx`` (N, n) or 0.
    """
    xp = x @ A.T + bx
    n = A.shape[-1]
    if A.ndim == 2 and P.ndim >= 2:
        # one GEMM per product over the stacked rows instead of a batched matmul of tiny
        # matrices (4x faster for 10^4 runs of n = 2): X = P A^T, then X^T A^T = A P^T A^T,
        # which the symmetrization makes equal to sym(A P A^T)
        X = (P.reshape(-1, n) @ A.T).reshape(P.shape)
        Pp = (X.swapaxes(-1, -2).reshape(-1, n) @ A.T).reshape(P.shape) + Qd
    else:
        Pp = A @ P @ A.T + Qd
    return xp, symmetrize(Pp)


def shift_predict(xi: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0, *, source: int = 0):
    r"""Time update of a state augmented with its own past (block-shift transition), batched.

    :math:`\xi = \mathrm{col}\{\xi_0, \dots, \xi_L\}` (blocks of size n); the transition puts
    :math:`A\xi_{source} + b` on top and shifts every block down by one:
    :math:`\bar\xi = [A\xi_s + b;\ \xi_0;\ \dots;\ \xi_{L-1}]`, with the noise ``Qd`` in the top block only:

    .. math::

        \bar P_{00} = AP_{ss}A^T + Q_d, \quad \bar P_{0,j+1} = AP_{s,j}, \quad \bar P_{i+1,j+1} = P_{ij}.

    ``source = 0`` is the fading and protocol augmentation (Geng et al. 2017, (17)–(18); Geng et al.,
    (17)–(18)); ``source = d`` the pure-delay model :math:`x(t+1) = Ax(t-d) + \cdots` (Li, Li & Wang).
    ``P`` (N or 1, n_x, n_x) must be **exactly symmetric**; O(N n n_x²) copies and two GEMMs over the
    stacked runs instead of two batched (n_x × n_x) matmuls. Only the top block can come out
    asymmetric (rounding), so only it is symmetrized. Equals ``sym(Aa @ P @ Aa.T + Qa)`` to
    rounding (tested) and is exactly symmetric.
    """
    N, nxi = xi.shape
    n = A.shape[-1]
    s0, s1 = source * n, (source + 1) * n
    xi_p = np.empty_like(xi)
    xi_p[:, :n] = xi[:, s0:s1] @ A.T + bx
    xi_p[:, n:] = xi[:, : nxi - n]
    Np = P.shape[0]
    X = (P[:, :, s0:s1].reshape(-1, n) @ A.T).reshape(Np, nxi, n)  # P[:, :, s] A^T = (A P[:, s, :])^T
    P_p = np.empty_like(P)
    top = (X[:, s0:s1].swapaxes(-1, -2).reshape(-1, n) @ A.T).reshape(Np, n, n) + Qd
    P_p[:, :n, :n] = 0.5 * (top + top.swapaxes(-1, -2))
    P_p[:, n:, :n] = X[:, : nxi - n]
    P_p[:, :n, n:] = X[:, : nxi - n].swapaxes(-1, -2)
    P_p[:, n:, n:] = P[:, : nxi - n, : nxi - n]
    return xi_p, P_p


def sqrt_predict(x: np.ndarray, S: np.ndarray, A: np.ndarray, Qroot: np.ndarray, bx: Any = 0.0):
    r"""Square-root time update: :math:`\bar x = A\hat x + B^u u` and a factor of :math:`\bar P = APA^T + Q`.

    With :math:`P = SS^T` and :math:`Q = Q^{1/2}Q^{1/2\,T}`, the QR factorization

    .. math::

        \begin{bmatrix} S^T A^T \\ Q^{1/2\,T} \end{bmatrix} = \mathcal Q\,U, \qquad
        U^TU = A S S^T A^T + Q = \bar P,

    gives the new lower factor :math:`\bar S = U^T`, so :math:`\bar P = \bar S\bar S^T` is
    PSD by construction. ``x`` (N, n), ``S`` (N or 1, n, n); ``A`` (n, n); ``Qroot`` (n, q) with
    ``Qroot @ Qroot.T`` the noise covariance B Q B^T. Returns x̄ (N, n) and S̄ (N or 1, n, n),
    lower triangular, determined up to the signs of its columns (which do not change S̄S̄^T).
    """
    xp = x @ A.T + bx
    top = np.swapaxes(A @ S, -1, -2)
    bottom = np.broadcast_to(Qroot.T, top.shape[:-2] + Qroot.T.shape)
    U = qr_r(np.concatenate([top, bottom], axis=-2))
    return xp, np.swapaxes(U, -1, -2)


def _dense_shift(A: np.ndarray, nx: int, source: int) -> np.ndarray:
    """The (n_x, n_x) block-shift matrix with A acting on block ``source`` (square-root form)."""
    n = A.shape[-1]
    out = np.zeros((nx, nx))
    out[:n, source * n : (source + 1) * n] = A
    out[n:, : nx - n] = np.eye(nx - n)
    return out


def qr_r(M: np.ndarray) -> np.ndarray:
    """The R factor of the batched QR decomposition of ``M`` (``np.linalg.qr(M, mode="r")``; numpy's type
    stubs declare a QRResult for every mode)."""
    return cast(np.ndarray, np.linalg.qr(M, mode="r"))


def time_update(
    x: np.ndarray, P: np.ndarray | None, S: np.ndarray | None, tr: Transition, form: str, *, compiled: bool = False
):
    """The one predict of every Gaussian family: ``(x̄, P̄, S̄)`` from ``(x, P, S)`` and a :class:`Transition`.

    ``form`` is the covariance form (``"standard"``/``"joseph"`` propagate P, ``"square_root"`` S
    and P = S S^T). A fixed covariance (``tr.P_fixed``) is returned as is. ``compiled=True`` runs the
    compiled form (:func:`tobitkf.filters._kernels_core.time_update_runs`, equal to rounding) when numba
    imports and the case is covered (standard or Joseph form, one covariance per run), else this numpy code.
    """
    if compiled and P is not None and _compiled_covers(x, P, form) and tr.P_fixed is None and tr.source == 0:
        kern = _core_compiled_module()
        if kern is not None:
            xp, Pp = _compiled_time_update(kern, x, P, tr)
            return xp, Pp, None
    if tr.P_fixed is not None:
        return (_shift_mean(x, tr) if tr.shift else x @ tr.A.T + tr.b), tr.P_fixed, None
    if form == "square_root":
        assert S is not None, "the square-root form carries the factor S"
        nx = x.shape[-1]
        if tr.shift:
            A = _dense_shift(tr.A, nx, tr.source)
            G = tr.G if tr.G is not None else psd_sqrt(tr.Qd)
            Gd = np.zeros((nx, G.shape[-1]))
            Gd[: G.shape[0]] = G
            xp, Sp = sqrt_predict(x, S, A, Gd, 0.0)
            if not (np.isscalar(tr.b) and tr.b == 0.0):
                xp[:, : tr.A.shape[-1]] += tr.b
        else:
            G = tr.G if tr.G is not None else psd_sqrt(tr.Qd)
            xp, Sp = sqrt_predict(x, S, tr.A, G, tr.b)
        return xp, symmetrize(Sp @ np.swapaxes(Sp, -1, -2)), Sp
    assert P is not None, "the standard and Joseph forms carry P"
    if tr.shift:
        xp, Pp = shift_predict(x, P, tr.A, tr.Qd, tr.b, source=tr.source)
    else:
        xp, Pp = predict(x, P, tr.A, tr.Qd, tr.b)
    return xp, Pp, None


def _core_compiled_module():
    """The compiled shared step (:mod:`tobitkf.filters._kernels_core`), or None when the filters' kernels
    cannot be compiled (:func:`tobitkf.filters._backend.numba_available`)."""
    return _load_core() if _backend.numba_available() else None


@lru_cache(maxsize=1)
def _load_core():
    try:
        from . import _kernels_core
    except ImportError:
        return None
    return _kernels_core


def _compiled_covers(x: np.ndarray, P: np.ndarray | None, form: str) -> bool:
    """Whether the compiled shared step covers this case: the standard or Joseph form with one covariance
    per run (a covariance shared by the runs, P (1, n, n) for N > 1, stays on numpy, which keeps it shared)."""
    return form != "square_root" and P is not None and P.ndim == 3 and P.shape[0] == x.shape[0]


def _f64(a: Any) -> np.ndarray:
    """``a`` as a C-contiguous, writeable float64 array: the one array type the compiled step is compiled for
    (a read-only or strided input would compile another specialization, tens of seconds on a loaded machine)."""
    arr = np.ascontiguousarray(a, dtype=np.float64)
    return arr if arr.flags.writeable else arr.copy()


def _compiled_time_update(kern, x: np.ndarray, P: np.ndarray, tr: Transition):
    N, nx = x.shape
    A = _f64(tr.A)
    n = A.shape[0]
    b = tr.b
    if isinstance(b, np.ndarray) and b.ndim == 2:
        bvec = _f64(b)
    else:
        bvec = np.zeros((1, n)) if (np.isscalar(b) and b == 0.0) else _f64(np.broadcast_to(b, (1, n)))
    xp, Pp = np.empty((N, nx)), np.empty((N, nx, nx))
    kern.time_update_runs(_f64(x), _f64(P), A, _f64(tr.Qd), bvec, xp, Pp)
    return xp, Pp


_ONES: dict[int, np.ndarray] = {}
_NO_ROWS: dict[tuple[int, str], np.ndarray] = {}


def _compiled_measurement_update(kern, x: np.ndarray, P: np.ndarray, innov, valid, mp: MeasurementPrediction, joseph):
    N, nx = x.shape
    m = mp.H0.shape[0]
    if mp.scale is None:
        scale = _ONES.get(m)
        if scale is None:
            scale = _ONES[m] = np.ones((1, m))
    else:
        scale = _f64(mp.scale).reshape(-1, m)
    noise = _f64(mp.noise)
    diag = noise.ndim == 2
    if diag:
        noise = noise.reshape(noise.shape[0], m, 1)
    valid = _no_rows(m, "b") if valid is None else np.ascontiguousarray(valid, dtype=np.bool_)
    retained = _no_rows(m, "f") if mp.retained is None else _f64(mp.retained).reshape(-1, m)
    xn, Pn = np.empty((N, nx)), np.empty((N, nx, nx))
    K, Ree = np.empty((N, nx, m)), np.empty((N, m, m))
    kern.measurement_update_runs(
        _f64(x),
        _f64(P),
        _f64(innov),
        valid,
        _f64(mp.H0),
        scale,
        noise,
        bool(diag),
        retained,
        bool(joseph),
        xn,
        Pn,
        K,
        Ree,
    )
    return xn, Pn, None, K, Ree


def _no_rows(m: int, kind: str) -> np.ndarray:
    """An empty (0, m) array (bool for ``kind`` "b"): the kernels' "not given"."""
    arr = _NO_ROWS.get((m, kind))
    if arr is None:
        arr = _NO_ROWS[(m, kind)] = np.empty((0, m), dtype=bool if kind == "b" else np.float64)
    return arr


def _shift_mean(x: np.ndarray, tr: Transition) -> np.ndarray:
    n = tr.A.shape[-1]
    out = np.empty_like(x)
    out[:, :n] = x[:, tr.source * n : (tr.source + 1) * n] @ tr.A.T + tr.b
    out[:, n:] = x[:, : x.shape[-1] - n]
    return out


# --------------------------------------------------------------------------- the one measurement update


def _gain(Rxe: np.ndarray, Ree: np.ndarray) -> np.ndarray:
    """K = Rxe Ree^{-1} for m > 1, solved with Ree scaled to unit diagonal.

    Channels whose innovation variances differ by many orders of magnitude (a nearly
    surely censored channel beside an ordinary one: Ree_ll ~ 1e-77 next to 1) make Ree
    so badly scaled that an unscaled solve returns gain entries wrong by 1e50 and the
    Joseph form turns them into a covariance of 1e33. With D = diag(Ree)^{-1/2},
    K = Rxe D (D Ree D)^{-1} D, and D Ree D is well conditioned. Requires diag(Ree) > 0.
    """
    d = 1.0 / np.sqrt(np.diagonal(Ree, axis1=-2, axis2=-1))
    scaled = Ree * d[..., :, None] * d[..., None, :]
    return np.swapaxes(np.linalg.solve(scaled, np.swapaxes(Rxe * d[..., None, :], -1, -2)), -1, -2) * d[..., None, :]


def gain_update(
    x: np.ndarray,
    P: np.ndarray,
    innov: np.ndarray,
    Rxe: np.ndarray,
    Ree: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    H: np.ndarray | None = None,
    noise: np.ndarray | None = None,
):
    r"""Linear MMSE measurement update from its moments, batched, with per-run channel masks.

    .. math::

        K = R_{xe} R_{ee}^{-1}, \qquad \hat x = \bar x + K e, \qquad P = \bar P - K R_{xe}^T

    (Miller (3.32), (3.22), (3.42) corrected as in (3.55)). Channels where
    ``valid`` is False (missing, dropped, or with :math:`R_{ee,ll} = 0`, which includes a
    subnormal :math:`R_{ee,ll}` such as :math:`\gamma^2 C\bar P C^T` after γ underflowed) are removed
    from the update exactly: their rows and columns of :math:`R_{ee}` are replaced
    by the identity and their gain columns are zero.

    When ``H`` (N or 1, m, n) and ``noise`` (N or 1, m, m) are given, the covariance
    uses the Joseph form :math:`(I - KH)\bar P(I - KH)^T + K\,\mathrm{noise}\,K^T`.
    This is the procedural form (filterpy's ``update``); the families call
    :func:`measurement_update`, which computes the moments from a :class:`MeasurementPrediction`.

    Parameters
    ----------
    x : (N, n) ; P : (N or 1, n, n) ; innov : (N, m) ; Rxe : (N or 1, n, m) ; Ree : (N or 1, m, m)
    valid : (N, m) bool, optional

    Returns
    -------
    x, P, K
    """
    K, e, ok = _solve(Rxe, Ree, innov, valid)
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    if H is None:
        P_new = P - K @ np.swapaxes(Rxe, -1, -2)
    else:
        if ok is not None:
            H = H * ok[..., :, None]
        n = P.shape[-1]
        IKH = np.eye(n) - K @ H
        P_new = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ noise @ np.swapaxes(K, -1, -2)
    return x_new, symmetrize(P_new), K


def _solve(Rxe: np.ndarray, Ree: np.ndarray, innov: np.ndarray, valid: np.ndarray | None):
    """Masked gain: ``(K, e, ok)``; ``ok`` is None when every channel of every run takes part."""
    m = Ree.shape[-1]
    diag = Ree.diagonal(0, -2, -1)
    # a subnormal diagonal (e.g. a TKF channel 40 sigma into the censored side) counts as 0:
    # LAPACK's solve takes its reciprocal, which overflows and turns the whole gain into NaN
    degenerate = ~(diag > _TINY)
    if valid is not None and valid.all():
        valid = None  # every channel takes part: the unmasked solve gives the same gain
    if valid is None and not degenerate.any():
        K = Rxe / Ree if m == 1 else _gain(Rxe, Ree)
        return K, innov, None
    ok = ~degenerate if valid is None else (valid & ~degenerate)
    if m == 1:
        K = Rxe * ok[..., None, :] / np.where(ok, diag, 1.0)[..., None, :]
    else:
        pair = ok[..., :, None] & ok[..., None, :]
        K = _gain(Rxe * ok[..., None, :], np.where(pair, Ree, np.eye(m)))
    return K, np.where(ok, innov, 0.0), ok


def _psd_root(M: np.ndarray) -> np.ndarray:
    return psd_sqrt(M)


def _solve_upper(U: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with U X = B for upper-triangular U (..., m, m), B (..., m, r): back substitution over m."""
    m = U.shape[-1]
    X = np.empty(np.broadcast_shapes(U.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(m - 1, -1, -1):
        acc = B[..., i, :] - np.einsum("...j,...jr->...r", U[..., i, i + 1 :], X[..., i + 1 :, :])
        X[..., i, :] = acc / U[..., i, i, None]
    return X


def sqrt_update(
    x: np.ndarray,
    S: np.ndarray,
    innov: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    R_root: np.ndarray | None = None,
):
    r"""Square-root (array) form of the Kalman measurement update, batched, with per-run channel masks.

    With the prior factor :math:`\bar P = \bar S\bar S^T` and :math:`R = R^{1/2}R^{1/2\,T}`,
    one QR factorization of the pre-array

    .. math::

        \begin{bmatrix} R^{1/2\,T} & 0 \\ \bar S^T H^T & \bar S^T \end{bmatrix}
        = \mathcal Q \begin{bmatrix} U_{11} & U_{12} \\ 0 & U_{22} \end{bmatrix}

    gives, by comparing :math:`M^TM = U^TU`,
    :math:`U_{11}^TU_{11} = R_{ee} = H\bar PH^T + R`, :math:`U_{12}^TU_{11} = \bar PH^T` and
    :math:`U_{22}^TU_{22} = \bar P - \bar PH^TR_{ee}^{-1}H\bar P = P`. Hence
    :math:`K = \bar PH^TR_{ee}^{-1} = U_{12}^TU_{11}^{-T}` (one triangular solve,
    :math:`K^T = U_{11}^{-1}U_{12}`), :math:`\hat x = \bar x + Ke` and the new factor
    :math:`S = U_{22}^T`. The covariance :math:`P = SS^T` is PSD by construction. Cost per
    run: a QR of an (m+n) x (m+n) matrix, about :math:`\tfrac43(m+n)^3` flops, against
    :math:`\approx 2n^2m + nm^2` for the standard update. The form is not in the sources; it is
    the array form of the square-root filter (Kaminski, Bryson & Schmidt 1971; Bierman 1977).

    Channels are left out exactly as in :func:`gain_update`: a channel that is not
    ``valid`` or whose :math:`R_{ee,ll} = (H\bar P H^T)_{ll} + R_{ll}` is not above the
    smallest normal number gets a zero row of H, a unit noise decoupled from the other
    channels (its rows and columns of R replaced by the identity) and a zero innovation;
    its column of the pre-array is then a unit vector orthogonal to the others, so its gain
    column is exactly zero and the other channels' update is that of the reduced model.

    Parameters
    ----------
    x : (N, n) ; S : (N or 1, n, n) prior factor ; innov : (N, m)
    H : (N or 1, m, n) ; R : (N or 1, m, m) measurement-noise covariance (PSD)
    valid : (N, m) bool, optional
    R_root : (N or 1, m, m), optional
        A root of ``R`` to use when no channel is left out (saves a factorization).

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n) symmetric ; S : (N or 1, n, n) ; K : (N or 1, n, m)
    """
    m, n = H.shape[-2], H.shape[-1]
    HS = H @ S
    Rdiag = np.diagonal(R, axis1=-2, axis2=-1)
    diag = np.einsum("...ij,...ij->...i", HS, HS) + Rdiag
    degenerate = ~(diag > _TINY)
    e = innov
    if valid is None and not degenerate.any():
        root = psd_sqrt(R) if R_root is None else R_root
    else:
        ok = ~degenerate if valid is None else (valid & ~degenerate)
        HS = HS * ok[..., :, None]
        e = np.where(ok, innov, 0.0)
        off_diagonal = np.count_nonzero(R - Rdiag[..., :, None] * np.eye(m)) > 0
        if off_diagonal:
            pair = ok[..., :, None] & ok[..., None, :]
            root = psd_sqrt(np.where(pair, R, np.eye(m)))
        else:
            root = np.sqrt(np.where(ok, Rdiag, 1.0))[..., :, None] * np.eye(m)
    batch = np.broadcast_shapes(HS.shape[:-2], S.shape[:-2], root.shape[:-2])
    M = np.zeros(batch + (m + n, m + n))
    M[..., :m, :m] = np.swapaxes(root, -1, -2)
    M[..., m:, :m] = np.swapaxes(HS, -1, -2)
    M[..., m:, m:] = np.swapaxes(S, -1, -2)
    U = qr_r(M)
    K = np.swapaxes(_solve_upper(U[..., :m, :m], U[..., :m, m:]), -1, -2)
    S_new = np.swapaxes(U[..., m:, m:], -1, -2)
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    return x_new, symmetrize(S_new @ np.swapaxes(S_new, -1, -2)), S_new, K


def _moments(P: np.ndarray, mp: MeasurementPrediction):
    """``(R_xe (Np, n_x, m), R_ee (Np', m, m), P H0^T)`` with GEMMs over the stacked runs."""
    H0 = mp.H0
    m, nx = H0.shape
    Np = P.shape[0]
    # P H0^T for every run as one GEMM over the stacked rows (P symmetric): (Np, nx, m)
    PH = (P.reshape(Np * nx, nx) @ H0.T).reshape(Np, nx, m)
    HPH = (PH.swapaxes(-1, -2).reshape(Np * m, nx) @ H0.T).reshape(Np, m, m)
    s = mp.scale
    if s is None:
        Rxe, Ree = PH, HPH
    else:
        Rxe = PH * s[:, None, :]
        Ree = HPH * s[:, :, None] * s[:, None, :]
    noise = mp.noise
    if noise.ndim == Ree.ndim - 1:  # diagonal noise (N or 1, m)
        Ree = Ree + (noise[..., :, None] if m == 1 else noise[..., :, None] * np.eye(m))
    else:
        Ree = Ree + noise
    return Rxe, Ree, PH


def measurement_update(
    x: np.ndarray,
    P: np.ndarray | None,
    S: np.ndarray | None,
    y: np.ndarray,
    mp: MeasurementPrediction,
    form: str = "standard",
    *,
    compiled: bool = False,
):
    r"""The one measurement update of every Gaussian family, in the covariance form ``form``.

    Computes :math:`R_{xe} = \bar PH^T`, :math:`R_{ee} = H\bar PH^T + N` from the family's
    :class:`MeasurementPrediction` (H = diag(scale) H0), the masked gain (channels that are not
    ``valid``, whose reading is NaN, or whose :math:`R_{ee,ll}` is not above the smallest normal
    number are left out exactly), and the posterior

    * ``"standard"``: :math:`P = \bar P - KR_{xe}^T`;
    * ``"joseph"``: :math:`(I - KH)\bar P(I - KH)^T + KNK^T`, applied as
      :math:`M = \bar P - KR_{xe}^T`, :math:`P = M - (MH^T - KN)K^T` (rank-m products over the
      stacked runs instead of dense (n_x × n_x) products; equal to rounding, tested);
    * ``"square_root"``: the QR array form of :func:`sqrt_update` on the factor ``S``;

    plus :math:`KVK^T` when the family retains a variance V (``mp.retained``); or, with a fixed gain (``mp.gain``), :math:`\hat x = \bar x + K(y - \hat y)` and the covariance
    unchanged.

    Parameters
    ----------
    x : (N, n_x) ; P : (N or 1, n_x, n_x) ; S : (N or 1, n_x, n_x) or None ; y : (N, m)
    mp : MeasurementPrediction
    form : {"standard", "joseph", "square_root"}
    compiled : bool, default False
        Run the compiled form (:func:`tobitkf.filters._kernels_core.measurement_update_runs`, equal to
        rounding) when numba imports and the case is covered (the standard or Joseph form, one covariance
        per run, no fixed gain), else this numpy code.

    Returns
    -------
    x : (N, n_x) ; P ; S (or None) ; K : gain ; Ree : innovation covariance (None for a fixed gain)
    """
    obs = y if mp.observed is None else mp.observed
    innov = obs - mp.expected
    missing = np.isnan(innov)
    valid = mp.valid
    if missing.any():
        valid = ~missing if valid is None else (valid & ~missing)
        innov = np.where(missing, 0.0, innov)
    if mp.gain is not None:
        e = innov if valid is None else np.where(valid, innov, 0.0)
        return x + e @ mp.gain.T, (P if mp.posterior_cov is None else mp.posterior_cov), S, mp.gain, None
    if compiled and _compiled_covers(x, P, form) and mp.H0.ndim == 2:
        kern = _core_compiled_module()
        if kern is not None:
            assert P is not None
            return _compiled_measurement_update(kern, x, P, innov, valid, mp, form == "joseph")
    if form == "square_root":
        H = mp.H0[None] if mp.scale is None else mp.H0[None] * mp.scale[:, :, None]
        noise = mp.noise
        m = mp.H0.shape[0]
        if noise.ndim == 2:
            nz = np.maximum(noise, 0.0)
            R = nz[..., :, None] * np.eye(m)
            root = np.sqrt(nz)[..., :, None] * np.eye(m)
        else:
            R = noise
            root = None
        assert S is not None, "the square-root form carries the factor S"
        xn, Pn, Sn, K = sqrt_update(x, S, innov, H, R, valid, R_root=root)
        if mp.retained is not None:
            # P + K V K^T as the factor of [S, K V^{1/2}]: one more QR, PSD by construction
            KV = K * np.sqrt(np.maximum(mp.retained, 0.0))[..., None, :]
            Sb = np.broadcast_to(Sn, KV.shape[:-2] + Sn.shape[-2:])
            U = qr_r(np.concatenate([np.swapaxes(Sb, -1, -2), np.swapaxes(KV, -1, -2)], axis=-2))
            Sn = np.swapaxes(U, -1, -2)
            Pn = symmetrize(Sn @ np.swapaxes(Sn, -1, -2))
        return xn, Pn, Sn, K, None
    assert P is not None, "the standard and Joseph forms carry P"
    Rxe, Ree, _ = _moments(P, mp)
    K, e, ok = _solve(Rxe, Ree, innov, valid)
    if K.shape[-1] == 1:  # one channel: K e and K R_xe^T are plain products (the same numbers, no einsum)
        x_new = x + K[..., 0] * e
        M = P - K * Rxe.swapaxes(-1, -2)
    else:
        x_new = x + np.einsum("...ij,...j->...i", K, e)
        M = P - K @ Rxe.swapaxes(-1, -2)
    if form == "joseph":
        nx = x.shape[-1]
        Nk = K.shape[0]
        MH = (M.reshape(Nk * nx, nx) @ mp.H0.T).reshape(Nk, nx, -1)  # M H0^T
        if mp.scale is not None:
            MH = MH * mp.scale[:, None, :]
        noise = mp.noise
        KN = K * noise[..., None, :] if noise.ndim == K.ndim - 1 else K @ noise
        M = M - (MH - KN) @ K.swapaxes(-1, -2)
    if mp.retained is not None:
        M = M + (K * mp.retained[..., None, :]) @ K.swapaxes(-1, -2)
    return x_new, symmetrize(M), None, K, Ree


# --------------------------------------------------------------------------- boundary checks


def prepare_measurements(
    y: Any, m: int, name: str = "y", *, allow_nan: bool = True
) -> tuple[np.ndarray, tuple[int, ...]]:
    """Validate ``y`` of shape ``(..., T, m)`` and flatten the batch axes.

    NaN entries are allowed (missing samples) unless ``allow_nan`` is False; infinities are not, nor are
    readings beyond :data:`~tobitkf._validation.READING_LIMIT` in magnitude (their squares overflow). The
    masked entries of a numpy masked array are missing (NaN).

    Returns
    -------
    y2 : (N, T, m) ndarray
    batch_shape : tuple
        The leading shape to restore on outputs (``()`` for a single ``(T, m)`` record).
    """
    if isinstance(y, np.ndarray) and not y.flags.c_contiguous:
        # a broadcast or strided view: the flat layout and the compiled loops copy it. Refused before its values
        # are read (a broadcast of 10^10 readings takes minutes to scan) or converted (a copy)
        check_memory(8 * y.size, name, f"the readings of shape {y.shape} as one contiguous array")
    arr = as_float_array(y, name, allow_nan=allow_nan)
    check_scale(arr, name)
    if arr.ndim < 2:
        raise ShapeError(
            f"{name}: expected (..., T, {m}) (for one scalar channel pass y[:, None]), got shape {arr.shape}"
        )
    if arr.shape[-1] != m:
        raise ShapeError(f"{name}: expected last axis of length m={m} (measurement channels), got shape {arr.shape}")
    if arr.shape[-2] < 1:
        raise ShapeError(f"{name}: expected at least one time step, got shape {arr.shape}")
    batch = arr.shape[:-2]
    if 0 in batch:
        raise ShapeError(f"{name}: expected at least one run (leading axes of positive length), got shape {arr.shape}")
    return arr.reshape((-1,) + arr.shape[-2:]), batch


def prepare_inputs(system, u: Any, runs: int, steps: int) -> np.ndarray | None:
    """Validate control inputs ``(T, p)`` or ``(..., T, p)`` and broadcast to ``(N, T, p)``."""
    if u is None:
        return None
    arr = system.check_inputs(u, steps)
    if arr.ndim == 2:
        return np.broadcast_to(arr, (runs, steps, arr.shape[-1]))
    flat = arr.reshape((-1,) + arr.shape[-2:])
    if flat.shape[0] != runs:
        raise ShapeError(f"u: expected (T, p) or the batch shape of y, got {arr.shape}")
    return flat


def check_prior(system, x0: Any, P0: Any, runs: int, batch: tuple[int, ...] | None = None):
    """Initial (x0, P0) broadcast to ``(N, n)``, ``(N, n, n)``; defaults from the system.

    With ``batch`` (the leading shape of ``y``, N = prod(batch)), per-run priors of shape
    ``batch + (n,)`` / ``batch + (n, n)`` (or broadcastable to them) are accepted.
    """
    n = system.n
    x = system.x0 if x0 is None else as_float_array(x0, "x0")
    P = system.P0 if P0 is None else as_float_array(P0, "P0")
    if P0 is not None and P.ndim >= 2:
        check_psd(P, "P0")
    if x.shape[-1:] != (n,) or P.shape[-2:] != (n, n):
        raise ShapeError(f"x0/P0: expected (..., {n}) and (..., {n}, {n}), got {x.shape} and {P.shape}")
    try:
        if batch is not None:  # priors laid out like y's leading axes; else flat (N, ...) as before
            try:
                x = np.broadcast_to(x, tuple(batch) + (n,)).reshape(runs, n)
            except ValueError:
                pass
            try:
                P = np.broadcast_to(P, tuple(batch) + (n, n)).reshape(runs, n, n)
            except ValueError:
                pass
        x = np.broadcast_to(x, (runs, n)).copy()
        P = np.broadcast_to(P, (runs, n, n)).copy()
    except ValueError:
        raise ShapeError(f"x0/P0: batch shapes {x.shape[:-1]} / {P.shape[:-2]} do not match {runs} runs") from None
    return x, P


def check_keywords(options: dict[str, Any], allowed: dict[str, tuple]) -> None:
    """Check each option value against its allowed set."""
    for key, value in options.items():
        if key not in allowed:
            raise TypeError(f"unexpected keyword argument {key!r}")
        check_option(value, key, allowed[key])  # of the same kind: 1.0 is not True


def process_roots(system):
    r"""The roots :math:`G_k` (n, q), :math:`G_kG_k^T = B_kQ_kB_k^T`, of the process noise, as a function of k.

    :math:`B_k Q_k^{1/2}` with :math:`Q_k^{1/2}` from :func:`psd_sqrt` (so a singular Q,
    e.g. one with zero rows, is fine); factored once when Q and B do not vary with k.
    """

    def root(k: int) -> np.ndarray:
        r = psd_sqrt(system.Q.at(k))
        return r if system.B is None else system.B.at(k) @ r

    if not system.Q.varying and (system.B is None or not system.B.varying):
        fixed = root(0)
        return lambda k: fixed
    return root


# --------------------------------------------------------------------------- outputs


def parse_outputs(outputs: Any) -> frozenset[str]:
    """The per-step outputs a ``filter`` call records: ``"all"`` (default: mean, cov, pred_mean,
    pred_cov, extras), ``"last"`` (only the final state), or names from :data:`OUTPUTS`."""
    if outputs is None or (isinstance(outputs, str) and outputs == "all"):
        return frozenset(("mean", "cov", "pred_mean", "pred_cov", "extras"))
    if isinstance(outputs, str) and outputs == "last":
        return frozenset()
    if isinstance(outputs, str):
        names: tuple[Any, ...] = (outputs,)
    else:
        try:
            names = tuple(outputs)
        except TypeError:
            raise ValidationError(
                f"outputs: expected 'all', 'last', a name or a list of names from {', '.join(OUTPUTS)}, got "
                f"{outputs!r} ({type(outputs).__name__})"
            ) from None
    bad = [o for o in names if not isinstance(o, str) or o not in OUTPUTS]
    if bad:
        raise ValidationError(f"outputs: expected 'all', 'last' or names from {', '.join(OUTPUTS)}, got {bad[0]!r}")
    return frozenset(names)


class _Recorder:
    """Per-step outputs stored time-major (T, N, ...), each step one contiguous block; returned as
    ``batch + (T, ...)`` views. A covariance shared by the runs (leading axis 1) is stored once."""

    def __init__(self, outputs: frozenset[str], T: int, batch: tuple[int, ...], n: int):
        self.want, self.T, self.batch, self.n = outputs, T, batch, n
        self.arrays: dict[str, np.ndarray] = {}
        self.extras: dict[str, np.ndarray] = {}
        self.shared: dict[str, bool] = {}

    def _put(self, store: dict, key: str, i: int, value: Any) -> None:
        arr = store.get(key)
        if arr is None:
            value = np.asarray(value)
            arr = store[key] = np.empty((self.T,) + value.shape, dtype=value.dtype)
        arr[i] = value

    def record(self, i: int, xp, Pp, x, P, extras: Mapping[str, Any] | None) -> None:
        n, w = self.n, self.want
        if "mean" in w:
            self._put(self.arrays, "mean", i, x[:, :n])
        if "pred_mean" in w and xp is not None:
            self._put(self.arrays, "pred_mean", i, xp[:, :n])
        for key, cov in (("cov", P), ("pred_cov", Pp)):
            if key in w and cov is not None:
                if key in self.arrays and self.arrays[key].shape[1] != cov.shape[0]:
                    # the runs stopped sharing one covariance: widen the store
                    old = self.arrays[key]
                    self.arrays[key] = np.broadcast_to(old, (self.T, cov.shape[0]) + old.shape[2:]).copy()
                self._put(self.arrays, key, i, cov[:, :n, :n])
        if "var" in w and P is not None:
            if "var" in self.arrays and self.arrays["var"].shape[1] != P.shape[0]:
                old = self.arrays["var"]
                self.arrays["var"] = np.broadcast_to(old, (self.T, P.shape[0]) + old.shape[2:]).copy()
            self._put(self.arrays, "var", i, np.diagonal(P[:, :n, :n], axis1=-2, axis2=-1))
        if "extras" in w and extras:
            for key, val in extras.items():
                self._put(self.extras, key, i, val)

    def _out(self, arr: np.ndarray, runs: int) -> np.ndarray:
        if arr.shape[1] == 1 and runs != 1:  # shared by the runs: one copy, broadcast read-only
            return np.broadcast_to(np.moveaxis(arr, 0, 1)[0], self.batch + arr.shape[:1] + arr.shape[2:])
        return np.moveaxis(arr, 0, 1).reshape(self.batch + arr.shape[:1] + arr.shape[2:])

    def result(self, runs: int, times: np.ndarray, final: FilterState | None) -> FilterResult:
        a = {k: self._out(v, runs) for k, v in self.arrays.items()}
        extras = {
            k: self._out(v, runs) if v.ndim >= 2 and v.shape[1] in (1, runs) else v for k, v in self.extras.items()
        }
        return FilterResult(
            mean=a.get("mean"),
            cov=a.get("cov"),
            pred_mean=a.get("pred_mean"),
            pred_cov=a.get("pred_cov"),
            extras=extras,
            times=times,
            var=a.get("var"),
            final=final,
        )


# --------------------------------------------------------------------------- the estimator base and the loop


class Estimator:
    r"""Base of every estimator: the online API (:meth:`init`, :meth:`step`) and the one time loop
    (:meth:`_run`, behind each family's ``filter``).

    An estimator implements ``_initial(N, x0, P0, batch)`` → ``(x, P, carry)`` (the prior) and
    ``_step_arrays(k, x, P, S, carry, y, u, options)`` → ``(x, P, S, carry, x̄, P̄, extras)`` (one
    reading, batched over N runs, no validation inside). :class:`GaussianFilter` implements the
    second from three smaller hooks shared by every Gaussian-update family; estimators that are not
    Gaussian updates (the particle filter, the H∞ filter, the tracker) implement it directly and get
    the same ``init``/``step``/``filter`` and the same recorded outputs.
    """

    #: dimension of the reported state (set by the family)
    n: int
    #: number of measurement channels (set by the family)
    m: int
    #: time index of the prior (0: x_0 prior, y_1 first reading)
    k0: int = 0
    #: covariance form
    covariance_update: str = "standard"
    #: name used in messages
    _name: str = "estimator"
    #: per-step options ``step``/``update`` accept (e.g. ``lower``/``upper`` for a steered limit)
    _step_options: tuple[str, ...] = ()
    #: whether a reading may be NaN (missing); False for the estimators whose covariances do not depend
    #: on the data (the delay family) or that have no update to skip (the H-infinity filter)
    _allow_missing: bool = True
    _missing_reason: str = ""  # why a family that refuses NaN readings does (appended to the error)

    def _initial(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...]):  # pragma: no cover - abstract
        raise NotImplementedError

    def _check_record(self, y2: np.ndarray, u2: np.ndarray | None, k0: int, name: str = "y") -> None:
        """Checks of a whole record at the boundary (limits, horizon); families extend."""

    def _prepare_inputs(self, u: Any, N: int, T: int, batch: tuple[int, ...]) -> np.ndarray | None:
        if u is None:
            return None
        raise ValidationError(f"u: {self._name} takes no control input")

    def _compiled_filter(self, y2, u2, state: FilterState, want: frozenset[str], batch) -> FilterResult | None:
        """A compiled implementation of the loop, or None (the numpy loop runs)."""
        return None

    def _compiled_filter_with(self, y2, u2, state: FilterState, want: frozenset[str], batch, step_options):
        """:meth:`_compiled_filter` for a loop run with ``step_options`` (a family whose kernel depends on
        them overrides this; by default they are not looked at)."""
        return self._compiled_filter(y2, u2, state, want, batch)

    def _compiled_core(self) -> bool:
        """Whether the shared predict and update run compiled (:mod:`tobitkf.filters._kernels_core`):
        numba imports and the estimator's ``backend`` (``"auto"`` for the families without the option) is not
        ``"numpy"``. Decided once per estimator."""
        cached = self.__dict__.get("_core_compiled")
        if cached is None:
            cached = self._core_compiled = (
                getattr(self, "backend", "auto") != "numpy" and _core_compiled_module() is not None
            )
        return cached

    def _compiled_online_step(self, state: FilterState, y: np.ndarray, u, options) -> FilterState | None:
        """A compiled single step, or None (the numpy step runs)."""
        return None

    def init(self, batch_shape: Any = (), *, x0: Any = None, P0: Any = None) -> FilterState:
        """The prior as a :class:`FilterState` for ``batch_shape`` runs (``()`` for one run).

        ``x0``/``P0`` override the model's prior (``(n,)``/``(n, n)`` or laid out like the batch).
        """
        batch = _check_batch(batch_shape)
        N = math.prod(batch)  # a Python int: no overflow before the memory check
        check_memory(N * self._bytes_per_run(), "batch_shape", f"the state of {plural(N, 'run')} of this {self._name}")
        x, P, carry = self._initial(N, x0, P0, batch)
        S = None
        if self.covariance_update == "square_root" and P is not None:
            S = psd_sqrt(P)
        return mark_trusted(self, FilterState(k=self.k0, batch_shape=batch, x=x, P=P, n=self.n, S=S, carry=carry))

    def _bytes_per_run(self) -> int:
        """Bytes the state of one run takes (its mean and covariance, and the factor in the square-root form);
        a family that carries more per run (particles) says so."""
        nx = self._state_dim()
        return 8 * (nx + nx * nx * (2 if self.covariance_update == "square_root" else 1))

    def _check_state(self, state: Any) -> FilterState:
        """``state`` as it may enter this estimator: a state this estimator made passes at the cost of two
        dictionary look-ups (:func:`is_trusted`); any other (unpickled, copied, ``replace``-d, built by hand or
        made by another estimator) gets the full check of :func:`check_state` once."""
        if is_trusted(self, state):
            return state
        return check_state(self, state)

    def _state_dim(self) -> int:
        return self.n

    def _refused_nan(self, err: ValidationError) -> ValidationError:
        """The NaN refusal ``err`` with the family's reason appended."""
        if self._missing_reason and "NaN" in str(err):
            return ValidationError(f"{err} ({self._missing_reason})")
        return err

    def _reading(self, state: FilterState, y: Any, name: str = "y") -> np.ndarray:
        # The online step of one run with a float64 reading of shape (m,) (a row of a record): the verdict of
        # the general path below in Python floats, without its conversion, broadcast and checks' calls (in-process
        # A/B, thread CPU time, median of 15 x 20 000 calls, load ~1.1: 1.0 -> 0.56 µs of a 8-16 µs step); anything
        # else, or a reading it would refuse, takes the general path, which raises its errors.
        if type(y) is np.ndarray and y.dtype is _F64 and y.ndim == 1 and not state.batch_shape:
            vals = y.tolist()
            if (
                len(vals) == self.m
                and (not any(map(math.isinf, vals)) if self._allow_missing else all(map(math.isfinite, vals)))
                and reading_in_scale(vals)
            ):
                return y[None]
        try:
            arr = as_float_array(y, name, allow_nan=self._allow_missing)
        except ValidationError as err:
            raise self._refused_nan(err) from None
        check_scale(arr, name)
        m = self.m
        want = state.batch_shape + (m,)
        if arr.shape != want:
            try:
                arr = np.broadcast_to(arr, want)
            except ValueError:
                raise ShapeError(
                    f"{name}: expected one reading of shape {want} (batch_shape + (m,)), got {arr.shape}"
                ) from None
        return arr.reshape(-1, m) if m else arr.reshape(state.runs, 0)  # (runs, m): -1 spares the product

    def _step_input(self, state: FilterState, u: Any) -> np.ndarray | None:
        if u is None:
            return None
        raise ValidationError(f"u: {self._name} takes no control input")

    def _check_options(self, options: Mapping[str, Any]) -> dict[str, Any]:
        for key in options:
            if key not in self._step_options:
                raise TypeError(f"unexpected keyword argument {key!r}")
        return dict(options)

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (m,)``); NaN = missing channel.

        Equal to one row of :meth:`filter` (tested to 1e-12 on the numpy path). Returns the new state
        (``state.k`` advanced by one); the old one is unchanged.

        Warns (``RuntimeWarning``) as :meth:`filter` does: when the covariance stops being finite, and, for a
        Gaussian-update family, once per lineage of states when the updates grow far larger than the
        filter's own covariance allows (a diverging filter: :mod:`tobitkf.filters._online_check`, every
        8th step), naming the step and the remedy.
        """
        state = self._check_state(state)
        if state.carry.get("_predicted"):
            raise _prediction_to_step()
        yk = self._reading(state, y)
        if u is None and not options:  # a plain call: no input to form, no keyword to vet
            uk, opts = None, self._prepare_step_options(state, options)
        else:
            uk = self._step_input(state, u)
            opts = self._prepare_step_options(state, self._check_options(options))
        self._check_reading(state, yk, opts)
        fast = self._compiled_online_step(state, yk, uk, opts)
        if fast is not None:
            # the check's own test, without its call, for the common case: a step it does not look at whose carry
            # (and so the check's memory) passed through unchanged
            if (fast.k % _online_check.STRIDE == 0 or fast.carry is not state.carry) and isinstance(
                self, GaussianFilter
            ):
                fast = _online_check.check_step(self, state, fast, uk)
            return mark_trusted(self, fast)
        k = state.k + 1
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is detected and reported below
            x, P, S, carry, xp, Pp, extras = self._step_arrays(k, state.x, state.P, state.S, state.carry, yk, uk, opts)
        x, carry = _divergence_check(
            self._name, x, P if S is None else S, k, self.covariance_update, carry, state.carry
        )
        new = step_state(k, state.batch_shape, x, P, self.n, S, carry, extras or None)
        if isinstance(self, GaussianFilter):
            new = _online_check.check_step(self, state, new, uk, xp, Pp)
        return mark_trusted(self, new)

    def _prepare_step_options(self, state: FilterState, options: dict[str, Any]) -> dict[str, Any]:
        return options

    def _check_reading(self, state: FilterState, y: np.ndarray, options: Mapping[str, Any]) -> None:
        """Checks of one reading (N, m) of ``step`` beyond its shape (e.g. within the censoring limits): those of
        ``filter`` (:meth:`_check_record` of a record of one step), so that ``step`` and ``filter`` accept the
        same readings; a step that sets its own limits (``lower``/``upper``) is checked by its family."""
        if options and (options.get("lower") is not None or options.get("upper") is not None):
            return
        self._check_record(y[:, None], None, state.k)

    def _run(
        self,
        y: Any,
        u: Any = None,
        x0: Any = None,
        P0: Any = None,
        *,
        outputs: Any = "all",
        state: FilterState | None = None,
        step_options: Mapping[str, Any] | None = None,
        step_data: Mapping[str, np.ndarray] | None = None,
        name: str = "y",
    ) -> FilterResult:
        """The one time loop: validate once, then :meth:`_step_arrays` for each reading (with the same
        ``step_options`` at every step, e.g. ``latent=True`` for a sensor that censors in the loop, and
        row ``i`` of each ``step_data`` array (N, T, ...), e.g. a censoring indicator)."""
        want = parse_outputs(outputs)
        y2, batch = self._prepare_record(y, name)
        N, T, _ = y2.shape
        if state is not None:
            if x0 is not None or P0 is not None:
                raise ValidationError("state: give either a state to continue from or x0/P0, not both")
            state = self._check_state(state)
            if state.carry.get("_predicted"):
                raise _prediction_to_step("filter")
            if state.batch_shape != batch and state.runs != N:
                raise ShapeError(f"state: batch shape {state.batch_shape} does not match y's {batch}")
        else:
            state = self.init(batch, x0=x0, P0=P0)
        u2 = self._prepare_inputs(u, N, T, batch)
        self._check_record(y2, u2, state.k, name)
        _check_output_memory(want, N, T, self.n, name)
        fast = self._compiled_filter_with(y2, u2, state, want, batch, step_options)
        if fast is None:
            rec = _Recorder(want, T, batch, self.n)
            x, P, S, carry = state.x, state.P, state.S, state.carry
            with np.errstate(over="ignore", invalid="ignore"):  # an overflow is detected and reported below
                fast = self._loop(rec, state, x, P, S, carry, y2, u2, step_options, step_data, batch, N, T)
        if fast.final is not None:
            mark_trusted(self, fast.final)
        if isinstance(self, GaussianFilter):
            _correction_check(self, fast)
        return fast

    def _loop(self, rec, state, x, P, S, carry, y2, u2, step_options, step_data, batch, N, T):
        first_bad = None
        for i in range(T):
            k = state.k + i + 1
            opts = step_options
            if step_data:
                opts = dict(step_options or {})
                opts.update({key: val[:, i] for key, val in step_data.items()})
            x, P, S, carry, xp, Pp, extras = self._step_arrays(
                k, x, P, S, carry, y2[:, i], None if u2 is None else u2[:, i], opts
            )
            if first_bad is None:
                first_bad = _first_nonfinite(P if S is None else S, k)
            if first_bad is not None:
                x = _poison_diverged(x, P if S is None else S)
            rec.record(i, xp, Pp, x, P, extras)
        if first_bad is not None:
            _divergence_warning(self._name, first_bad, self.covariance_update)
        final = FilterState(k=state.k + T, batch_shape=batch, x=x, P=P, n=self.n, S=S, carry=carry)
        times = np.arange(state.k + 1, state.k + T + 1)
        return rec.result(N, times, final)

    def _prepare_record(self, y: Any, name: str = "y") -> tuple[np.ndarray, tuple[int, ...]]:
        try:
            return prepare_measurements(y, self.m, name, allow_nan=self._allow_missing)
        except ValidationError as err:
            raise self._refused_nan(err) from None

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):  # pragma: no cover - abstract
        raise NotImplementedError


class GaussianFilter(Estimator):
    r"""Base of every Gaussian-update family: the shared predict and update behind the online API.

    A family implements three hooks on arrays (batched over N runs, no validation inside):

    * ``_initial(N, x0, P0)`` → ``(x, P, carry)``: the prior;
    * ``_transition(k, u, carry)`` → :class:`Transition` from k-1 to k;
    * ``_measurement(k, x̄, P̄, y, u, carry, **step_options)`` → ``(MeasurementPrediction, carry)``;

    and optionally ``_extras(k, x̄, P̄, x, P, mp, K, Ree, options)`` for per-step quantities that need
    the posterior. Everything else (the predict, the update in each covariance form, the masking, the
    divergence check, the recording of outputs, :meth:`init`, :meth:`predict`, :meth:`update`,
    :meth:`step` and :meth:`filter`) is shared.
    """

    _name = "filter"

    def _transition(self, k: int, u: np.ndarray | None, carry: Mapping[str, Any]) -> Transition:  # pragma: no cover
        raise NotImplementedError

    def _measurement(
        self,
        k: int,
        xp: np.ndarray,
        Pp: np.ndarray | None,
        y: np.ndarray,
        u: np.ndarray | None,
        carry: Mapping[str, Any],
        **options: Any,
    ):  # pragma: no cover - abstract
        raise NotImplementedError

    def _extras(self, k: int, xp, Pp, x, P, mp: MeasurementPrediction, K, Ree, options) -> dict[str, Any] | None:
        return mp.extras

    def _update_arrays(self, k: int, xp, Pp, Sp, y, u, carry, options):
        """The measurement update on arrays: ``(x, P, S, carry, extras)`` from the prediction. The Kalman-type
        update of :meth:`_measurement`'s moments; an assumed-density family replaces it by its projection."""
        mp, carry = self._measurement(k, xp, Pp, y, u, carry, **options)
        xn, Pn, Sn, K, Ree = measurement_update(
            xp, Pp, Sp, y, mp, self.covariance_update, compiled=self._compiled_core()
        )
        return xn, Pn, Sn, carry, self._extras(k, xp, Pp, xn, Pn, mp, K, Ree, options)

    def _check_update_reading(self, state: FilterState, y: np.ndarray, options: Mapping[str, Any]) -> None:
        """Checks of :meth:`update`'s reading (N, m) beyond its shape: those of ``filter`` for the reading of
        time ``state.k`` (as :meth:`~Estimator._check_reading`)."""
        if options and (options.get("lower") is not None or options.get("upper") is not None):
            return
        self._check_record(y[:, None], None, state.k - 1)

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):
        """One predict + update on arrays: returns ``(x, P, S, carry, x̄, P̄, extras)``."""
        tr = self._transition(k, u, carry)
        xp, Pp, Sp = time_update(x, P, S, tr, self.covariance_update, compiled=self._compiled_core())
        xn, Pn, Sn, carry, extras = self._update_arrays(k, xp, Pp, Sp, y, u, carry, options or {})
        return xn, Pn, Sn, carry, xp, Pp, extras

    def predict(self, state: FilterState, *, u: Any = None) -> FilterState:
        """The time update alone: the prediction :math:`\\hat x_{k+1|k}`, :math:`P_{k+1|k}` as a state
        whose ``k`` is the predicted time (pass it to :meth:`update` with that time's reading)."""
        state = self._check_state(state)
        uk = self._step_input(state, u)
        k = state.k + 1
        tr = self._transition(k, uk, state.carry)
        xp, Pp, Sp = time_update(state.x, state.P, state.S, tr, self.covariance_update, compiled=self._compiled_core())
        carry = dict(state.carry)
        carry["_predicted"] = True
        carry.pop("_u", None)  # a prediction of a prediction: the first step's input is not this one's
        if uk is not None:
            carry["_u"] = uk
        return mark_trusted(
            self, FilterState(k=k, batch_shape=state.batch_shape, x=xp, P=Pp, n=self.n, S=Sp, carry=carry)
        )

    def update(self, state: FilterState, y: Any, **options: Any) -> FilterState:
        """The measurement update alone, of a state from :meth:`predict` with the reading of its time."""
        state = self._check_state(state)
        if not state.carry.get("_predicted"):
            raise ValidationError(
                "state: update() needs a predicted state (from predict()); use step() for a filtered one"
            )
        yk = self._reading(state, y)
        self._check_update_reading(state, yk, options)
        opts = self._prepare_step_options(state, self._check_options(options))
        carry = {k: v for k, v in state.carry.items() if k not in ("_predicted", "_u")}
        uk = state.carry.get("_u")
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is detected and reported below
            x, P, S, carry, extras = self._update_arrays(state.k, state.x, state.P, state.S, yk, uk, carry, opts)
        x, carry = _divergence_check(
            self._name, x, P if S is None else S, state.k, self.covariance_update, carry, state.carry
        )
        return mark_trusted(
            self,
            FilterState(
                k=state.k, batch_shape=state.batch_shape, x=x, P=P, n=self.n, S=S, carry=carry, extras=extras or {}
            ),
        )


def _check_batch(batch_shape: Any) -> tuple[int, ...]:
    if isinstance(batch_shape, (int, np.integer)) and not isinstance(batch_shape, bool):
        batch_shape = (batch_shape,)
    try:
        batch = tuple(batch_shape)
    except TypeError:
        raise ValidationError(f"batch_shape: expected a tuple of positive integers, got {batch_shape!r}") from None
    for b in batch:
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or b < 1:
            raise ValidationError(f"batch_shape: expected a tuple of positive integers, got {batch_shape!r}")
    return tuple(int(b) for b in batch)


def _first_nonfinite(P: np.ndarray | None, k: int) -> int | None:
    if P is None:
        return None
    d = P.diagonal(0, -2, -1)
    if d.size <= 16:  # one run of a small state (the online step): Python floats, the same verdict
        return None if all(map(math.isfinite, d.ravel().tolist())) else k
    if np.isfinite(d).all():
        return None
    return k


def _poison_diverged(x: np.ndarray, P: np.ndarray | None) -> np.ndarray:
    """A run whose covariance is no longer finite has no meaningful mean: NaN, never a finite wrong one."""
    if P is None:
        return x
    d = np.diagonal(P, axis1=-2, axis2=-1)
    bad = ~np.isfinite(d).all(axis=-1)
    if not bad.any():
        return x
    if bad.shape[0] == 1 and x.shape[0] != 1:
        bad = np.broadcast_to(bad, (x.shape[0],))
    return np.where(bad[:, None], np.nan, x)


def _divergence_warning(name: str, k: int, form: str) -> None:
    remedy = (
        "a bounded horizon or a stabilizable model"
        if form == "square_root"
        else "covariance_update='square_root', which keeps the factor finite far longer"
    )
    warnings.warn(
        f"{name}: the covariance stopped being finite at step k={k} (overflow: an unstable model "
        f"predicted without readings for too long); the means of the affected runs are NaN from there "
        f"on. Remedy: {remedy}",
        RuntimeWarning,
        stacklevel=5,
    )


def _divergence_check(
    name: str,
    x: np.ndarray,
    P: np.ndarray | None,
    k: int,
    form: str,
    carry: Mapping[str, Any],
    prev: Mapping[str, Any],
):
    """Online form of the loop's check: NaN means for diverged runs, one warning per run of steps. The flag
    that it warned is read from ``prev``, the carry the step started from, as well as from the step's new
    ``carry`` (a family's step may build its carry afresh, and would otherwise warn at every later step)."""
    if _first_nonfinite(P, k) is None:
        return x, carry
    if not carry.get("_diverged"):
        if not prev.get("_diverged"):
            _divergence_warning(name, k, form)
        carry = dict(carry)
        carry["_diverged"] = True
    return _poison_diverged(x, P), carry


# --------------------------------------------------------------------------- a state entering an estimator


def _prediction_to_step(what: str = "step") -> ValidationError:
    return ValidationError(
        f"state: a prediction from predict() (its reading not applied yet): give it its reading with update(state, "
        f"y), or pass the filtered state (from init(), step() or update()) to {what}()"
    )


def _describe(arr: Any) -> str:
    if isinstance(arr, np.ndarray):
        return f"a {arr.dtype} array of shape {arr.shape}"
    return f"{type(arr).__name__}"


def _state_template(est: Estimator) -> FilterState | None:
    """The prior of one run of ``est`` (its layout: covariance or none, carried arrays), made once; None when
    the estimator's ``init`` needs arguments (the tracker's locations)."""
    cached = est.__dict__.get("_state_layout", _UNTRUSTED)
    if cached is _UNTRUSTED:
        try:
            cached = est.init()
        except Exception:  # noqa: BLE001 - an init that needs arguments: no layout to compare with
            cached = None
        est.__dict__["_state_layout"] = cached
    return cast("FilterState | None", cached)


def check_state(est: Estimator, state: Any) -> FilterState:
    r"""The full check of a state entering ``est`` (:meth:`Estimator._check_state` of a state it did not make).

    Checks, naming the field: a :class:`FilterState`; ``k`` an integer not before the estimator's prior
    (``est.k0``); ``batch_shape`` a tuple of positive integers; ``n`` and ``x`` (N, n_x) float64 of this
    estimator's dimensions; ``P`` (N or 1, n_x, n_x) float64, finite, symmetric and positive semi-definite
    (:func:`~tobitkf._validation.check_psd`), present when the estimator keeps a covariance; ``S`` of the same
    shape with :math:`SS^T = P` (to 1e-8 relative); the carried quantities the estimator keeps (a state
    made by another estimator lacks them). Means may be non-finite (an overflowed or diverged run, as the
    estimator leaves it); so may the covariance of a diverged run (the others are checked). Cost: :math:`O(N n_x^3)` (one symmetric eigendecomposition per run), paid once per
    state; the state is then marked as this estimator's (:func:`mark_trusted`).

    Raises
    ------
    ValidationError, ShapeError
        What is wrong, naming the field (``state.P``, ``state.k``...).
    """
    name = est._name
    if not isinstance(state, FilterState):
        raise ValidationError(f"state: expected a FilterState (from init() or step()), got {type(state).__name__}")
    k = state.k
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
        raise ValidationError(f"state.k: expected an integer time index, got {k!r} ({type(k).__name__})")
    if k < est.k0:
        raise ValidationError(
            f"state.k: expected a time index >= {est.k0} (the prior of this {name}), got {k}: a state from "
            "another estimator?"
        )
    if not isinstance(state.batch_shape, tuple):
        raise ValidationError(f"state.batch_shape: expected a tuple of positive integers, got {state.batch_shape!r}")
    try:
        batch = _check_batch(state.batch_shape)
    except ValidationError:
        raise ValidationError(
            f"state.batch_shape: expected a tuple of positive integers, got {state.batch_shape!r}"
        ) from None
    if not isinstance(state.carry, Mapping):
        raise ValidationError(f"state.carry: expected a mapping, got {type(state.carry).__name__}")
    N, nx = math.prod(batch), est._state_dim()
    if state.n != est.n:
        raise ShapeError(f"state.n: expected {est.n} (the state dimension of this {name}), got {state.n!r}")
    x = state.x
    if not (isinstance(x, np.ndarray) and x.dtype == np.float64 and x.shape == (N, nx)):
        raise ShapeError(
            f"state.x: expected a float64 array of shape ({N}, {nx}) (runs of batch shape {batch}, the state "
            f"dimension of this {name}), got {_describe(x)}"
        )
    template = _state_template(est)
    for key, mat in (("P", state.P), ("S", state.S)):
        if mat is None:
            continue
        if not (
            isinstance(mat, np.ndarray)
            and mat.dtype == np.float64
            and mat.ndim == 3
            and mat.shape[1:] == (nx, nx)
            and mat.shape[0] in (1, N)
        ):
            shapes = f"({N}, {nx}, {nx})" + ("" if N == 1 else f" or (1, {nx}, {nx})")
            raise ShapeError(f"state.{key}: expected a float64 array of shape {shapes}, got {_describe(mat)}")
    P, S = state.P, state.S
    if P is None:
        if template is not None and template.P is not None:
            raise ValidationError(f"state.P: this {name} keeps a covariance, got None: a state from another estimator?")
    else:
        # a run whose covariance is no longer finite diverged (its mean is NaN, as the estimator leaves it)
        ok = np.isfinite(P).all(axis=(-2, -1))
        Pf = P[ok]
        check_psd(Pf, "state.P")
        if S is not None:
            SS = S[ok] @ S[ok].swapaxes(-1, -2) if S.shape[0] == P.shape[0] else None
            scale = max(float(np.abs(Pf).max(initial=0.0)), _TINY)
            if SS is None or float(np.abs(SS - Pf).max(initial=0.0)) > 1e-8 * scale:
                raise ValidationError("state.S: expected a factor of state.P (S S^T = P, one per covariance)")
    if template is not None:
        for key, val in template.carry.items():
            if key.startswith("_") or not isinstance(val, (np.ndarray, Mapping)):
                continue  # the carried arrays and tables; a family's warm-up scalars may come and go
            if key not in state.carry:
                raise ValidationError(
                    f"state.carry: lacks {key!r}, which this {name} keeps: a state from another estimator? Pass a "
                    "state from this estimator's init(), step() or filter(...).final"
                )
            got = state.carry[key]
            if isinstance(val, np.ndarray) and val.ndim >= 1:
                if not (isinstance(got, np.ndarray) and got.ndim == val.ndim and got.shape[1:] == val.shape[1:]):
                    raise ShapeError(
                        f"state.carry[{key!r}]: expected an array of shape (..., {', '.join(map(str, val.shape[1:]))}) "
                        f"as this {name} keeps, got {_describe(got)}: a state from another estimator?"
                    )
    if est.covariance_update == "square_root" and S is None and P is not None:
        state = state.replace(S=psd_sqrt(P))
    return mark_trusted(est, state)


# --------------------------------------------------------------------------- memory of a run's outputs

_OUTPUT_SIZES = {"mean": 1, "pred_mean": 1, "var": 1, "cov": 2, "pred_cov": 2}


def _check_output_memory(want: frozenset[str], N: int, T: int, n: int, name: str) -> None:
    """Refuse, before the loop allocates them, outputs that cannot fit in memory (``name``: the readings)."""
    per = sum(n ** _OUTPUT_SIZES[key] for key in want if key in _OUTPUT_SIZES)
    if per:
        check_memory(
            8 * N * T * per,
            name,
            f"the outputs ({', '.join(sorted(want & set(_OUTPUT_SIZES)))}) of {plural(N, 'run')} x {plural(T, 'step')}",
        )


# --------------------------------------------------------------------------- a filter that stopped listening


def correction_statistic(mean: np.ndarray, pred_mean: np.ndarray, pred_cov: np.ndarray) -> np.ndarray:
    r"""Size of each update relative to the prediction's spread: :math:`c_k = \max_i (\hat x_{k|k} -
    \hat x_{k|k-1})_i^2 / (P_{k|k-1})_{ii}`, shape ``mean.shape[:-1]``.

    For a consistent Kalman-type update :math:`\hat x_{k|k} - \hat x_{k|k-1} = Ke_k`, and each component's
    :math:`c` is at most the Mahalanobis size :math:`(Ke)^T\bar P^{-1}Ke = e^TR_{ee}^{-1}H\bar PH^T R_{ee}^{-1}e
    \le e^TR_{ee}^{-1}e`, the normalised innovation squared (:math:`\chi^2_m`). So a sum of c over W steps is
    below a :math:`\chi^2_{mW}` variable. Rows without a reading give 0; a component of zero predicted
    variance, or non-finite values (a diverged run), count 0 here (the covariance check reports those).
    """
    d = mean - pred_mean
    v = np.diagonal(pred_cov, axis1=-2, axis2=-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = np.where(v > _TINY, d * d / np.where(v > _TINY, v, 1.0), 0.0)
    c = np.where(np.isfinite(c), c, 0.0)
    return c.max(axis=-1) if c.shape[-1] else np.zeros(c.shape[:-1])


def _correction_check(est: Any, result: FilterResult) -> None:
    r"""Warn once when a ``filter`` run's updates are far larger than its own covariance allows: the window sum
    over :data:`CORRECTION_WINDOW` steps of :func:`correction_statistic`, each step capped at
    :data:`CORRECTION_CAP` of the threshold (so one outlier never suffices), above :func:`correction_threshold`
    (the capped sum is below the plain one, so the bound for a consistent filter still holds).
    A diverging filter whose covariance stays finite and small (confidently wrong, e.g. the TKF's
    ``noise_term="total_variance"`` deep in the censored region) is caught here; the non-finite covariance
    check (:func:`_divergence_warning`) catches the others. Needs the recorded ``mean``, ``pred_mean`` and
    ``pred_cov`` (``outputs="all"``, the default); a fixed-gain filter (its covariance the same at every
    step, a nominal one) is not checked."""
    mean, pm, pc = result.mean, result.pred_mean, result.pred_cov
    if mean is None or pm is None or pc is None or mean.ndim < 2 or mean.shape[-2] < 1:
        return
    if pc.shape[-3] > 1 and (pc == pc[..., :1, :, :]).all():
        return  # a fixed-gain filter's nominal covariance (the same at every step) claims no consistency
    c = correction_statistic(mean, pm, pc)  # batch + (T,)
    T = c.shape[-1]
    W = min(CORRECTION_WINDOW, T)
    limit = correction_threshold(est.m, W)
    c = np.minimum(c, CORRECTION_CAP * limit)
    cs = np.cumsum(c, axis=-1)
    win = cs[..., W - 1 :].copy()
    win[..., 1:] -= cs[..., : T - W]
    over = win > limit
    # a run whose means stopped being finite is the non-finite check's to report (one warning per event)
    over &= np.isfinite(mean).all(axis=(-2, -1))[..., None]
    if not over.any():
        return
    flat = over.reshape(-1, over.shape[-1])
    hit = flat.any(axis=-1)
    ends = np.where(hit, np.argmax(flat, axis=-1), flat.shape[-1])
    run = int(np.argmin(ends))  # the run that crossed first; its window ends at row ends[run] + W - 1
    end = int(ends[run]) + W
    first = end - W + int(np.argmax(c.reshape(-1, T)[run, end - W : end]))  # the largest update of that window
    runs = int(hit.sum())
    k = int(result.times[first]) if result.times is not None else first + 1
    warnings.warn(
        f"{est._name}: its updates became far larger than its own covariance allows at step k={k} in {runs} of "
        f"{plural(flat.shape[0], 'run')} (the sum over {W} steps of the squared updates, in predicted variances and "
        f"each capped at {CORRECTION_CAP * limit:.3g}, exceeds {limit:.3g}): the estimate no longer follows the readings while its covariance "
        f"says it should (a diverging filter, or a model or readings with gross errors). Remedy: "
        f"{_correction_remedy(est)}",
        RuntimeWarning,
        stacklevel=_caller_level(),
    )
