"""Fits (tobitkf.fit): exact ML of the censored AR model (optimum, standard errors, criteria, what a user
does next), EM and direct fits of state-space models, recovery on simulated censored data."""

import json

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ShapeError, ValidationError
from tobitkf.data import load_phosphorus
from tobitkf.inference import CensoredAR, load_fit, residual_diagnostics
from tobitkf.inference._optimize import central_gradient, central_hessian
from tobitkf.inference.censored_ar import ar_state_space


@pytest.fixture(scope="module")
def phos_fit():
    d = load_phosphorus()
    return tk.fit(CensoredAR(1), d.y, X=d.design("lQ"), lower=d.lower, censored=d.censored)


def test_censored_ar_fit_is_a_maximum_with_observed_information_standard_errors(phos_fit):
    f = phos_fit
    data = f.data
    m = f.model
    ll = lambda th: m.log_likelihood(data, th)  # noqa: E731
    assert f.converged
    assert abs(ll(f.theta) - f.loglik) < 1e-9
    # the gradient in s.e. units vanishes; an independent central-difference Hessian gives the same s.e.
    se = np.array([f.se[n] for n in f.names])
    g = central_gradient(lambda v: ll(f.theta + v * se), np.zeros(f.theta.size), 1e-4)
    assert np.max(np.abs(g)) < 1e-3
    H = central_hessian(ll, f.theta, 1e-4)
    np.testing.assert_allclose(np.sqrt(np.diagonal(np.linalg.inv(-H))), se, rtol=1e-3)
    assert abs(f.aic - (-2 * f.loglik + 2 * 4)) < 1e-12
    assert abs(f.bic - (-2 * f.loglik + 4 * np.log(174))) < 1e-12
    assert f.n_obs == 174 and f.trace and f.trace[-1]["loglik"] <= f.loglik + 1e-9


def test_fit_save_and_load_roundtrip_plain_json(phos_fit, tmp_path):
    path = phos_fit.save(tmp_path / "fit.json")
    rec = json.loads(path.read_text())
    assert rec["format"] == "tobitkf-fit" and rec["model"]["kind"] == "censored_ar"
    assert set(rec["estimates"]) == {"beta0", "beta1", "sigma2", "phi1"}
    back = load_fit(path, data=phos_fit.data)
    np.testing.assert_array_equal(back.theta, phos_fit.theta)
    np.testing.assert_allclose(back.cov, phos_fit.cov, rtol=0, atol=0)
    assert back.loglik == phos_fit.loglik and back.aic == phos_fit.aic
    a, b = (
        back.forecast(3, X=np.c_[np.ones(3), np.full(3, 6.0)]),
        phos_fit.forecast(3, X=np.c_[np.ones(3), np.full(3, 6.0)]),
    )
    np.testing.assert_allclose(a["mean"], b["mean"], rtol=0, atol=0)
    with pytest.raises(ValidationError, match="data"):
        load_fit(path).forecast(2)
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(ValidationError, match="not a tobitkf fit"):
        load_fit(bad)


def test_forecasts_with_intervals_and_the_censored_reading(phos_fit):
    Xf = np.c_[np.ones(12), np.full(12, 6.5)]
    fc = phos_fit.forecast(12, X=Xf, level=0.9)
    assert np.all(fc["lower"] < fc["mean"]) and np.all(fc["mean"] < fc["upper"])
    # far ahead: the stationary regression mean and variance
    b0, b1, s2, phi = (phos_fit.params[k] for k in ("beta0", "beta1", "sigma2", "phi1"))
    assert abs(fc["mean"][-1] - (b0 + b1 * 6.5)) < 1e-6
    assert abs(fc["sd"][-1] ** 2 - s2 / (1 - phi**2)) < 1e-6
    from scipy.stats import norm

    half = norm.ppf(0.95) * fc["sd"][-1]
    assert abs(fc["upper"][-1] - fc["mean"][-1] - half) < 1e-6
    lim = phos_fit.data.lower[-1]
    assert np.all(fc["censored_lower"] >= lim) and np.all(fc["censored_mean"] >= lim)
    with pytest.raises(ValidationError, match="X"):
        phos_fit.forecast(2)
    with pytest.raises(ShapeError, match="X"):
        phos_fit.forecast(2, X=np.ones((3, 2)))


def test_quantile_residuals_and_diagnostics(phos_fit):
    r = phos_fit.residuals(seed=1)
    assert r.shape == (181,) and np.isnan(r).sum() == 7
    d = phos_fit.diagnostics(seed=1)
    assert abs(d["mean"]) < 0.3 and 0.6 < d["variance"] < 1.5
    assert d["ljung_box_p"] > 0.001 and d["ljung_box_dof"] == d["ljung_box_lags"] - 1
    # the residuals of exact readings do not depend on the seed, the censored ones do
    r2 = phos_fit.residuals(seed=2)
    exact = phos_fit.data.observed
    np.testing.assert_array_equal(r[exact], r2[exact])
    assert not np.allclose(r[phos_fit.data.side != 0], r2[phos_fit.data.side != 0])
    rng = np.random.default_rng(0)
    iid = residual_diagnostics(rng.normal(size=400))
    assert iid["ljung_box_p"] > 1e-3 and iid["jarque_bera_p"] > 1e-3
    with pytest.raises(ValidationError, match="at least 3"):
        residual_diagnostics([0.1, np.nan])


