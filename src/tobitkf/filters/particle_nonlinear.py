r"""The particle filter's reading model of a :class:`~tobitkf.NonlinearSystem` (internal).

:class:`~tobitkf.ParticleFilter` on a nonlinear model is the bootstrap filter (Gordon, Salmond & Smith
1993): particles drawn from :math:`p(x_k \mid x_{k-1})`, :math:`x_k = f(x_{k-1}, k-1) + w_{k-1}`, weighted by
the exact likelihood of the reading through the channel, :math:`p(y_k \mid x_k) = \prod_l
p(y_{k,l} \mid y^*_{k,l} \sim N(h_l(x_k, k), R_{k,ll}))` (the channel's ``reading_log_likelihood``; no channel:
the plain Gaussian reading). The predicted moments it reports (``pred_mean``, ``pred_cov``) are the
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
from ..models.nonlinear import NonlinearSystem
from ._particle_models import SYSTEM_MODELS, _diag_sigma, _flatten, _mat, _Model, channel_log_likelihood
from .nonlinear import SigmaPoints, _sigma_moments

__all__ = ["nonlinear_model"]  # registered with the particle filter when imported (by tobitkf)

_PREDICTION = SigmaPoints("unscented")


class _Nonlinear(_Model):
    """Bootstrap proposal and contract likelihood for a NonlinearSystem."""

    def __init__(self, system: NonlinearSystem, channel: Channel):
        self.system: Any = system
        self.n = system.n
        channel.check(system)
        self.channel = channel
        self.nx, self.m = system.n, system.m
        # the particle filter then hands the step's input u_k (N, p) to predict_moments/propagate as ``b``
        self.takes_input = system.takes_input
        # ... and, for an h(x, k, u), the same input to log_likelihood as ``dy``
        self.feedthrough_input = system.h_takes_input

    @property
    def label(self) -> str:
        return f"nonlinear {type(self.channel).__name__}"

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

    def log_likelihood(self, rng, k, X, y, dy):
        N, Np, n = X.shape
        mu = self.system.measurement_map(X.reshape(N * Np, n), k, self._input(dy, Np)).reshape(N, Np, self.m)
        sd = _diag_sigma(self.system, k, f"{type(self.channel).__name__} readings")
        return channel_log_likelihood(self.channel, k, y, mu, sd)

    def check_record(self, y2: np.ndarray, start: int) -> None:
        self.channel.check(self.system, start - 1 + y2.shape[1])
        self.channel.check_readings(y2, start=start)


def nonlinear_model(system: Any, channel: Any, censoring: Any) -> _Model:
    """The particle filter's model of ``system`` (a NonlinearSystem) read through one contract channel (or a
    Censoring given as ``censoring``; none: plain Gaussian readings)."""
    pieces = _flatten(channel) + ([] if censoring is None else [censoring])
    if len(pieces) > 1:
        raise ValidationError(
            "channel: the particle filter of a NonlinearSystem takes one channel piece, got "
            + ", ".join(type(p).__name__ for p in pieces)
        )
    piece = pieces[0] if pieces else Censoring()
    if not isinstance(piece, Channel) or not piece.supports("likelihood"):
        raise ValidationError(
            f"channel: {type(piece).__name__} supplies neither region() nor reading_moments() "
            "(tobitkf.channels.base), which the particle filter of a NonlinearSystem needs"
        )
    return _Nonlinear(system, piece)


SYSTEM_MODELS[NonlinearSystem] = nonlinear_model
