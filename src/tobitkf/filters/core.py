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
    check_psd,
    check_scale,
    reading_in_scale,
)
from . import _online_check
from ._boundary import check_keywords, check_prior, prepare_inputs, prepare_measurements, process_roots
from ._filter_doc import document_filter, filter_docstring
from ._online_check import (
    _correction_check,
)
from ._output_names import OUTPUTS, check_output_memory, parse_outputs
from ._update import (
    MeasurementPrediction,
    Transition,
    _core_compiled_module,
    gain_update,
    measurement_update,
    predict,
    qr_r,
    shift_predict,
    sqrt_predict,
    sqrt_update,
    time_update,
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
    "qr_r",
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
    and ``update`` without the full check of :func:`entering_state`. Returns ``state``."""
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


# --------------------------------------------------------------------------- outputs


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
    r"""Base of every estimator: the online API (:meth:`init`, :meth:`step`), the one record filter
    (:meth:`filter`) and the one time loop behind it (:meth:`_run`).

    The hooks a family supplies, on arrays batched over N runs (no validation inside); the first two are
    required, every other one has a default:

    * ``_initial(N, x0, P0, batch)`` → ``(x, P, carry)``: the prior (``P`` (N or 1, n_x, n_x) or None);
    * ``_step_arrays(k, x, P, S, carry, y, u, options)`` → ``(x, P, S, carry, x̄, P̄, extras)``: one reading.
      :class:`GaussianFilter` implements it from ``_transition`` and ``_measurement``; estimators that are not
      Gaussian updates (the particle filter, the H∞ filter, the tracker) implement it directly and get the same
      ``init``/``step``/``filter`` and the same recorded outputs;
    * ``_state_dim()``: the dimension n_x of the carried state when it is not ``n`` (an augmented state);
      ``_bytes_per_run()`` when a run carries more than its mean and covariance (particles);
    * ``_check_record(y2, u2, k0, name)``: the checks of a record (N, T, m) whose first reading has time
      ``k0 + 1`` (limits, horizon); ``_check_reading(k, y, options)``: those of the one reading (N, m) of time k
      of ``step`` and ``update`` (default: ``_check_record`` of a record of one step);
    * ``_prepare_record(y, name)``: the record's layout, ``(N, T, m)`` and the batch shape (default ``(..., T, m)``);
    * ``_prepare_inputs(u, N, T, batch)`` and ``_step_input(state, u)``: control inputs of a record and of one
      step (default: refused);
    * ``_prepare_step_options(state, options)``: the keywords of ``step``/``update`` (their names in the class
      attribute ``_step_options``) as the arrays ``_step_arrays`` takes;
    * ``_compiled_filter(y2, u2, state, want, batch, step_options)`` and
      ``_compiled_online_step(state, y, u, options)``: the compiled path of a record and of one step, each None
      when it does not cover the call (the numpy path runs); ``_compiled_core()``: whether the shared predict and
      update run compiled (default: numba imports and ``backend`` is not ``"numpy"``).

    :meth:`filter` is written once: a family names its equations in the class attribute ``_filter_doc`` (and
    its own keywords in ``_filter_params``, what else it refuses in ``_filter_raises``), which complete the
    shared docstring (:mod:`tobitkf.filters._filter_doc`); a family with keywords of its own overrides ``filter``
    (without a docstring) and calls ``super().filter`` or :meth:`_run`. :meth:`_run` (the loop) and ``_reading``
    (the reading of one step, parsed and checked) are the machinery around those hooks, not hooks.
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
    #: the summary of :meth:`filter`'s docstring, naming the family's equations; with ``_filter_params`` (the text
    #: of the family's own keywords) and ``_filter_raises`` (what else it refuses) it completes the shared text
    #: (:mod:`tobitkf.filters._filter_doc`)
    _filter_doc: str = "Filter the readings ``y`` (..., T, m) of a batch of records: one predict and update per step."
    _filter_params: Mapping[str, str] = {}
    _filter_raises: str = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        document_filter(cls)

    def filter(
        self,
        y: Any,
        *,
        u: Any = None,
        x0: Any = None,
        P0: Any = None,
        outputs: Any = "all",
        state: FilterState | None = None,
    ) -> FilterResult:
        # the docstring is the shared text completed by the family's fragments (set below and per subclass)
        return self._run(y, u, x0, P0, outputs=outputs, state=state)

    def _initial(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...]):  # pragma: no cover - abstract
        raise NotImplementedError

    def _check_record(self, y2: np.ndarray, u2: np.ndarray | None, k0: int, name: str = "y") -> None:
        """Checks of a whole record at the boundary (limits, horizon); families extend."""

    def _prepare_inputs(self, u: Any, N: int, T: int, batch: tuple[int, ...]) -> np.ndarray | None:
        if u is None:
            return None
        raise ValidationError(f"u: {self._name} takes no control input")

    def _compiled_filter(
        self, y2, u2, state: FilterState, want: frozenset[str], batch, step_options=None
    ) -> FilterResult | None:
        """A compiled implementation of the loop over the record ``y2`` (N, T, m) from ``state``, or None (the
        numpy loop runs); ``step_options`` are those of the loop (:meth:`_run`)."""
        return None

    def _compiled_core(self) -> bool:
        """Whether the shared predict and update run compiled (:mod:`tobitkf.filters._compiled_step`):
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

    def _state_dim(self) -> int:
        return self.n

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
            raise _refused_nan(self, err) from None
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

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (m,)``); NaN = missing channel.

        Equal to one row of :meth:`filter` (tested to 1e-12 on the numpy path). Returns the new state
        (``state.k`` advanced by one); the old one is unchanged.

        Warns (``RuntimeWarning``) as :meth:`filter` does: when the covariance stops being finite, and, for a
        Gaussian-update family, once per lineage of states when the updates grow far larger than the
        filter's own covariance allows (a diverging filter: :mod:`tobitkf.filters._online_check`, every
        8th step), naming the step and the remedy.
        """
        state = entering_state(self, state)
        if state.carry.get("_predicted"):
            raise _prediction_to_step()
        yk = self._reading(state, y)
        if u is None and not options:  # a plain call: no input to form, no keyword to vet
            uk, opts = None, self._prepare_step_options(state, options)
        else:
            uk = self._step_input(state, u)
            opts = self._prepare_step_options(state, _step_keywords(self, options))
        self._check_reading(state.k + 1, yk, opts)
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

    def _check_reading(self, k: int, y: np.ndarray, options: Mapping[str, Any]) -> None:
        """Checks of the reading (N, m) of time ``k`` beyond its shape (e.g. within the censoring limits), for
        ``step`` and ``update``: those of ``filter`` (:meth:`_check_record` of a record of one step), so that
        ``step``, ``update`` and ``filter`` accept the same readings; a step that sets its own limits
        (``lower``/``upper``) is checked by its family."""
        if options and (options.get("lower") is not None or options.get("upper") is not None):
            return
        self._check_record(y[:, None], None, k - 1)

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
            state = entering_state(self, state)
            if state.carry.get("_predicted"):
                raise _prediction_to_step("filter")
            if state.batch_shape != batch and state.runs != N:
                raise ShapeError(f"state: batch shape {state.batch_shape} does not match y's {batch}")
        else:
            state = self.init(batch, x0=x0, P0=P0)
        u2 = self._prepare_inputs(u, N, T, batch)
        self._check_record(y2, u2, state.k, name)
        check_output_memory(want, N, T, self.n, name)
        fast = self._compiled_filter(y2, u2, state, want, batch, step_options)
        if fast is None:
            rec = _Recorder(want, T, batch, self.n)
            with np.errstate(over="ignore", invalid="ignore"):  # an overflow is detected and reported below
                fast = _numpy_loop(self, rec, state, y2, u2, step_options, step_data, batch)
        if fast.final is not None:
            mark_trusted(self, fast.final)
        if isinstance(self, GaussianFilter):
            _correction_check(self, fast)
        return fast

    def _prepare_record(self, y: Any, name: str = "y") -> tuple[np.ndarray, tuple[int, ...]]:
        try:
            return prepare_measurements(y, self.m, name, allow_nan=self._allow_missing)
        except ValidationError as err:
            raise _refused_nan(self, err) from None

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):  # pragma: no cover - abstract
        raise NotImplementedError


