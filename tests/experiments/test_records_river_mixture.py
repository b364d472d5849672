"""The river model's heavier-tailed sample noise (RiverModel(noise="mixture")): at weight 0 it is the normal model
(filter, likelihood, smoother, leave-one-out predictive and scores), one update step is the moment-matched exact
posterior (brute-force quadrature of the posterior mean, variance and evidence), and the mixture predictive is a
density (it integrates to 1 and its censored score is its integral below the limit). The compiled mixture filter
equals its numpy reference."""

import numpy as np
import pytest
from scipy import integrate
from scipy.special import expit
from scipy.stats import norm

from tobitkf import ValidationError
from tobitkf.data import load_arkansas
from tobitkf.experiments.records_arkansas import ARKANSAS_CANDIDATES, ARKANSAS_MODEL, NORMAL_NOISE_MODEL, loo_scores
from tobitkf.experiments.records_common import adf_pass, mixture_predictive_scores, mixture_update
from tobitkf.experiments.records_river import RiverModel, batched_loo_refit
from tobitkf.inference.wrtds import predictive_scores

DAYS = 8 * 365
SMALL = {"drift": ("intercept",), "flow_variance": True, "season_variance": True}


@pytest.fixture(scope="module")
def rec():
    return load_arkansas()


def _short(rec, **options):
    """The model on the first eight years of the record (79 samples)."""
    full = RiverModel.from_record(rec, **options)
    keep = full.day < DAYS
    return RiverModel(
        day=full.day[keep],
        y=full.y[keep],
        censored=full.censored[keep],
        rows=full.rows[:DAYS],
        coef=full.coef,
        years=full.years[:DAYS],
        **{k: v for k, v in options.items() if k not in ("harmonics", "flow_anomaly_days", "slow_anomaly_days")},
    )


def _thetas(m, rng, count=3):
    th = m.start()[None] + rng.normal(0, 0.2, (count, m.p))
    if "log_tau_days" in m.names:
        th[:, m.names.index("log_tau_days")] = np.log(40.0)
    return th


