"""Monte Carlo consistency of the TKF-FM, spec 000 §8 items 10-12, as regression bands.

Ratio = empirical MSE / mean filter variance, **mean of the per-k ratios** over k = 1..100
(the first reading in the spec's closing note), per state component. M = 2000 runs, N = 100
steps, seeds fixed below. The reference values are the spec's independent prototype
([S], M = 4000) and the bands are its suggested ±0.05 (the batch-means standard error of a
ratio at M = 2000 is about 0.01, so ±0.05 is about 5 standard errors).
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.filters.fading import FadingTobitKalmanFilter

RUNS, STEPS = 2000, 100
MEANS, VARS = [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049]


def _system():
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))


def _ratio(fading, lower, seed, **options):
    sys = _system()
    cens = tk.Censoring(lower=lower)
    d = tk.simulate(sys, STEPS, RUNS, censoring=cens, measurement=fading, seed=seed)
    out = FadingTobitKalmanFilter(sys, fading, cens, **options).filter(d.y)
    err = out.mean - d.x[:, 1:]
    var = np.diagonal(out.cov, axis1=-2, axis2=-1)
    ratio = ((err**2).mean(0) / var.mean(0)).mean(0)
    # standard error by batch means over 20 independent groups of runs
    groups = np.array([((err[g::20] ** 2).mean(0) / var[g::20].mean(0)).mean(0) for g in range(20)])
    return ratio, groups.std(0, ddof=1) / np.sqrt(20), err.mean(0)


def test_item10_no_censoring_no_fading_variance_is_consistent():
    ratio, se, bias = _ratio(RiceFading.gaussian(2, MEANS, 0.0), -np.inf, seed=101)
    # the exact optimal KF on the augmented model: ratio 1 within Monte Carlo error
    assert np.all(np.abs(ratio - 1.0) < np.maximum(5 * se, 0.03)), (ratio, se)
    # bias ~ 0: per-step mean error within 5 standard errors of 0 (sd ~ sqrt(P) ~ 0.5)
    assert np.all(np.abs(bias).mean(0) < 5 * 0.5 / np.sqrt(RUNS))


def test_item11_plain_tkf_ratio_band():
    ratio, _, _ = _ratio(RiceFading.gaussian(0, [1.0], 0.0), 0.0, seed=102)
    # spec §8 item 11: about 1.04 (TKF approximations); reported, banded, not asserted to be 1
    assert np.all((ratio > 0.98) & (ratio < 1.10)), ratio


@pytest.mark.parametrize(
    "lower, variance_term, expected",
    [
        (0.0, False, (1.14, 1.11)),  # full paper model: over-confident (spec A4)
        (0.0, True, (1.02, 1.01)),  # with the fading-variance option
        (-np.inf, False, (1.15, 1.11)),  # no censoring, fading variance > 0, paper filter
        (-np.inf, True, (1.005, 1.008)),  # the same with the option (the LMMSE fading filter)
    ],
)
def test_item12_fading_model_ratio_bands(lower, variance_term, expected):
    ratio, _, _ = _ratio(RiceFading.gaussian(2, MEANS, VARS), lower, seed=103, fading_variance_term=variance_term)
    np.testing.assert_allclose(ratio, expected, atol=0.05)


def test_fading_variance_term_reduces_overconfidence():
    paper, se_p, _ = _ratio(RiceFading.gaussian(2, MEANS, VARS), 0.0, seed=104)
    fixed, se_f, _ = _ratio(RiceFading.gaussian(2, MEANS, VARS), 0.0, seed=104, fading_variance_term=True)
    assert np.all(paper - fixed > 0.05)
    assert np.all(np.abs(fixed - 1.0) < np.abs(paper - 1.0))
