"""Estimators, one source family per module, all with the same batched call shape."""

from .core import FilterResult
from .kalman import DroppingKalmanFilter, KalmanFilter, kalman_filter
from .tobit import TobitKalmanFilter, tobit_kalman_filter, tobit_update

__all__ = [
    "FilterResult",
    "KalmanFilter",
    "DroppingKalmanFilter",
    "kalman_filter",
    "TobitKalmanFilter",
    "tobit_kalman_filter",
    "tobit_update",
]
