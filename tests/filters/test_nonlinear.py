"""ExtendedKalmanFilter and UnscentedKalmanFilter: filterpy, the Kalman filter, exact rules, the online API."""

from __future__ import annotations

import math

import numpy as np
import pytest

import tobitkf as tk

from .test_nonlinear_model import DT, P0, X0, F, H, Q, R, f, h, pendulum

RULES = [
    {"rule": "unscented"},
    {"rule": "unscented", "alpha": 0.5, "beta": 2.0, "kappa": 1.0},
    {"rule": "cubature"},
    {"rule": "gauss_hermite", "order": 3},
]


@pytest.fixture(scope="module")
def record():
    return tk.simulate(pendulum(), 40, 3, seed=3).y


def test_ekf_equals_filterpy(record):
    FilterpyEKF = pytest.importorskip("filterpy.kalman").ExtendedKalmanFilter

    # filterpy's EKF with the same f (its predict_x), the same Jacobians, its Joseph update
    class EKF(FilterpyEKF):
        def predict_x(self, u=0):
            self.x = f(self.x, 0)

    sys_ = pendulum(F=F, H=H)
    for form in ("standard", "joseph"):
        ours = tk.ExtendedKalmanFilter(sys_, covariance_update=form).filter(record[0])
        ref = EKF(2, 2)
        ref.x, ref.P, ref.Q, ref.R = X0.copy(), P0.copy(), Q, R
        means, covs = [], []
        for z in record[0]:
            ref.F = F(ref.x, 0)
            ref.predict()
            ref.update(z, HJacobian=lambda x: H(x, 0), Hx=lambda x: h(x, 0))
            means.append(ref.x.copy())
            covs.append(ref.P.copy())
        np.testing.assert_allclose(ours.mean, np.array(means), rtol=0, atol=1e-10)
        np.testing.assert_allclose(ours.cov, np.array(covs), rtol=0, atol=1e-10)


@pytest.mark.parametrize("abk", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (0.8, 0.0, -1.0)])
def test_ukf_equals_filterpy(record, abk):
    fk = pytest.importorskip("filterpy.kalman")
    FilterpyUKF, MerweScaledSigmaPoints = fk.UnscentedKalmanFilter, fk.MerweScaledSigmaPoints
    a, b, kap = abk
    ours = tk.UnscentedKalmanFilter(pendulum(), alpha=a, beta=b, kappa=kap).filter(record[1])
    ref = FilterpyUKF(
        2, 2, DT, hx=lambda x: h(x, 0), fx=lambda x, dt: f(x, 0), points=MerweScaledSigmaPoints(2, a, b, kap)
    )
    ref.x, ref.P, ref.Q, ref.R = X0.copy(), P0.copy(), Q, R
    means, covs, pm = [], [], []
    for z in record[1]:
        ref.predict()
        pm.append(ref.x.copy())
        ref.update(z)
        means.append(ref.x.copy())
        covs.append(ref.P.copy())
    np.testing.assert_allclose(ours.mean, np.array(means), rtol=0, atol=1e-10)
    np.testing.assert_allclose(ours.cov, np.array(covs), rtol=0, atol=1e-10)
    np.testing.assert_allclose(ours.pred_mean, np.array(pm), rtol=0, atol=1e-10)


def _linear_pair():
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.5], [0.0, 1.0]])
    Qd, Rd = np.array([[0.1, 0.02], [0.02, 0.05]]), np.diag([0.3, 0.2])
    x0, P0_ = np.array([0.5, -0.2]), np.array([[1.0, 0.3], [0.3, 0.8]])
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, Qd, Rd, x0, P0_)
    lin = tk.LinearSystem(A=A, C=C, Q=Qd, R=Rd, x0=x0, P0=P0_)
    return nl, lin


@pytest.mark.parametrize("opts", RULES, ids=lambda o: "-".join(str(v) for v in o.values()))
def test_sigma_point_filters_on_a_linear_model_are_the_kalman_filter(opts):
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 25, 2, seed=8).y
    y[0, 3, 1] = np.nan  # a lost reading: the other channel still updates
    want = tk.KalmanFilter(lin, backend="numpy").filter(y)
    for got in (tk.UnscentedKalmanFilter(nl, **opts).filter(y), tk.ExtendedKalmanFilter(nl).filter(y)):
        np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-9)


def _normal_moment(mu: float, s: float, d: int) -> float:
    """E[X^d], X ~ N(mu, s^2): sum over even j of C(d, j) mu^(d-j) s^j (j-1)!!."""
    return sum(math.comb(d, j) * mu ** (d - j) * s**j * math.prod(range(j - 1, 0, -2)) for j in range(0, d + 1, 2))


