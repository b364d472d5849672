"""The assumed-density filters: the Tobit ADF, the fading ADF and the protocol (failure-conditioning) ADF.

Oracles: the Kalman filter (infinite limits, deterministic fading, no failures) to 1e-12, and
brute-force two-dimensional quadrature of the exact posterior moments of one step, including
readings 40 standard deviations into either tail.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk
from tobitkf.channels.laws import PMF, Uniform
from tobitkf.filters.adf_protocol import failure_nodes
from tobitkf.filters.assumed_density import assumed_density_update, merge_gaussians

TOL = 1e-12
FORMS = ["standard", "joseph", "square_root"]


def oscillator(**kw):
    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    base = dict(A=A, C=[[1.0, 0.0]], Q=1e-2 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.5 * np.eye(2))
    base.update(kw)
    return tk.LinearSystem(**base)


def _trapezoid_weights(t):
    w = np.zeros_like(t)
    d = np.diff(t)
    w[:-1] += d / 2
    w[1:] += d / 2
    return w


def quadrature_moments(logpost, xbar, Pbar, limits, r):
    """Mean and covariance of exp(logpost) on R^2, the reading on x_1, by a brute-force tensor grid.

    Coordinates (t, e) = (x_1, x_2 - beta x_1), beta = P_21 / P_11 (the prior's are independent in them);
    the t-grid is the union of dense uniform grids over +-14 sd of the prior, +-14 sd of the posterior
    around its numerically found mode, and +-14 sqrt(r) around each finite limit (the soft wall of a
    censored reading); the e-grid covers +-14 of its prior sd. Trapezoid weights, log-space weights."""
    beta = Pbar[1, 0] / Pbar[0, 0]
    st, se = np.sqrt(Pbar[0, 0]), np.sqrt(Pbar[1, 1] - beta * Pbar[1, 0])
    eb = xbar[1] - beta * xbar[0]

    def lp_t(t):  # log-posterior of t (e at its prior mean: the t-marginal up to a constant)
        return logpost(np.stack([t, eb + beta * t], -1))

    walls = [np.linspace(lim - 14 * np.sqrt(r), lim + 14 * np.sqrt(r), 2001) for lim in limits if np.isfinite(lim)]
    t0 = np.unique(np.concatenate([np.linspace(xbar[0] - 14 * st, xbar[0] + 14 * st, 8001)] + walls))
    mode = t0[np.argmax(lp_t(t0))]
    fine = np.linspace(mode - 0.1 * st, mode + 0.1 * st, 2001)
    mode = fine[np.argmax(lp_t(fine))]
    h = 1e-3 * st
    curv = -(lp_t(np.array([mode + h])) - 2 * lp_t(np.array([mode])) + lp_t(np.array([mode - h])))[0] / h**2
    sp = 1 / np.sqrt(max(curv, 1e-12))
    t = np.unique(np.concatenate([t0, np.linspace(mode - 14 * sp, mode + 14 * sp, 2001)]))
    e = np.linspace(eb - 14 * se, eb + 14 * se, 201)
    T, E = np.meshgrid(t, e, indexing="ij")
    X = np.stack([T, E + beta * T], -1).reshape(-1, 2)
    lp = logpost(X)
    p = np.exp(lp - lp.max()) * np.outer(_trapezoid_weights(t), _trapezoid_weights(e)).ravel()
    p /= p.sum()
    mean = p @ X
    d = X - mean
    return mean, (d * p[:, None]).T @ d


def tobit_logpost(xbar, Pbar, c, r, y, lo, hi):
    Pi = np.linalg.inv(Pbar)

    def f(X):
        d = X - xbar
        lp = -0.5 * np.einsum("ni,ij,nj->n", d, Pi, d)
        mu = X @ c
        sd = np.sqrt(r)
        if y <= lo:
            return lp + log_ndtr((lo - mu) / sd)
        if y >= hi:
            return lp + log_ndtr((mu - hi) / sd)
        return lp - 0.5 * (y - mu) ** 2 / r

    return f


# --------------------------------------------------------------------------- the Tobit ADF


@pytest.mark.parametrize("form", FORMS)
def test_adf_reduces_to_the_kalman_filter_with_infinite_limits(form):
    sys_ = oscillator(C=[[1.0, 0.0], [0.3, 1.0]], R=np.diag([0.1, 0.2]))
    d = tk.simulate(sys_, 30, 8, seed=1)
    y = d.y.copy()
    y[np.random.default_rng(0).random(y.shape) < 0.15] = np.nan
    kf = tk.KalmanFilter(sys_, backend="numpy", covariance_update=form).filter(y)
    adf = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), covariance_update=form).filter(y)
    np.testing.assert_allclose(adf.mean, kf.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(adf.cov, kf.cov, rtol=0, atol=TOL)
    np.testing.assert_allclose(adf.pred_cov, kf.pred_cov, rtol=0, atol=TOL)


CASES = {  # prior mean, reading, limits: (x̄, y, lower, upper)
    "lower": ([0.4, -0.2], 0.0, 0.0, np.inf),
    "upper": ([0.4, -0.2], 1.0, -np.inf, 1.0),
    "two-sided-low": ([0.4, -0.2], -0.3, -0.3, 0.9),
    "two-sided-high": ([0.4, -0.2], 0.9, -0.3, 0.9),
    "interior": ([0.4, -0.2], 0.55, -0.3, 0.9),
    "lower-40-sigma-deep": ([40.0, 0.0], 0.0, 0.0, np.inf),  # censored 40 sigma below the prediction
    "lower-40-sigma-likely": ([-40.0, 0.0], 0.0, 0.0, np.inf),  # censored, the prediction 40 sigma inside
    "upper-40-sigma-deep": ([-40.0, 0.0], 0.0, -np.inf, 0.0),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_adf_update_equals_quadrature_of_the_posterior_moments(name):
    xbar, y, lo, hi = CASES[name]
    xbar = np.asarray(xbar)
    Pbar = np.array([[1.0, 0.3], [0.3, 0.5]])
    c, r = np.array([1.0, 0.0]), 1e-3
    s = np.sqrt(c @ Pbar @ c + r)
    mean, cov = quadrature_moments(tobit_logpost(xbar, Pbar, c, r, y, lo, hi), xbar, Pbar, (lo, hi), r)
    scale = np.sqrt(np.diagonal(cov))
    for form in FORMS:
        x, P = assumed_density_update(
            xbar[None], Pbar[None], np.array([[y]]), c[None], [r], [lo], [hi], covariance_update=form
        )
        np.testing.assert_allclose(x[0], mean, rtol=0, atol=1e-6 * (np.abs(mean).max() + s))
        np.testing.assert_allclose(P[0], cov, rtol=0, atol=1e-6 * np.outer(scale, scale).max() + 1e-12)
    if "40-sigma-deep" in name:  # the reading moved the estimate 40 prior sd, to the limit
        assert abs(x[0, 0] - (lo if np.isfinite(lo) else hi)) < 0.1


def test_adf_noiseless_reading_uses_the_prior_variance():
    """R = 0: a reading at the limit truncates the prior (half-normal moments), an interior one pins c x."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    adf = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=0.0))
    out = adf.filter(np.array([[0.0]]))
    assert out.mean[0, 0] == pytest.approx(-np.sqrt(2 / np.pi), rel=1e-12)
    assert out.cov[0, 0, 0] == pytest.approx(1 - 2 / np.pi, rel=1e-12)
    two = tk.LinearSystem(A=np.eye(2), C=[[1.0, 1.0]], Q=np.zeros((2, 2)), R=[[0.0]], x0=[0.0, 0.0], P0=np.eye(2))
    for form in FORMS:
        o = tk.AssumedDensityTobitFilter(two, tk.Censoring(lower=-5.0), covariance_update=form).filter([[0.7], [0.7]])
        assert o.mean[0] @ [1.0, 1.0] == pytest.approx(0.7, abs=1e-12)
        assert np.linalg.eigvalsh(o.cov[-1]).min() > -1e-12


@pytest.mark.parametrize("form", ["joseph", "square_root"])
def test_adf_covariance_forms_agree_on_censored_data(form):
    sys_ = oscillator(C=[[1.0, 0.0], [0.5, 1.0]], R=np.diag([0.05, 0.1]))
    cens = tk.Censoring(lower=[0.0, -0.2], upper=[0.8, np.inf])
    d = tk.simulate(sys_, 40, 10, censoring=cens, seed=2)
    a = tk.AssumedDensityTobitFilter(sys_, cens).filter(d.y)
    b = tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form).filter(d.y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=1e-10)


