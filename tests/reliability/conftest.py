"""Fixtures of the reliability tests."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="session", autouse=True)
def _compiled_shared_step():
    """Compile (or load from numba's disk cache) the compiled shared step once, before any test times a
    filter with :func:`tests.reliability._guards.no_hang`: the guard bounds the filter, not numba's one-time
    compilation (tens of seconds on a loaded machine)."""
    from tobitkf.filters.core import MeasurementPrediction, Transition, measurement_update, time_update

    x, P = np.zeros((1, 2)), np.eye(2)[None]
    time_update(x, P, None, Transition(A=np.eye(2), Qd=np.eye(2)), "standard", compiled=True)
    mp = MeasurementPrediction(expected=np.zeros((1, 1)), H0=np.ones((1, 2)), noise=np.ones((1, 1)))
    measurement_update(x, P, None, np.ones((1, 1)), mp, "standard", compiled=True)
