"""Rice fading of order L > 0 on a NonlinearSystem, y*_k = sum_s theta_k(s) h(x_(k-s), k-s) + v_k: the exact
reduction to the order-0 filters when the delayed gains vanish, a Monte Carlo check against the particle filter, the
simulated readings and the refusals (the linear fading filters of order 2 for a linear h: test_nonlinear_fading.py)."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

from .test_nonlinear_fading import _nonlinear, _scalar_model

TOL = 1e-10
FAD = tk.RiceFading.gaussian(2, [[0.8, 1.1], [0.5, 0.3], [0.3, -0.4]], [[0.05, 0.02], [0.01, 0.03], [0.02, 0.0]])


# --------------------------------------------------------------------------- exact reductions
# (for a linear h, the linear fading filters of order 2: tests/filters/test_nonlinear_fading.py)


@pytest.mark.parametrize(
    "make",
    [
        lambda s, f: tk.FadingExtendedKalmanFilter(s, f),
        lambda s, f: tk.FadingTobitExtendedKalmanFilter(s, f, tk.Censoring(lower=[0.9, -np.inf])),
    ],
)
def test_vanishing_delayed_gains_give_the_order_0_filter(make):
    """Gains of mean and variance 0 at s = 1, 2: the window's top block is the order-0 filter exactly (the
    extended forms: the other blocks enter neither the reading nor the gain's top rows)."""
    sys_ = _nonlinear()
    data = tk.simulate(
        sys_, steps=20, runs=4, channel=[tk.RiceFading.gaussian(0, [[0.8, 1.1]], [[0.05, 0.02]])], seed=6
    )
    y = np.maximum(data.y, [0.9, -np.inf])
    zero = tk.RiceFading.gaussian(2, [[0.8, 1.1], [0.0, 0.0], [0.0, 0.0]], [[0.05, 0.02], [0.0, 0.0], [0.0, 0.0]])
    a = make(sys_, tk.RiceFading.gaussian(0, [[0.8, 1.1]], [[0.05, 0.02]])).filter(y)
    b = make(sys_, zero).filter(y)
    # the same equations summed in another order: last-bit differences, which the central-difference Jacobians
    # (step ~6e-6) grow to ~1e-11
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)


# --------------------------------------------------------------------------- against the particle filter


def test_monte_carlo_against_the_particle_filter():
    """Fading of order 1 on a scalar nonlinear model: the fading UKF's and ADF's error variances match their
    reported variances (NEES of 1 within four standard errors of the run mean), and their MSE is within 5 % (plus
    three standard errors of the paired difference) of a particle filter's with the exact likelihood."""
    sys_, _, _ = _scalar_model()
    fad = tk.RiceFading.gaussian(1, [0.9, 0.5], [0.09, 0.04])
    N, T = 300, 30
    data = tk.simulate(sys_, steps=T, runs=N, channel=fad, seed=11)
    truth = data.x[:, 1:, 0]
    pf = tk.ParticleFilter(sys_, fad, particles=2000, resample_threshold=1.0, seed=13).filter(data.y).mean[..., 0]
    mse_pf = ((pf - truth) ** 2).mean(axis=1)
    for est in (tk.FadingUnscentedKalmanFilter(sys_, fad), tk.FadingNonlinearAssumedDensityFilter(sys_, fad)):
        out = est.filter(data.y)
        err2 = (out.mean[..., 0] - truth) ** 2
        nees = (err2 / out.cov[..., 0, 0]).mean(axis=1)
        se = nees.std(ddof=1) / np.sqrt(N)
        assert abs(nees.mean() - 1.0) < 4 * se, (type(est).__name__, nees.mean(), se)
        d = err2.mean(axis=1) - mse_pf
        assert d.mean() < 0.05 * mse_pf.mean() + 3 * d.std(ddof=1) / np.sqrt(N), (type(est).__name__, d.mean())


# --------------------------------------------------------------------------- simulation


def test_simulate_draws_the_delayed_terms_at_their_own_time():
    def h(x, k):  # reads its time: h(x_(k-s), k-s) must be called with k-s
        return np.concatenate([np.sin(x[..., :1]) + 0.1 * k, x[..., 1:] ** 2], axis=-1)

    sys_ = tk.NonlinearSystem(
        lambda x, k: 0.9 * x, h, Q=0.1 * np.eye(2), R=1e-20 * np.eye(2), x0=[0.5, 0.2], P0=0.1 * np.eye(2)
    )
    cens = tk.Censoring(lower=[0.3, -np.inf])
    N, T = 5, 8
    data = tk.simulate(sys_, steps=T, runs=N, channel=[FAD, cens], seed=8)
    theta = data.extras["fading"]  # (N, T, L+1, m), zero where s > k
    want = np.zeros((N, T, 2))
    for k in range(1, T + 1):
        for s in range(min(2, k) + 1):
            want[:, k - 1] += theta[:, k - 1, s] * h(data.x[:, k - s], k - s)
    np.testing.assert_allclose(data.y_latent, want, rtol=0, atol=1e-8)  # v has a standard deviation 1e-10
    np.testing.assert_array_equal(data.y, cens.clip(data.y_latent))
    assert (theta[:, 0, 2] == 0).all() and (theta[:, 1:, 2] != 0).all()  # no term s = 2 at k = 1


# --------------------------------------------------------------------------- refusals


def test_refusals_name_what_is_not_covered():
    sys_ = _nonlinear()
    fad = tk.RiceFading.gaussian(1, [0.9, 0.5], [0.01, 0.01])
    with_input = tk.NonlinearSystem(
        lambda x, k: x, lambda x, k, u: x + u, Q=np.eye(2), R=np.eye(2), x0=[0.0, 0.0], P0=np.eye(2), inputs=2
    )
    for make in (
        lambda s: tk.FadingUnscentedKalmanFilter(s, fad),
        lambda s: tk.FadingNonlinearAssumedDensityFilter(s, fad),
        lambda s: tk.ParticleFilter(s, fad),
        lambda s: tk.simulate(s, 3, channel=fad),
    ):
        with pytest.raises(tk.ValidationError, match="past inputs"):
            make(with_input)
    y = tk.simulate(sys_, 4, 2, channel=fad, seed=1).y
    with pytest.raises(tk.ValidationError, match="order L=1"):
        tk.FadingUnscentedKalmanFilter(sys_, fad, backend="numba").filter(y)
    with pytest.raises(tk.ValidationError, match="smooth"):
        tk.FadingExtendedKalmanFilter(sys_, fad).smooth(y)
    with pytest.raises(tk.ValidationError, match="smooth"):
        tk.FadingNonlinearAssumedDensityFilter(sys_, fad).smooth(y, iterations=2)
    with pytest.raises(tk.ValidationError, match="covariance_update"):
        tk.FadingUnscentedKalmanFilter(sys_, fad, covariance_update="square_root")