def test_adf_time_varying_and_steered_limits_and_multi_region():
    sys_ = oscillator()
    T = 10
    lower = np.linspace(-0.2, 0.3, T)[:, None]
    d = tk.simulate(sys_, T, 3, censoring=tk.Censoring(lower=lower), seed=3)
    ref = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=lower)).filter(d.y)
    adf = tk.AssumedDensityTobitFilter(sys_, tk.Censoring())
    state = adf.init((3,))
    for k in range(T):
        state = adf.update(adf.predict(state), d.y[:, k], lower=lower[k])
        np.testing.assert_allclose(state.mean, ref.mean[:, k], rtol=0, atol=TOL)
    stacked, mr = tk.multi_region(sys_, [[(-np.inf, 0.0), (0.0, np.inf)]])
    d2 = tk.simulate(stacked, 20, 5, censoring=mr, seed=4)
    out = tk.AssumedDensityTobitFilter(stacked, mr).filter(d2.y)
    assert np.isfinite(out.mean).all() and out.extras["p_uncensored"].shape == (5, 20, 2)


def test_adf_is_near_the_optimum_where_the_tkf_is_not():
    """On a censored random walk (Miller Example 2, shortened) the ADF tracks the particle filter."""
    sys_ = tk.LinearSystem(A=[[0.999]], C=[[1.0]], Q=[[0.01]], R=[[0.05**2]], x0=[0.05], P0=[[0.05]])
    cens = tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 300, 60, censoring=cens, seed=5)
    pf = tk.ParticleFilter(sys_, cens, particles=1000, seed=6).filter(d.y, outputs="mean")
    r = {
        k: tk.metrics.rmse(d.x, e.filter(d.y).mean).mean()
        for k, e in {
            "adf": tk.AssumedDensityTobitFilter(sys_, cens),
            "tkf": tk.TobitKalmanFilter(sys_, cens, noise_term="exact_pv"),
        }.items()
    }
    r_pf = tk.metrics.rmse(d.x, pf.mean).mean()
    assert r["adf"] / r_pf < 1.03 and r["tkf"] / r_pf > 1.3


