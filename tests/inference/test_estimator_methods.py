"""The estimators' smooth / log_likelihood methods and the recorded censoring indicator on the censored
estimators (thin delegations to tobitkf.inference)."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ShapeError, ValidationError


@pytest.fixture()
def case():
    sys_ = tk.LinearSystem(
        A=[[0.9, 0.1], [0.0, 0.8]], C=[[1.0, 0.3]], Q=np.eye(2) * 0.3, R=[[0.2]], x0=np.zeros(2), P0=np.eye(2)
    )
    rng = np.random.default_rng(0)
    y = np.maximum(rng.normal(size=(12, 1)), 0.0)
    y[4] = 0.0  # at the limit; the record says uncensored
    flags = y == 0.0
    flags[4] = False
    return sys_, tk.Censoring(lower=0.0), y, flags


def test_kalman_filter_smooth_and_log_likelihood(case):
    sys_, _, y, _ = case
    kf = tk.KalmanFilter(sys_)
    np.testing.assert_allclose(kf.smooth(y).mean, tk.smooth(sys_, y).mean, atol=1e-12, rtol=0)
    assert kf.log_likelihood(y) == pytest.approx(float(tk.kalman_log_likelihood(sys_, y)), abs=1e-12)
    assert kf.log_likelihood(y, per_step=True).shape == (12,)


def test_dropping_filter_takes_the_recorded_indicator(case):
    sys_, cens, y, flags = case
    dkf = tk.DroppingKalmanFilter(sys_, cens)
    got = dkf.filter(y, censored=flags)
    ym = np.where(flags, np.nan, y)
    ref = tk.KalmanFilter(sys_).filter(ym)
    np.testing.assert_allclose(got.mean, ref.mean, atol=1e-12, rtol=0)
    np.testing.assert_array_equal(got.extras["censored"], flags)
    rule = dkf.filter(y)  # the limit rule drops reading 4 too
    assert bool(rule.extras["censored"][4, 0]) and not bool(got.extras["censored"][4, 0])
    np.testing.assert_allclose(
        dkf.smooth(y, censored=flags).mean, tk.KalmanFilter(sys_).smooth(ym).mean, atol=1e-12, rtol=0
    )
    with pytest.raises(ShapeError, match="censored"):
        dkf.filter(y, censored=flags[:5])


def test_tobit_filter_checks_the_indicator_smooths_and_gives_the_assumed_density_likelihood(case):
    sys_, cens, y, flags = case
    tkf = tk.TobitKalmanFilter(sys_, cens)
    np.testing.assert_allclose(tkf.filter(y, censored=flags).mean, tkf.filter(y).mean, atol=0, rtol=0)
    bad = flags.copy()
    bad[np.flatnonzero(y[:, 0] > 0)[0]] = True
    with pytest.raises(ValidationError, match="censored"):
        tkf.filter(y, censored=bad)
    np.testing.assert_allclose(
        tkf.smooth(y).mean, tk.smooth(sys_, y, censoring=cens, method="tobit").mean, atol=1e-12, rtol=0
    )
    assert tkf.log_likelihood(y, censored=flags) == pytest.approx(
        float(tk.adf_log_likelihood(sys_, cens, y, censored=flags)), abs=1e-12
    )


def test_assumed_density_filter_smooths_and_gives_its_likelihood_with_the_indicator(case):
    sys_, cens, y, flags = case
    adf = tk.AssumedDensityTobitFilter(sys_, cens, order="uncensored_first")
    ref = tk.smooth(sys_, y, censoring=cens, censored=flags, method="adf")
    np.testing.assert_allclose(adf.smooth(y, censored=flags).mean, ref.mean, atol=1e-12, rtol=0)
    assert adf.log_likelihood(y, censored=flags) == pytest.approx(
        float(tk.adf_log_likelihood(sys_, cens, y, censored=flags)), abs=1e-12
    )
    assert adf.log_likelihood(y, per_step=True).shape == (12,)
    # the indicator decides reading 4 (at the limit, recorded uncensored): a density, not a mass
    assert adf.log_likelihood(y, censored=flags) != pytest.approx(float(adf.log_likelihood(y)), abs=1e-6)