@pytest.mark.parametrize("options", [SMALL, ARKANSAS_MODEL], ids=["ar_residual", "experiment_model"])
def test_zero_weight_is_the_normal_model(rec, options):
    """w = 0 (fixed, or its logit at -inf): the likelihood terms, the filtered and smoothed moments, the smoothed
    predictive and the daily smoother equal the normal model's to 1e-12."""
    options = {**options, "noise": "normal"}
    m0 = RiverModel.from_record(rec, **options)
    fixed = RiverModel.from_record(rec, **{**options, "noise": "mixture", "outlier_weight": 0.0, "outlier_scale": 3.0})
    fitted = RiverModel.from_record(rec, **{**options, "noise": "mixture"})
    assert fixed.names == m0.names and fitted.names == m0.names + ("logit_outlier_weight", "log_outlier_scale")
    th = _thetas(m0, np.random.default_rng(3))
    th_fitted = np.column_stack([th, np.full(len(th), -np.inf), np.full(len(th), np.log(3.0))])
    ref = m0.run(th, smooth=True)
    for m, t in ((fixed, th), (fitted, th_fitted)):
        got = m.run(t, smooth=True)
        for key in ("terms", "loglik", "mean", "sd", "latent_var"):
            np.testing.assert_allclose(got[key], ref[key], rtol=1e-12, atol=1e-12, err_msg=key)
        for key in ("mean", "cov", "pred_mean", "pred_cov"):
            np.testing.assert_allclose(
                getattr(got["filtered"], key), getattr(ref["filtered"], key), rtol=1e-12, atol=1e-12, err_msg=key
            )
        np.testing.assert_allclose(got["smoothed"].cov, ref["smoothed"].cov, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(m.run(t)["terms"], ref["terms"], rtol=1e-12, atol=1e-12)  # the likelihood path
    d0, d1 = m0.daily_smooth(th[0]), fixed.daily_smooth(th[0])
    for key in ("mean", "cov", "ln_mean", "ln_sd", "noise_sd"):
        np.testing.assert_allclose(d1[key], d0[key], rtol=1e-12, atol=1e-12, err_msg=key)
    # and a positive weight changes the likelihood
    th_w = th_fitted.copy()
    th_w[:, -2] = np.log(0.05 / 0.95)
    assert np.all(np.abs(fitted.run(th_w)["loglik"] - ref["loglik"]) > 1e-3)


def test_zero_weight_leave_one_out_is_the_normal_models(rec):
    """The leave-one-out of a censored and a measured sample: at w = 0 the refits follow the normal model's (the
    same search on likelihoods equal to rounding; finite differences amplify the rounding, hence 1e-6), and at the
    same refitted parameters the predictive (mean, sd, components) and the scores equal the normal model's to
    1e-12."""
    m0 = _short(rec, **SMALL)
    m1 = _short(rec, **SMALL, noise="mixture", outlier_weight=0.0, outlier_scale=2.5)
    from tobitkf.experiments.records_common import fit_ml

    fit = fit_ml(m0)
    samples = np.array([int(np.flatnonzero(m0.censored)[0]), int(np.flatnonzero(~m0.censored)[1])])
    a = batched_loo_refit(m0, fit["theta"], fit["cov"], samples, gtol=1e-5)
    b = batched_loo_refit(m1, fit["theta"], fit["cov"], samples, gtol=1e-5)
    np.testing.assert_allclose(b["theta"], a["theta"], atol=1e-6)
    np.testing.assert_allclose(b["loglik"], a["loglik"], atol=1e-9)
    # the predictive at the same parameters, the sample removed
    Y = np.repeat(m0.y[None], samples.size, axis=0)
    Y[np.arange(samples.size), samples] = np.nan
    low = np.where(m0.censored, -np.inf, m0.y)[samples]
    high = m0.y[samples]
    idx = np.arange(samples.size)
    outs = []
    for m in (m0, m1):
        sm = m.run(a["theta"], Y, smooth=True)
        sds, weights = m.predictive(a["theta"], samples, sm["latent_var"][idx, samples])
        loo = {"mean": sm["mean"][idx, samples], "sd": sm["sd"][idx, samples]}
        loo.update(component_sd=sds, component_weight=weights)
        outs.append((loo, loo_scores(m, loo, low, high)))
    (l0, s0), (l1, s1) = outs
    for key in ("mean", "sd", "component_weight"):
        np.testing.assert_allclose(l1[key], l0[key], rtol=1e-12, atol=1e-12, err_msg=key)
    np.testing.assert_allclose(l1["component_sd"][:, 0], l0["sd"], rtol=1e-12)  # the wide one has weight 0
    np.testing.assert_allclose(l0["component_sd"][:, 0], l0["sd"], rtol=1e-12)
    np.testing.assert_array_equal(l1["component_weight"][:, 1], 0.0)
    np.testing.assert_allclose(s1.log_score, s0.log_score, rtol=1e-12, atol=1e-12)
    assert s1.rmse == pytest.approx(s0.rmse, rel=1e-12)


def _quadrature_posterior(m, P, c, dy, y, lower, r, w, cs):
    """Posterior mean, variance and evidence of a scalar state x ~ N(m, P) given the reading of
    y* = c x + dy + v, v ~ (1 - w) N(0, r^2) + w N(0, (cs r)^2): a measured y, or y* <= lower (y = nan)."""

    def like(x):
        mu = c * x + dy
        if np.isnan(y):
            return (1 - w) * norm.cdf(lower, mu, r) + w * norm.cdf(lower, mu, cs * r)
        return (1 - w) * norm.pdf(y, mu, r) + w * norm.pdf(y, mu, cs * r)

    sd = np.sqrt(P)
    lo, hi = m - 14 * sd, m + 14 * sd
    opts = {"epsabs": 0.0, "epsrel": 1e-12, "limit": 400}

    def integral(f):
        return integrate.quad(lambda x: f(x) * norm.pdf(x, m, sd) * like(x), lo, hi, **opts)[0]

    Z = integral(lambda x: 1.0)
    mean = integral(lambda x: x) / Z
    var = integral(lambda x: (x - mean) ** 2) / Z
    return mean, var, Z


@pytest.mark.parametrize("censored", [False, True], ids=["measured", "censored"])
def test_one_update_is_the_moment_matched_exact_posterior(censored):
    """One mixture update of a scalar state against brute-force quadrature of p(x) p(reading | x): posterior mean,
    variance and log evidence, for runs with different priors, weights and sd ratios (an outlying reading
    among them, where the wide component takes most of the posterior weight)."""
    m = np.array([0.3, -1.0, 2.0, 0.0])
    P = np.array([0.5, 2.0, 0.3, 1.0])
    c, dy = 1.3, np.array([0.1, -0.2, 0.0, 0.5])
    r = np.array([0.4, 0.7, 0.25, 0.5])
    w = np.array([0.1, 0.3, 0.05, 0.2])
    cs = np.array([3.0, 2.0, 6.0, 0.5])
    y = np.array([0.9, -2.5, 0.2, 0.4])  # run 2: an outlier 4.6 predictive sd below its mean
    lower = np.full(4, -np.inf)
    if censored:
        lower, y = y.copy(), y.copy()  # the readings are at their detection limits
    x1, P1, ll = mixture_update(m[:, None], P[:, None, None], y, np.array([c]), r**2, w, cs**2, lower, np.inf, dy=dy)
    for i in range(4):
        ref = _quadrature_posterior(m[i], P[i], c, dy[i], np.nan if censored else y[i], lower[i], r[i], w[i], cs[i])
        assert x1[i, 0] == pytest.approx(ref[0], rel=1e-8, abs=1e-10)
        assert P1[i, 0, 0] == pytest.approx(ref[1], rel=1e-8)
        assert ll[i] == pytest.approx(np.log(ref[2]), rel=1e-9, abs=1e-10)
    # the moment matching is not the Gaussian update of either component (the test can fail)
    assert abs(P1[2, 0, 0] - P[2] * r[2] ** 2 / (c**2 * P[2] + r[2] ** 2)) > 1e-3


def test_missing_reading_leaves_the_prior():
    x, P, ll = mixture_update(
        np.array([[0.3, 1.0]]), np.eye(2)[None], np.array([np.nan]), np.array([1.0, 0.5]), np.array([0.2]),
        np.array([0.1]), np.array([9.0]), np.array([-np.inf]), np.array([np.inf]),
    )  # fmt: skip
    assert ll[0] == 0.0
    np.testing.assert_array_equal(x, [[0.3, 1.0]])
    np.testing.assert_array_equal(P, np.eye(2)[None])


def test_mixture_predictive_is_a_density():
    """The mixture predictive's density integrates to 1 and its censored score is the log of its integral below the
    limit (quadrature); a single component of weight 1 is the Gaussian score."""
    mean = np.array([0.4])
    sds = np.array([[0.3, 1.5]])
    weights = np.array([[0.85, 0.15]])

    def density(v):
        s = mixture_predictive_scores(mean, sds, weights, np.array([v]), np.array([v]))
        return np.exp(s.log_score[0])

    total = integrate.quad(density, -np.inf, np.inf, epsabs=0.0, epsrel=1e-12, limit=200)[0]
    assert total == pytest.approx(1.0, abs=1e-9)
    limit = -1.1
    below = integrate.quad(density, -np.inf, limit, epsabs=0.0, epsrel=1e-12, limit=200)[0]
    cens = mixture_predictive_scores(mean, sds, weights, np.array([-np.inf]), np.array([limit]))
    assert cens.log_score[0] == pytest.approx(np.log(below), rel=1e-9)
    # weight 1 on the first component: the Gaussian scores
    lo, hi = np.array([-np.inf, 0.2, 0.1]), np.array([-0.5, 0.2, 0.6])
    mu, sd2 = np.array([0.1, 0.0, 0.3]), np.array([[0.5, 2.0], [0.4, 3.0], [0.7, 1.0]])
    one = mixture_predictive_scores(mu, sd2, np.array([[1.0, 0.0]] * 3), lo, hi)
    ref = predictive_scores(mu, sd2[:, 0], lo, hi)
    np.testing.assert_array_equal(one.log_score, ref.log_score)


def test_mixture_options_are_checked(rec):
    for bad, word in (({"noise": "student"}, "noise"), ({"noise": "mixture", "outlier_weight": 1.0}, "outlier_weight"),
                      ({"noise": "mixture", "outlier_scale": 0.0}, "outlier_scale")):  # fmt: skip
        with pytest.raises(ValidationError, match=word):
            RiverModel.from_record(rec, **SMALL, **bad)
    m = RiverModel.from_record(rec, **SMALL, noise="mixture")
    with pytest.raises(ValidationError, match="daily_system"):
        m.daily_system(m.start())
    nat = m.natural(m.start())
    assert nat["w"] == pytest.approx(0.05) and nat["c"] == pytest.approx(3.0)
    assert expit(m.start()[m.names.index("logit_outlier_weight")]) == pytest.approx(0.05)


def test_mixture_candidates_are_appended_to_their_normal_counterparts():
    """Each mixture candidate is a normal candidate with the mixture noise, listed after every normal one (the
    order tried)."""
    normal = [c for c in ARKANSAS_CANDIDATES if c.get("noise", "normal") == "normal"]
    mixture = [c for c in ARKANSAS_CANDIDATES if c.get("noise", "normal") == "mixture"]
    assert mixture and ARKANSAS_CANDIDATES[: len(normal)] == tuple(normal)
    for c in mixture:
        assert {k: v for k, v in c.items() if k != "noise"} in normal
    assert ARKANSAS_MODEL in mixture and {**NORMAL_NOISE_MODEL, "noise": "mixture"} in mixture


def test_mixture_daily_smoother_agrees_with_the_sample_grid(rec):
    """With w > 0 the daily smoother (the mixture filter's moments, the package's RTS pass, the fill-in between
    samples) gives each sample day the sample-grid smoother's latent mean and variance, and the predictive sd adds
    the mixture's noise variance (1 - w + w c^2) s^2."""
    m = RiverModel.from_record(rec, **SMALL, noise="mixture")
    th = m.start()
    th[m.names.index("log_tau_days")] = np.log(40.0)
    sm = m.run(th[None], smooth=True)
    daily = m.daily_smooth(th)
    np.testing.assert_allclose(daily["ln_mean"][m.day], sm["mean"][0], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(daily["ln_sd"][m.day] ** 2, sm["latent_var"][0], rtol=1e-9, atol=1e-12)
    nat = m.natural(th[None])
    w, c = float(nat["w"][0]), float(nat["c"][0])
    noise = (1 - w + w * c**2) * daily["noise_sd"][m.day] ** 2
    np.testing.assert_allclose(sm["sd"][0] ** 2, sm["latent_var"][0] + noise, rtol=1e-12)


def _assert_same_pass(got, ref):
    """Two results of :func:`adf_pass` with ``smooth``: likelihood, filtered and smoothed moments to 1e-12."""
    for key in ("terms", "loglik", "mean", "sd", "latent_var"):
        np.testing.assert_allclose(got[key], ref[key], rtol=1e-12, atol=1e-12, err_msg=key)
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(
            getattr(got["filtered"], key), getattr(ref["filtered"], key), rtol=1e-12, atol=1e-12, err_msg=key
        )
    np.testing.assert_allclose(got["smoothed"].cov, ref["smoothed"].cov, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("weight", [0.0, 0.08], ids=["w0", "w_positive"])
def test_compiled_mixture_pass_is_the_numpy_pass(rec, weight):
    """The experiment's model on the whole record (measured and censored samples) with some samples removed
    (missing): the compiled mixture filter's likelihood terms, filtered and predicted moments, smoothed moments and
    predictive equal the numpy reference's to 1e-12, at w = 0 and w > 0; so does the likelihood-only pass."""
    m = RiverModel.from_record(rec, **ARKANSAS_MODEL)
    assert m.censored.any() and (~m.censored).any()
    th = _thetas(m, np.random.default_rng(5))
    th[:, m.names.index("logit_outlier_weight")] = np.log(weight / (1 - weight)) if weight > 0 else -np.inf
    Y = np.repeat(m.y[None], len(th), axis=0)
    Y[0, [3, 4, 40]] = np.nan
    Y[1, np.flatnonzero(m.censored)[:2]] = np.nan
    ref = m.run(th, Y, smooth=True, compiled=False)
    _assert_same_pass(m.run(th, Y, smooth=True, compiled=True), ref)
    np.testing.assert_allclose(m.run(th, Y, compiled=True)["terms"], ref["terms"], rtol=1e-12, atol=1e-12)
    assert np.all(ref["terms"][0, [3, 4, 40]] == 0.0)  # the missing readings


def test_compiled_mixture_pass_reading_classes():
    """Every reading class through :func:`adf_pass` directly (measured, below a lower limit, above an upper limit,
    an interval reading flagged censored between finite limits, missing), two states, runs of their own weights
    (one at 0) and ratios: the compiled filter equals the numpy reference to 1e-12."""
    rng = np.random.default_rng(11)
    N, n, T = 4, 2, 40
    y = rng.normal(0.0, 1.5, (N, T))
    lower = np.full((N, T), -1.0)
    upper = np.full((N, T), 1.5)
    y = np.clip(y, lower, upper)  # the readings beyond a limit hold it
    flags = (y <= lower) | (y >= upper)
    inside = np.abs(y) < 0.5
    flags[inside & (rng.random((N, T)) < 0.3)] = True  # flagged inside the limits: interval readings
    y[:, ::7] = np.nan
    flags[:, ::7] = False
    kwargs = dict(
        x0=rng.normal(0, 0.3, (N, n)), P0=np.repeat(np.eye(n)[None], N, axis=0) * 0.5,
        rate=np.array([[0.1, 0.0]] * N), diffusion=np.array([[0.2, 0.05]] * N),
        gaps=rng.uniform(0.2, 3.0, T), C=np.column_stack([np.ones(T), rng.normal(0, 1, T)]), y=y,
        lower=lower, upper=upper, r2=rng.uniform(0.05, 0.3, (N, T)), dy=rng.normal(0, 0.1, (N, T)),
        smooth=True, censored=flags, mixture=(np.array([0.0, 0.05, 0.2, 0.4]), np.array([4.0, 9.0, 2.0, 25.0])),
    )  # fmt: skip
    assert (y <= lower).any() and (y >= upper).any() and (flags & (y > lower) & (y < upper)).any()
    ref = adf_pass(**kwargs, compiled=False)
    got = adf_pass(**kwargs, compiled=True)
    assert np.isfinite(ref["loglik"]).all()
    _assert_same_pass(got, ref)
