"""The quantized sensor and the channel contract it proves: levels and cells, reading checks, the generic
assumed-density update against brute-force quadrature of the interval posterior, the Tobit-type statistics,
the Fisher information, the particle filter, and the generic filters against the named forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr, ndtr

import tobitkf as tk
from tobitkf.channels.base import interval_moments, log_interval_mass, registered_channels, section_of
from tobitkf.filters.adf_generic import AssumedDensityFilter


class GenericADF(AssumedDensityFilter):
    """A subclass always runs the generic update (no named form)."""


def scalar_system(R=0.05, P0=1.0, x0=0.0):
    return tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.1]], R=[[R]], x0=[x0], P0=[[P0]])


# --------------------------------------------------------------------------- levels, cells, checks


def test_levels_cells_and_saturating_ends():
    q = tk.Quantizer(0.5, offset=0.1, lower=-1.0, upper=1.0)
    assert float(q.lowest_level) == pytest.approx(-0.9) and float(q.highest_level) == pytest.approx(0.6)
    y = q.quantize(np.array([-5.0, -0.66, -0.64, 0.35, 0.349, 0.84, 7.0, np.nan]))
    np.testing.assert_allclose(y[:-1], [-0.9, -0.9, -0.4, 0.6, 0.1, 0.6, 0.6], atol=1e-15)
    assert np.isnan(y[-1])
    lo, hi = q.region(np.array([-0.9, 0.1, 0.6]), 1, 0)
    np.testing.assert_allclose(lo, [-np.inf, -0.15, 0.35])
    np.testing.assert_allclose(hi, [-0.65, 0.35, np.inf])
    # the cell is [l - w/2, l + w/2): the lower edge belongs to the level
    assert float(tk.Quantizer(1.0).quantize(np.array(0.5))) == 1.0


def test_constructor_refuses_bad_parameters():
    with pytest.raises(tk.ValidationError, match="width: expected a step > 0"):
        tk.Quantizer(0.0)
    with pytest.raises(tk.ValidationError, match="offset"):
        tk.Quantizer(1.0, offset=np.inf)
    with pytest.raises(tk.ValidationError, match="at least two levels"):
        tk.Quantizer(1.0, lower=0.2, upper=0.8)
    with pytest.raises(tk.ValidationError, match="lower: \\+inf"):
        tk.Quantizer(1.0, lower=np.inf)
    with pytest.raises(tk.ShapeError, match="do not broadcast"):
        tk.Quantizer([1.0, 2.0], offset=[0.0, 0.0, 0.0])
    sys2 = tk.LinearSystem(A=np.eye(2), C=np.eye(2), Q=np.eye(2), R=np.eye(2), x0=[0, 0], P0=np.eye(2))
    with pytest.raises(tk.ShapeError, match="parameters for 2 channel"):
        tk.AssumedDensityFilter(sys2, tk.Quantizer([1.0, 2.0, 3.0]))


def test_a_reading_off_the_level_grid_is_refused():
    sys_ = scalar_system()
    adf = tk.AssumedDensityFilter(sys_, tk.Quantizer(0.25, lower=-1.0, upper=1.0))
    with pytest.raises(
        tk.ValidationError, match=r"y: reading 0.3 .* is not a level of the quantizer .*nearest level 0.25"
    ):
        adf.filter([[0.25], [0.3]])
    with pytest.raises(tk.ValidationError, match=r"lies outside the quantizer's levels \[-1, 1\]"):
        adf.filter([[1.25]])
    state = adf.init()
    with pytest.raises(tk.ValidationError, match="not a level of the quantizer"):
        adf.step(state, [0.1])
    with pytest.raises(tk.ValidationError, match="not a level of the quantizer"):
        tk.ParticleFilter(sys_, tk.Quantizer(0.25), particles=10, seed=0).filter([[0.1]])
    # values written with a few decimals (0.3 = 3 * 0.1 up to rounding) are on the grid; NaN is missing. The
    # readings are checked before either backend runs: the numpy path accepts them without compiling the loop
    tk.AssumedDensityFilter(sys_, tk.Quantizer(0.1), backend="numpy").filter([[0.3], [np.nan], [-0.7]])


def test_simulated_readings_are_the_quantized_latent_readings():
    sys_ = scalar_system()
    q = tk.Quantizer(0.4, offset=0.2, upper=1.0)
    d = tk.simulate(sys_, 30, 20, channel=q, seed=3)
    np.testing.assert_array_equal(d.y, q.quantize(d.y_latent))
    q.check_readings(d.y)  # every simulated reading is a level
    assert d.y.max() <= 1.0 + 1e-12


def test_channels_register_themselves():
    reg = registered_channels()
    assert reg["quantizer"] is tk.Quantizer and reg["censoring"] is tk.Censoring
    assert {"fading", "protocol", "saturation"} <= set(reg)
    assert section_of(tk.Quantizer(1.0)) == "quantizer" and section_of(object()) is None
    with pytest.raises(tk.ValidationError, match="already the channel"):

        class Other(tk.Channel):  # noqa: F841  (refused when defined)
            section = "quantizer"


# --------------------------------------------------------------------------- interval moments


def test_interval_mass_is_finite_and_exact_in_the_tails():
    # one-sided windows 40 sigma out: log Phi(-40); a narrow window far out (the density times the width)
    assert float(log_interval_mass(40.0, np.inf)) == pytest.approx(float(log_ndtr(-40.0)), rel=1e-14)
    assert float(log_interval_mass(-np.inf, -40.0)) == pytest.approx(float(log_ndtr(-40.0)), rel=1e-14)
    lm = float(log_interval_mass(30.0, 30.0 + 1e-6))
    assert lm == pytest.approx(-0.5 * 30.0**2 - 0.5 * np.log(2 * np.pi) + np.log(1e-6) - 15e-6, rel=1e-10)
    assert float(log_interval_mass(-1.0, 2.0)) == pytest.approx(np.log(ndtr(2.0) - ndtr(-1.0)), rel=1e-14)


def test_interval_moments_match_quadrature_far_into_the_tails():
    for lo, hi in [(-0.3, 0.2), (35.0, 35.5), (-41.0, -40.0), (5.0, np.inf)]:
        z = np.linspace(max(lo, -60), min(hi, 60), 200001) if np.isfinite(hi) else np.linspace(lo, lo + 10, 800001)
        logw = -0.5 * z * z
        w = np.exp(logw - logw.max())
        m = np.trapezoid(w * z, z) / np.trapezoid(w, z)
        v = np.trapezoid(w * (z - m) ** 2, z) / np.trapezoid(w, z)
        obs, var, _ = interval_moments(0.0, 1.0, lo, hi)
        assert float(obs) == pytest.approx(m, rel=1e-9, abs=1e-12)
        assert float(var) == pytest.approx(v, rel=1e-6)


# --------------------------------------------------------------------------- the ADF update vs quadrature


def _quadrature_posterior(m, P, c, r, lo, hi, half=9.0, pts=601):
    """Brute force: the moments of N(x; m, P) * P(lo <= c x + v < hi), v ~ N(0, r), on a grid in the prior's
    whitened coordinates (trapezoid; spectrally accurate for this analytic integrand)."""
    n = m.size
    L = np.linalg.cholesky(P)
    g = np.linspace(-half, half, pts)
    Z = np.stack(np.meshgrid(*([g] * n), indexing="ij"), -1).reshape(-1, n)
    X = m + Z @ L.T
    mu = X @ c
    s = np.sqrt(r)
    a = np.where(np.isneginf(lo), -np.inf, (lo - mu) / s)
    b = np.where(np.isposinf(hi), np.inf, (hi - mu) / s)
    like = np.exp(log_interval_mass(a, b))
    w = np.exp(-0.5 * (Z * Z).sum(1)) * like
    w /= w.sum()
    mean = w @ X
    d = X - mean
    return mean, (w[:, None] * d).T @ d, None


@pytest.mark.parametrize("reading", [0.0, 1.5, -1.0, 2.0])  # -1.0 / 2.0: the saturated ends
def test_one_quantized_update_is_the_interval_posterior_scalar(reading):
    q = tk.Quantizer(0.5, lower=-1.0, upper=2.0)
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.04]], x0=[0.3], P0=[[0.8]])
    out = tk.AssumedDensityFilter(sys_, q).filter([[reading]])
    lo, hi = q.region(np.array([reading]), 1, 0)
    mean, cov, _ = _quadrature_posterior(
        np.array([0.3]), np.array([[0.8]]), np.array([1.0]), 0.04, lo[0], hi[0], half=12.0, pts=20001
    )
    np.testing.assert_allclose(out.mean[0], mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.cov[0], cov, rtol=1e-8, atol=0)


@pytest.mark.parametrize("form", ["standard", "joseph", "square_root"])
def test_one_quantized_update_is_the_interval_posterior_2d(form):
    q = tk.Quantizer(0.6, offset=0.1, lower=-2.0)
    P0 = np.array([[1.0, 0.4], [0.4, 0.6]])
    sys_ = tk.LinearSystem(A=np.eye(2), C=[[1.0, 0.5]], Q=np.zeros((2, 2)), R=[[0.05]], x0=[0.2, -0.4], P0=P0)
    for reading in (0.1, -1.7, 1.3):
        out = tk.AssumedDensityFilter(sys_, q, covariance_update=form).filter([[reading]])
        lo, hi = q.region(np.array([reading]), 1, 0)
        mean, cov, _ = _quadrature_posterior(np.array([0.2, -0.4]), P0, np.array([1.0, 0.5]), 0.05, lo[0], hi[0])
        np.testing.assert_allclose(out.mean[0], mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.cov[0], cov, rtol=0, atol=1e-9)


def test_one_step_log_likelihood_is_the_probability_of_the_reading():
    q = tk.Quantizer(0.5)
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.04]], x0=[0.3], P0=[[0.8]])
    ll = tk.AssumedDensityFilter(sys_, q).log_likelihood([[1.0]])
    s = np.sqrt(0.84)
    assert float(ll) == pytest.approx(np.log(ndtr((1.25 - 0.3) / s) - ndtr((0.75 - 0.3) / s)), rel=1e-13)


def test_a_saturated_end_40_sigma_away_is_the_censored_update():
    """The lowest level of a quantizer says y* < l_min + w/2: the assumed-density update of a reading censored
    at that limit, to rounding, with the prior 40 sigma away (log_ndtr, no cancellation)."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.01]], x0=[40.0], P0=[[0.99]])
    q = tk.Quantizer(1.0, lower=-1.0)
    a = tk.AssumedDensityFilter(sys_, q).filter([[-1.0]])
    b = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=-0.5)).filter([[-0.5]])
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-13)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-11)
    assert np.isfinite(a.extras["log_likelihood"]).all() and a.extras["log_likelihood"][0] < -800


