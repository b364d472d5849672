"""The models whose truth the simulators draw and whose structure the estimators use.

- :class:`LinearSystem` (:mod:`tobitkf.models.linear`): linear time-varying Gaussian state space,
  the model of the Kalman, Tobit, fading and protocol families and of the closed loops.
- :class:`ContinuousLinearSystem` (:mod:`tobitkf.models.continuous`): the same in continuous time,
  discretised exactly over each gap between irregular sample times.
- :class:`DelayFadingSystem`, :class:`HistoryPrior` (:mod:`tobitkf.models.delay`): pure-delay
  systems with multiplicative noise, fading measurements and correlated noises (Li, Li & Wang 2018).
- :class:`RossModel` (:mod:`tobitkf.models.ross`): sector-bounded plant with randomly saturating
  sensors (Wang, Shen & Liu), the model of the regional H∞ design.
"""

from .continuous import ContinuousLinearSystem, time_values
from .delay import DelayFadingSystem, FadingMoments, FadingPMF, HistoryPrior, paper_example, paper_fading, paper_prior
from .linear import LinearSystem
from .ross import RossModel, wang2010_model

__all__ = [
    "LinearSystem",
    "ContinuousLinearSystem",
    "time_values",
    "DelayFadingSystem",
    "HistoryPrior",
    "FadingPMF",
    "FadingMoments",
    "paper_example",
    "paper_prior",
    "paper_fading",
    "RossModel",
    "wang2010_model",
]
