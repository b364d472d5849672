"""Joint state-parameter tracking by state augmentation (tk.augment_parameters)."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

DT, DAMPING, TRUTH = 0.1, 0.1, 4.0
Q = np.diag([1e-4, 1e-2])
X0, P0 = [1.0, 0.0], np.diag([0.1, 0.1])


def oscillator(x, k, theta):  # x'' = -theta x - c x' (theta = omega^2), one RK4 step of DT
    def rate(z):
        return np.stack([z[..., 1], -theta[..., 0] * z[..., 0] - DAMPING * z[..., 1]], -1)

    k1 = rate(x)
    k2 = rate(x + 0.5 * DT * k1)
    k3 = rate(x + 0.5 * DT * k2)
    k4 = rate(x + DT * k3)
    return x + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def position(x, k, theta):
    return x[..., :1]


def fixed(theta):
    return tk.NonlinearSystem(
        lambda x, k: oscillator(x, k, np.full(x.shape[:-1] + (1,), theta)),
        lambda x, k: x[..., :1],
        Q,
        [[0.01]],
        X0,
        P0,
    )


def test_augmented_model_structure():
    aug = tk.augment_parameters(
        oscillator, position, Q, [[0.01]], X0, P0, theta0=[2.5], theta_cov=[1.0], theta_noise=1e-6
    )
    assert (aug.n, aug.m) == (3, 1)
    np.testing.assert_array_equal(aug.x0, [1.0, 0.0, 2.5])
    np.testing.assert_array_equal(aug.P0, np.diag([0.1, 0.1, 1.0]))
    np.testing.assert_array_equal(aug.process_cov(0), np.diag([1e-4, 1e-2, 1e-6]))
    z = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_array_equal(aug.transition_map(z, 0)[:, 2], z[:, 2])  # a random walk: f keeps theta
    np.testing.assert_array_equal(aug.transition_map(z, 0)[:, :2], oscillator(z[:, :2], 0, z[:, 2:]))
    with pytest.raises(tk.ShapeError, match="theta_cov"):
        tk.augment_parameters(oscillator, position, Q, [[0.01]], X0, P0, theta0=[2.5], theta_cov=[1.0, 1.0])
    with pytest.raises(tk.ValidationError, match="theta_noise"):
        tk.augment_parameters(oscillator, position, Q, [[0.01]], X0, P0, theta0=[2.5], theta_cov=1.0, theta_noise=-1)


def test_a_known_parameter_reduces_to_the_filter_of_the_fixed_model():
    # theta_cov = theta_noise = 0: the parameter block of the covariance stays 0 and the extended filter of the
    # augmented model is that of the model with theta fixed (to the central differences' ~1e-9)
    cens = tk.Censoring(lower=-0.2)
    y = tk.simulate(fixed(TRUTH), 40, 3, channel=cens, seed=1).y
    aug = tk.augment_parameters(oscillator, position, Q, [[0.01]], X0, P0, theta0=[TRUTH], theta_cov=0.0)
    a = tk.TobitExtendedKalmanFilter(aug, cens).filter(y)
    b = tk.TobitExtendedKalmanFilter(fixed(TRUTH), cens).filter(y)
    np.testing.assert_allclose(a.mean[..., :2], b.mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(a.mean[..., 2], TRUTH, rtol=0, atol=1e-12)


@pytest.mark.parametrize("make", [tk.NonlinearAssumedDensityFilter, tk.TobitExtendedKalmanFilter])
def test_tracked_stiffness_converges_within_its_band_on_a_censored_oscillator(make):
    # the setting of Arthur et al. 2018: an oscillator whose position is censored below (about 40 % of the
    # readings), its stiffness unknown (prior 2.5 +- 1, truth 4). After 150 readings the estimate of each of
    # 100 runs must lie within 3 of its reported standard deviations (a calibrated band misses 0.3 % of runs;
    # at most 10 % allowed), and the mean error must have fallen from 1.5 to under 0.3
    cens = tk.Censoring(lower=-0.2)
    data = tk.simulate(fixed(TRUTH), 150, 100, channel=cens, seed=5)
    assert 0.3 < cens.at_limit(data.y).mean() < 0.5
    aug = tk.augment_parameters(
        oscillator, position, Q, [[0.01]], X0, P0, theta0=[2.5], theta_cov=[1.0], theta_noise=1e-6
    )
    out = make(aug, cens).filter(data.y)
    theta, sd = out.mean[:, -1, 2], np.sqrt(out.cov[:, -1, 2, 2])
    assert np.mean(np.abs(theta - TRUTH) < 3 * sd) >= 0.9
    assert np.mean(np.abs(theta - TRUTH)) < 0.3
    assert np.all(sd < 0.5)  # the band itself has shrunk from the prior's 1


def test_an_output_with_a_known_input_and_a_tracked_parameter():
    # h(x, k, theta, u) = theta C x + D u with theta known (variance 0): along the sigma points theta stays fixed,
    # so the map is linear in x and the unscented filter of the augmented model is the Kalman filter of the
    # linear model with C -> theta C and the feed-through D (to rounding); f takes no input
    A, C, D, R, theta = np.array([[0.9, 0.1], [0.0, 0.8]]), np.array([[1.0, 0.5]]), np.array([[0.7]]), [[0.05]], 1.5

    def f(x, k, th):
        return x @ A.T

    def h(x, k, th, u):
        return th * (x @ C.T) + u @ D.T

    aug = tk.augment_parameters(f, h, Q, R, X0, P0, theta0=[theta], theta_cov=0.0, inputs=1)
    assert (aug.f_takes_input, aug.h_takes_input) == (False, True)
    lin = tk.LinearSystem(A=A, C=theta * C, Q=Q, R=R, x0=X0, P0=P0, Bu=np.zeros((2, 1)), D=D)
    u = np.random.default_rng(3).normal(size=(25, 1))
    y = tk.simulate(lin, 25, 3, seed=4, inputs=u).y
    a = tk.UnscentedKalmanFilter(aug).filter(y, u=u)
    b = tk.KalmanFilter(lin).filter(y, u=u)
    np.testing.assert_allclose(a.mean[..., :2], b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov[..., :2, :2], b.cov, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(a.mean[..., 2], theta)
    with pytest.raises(tk.ValidationError, match="inputs"):  # an input taken but its length not given
        tk.augment_parameters(f, h, Q, R, X0, P0, theta0=[theta], theta_cov=0.0)
    with pytest.raises(tk.ValidationError, match="inputs"):  # a length given but no map takes an input
        tk.augment_parameters(f, position, Q, R, X0, P0, theta0=[theta], theta_cov=0.0, inputs=1)
