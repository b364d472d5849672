"""The river model's flow-response and noise options (tobitkf.experiments.records_river): each at its null value
equals the model without it, each regressor and noise sd is what the docstring says (written out from the dates
and the discharge), the sample-grid pass with them equals the package's ADF on the daily grid, and the spline is
a natural cubic spline (scipy's interpolant lies in its span)."""

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

import tobitkf as tk
from tobitkf.data import load_arkansas
from tobitkf.experiments.records_river import RiverModel, flow_spline_basis, spline_knots
from tobitkf.inference.wrtds import decimal_year

OPTIONS = [
    {"flow_spline_knots": 4},
    {"flow_spline_knots": 3},
    {"flow_anomaly_days": 30.0, "anomaly_slope": True},
    {"slope_trend": True},
    {"flow_variance": True, "flow_variance_square": True},
    {"variance_trend": True},
    {"flow_anomaly_days": 30.0, "anomaly_variance": True},
    {"flow_anomaly_days": 10.0, "slow_anomaly_days": 90.0},
]
BASE = {"drift": ("intercept",), "flow_variance": True, "harmonics": 2}


@pytest.fixture(scope="module")
def rec():
    return load_arkansas()


def _null_theta(model, reduced_model, theta_reduced):
    """The model's parameters equal to the reduced model's, the option's own parameters at 0."""
    est = dict(zip(reduced_model.names, theta_reduced))
    extra = set(model.names) - set(reduced_model.names)
    assert extra and all(not n.startswith("log_") for n in extra)
    return np.array([est.get(n, 0.0) for n in model.names])


