"""WRTDS (tobitkf.wrtds) against first principles: EGRET's decimal years and tricube windows written out
by hand, the weighted censored likelihood maximised by brute force, leave-one-out against a refit done by
hand, and the predictive scores against scipy.stats."""

from __future__ import annotations

import datetime as dt
import doctest
import math

import numpy as np
import pytest
from scipy import optimize, stats

import tobitkf as tk
from tobitkf.data import load_arkansas
from tobitkf.inference import wrtds as W


@pytest.fixture(scope="module")
def rec():
    return load_arkansas()


def _egret_year(date: str) -> float:
    """EGRET's decimal year of a date without a time of day: noon of that day."""
    d = dt.date.fromisoformat(date)
    start, end = dt.date(d.year, 1, 1), dt.date(d.year + 1, 1, 1)
    return d.year + ((d - start).days + 0.5) / (end - start).days


def _tricube(d: float, h: float) -> float:
    u = abs(d) / h
    return (1.0 - u**3) ** 3 if u < 1.0 else 0.0


def _hand_weights(times, lnq, uncen, t0, lq0, period, wy, wq, ws, min_obs, min_unc, edge=True):
    """run_WRTDS's window loop, one sample at a time in plain Python."""
    dist = min(t0 - period[0], period[1] - t0)
    hy = wy if (not edge or dist > wy) else 2 * wy - dist
    hq, hs = wq, ws
    while True:
        w = []
        for t, q in zip(times, lnq):
            d = abs(t - t0)
            ds = min(math.ceil(d) - d, d - math.floor(d))
            w.append(_tricube(d, hy) * _tricube(q - lq0, hq) * _tricube(ds, hs) if d <= hy else 0.0)
        w = np.array(w)
        pos = w > 0
        used = (hy, hq, hs)
        hy, hq = hy * 1.1, hq * 1.1
        hs = min(hs * 1.1, 0.5) if ws <= 0.5 else ws
        if pos.sum() >= min_obs and (pos & uncen).sum() >= min_unc:
            return w, used


def test_decimal_year_is_egrets_noon_rule():
    got = W.decimal_year(np.array(["2001-01-01", "2000-12-31", "2012-09-25"], dtype="datetime64[D]"))
    np.testing.assert_allclose(
        got, [2001 + 0.5 / 365, 2000 + 365.5 / 366, _egret_year("2012-09-25")], rtol=0, atol=1e-12
    )
    # a time of day is kept: 06:00 on 1 January 2001
    assert W.decimal_year(np.array(["2001-01-01T06:00"], dtype="datetime64[m]"))[0] == pytest.approx(2001 + 0.25 / 365)
    np.testing.assert_array_equal(W.decimal_year([1990.5, 2001.25]), [1990.5, 2001.25])


def test_tricube_values():
    # (1 - (1/2)^3)^3 = (7/8)^3; zero at and beyond the half-window
    np.testing.assert_allclose(W.tricube([0.0, -1.0, 1.0, 2.0, 3.0], 2.0), [1.0, (7 / 8) ** 3, (7 / 8) ** 3, 0.0, 0.0])


def _explicit_loglik(params, X, lo, hi, w):
    """sum_i w_i l_i with scipy.stats, parameters (beta, log sigma)."""
    beta, s = params[:-1], math.exp(params[-1])
    m = X @ beta
    exact = lo == hi
    ll = np.empty(len(lo))
    ll[exact] = stats.norm.logpdf(hi[exact], m[exact], s)
    left = np.isneginf(lo) & ~exact
    ll[left] = stats.norm.logcdf(hi[left], m[left], s)
    right = np.isposinf(hi) & ~exact
    ll[right] = stats.norm.logsf(lo[right], m[right], s)
    mid = ~exact & ~left & ~right
    ll[mid] = np.log(stats.norm.cdf(hi[mid], m[mid], s) - stats.norm.cdf(lo[mid], m[mid], s))
    return float(np.sum(w * ll))


def _nelder_mead(X, lo, hi, w, start):
    x = np.asarray(start, dtype=float)
    f = lambda p: -_explicit_loglik(p, X, lo, hi, w)  # noqa: E731 - a one-line objective
    for _ in range(8):  # restarts until the simplex stops moving
        res = optimize.minimize(
            f, x, method="Nelder-Mead", options={"xatol": 1e-11, "fatol": 1e-13, "maxiter": 40000, "maxfev": 80000}
        )
        if np.max(np.abs(res.x - x)) < 1e-10:
            break
        x = res.x
    return res.x


