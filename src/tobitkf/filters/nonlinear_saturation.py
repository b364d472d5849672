r"""Randomly saturated readings of a :class:`~tobitkf.NonlinearSystem`: the assumed-density filter.

The reading of sensor l is the randomly occurring saturation with missing measurements of Wang, Shen & Liu
((2)–(3); :class:`~tobitkf.RandomSaturation`) with :math:`C_lx_k` replaced by :math:`h_l(x_k, k)`:

.. math::

    y_k(l) = \alpha_k^l\,\sigma(h_l(x_k)) + (1 - \alpha_k^l)\beta_k^l\,h_l(x_k) + v_k(l), \qquad
    \sigma(c) = \mathrm{sign}(c)\min\{u_l, |c|\},

:math:`\alpha \sim \mathrm{Bernoulli}(\mu_l)` (saturated), :math:`\beta \sim \mathrm{Bernoulli}(\nu_l)` (arrives
when not saturated). Channel by channel, the sigma-point linearisation of :math:`h_l` about the prediction (or,
with ``iterations > 1``, about the posterior) gives :math:`c = h_l(x) \approx N(\mu, s^2_c)` with
:math:`\mu = \hat y_l`, :math:`s^2_c = P_{yy,ll}` (plus the linearisation's :math:`\Omega` when re-linearised)
and covariance :math:`P_{xy,\cdot l}` with x; the three modes (saturated: the three pieces of :math:`\sigma(c)`;
linear: the Kalman update; noise only: no change) are weighed by their posterior probabilities and merged
into one Gaussian, exactly the update of the linear :class:`~tobitkf.SaturationAssumedDensityFilter`, whose
compiled moments (:func:`~tobitkf.filters._compiled_moments.saturation_block`) both paths of this filter call.
For a linear h it is that filter (tested).
"""

from __future__ import annotations

import numpy as np

from .._validation import check_instance
from ..channels.saturation import RandomSaturation
from ..models.nonlinear import NonlinearSystem
from ._boundary import _noise_variances
from .core import _TINY
from .nonlinear_adf import NonlinearAssumedDensityFilter

__all__ = ["SaturationNonlinearAssumedDensityFilter"]


class SaturationNonlinearAssumedDensityFilter(NonlinearAssumedDensityFilter):
    r"""The assumed-density filter of a nonlinear model read through randomly saturating sensors (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal with positive entries.
    channel : RandomSaturation
        The saturation probabilities :math:`\mu`, the arrival probabilities :math:`\nu` and the levels u.
    rule, alpha, beta, kappa, order, iterations, backend
        As :class:`~tobitkf.NonlinearAssumedDensityFilter`.

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, ``channel`` not a RandomSaturation, R not diagonal or a variance not
        positive, an unknown rule or a bad parameter.
    ShapeError
        A channel whose sensors do not match the system's outputs.

    Notes
    -----
    Extras: ``log_likelihood`` (..., T), :math:`\sum_l\log p(y_k(l))` under the first linearisation of each
    channel. Only the standard covariance form.

    Examples
    --------
    Sensors that never saturate and always deliver give the unscented assumed-density filter of plain readings:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.NonlinearSystem(lambda x, k: 0.9 * x, lambda x, k: np.sin(x), Q=[[0.1]], R=[[0.5]], x0=[0.2], P0=[[1.0]])
    >>> y = np.array([[0.3], [-0.4], [0.7]])
    >>> a = tk.SaturationNonlinearAssumedDensityFilter(sys, tk.RandomSaturation(mu=[0.0], nu=[1.0])).filter(y)
    >>> b = tk.NonlinearAssumedDensityFilter(sys, tk.Censoring()).filter(y)
    >>> bool(np.allclose(a.mean, b.mean, rtol=0, atol=1e-12))
    True
    """

    _name = "SaturationNonlinearAssumedDensityFilter"
    _forms = ("standard",)

    def _take_channel(self, system: NonlinearSystem, channel: RandomSaturation) -> None:
        """The saturation channel, its noise variances (positive) and the parameters of ``saturation_block``."""
        check_instance(channel, RandomSaturation, "channel")
        channel.check(system)
        self.channel = channel
        self._r = (
            None
            if system.R.varying
            else _noise_variances(system.measurement_cov(1), "R", positive="the saturation filter")
        )
        with np.errstate(divide="ignore"):
            mu, nu = channel.mu, channel.nu
            logp = np.stack([np.log(mu), np.log((1 - mu) * nu), np.log((1 - mu) * (1 - nu))], axis=-1)
        #: per sensor (u, log P(saturated), log P(linear), log P(noise only)): the parameters of saturation_block
        self._par = np.ascontiguousarray(np.concatenate([channel.level[:, None], logp], axis=1))

    def _compiled_channel(self, k0: int, T: int):
        """``(family, lo, hi, par, noise_code)`` of the compiled loop (its ``channel_arrays``; ``family`` a kind)."""
        from ._compiled_moments import SATURATION, kind

        inf = np.full((1, self.m), np.inf)
        return kind(SATURATION), -inf, inf, self._par[None].copy(), 0

    def _latent_moments(self, k, l, y, has, mu, s2, ll):
        r"""The three modes' merged moments of the latent reading :math:`y^* \sim N(\mu, s^2)`, :math:`s^2 =
        s_c^2 + R_{ll}`, from :func:`~tobitkf.filters._compiled_moments.saturation_block`'s :math:`(\alpha,
        \beta)`: :math:`E = \mu + \alpha s^2`, :math:`V = s^2 - \beta s^4` (the projection's form)."""
        from ._compiled_moments import INTERIOR, SATURATION, family_array, kind

        r = (
            self._r
            if self._r is not None
            else _noise_variances(self._noise(k), f"R({k})", positive="the saturation filter")
        )[l]
        ok = has & (s2 > _TINY)
        obs, V = np.array(mu), np.zeros(mu.shape[0])
        if ok.any():
            q = int(ok.sum())
            sv = np.ascontiguousarray(s2[ok])
            alpha, beta, lp, _, _ = family_array(
                kind(SATURATION), np.ascontiguousarray(y[ok]), np.full(q, INTERIOR, dtype=np.int8),
                np.ascontiguousarray(mu[ok]), sv - r, np.full(q, float(r)), np.full(q, -np.inf), np.full(q, np.inf),
                self._par[l].copy(), 3,
            )  # fmt: skip
            obs[ok] = mu[ok] + alpha * sv
            V[ok] = sv - beta * sv * sv
            if ll is not None:
                ll[ok] = lp
        return ok, obs, V
