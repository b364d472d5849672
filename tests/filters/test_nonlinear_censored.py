"""Tobit EKF/UKF and the nonlinear assumed-density filter: reductions to the linear filters and quadrature."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

import tobitkf as tk

from .test_nonlinear_model import P0, X0, Q, f, h, pendulum


def _linear_pair(c_rows=((1.0, 0.5), (0.0, 1.0)), r=(0.3, 0.2)):
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array(c_rows, dtype=float)
    Qd, Rd = np.array([[0.1, 0.02], [0.02, 0.05]]), np.diag(r)
    x0, P0_ = np.array([0.5, -0.2]), np.array([[1.0, 0.3], [0.3, 0.8]])
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, Qd, Rd, x0, P0_)
    lin = tk.LinearSystem(A=A, C=C, Q=Qd, R=Rd, x0=x0, P0=P0_)
    return nl, lin


CHANNELS = {
    "censoring": tk.Censoring(lower=[-0.2, 0.0], upper=[0.6, np.inf]),
    "quantizer": tk.Quantizer([0.5, 0.4], lower=[-1.0, -0.8], upper=[1.0, 0.8]),
}


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_tobit_filters_on_a_linear_model_are_the_tobit_filter(name):
    channel = CHANNELS[name]
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 30, 2, channel=channel, seed=11).y
    y[1, 4, 0] = np.nan
    want = tk.TobitFilter(lin, channel).filter(y)
    term = {"noise_term": "total_variance"}
    for est in (tk.TobitExtendedKalmanFilter(nl, channel, **term), tk.TobitUnscentedKalmanFilter(nl, channel, **term)):
        got = est.filter(y)
        np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.extras["slope"], want.extras["slope"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("term", ["dissertation", "total_variance", "exact_pv"])
def test_tobit_filters_on_a_linear_model_are_the_tobit_kalman_filter(term):
    channel = CHANNELS["censoring"]
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 30, 2, channel=channel, seed=16).y
    y[0, 2, 1] = np.nan
    want = tk.TobitKalmanFilter(lin, channel, noise_term=term, backend="numpy").filter(y)
    for est in (
        tk.TobitExtendedKalmanFilter(nl, channel, noise_term=term),
        tk.TobitUnscentedKalmanFilter(nl, channel, noise_term=term, rule="cubature"),
    ):
        assert est.noise_term == term
        got = est.filter(y)
        np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-9)
    assert tk.TobitExtendedKalmanFilter(nl, channel).noise_term == "dissertation"  # the TKF's default
    assert tk.TobitExtendedKalmanFilter(nl, CHANNELS["quantizer"]).noise_term == "total_variance"
    with pytest.raises(tk.ValidationError, match="noise_term"):
        tk.TobitExtendedKalmanFilter(nl, CHANNELS["quantizer"], noise_term="dissertation")


def test_tobit_filters_without_censoring_are_the_uncensored_filters():
    y = tk.simulate(pendulum(), 30, 2, seed=12).y
    free = tk.Censoring()
    for tobit, plain in (
        (tk.TobitExtendedKalmanFilter(pendulum(), free), tk.ExtendedKalmanFilter(pendulum())),
        (
            tk.TobitUnscentedKalmanFilter(pendulum(), free, rule="cubature"),
            tk.UnscentedKalmanFilter(pendulum(), rule="cubature"),
        ),
    ):
        # g = 1, E[y] = mu and Var[y] = sigma^2 = R up to the rounding of sqrt(R)^2, carried over 30 steps
        a, b = tobit.filter(y), plain.filter(y)
        np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_adf_on_a_linear_model_is_the_linear_adf(name):
    channel = CHANNELS[name]
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 30, 2, channel=channel, seed=13).y
    y[0, 7, 1] = np.nan
    want = tk.AssumedDensityFilter(lin, channel).filter(y)
    for rule in ("unscented", "cubature"):
        got = tk.NonlinearAssumedDensityFilter(nl, channel, rule=rule).filter(y)
        np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.extras["log_likelihood"], want.extras["log_likelihood"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        tk.NonlinearAssumedDensityFilter(nl, channel).log_likelihood(y),
        tk.AssumedDensityFilter(lin, channel).log_likelihood(y),
        rtol=0,
        atol=1e-8,
    )
    # a linear h is linearised exactly: iterating changes nothing
    again = tk.NonlinearAssumedDensityFilter(nl, channel, iterations=3).filter(y)
    np.testing.assert_allclose(again.mean, want.mean, rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- one step against quadrature


def _likelihood(channel, y, hx, r, l):
    """p(y | x) on the grid from the channel's region: the normal density for an exact reading, the normal
    mass of the interval otherwise (scipy.stats, independent of the filters' moment code)."""
    lo, hi = channel.region(np.array([y]), 1, l)
    lo, hi = float(lo[0]), float(hi[0])
    s = np.sqrt(r)
    if lo == hi:
        return norm.pdf(y, loc=hx, scale=s)
    return norm.cdf(hi, loc=hx, scale=s) - norm.cdf(lo, loc=hx, scale=s)


def _quadrature(mean, cov, hfun, channel, y, r, size):
    """Posterior mean and covariance of x ~ N(mean, cov) given the readings y (m,) of y* = h(x) + v through
    ``channel``, by a Riemann sum on a whitened grid of ±10 standard deviations (the integrands are smooth with
    Gaussian tails: the sum converges faster than any power of the spacing)."""
    n = mean.shape[0]
    z1 = np.linspace(-10, 10, size)
    Z = np.stack(np.meshgrid(*([z1] * n), indexing="ij"), axis=-1).reshape(-1, n)
    X = mean + Z @ np.linalg.cholesky(cov).T
    w = np.exp(-0.5 * (Z**2).sum(-1))
    HX = hfun(X)
    for l in range(y.shape[0]):
        w = w * _likelihood(channel, y[l], HX[:, l], r[l], l)
    w = w / w.sum()
    mu = w @ X
    D = X - mu
    return mu, (D * w[:, None]).T @ D


SCALAR_CASES = [
    ("censored low", tk.Censoring(lower=0.0, upper=1.5), -0.0),
    ("exact", tk.Censoring(lower=0.0, upper=1.5), 0.7),
    ("saturated high", tk.Censoring(lower=0.0, upper=1.5), 1.5),
    ("quantizer cell", tk.Quantizer(0.5), 0.5),
    ("quantizer saturated", tk.Quantizer(0.5, lower=-0.5, upper=0.5), 0.5),
]


@pytest.mark.parametrize("case", SCALAR_CASES, ids=[c[0] for c in SCALAR_CASES])
def test_adf_update_equals_quadrature_scalar(case):
    _, channel, y = case
    a, q, r, x0, p0 = 0.9, 0.2, 0.3, 0.4, 1.1
    sys_ = tk.NonlinearSystem(lambda x, k: a * x, lambda x, k: 1.3 * x, [[q]], [[r]], [x0], [[p0]])
    out = tk.NonlinearAssumedDensityFilter(sys_, channel).filter([[y]])
    mu, P = _quadrature(
        np.array([a * x0]), np.array([[a * a * p0 + q]]), lambda X: 1.3 * X, channel, np.array([y]), [r], 4001
    )
    np.testing.assert_allclose(out.mean[0], mu, rtol=0, atol=1e-8)
    np.testing.assert_allclose(out.cov[0], P, rtol=0, atol=1e-8)


TWO_D_CASES = [
    ("censored", tk.Censoring(lower=[-np.inf, 0.0]), [0.4, 0.0]),
    ("exact", tk.Censoring(lower=[-np.inf, 0.0]), [0.4, 0.9]),
    ("saturated", tk.Censoring(lower=[-np.inf, -1.0], upper=[np.inf, 0.3]), [-0.2, 0.3]),
    ("interval", tk.Quantizer([1e-3, 0.5]), [0.4, -0.5]),
]


@pytest.mark.parametrize("case", TWO_D_CASES, ids=[c[0] for c in TWO_D_CASES])
def test_adf_update_equals_quadrature_two_d(case):
    # channel 0 is an exact reading (quantizer width 1e-3 is an interval of 1e-3 against a noise of 0.55: treated as
    # such by both) and comes first, so the sequential update of the two channels is the exact posterior's moments
    _, channel, y = case
    nl, lin = _linear_pair(r=(0.3, 0.2))
    C = np.array([[1.0, 0.5], [0.0, 1.0]])
    y = np.array(y, dtype=float)
    if isinstance(channel, tk.Quantizer):
        y[0] = channel.quantize(np.array([y[0], 0.0]))[0]
    out = tk.NonlinearAssumedDensityFilter(nl, channel, rule="cubature").filter(y[None])
    Ad = np.array([[0.9, 0.2], [-0.1, 0.8]])
    m1 = Ad @ lin.x0
    P1 = Ad @ lin.P0 @ Ad.T + lin.Q.at(0)
    mu, P = _quadrature(m1, P1, lambda X: X @ C.T, channel, y, [0.3, 0.2], 801)
    np.testing.assert_allclose(out.mean[0], mu, rtol=0, atol=1e-7)
    np.testing.assert_allclose(out.cov[0], P, rtol=0, atol=1e-7)


@pytest.mark.parametrize("y", [0.0, 1.2], ids=["censored", "exact"])
def test_iterated_adf_approaches_quadrature_for_a_mildly_nonlinear_h(y):
    # h(x) = x + c x^2 with c = 0.1 over a prior of standard deviation 1: the slope varies by +-20 % across the
    # prior. Posterior linearisation refits the affine model where the posterior mass is, so its fixed point is
    # closer to the exact posterior moments than the fit about the prior; it is not exact (the posterior is not
    # Gaussian), so the bound is a fraction of the posterior standard deviation (5 %), and the error must shrink
    # with the curvature c (the linearisation error is of order c).
    channel = tk.Censoring(lower=0.0)

    def errors(c, iterations):
        sys_ = tk.NonlinearSystem(lambda x, k: x, lambda x, k: x + c * x**2, [[0.0]], [[0.1]], [0.3], [[1.0]])
        out = tk.NonlinearAssumedDensityFilter(sys_, channel, rule="gauss_hermite", order=8, iterations=iterations)
        res = out.filter([[y]])
        mu, P = _quadrature(
            np.array([0.3]), np.array([[1.0]]), lambda X: X + c * X**2, channel, np.array([y]), [0.1], 40001
        )
        return abs(res.mean[0, 0] - mu[0]), abs(res.cov[0, 0, 0] - P[0, 0]), np.sqrt(P[0, 0]), res.mean[0, 0]

    e1, v1, sd, _ = errors(0.1, 1)
    e10, v10, _, m10 = errors(0.1, 10)
    _, _, _, m20 = errors(0.1, 20)
    assert abs(m20 - m10) < 1e-8  # the iteration has converged
    assert e10 < e1 and e10 < 0.05 * sd
    assert v10 < 0.1 * sd**2
    e_small = errors(0.025, 10)[0]
    assert e_small < 0.5 * e10


def test_tobit_and_adf_step_loop_equals_filter():
    channel = tk.Censoring(lower=[-0.3, -np.inf], upper=[0.5, 0.9])
    sys_ = pendulum()
    y = tk.simulate(sys_, 25, 2, channel=channel, seed=14).y
    y[0, 3] = np.nan
    for est in (
        tk.TobitExtendedKalmanFilter(sys_, channel),
        tk.TobitUnscentedKalmanFilter(sys_, channel),
        tk.NonlinearAssumedDensityFilter(sys_, channel, iterations=2),
    ):
        whole = est.filter(y)
        state = est.init(batch_shape=(2,))
        for i in range(y.shape[1]):
            state = est.step(state, y[:, i])
            np.testing.assert_allclose(state.mean, whole.mean[:, i], rtol=0, atol=1e-12)
            np.testing.assert_allclose(state.cov, whole.cov[:, i], rtol=0, atol=1e-12)
        one = est.filter(y[1])
        np.testing.assert_allclose(one.mean, whole.mean[1], rtol=0, atol=1e-12)


def test_refusals():
    sys_ = pendulum()
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        tk.NonlinearAssumedDensityFilter(sys_, tk.Censoring(lower=0.0)).filter(np.full((3, 2), -1.0))
    with pytest.raises(tk.ValidationError, match="diagonal R"):
        bad = tk.NonlinearSystem(f, h, Q, np.array([[0.1, 0.05], [0.05, 0.1]]), X0, P0)
        tk.NonlinearAssumedDensityFilter(bad, tk.Censoring(lower=0.0))
    with pytest.raises(tk.ValidationError, match="iterations"):
        tk.NonlinearAssumedDensityFilter(sys_, tk.Censoring(lower=0.0), iterations=0)
    with pytest.raises(tk.ValidationError, match="reading_statistics"):
        tk.TobitExtendedKalmanFilter(sys_, tk.RandomSaturation(mu=[0.5, 0.5], nu=[0.5, 0.5]))


# --------------------------------------------------------------------------- the particle filter


@pytest.mark.parametrize("name", ["censoring", "quantizer", "none"])
def test_particle_filter_on_a_linear_nonlinear_system_is_the_linear_bootstrap_filter(name):
    # the same generator, the same draws in the same order, the same weights (the channel's likelihood): the
    # bootstrap filter of the NonlinearSystem with a linear f, h is the linear model's bootstrap filter
    channel = CHANNELS.get(name)
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 15, 2, channel=channel, seed=15).y
    y[1, 2, 0] = np.nan
    a = tk.ParticleFilter(nl, channel, particles=300, seed=4).filter(y)
    # the linear model's numpy loop (its compiled loop draws the same kinds of numbers in another order)
    b = tk.ParticleFilter(lin, channel, particles=300, proposal="prior", seed=4, backend="numpy").filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.pred_mean, b.pred_mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=0, atol=1e-9)


