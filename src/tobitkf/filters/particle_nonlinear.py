r"""The particle filter's reading model of a :class:`~tobitkf.NonlinearSystem` (internal).

:class:`~tobitkf.ParticleFilter` on a nonlinear model is the bootstrap filter (Gordon, Salmond & Smith
1993): particles drawn from :math:`p(x_k \mid x_{k-1})`, :math:`x_k = f(x_{k-1}, k-1) + w_{k-1}`, weighted by
the exact likelihood of the reading through the channel, :math:`p(y_k \mid x_k) = \prod_l
p(y_{k,l} \mid y^*_{k,l} \sim N(h_l(x_k, k), R_{k,ll}))` (the channel's ``reading_log_likelihood``; no channel:
the plain Gaussian reading). Two channels have a reading model of their own, the linear model's with
:math:`C_kx_k` replaced by :math:`h(x_k, k)` (:mod:`tobitkf.filters._particle_models`, one likelihood for both),
each optionally followed by a :class:`~tobitkf.Censoring` of the reading:

* :class:`~tobitkf.RiceFading` of order L, :math:`y^*_{k,l} = \sum_{s\le\min(L,k)}\vartheta_k(s)_lh_l(x_{k-s},
  k-s) + v_{k,l}`: a Gaussian gain law marginalised exactly, :math:`y^*_{k,l} \mid x_{k-L..k} \sim
  N(\sum_s\bar\vartheta(s)_lh_l, \sum_s\tilde\vartheta(s)_lh_l^2 + R_{k,ll})`; any other law drawn per particle.
  The particles carry the window :math:`[x_k; \dots; x_{k-L}]` (zero blocks before time 0), the top block moved by
  :math:`f`, the others shifted down; an ``h(x, k)`` without input for L > 0;
* :class:`~tobitkf.RandomSaturation`, the three modes :math:`\sigma(h_l(x_k, k))`, :math:`h_l(x_k, k)` and 0
  with probabilities :math:`\mu_l`, :math:`(1-\mu_l)\nu_l`, :math:`(1-\mu_l)(1-\nu_l)`, each plus
  :math:`v_{k,l}`.

With a linear :math:`h(x) = Cx` and :math:`f(x) = Ax` these give, for the same seed, the particles and weights of
the linear model's bootstrap filter (``proposal="prior"``). The predicted moments it reports (``pred_mean``, ``pred_cov``) are the
unscented prediction of the filtered moments (:class:`~tobitkf.UnscentedKalmanFilter`'s).

**The linearised optimal proposal** (``proposal="linearised"``; Doucet, Godsill & Andrieu 2000, §II.D.2), for one
contract channel with a ``region`` (:class:`~tobitkf.Censoring`, :class:`~tobitkf.Quantizer`, ...): per particle,
:math:`h` is linearised about a point :math:`a`, :math:`h(x) \approx Hx + o`, :math:`H = \partial h/\partial x(a)`,
:math:`o = h(a) - Ha`, and the linear model's locally optimal proposal is drawn for the exact readings E: the
channels in sequence (diagonal R), each conditioning :math:`N(\mu, Q_{k-1})`, :math:`\mu = f(x_{k-1}, k-1)`, on its
value (:math:`p_l = H_l\mu_{<l} + o_l`, :math:`s_l^2 = H_l\Sigma_{<l}H_l^T + R_{ll}`). The point is
:math:`a = \mu` (``linearisation_steps=1``, the extended Kalman update) or the result of s - 1 Gauss–Newton steps
:math:`a \leftarrow \mu + K(y_E - h_E(a) - H_E(\mu - a))`, :math:`K = QH_E^T(H_EQH_E^T + R_E)^{-1}` (the iterated
update, towards the mode of :math:`p(x_k \mid x_{k-1}, y_k)`). The readings that say an interval (censored,
quantized) do not move the proposal and enter the weight by their probability under the model. The weight

.. math::

    \log w = \sum_{l \in E}\Big[\log N(y_l; p_l, s_l^2) + \log N(y_l; h_l(x_k), R_{ll})
      - \log N(y_l; H_lx_k + o_l, R_{ll})\Big] + \sum_{l \notin E}\log p(y_l \mid x_k)

is :math:`p(y_k \mid x_k)p(x_k \mid x_{k-1})/q(x_k \mid x_{k-1}, y_k)` exactly (the linearised model's joint density
of :math:`x_k` and :math:`y_E` factors as :math:`q(x_k)\prod_{l\in E}N(y_l; p_l, s_l^2)`), so the filter stays
consistent however poor the linearisation. For a linear :math:`h` and exact readings the bracket's last two terms
cancel and the particles and weights are those of the linear model's ``"optimal"`` proposal for the same seed
(tested). A Gaussian per particle: where the posterior has a mode the linearisation does not see (a non-monotone h)
or a heavier tail than the Gaussian, the weights stay exact but their variance can be large, and the bootstrap
proposal (the default, ``"auto"``) is the safer choice. The Jacobian is the system's ``H`` or central differences.

**Known inputs.** With an ``f(x, k, u)`` (``NonlinearSystem(inputs=p)``) the filter's ``filter``, ``step`` and
``log_likelihood`` take ``u`` (..., T, p) as the Gaussian filters do (row k-1 holds :math:`u_k`): every particle
of a run moves by :math:`x_k = f(x_{k-1}, k-1, u_k) + w_{k-1}` with its run's input, and the reported prediction
pushes the sigma points through the same map. No ``u`` means :math:`u_k = 0`. With the same seed the result equals,
to rounding, that of the model with the inputs folded into ``f`` (a map ``f(x, k)`` that reads them itself).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._linalg import psd_sqrt
from .._validation import ValidationError
from ..channels.base import Channel
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading
from ..channels.saturation import RandomSaturation
from ..models.nonlinear import NonlinearSystem
from ._backend import BACKENDS
from ._particle_models import (
    SYSTEM_MODELS,
    _condition_in_sequence,
    _diag_sigma,
    _Fading,
    _flatten,
    _mat,
    _Model,
    _Saturation,
    channel_log_likelihood,
    region_reader,
)
from ._readings import _INTERIOR, _MISSING
from .nonlinear import SigmaPoints, _sigma_moments
from .nonlinear_fading_window import window_predict
from .particle import ParticleFilter
from .registry import family_entry, register

__all__ = ["nonlinear_model"]  # registered with the particle filter when imported (by tobitkf)

_PREDICTION = SigmaPoints("unscented")


class _NonlinearDynamics:
    """The bootstrap proposal of a NonlinearSystem and its reading map h, shared by its reading models."""

    system: Any
    nx: int
    n: int

    def _nonlinear_setup(self, system: NonlinearSystem) -> None:
        # the particle filter then hands the step's input u_k (N, p) to predict_moments/propagate as ``b``
        self.takes_input = system.takes_input
        # ... and, for an h(x, k, u), the same input to log_likelihood as ``dy``
        self.feedthrough_input = system.h_takes_input

    @staticmethod
    def _input(b: Any, rows: int) -> np.ndarray | None:
        """The input u_k of each run (``b``, (N, p); the scalar 0.0 when none is given) repeated for its ``rows``
        points (run-outermost), or None (no input: u = 0, or an f(x, k))."""
        if np.ndim(b) == 0:
            return None
        return np.repeat(np.asarray(b, dtype=float), rows, axis=0)

    def predict_moments(self, k, x, P, b):
        sys_ = self.system
        L = _PREDICTION.unit(self.nx)[0].shape[0]
        u = self._input(b, L)
        xp, _, Pf = _sigma_moments(_PREDICTION, lambda z: sys_.transition_map(z, k - 1, u), x, P)
        return xp, Pf + sys_.process_cov(k - 1)

    def propagate(self, rng, k, X, b):
        N, Np, n = X.shape
        Xn = self.system.transition_map(X.reshape(N * Np, n), k - 1, self._input(b, Np)).reshape(N, Np, n)
        G = psd_sqrt(self.system.process_cov(k - 1))
        z = rng.standard_normal((N, Np, G.shape[1]))
        return Xn + _mat(z, G.T)

    def _h(self, k, X, dy):
        """:math:`h(x_k, k)` (or :math:`h(x_k, k, u_k)`, ``dy`` the input) of every particle, (N, Np, m)."""
        N, Np, n = X.shape
        return self.system.measurement_map(X.reshape(N * Np, n), k, self._input(dy, Np)).reshape(N, Np, -1)


class _Nonlinear(_NonlinearDynamics, _Model):
    """A channel of the measurement contract: the weight is its ``reading_log_likelihood`` of y* ~ N(h(x), R_ll)."""

    def __init__(self, system: NonlinearSystem, channel: Channel):
        self.system: Any = system
        self.n = system.n
        channel.check(system)
        self.channel = channel
        self.nx, self.m = system.n, system.m
        self._nonlinear_setup(system)
        self.linearised = type(channel).region is not Channel.region  # the readings say an interval of y*

    @property
    def label(self) -> str:
        return f"nonlinear {type(self.channel).__name__}"

    def propose(self, rng, k, X, y, b, dy, xp=None, Pp=None):
        r"""The linearised locally optimal proposal (``proposal="linearised"``, module docstring): per particle, the
        exact readings in sequence conditioned on under :math:`h` linearised about :math:`\mu = f(x_{k-1}, k-1)`
        (or the point of ``steps - 1`` Gauss–Newton steps from it), the interval readings left to the weight, which
        is exact. Returns (X_new (N, Np, n), log weight (N, Np))."""
        sys_ = self.system
        N, Np, n = X.shape
        m = self.m
        mu = sys_.transition_map(X.reshape(N * Np, n), k - 1, self._input(b, Np))
        uh = self._input(dy, Np)
        r = _diag_sigma(sys_, k, f"{type(self.channel).__name__} readings") ** 2
        # the uniforms the linear proposal draws for its interval readings, so that a linear h draws its numbers
        cls, reading = region_reader(self.channel, k, y, rng.random((N, Np, m)))
        exact = cls == _INTERIOR  # (N, m); the interval readings enter the weight only
        Q = sys_.process_cov(k - 1)
        at = mu
        ex = np.repeat(exact, Np, axis=0)  # (N Np, m)
        yy = np.repeat(np.where(exact, y, 0.0), Np, axis=0)
        for _ in range(self.steps - 1):  # x <- mu + K(y - h(x) - H(mu - x)), K = Q H^T (H Q H^T + R)^-1
            H = sys_.measurement_jacobian(at, k, uh) * ex[:, :, None]
            innov = np.where(ex, yy - sys_.measurement_map(at, k, uh), 0.0) + np.einsum("qij,qj->qi", H, at - mu)
            S = H @ Q @ np.swapaxes(H, -1, -2) + np.where(ex, r, 1.0)[:, :, None] * np.eye(m)
            at = mu + np.einsum("ij,qkj,qk->qi", Q, H, np.linalg.solve(S, innov[..., None])[..., 0])
        H = sys_.measurement_jacobian(at, k, uh)  # (N Np, m, n)
        off = sys_.measurement_map(at, k, uh) - np.einsum("qij,qj->qi", H, at)
        H, off, mu = H.reshape(N, Np, m, n), off.reshape(N, Np, m), mu.reshape(N, Np, n)
        eps = rng.standard_normal((N, Np, n))
        cond = np.where(exact, cls, _MISSING).astype(cls.dtype)
        Xn, logw = _condition_in_sequence(mu, Q, H, off, r[None, :], cond, reading, eps)
        # log N(y; h(x_k), r) - log N(y; H x_k + o, r): the model's density of an exact reading over the linearised
        # one's; an interval reading: its probability under the model
        hx = self._h(k, Xn, dy)
        lin = np.einsum("rpij,rpj->rpi", H, Xn) + off
        yl = np.where(exact, y, 0.0)[:, None, :]
        corr = ((yl - lin) ** 2 - (yl - hx) ** 2) / (2.0 * r)
        logw = logw + np.where(exact[:, None, :], corr, 0.0).sum(axis=-1)
        interval = np.where(exact, np.nan, y)
        return Xn, logw + channel_log_likelihood(self.channel, k, interval, hx, np.sqrt(r))

    def log_likelihood(self, rng, k, X, y, dy):
        sd = _diag_sigma(self.system, k, f"{type(self.channel).__name__} readings")
        return channel_log_likelihood(self.channel, k, y, self._h(k, X, dy), sd)

    def check_record(self, y2: np.ndarray, start: int) -> None:
        self.channel.check(self.system, start - 1 + y2.shape[1])
        self.channel.check_readings(y2, start=start)


class _NonlinearFading(_NonlinearDynamics, _Fading):
    r"""Fading of order L, :math:`y^* = \sum_s\vartheta(s)\odot h(x_{k-s}, k-s) + v` (then censored): the linear
    fading model's law of the latent reading with :math:`C_{k-s}x_{k-s}` replaced by :math:`h(x_{k-s}, k-s)` (a
    feedthrough sits inside h, order 0 only), the window of past states moved by f."""

    def __init__(self, system: NonlinearSystem, fading: RiceFading, censoring: Censoring | None):
        fading._check_nonlinear(system)
        super().__init__(system, fading, censoring)
        self._nonlinear_setup(system)

    @property
    def label(self) -> str:
        return "nonlinear fading"

    def predict_moments(self, k, x, P, b):
        if not self.L:
            return super().predict_moments(k, x, P, b)
        return window_predict(_PREDICTION, self.system, self.nx, k, x, P, None if np.ndim(b) == 0 else b)

    def propagate(self, rng, k, X, b):
        top = super().propagate(rng, k, X[..., : self.n], b)  # the window shifts down one
        return np.concatenate([top, X[..., : self.nx - self.n]], axis=-1)

    def modes(self, rng, k, X, dy):
        n = self.n
        terms = [self._h(k - s, X[..., s * n : (s + 1) * n], dy) for s in range(min(self.L, k) + 1)]
        return self._faded_modes(rng, k, np.stack(terms, axis=2), 0.0)


class _NonlinearSaturation(_NonlinearDynamics, _Saturation):
    r"""Random saturation of :math:`h(x_k, k)`: the linear saturation model's three modes with :math:`C_kx_k`
    replaced by :math:`h(x_k, k)`; bootstrap proposal only (the closed-form proposal needs a linear reading)."""

    optimal = False

    def __init__(self, system: NonlinearSystem, channel: RandomSaturation, censoring: Censoring | None):
        super().__init__(system, channel, censoring)
        self._nonlinear_setup(system)

    @property
    def label(self) -> str:
        return "nonlinear saturation"

    def modes(self, rng, k, X, dy):
        return self._saturated_modes(k, self._h(k, X, dy))


#: the channels with a reading model of their own (tobitkf.filters._particle_models) -> their NonlinearSystem form
_READING_MODELS: dict[type, Any] = {RiceFading: _NonlinearFading, RandomSaturation: _NonlinearSaturation}


def _reading_model(piece: Any) -> Any:
    """The NonlinearSystem reading model of ``piece`` (by its class or a parent's), or None."""
    return next((_READING_MODELS[t] for t in type(piece).__mro__ if t in _READING_MODELS), None)


def nonlinear_model(system: Any, channel: Any, censoring: Any) -> _Model:
    """The particle filter's model of ``system`` (a NonlinearSystem) read through one contract channel (or a
    Censoring given as ``censoring``; none: plain Gaussian readings), or through Rice fading of any order or random
    saturation, either with an optional Censoring of the reading."""
    pieces = _flatten(channel) + ([] if censoring is None else [censoring])
    own = [(p, model) for p in pieces if (model := _reading_model(p)) is not None]
    cens = [p for p in pieces if isinstance(p, Censoring)]
    if len(own) == 1 and len(cens) <= 1 and len(pieces) == 1 + len(cens):
        piece, model = own[0]
        return model(system, piece, cens[0] if cens else None)
    if len(pieces) > 1:
        raise ValidationError(
            "channel: the particle filter of a NonlinearSystem takes one channel piece (or RiceFading or "
            "RandomSaturation with a Censoring), got " + ", ".join(type(p).__name__ for p in pieces)
        )
    piece = pieces[0] if pieces else Censoring()
    if not isinstance(piece, Channel) or not piece.supports("likelihood"):
        raise ValidationError(
            f"channel: {type(piece).__name__} supplies neither region() nor reading_moments() "
            "(tobitkf.channels.base), which the particle filter of a NonlinearSystem needs"
        )
    return _Nonlinear(system, piece)


SYSTEM_MODELS[NonlinearSystem] = nonlinear_model


# The particle filter's registry entry, beside its other registration (the model of a NonlinearSystem above)
register(
    family_entry(
        ParticleFilter,
        "bootstrap / optimal-proposal particle filter on any channel: the Bayes optimum (beyond the sources)",
        ("channel",),
        needs=(),  # no channel piece: linear readings
        options={
            "particles": int,
            "resample_threshold": float,
            "proposal": ("auto", "optimal", "prior", "rao_blackwellised"),
            "seed": object,
            "backend": BACKENDS,  # compiled for linear readings with censoring; the other channels run numpy
        },
        required=("seed",),  # a registry-built particle filter draws the same particles on every run
    )
)
