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