# --------------------------------------------------------------------------- generic vs named forms


def _two_channel_system():
    return tk.LinearSystem(
        A=[[0.95, 0.1], [0.0, 0.9]],
        C=[[1.0, 0.0], [0.5, 1.0]],
        Q=0.05 * np.eye(2),
        R=np.diag([0.1, 0.2]),
        x0=[0.5, 0.0],
        P0=np.eye(2),
    )


@pytest.mark.parametrize("form", ["standard", "joseph", "square_root"])
def test_the_generic_update_of_censoring_is_the_named_form(form):
    sys_ = _two_channel_system()
    cens = tk.Censoring(lower=[0.0, -0.5], upper=[1.0, np.inf])
    d = tk.simulate(sys_, 40, 6, censoring=cens, seed=5)
    y = d.y.copy()
    y[0, 3, 1] = np.nan
    a = GenericADF(sys_, cens, covariance_update=form).filter(y)
    b = tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form).filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=1e-12, atol=1e-12)


def test_assumed_density_filter_builds_the_named_forms():
    sys_ = scalar_system()
    assert type(tk.AssumedDensityFilter(sys_, tk.Censoring(lower=0.0))) is tk.AssumedDensityTobitFilter
    fad = tk.RiceFading.gaussian(1, [0.9, 0.3], [0.01, 0.01])
    assert type(tk.AssumedDensityFilter(sys_, [fad, tk.Censoring(lower=0.0)])) is tk.FadingAssumedDensityFilter
    sat = tk.RandomSaturation([0.2], [0.9])
    assert type(tk.AssumedDensityFilter(sys_, sat)) is tk.SaturationAssumedDensityFilter
    sys2 = tk.LinearSystem(A=np.eye(2), C=np.eye(2), Q=np.eye(2), R=np.eye(2), x0=[0, 0], P0=np.eye(2))
    prot = tk.ProtocolChannel(2, window=1, threshold=0.0)
    assert type(tk.AssumedDensityFilter(sys2, prot, nodes=4)) is tk.ProtocolAssumedDensityFilter
    est = tk.AssumedDensityFilter(sys_, tk.Censoring(lower=0.0), order="uncensored_first")
    assert est.order == "uncensored_first"  # the named form's own options pass through
    with pytest.raises(tk.ValidationError, match="takes no censoring piece"):
        tk.AssumedDensityFilter(sys_, [sat, tk.Censoring(lower=0.0)])
    with pytest.raises(tk.ValidationError, match="one channel piece"):
        tk.AssumedDensityFilter(sys_, [tk.Quantizer(1.0), tk.Censoring(lower=0.0)])