Estimator.filter.__doc__ = filter_docstring(Estimator, Estimator.filter)


class GaussianFilter(Estimator):
    r"""Base of every Gaussian-update family: the shared predict and update behind the online API.

    A family implements three hooks on arrays (batched over N runs, no validation inside):

    * ``_initial(N, x0, P0, batch)`` → ``(x, P, carry)``: the prior;
    * ``_transition(k, u, carry)`` → :class:`Transition` from k-1 to k;
    * ``_measurement(k, x̄, P̄, y, u, carry, **step_options)`` → ``(MeasurementPrediction, carry)``;

    and optionally ``_extras(k, x̄, P̄, x, P, mp, K, Ree, options)`` for per-step quantities that need
    the posterior, and ``_update_arrays(k, x̄, P̄, S̄, y, u, carry, options)`` → ``(x, P, S, carry, extras)`` to
    replace the Kalman-type update of ``_measurement``'s moments (an assumed-density family's projection); the
    optional hooks of :class:`Estimator` apply too. Everything else (the predict, the update in each covariance form, the masking, the
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

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):
        """One predict + update on arrays: returns ``(x, P, S, carry, x̄, P̄, extras)``."""
        tr = self._transition(k, u, carry)
        xp, Pp, Sp = time_update(x, P, S, tr, self.covariance_update, compiled=self._compiled_core())
        xn, Pn, Sn, carry, extras = self._update_arrays(k, xp, Pp, Sp, y, u, carry, options or {})
        return xn, Pn, Sn, carry, xp, Pp, extras

    def predict(self, state: FilterState, *, u: Any = None) -> FilterState:
        """The time update alone: the prediction :math:`\\hat x_{k+1|k}`, :math:`P_{k+1|k}` as a state
        whose ``k`` is the predicted time (pass it to :meth:`update` with that time's reading)."""
        state = entering_state(self, state)
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
        state = entering_state(self, state)
        if not state.carry.get("_predicted"):
            raise ValidationError(
                "state: update() needs a predicted state (from predict()); use step() for a filtered one"
            )
        yk = self._reading(state, y)
        self._check_reading(state.k, yk, options)
        opts = self._prepare_step_options(state, _step_keywords(self, options))
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


def _numpy_loop(est: Estimator, rec: _Recorder, state: FilterState, y2, u2, step_options, step_data, batch):
    """The numpy time loop of :meth:`Estimator._run`: :meth:`~Estimator._step_arrays` for each reading of ``y2``
    (N, T, m) from ``state``, the outputs recorded, the runs whose covariance stopped being finite poisoned (NaN
    means) and reported once."""
    N, T = y2.shape[0], y2.shape[1]
    x, P, S, carry = state.x, state.P, state.S, state.carry
    first_bad = None
    for i in range(T):
        k = state.k + i + 1
        opts = step_options
        if step_data:
            opts = dict(step_options or {})
            opts.update({key: val[:, i] for key, val in step_data.items()})
        x, P, S, carry, xp, Pp, extras = est._step_arrays(
            k, x, P, S, carry, y2[:, i], None if u2 is None else u2[:, i], opts
        )
        if first_bad is None:
            first_bad = _first_nonfinite(P if S is None else S, k)
        if first_bad is not None:
            x = _poison_diverged(x, P if S is None else S)
        rec.record(i, xp, Pp, x, P, extras)
    if first_bad is not None:
        _divergence_warning(est._name, first_bad, est.covariance_update)
    final = FilterState(k=state.k + T, batch_shape=batch, x=x, P=P, n=est.n, S=S, carry=carry)
    times = np.arange(state.k + 1, state.k + T + 1)
    return rec.result(N, times, final)


def _step_keywords(est: Estimator, options: Mapping[str, Any]) -> dict[str, Any]:
    """The keywords of ``step``/``update`` as a dict, each one of the family's ``_step_options``."""
    for key in options:
        if key not in est._step_options:
            raise TypeError(f"unexpected keyword argument {key!r}")
    return dict(options)


def entering_state(est: Estimator, state: Any) -> FilterState:
    """``state`` as it may enter ``est``: a state this estimator made passes at the cost of two dictionary
    look-ups (:func:`is_trusted`); any other (unpickled, copied, ``replace``-d, built by hand or made by another
    estimator) gets the full check of :func:`check_state` once."""
    if is_trusted(est, state):
        return state
    return check_state(est, state)


def _refused_nan(est: Estimator, err: ValidationError) -> ValidationError:
    """The NaN refusal ``err`` with the family's reason (``_missing_reason``) appended."""
    if est._missing_reason and "NaN" in str(err):
        return ValidationError(f"{err} ({est._missing_reason})")
    return err


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
    r"""The full check of a state entering ``est`` (:func:`entering_state` of a state it did not make).

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
