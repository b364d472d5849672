"""Panels of short irregular series on one continuous-time model: padding changes nothing (each subject's
likelihood, smoother and forecast equal its own series'), and a joint fit recovers simulated parameters."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.inference.panel import panel_forecast, panel_log_likelihood, panel_smooth

R = 0.3**2


def _ou(th):
    """OU level around a mean mu (the input D u with u = 1): theta = (log rate, log stationary sd, mu)."""
    rate, sd, mu = np.exp(th[0]), np.exp(th[1]), th[2]
    return tk.ContinuousLinearSystem([[-rate]], [[2 * rate * sd**2]], [[1.0]], [[R]], [0.0], [[sd**2]], D=[[mu]])


def _simulate(N, seed, th, upper=3.8):
    rate, sd, mu = np.exp(th[0]), np.exp(th[1]), th[2]
    rng = np.random.default_rng(seed)
    times, ys, los, his = [], [], [], []
    for i in range(N):
        n = int(rng.integers(3, 9))
        t = np.concatenate([[0.0], np.cumsum(rng.integers(1, 15, size=n - 1))]).astype(float) + rng.integers(0, 5)
        x = np.empty(n)
        x[0] = rng.normal(0, sd)
        for k in range(1, n):  # the exact OU transition, written out (independent of the Van Loan code)
            a = np.exp(-rate * (t[k] - t[k - 1]))
            x[k] = a * x[k - 1] + np.sqrt(sd**2 * (1 - a * a)) * rng.normal()
        lo = 1.0 if i % 2 else 1.3  # two assay limits below, one above
        hi = np.full(n, upper)
        y = np.clip(mu + x + rng.normal(0, np.sqrt(R), n), lo, hi)
        times.append(t), ys.append(y), los.append(np.full(n, lo)), his.append(hi)
    return times, ys, los, his


TRUE = np.array([np.log(0.1), 0.0, 2.0])


def test_padding_changes_nothing_for_each_subject():
    times, ys, los, his = _simulate(6, 1, TRUE, upper=2.6)
    ys[2] = ys[2].copy()
    ys[2][1] = np.nan  # a missing reading of its own
    us = [np.ones((len(t), 1)) for t in times]
    panel = tk.Panel(times, ys, lower=los, upper=his, u=us)
    assert (np.concatenate([y[np.isfinite(y)] for y in ys]) == 2.6).any()  # right-censored readings present
    assert np.isin(np.concatenate(ys), [1.0, 1.3]).any()  # and left-censored ones
    sys_ = _ou(TRUE)
    per = panel_log_likelihood(sys_, panel, per_subject=True)
    sm = panel_smooth(sys_, panel)
    fc = panel_forecast(sys_, panel, 2.5, u=[1.0])
    for i, (t, y, lo, hi, u) in enumerate(zip(times, ys, los, his, us)):
        cens = tk.Censoring(lower=lo[:, None], upper=hi[:, None])
        adf = tk.AssumedDensityTobitFilter(sys_, cens, order="uncensored_first")
        own = adf.log_likelihood(y[:, None], u=u, times=t)
        assert np.isclose(per[i], own, rtol=0, atol=1e-10)
        s = adf.smooth(y[:, None], u=u, times=t)
        assert np.allclose(sm[i]["mean"], s.mean, rtol=0, atol=1e-10)
        assert np.allclose(sm[i]["cov"], s.cov, rtol=0, atol=1e-10)
        # the forecast is the filter's prediction at a missing reading 2.5 time units later
        cens2 = tk.Censoring(lower=np.append(lo, -np.inf)[:, None], upper=np.append(hi, np.inf)[:, None])
        f = tk.AssumedDensityTobitFilter(sys_, cens2, order="uncensored_first").filter(
            np.append(y, np.nan)[:, None], u=np.ones((len(t) + 1, 1)), times=np.append(t, t[-1] + 2.5)
        )
        assert np.allclose(fc["mean"][i], f.mean[-1], rtol=0, atol=1e-10)
        assert np.allclose(fc["cov"][i], f.cov[-1], rtol=0, atol=1e-10)
    # the state on a grid (days since each first visit) = each series' own grid smoother
    grid = np.arange(0.0, 120.0)  # whole days: every visit is a grid day
    smg = panel_smooth(sys_, panel, grid=grid)
    for i, (t, y, lo, hi, u) in enumerate(zip(times, ys, los, his, us)):
        cens = tk.Censoring(lower=lo[:, None], upper=hi[:, None])
        adf = tk.AssumedDensityTobitFilter(sys_, cens, order="uncensored_first")
        own_g = adf.smooth(y[:, None], times=t - t[0], grid=grid, u=np.ones((grid.size, 1)))
        assert np.allclose(smg[i]["grid_mean"], own_g.mean, rtol=0, atol=1e-10)
        assert np.allclose(smg[i]["grid_cov"], own_g.cov, rtol=0, atol=1e-10)
        assert np.allclose(smg[i]["mean"], sm[i]["mean"], rtol=0, atol=1e-10)
    # a panel of one subject is the plain series; tk.fit's times= route builds exactly that panel
    one = tk.Panel([times[0]], [ys[0]], lower=[los[0]], upper=[his[0]], u=[us[0]])
    assert np.isclose(panel_log_likelihood(sys_, one), per[0], rtol=0, atol=1e-12)
    # without limits: the exact Kalman likelihood of each series
    free = tk.Panel(times, ys, u=us)
    per_k = panel_log_likelihood(sys_, free, per_subject=True)
    for i, (t, y, u) in enumerate(zip(times, ys, us)):
        assert np.isclose(per_k[i], tk.kalman_log_likelihood(sys_, y[:, None], u=u, times=t), rtol=0, atol=1e-10)


def test_align_common_puts_every_prior_at_the_panel_start():
    times, ys, los, his = _simulate(3, 2, TRUE)
    us = [np.ones((len(t), 1)) for t in times]
    panel = tk.Panel(times, ys, lower=los, upper=his, u=us)
    sys_ = _ou(TRUE)
    per = panel_log_likelihood(sys_, panel, align="common", start=-1.0, per_subject=True)
    for i, (t, y, lo, hi, u) in enumerate(zip(times, ys, los, his, us)):
        cens = tk.Censoring(lower=lo[:, None], upper=hi[:, None])
        adf = tk.AssumedDensityTobitFilter(sys_.at_times(t, start=-1.0), cens, order="uncensored_first")
        assert np.isclose(per[i], adf.log_likelihood(y[:, None], u=u), rtol=0, atol=1e-10)


def test_from_long_and_refusals():
    times, ys, los, his = _simulate(3, 3, TRUE)
    sub = np.concatenate([[f"s{i}"] * len(t) for i, t in enumerate(times)])
    long = tk.Panel.from_long(sub, np.concatenate(times), np.concatenate(ys), lower=np.concatenate(los), upper=3.8)
    wide = tk.Panel(times, ys, lower=los, upper=3.8)
    sys_ = tk.ContinuousLinearSystem([[-0.1]], [[0.2]], [[1.0]], [[R]], [2.0], [[1.0]])
    assert long.ids == ["s0", "s1", "s2"]
    assert np.isclose(panel_log_likelihood(sys_, long), panel_log_likelihood(sys_, wide), rtol=0, atol=1e-12)
    with pytest.raises(tk.ValidationError, match=r"times\[1\].*duplicate"):
        tk.Panel([[0.0, 1.0], [0.0, 2.0, 2.0]], [[1.0, 2.0], [1.0, 2.0, 3.0]])
    with pytest.raises(tk.ValidationError, match=r"y\[0\].*outside"):
        tk.Panel([[0.0, 1.0]], [[0.5, 2.0]], lower=1.0)
    with pytest.raises(tk.ShapeError, match="one per reading"):
        tk.Panel([[0.0, 1.0]], [[1.0, 2.0, 3.0]])
    with pytest.raises(tk.ValidationError, match="continuous time"):
        panel_log_likelihood(tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]]), wide)


@pytest.mark.heavy  # a Monte Carlo recovery (tens of seconds on a loaded machine): run with -m heavy
def test_the_panel_fit_recovers_simulated_parameters():
    times, ys, los, his = _simulate(50, 11, TRUE)
    us = [np.ones((len(t), 1)) for t in times]
    panel = tk.Panel(times, ys, lower=los, upper=his, u=us)
    frac = np.mean(np.isin(np.concatenate(ys), [1.0, 1.3, 3.8]))
    assert 0.1 < frac < 0.4  # left- and right-censoring both matter here
    res = tk.fit(_ou, panel, theta0=[np.log(0.3), np.log(0.7), 1.5], names=["log_rate", "log_sd", "mu"])
    assert res.converged and res.likelihood == "adf" and res.n_obs == sum(len(t) for t in times)
    se = np.sqrt(np.diagonal(res.cov))
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    # one simulated panel: each estimate within 3 standard errors of the truth (about 1 % chance per parameter
    # of a false failure under the model; the seed is fixed)
    assert np.all(np.abs(res.theta - TRUE) <= 3 * se), (res.theta, TRUE, se)
    sm = res.smooth()
    assert len(sm) == 50 and sm[0]["mean"].shape == (len(times[0]), 1)
    fc = res.forecast(3, X=[1.0])
    assert fc["mean"].shape == (50, 3, 1) and np.all(np.diff(fc["sd"], axis=1) > 0)


def test_fit_with_times_is_the_panel_of_one_series(tmp_path):
    times, ys, los, his = _simulate(1, 5, TRUE, upper=2.6)
    t, y, u = times[0], ys[0], np.ones((len(times[0]), 1))
    res = tk.fit(_ou, y, times=t, u=u, lower=los[0], upper=his[0], theta0=TRUE, maxiter=2, standard_errors=False)
    cens = tk.Censoring(lower=los[0][:, None], upper=his[0][:, None])
    own = tk.AssumedDensityTobitFilter(_ou(res.theta), cens, order="uncensored_first").log_likelihood(
        y[:, None], u=u, times=t
    )
    assert np.isclose(res.loglik, own, rtol=0, atol=1e-10) and res.n_obs == len(t)
    back = tk.load_fit(res.save(tmp_path / "fit.json"), data=res.data)  # saved and read back
    assert np.array_equal(back.theta, res.theta) and np.allclose(back.model.fitted.Ac, res.model.fitted.Ac)
    assert np.allclose(back.smooth()[0]["mean"], res.smooth()[0]["mean"], rtol=0, atol=1e-12)
    panel = tk.Panel(times, ys)
    with pytest.raises(tk.ValidationError, match="carries its own"):
        tk.fit(_ou, panel, times=t, theta0=TRUE)
    with pytest.raises(tk.ValidationError, match="ContinuousLinearSystem"):
        tk.fit(
            lambda th: tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]]),
            panel,
            theta0=[0.0],
        )
