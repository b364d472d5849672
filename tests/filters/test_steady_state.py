"""Steady-state TKF with a controlled censoring limit (Miller §3.4.2; spec 001a §3.7, 001b §0.3)."""

import numpy as np
import pytest
from scipy.stats import norm

import tobitkf as tk
from tobitkf.filters.steady_state import (
    SteadyStateTobitKalmanFilter,
    controlled_limit_statistics,
    tobit_kalman_filter_controlled,
)


def oscillator(omega=0.05):
    c, s = np.cos(omega), np.sin(omega)
    return tk.LinearSystem(
        A=[[c, -s], [s, c]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )


# spec 001b §0.3 table ([S] prototype, 6 digits), independent of this code
@pytest.mark.parametrize(
    "xi, alpha, lam, ups",
    [
        (0.33, -0.439913, 1.097420, 0.278438),
        (0.5, 0.0, 0.797885, 0.363380),
        (0.8, 0.841621, 0.349952, 0.583006),
        (0.95, 1.644854, 0.108564, 0.809642),
    ],
)
def test_constant_statistics_match_spec_table(xi, alpha, lam, ups):
    a, l, u, _ = controlled_limit_statistics(xi, 1.0)
    assert a == pytest.approx(alpha, abs=2e-6)
    assert l == pytest.approx(lam, abs=2e-6)
    assert u == pytest.approx(ups, abs=2e-6)


def test_half_probability_noise_term_is_closed_form():
    # ξ = 0.5: α = 0, λ̂ = φ(0)/0.5 = sqrt(2/π), υ = σ²(1 - 2/π)
    _, lam, ups, off = controlled_limit_statistics(0.5, 0.3)
    assert lam == pytest.approx(np.sqrt(2 / np.pi), rel=1e-14)
    assert ups == pytest.approx(0.09 * (1 - 2 / np.pi), rel=1e-14)
    assert off == pytest.approx(0.3 * norm.pdf(0.0), rel=1e-14)


@pytest.mark.parametrize("xi, gain", [(0.95, [0.3277, -0.2506]), (0.5, [0.5185, -0.3727]), (0.2, [0.7663, -0.4328])])
def test_gain_matches_spec_table(xi, gain):
    f = SteadyStateTobitKalmanFilter(oscillator(), xi)
    np.testing.assert_allclose(f.gain[:, 0], gain, atol=6e-5)


def test_dare_residual_and_posterior():
    sys_ = oscillator()
    f = SteadyStateTobitKalmanFilter(sys_, 0.8)
    A, Q, Ct, U = sys_.transition(0), sys_.process_cov(0), f.modified_C, np.diag(f.upsilon)
    P = f.prior_cov
    resid = A @ P @ A.T - A @ P @ Ct.T @ np.linalg.solve(Ct @ P @ Ct.T + U, Ct @ P @ A.T) + Q - P
    assert np.abs(resid).max() < 1e-12
    np.testing.assert_allclose(f.cov, P - f.gain @ Ct @ P, atol=1e-14)


@pytest.mark.parametrize("xi", [0.95, 0.5, 0.2])
def test_full_tkf_with_controlled_limit_converges_to_dare(xi):
    """Spec 001a §6 item 4: E(p_k) ≡ ξ at every step and Ψ_k -> Ψ∞ (issue: to 1e-6)."""
    sys_ = oscillator()
    data = tk.simulate(sys_, 400, 3, seed=4)
    out = tobit_kalman_filter_controlled(sys_, xi, data.y_latent)
    f = SteadyStateTobitKalmanFilter(sys_, xi)
    np.testing.assert_allclose(out.extras["p_uncensored"], xi, atol=1e-12)
    assert np.abs(out.cov[:, -1] - f.cov).max() < 1e-6
    assert np.abs(out.pred_cov[:, -1] - f.prior_cov).max() < 1e-6
    # the readings the filter got are censored at the limits it set
    assert np.all(out.extras["y"] <= out.extras["limits"] + 1e-15)


def test_fixed_gain_filter_equals_full_tkf_once_converged():
    """With the prior started at the DARE solution, the full TKF under (3.56) *is* the fixed-gain filter."""
    sys0 = oscillator()
    psi_inf = SteadyStateTobitKalmanFilter(sys0, 0.9).cov
    # prior covariance Ψ∞ makes every prior covariance of the full TKF exactly Ψ̄∞
    sys_ = tk.LinearSystem(
        A=sys0.transition(0),
        C=sys0.measurement(1),
        Q=sys0.process_cov(0),
        R=sys0.measurement_cov(1),
        x0=[0.3, -0.2],
        P0=psi_inf,
    )
    f = SteadyStateTobitKalmanFilter(sys_, 0.9)
    data = tk.simulate(sys_, 200, 4, seed=2)
    a = f.filter_controlled(data.y_latent)
    b = tobit_kalman_filter_controlled(sys_, 0.9, data.y_latent)
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-10)
    np.testing.assert_allclose(a.extras["limits"], b.extras["limits"], atol=1e-10)


