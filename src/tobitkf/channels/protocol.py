r"""Channel pieces of the protocol-based TKF: integral measurements, sensor failures, Round-Robin.

Source: Geng, Wang, Zou, Mousavi, Cheng, "Protocol-Based Tobit Kalman Filter under
Integral Measurements and Probabilistic Sensor Failures" (eqs. (2)–(7); our deviations: docs/sources/geng-protocol.md).

Model of what reaches the estimator (paper equations (2)–(7)), sensors m = 1..p:

.. math::

    z_{m,k} &= \Lambda_{m,k}\, C_{m,k} \sum_{s=0}^{\ell} x_{k-s} + v_{m,k}
        &(2) \\
    \bar h_k &= \mathrm{mod}(k-1, p) + 1, \qquad \Gamma_{m,\bar h_k} = \delta(\bar h_k - m)
        &\text{(RRP)} \\
    \bar y_k &= \sum_m \Gamma_{m,\bar h_k} z_{m,k} = z_{\bar h_k,k}  &(3) \\
    y_k &= \max(\bar y_k, \tau), \qquad \gamma_k = \mathbb 1[\bar y_k > \tau]  &(4)\text{–}(5)

* The "integral" is a plain sum of the last :math:`\ell+1` states (:class:`IntegralMeasurement`).
* :math:`\Lambda_{m,k}\in[0,1]` are independent failure gains with a given law: a
  :class:`~tobitkf.channels.laws.PMF` (the example's discrete laws), a
  :class:`~tobitkf.channels.laws.Uniform`, a constant, or any object with scalar ``mean``,
  ``variance`` and ``sample(rng, shape)`` (checked by :func:`check_failure_law`).
* Round-Robin with the **zero-input** strategy (:class:`RoundRobin`): only the
  scheduled sensor's value reaches the estimator; nothing is held (no ZOH).
  :math:`\delta` is a Kronecker delta (the paper says "Dirac", GP-14).
* Tobit censoring at the estimator input is the core :class:`~tobitkf.Censoring`
  with ``lower=tau``. Because it is element-wise with one threshold, censoring every
  sensor's reading and then selecting the scheduled one equals (4) exactly.

Composition with the core simulator (:func:`tobitkf.simulate`): the sensors are the
``p`` rows of the system's ``C`` and the diagonal of its ``R`` (so ``system.m = p``);
:class:`ProtocolChannel` is a :class:`~tobitkf.channels.base.Channel` at all three stages:
it draws every sensor's :math:`z_{m,k}` (Λ and the pre-history), censors at τ, and keeps the
scheduled sensor; ``tk.simulate(system, T, N, channel=ch, seed=s)`` draws it.
The result's ``y`` is ``(N, T, 1)`` (the scalar :math:`y_k`), ``y_latent`` is
``(N, T, p)`` (every :math:`z_{m,k}`), and ``extras`` holds ``failure_gain``
(N, T, p), ``prehistory`` (N, ℓ, n) = :math:`x_{-1},\dots,x_{-\ell}`, ``scheduled``
(T,) (1-based :math:`\bar h_k`), ``y_transmitted`` (N, T, 1) = :math:`\bar y_k` and
``uncensored`` (N, T, 1) = :math:`\gamma_k` (laid out like ``y``, so that it can be passed to the
filter's ``uncensored=``).

Time convention: :math:`x_0` is the prior state; :math:`y_1` is stored at index 0.
The pre-history :math:`x_{-1..-\ell}` is drawn from the filter prior (not stated in the source, GP-08).

Code names -> paper symbols: ``window`` = ℓ, ``failure_gain`` = Λ, ``scheduled`` =
:math:`\bar h_k`, ``schedule_indicator`` = Γ, ``threshold`` = τ, ``uncensored`` = γ.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .._linalg import eigh_sqrt
from .._validation import ShapeError, ValidationError, as_float_array, check_memory
from .base import Channel, refuse_feedthrough
from .censoring import Censoring
from .laws import PMF, Constant, Gaussian

__all__ = [
    "check_failure_law",
    "IntegralMeasurement",
    "RoundRobin",
    "ProtocolChannel",
    "LAMBDA_BASE",
    "LAMBDA_1",
    "NO_FAILURE",
    "PREHISTORY",
]

_PROB_TOL = 1e-9
PREHISTORY = ("prior", "hold", "zero")


LAMBDA_BASE = PMF([0.0, 0.5, 1.0], [0.05, 0.10, 0.85])
r"""The example's base law (labelled :math:`\Lambda_2` in Fig. 8): mean 0.9, variance 0.065."""
LAMBDA_1 = PMF([0.0, 0.5, 1.0], [0.35, 0.10, 0.55])
r"""Fig. 8's :math:`\Lambda_1`: mean 0.6, variance 0.215 (35 % complete outages)."""
NO_FAILURE = Constant(1.0)
r"""No failures: :math:`\Lambda \equiv 1`."""