# --------------------------------------------------------------------------- the fading ADF


@pytest.mark.parametrize("form", FORMS)
def test_fading_adf_with_deterministic_gains_is_the_augmented_kalman_filter(form):
    sys_ = oscillator()
    fad = tk.RiceFading(2, [0.9, 0.6, 0.3])
    d = tk.simulate(sys_, 20, 6, measurement=fad, seed=7)
    n, L = 2, 2
    nx = n * (L + 1)
    Aa = np.zeros((nx, nx))
    Aa[:n, :n] = sys_.A.at(0)
    Aa[n:, :-n] = np.eye(n * L)
    Qa = np.zeros((nx, nx))
    Qa[:n, :n] = 1e-2 * np.eye(2)
    P0 = np.zeros((nx, nx))
    P0[:n, :n] = 0.5 * np.eye(2)

    def C(k):
        H = np.zeros((1, nx))
        for s in range(min(L, k) + 1):
            H[0, s * n] = [0.9, 0.6, 0.3][s]
        return H

    aug = tk.LinearSystem(A=Aa, C=C, Q=Qa, R=[[0.1]], x0=np.zeros(nx), P0=P0)
    kf = tk.KalmanFilter(aug, backend="numpy", covariance_update=form).filter(d.y)
    adf = tk.FadingAssumedDensityFilter(sys_, fad, covariance_update=form).filter(d.y)
    np.testing.assert_allclose(adf.mean, kf.mean[..., :n], rtol=0, atol=1e-10)
    np.testing.assert_allclose(adf.cov, kf.cov[..., :n, :n], rtol=0, atol=1e-10)


def test_fading_adf_is_at_least_as_good_as_the_tkf_fm():
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
    d = tk.simulate(sys_, 60, 200, censoring=cens, measurement=fad, seed=8)
    adf = tk.metrics.rmse(d.x, tk.FadingAssumedDensityFilter(sys_, fad, cens).filter(d.y).mean).mean(0)
    fm = tk.metrics.rmse(d.x, tk.FadingTobitKalmanFilter(sys_, fad, cens).filter(d.y).mean).mean(0)
    assert (adf < fm).all()


# --------------------------------------------------------------------------- the protocol ADF