@pytest.mark.parametrize("option", OPTIONS, ids=lambda o: "+".join(k for k in o if k not in BASE))
def test_each_option_at_its_null_value_is_the_model_without_it(rec, option):
    base = {**BASE, **{k: v for k, v in option.items() if k in ("flow_anomaly_days", "flow_variance")}}
    m0 = RiverModel.from_record(rec, **base)
    m1 = RiverModel.from_record(rec, **{**base, **option})
    rng = np.random.default_rng(5)
    th0 = m0.start()[None] + rng.normal(0, 0.2, (3, m0.p))
    th1 = np.array([_null_theta(m1, m0, t) for t in th0])
    a, b = m0.run(th0, smooth=True), m1.run(th1, smooth=True)
    np.testing.assert_allclose(b["terms"], a["terms"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b["mean"], a["mean"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b["sd"], a["sd"], rtol=1e-12, atol=1e-12)
    # and away from the null the option changes the likelihood
    th2 = th1.copy()
    new = [i for i, n in enumerate(m1.names) if n not in m0.names]
    th2[:, new] += 0.1
    assert np.all(np.abs(m1.run(th2)["loglik"] - a["loglik"]) > 1e-3)


def test_added_regressors_and_noise_sd_written_out(rec):
    m = RiverModel.from_record(
        rec, drift=(), flow_variance=True, flow_variance_square=True, variance_trend=True, season_variance=True,
        flow_anomaly_days=30.0, slow_anomaly_days=90.0, anomaly_variance=True, anomaly_slope=True, slope_trend=True, flow_spline_knots=4,
    )  # fmt: skip
    t = decimal_year(rec.daily_date)
    z = np.log(rec.daily_q) - np.log(rec.daily_q).mean()
    dec = (t - 0.5 * (t[0] + t[-1])) / 10.0
    ema = np.empty_like(z)
    ema[0] = z[0]
    for d in range(1, z.size):
        ema[d] = ema[d - 1] + (z[d] - ema[d - 1]) / 30.0
    anomaly = z - np.r_[z[0], ema[:-1]]
    col = m.coef.index
    np.testing.assert_allclose(m.rows[:, col("flow_anomaly_ln_q")], anomaly * z, atol=1e-12)
    ema90 = np.empty_like(z)
    ema90[0] = z[0]
    for d in range(1, z.size):
        ema90[d] = ema90[d - 1] + (z[d] - ema90[d - 1]) / 90.0
    np.testing.assert_allclose(m.rows[:, col("flow_anomaly_slow")], z - np.r_[z[0], ema90[:-1]], atol=1e-12)
    np.testing.assert_allclose(m.rows[:, col("ln_q_trend")], z * dec, atol=1e-12)
    k = np.quantile(z, [0.05, 0.35, 0.65, 0.95])
    s1 = (
        np.maximum(z - k[0], 0) ** 3
        - np.maximum(z - k[2], 0) ** 3 * (k[3] - k[0]) / (k[3] - k[2])
        + np.maximum(z - k[3], 0) ** 3 * (k[2] - k[0]) / (k[3] - k[2])
    ) / (k[3] - k[0]) ** 2
    np.testing.assert_allclose(m.rows[:, col("ln_q_rcs1")], s1, atol=1e-12)
    assert "ln_q_rcs2" in m.coef and "ln_q_rcs3" not in m.coef
    assert np.all(m.rows[:, -1] == 1.0)  # the residual's column stays last
    th = m.start()
    g = {"gamma_flow": -0.2, "gamma_flow_sq": 0.05, "gamma_sin": 0.3, "gamma_cos": -0.1, "gamma_trend": 0.15}
    g["gamma_anomaly"] = 0.4
    for name, v in g.items():
        th[m.names.index(name)] = v
    r = np.exp(th[m.names.index("log_r")])
    want = r * np.exp(
        -0.2 * z
        + 0.05 * z**2
        + 0.3 * np.sin(2 * np.pi * t)
        - 0.1 * np.cos(2 * np.pi * t)
        + 0.15 * dec
        + 0.4 * np.abs(anomaly)
    )
    nat = m.natural(th[None])
    np.testing.assert_allclose(m.noise_sd(nat)[0], want, rtol=1e-12)
    np.testing.assert_allclose(m.noise_var(nat, np.arange(m.n_samples))[0], want[m.day] ** 2, rtol=1e-12)


def test_the_options_on_the_sample_grid_equal_the_adf_on_the_daily_grid(rec):
    """Eight years of the record with every new option on: the per-gap pass against the package's ADF over every
    day (time-varying C and R, readings NaN between samples) and its smoother."""
    full = RiverModel.from_record(
        rec, drift=("intercept",), flow_variance=True, flow_variance_square=True, variance_trend=True,
        flow_anomaly_days=30.0, anomaly_slope=True, slope_trend=True, flow_spline_knots=3,
    )  # fmt: skip
    days = 8 * 365
    keep = full.day < days
    m = RiverModel(
        day=full.day[keep], y=full.y[keep], censored=full.censored[keep], rows=full.rows[:days], coef=full.coef,
        drift=full.drift, flow_variance=True, flow_variance_square=True, variance_trend=True,
        years=full.years[:days],
    )  # fmt: skip
    assert m.names == full.names
    th = m.start()
    th[m.names.index("log_tau_days")] = np.log(40.0)
    for name, v in {"gamma_flow": -0.2, "gamma_flow_sq": 0.05, "gamma_trend": 0.3}.items():
        th[m.names.index(name)] = v
    sys_, y, cens, ind = m.daily_system(th)
    ll_daily = tk.adf_log_likelihood(sys_, cens, y, censored=ind, per_step=True)
    np.testing.assert_allclose(m.run(th[None])["terms"][0], ll_daily[m.day], rtol=1e-10, atol=1e-12)
    ref = tk.smooth(sys_, y, censoring=cens, censored=ind)
    got = m.daily_smooth(th)
    np.testing.assert_allclose(got["mean"], ref.mean, rtol=1e-9, atol=1e-11)


def test_the_spline_basis_spans_the_natural_cubic_splines():
    """scipy's natural cubic interpolant through values at the knots is 1, z and the K - 2 columns combined
    (to rounding); the columns are 0 below the first knot and linear above the last."""
    rng = np.random.default_rng(2)
    k = np.array([-1.7, -0.4, 0.2, 0.9, 2.3])
    z = np.linspace(-3.0, 4.0, 1401)
    B = np.column_stack([np.ones_like(z), z, flow_spline_basis(z, k)])
    for _ in range(3):
        f = CubicSpline(k, rng.normal(size=k.size), bc_type="natural", extrapolate=True)
        inside = (z >= k[0]) & (z <= k[-1])
        target = f(z[inside])
        coef, *_ = np.linalg.lstsq(B[inside], target, rcond=None)
        np.testing.assert_allclose(B[inside] @ coef, target, atol=1e-11)
    S = flow_spline_basis(z, k)
    assert np.all(S[z <= k[0]] == 0.0)
    np.testing.assert_allclose(np.diff(S[z >= k[-1]], 2, axis=0), 0.0, atol=1e-11)
    np.testing.assert_allclose(spline_knots(z, 3), np.quantile(z, [0.1, 0.5, 0.9]))


def test_option_errors_name_the_argument(rec):
    with pytest.raises(ValueError, match="anomaly_variance"):
        RiverModel.from_record(rec, drift=(), anomaly_variance=True)
    with pytest.raises(ValueError, match="anomaly_slope"):
        RiverModel.from_record(rec, drift=(), anomaly_slope=True)
    with pytest.raises(ValueError, match="flow_spline_knots"):
        RiverModel.from_record(rec, drift=(), flow_spline_knots=2)
    with pytest.raises(ValueError, match="flow_variance_square"):
        RiverModel.from_record(rec, drift=(), flow_variance_square=True)
    m = RiverModel.from_record(rec, drift=())
    with pytest.raises(ValueError, match="slope_trend: needs years"):
        RiverModel(day=m.day, y=m.y, censored=m.censored, rows=m.rows, coef=m.coef, drift=(), slope_trend=True)
    with pytest.raises(ValueError, match="years: expected one decimal year per day"):
        RiverModel(day=m.day, y=m.y, censored=m.censored, rows=m.rows, coef=m.coef, drift=(), years=m.years[:-1])
    with pytest.raises(ValueError, match="knots"):
        flow_spline_basis(np.zeros(3), np.array([0.0, 0.0, 1.0]))
