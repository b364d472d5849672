"""The objects of one grid point of a model-mode sweep: system, censoring and estimators.

Used by the parser (:func:`tobitkf.sweep.spec.parse_sweep` builds every grid point once, so that a
bad matrix fails on load) and by the runner (:mod:`tobitkf.sweep.run`); it needs neither.
"""

from __future__ import annotations

from typing import Any

__all__ = ["build_point"]


def build_point(spec: Any, point: dict[str, Any], *, threads: int | None = None):
    """System, censoring and estimator objects of one grid point (model mode).

    ``threads`` is passed to the estimators that split their runs over threads (the TKF's
    compiled kernel); None keeps their default."""
    from ..channels.censoring import Censoring
    from ..filters.kalman import DroppingKalmanFilter, KalmanFilter
    from ..filters.tobit import TobitKalmanFilter
    from ..models.linear import LinearSystem

    r = spec.resolved(point)
    sys_ = LinearSystem(**r["model"])
    cens = Censoring(**r["censoring"])
    cens.check(sys_.m, spec.steps)
    estimators = {}
    for key, est in r["estimators"].items():
        opts = {k: v for k, v in est.items() if k != "type"}
        if est["type"] == "KalmanFilter":
            estimators[key] = KalmanFilter(sys_, **opts)
        elif est["type"] == "DroppingKalmanFilter":
            estimators[key] = DroppingKalmanFilter(sys_, cens, **opts)
        else:
            estimators[key] = TobitKalmanFilter(sys_, cens, threads=threads, **opts)
    return sys_, cens, estimators