def test_smoothed_latent_readings_sit_below_the_limit_where_censored(phos_fit):
    mean, var = phos_fit.smooth()
    data = phos_fit.data
    c = data.side != 0
    assert np.all(mean[c] <= data.lower[c] + 1e-9)
    np.testing.assert_allclose(mean[data.observed], data.y[data.observed], atol=1e-12)
    assert np.all(var[data.observed] == 0) and np.all(var[c] > 0)


def _simulate_censored_ar(rng, T, beta, s2, phi, frac):
    xi = np.zeros(T)
    xi[0] = rng.normal() * np.sqrt(s2 / (1 - phi * phi))
    for t in range(1, T):
        xi[t] = phi * xi[t - 1] + rng.normal() * np.sqrt(s2)
    x = rng.normal(size=T)
    X = np.c_[np.ones(T), x]
    ystar = X @ beta + xi
    lim = np.quantile(ystar, frac)
    return np.maximum(ystar, lim), X, lim


def test_recovery_of_a_censored_ar1_regression_bias_and_coverage_within_monte_carlo_error():
    """30 replications, T = 250, 40 % left-censored. Each estimate's mean error must lie within 3 Monte
    Carlo standard errors (sd / sqrt(30)) of zero, and the coverage of the 95 % Wald intervals (120
    intervals: 4 parameters x 30 replications) within 3 binomial standard errors of 0.95."""
    rng = np.random.default_rng(2024)
    beta, s2, phi = np.array([1.0, 0.5]), 0.6, 0.7
    truth = np.r_[beta, s2, phi]
    est, cover = [], []
    for _ in range(30):
        y, X, lim = _simulate_censored_ar(rng, 250, beta, s2, phi, 0.4)
        f = CensoredAR(1).fit(y, X, lower=lim)
        th = f.theta
        se = np.array([f.se[n] for n in f.names])
        est.append(th)
        cover.append(np.abs(th - truth) <= 1.959964 * se)
    est, cover = np.array(est), np.array(cover)
    err = est.mean(0) - truth
    mcse = est.std(0, ddof=1) / np.sqrt(len(est))
    assert np.all(np.abs(err) < 3 * mcse), (err, mcse)
    n = cover.size
    assert abs(cover.mean() - 0.95) < 3 * np.sqrt(0.95 * 0.05 / n), cover.mean()


def _lgssm(seed=3, T=300):
    A = np.array([[0.8, 0.2], [0.0, 0.6]])
    C = np.array([[1.0, 0.4]])
    system = tk.LinearSystem(A=A, C=C, Q=np.diag([0.3, 0.2]), R=[[0.25]], x0=np.zeros(2), P0=np.eye(2))
    y = tk.simulate(system, steps=T, runs=1, seed=seed).y[0]
    return system, y


def test_em_increases_the_exact_likelihood_and_agrees_with_direct_maximisation():
    system = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.0], P0=[[1.0]])
    y = tk.simulate(system, steps=400, runs=1, seed=4).y[0].copy()
    y[[10, 11, 50]] = np.nan
    templ = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[2.0]], R=[[2.0]], x0=[0.0], P0=[[1.0]])
    em = tk.fit(templ, y, estimate=("Q", "R"), method="em", maxiter=1000, tol=1e-11)
    ll = np.array([e["loglik"] for e in em.trace])
    assert np.all(np.diff(ll) > -1e-8)  # EM never decreases the exact likelihood
    assert em.converged and em.method == "em" and em.likelihood == "kalman"
    direct = tk.fit(templ, y, estimate=("Q", "R"), method="direct")
    assert abs(em.loglik - direct.loglik) < 1e-5
    for n in em.names:
        assert abs(em.params[n] - direct.params[n]) < 0.01 * em.se[n]
    # the EM log-likelihood is the Kalman one of the fitted system
    assert abs(em.loglik - float(tk.kalman_log_likelihood(em.system(), y))) < 1e-9


def test_em_of_a_and_c_recovers_a_scalar_model_and_reports_standard_errors():
    rng = np.random.default_rng(7)
    system = tk.LinearSystem(A=[[0.85]], C=[[1.0]], Q=[[0.4]], R=[[0.3]], x0=[0.0], P0=[[1.0]])
    y = tk.simulate(system, steps=800, runs=1, seed=rng.integers(1 << 30)).y[0]
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    f = tk.fit(templ, y, estimate=("A", "Q", "R"), method="em", maxiter=1000, tol=1e-11)
    for name, true in (("A[0,0]", 0.85), ("Q[0,0]", 0.4), ("R[0,0]", 0.3)):
        assert abs(f.params[name] - true) < 4 * f.se[name], (name, f.params[name], f.se[name])


