"""Runs of 10^6 steps (issue 9 item 3), slow-marked and *not* in the default suite: they run
only when asked for, ``pytest -m slow tests/reliability`` (or with TOBITKF_LONG=1).

One run per estimator family (the cases of benchmarks/bench_reliability.py): the whole
record stays finite, exactly symmetric and PSD, and the estimation error stays bounded
(no drift). About 10 minutes for all on one core; the default suite has a 2e4-step run in
test_extremes_core.py.
"""

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

_BENCH = Path(__file__).parents[2] / "benchmarks" / "bench_reliability.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_reliability", _BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


NAMES = [
    "KF",
    "DKF",
    "TKF",
    pytest.param(
        "TKF total_variance+joseph",
        marks=pytest.mark.xfail(
            strict=True,
            reason="measured: finite, symmetric, PSD, but |error| reaches 158 over 10^6 steps: an uncensored "
            "reading where p_uncensored ~ 0 meets Ree ~ Var[y] ~ 0 (docs/reliability.md)",
        ),
    ),
    "SSTKF",
    "controlled TKF",
    "TKF-FM",
    "PBTKF-IMSF",
    "chain LMMSE (delay)",
]


@pytest.fixture
def asked_for(request):
    if "slow" not in (request.config.getoption("markexpr") or "") and os.environ.get("TOBITKF_LONG") != "1":
        pytest.skip("10^6-step run: select with -m slow or TOBITKF_LONG=1")


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_one_million_steps_stay_finite_symmetric_psd_and_bounded(name, asked_for):
    bench = _bench()
    mean, cov, truth = bench.cases(1_000_000)[name]()
    h = bench.health(mean, cov, truth)
    assert h["finite"] and h["symmetric"] and h["psd"], h
    # bounded error: the estimation error of these filters has std ~ 0.1-1 (the state itself wanders to
    # |x| ~ 100 over 10^6 steps); 50 is a divergence, not noise
    assert h["max_abs_error"] < 50, h


def test_long_run_helper_smoke():
    """The same checks on 3000 steps (keeps the slow test's code exercised in the default suite)."""
    bench = _bench()
    for name in ("TKF", "PBTKF-IMSF", "chain LMMSE (delay)"):
        mean, cov, truth = bench.cases(3000)[name]()
        h = bench.health(mean, cov, truth)
        assert h["finite"] and h["symmetric"] and h["psd"] and h["max_abs_error"] < 50, (name, h)
        assert np.asarray(mean).shape[-2] == 3000
