r"""The particle filter's reading model of a :class:`~tobitkf.NonlinearSystem` (internal).

:class:`~tobitkf.ParticleFilter` on a nonlinear model is the bootstrap filter (Gordon, Salmond & Smith
1993): particles drawn from :math:`p(x_k \mid x_{k-1})`, :math:`x_k = f(x_{k-1}, k-1) + w_{k-1}`, weighted by
the exact likelihood of the reading through the channel, :math:`p(y_k \mid x_k) = \prod_l
p(y_{k,l} \mid y^*_{k,l} \sim N(h_l(x_k, k), R_{k,ll}))` (the channel's ``reading_log_likelihood``; no channel:
the plain Gaussian reading). Two channels have a reading model of their own, the linear model's with
:math:`C_kx_k` replaced by :math:`h(x_k, k)` (:mod:`tobitkf.filters._particle_models`, one likelihood for both),
each optionally followed by a :class:`~tobitkf.Censoring` of the reading:

* :class:`~tobitkf.RiceFading` of order 0, :math:`y^*_{k,l} = \vartheta_k(l)h_l(x_k, k) + v_{k,l}`: a Gaussian
  gain law marginalised exactly, :math:`y^*_{k,l} \mid x_k \sim N(\bar\vartheta_lh_l,
  \tilde\vartheta_lh_l^2 + R_{k,ll})`; any other law drawn per particle;
* :class:`~tobitkf.RandomSaturation`, the three modes :math:`\sigma(h_l(x_k, k))`, :math:`h_l(x_k, k)` and 0
  with probabilities :math:`\mu_l`, :math:`(1-\mu_l)\nu_l`, :math:`(1-\mu_l)(1-\nu_l)`, each plus
  :math:`v_{k,l}`.

With a linear :math:`h(x) = Cx` and :math:`f(x) = Ax` these give, for the same seed, the particles and weights of
the linear model's bootstrap filter (``proposal="prior"``). The predicted moments it reports (``pred_mean``, ``pred_cov``) are the
unscented prediction of the filtered moments (:class:`~tobitkf.UnscentedKalmanFilter`'s).

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
from ._particle_models import (
    SYSTEM_MODELS,
    _diag_sigma,
    _Fading,
    _flatten,
    _mat,
    _Model,
    _Saturation,
    channel_log_likelihood,
)
from .nonlinear import SigmaPoints, _sigma_moments

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

    @property
    def label(self) -> str:
        return f"nonlinear {type(self.channel).__name__}"

    def log_likelihood(self, rng, k, X, y, dy):
        sd = _diag_sigma(self.system, k, f"{type(self.channel).__name__} readings")
        return channel_log_likelihood(self.channel, k, y, self._h(k, X, dy), sd)

    def check_record(self, y2: np.ndarray, start: int) -> None:
        self.channel.check(self.system, start - 1 + y2.shape[1])
        self.channel.check_readings(y2, start=start)


class _NonlinearFading(_NonlinearDynamics, _Fading):
    r"""Fading of order 0, :math:`y^* = \vartheta\odot h(x_k, k) + v` (then censored): the linear fading model's law
    of the latent reading with :math:`C_kx_k` replaced by :math:`h(x_k, k)` (a feedthrough sits inside h)."""

    def __init__(self, system: NonlinearSystem, fading: RiceFading, censoring: Censoring | None):
        fading._check_nonlinear()
        super().__init__(system, fading, censoring)
        self._nonlinear_setup(system)

    @property
    def label(self) -> str:
        return "nonlinear fading"

    def modes(self, rng, k, X, dy):
        return self._faded_modes(rng, k, self._h(k, X, dy)[:, :, None, :], 0.0)


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
    Censoring given as ``censoring``; none: plain Gaussian readings), or through Rice fading of order 0 or random
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