def test_direct_fit_of_a_user_map_equals_the_exact_censored_ar_fit_without_censoring():
    rng = np.random.default_rng(5)
    y, X, _ = _simulate_censored_ar(rng, 200, np.array([0.5, 1.0]), 0.8, 0.6, 0.0)

    def model(th):
        return ar_state_space(th[:2], np.exp(th[2]), [np.tanh(th[3])])

    f = tk.fit(model, y, u=X, theta0=[0.0, 0.0, 0.0, 0.0], names=["b0", "b1", "log_s2", "atanh_phi"])
    g = CensoredAR(1).fit(y, X)
    got = np.r_[f.theta[:2], np.exp(f.theta[2]), np.tanh(f.theta[3])]
    np.testing.assert_allclose(got, g.theta, atol=2e-3 * np.max(np.abs(g.theta)))
    assert abs(f.loglik - g.loglik) < 1e-5
    assert f.method == "direct" and f.likelihood == "kalman"


def test_censored_state_space_fit_with_the_assumed_density_likelihood_and_a_stationary_prior():
    system = tk.LinearSystem(A=[[0.7]], C=[[1.0]], Q=[[0.5]], R=[[0.2]], x0=[0.0], P0=[[0.5 / 0.51]])
    y = tk.simulate(system, steps=200, runs=1, seed=21).y[0]
    lim = float(np.quantile(y, 0.35))
    yc = np.maximum(y, lim)
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    em = tk.fit(
        templ,
        yc,
        lower=lim,
        estimate=("A", "Q", "R"),
        prior="stationary",
        method="em",
        maxiter=25,
        tol=1e-9,
        standard_errors=False,
    )
    assert em.likelihood == "adf" and len(em.trace) == 25
    S = em.system()
    A, Q = S.A.at(0)[0, 0], S.Q.at(0)[0, 0]
    assert abs(S.P0[0, 0] - Q / (1 - A * A)) < 1e-10  # the stationary prior, tied to A and Q
    ll = np.array([e["loglik"] for e in em.trace])
    assert ll[-1] > ll[0] + 10 and np.all(np.diff(ll[5:]) > 0)  # the ADF likelihood climbs (not guaranteed)
    # direct maximisation of the same assumed-density likelihood does at least as well
    direct = tk.fit(
        templ, yc, lower=lim, estimate=("A", "Q", "R"), prior="stationary", method="direct", standard_errors=False
    )
    assert direct.converged and direct.loglik >= em.loglik - 1e-6


def test_state_space_fit_save_load_forecast_and_residuals(tmp_path):
    system, y = _lgssm(seed=13, T=120)
    templ = tk.LinearSystem(
        A=system.A.at(0), C=system.C.at(1), Q=np.eye(2) * 0.5, R=[[0.5]], x0=np.zeros(2), P0=np.eye(2)
    )
    f = tk.fit(templ, y, estimate=("R",), maxiter=100)
    back = load_fit(f.save(tmp_path / "ss.json"), data=f.data)
    np.testing.assert_allclose(back.system().R.at(1), f.system().R.at(1), rtol=0, atol=0)
    fc = back.forecast(4)
    assert fc["mean"].shape == (4, 1) and np.all(fc["lower"] < fc["upper"])
    r = f.residuals()
    assert r.shape == (120,) and abs(np.mean(r)) < 0.4


def test_fit_errors_name_the_argument():
    system, y = _lgssm(T=30)
    with pytest.raises(ValidationError, match="estimate"):
        tk.fit(system, y, estimate=("Z",))
    with pytest.raises(ValidationError, match="theta0"):
        tk.fit(lambda th: system, y)
    with pytest.raises(ValidationError, match="method"):
        tk.fit(system, y, method="newton")
    with pytest.raises(ValidationError, match="model"):
        tk.fit("ar1", y)
    with pytest.raises(ValidationError, match="LinearSystem"):
        tk.fit(lambda th: 3.0, y, theta0=[0.0])
    with pytest.raises(ValidationError, match="template has no D"):
        tk.fit(system, y, estimate=("D",))
    withD = tk.LinearSystem(
        A=system.A.at(0), C=system.C.at(1), Q=system.Q.at(0), R=system.R.at(1), x0=system.x0, P0=system.P0, D=[[0.1]]
    )
    with pytest.raises(ValidationError, match="u: estimating"):
        tk.fit(withD, y, estimate=("D",))
    with pytest.raises(ValidationError, match="p"):
        CensoredAR(-1)
    with pytest.raises(ShapeError, match="start"):
        CensoredAR(1).fit(np.zeros(20) + np.arange(20) * 0.1, start=[0.0, 1.0])
    with pytest.raises(ValidationError, match="progress"):
        CensoredAR(1).fit(np.arange(20) * 0.1, progress="yes")