def test_protocol_adf_without_failures_or_censoring_is_the_augmented_kalman_filter():
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
    for mode in ("prior", "hold", "zero"):
        ch = tk.ProtocolChannel(2, window=2, prehistory=mode)
        d = tk.simulate(sys_, 15, 4, channel=ch, seed=9)
        n, ell = 2, 2
        nx = n * (ell + 1)
        Aa = np.zeros((nx, nx))
        Aa[:n, :n] = sys_.A.at(0)
        Aa[n:, :-n] = np.eye(n * ell)
        Qa = np.zeros((nx, nx))
        Qa[:n, :n] = 1e-2 * np.eye(2)
        blocks = {"prior": np.eye(ell + 1), "hold": np.ones((ell + 1, ell + 1)), "zero": np.diag([1.0] + [0.0] * ell)}[
            mode
        ]
        P0 = np.kron(blocks, 0.5 * np.eye(2))
        x0 = np.zeros(nx)
        aug = tk.LinearSystem(
            A=Aa,
            C=lambda k: np.tile(np.eye(2)[(k - 1) % 2], ell + 1)[None],
            Q=Qa,
            R=lambda k: np.array([[[0.1, 0.2][(k - 1) % 2]]]),
            x0=x0,
            P0=P0,
        )
        kf = tk.KalmanFilter(aug, backend="numpy").filter(d.y)
        adf = tk.ProtocolAssumedDensityFilter(sys_, ch).filter(d.y)
        np.testing.assert_allclose(adf.mean, kf.mean[..., :n], rtol=0, atol=1e-10)
        np.testing.assert_allclose(adf.cov, kf.cov[..., :n, :n], rtol=0, atol=1e-10)


@pytest.mark.parametrize("reading", [0.0, 0.7, 3.0])
def test_protocol_adf_update_equals_quadrature_of_the_mixture_posterior(reading):
    """One step, window 0 (the state is x): prior times sum_j pi_j L_j(x) integrated numerically."""
    law = PMF([0.0, 0.5, 1.0], [0.05, 0.10, 0.85])
    sys_ = tk.LinearSystem(
        A=np.eye(2),
        C=np.eye(2),
        Q=np.zeros((2, 2)),
        R=np.diag([0.04, 0.04]),
        x0=[0.4, -0.3],
        P0=[[1.0, 0.3], [0.3, 0.5]],
    )
    ch = tk.ProtocolChannel(2, window=0, failures=law, threshold=0.0)
    for form in FORMS:
        out = tk.ProtocolAssumedDensityFilter(sys_, ch, covariance_update=form).filter(np.array([[reading]]))
        Pi = np.linalg.inv(sys_.P0)

        def logpost(X):
            d = X - sys_.x0
            lp = -0.5 * np.einsum("ni,ij,nj->n", d, Pi, d)
            terms = []
            for lam, p in zip(law.values, law.probs):
                mu = lam * X[:, 0]
                if reading <= 0.0:
                    terms.append(np.log(p) + log_ndtr((0.0 - mu) / 0.2))
                else:
                    terms.append(np.log(p) - 0.5 * ((reading - mu) / 0.2) ** 2 - np.log(0.2))
            return lp + np.logaddexp.reduce(np.stack(terms), axis=0)

        # the mixture may be bimodal: a wide fixed grid (prior scale) instead of the mode-centred one
        t = np.linspace(-9, 9, 1201)
        U = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
        X = sys_.x0 + U @ np.linalg.cholesky(sys_.P0).T
        lp = logpost(X)
        p = np.exp(lp - lp.max())
        p /= p.sum()
        mean = p @ X
        cov = ((X - mean) * p[:, None]).T @ (X - mean)
        np.testing.assert_allclose(out.mean[0], mean, rtol=0, atol=1e-7)
        np.testing.assert_allclose(out.cov[0], cov, rtol=0, atol=1e-7)
        post = out.extras["failure_posterior"][0]
        assert post.shape == (3,) and post.sum() == pytest.approx(1.0)
        if reading == 3.0:
            assert post[2] > 0.99  # a large reading comes from a healthy sensor


