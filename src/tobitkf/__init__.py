"""tobitkf: state estimation and control from imperfect measurements.

Censored (Tobit), saturated, fading, delayed, missing, failed, integrated and
protocol-scheduled measurements; batched over Monte Carlo runs.

Public API (stable):

- :class:`LinearSystem` -- the state-space model.
- :class:`Censoring`, :func:`multi_region` -- censoring limits.
- :func:`simulate` -- batched truth and measurements.
- :class:`KalmanFilter`, :class:`DroppingKalmanFilter`, :class:`TobitKalmanFilter`,
  :class:`SteadyStateTobitKalmanFilter` -- estimators.
- :func:`censored_moments` -- censored-normal statistics, safe in the tails.
- :mod:`tobitkf.metrics` -- RMSE, bias, NEES.
"""

from ._validation import ShapeError, ValidationError
from .censored import CensoredMoments, censored_moments
from .channels import Censoring, multi_region
from .filters import (DroppingKalmanFilter, FilterResult, KalmanFilter, TobitKalmanFilter, kalman_filter,
                      tobit_kalman_filter)
from .filters.steady_state import SteadyStateTobitKalmanFilter, tobit_kalman_filter_controlled
from .models import LinearSystem
from .simulate import SimulationData, simulate
from . import metrics

__version__ = "0.1.0"

__all__ = [
    "LinearSystem", "Censoring", "multi_region", "simulate", "SimulationData",
    "KalmanFilter", "DroppingKalmanFilter", "TobitKalmanFilter", "kalman_filter", "tobit_kalman_filter",
    "SteadyStateTobitKalmanFilter", "tobit_kalman_filter_controlled",
    "FilterResult", "censored_moments", "CensoredMoments", "metrics", "ShapeError", "ValidationError",
    "__version__",
]
