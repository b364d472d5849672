r"""Randomly occurring sensor saturation (ROSS) with missing measurements.

Source: Wang, Shen, Liu, "H∞ filtering with randomly occurring sensor saturations and
missing measurements", eqs. (2)–(3) and Remark 2.

For sensor :math:`i = 1..m` at time :math:`k`

.. math::

    y_k^i = \alpha_k^i\,\sigma(C_i x_k) + (1-\alpha_k^i)\beta_k^i\,C_i x_k + D_i v_k^i  \qquad (2)

with :math:`\sigma(v) = \mathrm{sign}(v)\min\{u_i, |v|\}` (eq. (3) with level :math:`u_i`,
the paper fixes :math:`u_i = 1`), :math:`\alpha_k^i \sim \mathrm{Bernoulli}(\mu_i)`
(saturation occurs) and :math:`\beta_k^i \sim \mathrm{Bernoulli}(\nu_i)` (measurement
arrives, given no saturation). All :math:`2m` variables are drawn independently at every
step (independence across i, between α^i and β^i, and in time: docs/sources WH-05).

Sensor modes (Remark 2): saturated with probability μ_i, normal (linear) with
probability (1−μ_i)ν_i, missing (noise only) with probability (1−μ_i)(1−ν_i).

Moments used by the LMIs (symbols under (13)): with
:math:`a_i = \alpha^i-\mu_i` and :math:`b_i = (1-\alpha^i)\beta^i-(1-\mu_i)\nu_i`,
``var_alpha`` = ϱ_i = E a_i², ``var_beta`` = δ_i = E b_i², ``cov_alpha_beta`` = −ς_i = E a_i b_i
(``varsigma`` = ς_i).

Code name -> paper symbol: ``mu`` μ_i (\bar Λ_α), ``nu`` ν_i (\bar Λ_β), ``level`` u_i (1 in
the paper), ``alpha``/``beta`` α_k^i/β_k^i.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array, check_probability
from .base import Channel, refuse_feedthrough

__all__ = ["RandomSaturation", "saturate"]


def saturate(v: Any, level: Any = 1.0) -> np.ndarray:
    r"""Saturation (3): :math:`\sigma(v) = \mathrm{sign}(v)\min\{u, |v|\}` component-wise.

    ``level`` (u) broadcasts against the last axis of ``v``; ``σ(0) = 0`` (WH-15).
    """
    v = np.asarray(v, dtype=float)
    level = np.asarray(level, dtype=float)
    return np.clip(v, -level, level)


class RandomSaturation(Channel):
    """The ROSS + missing-measurement sensor channel of eq. (2).

    Parameters
    ----------
    mu : (m,) array_like
        Saturation probabilities μ_i = Prob{α^i = 1}, in [0, 1].
    nu : (m,) array_like
        Arrival probabilities ν_i = Prob{β^i = 1} (used when not saturated), in [0, 1].
    level : float or (m,) array_like, default 1.0
        Saturation levels u_i > 0. The paper uses 1 ("without loss of generality"); a
        level other than 1 is *not* a rescaling of C_i here because the linear branch
        is unsaturated (WH-13), so the LMIs carry it explicitly.

    Raises
    ------
    ValidationError
        Probabilities outside [0, 1], levels <= 0 or non-finite.
    ShapeError
        ``mu``, ``nu``, ``level`` not of one common length m.
    """

    section = "saturation"  # no sweep-file section: the registry and the particle filter name it

    def __init__(self, mu: Any, nu: Any, level: Any = 1.0):
        mu = np.atleast_1d(check_probability(mu, "mu"))
        nu = np.atleast_1d(check_probability(nu, "nu"))
        if mu.ndim != 1 or nu.ndim != 1 or mu.shape != nu.shape:
            raise ShapeError(f"mu, nu: expected two vectors of the same length m, got shapes {mu.shape} and {nu.shape}")
        level_arr = as_float_array(level, "level")
        if (level_arr <= 0).any():
            raise ValidationError(f"level: expected saturation levels > 0, got {level_arr.ravel()}")
        level_arr = np.broadcast_to(level_arr, mu.shape).copy() if level_arr.ndim == 0 else level_arr
        if level_arr.shape != mu.shape:
            raise ShapeError(f"level: expected a scalar or shape {mu.shape}, got shape {level_arr.shape}")
        self.mu, self.nu, self.level = mu, nu, level_arr

    @property
    def m(self) -> int:
        """Number of sensors."""
        return self.mu.shape[0]

    def check(self, system: Any, steps: int | None = None) -> None:
        """Raise :class:`ShapeError` unless the system has m outputs (one per sensor)."""
        m = system if isinstance(system, (int, np.integer)) else system.m
        if m != self.m:
            raise ShapeError(f"system: expected {self.m} measurement channels (length of mu), got {m}")

    # --- statistics (under (13)) ---------------------------------------------------
    @property
    def var_alpha(self) -> np.ndarray:
        """ϱ_i = μ_i(1−μ_i) = E(α^i−μ_i)²."""
        return self.mu * (1 - self.mu)

    @property
    def var_beta(self) -> np.ndarray:
        """δ_i = (1−μ_i)ν_i − (1−μ_i)²ν_i² = E((1−α^i)β^i − (1−μ_i)ν_i)²."""
        q = (1 - self.mu) * self.nu
        return q - q * q

    @property
    def varsigma(self) -> np.ndarray:
        """ς_i = (1−μ_i)μ_iν_i, so E(α^i−μ_i)((1−α^i)β^i−(1−μ_i)ν_i) = −ς_i."""
        return (1 - self.mu) * self.mu * self.nu

    def mode_probabilities(self) -> dict[str, np.ndarray]:
        """Remark 2: probabilities of the saturated, normal and missing modes, each (m,)."""
        return {
            "saturated": self.mu.copy(),
            "normal": (1 - self.mu) * self.nu,
            "missing": (1 - self.mu) * (1 - self.nu),
        }

    @property
    def draws_nonlinear(self) -> bool:
        r"""True: :func:`tobitkf.simulate` draws (2) for a :class:`~tobitkf.NonlinearSystem` with :math:`h(x_k, k)`
        in place of :math:`C_kx_k` (its filters: :class:`~tobitkf.SaturationNonlinearAssumedDensityFilter`, the
        particle filter)."""
        return True

    # --- drawing and applying -------------------------------------------------------
    def draw_modes(self, rng: np.random.Generator, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Draw α and β of shape ``shape + (m,)`` (0/1 floats), α first, then β."""
        size = tuple(shape) + (self.m,)
        alpha = (rng.random(size) < self.mu).astype(float)
        beta = (rng.random(size) < self.nu).astype(float)
        return alpha, beta

    def measure(self, cx: Any, alpha: Any, beta: Any, noise: Any = 0.0) -> np.ndarray:
        r"""Eq. (2): :math:`\alpha\sigma(c) + (1-\alpha)\beta c + \text{noise}` for ``cx`` (..., m).

        ``noise`` is :math:`D_i v^i` (already scaled), broadcast against ``cx``.
        """
        cx = np.asarray(cx, dtype=float)
        if cx.shape[-1:] != (self.m,):
            raise ShapeError(f"cx: expected last axis of length m={self.m}, got shape {cx.shape}")
        alpha = np.asarray(alpha, dtype=float)
        beta = np.asarray(beta, dtype=float)
        return alpha * saturate(cx, self.level) + (1 - alpha) * beta * cx + noise

    def draw(
        self, rng: np.random.Generator, x: np.ndarray, system: Any, noise: np.ndarray, inputs: Any = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Measurement-model hook of :func:`tobitkf.simulate`: eq. (2) on a linear system, or on a
        :class:`~tobitkf.NonlinearSystem` with :math:`h(x_k, k)` (or :math:`h(x_k, k, u_k)`) in place of
        :math:`C_kx_k`.

        ``x`` is (N, T+1, n), ``noise`` the (N, T, m) draw of v_k; returns y_1..y_T and the
        draws ``{"alpha", "beta"}`` (N, T, m). Lets the linear-Gaussian simulator produce ROSS
        measurements for the other estimators (Gaussian noise instead of the paper's l_2 noise).
        """
        N, T = noise.shape[0], noise.shape[1]
        if hasattr(system, "C"):
            refuse_feedthrough(system, inputs, "the randomly saturated reading (2)")
        alpha, beta = self.draw_modes(rng, (N, T))
        if not hasattr(system, "C"):  # a NonlinearSystem (draws_nonlinear): an input enters through h
            cx = np.stack(
                [
                    system.measurement_map(x[:, k], k, None if inputs is None else inputs[:, k - 1])
                    for k in range(1, T + 1)
                ],
                axis=1,
            )
        else:
            cx = np.stack([x[:, k] @ system.measurement(k).T for k in range(1, T + 1)], axis=1)
        if cx.shape[-1] != self.m:
            raise ShapeError(f"system: expected {self.m} measurement channels (length of mu), got {cx.shape[-1]}")
        return self.measure(cx, alpha, beta, noise), {"alpha": alpha, "beta": beta}