def test_one_estimation_point_matches_a_hand_computed_weighted_tobit_fit(rec):
    """EGRET's settings for this record at one sample's time and discharge (the windows widen): the weights
    by the tricube formulas, the fit by Nelder-Mead on the explicit weighted log-likelihood."""
    dates = [str(d) for d in rec.date]
    times = np.array([_egret_year(d) for d in dates])
    lnq = np.log(rec.q)
    uncen = rec.uncensored
    period = (_egret_year(str(rec.daily_date[0])), _egret_year(str(rec.daily_date[-1])))
    i0 = 120
    t0, lq0 = times[i0], lnq[i0]
    w, used = _hand_weights(times, lnq, uncen, t0, lq0, period, 7.0, 1.0, 0.5, 100, 127)
    w = w / w[w > 0].mean()

    model = W.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high, period=rec.period, window_q=1.0, min_num_uncen=127)
    est = model.estimate(rec.date[i0 : i0 + 1], rec.q[i0 : i0 + 1])
    np.testing.assert_allclose(est.windows.weights[0], w, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(est.windows.half_windows[0], used, rtol=1e-12)
    assert est.windows.widenings[0] > 0  # the point tests the widening too

    lo = np.where(uncen, np.log(rec.conc_low), -np.inf)
    hi = np.log(rec.conc_high)
    keep = w > 0
    # regressors centred on the record's means (conditioning for the brute-force search)
    X = np.column_stack([np.ones_like(times), times, lnq, np.sin(2 * np.pi * times), np.cos(2 * np.pi * times)])
    centre = X[keep].mean(axis=0)
    centre[0] = 0.0
    Xc = X - centre
    ols = np.linalg.lstsq(Xc[keep], hi[keep], rcond=None)[0]
    p = _nelder_mead(Xc[keep], lo[keep], hi[keep], w[keep], np.r_[ols, math.log(0.7)])
    beta = p[:-1].copy()
    beta[0] -= centre @ beta  # back to EGRET's raw regressors
    x0 = np.array([1.0, t0, lq0, math.sin(2 * math.pi * t0), math.cos(2 * math.pi * t0)])
    np.testing.assert_allclose(est.coef[0, 1:], beta[1:], rtol=0, atol=1e-6)
    assert est.sd[0] == pytest.approx(math.exp(p[-1]), abs=1e-6)
    assert est.mean[0] == pytest.approx(x0 @ beta, abs=1e-6)
    assert est.conc[0] == pytest.approx(math.exp(x0 @ beta + math.exp(p[-1]) ** 2 / 2), rel=1e-6)
    assert est.converged[0]


def test_weighted_tobit_handles_every_kind_of_bound():
    """Measured, left-, right- and interval-censored samples, random weights: Newton equals brute force."""
    rng = np.random.default_rng(3)
    n = 80
    X = np.column_stack([np.ones(n), rng.normal(size=n), rng.normal(size=n)])
    y = X @ [0.5, 1.0, -0.7] + 0.8 * rng.normal(size=n)
    lo, hi = y.copy(), y.copy()
    kind = rng.integers(0, 4, size=n)
    lo[kind == 1], hi[kind == 1] = -np.inf, np.maximum(y[kind == 1], 0.3)  # below a limit
    lo[kind == 2], hi[kind == 2] = np.minimum(y[kind == 2], 1.0), np.inf  # above a limit
    lo[kind == 3], hi[kind == 3] = np.floor(y[kind == 3]), np.floor(y[kind == 3]) + 1  # an interval
    w = rng.uniform(0.0, 2.0, size=n)
    w[:5] = 0.0
    beta, sigma, ll, conv = W.fit_weighted_tobit(X[None], lo, hi, w[None])
    p = _nelder_mead(X, lo, hi, w, np.r_[0.0, 0.0, 0.0, 0.0])
    assert conv[0]
    np.testing.assert_allclose(beta[0], p[:-1], atol=1e-6)
    assert sigma[0] == pytest.approx(math.exp(p[-1]), abs=1e-6)
    assert ll[0] == pytest.approx(_explicit_loglik(p, X, lo, hi, w), abs=1e-9)


def test_windows_widen_until_the_minimum_counts_and_no_further(rec):
    model = W.WRTDS(
        rec.date, rec.q, rec.conc_low, rec.conc_high, window_y=1.0, window_q=0.3, window_s=0.2, edge_adjust=False
    )
    t = W.decimal_year(rec.date)
    win = model.windows(t[::25], np.log(rec.q[::25]))
    assert np.all(win.num_obs >= 100) and np.all(win.num_uncen >= 50)
    assert np.all(win.widenings > 0)
    np.testing.assert_array_equal((win.weights > 0).sum(axis=1), win.num_obs)
    np.testing.assert_allclose(win.weights.sum(axis=1), win.num_obs)  # normalised to mean 1
    for p in range(t[::25].size):
        k = win.widenings[p]
        # k widenings by 10 % (the season window capped at half a year)
        np.testing.assert_allclose(win.half_windows[p], [1.0 * 1.1**k, 0.3 * 1.1**k, min(0.2 * 1.1**k, 0.5)])
        # one step narrower the counts are not met
        prev = (1.0 * 1.1 ** (k - 1), 0.3 * 1.1 ** (k - 1), min(0.2 * 1.1 ** (k - 1), 0.5))
        d = np.abs(t - t[::25][p])
        ds = np.minimum(np.ceil(d) - d, d - np.floor(d))
        w = W.tricube(d, prev[0]) * W.tricube(np.log(rec.q) - np.log(rec.q[::25][p]), prev[1]) * W.tricube(ds, prev[2])
        assert (w > 0).sum() < 100 or ((w > 0) & rec.uncensored).sum() < 50


def test_edge_adjustment_widens_the_time_window_near_the_ends(rec):
    model = W.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high, period=rec.period, min_num_obs=10, min_num_uncen=5)
    lo, hi = model.period
    win = model.windows(np.array([lo + 1.0, 0.5 * (lo + hi)]), np.log([5000.0, 5000.0]))
    assert win.half_windows[0, 0] == pytest.approx(2 * 7.0 - 1.0)
    assert win.half_windows[1, 0] == pytest.approx(7.0)
    flat = W.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high, edge_adjust=False, min_num_obs=10, min_num_uncen=5)
    assert flat.windows(np.array([lo + 1.0]), np.log([5000.0])).half_windows[0, 0] == pytest.approx(7.0)


