r"""The interface every channel implements: what happens between the sensor and the estimator.

A channel takes part in a simulation at up to three stages, in this order, and every stage has a
do-nothing default so that a channel implements only what it does:

==============================================  ==========================================================
``draw(rng, x, system, noise, inputs)``          the sensor reading that replaces :math:`C_kx_k + D_ku_k + v_k`
                                                 (Rice fading, integral measurements with failures, random
                                                 saturation); returns ``(y_latent, extras)`` or ``None`` for
                                                 the plain linear reading
``censor(y_latent)``                             what a limited sensor reports (Tobit censoring, a threshold)
``apply(rng, y, extras)``                        what the network does with the censored reading afterwards
                                                 (scheduling, packet loss)
==============================================  ==========================================================

``check(system, steps)`` is called once, before anything is drawn or filtered, and raises a
:class:`~tobitkf.ShapeError` or :class:`~tobitkf.ValidationError` when the channel does not fit the
system. The estimator of a family reads the channel's statistics (limits, fading moments, failure
moments) through the channel's own documented attributes; the simulator draws it through this
interface (:func:`tobitkf.simulate`, ``channel=``).

Arrays: ``x`` is ``(N, T+1, n)`` (x_0..x_T), ``noise`` the ``(N, T, m)`` draw of :math:`v_k`, ``y``
and ``y_latent`` ``(N, T, m)`` (y_1..y_T at indices 0..T-1), ``extras`` a dict of the channel's own
random variables, kept in :attr:`SimulationData.extras <tobitkf.SimulationData.extras>`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["Channel", "refuse_feedthrough"]


class Channel:
    """Base class of the channel pieces (censoring, fading, protocol, saturation); see the module docstring."""

    def check(self, system: Any, steps: int | None = None) -> None:
        """Raise unless the channel fits ``system`` (and a horizon of ``steps``); default: always fits."""

    def draw(
        self, rng: np.random.Generator, x: np.ndarray, system: Any, noise: np.ndarray, inputs: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        """The latent readings ``(N, T, m)`` and the channel's draws; ``None``: the plain linear reading."""
        return None

    def censor(self, y_latent: np.ndarray) -> np.ndarray:
        """What the sensor reports for the latent readings ``(..., T, m)``; default: unchanged."""
        return y_latent

    def apply(self, rng: np.random.Generator, y: np.ndarray, extras: dict[str, Any]) -> np.ndarray:
        """What reaches the estimator after censoring; default: unchanged."""
        return y

    @property
    def measures(self) -> bool:
        """True when the channel replaces the linear reading (overrides :meth:`draw`)."""
        return type(self).draw is not Channel.draw


def refuse_feedthrough(system: Any, inputs: Any, reading: str) -> None:
    """Raise :class:`~tobitkf.ValidationError` for control ``inputs`` on a ``system`` with a feedthrough D when
    the channel's ``reading`` replaces :math:`Cx + Du + v` by a model without a :math:`Du` term (the
    protocol channel's integral reading, the randomly saturated one): drawing it would drop D u silently,
    as its filters would (they refuse it the same way)."""
    if inputs is not None and getattr(system, "D", None) is not None:
        from .._validation import ValidationError

        raise ValidationError(
            f"u: {reading} has no feedthrough D u; give the system no D (a control input enters through Bu only)"
        )