@pytest.mark.parametrize(
    "opts,degree",
    [
        ({"rule": "unscented"}, 3),
        ({"rule": "unscented", "alpha": 0.3, "beta": 2.0, "kappa": 1.0}, 3),
        ({"rule": "cubature"}, 3),
        ({"rule": "gauss_hermite", "order": 2}, 3),
        ({"rule": "gauss_hermite", "order": 3}, 5),
        ({"rule": "gauss_hermite", "order": 5}, 9),
    ],
)
def test_rules_integrate_polynomials_of_their_degree_exactly(opts, degree):
    # the polynomials of degree d are spanned by the powers (a^T x)^d of linear forms, and a^T x ~ N(a^T m, a^T P a):
    # the rule's mean of (a^T x)^j must equal the analytic normal moment for every j <= degree and direction a
    rule = tk.SigmaPoints(**opts)
    rng = np.random.default_rng(9)
    n = 3
    m = rng.normal(size=n)
    G = rng.normal(size=(n, n))
    P = G @ G.T + 0.5 * np.eye(n)
    X = rule.points(m[None], P[None])[0]
    _, wm, _ = rule.unit(n)
    for a in rng.normal(size=(6, n)):
        z = X @ a
        mu, s = float(a @ m), math.sqrt(a @ P @ a)
        for d in range(degree + 1):
            assert np.dot(wm, z**d) == pytest.approx(_normal_moment(mu, s, d), rel=1e-10, abs=1e-10)
    # one degree more is not integrated in general (the rule's degree is sharp): a direction where it fails
    fails = False
    for a in rng.normal(size=(6, n)):
        z = X @ a
        mu, s = float(a @ m), math.sqrt(a @ P @ a)
        fails |= abs(np.dot(wm, z ** (degree + 1)) - _normal_moment(mu, s, degree + 1)) > 1e-6
    assert fails


def test_gauss_hermite_point_count_and_weights():
    rule = tk.SigmaPoints("gauss_hermite", order=4)
    xi, wm, wc = rule.unit(2)
    assert xi.shape == (16, 2) and wm.sum() == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_array_equal(wm, wc)


@pytest.mark.parametrize(
    "make",
    [
        lambda s: tk.ExtendedKalmanFilter(s),
        lambda s: tk.UnscentedKalmanFilter(s),
        lambda s: tk.UnscentedKalmanFilter(s, rule="gauss_hermite", order=2),
    ],
    ids=["ekf", "ukf", "ghkf"],
)
def test_step_loop_equals_filter_and_batched_equals_per_run(make, record):
    est = make(pendulum())
    y = record.copy()
    y[1, 5, 0] = np.nan
    y[2, 6] = np.nan  # a step with no reading at all: the prediction
    whole = est.filter(y)
    state = est.init(batch_shape=(3,))
    for i in range(y.shape[1]):
        state = est.step(state, y[:, i])
        np.testing.assert_allclose(state.mean, whole.mean[:, i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(state.cov, whole.cov[:, i], rtol=0, atol=1e-12)
    for r in range(3):
        one = est.filter(y[r])
        np.testing.assert_allclose(one.mean, whole.mean[r], rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.cov, whole.cov[r], rtol=0, atol=1e-12)
    # a missing step is the prediction alone
    np.testing.assert_array_equal(whole.mean[2, 6], whole.pred_mean[2, 6])
    # predict + update = step; outputs= and continuation from a final state
    st = est.init()
    a = est.step(est.step(st, y[0, 0]), y[0, 1])
    b = est.update(est.predict(est.step(st, y[0, 0])), y[0, 1])
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-14)
    first = est.filter(y[0, :10], outputs="last")
    assert first.mean is None
    rest = est.filter(y[0, 10:], state=first.final)
    np.testing.assert_allclose(rest.mean, whole.mean[0, 10:], rtol=0, atol=1e-12)


def test_refusals():
    with pytest.raises(tk.ValidationError, match="system"):
        tk.UnscentedKalmanFilter(tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]]))
    with pytest.raises(tk.ValidationError, match="rule"):
        tk.UnscentedKalmanFilter(pendulum(), rule="simpson")
    with pytest.raises(tk.ValidationError, match="kappa"):
        tk.UnscentedKalmanFilter(pendulum(), kappa=-2.0)
    with pytest.raises(tk.ValidationError, match="covariance_update"):
        tk.ExtendedKalmanFilter(pendulum(), covariance_update="information")
    with pytest.raises(tk.ValidationError, match="covariance_update"):
        tk.UnscentedKalmanFilter(pendulum(), covariance_update="joseph")
    with pytest.raises(tk.ShapeError):
        tk.ExtendedKalmanFilter(pendulum()).filter(np.zeros((5, 3)))


@pytest.mark.parametrize("opts", [None, {"rule": "unscented"}, {"rule": "gauss_hermite", "order": 2}])
def test_smoothers_on_a_linear_model_are_the_kalman_smoother(opts):
    nl, lin = _linear_pair()
    y = tk.simulate(lin, 20, 2, seed=17).y
    y[0, 5] = np.nan
    want = tk.KalmanFilter(lin, backend="numpy").smooth(y)
    est = tk.ExtendedKalmanFilter(nl) if opts is None else tk.UnscentedKalmanFilter(nl, **opts)
    got = est.smooth(y)
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.cov, np.broadcast_to(want.cov, got.cov.shape), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.times, want.times)


def test_smoother_last_row_is_the_filter_and_smoothing_helps():
    # the smoothed estimate at T is the filtered one; on the pendulum the smoothed RMSE over the interior is
    # below the filtered one (the smoother uses the readings after k as well; 20 runs x 40 steps)
    sys_ = pendulum()
    d = tk.simulate(sys_, 40, 20, seed=18)
    est = tk.UnscentedKalmanFilter(sys_)
    sm, fl = est.smooth(d.y), est.filter(d.y)
    np.testing.assert_allclose(sm.mean[:, -1], fl.mean[:, -1], rtol=0, atol=1e-14)
    err_s = np.sqrt(((sm.mean - d.x[:, 1:]) ** 2).sum(-1)[:, :-5].mean())
    err_f = np.sqrt(((fl.mean - d.x[:, 1:]) ** 2).sum(-1)[:, :-5].mean())
    assert err_s < err_f