@pytest.mark.parametrize("i", [0, 7, 130, 253])
def test_leave_one_out_equals_a_fit_without_the_sample(rec, i):
    settings = W.settings_from_egret(rec.egret_info)
    assert settings == {
        "window_y": 7.0,
        "window_q": 1.0,
        "window_s": 0.5,
        "min_num_obs": 100,
        "min_num_uncen": 127,
        "edge_adjust": True,
    }
    model = W.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high, period=rec.period, **settings)
    cv = model.cross_validate()
    keep = np.arange(rec.num_samples) != i
    alone = W.WRTDS(
        rec.date[keep], rec.q[keep], rec.conc_low[keep], rec.conc_high[keep], period=rec.period, **settings
    ).estimate(rec.date[i : i + 1], rec.q[i : i + 1])
    assert cv.mean[i] == pytest.approx(alone.mean[0], abs=1e-9)
    assert cv.sd[i] == pytest.approx(alone.sd[0], abs=1e-9)
    assert cv.windows.num_obs[i] == alone.windows.num_obs[0]
    assert cv.converged.all()


def test_arkansas_leave_one_out_scores_match_an_independent_implementation(rec):
    """An earlier, separate implementation of WRTDS with EGRET's settings for this record measured a mean
    log predictive score of -0.871 and an RMSE of the uncensored ln values of 0.704 (three decimals)."""
    model = W.WRTDS(
        rec.date, rec.q, rec.conc_low, rec.conc_high, period=rec.period, **W.settings_from_egret(rec.egret_info)
    )
    cv = model.cross_validate()
    s = W.predictive_scores(
        cv.mean, cv.sd, np.where(rec.uncensored, np.log(rec.conc_low), -np.inf), np.log(rec.conc_high)
    )
    assert s.mean_log_score == pytest.approx(-0.871, abs=5e-4)
    assert s.rmse == pytest.approx(0.704, abs=5e-4)
    assert s.num_uncensored == 139