def test_failure_nodes_and_merge():
    v, p = failure_nodes(Uniform(0.2, 0.8), 8)
    assert (
        p.sum() == pytest.approx(1.0) and (p @ v) == pytest.approx(0.5) and (p @ (v - 0.5) ** 2) == pytest.approx(0.03)
    )
    v, p = failure_nodes(tk.channels.laws.Constant(1.0))
    assert v.tolist() == [1.0] and p.tolist() == [1.0]
    with pytest.raises(tk.ValidationError, match="needs a PMF, constant or Uniform failure law"):
        failure_nodes(tk.channels.laws.Gaussian(0.5, 0.01))
    rng = np.random.default_rng(0)
    means = rng.standard_normal((3, 4, 2))
    L = rng.standard_normal((3, 4, 2, 2))
    covs = L @ np.swapaxes(L, -1, -2)
    w = rng.random((3, 4))
    w /= w.sum(0)
    x, P, _ = merge_gaussians(w, means, covs)
    x2, P2, S2 = merge_gaussians(w, means, covs, np.linalg.cholesky(covs))
    np.testing.assert_allclose(x2, x, atol=TOL)
    np.testing.assert_allclose(P2, P, atol=1e-12)
    np.testing.assert_allclose(S2 @ np.swapaxes(S2, -1, -2), P, atol=1e-12)


# --------------------------------------------------------------------------- the saturation ADF


def test_saturation_adf_without_saturation_or_losses_is_the_kalman_filter():
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.05, 0.1]))
    d = tk.simulate(sys_, 20, 5, seed=13)
    y = d.y.copy()
    y[np.random.default_rng(1).random(y.shape) < 0.1] = np.nan
    for form in FORMS:
        kf = tk.KalmanFilter(sys_, backend="numpy", covariance_update=form).filter(y)
        adf = tk.SaturationAssumedDensityFilter(
            sys_, tk.RandomSaturation([0.0, 0.0], [1.0, 1.0]), covariance_update=form
        ).filter(y)
        np.testing.assert_allclose(adf.mean, kf.mean, rtol=0, atol=TOL)
        np.testing.assert_allclose(adf.cov, kf.cov, rtol=0, atol=TOL)


@pytest.mark.parametrize("reading", [-0.95, 0.3, 1.02, 2.5])
def test_saturation_adf_update_equals_quadrature_of_the_mode_mixture(reading):
    mu, nu, u, r = 0.4, 0.7, 1.0, 0.01
    xbar, Pbar = np.array([0.6, -0.2]), np.array([[1.0, 0.3], [0.3, 0.5]])
    sys_ = tk.LinearSystem(A=np.eye(2), C=[[1.0, 0.0]], Q=np.zeros((2, 2)), R=[[r]], x0=xbar, P0=Pbar)
    Pi = np.linalg.inv(Pbar)

    def npdf(m):
        return np.exp(-0.5 * (reading - m) ** 2 / r) / np.sqrt(2 * np.pi * r)

    def logpost(X):
        d = X - xbar
        c = X[:, 0]
        lik = mu * npdf(np.clip(c, -u, u)) + (1 - mu) * nu * npdf(c) + (1 - mu) * (1 - nu) * npdf(0.0)
        return -0.5 * np.einsum("ni,ij,nj->n", d, Pi, d) + np.log(lik)

    mean, cov = quadrature_moments(logpost, xbar, Pbar, (-u, u), r)
    for form in FORMS:
        out = tk.SaturationAssumedDensityFilter(
            sys_, tk.RandomSaturation([mu], [nu], level=u), covariance_update=form
        ).filter(np.array([[reading]]))
        np.testing.assert_allclose(out.mean[0], mean, rtol=0, atol=2e-6)
        np.testing.assert_allclose(out.cov[0], cov, rtol=0, atol=2e-6)
        assert out.extras["mode_posterior"].shape == (1, 1, 3)


def test_saturation_adf_is_near_the_optimum_where_the_kalman_filter_is_not():
    w = 0.1 * np.pi
    sys_ = tk.LinearSystem(
        A=0.95 * np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]),
        C=np.eye(2),
        Q=0.1 * np.eye(2),
        R=0.01 * np.eye(2),
        x0=[0.0, 0.0],
        P0=np.eye(2),
    )
    ch = tk.RandomSaturation([0.7, 0.6], [0.7, 0.75])  # the H-infinity example's probabilities
    d = tk.simulate(sys_, 40, 60, channel=ch, seed=14)
    pf = tk.ParticleFilter(sys_, ch, particles=1000, seed=15).filter(d.y, outputs="mean")
    r_pf = tk.metrics.rmse(d.x, pf.mean).mean()
    r_adf = tk.metrics.rmse(d.x, tk.SaturationAssumedDensityFilter(sys_, ch).filter(d.y).mean).mean()
    r_kf = tk.metrics.rmse(d.x, tk.KalmanFilter(sys_).filter(d.y).mean).mean()
    assert r_adf / r_pf < 1.05 and r_kf / r_pf > 1.5


