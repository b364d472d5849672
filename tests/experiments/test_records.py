"""The record experiments (tobitkf.experiments.records): the per-gap filter against the package's filter on the
daily grid, the batched leave-one-out refits against one-by-one refits, the panel likelihood against the
per-patient likelihoods, and reduced runs of the three experiments."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.data import load_arkansas, load_hiv_viral_load
from tobitkf.experiments import get
from tobitkf.experiments._claims import check_claims
from tobitkf.experiments.records import (
    ARKANSAS_MODEL,
    STATIC_MODEL,
    PanelModel,
    RiverModel,
    batched_loo_refit,
    fit_ml,
    last_visit_predictions,
    run_arkansas,
)

DAYS = 8 * 365  # a reduced record: the first eight years of the daily grid (79 samples)


@pytest.fixture(scope="module")
def short_model():
    """The Arkansas model on the first eight years (its samples and its daily rows)."""
    # a smaller model than the experiment's: on eight years of samples its intercept drift stays identified
    full = RiverModel.from_record(load_arkansas(), drift=("intercept",), flow_variance=True)
    keep = full.day < DAYS
    return RiverModel(
        day=full.day[keep],
        y=full.y[keep],
        censored=full.censored[keep],
        rows=full.rows[:DAYS],
        coef=full.coef,  # the rows already hold the added regressors (square, harmonics, flow anomaly)
        drift=full.drift,
        flow_variance=full.flow_variance,
    )


def _theta(m):
    """A parameter vector away from any optimum, every component active."""
    th = m.start()
    th[m.names.index("log_tau_days")] = np.log(40.0)
    th[m.names.index("gamma_flow")] = -0.2
    return th


def test_sample_grid_filter_equals_the_adf_on_the_daily_grid(short_model):
    """Each gap taken in one exact step equals the package's ADF over every day, readings NaN between samples."""
    m = short_model
    th = _theta(m)
    sys_, y, cens, ind = m.daily_system(th)
    ll_daily = tk.adf_log_likelihood(sys_, cens, y, censored=ind, per_step=True)
    out = m.run(th[None])
    np.testing.assert_allclose(out["terms"][0], ll_daily[m.day], rtol=1e-10, atol=1e-12)
    assert np.all(np.delete(ll_daily, m.day) == 0.0)
    assert m.censored.any() and (~m.censored).any()