def check_failure_law(law: Any, name: str = "failures", *, unit_interval: bool = True) -> Any:
    """Check that ``law`` is a law of a scalar gain usable as a failure coefficient.

    Any object with scalar ``mean`` and ``variance`` and ``sample(rng, shape)`` is
    accepted. When the law exposes its support (``values``/``probs`` of a discrete law,
    or ``low``/``high`` of a uniform one) the support must lie in [0, 1]; otherwise the
    moments must be possible for a [0, 1] variable: mean in [0, 1] and
    ``variance <= mean (1 - mean)``.

    Raises
    ------
    ValidationError
        Missing attributes, negative variance, probabilities not summing to 1, support
        outside [0, 1].
    """
    for attr in ("mean", "variance", "sample"):
        if not hasattr(law, attr):
            raise ValidationError(
                f"{name}: expected a law with mean, variance and sample(rng, shape); "
                f"{type(law).__name__} has no {attr!r}"
            )
    mean = np.asarray(law.mean, dtype=float)
    var = np.asarray(law.variance, dtype=float)
    if isinstance(law, Gaussian) and unit_interval and float(var) > 0:
        raise ValidationError(
            f"{name}: a Gaussian gain with positive variance leaves [0, 1] (Assumption 2); "
            "use a PMF or Uniform law, or any law supported in [0, 1]"
        )
    if mean.shape != () or var.shape != ():
        raise ShapeError(f"{name}: expected a law of one scalar gain, got mean of shape {mean.shape}")
    if not (np.isfinite(mean) and np.isfinite(var)) or var < 0:
        raise ValidationError(f"{name}: expected a finite mean and a variance >= 0, got {float(mean)}, {float(var)}")
    if hasattr(law, "probs"):
        probs = np.asarray(law.probs, dtype=float)
        if (probs < 0).any() or abs(probs.sum() - 1.0) > _PROB_TOL:
            raise ValidationError(f"{name}: probabilities must be >= 0 and sum to 1, got sum {probs.sum():.12g}")
    if unit_interval:
        if hasattr(law, "values"):
            vals = np.asarray(law.values, dtype=float)
            lo, hi = float(vals.min()), float(vals.max())
        elif hasattr(law, "low") and hasattr(law, "high"):
            lo, hi = float(np.min(law.low)), float(np.max(law.high))
        else:
            lo = hi = float(mean)
            if var > mean * (1 - mean) + 1e-12:
                raise ValidationError(
                    f"{name}: variance {float(var):.6g} exceeds mean(1-mean) = "
                    f"{float(mean * (1 - mean)):.6g}, impossible for a gain in [0, 1]"
                )
        if lo < 0 or hi > 1:
            raise ValidationError(
                f"{name}: a failure gain must take values in [0, 1] (Assumption 2), got support [{lo}, {hi}]"
            )
    return law