@pytest.mark.parametrize("form", ["standard", "joseph"])
def test_the_tobit_type_filter_of_censoring_is_the_tkf_with_the_total_variance(form):
    sys_ = _two_channel_system()
    cens = tk.Censoring(lower=[0.0, -0.5], upper=[1.0, np.inf])
    d = tk.simulate(sys_, 40, 6, censoring=cens, seed=6)
    a = tk.TobitFilter(sys_, cens, covariance_update=form).filter(d.y)
    b = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", covariance_update=form, backend="numpy")
    b = b.filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-12)


def test_quantizer_statistics_match_brute_force_sums():
    q = tk.Quantizer(0.7, offset=0.2, lower=-1.5, upper=2.0)
    mean, sd = np.array([-3.0, 0.1, 0.45, 2.5]), np.array([0.3, 0.5, 1.2, 0.2])
    E, g, V = q.reading_statistics(mean, sd, 1, 0)
    from scipy.integrate import quad

    for i in range(mean.size):
        # the reading's law by adaptive quadrature of the latent density between the thresholds
        ts = np.array([-0.85, -0.15, 0.55, 1.25])  # the thresholds between the levels -1.2, -0.5, 0.2, 0.9, 1.6
        edges = np.concatenate(
            [
                [mean[i] - 15 * sd[i]],
                ts[(ts > mean[i] - 15 * sd[i]) & (ts < mean[i] + 15 * sd[i])],
                [mean[i] + 15 * sd[i]],
            ]
        )
        pdf = lambda t, i=i: np.exp(-0.5 * ((t - mean[i]) / sd[i]) ** 2) / (sd[i] * np.sqrt(2 * np.pi))  # noqa: E731
        mass = np.array([quad(pdf, a, b, epsabs=1e-14, epsrel=1e-13)[0] for a, b in zip(edges[:-1], edges[1:])])
        lev = q.quantize(0.5 * (edges[:-1] + edges[1:]))
        e = mass @ lev / mass.sum()
        assert E[i] == pytest.approx(e, abs=1e-10)
        assert V[i] == pytest.approx(mass @ (lev - e) ** 2 / mass.sum(), abs=1e-10)
        h = 1e-5  # the slope: a central difference of E
        Ep = q.reading_statistics(mean[i : i + 1] + h, sd[i : i + 1], 1, 0)[0]
        Em = q.reading_statistics(mean[i : i + 1] - h, sd[i : i + 1], 1, 0)[0]
        assert g[i] == pytest.approx(float((Ep - Em)[0] / (2 * h)), rel=1e-6, abs=1e-9)