def test_daily_smoother_equals_tk_smooth_on_the_daily_grid(short_model):
    m = short_model
    th = _theta(m)
    sys_, y, cens, ind = m.daily_system(th)
    ref = tk.smooth(sys_, y, censoring=cens, censored=ind)
    got = m.daily_smooth(th)
    np.testing.assert_allclose(got["mean"], ref.mean, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(got["cov"], ref.cov, rtol=1e-9, atol=1e-12)
    # the sample-grid smoother's predictive of each sample: the daily smoother's at its day, plus the noise
    sm = m.run(th[None], smooth=True)
    np.testing.assert_allclose(sm["mean"][0], got["ln_mean"][m.day], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(sm["sd"][0] ** 2, got["ln_sd"][m.day] ** 2 + got["noise_sd"][m.day] ** 2, rtol=1e-9)


def test_batched_leave_one_out_equals_one_by_one_refits(short_model):
    """Two samples (one censored, one measured): the batched quasi-Newton refit against scipy's BFGS on the
    record without the sample, both from the full fit."""
    m = short_model
    fit = fit_ml(m)
    cens_i = int(np.flatnonzero(m.censored)[0])
    meas_i = int(np.flatnonzero(~m.censored)[1])
    samples = np.array([cens_i, meas_i])
    gtol = 1e-5
    loo = batched_loo_refit(m, fit["theta"], fit["cov"], samples, gtol=gtol)
    assert loo["converged"].all() and loo["gradient_max"].max() < gtol
    for j, i in enumerate(samples):
        y = m.y.copy()
        y[i] = np.nan
        mi = RiverModel(
            day=m.day,
            y=y,
            censored=m.censored & (np.arange(m.n_samples) != i),
            rows=m.rows,
            coef=m.coef,
            drift=m.drift,
            flow_variance=m.flow_variance,
        )
        ref = fit_ml(mi, start=fit["theta"], gtol=1e-7)
        # both stop near a zero of the gradient: the distance is bounded by |H^-1| (|g1| + |g2|) sqrt(p)
        Hinv = np.linalg.norm(ref["cov"], 2)
        tol = Hinv * 2 * gtol * np.sqrt(m.p)
        assert np.max(np.abs(loo["theta"][j] - ref["theta"])) < tol
        assert loo["loglik"][j] == pytest.approx(ref["loglik"], abs=1e-7)
        sm = mi.run(ref["theta"][None], smooth=True)
        assert loo["mean"][j] == pytest.approx(sm["mean"][0, i], abs=1e-3)
        assert loo["sd"][j] == pytest.approx(sm["sd"][0, i], abs=1e-3)
        # the removed sample moved the fit (a refit that did nothing would equal the full fit)
        assert np.max(np.abs(ref["theta"] - fit["theta"])) > 10 * tol


@pytest.mark.parametrize("options", [{}, {"trend": True, "rebound": True}])
def test_panel_likelihood_is_the_sum_of_the_patients_likelihoods(options):
    """The batched panel pass against the package's ADF likelihood of each patient on its own, with per-gap
    (T, n, n) transition and noise matrices, the mean course through D u (the on-treatment shift, or the
    rebound e^(-t/T_r) and the yearly trend) and limits per visit on both sides."""
    model, _ = PanelModel.from_panel(load_hiv_viral_load(), setpoint=True, **options)
    th = np.array([4.2, -0.5, np.log(0.4), np.log(200.0), np.log(0.8), np.log(0.3)])
    if options:
        th = np.r_[th, 0.3, np.log(40.0)]
    out = model.run(th[None])
    nat = model.natural(th)
    checked = 0
    for i in range(model.subjects):
        ok = np.isfinite(model.y[i])
        T = int(ok.sum())
        gaps = model.gaps[i, :T]
        phi = np.exp(-gaps / nat["T"])
        A = np.zeros((T, 2, 2))
        A[:, 0, 0], A[:, 1, 1] = 1.0, phi
        Q = np.zeros((T, 2, 2))
        Q[:, 1, 1] = nat["sigma"] ** 2 * (1 - phi**2)
        t = model.day[i, :T]
        if options:  # the rebound from the on-treatment level and the trend, by hand
            u = np.column_stack([np.where(t <= 0, 1.0, np.exp(-t / 40.0)), np.maximum(t, 0) / 365.25])
            D = [[nat["delta"], 0.3]]
        else:
            u = (t <= 0).astype(float)[:, None]
            D = [[nat["delta"]]]
        # the package's A_k takes x_k to x_{k+1}: A[j] spans the gap before visit j + 1 (the first visit's
        # gap is 0: A = I, Q = 0, so x_1 = x_0, the patient's prior at the first visit)
        sys_ = tk.LinearSystem(
            A=A,
            C=np.ones((1, 2)),
            Q=Q,
            R=[[nat["r"] ** 2]],
            x0=[nat["mu"], 0.0],
            P0=np.diag([nat["tau_s"] ** 2, nat["sigma"] ** 2]),
            D=D,
        )
        lo = model.lower[i, :T][:, None]
        hi = model.upper[i, :T][:, None]
        ll = tk.adf_log_likelihood(
            sys_,
            tk.Censoring(lower=lo, upper=hi),
            model.y[i, :T][:, None],
            censored=(np.isfinite(lo) | np.isfinite(hi)),
            u=u,
        )
        assert out["per_subject"][0, i] == pytest.approx(float(ll), rel=1e-10, abs=1e-10)
        checked += 1
    assert checked == 72
    assert out["loglik"][0] == pytest.approx(out["per_subject"][0].sum(), rel=1e-12)
    assert np.isfinite(model.lower).sum() > 0 and np.isfinite(model.upper).sum() > 0  # both sides censored


def test_last_visit_baselines_are_what_they_say():
    panel = load_hiv_viral_load()
    lv = last_visit_predictions(panel)
    model, info = PanelModel.from_panel(panel, drop_last=True)
    who = np.flatnonzero(info["last"] >= 0)
    assert len(lv["patients"]) == who.size == np.sum(np.isfinite(model.y).sum(axis=1) >= 2)
    prev = model.y[who, info["last"][who] - 1]
    np.testing.assert_array_equal(lv["lvcf"]["mean"], prev)  # the previous reading as recorded
    assert np.unique(lv["lvcf"]["sd"]).size == 1 and np.unique(lv["half_limit"]["sd"]).size == 1
    # a patient whose earlier visits include one below the limit: its mean uses half that limit
    for j, i in enumerate(who):
        earlier = slice(0, info["last"][i])
        low = np.isfinite(model.lower[i, earlier])
        if low.any():
            vals = np.where(low, model.y[i, earlier] - np.log10(2), model.y[i, earlier])
            assert lv["half_limit"]["mean"][j] == pytest.approx(vals.mean())
            break
    else:
        pytest.fail("no patient with a censored earlier visit")


def test_arkansas_reduced_run_has_the_loo_fields():
    """Leave-one-out on 10 samples: the metrics the report and users read."""
    idx = np.arange(0, 254, 26)[:10]
    small = {"drift": ("intercept",), "flow_variance": True}  # identified without a nested start
    metrics, data = run_arkansas(loo_samples=idx, candidates=(STATIC_MODEL, small))
    loo = metrics["loo"]
    for k in ("wrtds", "state_space"):
        e = loo[k]
        assert len(e["date"]) == len(e["mean"]) == len(e["sd"]) == 10
        assert e["date"][0] == str(load_arkansas().date[idx[0]])
        assert np.all(np.array(e["sd"]) > 0)
        assert np.isfinite(e["mean_log_score"]) and np.isfinite(e["rmse_uncensored"])
        assert e["mean_log_score"] == pytest.approx(np.mean(e["log_score"]))
    d = loo["difference_state_space_minus_wrtds"]
    assert d["mean_log_score"] == pytest.approx(loo["state_space"]["mean_log_score"] - loo["wrtds"]["mean_log_score"])
    assert d["se"] > 0
    per_sample = np.array(loo["state_space"]["log_score"]) - np.array(loo["wrtds"]["log_score"])
    worst = d["largest_wrtds_advantage"]
    np.testing.assert_allclose([w["difference"] for w in worst], np.sort(per_sample)[:3], rtol=1e-12)
    assert worst[0]["date"] == loo["wrtds"]["date"][int(np.argmin(per_sample))]
    assert loo["state_space"]["refits_converged"] == 10
    # the model is the candidate of smallest AIC, and the table scores every candidate against WRTDS
    table = metrics["models_compared"]
    assert len(table) == 2
    aic = [r["aic"] for r in table]
    assert metrics["model"]["options"] == table[int(np.argmin(aic))]["options"]
    for r in table:
        assert r["aic"] == pytest.approx(-2 * r["loglik"] + 2 * r["n_params"])
        assert r["bic"] == pytest.approx(-2 * r["loglik"] + np.log(254) * r["n_params"])
        assert r["minus_wrtds"] == pytest.approx(r["loo_mean_log_score"] - loo["wrtds"]["mean_log_score"])
    assert table[0]["loo_mean_log_score"] == pytest.approx(loo["static_ar1"]["mean_log_score"])
    fit = metrics["model"]["fit"]
    assert fit["converged"] and fit["hessian_negative_definite"]
    assert all(np.isfinite(v) and v > 0 for v in fit["se"].values())
    # flux = concentration x Q x the unit factor
    np.testing.assert_allclose(data["flux"], data["conc"] * load_arkansas().daily_q * 2.446576, rtol=1e-6)


@pytest.mark.parametrize("exp_id", ["data-hiv", "data-niagara"])
def test_small_record_experiments_follow_the_claims_rule(exp_id, tmp_path):
    e = get(exp_id)
    r = e.run(runs=1, seed=0)
    check_claims(r.claims, exp_id)
    assert r.metrics["model"]["fit"]["converged"]
    paths = e.plot(r, tmp_path)
    assert all(p.exists() for p in paths)
    assert set(r.metrics["figure_captions"]) == {p.name for p in paths}


@pytest.mark.heavy
def test_arkansas_full_run(tmp_path):
    e = get("data-arkansas")
    r = e.run(runs=1, seed=0)
    loo = r.metrics["loo"]
    assert loo["samples"] == 254 and loo["state_space"]["refits_converged"] == 254
    # the static AR(1) regression reproduces the measured tie with WRTDS (-0.888 against -0.871)
    assert loo["wrtds"]["mean_log_score"] == pytest.approx(-0.871, abs=0.001)
    assert loo["static_ar1"]["mean_log_score"] == pytest.approx(-0.888, abs=0.002)
    paths = e.plot(r, tmp_path)
    assert len(paths) == 2


def test_finite_differences_are_exact_on_a_quadratic():
    """Central differences are exact for a quadratic: the gradient and the Hessian of one batched call each."""
    from tobitkf.experiments.records import fd_gradient, fd_hessian

    rng = np.random.default_rng(1)
    M = rng.normal(size=(4, 4))
    A = M @ M.T + np.eye(4)
    b = rng.normal(size=4)
    calls = []

    def f(pts, rep=None):
        calls.append(len(pts))
        return -0.5 * np.einsum("ni,ij,nj->n", pts, A, pts) + pts @ b

    th = rng.normal(size=(3, 4))
    val, g = fd_gradient(f, th, h=1e-3)
    np.testing.assert_allclose(val, f(th))
    np.testing.assert_allclose(g, -th @ A + b, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(fd_hessian(f, th[0], h=1e-2), -A, rtol=1e-7, atol=1e-7)
    assert calls[0] == 3 * 9 and calls[-1] == 2 * 4 * 5


def test_gap_matrices_compose_and_reduce_to_a_random_walk():
    """A gap of 2 d is two steps of d (a(2d) = a(d)^2, q(2d) = a(d)^2 q(d) + q(d)); rate 0 is a random walk
    (q d); the stationary variance of an OU state is q / (2 rate)."""
    from tobitkf.experiments.records_common import gap_matrices

    rate = np.array([[0.0, 0.03, 2.0]])
    diff = np.array([[0.5, 0.2, 1.5]])
    a1, q1 = gap_matrices(rate, diff, np.array([7.0]))
    a2, q2 = gap_matrices(rate, diff, np.array([14.0]))
    np.testing.assert_allclose(a2, a1**2, rtol=1e-14)
    np.testing.assert_allclose(q2, a1**2 * q1 + q1, rtol=1e-13)
    assert a1[0, 0, 0] == 1.0 and q1[0, 0, 0] == pytest.approx(0.5 * 7.0, rel=1e-15)
    _, q_far = gap_matrices(rate, diff, np.array([1e4]))
    assert q_far[0, 0, 2] == pytest.approx(1.5 / 4.0, rel=1e-14)


def test_batched_parameter_vectors_equal_each_on_the_daily_grid(short_model):
    """The batch of parameter vectors (one model per run through the package's ADF, compiled loop) against each
    vector's model on the daily grid, run alone with one shared system (readings NaN between samples)."""
    m = short_model
    rng = np.random.default_rng(3)
    th = _theta(m)[None] + rng.normal(0, 0.3, (4, m.p))
    terms = m.run(th)["terms"]
    for i in range(th.shape[0]):
        sys_, y, cens, ind = m.daily_system(th[i])
        daily = tk.adf_log_likelihood(sys_, cens, y, censored=ind, per_step=True)
        np.testing.assert_allclose(terms[i], daily[m.day], rtol=1e-10, atol=1e-11)
    assert np.all(np.isfinite(terms))


def test_seasonal_sample_noise_is_what_the_model_says_and_the_pass_equals_the_daily_adf(short_model):
    """season_variance: the noise sd r exp(gamma z + gamma_s sin 2 pi t + gamma_c cos 2 pi t) of each sample, written
    out from the dates, and the sample-grid pass with it against the package's ADF on the daily grid."""
    from tobitkf.inference.wrtds import decimal_year

    m0 = short_model
    m = RiverModel(
        day=m0.day, y=m0.y, censored=m0.censored, rows=m0.rows, coef=m0.coef, drift=m0.drift, flow_variance=True,
        season_variance=True,
    )  # fmt: skip
    assert m.names[m.names.index("gamma_flow") + 1 : m.names.index("gamma_flow") + 3] == ("gamma_sin", "gamma_cos")
    th = _theta(m)
    th[m.names.index("gamma_sin")], th[m.names.index("gamma_cos")] = 0.4, -0.3
    rec = load_arkansas()
    t = decimal_year(rec.daily_date[m.day])
    z = np.log(rec.daily_q) - np.log(rec.daily_q).mean()
    r = np.exp(th[m.names.index("log_r")])
    want = r * np.exp(-0.2 * z[m.day] + 0.4 * np.sin(2 * np.pi * t) - 0.3 * np.cos(2 * np.pi * t))
    np.testing.assert_allclose(m.noise_var(m.natural(th[None]), np.arange(m.n_samples))[0], want**2, rtol=1e-12)
    sys_, y, cens, ind = m.daily_system(th)
    ll_daily = tk.adf_log_likelihood(sys_, cens, y, censored=ind, per_step=True)
    np.testing.assert_allclose(m.run(th[None])["terms"][0], ll_daily[m.day], rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="season_variance"):
        RiverModel(day=m0.day, y=m0.y, censored=m0.censored, rows=m0.rows[:, [0, 1, -1]], coef=("intercept", "ln_q"),
                   drift=(), season_variance=True)  # fmt: skip


def test_added_regressors_are_what_the_model_says():
    """The second harmonic is sin/cos of 4 pi t on the daily dates; the flow anomaly is ln Q against its
    exponentially weighted mean of the days before (a loop over the days)."""
    from tobitkf.inference.wrtds import decimal_year

    rec = load_arkansas()
    m = RiverModel.from_record(rec, drift=(), harmonics=2, flow_anomaly_days=30.0, quadratic=True)
    t = decimal_year(rec.daily_date)
    np.testing.assert_allclose(m.rows[:, m.coef.index("sin2")], np.sin(4 * np.pi * t), atol=1e-12)
    np.testing.assert_allclose(m.rows[:, m.coef.index("cos2")], np.cos(4 * np.pi * t), atol=1e-12)
    z = np.log(rec.daily_q) - np.log(rec.daily_q).mean()
    ema = np.empty_like(z)
    ema[0] = z[0]
    for d in range(1, z.size):
        ema[d] = ema[d - 1] + (z[d] - ema[d - 1]) / 30.0
    np.testing.assert_allclose(m.rows[:, m.coef.index("flow_anomaly")], z - np.r_[z[0], ema[:-1]], atol=1e-12)
    assert m.coef[-1] == "flow_anomaly" and m.rows.shape[1] == len(m.coef) + 1
    assert np.all(m.rows[:, -1] == 1.0)  # the AR residual's column stays last
    with pytest.raises(ValueError, match="harmonics"):
        RiverModel.from_record(rec, drift=(), harmonics=3)


def test_the_documented_models_are_candidates():
    from tobitkf.experiments.records import ARKANSAS_CANDIDATES
    from tobitkf.experiments.records_arkansas import MOVING_WINDOWS_MODEL

    assert ARKANSAS_MODEL in ARKANSAS_CANDIDATES and STATIC_MODEL in ARKANSAS_CANDIDATES
    assert MOVING_WINDOWS_MODEL in ARKANSAS_CANDIDATES
    assert len({repr(sorted(c.items())) for c in ARKANSAS_CANDIDATES}) == len(ARKANSAS_CANDIDATES)  # no repeats


def test_daily_smoother_of_the_experiments_model_equals_tk_smooth():
    """The full record under the experiment's model (a drifting intercept, static coefficients of zero prior
    variance, the added regressors, days after the last sample): the one-step fill-in between sample days
    against the RTS pass over every day."""
    m = RiverModel.from_record(load_arkansas(), **{**ARKANSAS_MODEL, "noise": "normal"})  # a LinearSystem's noise
    th = m.start()
    th[m.names.index("gamma_flow")] = -0.2
    if m.residual_ar:
        th[m.names.index("log_tau_days")] = np.log(40.0)
    sys_, y, cens, ind = m.daily_system(th)
    ref = tk.smooth(sys_, y, censoring=cens, censored=ind)
    got = m.daily_smooth(th)
    assert m.day[-1] < m.rows.shape[0] - 1  # some days follow the last sample
    # the filter moves the drifting intercept (and the residual, if any) only
    assert m.dyn.tolist() == [0] + [m.nx - 1] * m.residual_ar
    np.testing.assert_allclose(got["mean"], ref.mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(got["cov"], ref.cov, rtol=1e-8, atol=1e-11)


@pytest.mark.parametrize("fast", [False, True])
def test_interval_samples_and_a_fast_residual_on_the_sample_grid_equal_the_daily_adf(short_model, fast):
    """Samples known only to lie in a range (interval readings) and the second (fast) residual: the per-gap pass
    equals the package's ADF and smoother on the daily grid, and the intervals are scored as intervals."""
    m0 = short_model
    iv = np.zeros(m0.n_samples, bool)
    iv[np.flatnonzero(~m0.censored)[::5]] = True
    lower = np.where(iv, m0.y - 0.3, m0.lower)
    upper = np.where(iv, m0.y + 0.2, np.inf)
    m = RiverModel(
        day=m0.day, y=np.where(iv, m0.y - 0.05, m0.y), censored=m0.censored | iv, rows=m0.rows, coef=m0.coef,
        drift=m0.drift, flow_variance=True, lower=lower, upper=upper, fast_residual=fast,
    )  # fmt: skip
    assert m.interval.sum() == iv.sum() and m.nx == m0.nx + int(fast)
    th = m.start()
    th[m.names.index("gamma_flow")] = -0.2
    sys_, y, cens, ind = m.daily_system(th)
    ll_daily = tk.adf_log_likelihood(sys_, cens, y, censored=ind, per_step=True)
    out = m.run(th[None])
    np.testing.assert_allclose(out["terms"][0], ll_daily[m.day], rtol=1e-10, atol=1e-12)
    ref = tk.smooth(sys_, y, censoring=cens, censored=ind)
    got = m.daily_smooth(th)
    np.testing.assert_allclose(got["mean"], ref.mean, rtol=1e-9, atol=1e-11)
    # an interval sample scores the predictive mass of its interval, not the density of its midpoint
    k = int(np.flatnonzero(iv)[0])
    ll_exact = RiverModel(
        day=m0.day, y=m.y, censored=m0.censored, rows=m0.rows, coef=m0.coef, drift=m0.drift, flow_variance=True,
        fast_residual=fast,
    ).run(th[None])["terms"][0]  # fmt: skip
    assert out["terms"][0, k] < 0 < abs(out["terms"][0, k] - ll_exact[k])


def test_a_sample_between_two_bounds_is_an_interval_reading_of_the_series():
    rec = load_arkansas()
    import dataclasses

    low = rec.conc_low.copy()
    j = int(np.flatnonzero(rec.censored)[0])
    low[j] = 0.5 * rec.conc_high[j]
    s = dataclasses.replace(rec, conc_low=low).series()
    assert s.interval[j] and s.interval.sum() == 1
    assert s.lower[j] == np.log(low[j]) and s.upper[j] == np.log(rec.conc_high[j]) and s.lower[j] < s.y[j] < s.upper[j]
    m = RiverModel.from_record(dataclasses.replace(rec, conc_low=low), **STATIC_MODEL)
    assert m.interval[j] and m.upper[j] == s.upper[j]
