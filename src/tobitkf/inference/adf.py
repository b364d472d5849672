r"""Deprecated: the inference package's own assumed-density filter, now :class:`~tobitkf.AssumedDensityTobitFilter`.

The smoothers, likelihoods and fits of :mod:`tobitkf.inference` were written before the package had
its assumed-density filter and carried a small exact-moment ADF of their own. The project keeps what
two families share once: they now run :class:`~tobitkf.AssumedDensityTobitFilter` with
``order="uncensored_first"`` (:func:`~tobitkf.filters.assumed_density.assumed_density_filter`), which gives
the same moments and log-likelihood terms (tested to 1e-12 against the old algorithm written out):
the uncensored readings of a step jointly (the Kalman update), then each censored reading in
channel order,

.. math::

    K = \bar Pc^T/s^2, \qquad \hat x = \bar x + K(m_{tr} - \mu), \qquad P = \bar P - K(s^2 - V_{tr})K^T,

with :math:`m_{tr}`, :math:`V_{tr}` the moments of the latent reading :math:`N(\mu, s^2)` truncated
to the censoring event, and the per-step term :math:`\log N(y_{k,u}; \hat y_u, S_{uu}) +
\sum_{l\ \text{censored}}\log\Phi(\pm(\text{limit}_l - \mu_l)/s_l)`.

:class:`ADFilter` remains as a thin alias for existing code and will be removed.
"""

from __future__ import annotations

import warnings

import numpy as np

from .._validation import ValidationError
from ..channels.censoring import Censoring
from ..filters.assumed_density import AssumedDensityTobitFilter
from ..models.linear import LinearSystem

__all__ = ["ADFilter"]

_RTOL = 1e-12


class ADFilter(AssumedDensityTobitFilter):
    r"""Deprecated alias: ``AssumedDensityTobitFilter(system, censoring, order="uncensored_first")``.

    Parameters
    ----------
    system : LinearSystem
        R diagonal; R = 0 allowed.
    censoring : Censoring
    rtol : float, default 1e-12
        The tolerance of the limit rule; the filter's rule is fixed at ``1e-12 max(1, |limit|)`` and
        only that value is accepted.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"

    Raises
    ------
    ValidationError
        ``rtol`` other than 1e-12; the filter's own input errors.

    Warns
    -----
    DeprecationWarning
        Always; use :class:`~tobitkf.AssumedDensityTobitFilter` with ``order="uncensored_first"``.

    Notes
    -----
    ``extras`` carry, besides the filter's ``log_likelihood`` (..., T), the old name ``log_lik`` for
    the same per-step terms, and ``side`` (..., T, m).
    """

    _name = "ADFilter"

    def __init__(
        self, system: LinearSystem, censoring: Censoring, *, rtol: float = _RTOL, covariance_update: str = "standard"
    ):
        warnings.warn(
            "tobitkf.inference.ADFilter is deprecated; use tobitkf.AssumedDensityTobitFilter(system, "
            "censoring, order='uncensored_first') (its extras['log_likelihood'] is the old 'log_lik')",
            DeprecationWarning,
            stacklevel=2,
        )
        if isinstance(rtol, bool) or not isinstance(rtol, (int, float, np.floating)) or rtol != _RTOL:
            raise ValidationError(f"rtol: the limit rule's tolerance is fixed at {_RTOL:g}, got {rtol!r}")
        super().__init__(system, censoring, covariance_update=covariance_update, order="uncensored_first")

    def _sequential(self, *args, **kwargs):
        x, P, S, extras = super()._sequential(*args, **kwargs)
        extras["log_lik"] = extras["log_likelihood"]
        return x, P, S, extras
