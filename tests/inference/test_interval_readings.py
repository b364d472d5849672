"""Interval readings (a value known only to lie in [lo, hi]) through the assumed-density filter, its
likelihood and smoother, and tk.fit: against brute-force quadrature and the one-sided censored reading."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import norm

import tobitkf as tk
from tobitkf.filters._readings import INTERVAL, censored_log_likelihood, censoring_sides

BACKENDS = ["numpy", "auto"]


def _system(r: float = 0.3):
    return tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.2]], R=[[r]], x0=[0.4], P0=[[1.5]])


def _one_step_oracle(sys_, lo, hi):
    """Brute-force quadrature of the one-step posterior of x_1 given lo <= x_1 + v <= hi."""
    m = 0.9 * 0.4
    P = 0.81 * 1.5 + 0.2
    r = 0.3

    def like(x):  # P(lo <= x + v <= hi)
        return norm.cdf((hi - x) / np.sqrt(r)) - norm.cdf((lo - x) / np.sqrt(r))

    def w(x):
        return norm.pdf(x, m, np.sqrt(P)) * like(x)

    a, b = m - 12 * np.sqrt(P), m + 12 * np.sqrt(P)
    z = integrate.quad(w, a, b, epsabs=1e-14, epsrel=1e-13, limit=200)[0]
    mean = integrate.quad(lambda x: x * w(x), a, b, epsabs=1e-14, epsrel=1e-13, limit=200)[0] / z
    var = integrate.quad(lambda x: (x - mean) ** 2 * w(x), a, b, epsabs=1e-14, epsrel=1e-13, limit=200)[0] / z
    return np.log(z), mean, var


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("lo, hi", [(0.1, 0.9), (-2.0, -1.7), (1.9, 2.0), (-0.5, np.inf), (-np.inf, 0.2)])
def test_an_interval_reading_is_the_quadrature_posterior(backend, lo, hi):
    sys_ = _system()
    est = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), backend=backend)
    y = np.array([[0.5 * (lo + hi) if np.isfinite(lo + hi) else (lo + 1.0 if np.isfinite(lo) else hi - 1.0)]])
    res = est.filter(y, censored=[[True]], lower=[[lo]], upper=[[hi]])
    ll, mean, var = _one_step_oracle(sys_, lo, hi)
    assert res.extras["log_likelihood"][0] == pytest.approx(ll, abs=1e-10)
    assert res.mean[0, 0] == pytest.approx(mean, abs=1e-9)
    assert res.cov[0, 0, 0] == pytest.approx(var, abs=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_interval_open_on_one_side_is_the_censored_reading_exactly(backend):
    sys_ = _system()
    rng = np.random.default_rng(3)
    T = 12
    y = rng.normal(0.0, 1.0, (T, 1))
    a = 0.2
    # reading 4: right-censored at a (y = a, upper = a) against the interval [a, +inf) (y inside, flagged)
    lo_c, hi_c = np.full((T, 1), -np.inf), np.full((T, 1), np.inf)
    yc = y.copy()
    yc[4] = a
    hi_c[4] = a
    flags = np.zeros((T, 1), bool)
    flags[4] = True
    est = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), backend=backend)
    ref = est.filter(yc, censored=flags, lower=lo_c, upper=hi_c)
    lo_i, hi_i = lo_c.copy(), np.full((T, 1), np.inf)
    lo_i[4] = a
    yi = y.copy()
    yi[4] = a + 1.0
    got = est.filter(yi, censored=flags, lower=lo_i, upper=hi_i)
    np.testing.assert_array_equal(got.mean, ref.mean)
    np.testing.assert_array_equal(got.cov, ref.cov)
    np.testing.assert_array_equal(got.extras["log_likelihood"], ref.extras["log_likelihood"])
    # and the left side: (-inf, a] against the reading censored below a
    lo_c2 = np.full((T, 1), -np.inf)
    lo_c2[4] = a
    ref2 = est.filter(yc, censored=flags, lower=lo_c2, upper=np.inf)
    hi_i2 = np.full((T, 1), np.inf)
    hi_i2[4] = a
    yi2 = y.copy()
    yi2[4] = a - 1.0
    got2 = est.filter(yi2, censored=flags, lower=-np.inf, upper=hi_i2)
    np.testing.assert_array_equal(got2.mean, ref2.mean)
    np.testing.assert_array_equal(got2.extras["log_likelihood"], ref2.extras["log_likelihood"])


def test_compiled_and_numpy_agree_on_a_record_with_intervals():
    sys_ = _system()
    rng = np.random.default_rng(5)
    N, T = 3, 20
    y = rng.normal(0.0, 1.0, (N, T, 1))
    lo = np.full((N, T, 1), -np.inf)
    hi = np.full((N, T, 1), np.inf)
    flags = rng.random((N, T, 1)) < 0.4
    lo[flags] = y[flags] - 0.3
    hi[flags] = y[flags] + 0.5
    out = [
        tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), backend=b).filter(y, censored=flags, lower=lo, upper=hi)
        for b in BACKENDS
    ]
    np.testing.assert_allclose(out[0].mean, out[1].mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[0].cov, out[1].cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[0].extras["log_likelihood"], out[1].extras["log_likelihood"], rtol=0, atol=1e-11)
    ll = tk.adf_log_likelihood(sys_, tk.Censoring(), y, censored=flags, lower=lo, upper=hi)
    np.testing.assert_allclose(ll, out[0].extras["log_likelihood"].sum(-1), rtol=1e-12)


def test_the_interval_log_likelihood_is_the_mass():
    got = censored_log_likelihood(0.5, 0.1, 0.7, 0.0, 1.0, classes=INTERVAL)
    want = np.log(norm.cdf((1.0 - 0.1) / 0.7) - norm.cdf((0.0 - 0.1) / 0.7))
    assert float(got) == pytest.approx(want, rel=1e-13)


def test_a_flagged_reading_inside_needs_a_finite_limit():
    y = np.array([[0.5]])
    with pytest.raises(tk.ValidationError, match="no finite limit"):
        censoring_sides(y, -np.inf, np.inf, [[True]], intervals=True)
    with pytest.raises(tk.ValidationError, match="strictly inside"):
        censoring_sides(y, 0.0, 1.0, [[True]])  # the estimators that take no interval readings refuse them
    est = tk.AssumedDensityTobitFilter(_system(), tk.Censoring())
    with pytest.raises(tk.ValidationError, match="no finite limit"):
        est.filter(y, censored=[[True]], lower=-np.inf, upper=np.inf)


def test_the_smoother_takes_interval_readings():
    sys_ = _system()
    y = np.array([[0.3], [0.5], [-0.2]])
    flags = np.array([[False], [True], [False]])
    lo = np.array([[-np.inf], [0.1], [-np.inf]])
    hi = np.array([[np.inf], [0.9], [np.inf]])
    est = tk.AssumedDensityTobitFilter(sys_, tk.Censoring())
    f = est.filter(y, censored=flags, lower=lo, upper=hi)
    from tobitkf.filters.smoothing import rts_smooth

    sm = rts_smooth(f, sys_)
    # the last smoothed state is the last filtered one; the interval reading moved the filter from the KF's
    assert sm.mean[-1, 0] == pytest.approx(f.mean[-1, 0], abs=1e-14)
    kf = tk.KalmanFilter(sys_).filter(y)
    assert abs(f.mean[1, 0] - kf.mean[1, 0]) > 1e-3


def _record(seed=11, T=40):
    rng = np.random.default_rng(seed)
    x = np.zeros(T)
    for k in range(1, T):
        x[k] = 0.8 * x[k - 1] + rng.normal(0, 0.5)
    y = x + rng.normal(0, 0.3, T)
    return y


def test_fit_scores_interval_readings_by_their_mass_and_open_ones_as_censored():
    """tk.fit (a LinearSystem template, direct ML): the fitted log-likelihood is the assumed-density one with
    the interval readings as intervals (not as exact midpoints), and a record whose intervals are open on one
    side fits exactly as the same record censored there."""
    y = _record()
    T = y.size
    iv = np.zeros(T, bool)
    iv[[3, 9, 17, 25]] = True
    lo = np.where(iv, np.floor(y * 2) / 2, -np.inf)  # each interval a bin of width 0.5 holding the value
    hi = np.where(iv, lo + 0.5, np.inf)
    yi = np.where(iv, lo + 0.25, y)
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[0.2]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    kw = dict(estimate=("A", "Q", "R"), method="direct", standard_errors=False)
    res = tk.fit(templ, yi[:, None], censored=iv[:, None], lower=lo[:, None], upper=hi[:, None], **kw)
    cens = tk.Censoring(lower=lo[:, None], upper=hi[:, None])
    ll = tk.adf_log_likelihood(res.system(), cens, yi[:, None], censored=iv[:, None])
    assert res.loglik == pytest.approx(float(ll), abs=1e-9)
    # the midpoints read as exact values give another likelihood
    exact = tk.adf_log_likelihood(res.system(), tk.Censoring(), yi[:, None])
    assert abs(float(exact) - res.loglik) > 0.1
    # [lo, +inf) against the reading right-censored at lo (the compiled kernel scores that one)
    hi_open = np.where(iv, np.inf, hi)
    y_open = np.where(iv, lo + 1.0, y)
    a = tk.fit(templ, y_open[:, None], censored=iv[:, None], lower=lo[:, None], upper=hi_open[:, None], **kw)
    y_r = np.where(iv, lo, y)
    b = tk.fit(templ, y_r[:, None], censored=iv[:, None], lower=-np.inf, upper=np.where(iv, lo, np.inf)[:, None], **kw)
    assert a.loglik == pytest.approx(b.loglik, abs=1e-9)
    np.testing.assert_allclose(a.theta, b.theta, rtol=0, atol=1e-6)


def test_a_panel_takes_interval_readings():
    from tobitkf.inference.panel import panel_log_likelihood

    sys_ = tk.ContinuousLinearSystem([[-0.2]], [[0.4]], [[1.0]], [[0.09]], [0.0], [[1.0]])
    times = [np.array([0.0, 2.0, 5.0]), np.array([1.0, 4.0])]
    ys = [np.array([0.3, 0.55, -0.2]), np.array([1.25, 0.1])]
    flags = [np.array([False, True, False]), np.array([True, False])]
    los = [np.array([-np.inf, 0.2, -np.inf]), np.array([1.0, -np.inf])]
    his = [np.array([np.inf, 0.9, np.inf]), np.array([1.5, np.inf])]
    panel = tk.Panel(times, ys, lower=los, upper=his, censored=flags)
    per = panel_log_likelihood(sys_, panel, per_subject=True)
    for i in range(2):
        est = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), order="uncensored_first")
        own = est.filter(
            ys[i][:, None], censored=flags[i][:, None], lower=los[i][:, None], upper=his[i][:, None], times=times[i]
        ).extras["log_likelihood"]
        assert per[i] == pytest.approx(float(own.sum()), abs=1e-10)


def test_the_censored_ar_model_refuses_interval_readings_with_the_way_out():
    y = _record()
    iv = np.zeros(y.size, bool)
    iv[4] = True
    lo = np.where(iv, y - 0.2, -np.inf)
    hi = np.where(iv, y + 0.2, np.inf)
    with pytest.raises(tk.ValidationError, match="interval reading .* state-space model"):
        tk.fit(tk.CensoredAR(1), y, X=np.ones((y.size, 1)), lower=lo, upper=hi, censored=iv)
