"""Inputs the second audit left answering with a plain Python error (found at its close)."""

from __future__ import annotations

import pytest

import tobitkf as tk
from tobitkf._validation import ValidationError

SYS = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])


@pytest.mark.parametrize("rtol", [10**400, -1.0, True, "1e-9", float("nan")])
def test_dropping_kf_rtol_is_a_named_error(rtol):
    with pytest.raises(ValidationError, match="rtol"):
        tk.DroppingKalmanFilter(SYS, tk.Censoring(lower=0.0), rtol=rtol)


@pytest.mark.parametrize("steps", [10**400, 0, 2.0, True])
def test_protocol_bounds_steps_is_a_named_error(steps):
    from tobitkf.experiments.geng_protocol import example_channel, example_system

    with pytest.raises(ValidationError, match="steps"):
        tk.protocol_covariance_bounds(example_system(True), example_channel(), steps)


def test_sweep_workers_are_capped():
    from tobitkf.sweep.run import MAX_WORKERS, run_sweep
    from tobitkf.sweep.spec import SweepSpec

    spec = object.__new__(SweepSpec)  # the workers check comes before anything reads the spec
    with pytest.raises(ValidationError, match="workers"):
        run_sweep(spec, "unused", workers=MAX_WORKERS + 1)