def test_predictive_scores_against_scipy():
    mean = np.array([0.0, 1.0, -1.0, 0.5])
    sd = np.array([1.0, 0.5, 2.0, 0.3])
    low = np.array([0.3, -np.inf, 0.2, 0.0])
    high = np.array([0.3, 0.8, np.inf, 1.0])
    s = W.predictive_scores(mean, sd, low, high)
    want = [
        stats.norm.logpdf(0.3, 0.0, 1.0),
        stats.norm.logcdf(0.8, 1.0, 0.5),
        stats.norm.logsf(0.2, -1.0, 2.0),
        math.log(stats.norm.cdf(1.0, 0.5, 0.3) - stats.norm.cdf(0.0, 0.5, 0.3)),
    ]
    np.testing.assert_allclose(s.log_score, want, rtol=1e-12)
    assert s.mean_log_score == pytest.approx(np.mean(want))
    assert s.se_mean_log_score == pytest.approx(np.std(want, ddof=1) / 2)
    assert s.rmse == pytest.approx(0.3) and s.num_uncensored == 1
    # far in the tail the censored score stays finite and exact
    far = W.predictive_scores([0.0], [1.0], [-np.inf], [-40.0])
    assert far.log_score[0] == pytest.approx(stats.norm.logcdf(-40.0), rel=1e-12)


def test_errors_name_the_argument(rec):
    args = (rec.date, rec.q, rec.conc_low, rec.conc_high)
    with pytest.raises(tk.ValidationError, match="min_num_uncen"):
        W.WRTDS(*args, min_num_uncen=139)
    with pytest.raises(tk.ValidationError, match="min_num_obs"):
        W.WRTDS(*args, min_num_obs=254)
    with pytest.raises(tk.ValidationError, match="q: expected positive"):
        W.WRTDS(rec.date, -rec.q, rec.conc_low, rec.conc_high)
    bad = rec.conc_low.copy()
    bad[2] = 10.0
    with pytest.raises(tk.ValidationError, match="sample 2"):
        W.WRTDS(rec.date, rec.q, bad, rec.conc_high)
    zero = rec.conc_high.copy()
    zero[5] = 0.0
    with pytest.raises(tk.ValidationError, match="conc_high: expected a positive concentration.*sample 5"):
        W.WRTDS(rec.date, rec.q, rec.conc_low, zero)
    with pytest.raises(tk.ShapeError, match="conc_high"):
        W.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high[:-1])
    with pytest.raises(tk.ValidationError, match="window_q"):
        W.WRTDS(*args, window_q=0.0)
    # leaving one sample out: 127 of the 139 uncensored samples are needed, 138 remain; 138 would not do
    with pytest.raises(tk.ValidationError, match="without one sample"):
        W.WRTDS(*args, min_num_uncen=138).cross_validate()


def test_public_names_and_docstring_examples():
    assert tk.wrtds is W and tk.inference.wrtds is W
    res = doctest.testmod(W, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0 and res.attempted > 0


def test_egret_interval_columns_become_log_bounds(rec):
    low, high = rec.conc_low.copy(), rec.conc_high.copy()
    low[3], high[3] = 0.02, np.nan  # above 0.02: right-censored
    low[4], high[4] = 0.01, 0.04  # an interval
    low[5] = 0.0  # a zero ConcLow is no lower bound, as EGRET reads it
    m = W.WRTDS(rec.date, rec.q, low, high)
    assert m.ln_low[3] == pytest.approx(math.log(0.02)) and m.ln_high[3] == np.inf
    assert (m.ln_low[4], m.ln_high[4]) == pytest.approx((math.log(0.01), math.log(0.04)))
    assert m.ln_low[5] == -np.inf and m.ln_high[5] == pytest.approx(math.log(rec.conc_high[5]))
    assert rec.uncensored[3:6].all() and not m.uncensored[3:6].any()
    assert m.uncensored.sum() == rec.uncensored.sum() - 3
    assert m.estimate(rec.date[:3], rec.q[:3]).converged.all()
