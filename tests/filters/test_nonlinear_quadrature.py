"""The nonlinear assumed-density filter's quadrature update: one step against brute-force quadrature of the exact
posterior (scalar and two states, measured and censored readings), the linear reduction, step = filter, the fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import multivariate_normal, norm

import tobitkf as tk

LIMIT = 0.4


def _h1(x, k):
    return x + 0.3 * x**2


def _scalar(R=0.3, P0=0.8, x0=0.2, curve=0.3):
    # f the identity and Q = 0: the prediction of the first step is the prior itself
    return tk.NonlinearSystem(lambda x, k: x, lambda x, k: x + curve * x**2, Q=[[0.0]], R=[[R]], x0=[x0], P0=[[P0]])


def _lik(y, hx, sd, lower):
    """p(y | x) of one reading: the density at h(x), or the mass below the limit for a reading at it."""
    return norm.cdf((lower - hx) / sd) if y <= lower else norm.pdf(y, hx, sd)


def _scalar_oracle(y, R, P0, x0, lower, curve):
    sd, s0 = np.sqrt(R), np.sqrt(P0)

    def w(x):
        return norm.pdf(x, x0, s0) * _lik(y, x + curve * x**2, sd, lower)

    a, b = x0 - 12 * s0, x0 + 12 * s0
    opts = dict(epsabs=0.0, epsrel=1e-12, limit=400)
    Z = integrate.quad(w, a, b, **opts)[0]
    m = integrate.quad(lambda x: x * w(x), a, b, **opts)[0] / Z
    v = integrate.quad(lambda x: (x - m) ** 2 * w(x), a, b, **opts)[0] / Z
    return m, v, np.log(Z)


CASES = [(0.3, 0.8, 0.2), (0.1, 0.5, -0.4)]  # R, P0, x0: the second reading 2.4 prior sd from the prediction


@pytest.mark.parametrize("y", [1.3, LIMIT])  # measured, censored at the limit
@pytest.mark.parametrize(("R", "P0", "x0"), CASES)
def test_scalar_step_is_the_projection_of_the_exact_posterior(y, R, P0, x0):
    # h = x + 0.1 x^2: its second branch (x = -10 - root) lies beyond 13 prior sd, so the posterior has one mode.
    # The default (40 nodes, the second quadrature re-centred on the first one's Gaussian) converges to rounding;
    # one quadrature over the prediction is off by up to 1e-4 where the reading lies in the prediction's tail
    cens = tk.Censoring(lower=LIMIT)
    m, v, lz = _scalar_oracle(y, R, P0, x0, LIMIT, 0.1)
    out = tk.NonlinearAssumedDensityFilter(_scalar(R, P0, x0, 0.1), cens, update="quadrature").filter([[y]])
    assert out.mean[0, 0] == pytest.approx(m, abs=1e-8)
    assert out.cov[0, 0, 0] == pytest.approx(v, rel=1e-7)
    assert out.extras["log_likelihood"][0] == pytest.approx(lz, abs=1e-8)
    one = tk.NonlinearAssumedDensityFilter(_scalar(R, P0, x0, 0.1), cens, update="quadrature", iterations=1)
    assert one.filter([[y]]).mean[0, 0] == pytest.approx(m, abs=2e-4)
    # the linearised update is a different, approximate projection of the same posterior
    lin = tk.NonlinearAssumedDensityFilter(_scalar(R, P0, x0, 0.1), cens).filter([[y]])
    assert abs(lin.mean[0, 0] - m) > 1e-4


def test_a_small_second_mode_is_what_the_rule_misses():
    # h = x + 0.3 x^2 read at 1.3: a second mode near x = -4.2, 4.9 prior sd out, carries about 1e-5 of the mass;
    # 40 nodes over the prediction resolve it to 1e-4 of the mean (one quadrature or two), 10 nodes do not
    m, v, lz = _scalar_oracle(1.3, 0.3, 0.8, 0.2, LIMIT, 0.3)
    errs = {}
    for q, it in ((10, 1), (40, 1), (10, 2), (40, 2)):
        est = tk.NonlinearAssumedDensityFilter(
            _scalar(), tk.Censoring(lower=LIMIT), update="quadrature", quadrature=q, iterations=it
        )
        errs[q, it] = abs(est.filter([[1.3]]).mean[0, 0] - m)
    assert errs[40, 1] < 1e-4 and errs[40, 2] < 1e-4 and errs[10, 1] > 0.05
    assert errs[10, 2] < 1e-3  # the re-centred second quadrature rescues the coarse rule


X0_2 = np.array([0.3, -0.2])
P0_2 = np.array([[0.6, 0.2], [0.2, 0.4]])
R_2 = np.array([0.25, 0.2])
LOWER_2 = np.array([-np.inf, 0.1])


def _h2(x, k):
    x = np.asarray(x)
    return np.stack([x[..., 0] + 0.4 * x[..., 1] ** 2, np.sin(x[..., 1]) + 0.5 * x[..., 0] * x[..., 1]], axis=-1)


def _two_state():
    return tk.NonlinearSystem(lambda x, k: x, _h2, Q=np.zeros((2, 2)), R=np.diag(R_2), x0=X0_2, P0=P0_2)


def _two_state_oracle(y):
    """Brute force: composite Simpson's rule (scipy.integrate.simpson) on a 1201 x 1201 grid over +-9 prior sd."""
    sd = np.sqrt(R_2)
    s = np.sqrt(np.diag(P0_2))
    a = np.linspace(X0_2[0] - 9 * s[0], X0_2[0] + 9 * s[0], 1201)
    b = np.linspace(X0_2[1] - 9 * s[1], X0_2[1] + 9 * s[1], 1201)
    A, B = np.meshgrid(a, b, indexing="ij")
    X = np.stack([A, B], axis=-1)
    w = multivariate_normal(X0_2, P0_2).pdf(X)
    hx = _h2(X, 1)
    for l in range(2):
        if not np.isnan(y[l]):
            w = w * _lik(y[l], hx[..., l], sd[l], LOWER_2[l])

    def moment(g):
        return integrate.simpson(integrate.simpson(g * w, x=b, axis=1), x=a)

    Z = moment(1.0)
    m = np.array([moment(A), moment(B)]) / Z
    dA, dB = A - m[0], B - m[1]
    c = np.array([[moment(dA * dA), moment(dA * dB)], [moment(dA * dB), moment(dB * dB)]]) / Z
    return m, c, np.log(Z)


