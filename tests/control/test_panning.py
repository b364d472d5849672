"""Panning laws and the steered-window TKF (spec 001b T19), printed (6.61) regression guard (T20)."""

import numpy as np
import pytest
from scipy.special import ndtri
from scipy.stats import truncnorm

from tobitkf import censored_moments, simulate
from tobitkf._validation import ValidationError
from tobitkf.control.panning import (
    centred_window,
    constant_velocity,
    covariance_panning_step,
    dissertation_variance_6_61,
    imr_panning_step,
    keep_in_view_limit,
    moving_window_tkf,
)


def test_t20_printed_6_61_variance_differs_from_truncnorm():
    printed = dissertation_variance_6_61(0.3, 0.5, -1.0, 1.0)
    a, b = (-1 - 0.3) / 0.5, (1 - 0.3) / 0.5
    exact = truncnorm.var(a, b, loc=0.3, scale=0.5)
    assert printed == pytest.approx(0.0142, abs=1e-4)
    assert exact == pytest.approx(0.177508, abs=1e-6)
    assert censored_moments(0.3, 0.5, -1.0, 1.0).truncated_var == pytest.approx(exact, rel=1e-9)


def test_t19_centred_window_gives_gamma_ed_and_zero_imr():
    mu = np.array([-3.0, 0.2, 7.0])
    lo, hi = centred_window(mu, 0.4, 0.8)
    st = censored_moments(mu, 0.4, lo, hi)
    assert st.p_uncensored == pytest.approx(0.8, abs=1e-12)
    assert st.inverse_mills == pytest.approx(0.0, abs=1e-12)
    z = ndtri(0.9)
    assert st.truncated_var == pytest.approx(
        0.16 * (1 - 2 * z * np.exp(-z * z / 2) / np.sqrt(2 * np.pi) / 0.8), rel=1e-9
    )
    with pytest.raises(ValidationError, match="ed: expected"):
        centred_window(mu, 0.4, 1.0)


def test_t19_keep_in_view_rule():
    lo, hi = keep_in_view_limit(np.array([0.0, 10.0, 30.0]), 0.5, 20.0, width=50.0)
    assert hi == pytest.approx([20.0, 20.0, 30.0 + 0.5 * 3.719016485455709])
    assert lo == pytest.approx(hi - 50.0)
    # the spec's option: the spread of the prior too
    _, hi2 = keep_in_view_limit(np.array([30.0]), 0.5, 20.0, prior_var=0.75)
    assert hi2[0] == pytest.approx(30.0 + 1.0 * 3.719016485455709)
    with pytest.raises(ValidationError, match="probability"):
        keep_in_view_limit(0.0, 0.5, 20.0, probability=1.0)


def test_t19_keep_in_view_in_a_loop():
    """A target moving up: T_h non-decreasing and T_h - C xbar >= 3.719 sigma once active."""
    sys = constant_velocity(0.1, 0.01, 0.5, x0=np.array([0.0, 1.0]), P0=np.diag([0.01, 1e-4]))
    sim = simulate(sys, 400, 3, seed=0)
    res = moving_window_tkf(sys, sim.y_latent, lambda k, xb, Pb, mem: keep_in_view_limit(xb[:, :1], 0.5, 20.0))
    Th = res.upper[..., 0]
    assert np.all(np.diff(Th, axis=1) >= -1e-9)
    assert np.any(Th > 20.0)
    assert np.mean(sim.y_latent[..., 0] >= Th) < 2e-3


def test_t19_imr_law_moves_the_window_toward_the_target():
    Th = np.array([10.0])
    new = imr_panning_step(Th, 20.0, np.array([[10.0 - 0.25]]), 0.5, 0.2)  # target at T_h - 0.5 sigma
    assert new[0] > Th[0]
    new = imr_panning_step(Th, 20.0, np.array([[-10.0 + 0.25]]), 0.5, 0.2)  # near the lower edge
    assert new[0] < Th[0]
    centred = imr_panning_step(Th, 20.0, np.array([[0.0]]), 0.5, 0.2)
    assert centred[0] == pytest.approx(10.0, abs=1e-12)
    with pytest.raises(ValidationError, match="kappa"):
        imr_panning_step(Th, 20.0, np.array([[0.0]]), 0.5, -1.0)


def test_covariance_law_signs():
    up = covariance_panning_step(10.0, np.array([2.0, 0.5]), np.array([0.5, 0.5]), np.array([12.0, 0.0]), 1.0)
    assert up == pytest.approx(11.5)  # target 1 (above) uncertain: move up
    down = covariance_panning_step(10.0, np.array([2.0, 0.5]), np.array([0.5, 0.5]), np.array([-12.0, 0.0]), 1.0)
    assert down == pytest.approx(8.5)
    single = covariance_panning_step(10.0, np.array([1.5]), np.array([0.5]), np.array([12.0]), 2.0, width=20.0)
    assert single == pytest.approx(12.0)
    assert covariance_panning_step(10.0, np.array([0.1]), np.array([0.5]), np.array([12.0]), 2.0, width=20.0) == 10.0
    with pytest.raises(ValidationError, match="width"):
        covariance_panning_step(10.0, np.array([1.5]), np.array([0.5]), np.array([12.0]), 2.0)


def test_moving_window_with_infinite_window_is_the_kalman_filter():
    from tobitkf import KalmanFilter

    sys = constant_velocity(0.1, 0.1, 0.5, cameras=2)
    sim = simulate(sys, 50, 2, seed=1)
    res = moving_window_tkf(
        sys, sim.y_latent, lambda k, xb, Pb, mem: (np.full((2, 2), -np.inf), np.full((2, 2), np.inf))
    )
    kf = KalmanFilter(sys).filter(sim.y_latent)
    assert res.mean == pytest.approx(kf.mean, abs=1e-12)
    with pytest.raises(ValidationError, match="y_latent"):
        moving_window_tkf(sys, sim.y_latent[0], lambda *a: None)
