"""tk.fit of a map theta -> NonlinearSystem: the assumed-density likelihood maximised, standard errors."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

TRUTH = np.array([0.6, 1.0])
CENS = tk.Censoring(lower=-0.3)


def build(theta):  # a parameter in f (a) and one in h (c)
    a, c = theta
    return tk.NonlinearSystem(
        lambda x, k: a * x + 0.5 * np.sin(x),
        lambda x, k: c * x + 0.1 * x**2,
        Q=[[0.3]],
        R=[[0.1]],
        x0=[0.0],
        P0=[[1.0]],
    )


def test_on_a_linear_model_the_fit_is_the_linear_assumed_density_fit():
    # the nonlinear ADF of a linear model is the linear ADF, so both fits maximise the same likelihood
    def nl(th):
        return tk.NonlinearSystem(lambda x, k: th[0] * x, lambda x, k: x, [[0.3]], [[th[1]]], [0.0], [[1.0]])

    def lin(th):
        return tk.LinearSystem(A=[[th[0]]], C=[[1.0]], Q=[[0.3]], R=[[th[1]]], x0=[0.0], P0=[[1.0]])

    y = tk.simulate(lin([0.7, 0.2]), 100, 1, censoring=CENS, seed=11).y[0]
    a = tk.fit(nl, y, theta0=[0.4, 0.5], censoring=CENS, progress=False)
    b = tk.fit(lin, y, theta0=[0.4, 0.5], censoring=CENS, progress=False)
    assert a.likelihood == b.likelihood == "adf" and a.converged and b.converged
    assert a.loglik == pytest.approx(b.loglik, abs=1e-6)
    se = np.sqrt(np.diag(b.cov))
    # both stop within gtol = 1e-3 standard errors of the same optimum
    np.testing.assert_allclose(a.theta, b.theta, rtol=0, atol=5e-3 * se.max())
    np.testing.assert_allclose(np.sqrt(np.diag(a.cov)), se, rtol=1e-2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_parameters_of_f_and_h_are_recovered_within_their_standard_errors(seed):
    # 8 records of 100 readings, about 45 % censored; the estimate must lie within 3.5 of its reported standard
    # errors of the truth (two-sided 5e-4 per parameter if the errors are right; the ADF likelihood's
    # approximation biases c by well under one standard error here)
    data = tk.simulate(build(TRUTH), 100, 8, channel=CENS, seed=seed)
    res = tk.fit(build, data.y, theta0=[0.3, 0.7], censoring=CENS, names=["a", "c"], progress=False)
    assert res.converged and res.likelihood == "adf" and res.method == "direct"
    se = np.array([res.se["a"], res.se["c"]])
    assert np.all(np.isfinite(se)) and np.all(se < 0.1)
    assert np.all(np.abs(res.theta - TRUTH) < 3.5 * se), (res.theta, se)
    assert isinstance(res.system(), tk.NonlinearSystem)


def test_refusals_and_saving(tmp_path):
    y = tk.simulate(build(TRUTH), 30, 1, channel=CENS, seed=3).y[0]
    with pytest.raises(tk.ValidationError, match="R"):  # the map's own refusal at theta0 (a negative variance)
        tk.fit(
            lambda th: tk.NonlinearSystem(lambda x, k: x, lambda x, k: x, [[0.1]], [[th[0]]], [0.0], [[1.0]]),
            y,
            theta0=[-1.0],
            censoring=CENS,
            progress=False,
        )
    with pytest.raises(tk.ValidationError, match="channel"):
        tk.fit(build, y, theta0=[0.5, 1.0], censoring=CENS, channel=CENS, progress=False)
    with pytest.raises(tk.ValidationError, match="method"):
        tk.fit(build, y, theta0=[0.5, 1.0], censoring=CENS, method="em", progress=False)
    res = tk.fit(build, y, theta0=[0.5, 1.0], censoring=CENS, progress=False, maxiter=3, standard_errors=False)
    back = tk.load_fit(res.save(tmp_path / "fit.json"))
    assert back.params == res.params and back.model.kind == "nonlinear"
    with pytest.raises(tk.ValidationError, match="rebuild"):
        back.system()


def test_inputs_reach_the_likelihood():
    # f(x, k, u) with u given equals the model with the inputs folded into f: the same objective, the same fit
    U = np.random.default_rng(2).normal(size=(40, 1))

    def forced(th):
        return tk.NonlinearSystem(
            lambda x, k, u: th[0] * np.tanh(x) + u, lambda x, k: x, [[0.2]], [[0.1]], [0.0], [[1.0]], inputs=1
        )

    def folded(th):
        return tk.NonlinearSystem(
            lambda x, k: th[0] * np.tanh(x) + U[k], lambda x, k: x, [[0.2]], [[0.1]], [0.0], [[1.0]]
        )

    y = tk.simulate(forced([0.8]), 40, 1, channel=CENS, inputs=U, seed=4).y[0]
    a = tk.fit(forced, y, u=U, theta0=[0.5], censoring=CENS, progress=False)
    b = tk.fit(folded, y, theta0=[0.5], censoring=CENS, progress=False)
    assert a.loglik == pytest.approx(b.loglik, abs=1e-9)
    np.testing.assert_allclose(a.theta, b.theta, rtol=0, atol=1e-8)


# the parametric-bootstrap bias correction ------------------------------------------------------------------------
def iid_model(theta):  # x_k = w_{k-1} ~ N(0, theta), y_k = x_k + v_k: y i.i.d. N(0, theta + 0.1), the Kalman likelihood
    return tk.LinearSystem(A=[[0.0]], C=[[1.0]], Q=[[theta[0]]], R=[[0.1]], x0=[0.0], P0=[[1.0]])


def test_bootstrap_correction_of_an_unbiased_estimate_is_its_monte_carlo_noise():
    # oracle, on a linear model: the fit is theta_hat = mean(y^2) - 0.1 (unbiased); each bootstrap refit is the
    # same function of n readings i.i.d. N(0, theta_hat + 0.1), so the estimated bias mean(theta*) - theta_hat is
    # (theta_hat + 0.1) (chi2_{nB} / (nB) - 1): mean 0, sd (theta_hat + 0.1) sqrt(2 / (nB)); the refits' spread is
    # (theta_hat + 0.1) sqrt(2 / n) within the chi2_{B-1} band. Both checked two-sided at 1e-4.
    from scipy.stats import chi2

    n, B = 200, 20
    y = tk.simulate(iid_model([1.0]), n, 1, seed=5).y[0]
    plain = tk.fit(iid_model, y, theta0=[0.5], progress=False)
    bc = tk.fit(iid_model, y, theta0=[0.5], progress=False, bias_correction="bootstrap", bootstrap_samples=B, seed=3)
    s2 = float(np.mean(y**2))
    assert plain.theta[0] == pytest.approx(s2 - 0.1, abs=1e-2 * plain.se["theta0"])
    info = bc.extra["bias_correction"]
    assert info["uncorrected"]["theta0"] == plain.theta[0] and info["used"] == B and info["samples"] == B
    bias = info["bias"]["theta0"]
    assert bc.theta[0] == pytest.approx(plain.theta[0] - bias, abs=1e-12)
    assert abs(bias) < 3.9 * s2 * np.sqrt(2.0 / (n * B)), bias
    lo, hi = np.sqrt(chi2.ppf([5e-5, 1 - 5e-5], B - 1) / (B - 1))
    assert lo < info["bootstrap_sd"]["theta0"] / (s2 * np.sqrt(2.0 / n)) < hi
    assert info["bias_se"]["theta0"] == pytest.approx(info["bootstrap_sd"]["theta0"] / np.sqrt(B))
    # the standard errors and the likelihood stay those of the maximum; the fitted system is the corrected one
    assert bc.se == plain.se and bc.loglik == plain.loglik
    assert bc.system().process_cov(1)[0, 0] == pytest.approx(bc.theta[0], abs=1e-12)


def test_bootstrap_correction_is_seeded_and_keeps_missing_readings_and_records(tmp_path):
    # two records with a missing reading: every bootstrap data set has the data's shape and its NaN
    d = tk.simulate(build(TRUTH), 20, 2, channel=CENS, seed=8)
    y = d.y.copy()
    y[0, 3, 0] = np.nan
    from tobitkf.inference._bias_correction import simulated_like

    ys = simulated_like(build(TRUTH), y, channel=CENS, u=None, seed=np.random.SeedSequence(1))
    assert ys.shape == y.shape and np.isnan(ys[0, 3, 0]) and np.isnan(ys).sum() == 1
    assert np.nanmin(ys) == -0.3  # drawn through the channel
    kw = dict(theta0=[0.5, 0.9], censoring=CENS, progress=False, bias_correction="bootstrap", bootstrap_samples=2)
    a, b, c = (tk.fit(build, y, seed=s, **kw) for s in (4, 4, 5))
    np.testing.assert_array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)
    back = tk.load_fit(a.save(tmp_path / "fit.json"))  # the correction's record is saved with the fit
    np.testing.assert_array_equal(back.theta, a.theta)
    assert back.extra["bias_correction"] == a.extra["bias_correction"]


def test_bootstrap_correction_of_a_nonlinear_map_keeps_the_map():
    y = tk.simulate(build(TRUTH), 40, 2, channel=CENS, seed=2).y
    res = tk.fit(
        build, y, theta0=[0.5, 0.9], censoring=CENS, progress=False, bias_correction="bootstrap", bootstrap_samples=2
    )
    assert res.extra["bias_correction"]["used"] == 2 and isinstance(res.system(), tk.NonlinearSystem)
    x = np.array([[0.7]])
    assert res.system().measurement_map(x, 1)[0, 0] == pytest.approx(res.theta[1] * 0.7 + 0.1 * 0.49, abs=1e-12)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"bias_correction": "jackknife"}, "bias_correction"),
        ({"seed": 1}, "bias_correction"),
        ({"bootstrap_samples": 10}, "bias_correction"),
        ({"bias_correction": "bootstrap", "bootstrap_samples": 1}, "bootstrap_samples"),
        ({"bias_correction": "bootstrap", "bootstrap_samples": 2.0}, "bootstrap_samples"),
        ({"bias_correction": "bootstrap", "bootstrap_samples": True}, "bootstrap_samples"),
        ({"bias_correction": "bootstrap", "seed": -1}, "seed"),
        ({"bias_correction": "bootstrap", "seed": "a"}, "seed"),
        ({"bias_correction": "bootstrap", "censored": np.zeros(30, bool)}, "censored indicator"),
    ],
)
def test_bootstrap_correction_refusals(kw, match):
    y = tk.simulate(build(TRUTH), 30, 1, channel=CENS, seed=3).y[0]
    with pytest.raises(tk.ValidationError, match=match):
        tk.fit(build, y, theta0=[0.5, 1.0], censoring=CENS, progress=False, **kw)


def test_bootstrap_correction_refuses_a_model_without_a_parameter_map():
    d = tk.simulate(tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[0.3]], R=[[0.2]], x0=[0.0], P0=[[1.0]]), 30, 1, seed=1)
    with pytest.raises(tk.ValidationError, match="bias_correction"):
        tk.fit(tk.CensoredAR(1), d.y[0], bias_correction="bootstrap", progress=False)