@pytest.mark.parametrize("y", [[0.9, 0.6], [0.2, 0.1], [np.nan, 0.1]])  # both measured; one censored; one missing
def test_two_state_step_is_the_projection_of_the_exact_posterior(y):
    y = np.array(y)
    cens = tk.Censoring(lower=LOWER_2)
    m, c, lz = _two_state_oracle(y)
    for form in ("standard", "square_root"):
        est = tk.NonlinearAssumedDensityFilter(_two_state(), cens, update="quadrature", covariance_update=form)
        out = est.filter(y[None])
        np.testing.assert_allclose(out.mean[0], m, rtol=0, atol=1e-7)
        np.testing.assert_allclose(out.cov[0], c, rtol=0, atol=1e-7)
        assert out.extras["log_likelihood"][0] == pytest.approx(lz, abs=1e-7)


def _linear_pair(lower):
    A, C = 0.9, 1.3
    nl = tk.NonlinearSystem(lambda x, k: A * x, lambda x, k: C * x, Q=[[0.2]], R=[[0.5]], x0=[0.1], P0=[[1.0]])
    lin = tk.LinearSystem(A=[[A]], C=[[C]], Q=[[0.2]], R=[[0.5]], x0=[0.1], P0=[[1.0]])
    return nl, lin, tk.Censoring(lower=lower)


@pytest.mark.parametrize("form", ["standard", "square_root"])
def test_a_linear_h_is_the_linear_assumed_density_filter(form):
    # one channel, h linear: the exact posterior's projection is the assumed-density update itself
    nl, lin, cens = _linear_pair(0.0)
    y = tk.simulate(lin, 25, 4, censoring=cens, seed=3).y
    y[1, 4, 0] = np.nan
    assert (y == 0.0).mean() > 0.2
    a = tk.NonlinearAssumedDensityFilter(nl, cens, update="quadrature", covariance_update=form).filter(y)
    b = tk.AssumedDensityFilter(lin, cens, backend="numpy").filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, np.broadcast_to(b.cov, a.cov.shape), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=0, atol=1e-10)