class IntegralMeasurement:
    r"""Integral measurement over the last :math:`\ell+1` states, eq. (2): :math:`\sum_{s=0}^{\ell} x_{k-s}`.

    Parameters
    ----------
    window : int
        :math:`\ell \ge 0` ("the time length required for the data collection").
        ``window=0`` is an ordinary (point) measurement.

    Raises
    ------
    ValidationError
        If ``window`` is not an integer >= 0.

    Examples
    --------
    >>> x = np.arange(5.0)[None, :, None]           # x_0..x_4 = 0..4 of one run, n = 1
    >>> past = np.array([[[-1.0], [-2.0]]])          # x_{-1} = -1, x_{-2} = -2
    >>> IntegralMeasurement(2).window_sum(x, past)[0, :, 0].tolist()     # x_k + x_{k-1} + x_{k-2}
    [0.0, 3.0, 6.0, 9.0]
    """

    def __init__(self, window: int):
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 0:
            raise ValidationError(f"window: expected an integer ell >= 0, got {window!r}")
        self.window = int(window)
        # the filter's augmented covariance is (n(ell+1))^2 floats, at least (ell+1)^2 for n = 1
        check_memory(
            8 * (self.window + 1) ** 2,
            "window",
            f"an integral window of {self.window} steps (the augmented covariance, at least "
            f"{self.window + 1} x {self.window + 1})",
        )

    def window_sum(self, x: np.ndarray, prehistory: np.ndarray) -> np.ndarray:
        r""":math:`\sum_{s=0}^{\ell} x_{k-s}` for k = 1..T.

        Parameters
        ----------
        x : (N, T+1, n) ndarray
            :math:`x_0..x_T`.
        prehistory : (N, ℓ, n) ndarray
            :math:`x_{-1}, \dots, x_{-\ell}` (index s-1 holds :math:`x_{-s}`).

        Returns
        -------
        (N, T, n) ndarray
        """
        ell = self.window
        if prehistory.shape[-2] != ell:
            raise ShapeError(f"prehistory: expected {ell} past states, got shape {prehistory.shape}")
        full = np.concatenate([prehistory[:, ::-1], x], axis=1)  # x_{-ell} .. x_T; x_k at k + ell
        T = x.shape[1] - 1
        out = full[:, ell + 1 : ell + 1 + T].copy()  # s = 0: x_1..x_T
        for s in range(1, ell + 1):
            out += full[:, ell + 1 - s : ell + 1 - s + T]
        return out