def test_a_two_level_quantizer_has_the_binary_sensor_information():
    """Two levels: the reading only says whether y* is below the threshold t, whose Fisher information about the
    mean is phi(z)^2 / (Phi(z) (1 - Phi(z)) s^2)."""
    q = tk.Quantizer(1.0, lower=0.0, upper=1.0)  # levels 0, 1; threshold 0.5
    mean, sd = np.array([0.5, -1.0, 2.0]), np.array([1.0, 0.5, 2.0])
    z = (0.5 - mean) / sd
    phi = np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
    np.testing.assert_allclose(q.fisher_information(mean, sd, 1, 0), phi**2 / (ndtr(z) * ndtr(-z)) / sd**2, rtol=1e-12)
    # a fine quantizer keeps nearly all of the information of the exact reading, 1/s^2
    fine = tk.Quantizer(0.01).fisher_information(np.array([0.3]), np.array([1.0]), 1, 0)
    assert float(fine[0]) == pytest.approx(1.0, rel=1e-4)


def test_a_fine_quantizer_filters_as_the_kalman_filter():
    sys_ = scalar_system(R=0.5)
    q = tk.Quantizer(1e-3)
    d = tk.simulate(sys_, 30, 5, channel=q, seed=2)
    kf = tk.KalmanFilter(sys_, backend="numpy").filter(d.y)
    for est in (tk.AssumedDensityFilter(sys_, q), tk.TobitFilter(sys_, q)):
        out = est.filter(d.y)
        np.testing.assert_allclose(out.mean, kf.mean, atol=1e-5)
        np.testing.assert_allclose(out.cov, kf.cov, rtol=1e-5)
    # the PCRLB of a fine quantizer is the Kalman filter's covariance
    b = tk.posterior_crlb(sys_, q, truth=d.x)
    np.testing.assert_allclose(b.var[:, 0], kf.cov[0, :, 0, 0], rtol=1e-5)