def test_particle_filter_matches_the_exact_one_step_posterior():
    # one reading from a Gaussian prior through a nonlinear h and a censoring: the exact posterior mean by
    # quadrature; the particle mean's Monte Carlo error over 20 000 particles is about sd/sqrt(ESS), ESS >= 5000
    channel = tk.Censoring(lower=0.0)
    sys_ = tk.NonlinearSystem(lambda x, k: x, lambda x, k: x + 0.4 * x**2, [[0.0]], [[0.1]], [0.3], [[1.0]])
    out = tk.ParticleFilter(sys_, channel, particles=20000, resample_threshold=0.0, seed=5).filter([[0.0]])
    mu, P = _quadrature(
        np.array([0.3]), np.array([[1.0]]), lambda X: X + 0.4 * X**2, channel, np.array([0.0]), [0.1], 40001
    )
    se = np.sqrt(P[0, 0] / out.extras["ess"][0])
    assert out.extras["ess"][0] > 5000
    assert abs(out.mean[0, 0] - mu[0]) < 5 * se


def test_particle_filter_refusals_for_a_nonlinear_system():
    with pytest.raises(tk.ValidationError, match="one channel piece"):
        tk.ParticleFilter(pendulum(), [tk.Censoring(lower=0.0), tk.Quantizer(0.5)])
    with pytest.raises(tk.ValidationError, match="region"):
        tk.ParticleFilter(pendulum(), tk.ProtocolChannel(2, window=0))
    with pytest.raises(tk.ValidationError, match="optimal"):
        tk.ParticleFilter(pendulum(), tk.Censoring(lower=0.0), proposal="optimal")