class RoundRobin:
    r"""Round-Robin protocol with the zero-input strategy.

    :math:`\bar h_k = \mathrm{mod}(k-1, p) + 1` ((3) of the source): sensors 1, 2, ..., p, 1, 2, ...
    A different cyclic order may be given (``order``); it is repeated with period
    ``len(order)``.

    Parameters
    ----------
    sensors : int
        Number of sensors :math:`p \ge 1`.
    order : sequence of int, optional
        1-based sensor numbers in the order they are served; default ``1..p``.

    Raises
    ------
    ValidationError
        ``p < 1``, an empty order, or an order naming a sensor outside ``1..p``.

    Examples
    --------
    >>> RoundRobin(3).scheduled(7).tolist()
    [1, 2, 3, 1, 2, 3, 1]
    >>> RoundRobin(2).indicator(2).tolist()
    [[1.0, 0.0], [0.0, 1.0]]
    """

    def __init__(self, sensors: int, order: Sequence[int] | None = None):
        if isinstance(sensors, bool) or not isinstance(sensors, (int, np.integer)) or sensors < 1:
            raise ValidationError(f"sensors: expected an integer p >= 1, got {sensors!r}")
        self.sensors = int(sensors)
        check_memory(8 * self.sensors, "sensors", f"{self.sensors} sensors")
        if order is None:
            order = range(1, self.sensors + 1)
        if isinstance(order, (str, bytes)) or not hasattr(order, "__iter__"):
            raise ValidationError(f"order: expected a non-empty sequence of integer sensor numbers, got {order!r}")
        arr = np.asarray(list(order))
        if arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
            raise ValidationError(f"order: expected a non-empty sequence of integer sensor numbers, got {order!r}")
        bad = (arr < 1) | (arr > self.sensors)
        if bad.any():
            raise ValidationError(f"order: names sensor {int(arr[bad][0])}, but only sensors 1..{self.sensors} exist")
        self.order = arr.astype(int)

    def scheduled(self, steps: int) -> np.ndarray:
        r""":math:`\bar h_k` for k = 1..steps, 1-based, shape (steps,)."""
        return self.order[np.arange(steps) % self.order.size]

    def indicator(self, steps: int) -> np.ndarray:
        r""":math:`\Gamma_{m,\bar h_k}` for k = 1..steps, shape (steps, p), one-hot rows."""
        return (self.scheduled(steps)[:, None] == np.arange(1, self.sensors + 1)).astype(float)

    def select(self, z: np.ndarray) -> np.ndarray:
        r"""Zero-input transmission (3): :math:`\bar y_k = \sum_m \Gamma_{m,\bar h_k} z_{m,k}`.

        ``z`` (N, T, p) -> (N, T, 1).
        """
        if z.shape[-1] != self.sensors:
            raise ShapeError(f"z: expected (..., T, {self.sensors}) sensor readings, got {z.shape}")
        h = self.scheduled(z.shape[-2]) - 1
        return np.take_along_axis(z, np.broadcast_to(h[:, None], z.shape[:-1] + (1,)), axis=-1)

    def __repr__(self) -> str:
        return f"RoundRobin(sensors={self.sensors}, order={self.order.tolist()})"


def _sweep_law(tbl: Any, name: str) -> Any:
    """A failure law of a sweep file: ``"none"`` (None), ``"base"``, ``"lambda1"`` or ``{values, probs}``."""
    if tbl is None or tbl == "none":
        return None
    if isinstance(tbl, str):
        laws = {"base": LAMBDA_BASE, "lambda1": LAMBDA_1}
        if tbl not in laws:
            raise ValidationError(
                f"{name}: expected 'none', 'base', 'lambda1' or a table {{values, probs}}, got {tbl!r}"
            )
        return laws[tbl]
    if not isinstance(tbl, dict) or set(tbl) != {"values", "probs"}:
        raise ValidationError(f"{name}: expected a table with 'values' and 'probs', got {tbl!r}")
    return PMF(tbl["values"], tbl["probs"])