def test_online_step_smooth_and_likelihood_on_the_quantizer():
    sys_ = scalar_system()
    q = tk.Quantizer(0.5, lower=-1.0, upper=1.0)
    d = tk.simulate(sys_, 25, 3, channel=q, seed=4)
    adf = tk.AssumedDensityFilter(sys_, q)
    res = adf.filter(d.y)
    st = adf.init(batch_shape=(3,))
    for k in range(25):
        st = adf.step(st, d.y[:, k])
    np.testing.assert_allclose(st.mean, res.mean[:, -1], rtol=0, atol=1e-12)
    ll = adf.log_likelihood(d.y)
    np.testing.assert_allclose(ll, res.extras["log_likelihood"].sum(-1), rtol=1e-12)
    sm = adf.smooth(d.y)
    np.testing.assert_allclose(sm.mean[:, -1], res.mean[:, -1], rtol=0, atol=1e-12)  # the last step is filtered
    assert (sm.cov <= res.cov + 1e-12).all()  # smoothing never adds variance (scalar state)


# --------------------------------------------------------------------------- vs the particle filter


def _paired_mse(sys_, q, runs, steps, particles, seed):
    d = tk.simulate(sys_, steps, runs, channel=q, seed=seed)
    adf = tk.AssumedDensityFilter(sys_, q).filter(d.y)
    pf = tk.ParticleFilter(sys_, q, particles=particles, seed=seed + 1).filter(d.y)
    e_adf = ((adf.mean - d.x[:, 1:]) ** 2).mean(axis=(1, 2))
    e_pf = ((pf.mean - d.x[:, 1:]) ** 2).mean(axis=(1, 2))
    return e_adf, e_pf


def test_the_quantized_adf_is_within_monte_carlo_error_of_the_particle_filter():
    """Width 0.5 against a state spread of about 1 and noise 0.3: the Gaussian approximation holds, so the
    ADF's MSE is the particle filter's within the Monte Carlo error of the MSE (3 standard errors over the
    runs)."""
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.1]], R=[[0.09]], x0=[0.0], P0=[[1.0]])
    e_adf, e_pf = _paired_mse(sys_, tk.Quantizer(0.5), runs=300, steps=40, particles=400, seed=11)
    se = np.sqrt(e_adf.var(ddof=1) / e_adf.size + e_pf.var(ddof=1) / e_pf.size)
    assert abs(e_adf.mean() - e_pf.mean()) <= 3 * se, (e_adf.mean(), e_pf.mean(), se)


def test_the_predictive_linearization_keeps_the_tobit_type_filter_on_a_coarse_quantizer():
    """At the prior mean (the TKF's assumption) the gain grows like 1/slope in the middle of a wide cell and a
    reading in the next cell throws the estimate off; under the predictive law the update is the linear
    minimum-MSE one and stays within a few percent of the assumed-density filter."""
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.1]], R=[[0.09]], x0=[0.0], P0=[[1.0]])
    q = tk.Quantizer(2.0)
    d = tk.simulate(sys_, 40, 200, channel=q, seed=11)

    def mse(est):
        return float(((est.filter(d.y).mean - d.x[:, 1:]) ** 2).mean())

    adf = mse(tk.AssumedDensityFilter(sys_, q))
    assert mse(tk.TobitFilter(sys_, q)) > 10 * adf
    assert mse(tk.TobitFilter(sys_, q, linearization="predictive")) < 1.05 * adf
