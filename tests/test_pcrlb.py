"""The posterior Cramér–Rao bound (tobitkf.design.pcrlb): the censored Fisher information, reductions, and the bound
lying below the particle filter's MSE (Holm's family-wise test at 1 % over the steps)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, stats

import tobitkf as tk
from tobitkf.design.pcrlb import bound_test, censored_fisher_information


def _fim_by_quadrature(mu, sd, lo, hi):
    """E[score score^T] in (mu, sigma) with scores of the log-likelihood differentiated numerically."""

    def ll(y, m, s):
        if y == lo:
            return stats.norm.logcdf((lo - m) / s)
        if y == hi:
            return stats.norm.logsf((hi - m) / s)
        return stats.norm.logpdf(y, m, s)

    h = 1e-5

    def score(y):
        return np.array(
            [(ll(y, mu + h, sd) - ll(y, mu - h, sd)) / (2 * h), (ll(y, mu, sd + h) - ll(y, mu, sd - h)) / (2 * h)]
        )

    I = np.zeros((2, 2))
    if np.isfinite(lo):
        I += np.outer(score(lo), score(lo)) * stats.norm.cdf((lo - mu) / sd)
    if np.isfinite(hi):
        I += np.outer(score(hi), score(hi)) * stats.norm.sf((hi - mu) / sd)
    for i, j in ((0, 0), (0, 1), (1, 1)):
        I[i, j] += integrate.quad(
            lambda y: score(y)[i] * score(y)[j] * stats.norm.pdf(y, mu, sd),
            max(lo, mu - 12 * sd),
            min(hi, mu + 12 * sd),
            limit=200,
        )[0]
    return I[0, 0], I[0, 1], I[1, 1]


@pytest.mark.parametrize(
    "args",
    [
        (0.3, 1.2, 0.0, np.inf),
        (0.3, 1.2, -np.inf, 0.5),
        (0.3, 0.7, -0.4, 1.0),
        (2.0, 1.0, 0.0, np.inf),
        (-1.5, 0.5, -np.inf, np.inf),
    ],
)
def test_censored_fisher_information_equals_quadrature(args):
    np.testing.assert_allclose(censored_fisher_information(*args), _fim_by_quadrature(*args), rtol=1e-6, atol=1e-9)


def test_censored_fisher_information_in_the_tails():
    # limit 40 sd below the mean: the normal's information; 40 sd above: nothing left (both finite)
    np.testing.assert_allclose(censored_fisher_information(0.0, 2.0, -80.0, np.inf), [0.25, 0.0, 0.5], atol=1e-15)
    np.testing.assert_allclose(censored_fisher_information(0.0, 1.0, 40.0, np.inf), [0.0, 0.0, 0.0], atol=1e-300)
    v = censored_fisher_information(0.0, 1.0, 8.0, np.inf)  # the mass beyond 8 sd still informs
    assert 0 < v[0] < 1e-12 and np.isfinite(v).all()
    with pytest.raises(tk.ValidationError, match="std: expected standard deviations > 0"):
        censored_fisher_information(0.0, 0.0)
    with pytest.raises(tk.ValidationError, match="lower/upper: expected lower < upper"):
        censored_fisher_information(0.0, 1.0, 1.0, 0.0)


def test_without_censoring_the_bound_is_the_kalman_covariance():
    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(
        A=A, C=[[1.0, 0.0], [0.0, 1.0]], Q=1e-2 * np.eye(2), R=np.diag([0.1, 0.3]), x0=[0.0, 0.0], P0=0.5 * np.eye(2)
    )
    b = tk.posterior_crlb(sys_, steps=30, runs=10)
    kf = tk.KalmanFilter(sys_).filter(np.zeros((30, 2)))
    np.testing.assert_allclose(b.bound, kf.cov, rtol=1e-11, atol=1e-14)
    assert b.var.shape == (30, 2) and b.times.tolist() == list(range(1, 31))


def test_deterministic_fading_bound_is_the_augmented_kalman_covariance():
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    fad = tk.RiceFading(1, [0.8, 0.5])
    b = tk.posterior_crlb(sys_, fad, steps=15, runs=10)
    kf = tk.FadingAssumedDensityFilter(sys_, fad).filter(np.zeros((15, 1)))
    np.testing.assert_allclose(b.bound, kf.cov, rtol=1e-10, atol=1e-14)


def _below_every_step(bound_var, truth, est_mean):
    """The calibrated verdict (Holm at 1 % family-wise over the steps; tests/test_bound_test.py)."""
    return bound_test((est_mean - truth[:, 1:]) ** 2, bound_var, 0.01)["holds"]


def test_pcrlb_lies_below_the_particle_filter_mse_on_a_censored_random_walk():
    sys_ = tk.LinearSystem(A=[[0.98]], C=[[1.0]], Q=[[0.05]], R=[[0.02]], x0=[0.3], P0=[[0.5]])
    cens = tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 40, 2000, censoring=cens, seed=1)
    pf = tk.ParticleFilter(sys_, cens, particles=300, seed=2).filter(d.y, outputs="mean")
    b = tk.posterior_crlb(sys_, cens, truth=d.x)
    assert _below_every_step(b.var, d.x, pf.mean)
    free = tk.posterior_crlb(sys_, truth=d.x)
    assert (b.var >= free.var - 1e-15).all() and (b.var[5:] > 1.2 * free.var[5:]).any()  # censoring costs


def test_pcrlb_lies_below_the_particle_filter_mse_with_fading_and_censoring():
    w = 0.052 * np.pi
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]],
        C=[[1.0, 0.0]],
        Q=0.0025 * np.eye(2),
        R=[[1.0]],
        x0=[5.0, 0.0],
        P0=np.eye(2),
    )
    fad = tk.RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    cens = tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 25, 500, censoring=cens, measurement=fad, seed=3)
    pf = tk.ParticleFilter(sys_, [fad, cens], particles=400, seed=4).filter(d.y, outputs="mean")
    b = tk.posterior_crlb(sys_, [fad, cens], truth=d.x)
    assert b.aug_bound.shape == (25, 6, 6)
    assert _below_every_step(b.var, d.x, pf.mean)


def test_bad_arguments_are_refused():
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="steps: give the horizon T"):
        tk.posterior_crlb(sys_)
    with pytest.raises(tk.ValidationError, match="channel: the PCRLB covers censored linear readings and Rice"):
        tk.posterior_crlb(sys_, tk.RandomSaturation([0.1], [0.9]), steps=3)
    with pytest.raises(tk.ValidationError, match="fading PCRLB needs Gaussian coefficients"):
        tk.posterior_crlb(sys_, tk.RiceFading(0, tk.laws.Uniform([0.5], [1.0])), steps=3)
    with pytest.raises(tk.ShapeError, match="truth: expected"):
        tk.posterior_crlb(sys_, truth=np.zeros((4, 1, 1)))
    two = tk.LinearSystem(A=np.eye(2), C=np.eye(2), Q=np.eye(2), R=[[1.0, 0.2], [0.2, 1.0]], x0=[0, 0], P0=np.eye(2))
    with pytest.raises(tk.ValidationError, match="R: the PCRLB needs a diagonal R"):
        tk.posterior_crlb(two, steps=2)


def test_censoring_gives_the_fisher_information_of_its_reading():
    """``Censoring.fisher_information`` (the contract's, which the PCRLB asks every channel): per channel at its
    limits, against quadrature of the squared score (independent oracle); no limit: 1/sigma^2."""
    cens = tk.Censoring(lower=[0.2, -np.inf], upper=[np.inf, np.inf])
    mu, sd = np.array([-0.4, 0.1, 0.9]), np.array([0.5, 1.0, 2.0])
    got = cens.fisher_information(mu, sd, 1, 0)
    for i in range(3):
        a = (0.2 - mu[i]) / sd[i]
        censored = stats.norm.pdf(a) ** 2 / stats.norm.cdf(a)  # P(at the limit) * score^2
        inside, _ = integrate.quad(lambda z: z * z * stats.norm.pdf(z), a, np.inf, epsabs=1e-14, epsrel=1e-12)
        np.testing.assert_allclose(got[i], (censored + inside) / sd[i] ** 2, rtol=1e-9)
    np.testing.assert_allclose(cens.fisher_information(mu, sd, 1, 1), 1.0 / sd**2, rtol=1e-12)