def test_two_measured_linear_channels_are_the_kalman_filter():
    # both channels at once: with Gaussian readings the exact posterior is the Kalman filter's
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.5], [0.0, 1.0]])
    kw = dict(Q=0.1 * np.eye(2), R=np.diag([0.3, 0.2]), x0=[0.5, -0.2], P0=np.eye(2))
    lin = tk.LinearSystem(A=A, C=C, **kw)
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, **kw)
    y = tk.simulate(lin, 12, 3, seed=1).y
    a = tk.NonlinearAssumedDensityFilter(nl, tk.Censoring(), update="quadrature").filter(y)
    b = tk.KalmanFilter(lin, backend="numpy").filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, np.broadcast_to(b.cov, a.cov.shape), rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        a.extras["log_likelihood"].sum(-1), tk.KalmanFilter(lin, backend="numpy").log_likelihood(y), atol=1e-9
    )


def test_step_loop_and_single_runs_equal_the_batched_filter():
    sys_ = tk.NonlinearSystem(lambda x, k: 0.8 * x + 0.5 * np.sin(x), _h1, Q=[[0.3]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    cens = tk.Censoring(lower=-0.3)
    y = tk.simulate(sys_, 15, 3, channel=cens, seed=2).y
    y[0, 2, 0] = np.nan
    for form in ("standard", "square_root"):
        est = tk.NonlinearAssumedDensityFilter(sys_, cens, update="quadrature", quadrature=20, covariance_update=form)
        full = est.filter(y)
        state = est.init(batch_shape=(3,))
        for t in range(15):
            split = est.update(est.predict(state), y[:, t])  # predict, then update: the same step
            state = est.step(state, y[:, t])
            np.testing.assert_allclose(state.mean, full.mean[:, t], rtol=0, atol=1e-12)
            np.testing.assert_allclose(state.cov, full.cov[:, t], rtol=0, atol=1e-12)
            np.testing.assert_allclose(split.mean, state.mean, rtol=0, atol=1e-12)
        for r in range(3):
            one = est.filter(y[r])
            np.testing.assert_allclose(one.mean, full.mean[r], rtol=0, atol=1e-12)
        # the missing reading: the prediction kept, no likelihood term
        np.testing.assert_array_equal(full.mean[0, 2], full.pred_mean[0, 2])
        assert full.extras["log_likelihood"][0, 2] == 0.0
    lin = tk.NonlinearAssumedDensityFilter(sys_, cens, update="quadrature", quadrature=20)
    sq = tk.NonlinearAssumedDensityFilter(
        sys_, cens, update="quadrature", quadrature=20, covariance_update="square_root"
    )
    np.testing.assert_allclose(lin.filter(y).cov, sq.filter(y).cov, rtol=1e-10, atol=1e-14)


def test_more_nodes_converge_and_the_cubature_rule_is_a_rough_choice():
    cens = tk.Censoring(lower=LIMIT)
    m, v, lz = _scalar_oracle(1.3, 0.1, 0.5, -0.4, LIMIT, 0.1)
    errs = []
    for q in (4, 8, 16, 32):
        est = tk.NonlinearAssumedDensityFilter(_scalar(0.1, 0.5, -0.4, 0.1), cens, update="quadrature", quadrature=q)
        errs.append(abs(est.filter([[1.3]]).mean[0, 0] - m))
    assert errs[-1] < 1e-8 and errs[0] > 1e3 * errs[-1]
    cub = tk.NonlinearAssumedDensityFilter(
        _scalar(0.1, 0.5, -0.4, 0.1), cens, update="quadrature", quadrature=tk.SigmaPoints("cubature")
    )
    assert abs(cub.filter([[1.3]]).mean[0, 0] - m) > 1e2 * errs[-1]


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"update": "exact"}, "update"),
        ({"update": "quadrature", "iterations": 0}, "iterations"),
        ({"quadrature": 10}, "quadrature"),
        ({"update": "quadrature", "quadrature": 1}, "quadrature"),
        ({"update": "quadrature", "quadrature": 2.5}, "quadrature"),
        ({"update": "quadrature", "quadrature": tk.SigmaPoints("unscented", alpha=0.5)}, "negative weight"),
    ],
)
def test_refusals(kw, match):
    with pytest.raises(tk.ValidationError, match=match):
        tk.NonlinearAssumedDensityFilter(_scalar(), tk.Censoring(lower=LIMIT), **kw)


