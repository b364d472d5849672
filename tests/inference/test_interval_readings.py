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
@pytest.mark.parametrize("lo, hi", [(0.1, 0.9), (-2.0, -1.7), (1.9, 2.0), (-0.5, 6.0), (-9.0, 0.2), (0.4, 0.45)])
def test_an_interval_reading_is_the_quadrature_posterior(backend, lo, hi):
    sys_ = _system()
    est = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(), backend=backend)
    y = np.array([[0.5 * (lo + hi)]])
    res = est.filter(y, censored=[[True]], lower=[[lo]], upper=[[hi]])
    ll, mean, var = _one_step_oracle(sys_, lo, hi)
    assert res.extras["log_likelihood"][0] == pytest.approx(ll, abs=1e-10)
    assert res.mean[0, 0] == pytest.approx(mean, abs=1e-9)
    assert res.cov[0, 0, 0] == pytest.approx(var, abs=1e-9)


def test_an_interval_open_on_one_side_is_the_censored_reading_exactly():
    """The interval event with one infinite end is, to the last bit, the censored reading at the other end: in
    the compiled moments (the loop's block), in the numpy moments and in the log-likelihood."""
    from tobitkf.filters._compiled_moments import CENSORED, family_array, kind
    from tobitkf.filters._readings import LOWER, UPPER
    from tobitkf.filters.assumed_density import censored_reading_moments

    rng = np.random.default_rng(2)
    n = 200
    mu, s2 = rng.normal(0, 3, n), rng.uniform(0.05, 4.0, n)
    a = rng.normal(0, 3, n)
    a[:5] = mu[:5] + 40 * np.sqrt(s2[:5])  # far tails
    a[5:10] = mu[5:10] - 40 * np.sqrt(s2[5:10])
    f = np.ascontiguousarray
    inf = np.full(n, np.inf)

    def block(cls, lo, hi):
        return family_array(
            kind(CENSORED), f(a), f(np.full(n, cls, np.int8)), f(mu), f(s2 - 0.01), f(np.full(n, 0.01)), f(lo), f(hi),
            np.zeros(0), 0,
        )[:3]  # fmt: skip

    for got, want in zip(block(INTERVAL, a, inf), block(UPPER, -inf, a)):  # [a, inf) and "above a"
        np.testing.assert_array_equal(got, want)
    for got, want in zip(block(INTERVAL, -inf, a), block(LOWER, a, inf)):  # (-inf, a] and "below a"
        np.testing.assert_array_equal(got, want)
    sd = np.sqrt(s2)
    for cls, lo, hi, ref in ((INTERVAL, a, inf, (UPPER, -inf, a)), (INTERVAL, -inf, a, (LOWER, a, inf))):
        got = censored_reading_moments(a, mu, sd, lo, hi, np.full(n, cls, np.int8))[:2]
        want = censored_reading_moments(a, mu, sd, ref[1], ref[2], np.full(n, ref[0], np.int8))[:2]
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(
            censored_log_likelihood(a, mu, sd, lo, hi, classes=cls),
            censored_log_likelihood(a, mu, sd, ref[1], ref[2], classes=ref[0]),
        )


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


def test_a_flagged_reading_inside_needs_two_finite_limits():
    y = np.array([[0.5]])
    for lo, hi in ((-np.inf, np.inf), (0.0, np.inf), (-np.inf, 1.0)):  # a flag that contradicts the reading
        with pytest.raises(tk.ValidationError, match="two finite limits"):
            censoring_sides(y, lo, hi, [[True]], intervals=True)
        est = tk.AssumedDensityTobitFilter(_system(), tk.Censoring())
        with pytest.raises(tk.ValidationError, match="two finite limits"):
            est.filter(y, censored=[[True]], lower=lo, upper=hi)
    with pytest.raises(tk.ValidationError, match="strictly inside"):
        censoring_sides(y, 0.0, 1.0, [[True]])  # the estimators that take no interval readings refuse them


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


def test_fit_scores_interval_readings_by_their_mass():
    """tk.fit (a LinearSystem template, direct ML): the fitted log-likelihood is the assumed-density one with
    the interval readings as intervals (not as exact midpoints)."""
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