def test_lower_side_mirrors_upper():
    sys_ = oscillator()
    neg = tk.LinearSystem(
        A=sys_.transition(0),
        C=-sys_.measurement(1),
        Q=sys_.process_cov(0),
        R=sys_.measurement_cov(1),
        x0=sys_.x0,
        P0=sys_.P0,
    )
    data = tk.simulate(sys_, 150, 3, seed=7)
    up = SteadyStateTobitKalmanFilter(sys_, 0.7).filter_controlled(data.y_latent)
    lo = SteadyStateTobitKalmanFilter(neg, 0.7, side="lower").filter_controlled(-data.y_latent)
    np.testing.assert_allclose(up.mean, lo.mean, atol=1e-12)
    np.testing.assert_allclose(up.extras["y"], -lo.extras["y"], atol=1e-12)


def test_realised_uncensored_fraction_follows_prior_error():
    """Spec 001b §0.3 caveat 2 and note 6: the realised P(uncensored) is Φ((aσ - b)/sqrt(σ² + s²)),
    with b, s² the mean and variance of the *true* prior error C(x - x̄); it is below ξ for ξ > 0.5.
    (The filter's own P̄ underestimates s², so Φ(aσ/sqrt(σ² + CP̄C')) is only a rough guide.)"""
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.01]], R=[[0.01]], x0=[0.0], P0=[[0.05]])
    xi = 0.95
    f = SteadyStateTobitKalmanFilter(sys_, xi)
    runs, steps, burn = 400, 300, 50
    data = tk.simulate(sys_, steps, runs, seed=11)
    out = f.filter_controlled(data.y_latent)
    realised = float((out.extras["y"][:, burn:] < out.extras["limits"][:, burn:]).mean())
    err = (data.x[:, 1:, 0] - out.pred_mean[..., 0])[:, burn:]
    sigma = 0.1
    predicted = norm.cdf((norm.ppf(xi) * sigma - err.mean()) / np.sqrt(sigma**2 + err.var()))
    se = np.sqrt(predicted * (1 - predicted) / (runs * (steps - burn)))
    assert realised < xi
    # the Gaussian approximation of the prior error is not exact: 6 s.e. plus 0.005 (spec note 6)
    assert abs(realised - predicted) < 6 * se + 0.005


@pytest.mark.parametrize("xi", [0.0, 1.0, -0.1, 1.5])
def test_xi_outside_open_interval_raises(xi):
    with pytest.raises(tk.ValidationError, match="xi_uncensored"):
        SteadyStateTobitKalmanFilter(oscillator(), xi)


def test_time_varying_system_rejected():
    sys_ = tk.LinearSystem(A=np.ones((5, 1, 1)), C=[[1.0]], Q=[[0.1]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="time-invariant"):
        SteadyStateTobitKalmanFilter(sys_, 0.5)


def test_undetectable_pair_names_the_riccati_equation():
    # unstable mode not seen by C: the modified DARE has no stabilizing solution
    sys_ = tk.LinearSystem(A=np.diag([1.2, 0.5]), C=[[0.0, 1.0]], Q=np.eye(2), R=[[0.1]], x0=[0, 0], P0=np.eye(2))
    with pytest.raises(tk.ValidationError, match="modified DARE"):
        SteadyStateTobitKalmanFilter(sys_, 0.5)


def test_unknown_side_rejected():
    with pytest.raises(tk.ValidationError, match="side"):
        SteadyStateTobitKalmanFilter(oscillator(), 0.5, side="both")