class ProtocolChannel(Channel):
    r"""Integral measurement + sensor failures + Round-Robin + Tobit censoring (eqs. (2)–(7)).

    The one description the simulator draws from and the estimator
    (:class:`~tobitkf.filters.protocol.ProtocolTobitKalmanFilter`) reads its statistics from.

    Parameters
    ----------
    sensors : int
        Number of sensors p (the rows of the system's ``C``).
    window : int, default 0
        :math:`\ell`.
    failures : law or sequence of p laws, optional
        Law of :math:`\Lambda_{m,k}` (iid over k): one law for every sensor or one per
        sensor. Default: no failures (:math:`\Lambda \equiv 1`).
    threshold : float, default -inf
        Censoring threshold :math:`\tau` (lower censoring, the same for every sensor).
    order : sequence of int, optional
        Cyclic service order (default Round-Robin 1..p).
    prehistory : {"prior", "hold", "zero"}, default "prior"
        How the simulator draws :math:`x_{-1..-\ell}`: iid from the prior
        :math:`N(\bar x_0, P_0)` (GP-08, consistent with the filter's default prior),
        equal to :math:`x_0`, or zero.

    Raises
    ------
    ValidationError
        Bad ``sensors``/``window``/``order``/``prehistory``, a NaN or +inf threshold, a law
        that is not a [0, 1] law, or a number of laws different from p.

    Examples
    --------
    >>> ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)   # a PMF on {0, 0.5, 1}
    >>> ch.failure_mean.tolist(), ch.failure_variance.round(6).tolist()
    ([0.9, 0.9], [0.065, 0.065])
    """

    section = "protocol"
    sweep_options = {"window": int, "threshold": float, "failures": object, "order": object, "prehistory": PREHISTORY}
    replaces_censoring = True

    @classmethod
    def from_options(cls, options: Any, system: Any = None) -> ProtocolChannel:
        """A sweep file's ``[protocol]`` for ``system`` (one sensor per output): ``window`` ℓ, ``threshold`` τ,
        ``failures`` = ``"none"``, ``"base"`` (:data:`LAMBDA_BASE`), ``"lambda1"`` (:data:`LAMBDA_1`) or a
        table ``{values = [...], probs = [...]}``, ``order``, ``prehistory``.

        Raises
        ------
        ValidationError
            An unknown key or failure law, and the constructor's errors.
        """
        tbl = dict(options)
        unknown = set(tbl) - set(cls.sweep_options)
        if unknown:
            raise ValidationError(f"{sorted(unknown)[0]}: not an option of [protocol]")
        kw = {k: v for k, v in tbl.items() if k in ("window", "threshold", "order", "prehistory")}
        if "threshold" in kw:
            kw["threshold"] = float(kw["threshold"])
        failures = _sweep_law(tbl.get("failures"), "failures")
        if failures is not None:
            kw["failures"] = failures
        return cls(system.m, **kw)

    def reading_width(self, system: Any) -> int:
        """1: the estimators receive the scheduled sensor's reading."""
        return 1

    def at_limit(self, y: np.ndarray, start: int = 1) -> np.ndarray:
        """Readings at (or below) the threshold τ."""
        with np.errstate(invalid="ignore"):
            return np.asarray(y) <= self.threshold

    def __init__(
        self,
        sensors: int,
        *,
        window: int = 0,
        failures: Any = None,
        threshold: float = -np.inf,
        order: Sequence[int] | None = None,
        prehistory: str = "prior",
    ):
        self.schedule = RoundRobin(sensors, order)
        self.integral = IntegralMeasurement(window)
        p = self.schedule.sensors
        if failures is None:
            failures = NO_FAILURE
        if isinstance(failures, (list, tuple)):
            if len(failures) != p:
                raise ValidationError(f"failures: expected one law or {p} laws (one per sensor), got {len(failures)}")
            self.laws = tuple(check_failure_law(f, f"failures[{i}]") for i, f in enumerate(failures))
            self.shared_law = False
        else:
            self.laws = (check_failure_law(failures),) * p
            self.shared_law = True
        tau = as_float_array(threshold, "threshold", ndim=0, allow_inf=True)
        if np.isposinf(tau):
            raise ValidationError("threshold: +inf would censor every reading")
        self.threshold = float(tau)
        if prehistory not in PREHISTORY:
            raise ValidationError(f"prehistory: expected one of {', '.join(map(repr, PREHISTORY))}, got {prehistory!r}")
        self.prehistory = prehistory

    # --- statistics the estimator needs --------------------------------------------
    @property
    def sensors(self) -> int:
        return self.schedule.sensors

    @property
    def window(self) -> int:
        return self.integral.window

    @property
    def failure_mean(self) -> np.ndarray:
        r""":math:`\bar\Lambda_m`, shape (p,)."""
        return np.array([float(law.mean) for law in self.laws])

    @property
    def failure_variance(self) -> np.ndarray:
        r""":math:`\check\Lambda_m`, shape (p,)."""
        return np.array([float(law.variance) for law in self.laws])

    @property
    def censoring(self) -> Censoring:
        """The estimator-input censoring :math:`y = \\max(\\bar y, \\tau)`."""
        return Censoring(lower=self.threshold)

    def replace(self, **changes: Any) -> ProtocolChannel:
        """A copy with some settings changed (``window``, ``failures``, ``threshold``, ...)."""
        kw = dict(
            sensors=self.sensors,
            window=self.window,
            failures=self.laws[0] if self.shared_law else list(self.laws),
            threshold=self.threshold,
            order=self.schedule.order.tolist(),
            prehistory=self.prehistory,
        )
        kw.update(changes)
        sensors = kw.pop("sensors")
        return ProtocolChannel(sensors, **kw)

    def check_system(self, system: Any) -> None:
        """Raise unless the system has one measurement row per sensor and a diagonal R, and the
        augmented covariance of the window fits in memory."""
        if hasattr(system, "n"):
            size = system.n * (self.window + 1)
            check_memory(
                8 * size * size,
                "window",
                f"an integral window of {self.window} steps with n = {system.n} "
                f"(the augmented covariance, {size} x {size})",
            )
        if system.m != self.sensors:
            raise ShapeError(f"system: expected C with p={self.sensors} rows (one per sensor), got m={system.m}")

    # --- simulation hooks (core simulate protocol) ----------------------------------
    def draw(self, rng: np.random.Generator, x: np.ndarray, system: Any, noise: np.ndarray, inputs: Any = None):
        r"""Every sensor's :math:`z_{m,k}` (2), shape (N, T, p), and the draws in ``extras``.

        Draw order: the failure gains (N, T, p) first (one uniform each for discrete laws,
        so scenarios that differ only in the law share random numbers), then the
        pre-history (N, ℓ, n).
        """
        self.check_system(system)
        refuse_feedthrough(system, inputs, "the protocol channel's reading (2)")
        N, T1, n = x.shape
        T, p = T1 - 1, self.sensors
        if self.shared_law:
            lam = np.asarray(self.laws[0].sample(rng, (N, T, p)), dtype=float)
        else:
            lam = np.stack([np.asarray(law.sample(rng, (N, T)), dtype=float) for law in self.laws], axis=-1)
        ell = self.window
        if self.prehistory == "prior":
            L = eigh_sqrt(system.P0)
            past = system.x0 + rng.standard_normal((N, ell, n)) @ L.T
        elif self.prehistory == "hold":
            past = np.repeat(x[:, :1], ell, axis=1)
        else:
            past = np.zeros((N, ell, n))
        s = self.integral.window_sum(x, past)  # (N, T, n)
        if system.C.varying:
            Cs = np.stack([system.measurement(k) for k in range(1, T + 1)])  # (T, p, n)
            clean = np.einsum("tpn,btn->btp", Cs, s)
        else:
            clean = s @ system.measurement(1).T
        z = lam * clean + noise
        return z, {"failure_gain": lam, "prehistory": past, "y_transmitted": self.schedule.select(z)}

    def check(self, system: Any, steps: int | None = None) -> None:
        """The :class:`~tobitkf.channels.base.Channel` check: :meth:`check_system`."""
        self.check_system(system)

    def censor(self, y_latent: np.ndarray) -> np.ndarray:
        r"""(4) applied to every sensor's reading: :math:`\max(z, \tau)` (element-wise, so censoring then
        scheduling equals scheduling then censoring)."""
        return np.maximum(y_latent, self.threshold)

    def apply(self, rng: np.random.Generator, y: np.ndarray, extras: dict) -> np.ndarray:
        """Round-Robin, zero-input: keep the scheduled sensor's (censored) reading, (N, T, 1)."""
        out = self.schedule.select(y)
        extras["scheduled"] = self.schedule.scheduled(y.shape[-2])
        extras["uncensored"] = out > self.threshold  # (N, T, 1), laid out like y
        return out

    def __repr__(self) -> str:
        return (
            f"ProtocolChannel(sensors={self.sensors}, window={self.window}, failures={list(self.laws)}, "
            f"threshold={self.threshold}, prehistory={self.prehistory!r})"
        )
