r"""Rice fading channel of order L (Geng et al. 2017, Signal Processing, (2); deviations: docs/sources/geng2017-fading.md).

Model, (2) of the source, per channel :math:`m = 1..n_y`:

.. math::

    y^*_k = \sum_{s=0}^{\ell_k} \vartheta_k(s)\, C_{k-s}\, x_{k-s} + D_k u_k + \upsilon_k,
    \qquad \ell_k = \min\{L, k\}, \qquad
    \vartheta_k(s) = \mathrm{diag}\{\vartheta^1_k(s), \dots, \vartheta^{n_y}_k(s)\}

The coefficients :math:`\vartheta^m_k(s)` are independent over :math:`(k, s, m)`
(GF-14): a **fresh draw at every reception time k and every delay s**,
so the same :math:`x_{k-s}` is weighted by different draws at different times.
Their law is any :mod:`tobitkf.channels.laws` law: :class:`~tobitkf.channels.laws.Gaussian`
(mean :math:`\bar\vartheta(s)`, variance :math:`\tilde\vartheta(s)`; the source's
Assumption 2), :class:`~tobitkf.channels.laws.Uniform` on [a, b] (the source's
conclusion, GF-15) or a :class:`~tobitkf.channels.laws.PMF` on a grid. Terms with
:math:`s > k` do not exist and are zero (the zero padding of GF-07).
The channel composes with censoring: ``simulate`` applies the Tobit limit (3)
after the fading ((3) of the source, GF-12), and the censoring indicator is the true mechanism
(3), not the Bernoulli fiction (4)–(5) (GF-12).

Time convention (package-wide): ``x`` holds :math:`x_0..x_T` at indices 0..T; the
measurement :math:`y_k` is stored at index k-1; the drawn coefficients
:math:`\vartheta_k(s)` at ``fading[..., k-1, s, m]``.

Code names: ``order`` = L, ``coefficients`` = the law of :math:`\vartheta(s)`,
``mean_gains`` = :math:`\bar\vartheta(s)`, ``var_gains`` = :math:`\tilde\vartheta(s)`.
This is Rice *channel* fading, not the "fading-memory" covariance inflation of filterpy.

``C_0`` (needed when L >= 1, for the term :math:`\vartheta_k(k) C_0 x_0`) is ``C(0)`` for
a callable ``C``, the constant ``C`` when constant, and ``C_1`` for a per-step ``(T, m, n)``
array (which stores :math:`C_1..C_T` only) (our convention; the source does not say).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError
from .base import Channel
from .laws import CoefficientLaw, Gaussian, as_law

__all__ = ["RiceFading", "measurement_matrix_at"]


def _check_order(order: Any) -> int:
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)):
        if isinstance(order, (float, np.floating)) and float(order).is_integer() and order >= 0:
            return int(order)
        raise ValidationError(f"order: expected a non-negative integer channel order L, got {order!r}")
    if order < 0:
        raise ValidationError(f"order: expected a non-negative integer channel order L, got {order}")
    return int(order)


def measurement_matrix_at(system, j: int) -> np.ndarray:
    """:math:`C_j` for j >= 0, with the ``C_0`` convention of the module docstring."""
    if j >= 1 or system.C.fn is not None:
        return system.C.at(j)
    if not system.C.varying:
        return system.C.array
    return system.C.at(1)


class RiceFading(Channel):
    r"""L-th order Rice fading channel with random coefficients (source (2), Assumption 2).

    Parameters
    ----------
    order : int
        Channel order :math:`L \ge 0`.
    coefficients : CoefficientLaw or array_like
        Law of :math:`\vartheta(s)`, core shape ``(L+1,)`` (the same law for every
        channel) or ``(L+1, m)`` (one per delay and channel). Plain numbers are
        deterministic gains.

    Raises
    ------
    ValidationError
        If ``order`` is negative or not an integer, or ``coefficients`` is not a law.
    ShapeError
        If ``coefficients`` does not have L+1 entries on its first axis.

    Examples
    --------
    The oscillator example of the source (Sec. 4.1): L = 2, means 0.95/0.75/0.85,
    variances 0.0081/0.0064/0.0049.

    >>> fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    >>> fad.order, fad.mean_gains(1).ravel().tolist()
    (2, [0.95, 0.75, 0.85])
    """

    section = "fading"
    sweep_options = {"order": int, "mean": object, "variance": object, "low": object, "high": object}

    @classmethod
    def from_options(cls, options: Any, system: Any = None) -> RiceFading:
        """A sweep file's ``[fading]``: ``order`` L and the coefficients' ``mean`` and ``variance`` per delay
        (a Gaussian law), or ``low``/``high`` (uniform).

        Raises
        ------
        ValidationError
            A missing order or means, both kinds of law given, an unknown key.
        """
        from .laws import Uniform

        tbl = dict(options)
        unknown = set(tbl) - set(cls.sweep_options)
        if unknown:
            raise ValidationError(f"{sorted(unknown)[0]}: not an option of [fading]")
        if "order" not in tbl:
            raise ValidationError("order: the [fading] channel needs its order L")
        if "low" in tbl or "high" in tbl:
            if "mean" in tbl or "variance" in tbl:
                raise ValidationError("mean: give either mean/variance (Gaussian) or low/high (uniform), not both")
            return cls(tbl["order"], Uniform(tbl.get("low"), tbl.get("high")))
        if "mean" not in tbl:
            raise ValidationError("mean: the [fading] channel needs the coefficients' means (or low/high)")
        return cls.gaussian(tbl["order"], tbl["mean"], tbl.get("variance", 0.0))

    def __init__(self, order: Any, coefficients: Any):
        self.order = _check_order(order)
        law = as_law(coefficients, "coefficients")
        if law.shape[:1] != (self.order + 1,) or len(law.shape) > 2:
            raise ShapeError(
                f"coefficients: expected a law of shape ({self.order + 1},) or ({self.order + 1}, m) "
                f"for order L={self.order}, got shape {law.shape}"
            )
        self.coefficients: CoefficientLaw = law

    @classmethod
    def gaussian(cls, order: Any, mean: Any, variance: Any = 0.0) -> RiceFading:
        r"""Gaussian coefficients :math:`\vartheta(s) \sim N(\bar\vartheta(s), \tilde\vartheta(s))` (Assumption 2)."""
        return cls(order, Gaussian(mean, variance))

    @property
    def channels(self) -> int | None:
        """Number of channels fixed by the law, or None when shared by all channels."""
        return self.coefficients.shape[1] if len(self.coefficients.shape) == 2 else None

    def check(self, m: Any, steps: int | None = None) -> None:
        """Raise :class:`ShapeError` unless the law fits ``m`` channels (or a system with ``m`` outputs)."""
        if not isinstance(m, (int, np.integer)):
            m = m.m
        if self.channels is not None and self.channels != m:
            raise ShapeError(f"coefficients: law has {self.channels} channels, the system has m={m}")

    def mean_gains(self, m: int) -> np.ndarray:
        r""":math:`\bar\vartheta(s)^m` as an ``(L+1, m)`` array."""
        self.check(m)
        mu = self.coefficients.mean
        return np.broadcast_to(mu if mu.ndim == 2 else mu[:, None], (self.order + 1, m)).copy()

    def var_gains(self, m: int) -> np.ndarray:
        r""":math:`\tilde\vartheta(s)^m` (variances) as an ``(L+1, m)`` array."""
        self.check(m)
        var = self.coefficients.variance
        return np.broadcast_to(var if var.ndim == 2 else var[:, None], (self.order + 1, m)).copy()

    def sample(self, rng: np.random.Generator, runs: int, steps: int, m: int) -> np.ndarray:
        r"""Draw :math:`\vartheta_k(s)^m` for k = 1..T: ``(runs, T, L+1, m)``, zero where s > k."""
        self.check(m)
        law = self.coefficients
        if law.shape == (self.order + 1,):
            theta = np.swapaxes(law.sample(rng, (runs, steps, m)), -1, -2)
        else:
            theta = law.sample(rng, (runs, steps))
        theta = np.array(theta, dtype=float)
        for s in range(1, self.order + 1):  # zero padding: no term s > k (k = 1..s-1)
            theta[:, : min(s - 1, steps), s, :] = 0.0
        return theta

    def draw(
        self, rng: np.random.Generator, x: np.ndarray, system, noise: np.ndarray, inputs: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        r"""Latent measurements :math:`y^*_k` of (2) for a batch of state trajectories.

        The hook called by :func:`tobitkf.simulate` (``measurement=``).

        Parameters
        ----------
        rng : numpy.random.Generator
        x : (N, T+1, n) ndarray
            True states :math:`x_0..x_T`.
        system : LinearSystem or NonlinearSystem
            A :class:`~tobitkf.NonlinearSystem` reads :math:`h(x_{k-s}, k-s)` in place of :math:`C_{k-s}x_{k-s}`.
        noise : (N, T, m) ndarray
            The drawn :math:`\upsilon_k`.
        inputs : (N, T, p) ndarray, optional
            Control inputs; ``D u_k`` is added unfaded.

        Returns
        -------
        y_latent : (N, T, m) ndarray
        extras : dict
            ``{"fading": (N, T, L+1, m)}``, the drawn :math:`\vartheta_k(s)`.
        """
        N, T1, n = x.shape
        T = T1 - 1
        m = system.m
        theta = self.sample(rng, N, T, m)
        if not hasattr(system, "C"):  # a NonlinearSystem: sum_s theta_k(s) h(x_(k-s), k-s) + v_k
            self._check_nonlinear(system)
            if self.order == 0:
                hx = np.stack(
                    [
                        system.measurement_map(x[:, k], k, None if inputs is None else inputs[:, k - 1])
                        for k in range(1, T1)
                    ],
                    axis=1,
                )
                return theta[:, :, 0] * hx + noise, {"fading": theta}
            cx = np.stack([system.measurement_map(x[:, j], j) for j in range(T + 1)], axis=1)  # h(x_j, j)
        elif system.C.varying:
            cx = np.stack([x[:, j] @ measurement_matrix_at(system, j).T for j in range(T + 1)], axis=1)
        else:
            cx = x @ measurement_matrix_at(system, 0).T  # (N, T+1, m): C_j x_j
        y = np.array(noise, dtype=float, copy=True)
        for s in range(self.order + 1):
            k0 = max(s, 1)  # first k with a term s
            if k0 > T:
                break
            y[:, k0 - 1 :] += theta[:, k0 - 1 :, s] * cx[:, k0 - s : T + 1 - s]
        if inputs is not None and getattr(system, "D", None) is not None:
            y += np.stack([inputs[:, k - 1] @ system.D.at(k).T for k in range(1, T + 1)], axis=1)
        return y, {"fading": theta}

    @property
    def draws_nonlinear(self) -> bool:
        r"""True: the reading :math:`\sum_{s\le\min(L,k)}\vartheta_k(s)h(x_{k-s}, k-s) + v_k` of a
        :class:`~tobitkf.NonlinearSystem` (:func:`tobitkf.simulate` draws it, term s = k with :math:`h(x_0, 0)`;
        the filters are in :mod:`tobitkf.filters.nonlinear_fading`); of order L > 0 for an ``h(x, k)`` without
        input."""
        return True

    def _check_nonlinear(self, system: Any) -> None:
        if self.order > 0 and system.h_takes_input:
            raise ValidationError(
                f"fading: an h(x, k, u) read through fading of order L={self.order} is not covered (the delayed "
                "terms h(x_(k-s), k-s) would need the past inputs); fold the input into h or use order 0"
            )

    def __repr__(self) -> str:
        return f"RiceFading(order={self.order}, coefficients={self.coefficients!r})"
