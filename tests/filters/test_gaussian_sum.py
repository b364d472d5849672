"""The Gaussian-sum assumed-density filter: its reductions, an oracle on a bimodal posterior, its bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk
from tobitkf.experiments.nonlinear import localisation_system
from tobitkf.filters.gaussian_sum import SPLIT_WEIGHTS, _merge, split_principal


def _localisation_record(runs=3, steps=15, seed=4):
    system, cens = localisation_system()
    data = tk.simulate(system, steps, runs, channel=cens, seed=seed)
    return system, cens, data


def test_one_component_is_the_nonlinear_adf():
    system, cens, data = _localisation_record()
    for opts in ({}, {"rule": "cubature", "iterations": 2}):
        gs = tk.GaussianSumAssumedDensityFilter(system, cens, components=1, **opts).filter(data.y)
        adf = tk.NonlinearAssumedDensityFilter(system, cens, **opts).filter(data.y)
        np.testing.assert_allclose(gs.mean, adf.mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gs.cov, adf.cov, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gs.pred_mean, adf.pred_mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gs.extras["log_likelihood"], adf.extras["log_likelihood"], rtol=0, atol=1e-12)


def test_inputs_reach_every_component():
    # f(x, k, u): each component gets its run's input; one component is the assumed-density filter with u, and a
    # bigger mixture differs from the same mixture run without the input
    sys_ = tk.NonlinearSystem(
        lambda x, k, u: x + u, lambda x, k: x**2, Q=[[0.1]], R=[[0.2]], x0=[1.0], P0=[[2.0]], inputs=1
    )
    cens = tk.Censoring(lower=0.3)
    u = np.array([[[0.5], [-1.0], [0.2], [0.0]], [[0.0], [0.3], [-0.4], [1.0]]])
    y = np.array([[[1.9], [0.3], [0.6], [0.8]], [[0.3], [1.2], [0.3], [2.5]]])
    one = tk.GaussianSumAssumedDensityFilter(sys_, cens, components=1).filter(y, u=u)
    adf = tk.NonlinearAssumedDensityFilter(sys_, cens).filter(y, u=u)
    np.testing.assert_allclose(one.mean, adf.mean, rtol=0, atol=1e-12)
    est = tk.GaussianSumAssumedDensityFilter(sys_, cens, components=7)
    state = est.init(batch_shape=(2,))
    for t in range(4):
        state = est.step(state, y[:, t], u=u[:, t])
    full = est.filter(y, u=u)
    np.testing.assert_allclose(state.mean, full.mean[:, -1], rtol=0, atol=1e-12)
    assert (full.extras["components"] > 1).any()
    assert not np.allclose(full.mean, est.filter(y, u=np.zeros_like(u)).mean)


@pytest.mark.parametrize("components", [1, 2, 3, 8])
def test_linear_gaussian_model_gives_the_kalman_filter_for_every_size(components):
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.5], [0.0, 1.0]])
    lin = tk.LinearSystem(A=A, C=C, Q=0.1 * np.eye(2), R=np.diag([0.3, 0.2]), x0=[0.5, -0.2], P0=np.eye(2))
    nl = tk.NonlinearSystem(
        lambda x, k: x @ A.T,
        lambda x, k: x @ C.T,
        Q=0.1 * np.eye(2),
        R=np.diag([0.3, 0.2]),
        x0=[0.5, -0.2],
        P0=np.eye(2),
    )
    y = tk.simulate(lin, 20, 4, seed=2).y
    y[1, 3, 0] = np.nan  # a lost reading
    want = tk.KalmanFilter(lin, backend="numpy").filter(y)
    got = tk.GaussianSumAssumedDensityFilter(nl, tk.Censoring(), components=components).filter(y)
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-10)
    assert (got.extras["components"] == 1).all()  # an affine h is never split


def _posterior_moments(prior_mean, prior_var, h, y, r, lower=-np.inf):
    """Brute-force quadrature of the posterior mean and variance of a scalar state (a fine grid over 12 sd)."""
    sd = np.sqrt(prior_var)
    x = np.linspace(prior_mean - 12 * sd, prior_mean + 12 * sd, 400001)
    log_prior = -0.5 * (x - prior_mean) ** 2 / prior_var
    if y <= lower:
        log_lik = log_ndtr((lower - h(x)) / np.sqrt(r))
    else:
        log_lik = -0.5 * (y - h(x)) ** 2 / r
    w = np.exp(log_prior + log_lik - np.max(log_prior + log_lik))
    w /= w.sum()
    mean = (w * x).sum()
    return mean, (w * (x - mean) ** 2).sum()


# the second case's prior is nearly symmetric about the removed centre: the single Gaussian's mean is right there
@pytest.mark.parametrize("x0, p0, r, mean_off", [(0.3, 1.0, 0.1, True), (0.5, 2.0, 0.3, False)])
def test_one_step_against_quadrature_of_a_bimodal_posterior(x0, p0, r, mean_off):
    # the reading of 1 - x^2 is censored below 0, so |x| >= 1: the centre of the prior is removed and the posterior
    # has two lobes. The single Gaussian gets their spread wrong by half; the mixture's error shrinks with its size.
    h, lower = (lambda x: 1.0 - x**2), 0.0
    sys_ = tk.NonlinearSystem(lambda x, k: x, lambda x, k: h(x), [[0.0]], [[r]], [x0], [[p0]])
    cens = tk.Censoring(lower=lower)
    mu, var = _posterior_moments(x0, p0, h, 0.0, r, lower)
    rule = {"rule": "gauss_hermite", "order": 5}
    adf = tk.NonlinearAssumedDensityFilter(sys_, cens, **rule).filter([[0.0]])
    e_adf = abs(adf.mean[0, 0] - mu) / np.sqrt(var), abs(adf.cov[0, 0, 0] / var - 1)
    assert e_adf[1] > 0.4  # the case is one a Gaussian cannot follow
    errors = []
    for K in (7, 15, 31):
        gs = tk.GaussianSumAssumedDensityFilter(sys_, cens, components=K, **rule).filter([[0.0]])
        errors.append((abs(gs.mean[0, 0] - mu) / np.sqrt(var), abs(gs.cov[0, 0, 0] / var - 1)))
        assert gs.extras["components"][0] > 1
    e15, e31 = errors[1], errors[2]
    # closer than the single Gaussian, by far on the spread (and on the mean where that is off); within 0.05 sd and
    # 10 % of the variance
    assert e15[1] < 0.25 * e_adf[1]
    assert e15[0] < 0.5 * e_adf[0] if mean_off else e_adf[0] < 0.01
    assert e15[0] < 0.05 and e15[1] < 0.1
    assert errors[2][1] < errors[0][1]  # and closer with more components
    assert e31[0] < 0.05 and e31[1] < 0.1


def test_weights_sum_to_one_and_stay_within_the_budget():
    system, cens, data = _localisation_record(runs=4, steps=20)
    out = tk.GaussianSumAssumedDensityFilter(system, cens, components=6).filter(data.y)
    W, count = out.extras["weights"], out.extras["components"]
    assert W.shape == (4, 20, 6)
    np.testing.assert_allclose(W.sum(-1), 1.0, rtol=0, atol=1e-12)
    assert (W >= 0).all() and (count >= 1).all() and (count <= 6).all()
    assert (count > 1).any()  # the wide prior is split on this model
    used = np.arange(6) < count[..., None]
    assert (W[~used] == 0).all()
    assert np.isfinite(out.extras["log_likelihood"]).all()


def test_step_loop_equals_filter():
    system, cens, data = _localisation_record(runs=2, steps=10)
    est = tk.GaussianSumAssumedDensityFilter(system, cens, components=5)
    want = est.filter(data.y)
    state = est.init(batch_shape=(2,))
    for t in range(10):
        state = est.step(state, data.y[:, t])
        np.testing.assert_allclose(state.mean, want.mean[:, t], rtol=0, atol=1e-12)
        np.testing.assert_allclose(state.cov, want.cov[:, t], rtol=0, atol=1e-12)
    np.testing.assert_allclose(est.log_likelihood(data.y), want.extras["log_likelihood"].sum(-1), rtol=0, atol=1e-12)


def test_split_keeps_mean_and_covariance():
    rng = np.random.default_rng(0)
    L = rng.standard_normal((5, 3, 3))
    P = L @ np.swapaxes(L, -1, -2) + 0.1 * np.eye(3)
    m = rng.standard_normal((5, 3))
    means, Pc = split_principal(m, P)
    w = np.array(SPLIT_WEIGHTS)
    assert w.sum() == pytest.approx(1.0, abs=1e-15)
    mean = np.einsum("c,rci->ri", w, means)
    d = means - mean[:, None]
    cov = Pc + np.einsum("c,rci,rcj->rij", w, d, d)
    np.testing.assert_allclose(mean, m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cov, P, rtol=0, atol=1e-12)
    assert (np.linalg.eigvalsh(Pc) > 0).all()


def test_repeated_splits_stay_close_to_the_normal_density():
    # three levels of splits of N(0, 1): 27 components whose mixture density stays within 0.02 of the normal's
    # (5 % of its peak 0.399): the split does not leave gaps that a reading could fall into
    from scipy.stats import norm

    m, P, w = np.zeros((1, 1)), np.ones((1, 1, 1)), np.ones(1)
    for _ in range(3):
        means, Pc = split_principal(m, P)
        m = means.reshape(-1, 1)
        P = np.repeat(Pc, 3, axis=0)
        w = (w[:, None] * np.array(SPLIT_WEIGHTS)).ravel()
    x = np.linspace(-6, 6, 2001)
    mix = (w[:, None] * norm.pdf(x, m, np.sqrt(P[:, :, 0]))).sum(0)
    assert m.shape[0] == 27 and np.abs(mix - norm.pdf(x)).max() < 0.02


def test_merging_everything_keeps_the_mixture_moments():
    rng = np.random.default_rng(1)
    N, K, n = 3, 5, 2
    M = rng.standard_normal((N, K, n))
    L = rng.standard_normal((N, K, n, n))
    Cv = L @ np.swapaxes(L, -1, -2) + 0.1 * np.eye(n)
    lw = np.log(rng.dirichlet(np.ones(K), size=N))
    lw[0, 4] = -np.inf  # run 0 uses four slots
    lw[0, :4] -= np.log(np.exp(lw[0, :4]).sum())
    count = np.array([4, 5, 5])
    from tobitkf.filters.particle import _mixture_moments

    want = _mixture_moments(M, Cv, np.exp(lw))
    M2, C2, lw2, count2 = _merge(M.copy(), Cv.copy(), lw.copy(), count.copy(), np.inf)
    assert (count2 == 1).all()
    np.testing.assert_allclose(np.exp(lw2[:, 0]), 1.0, rtol=0, atol=1e-12)
    assert np.isneginf(lw2[:, 1:]).all()
    np.testing.assert_allclose(M2[:, 0], want[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(C2[:, 0], want[1], rtol=0, atol=1e-12)


def test_refusals():
    system, cens = localisation_system()
    with pytest.raises(tk.ValidationError, match="components"):
        tk.GaussianSumAssumedDensityFilter(system, cens, components=0)
    with pytest.raises(tk.ValidationError, match="split_threshold"):
        tk.GaussianSumAssumedDensityFilter(system, cens, split_threshold=0.0)
    with pytest.raises(tk.ValidationError, match="merge_threshold"):
        tk.GaussianSumAssumedDensityFilter(system, cens, merge_threshold=-1.0)
    lin = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="system"):
        tk.GaussianSumAssumedDensityFilter(lin, tk.Censoring(lower=0.0))
    with pytest.raises(tk.ValidationError):
        tk.GaussianSumAssumedDensityFilter(system, cens).filter(np.full((4, 3), -90.0))  # below the floor