def test_refuses_a_noiseless_reading_and_too_many_states_without_a_rule():
    noiseless = tk.NonlinearSystem(lambda x, k: x, _h1, Q=[[0.1]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="positive"):
        tk.NonlinearAssumedDensityFilter(noiseless, tk.Censoring(lower=0.0), update="quadrature")
    n = 13
    big = tk.NonlinearSystem(
        lambda x, k: x, lambda x, k: x[..., :1], Q=np.eye(n), R=[[1.0]], x0=np.zeros(n), P0=np.eye(n)
    )
    with pytest.raises(tk.ValidationError, match="pass a rule"):
        tk.NonlinearAssumedDensityFilter(big, tk.Censoring(lower=0.0), update="quadrature")
    est = tk.NonlinearAssumedDensityFilter(
        big, tk.Censoring(lower=0.0), update="quadrature", quadrature=tk.SigmaPoints("cubature")
    )
    assert np.isfinite(est.filter([[0.5]]).mean).all()
    with pytest.raises(tk.ValidationError, match="iterations"):
        tk.NonlinearAssumedDensityFilter(_scalar(), tk.Censoring(lower=0.0), update="quadrature").smooth(
            [[1.0]], iterations=2
        )


def test_fit_maximises_the_quadrature_evidence_and_keeps_the_option(tmp_path):
    from tests.inference.test_nonlinear_fit import CENS, TRUTH, build

    y = tk.simulate(build(TRUTH), 60, 3, channel=CENS, seed=4).y
    res = tk.fit(build, y, theta0=[0.5, 0.9], censoring=CENS, progress=False, update="quadrature")
    assert res.converged and res.model.update == "quadrature" and res.model.iterations == 2
    back = tk.load_fit(res.save(tmp_path / "fit.json"))  # the update is saved with the fit
    assert back.model.update == "quadrature" and back.model.iterations == 2
    ll = tk.NonlinearAssumedDensityFilter(build(res.theta), CENS, update="quadrature").log_likelihood(y).sum()
    assert res.loglik == pytest.approx(ll, abs=1e-9)
    # the search stopped within 1e-3 standard errors of the quadrature evidence's maximum: a step of 0.05 of a
    # standard error either way lowers it (by about 0.05**2 / 2 against a slope of at most 1e-3 * 0.05)
    for i in range(2):
        for s in (-0.05, 0.05):
            th = res.theta.copy()
            th[i] += s * res.se[f"theta{i}"]
            est = tk.NonlinearAssumedDensityFilter(build(th), CENS, update="quadrature")
            assert est.log_likelihood(y).sum() < ll


@pytest.mark.heavy  # three fits (tens of seconds on a loaded machine)
def test_the_bootstrap_bias_correction_refits_with_the_quadrature_update():
    from tests.inference.test_nonlinear_fit import CENS, TRUTH, build

    y = tk.simulate(build(TRUTH), 60, 3, channel=CENS, seed=4).y
    kw = dict(theta0=[0.5, 0.9], censoring=CENS, progress=False, update="quadrature")
    res = tk.fit(build, y, **kw)
    bc = tk.fit(build, y, **kw, bias_correction="bootstrap", bootstrap_samples=2)
    info = bc.extra["bias_correction"]
    assert info["used"] == 2 and bc.model.update == "quadrature"
    np.testing.assert_allclose(list(info["uncorrected"].values()), res.theta, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bc.theta, res.theta - np.array(list(info["bias"].values())), rtol=0, atol=1e-12)


def test_a_filter_with_its_own_reading_model_refuses_the_quadrature_update():
    sat = tk.RandomSaturation(mu=[0.2], nu=[0.5], level=[1.0])
    with pytest.raises(tk.ValidationError, match="update"):
        tk.SaturationNonlinearAssumedDensityFilter(_scalar(), sat, update="quadrature")
