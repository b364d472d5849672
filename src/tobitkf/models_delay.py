"""Deprecated module: the delay model moved to :mod:`tobitkf.models.delay`, its simulator to
:mod:`tobitkf.simulate.delay`. This alias will be removed in the next release."""

import warnings

from .models.delay import (
    DelayFadingSystem,
    FadingMoments,
    FadingPMF,
    HistoryPrior,
    paper_example,
    paper_fading,
    paper_prior,
)
from .simulate.delay import full_states, simulate_delay

__all__ = [
    "DelayFadingSystem",
    "FadingMoments",
    "FadingPMF",
    "HistoryPrior",
    "paper_example",
    "paper_fading",
    "paper_prior",
    "full_states",
    "simulate_delay",
]

warnings.warn(
    "tobitkf.models_delay is deprecated: import from tobitkf.models.delay (the model) and "
    "tobitkf.simulate.delay (simulate_delay, full_states)",
    DeprecationWarning,
    stacklevel=2,
)