# --------------------------------------------------------------------------- online API and errors


def _cases():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0, upper=1.0)
    d = tk.simulate(sys_, 12, 4, censoring=cens, seed=10)
    psys = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
    ch = tk.ProtocolChannel(2, window=1, failures=PMF([0.0, 1.0], [0.2, 0.8]), threshold=0.0)
    pd = tk.simulate(psys, 12, 4, channel=ch, seed=11)
    fad = tk.RiceFading.gaussian(1, [0.9, 0.6], [0.01, 0.01])
    fd = tk.simulate(sys_, 12, 4, censoring=tk.Censoring(lower=0.0), measurement=fad, seed=12)
    ssys = oscillator(C=np.eye(2), R=np.diag([0.05, 0.1]))
    ros = tk.RandomSaturation([0.3, 0.2], [0.8, 0.9], level=0.5)
    sd = tk.simulate(ssys, 12, 4, channel=ros, seed=13)
    out = {}
    for form in FORMS:
        out[f"tobit-{form}"] = (tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form), d.y)
        out[f"protocol-{form}"] = (tk.ProtocolAssumedDensityFilter(psys, ch, covariance_update=form), pd.y)
        out[f"fading-{form}"] = (
            tk.FadingAssumedDensityFilter(sys_, fad, tk.Censoring(lower=0.0), covariance_update=form),
            fd.y,
        )
        out[f"saturation-{form}"] = (tk.SaturationAssumedDensityFilter(ssys, ros, covariance_update=form), sd.y)
    return out


@pytest.mark.parametrize("name", sorted(_cases()))
def test_step_loop_equals_filter_and_pickle_resumes(name):
    est, y = _cases()[name]
    y = y.copy()
    y[np.random.default_rng(0).random(y.shape) < 0.1] = np.nan
    res = est.filter(y)
    state = est.init((4,))
    means = []
    for k in range(12):
        state = est.step(state, y[:, k])
        means.append(state.mean)
        if k == 5:
            revived = pickle.loads(pickle.dumps(state))
    np.testing.assert_allclose(np.stack(means, 1), res.mean, rtol=0, atol=TOL)
    cont = est.filter(y[:, 6:], state=revived)
    np.testing.assert_allclose(cont.mean, res.mean[:, 6:], rtol=0, atol=TOL)
    s = est.init((4,))
    for k in range(3):
        s = est.update(est.predict(s), y[:, k])
    np.testing.assert_allclose(s.mean, res.mean[:, 2], rtol=0, atol=TOL)


def test_bad_arguments_are_refused():
    sys_ = oscillator()
    with pytest.raises(tk.ValidationError, match="R: the assumed-density filter processes the channels in sequence"):
        tk.AssumedDensityTobitFilter(oscillator(C=np.eye(2), R=[[1.0, 0.5], [0.5, 1.0]]), tk.Censoring())
    with pytest.raises(tk.ValidationError, match="covariance_update: expected one of"):
        tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), covariance_update="qr")
    with pytest.raises(tk.ValidationError, match="censoring: expected"):
        tk.AssumedDensityTobitFilter(sys_, "censoring")
    adf = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=0.0))
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        adf.filter(np.array([[-1.0]]))
    with pytest.raises(tk.ValidationError, match="update\\(\\) needs a predicted state"):
        adf.update(adf.init(), [0.0])
    with pytest.raises(tk.ValidationError, match="lower/upper: expected lower < upper"):
        adf.step(adf.init(), [0.5], lower=1.0, upper=0.5)
    psys = oscillator(C=np.eye(2), R=np.eye(2))
    with pytest.raises(tk.ValidationError, match="nodes: expected a positive integer"):
        tk.ProtocolAssumedDensityFilter(psys, tk.ProtocolChannel(2), nodes=0)
    with pytest.raises(tk.ShapeError):
        tk.ProtocolAssumedDensityFilter(sys_, tk.ProtocolChannel(2))
    with pytest.raises(tk.ValidationError, match="below the protocol threshold"):
        tk.ProtocolAssumedDensityFilter(psys, tk.ProtocolChannel(2, threshold=0.0)).filter([[-1.0]])
    with pytest.raises(tk.ValidationError, match="fading: expected"):
        tk.FadingAssumedDensityFilter(sys_, "fading")
