"""Closed-loop LQG with KF / TKF / moving-limit observers (spec 001b T4, T12–T15)."""

import numpy as np
import pytest
from scipy.special import ndtr, ndtri

from tobitkf import Censoring, LinearSystem
from tobitkf._validation import ShapeError, ValidationError
from tobitkf.control.closed_loop import quadratic_cost, simulate_closed_loop
from tobitkf.control.lqg import discretize, dlqr, tobit_dlqe
from tobitkf.control.plants import dc_motor_position, dc_motor_speed

DT = 0.01


def motor(model):
    p = model()
    Ad, Bd, Qd = discretize(p.A, p.B, p.G, p.W, DT)
    n = Ad.shape[0]
    plant = LinearSystem(A=Ad, C=p.C, Q=Qd, R=p.V, x0=np.zeros(n), P0=1e-6 * np.eye(n), Bu=Bd)
    Qlqr = np.zeros((n, n))
    Qlqr[0, 0] = 100.0
    K = dlqr(Ad, Bd, Qlqr, [[1e-6]]).gain
    return plant, K


@pytest.fixture(scope="module")
def position():
    return motor(dc_motor_position)


@pytest.fixture(scope="module")
def speed():
    return motor(dc_motor_speed)


def step_reference(steps=3000, start=400):
    r = np.zeros(steps)
    r[start:] = 1.0
    return r


def test_t4_infinite_limit_kf_and_tkf_loops_are_identical(position):
    plant, K = position
    r = step_reference(800, 100)
    a = simulate_closed_loop(plant, K, 800, 3, observer="kf", censoring=Censoring(upper=np.inf), reference=r, seed=5)
    b = simulate_closed_loop(plant, K, 800, 3, observer="tkf", censoring=Censoring(upper=np.inf), reference=r, seed=5)
    assert np.max(np.abs(a.x - b.x)) <= 1e-12 * max(1.0, np.abs(a.x).max())
    assert np.max(np.abs(a.estimate - b.estimate)) <= 1e-12 * max(1.0, np.abs(a.estimate).max())
    assert np.all(b.p_uncensored == 1.0)


@pytest.mark.parametrize("T, P11", [(1.0, 4.329e-4), (0.95, 1.5405e-3)])
def test_t13_marginal_plant_setpoint_inside_censored_region(position, T, P11):
    plant, K = position
    r = step_reference()
    kf = simulate_closed_loop(plant, K, 3000, 5, observer="kf", censoring=Censoring(upper=T), reference=r, seed=1)
    tkf = simulate_closed_loop(plant, K, 3000, 5, observer="tkf", censoring=Censoring(upper=T), reference=r, seed=1)
    th_tkf = tkf.x[:, -1000:, 0].mean(axis=1)
    th_kf = kf.x[:, -1000:, 0].mean(axis=1)
    assert np.all(np.abs(th_tkf - 1.0) < 0.1)
    assert abs(th_kf.mean() - 1.0) > 1.0
    # the TKF covariance at the end against the modified DARE at Xi = Phi((T - r)/sigma) (6.21)
    p = dc_motor_position()
    pred = tobit_dlqe(
        plant.transition(0), None, p.C, plant.process_cov(0), V=[[0.05**2]], xi_uncensored=ndtr((T - 1.0) / 0.05)
    ).cov[0, 0]
    assert pred == pytest.approx(P11, rel=2e-3)
    assert tkf.cov[:, -1, 0, 0] == pytest.approx(pred, rel=0.02)
    assert not tkf.diverged.any()


@pytest.mark.parametrize("T", [0.0, -0.05])
def test_t14_stable_plant_tkf_bias_much_smaller_than_kf(speed, T):
    plant, K = speed
    kf = simulate_closed_loop(plant, K, 2000, 5, observer="kf", censoring=Censoring(upper=T), seed=3)
    tkf = simulate_closed_loop(plant, K, 2000, 5, observer="tkf", censoring=Censoring(upper=T), seed=3)
    m_kf = kf.x[:, 1000:, 0].mean(axis=1)
    m_tkf = tkf.x[:, 1000:, 0].mean(axis=1)
    assert np.all(np.abs(m_tkf) < 0.2 * np.abs(m_kf))
    assert np.all(m_kf > 0)  # the KF's bias toward the limit drives theta-dot up (Fig 6.1)


def test_t12_moving_limit_gamma_is_xi_and_covariance_converges(position):
    plant, K = position
    xi = 0.95
    res = simulate_closed_loop(
        plant, K, 3000, 5, observer="tkf-moving", xi_uncensored=xi, reference=step_reference(), seed=2
    )
    assert np.all(res.p_uncensored == pytest.approx(xi, abs=1e-12))
    C, sigma = plant.measurement(1), 0.05
    g = tobit_dlqe(plant.transition(0), None, C, plant.process_cov(0), V=[[sigma**2]], xi_uncensored=xi)
    assert res.cov[0, -1] == pytest.approx(g.cov, rel=1e-3)
    assert g.cov[0, 0] == pytest.approx(3.0049e-4, rel=1e-3)
    # limit = C xbar + sigma Phi^-1(xi) at every step
    assert res.upper[..., 0] == pytest.approx(res.pred_estimate @ C[0] + sigma * ndtri(xi), abs=1e-12)
    # realized uncensored fraction ~ Phi(a sigma / sqrt(sigma^2 + C Pbar C')) (spec caveat 2, note 6)
    frac = np.mean(res.y_latent[:, 100:] < res.upper[:, 100:])
    s = np.sqrt(sigma**2 + (C @ g.prior_cov @ C.T)[0, 0])
    assert frac == pytest.approx(ndtr(ndtri(xi) * sigma / s), abs=0.005)
    assert frac < xi


def test_t15_unstable_plant_moving_limit_is_only_locally_stable():
    plant = LinearSystem(A=[[1.05]], C=[[1.0]], Q=[[0.01]], R=[[0.01]], x0=[0.0], P0=[[0.01]], Bu=[[1.0]])
    K = dlqr([[1.05]], [[1.0]], [[1.0]], [[1.0]]).gain
    ok = simulate_closed_loop(plant, K, 3000, 10, observer="tkf-moving", xi_uncensored=0.95, reference=1.0, seed=0)
    bad = simulate_closed_loop(plant, K, 3000, 10, observer="tkf-moving", xi_uncensored=0.5, reference=1.0, seed=0)
    assert not ok.diverged.any()
    assert bad.diverged.sum() >= 7
    assert np.all(np.isfinite(bad.x)) and np.all(np.isfinite(bad.estimate))
    assert np.all(bad.diverged_step[bad.diverged] > 0)
    # the linearisation A - L Xi C is Schur in both cases
    for xi in (0.5, 0.95):
        assert np.all(np.abs(tobit_dlqe([[1.05]], None, [[1.0]], [[0.01]], V=[[0.01]], xi_uncensored=xi).poles) < 1)


def test_quadratic_cost_and_reference():
    plant = LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[1e-12]], R=[[1e-4]], x0=[0.0], P0=[[0.0]], Bu=[[1.0]])
    K = np.array([[0.4]])
    res = simulate_closed_loop(plant, K, 200, 2, observer="kf", reference=1.0, seed=0)
    # unit DC gain: x_ss = 1; u_ss = (1 - 0.9) x_ss
    assert res.x[:, -1, 0] == pytest.approx(1.0, abs=1e-3)
    c = quadratic_cost(res, [[1.0]], [[1.0]], x_ref=[1.0], u_ref=[0.1], skip=100)
    assert c == pytest.approx(0.0, abs=1e-5)


def test_bad_input(position):
    plant, K = position
    with pytest.raises(ValidationError, match="observer: expected one of"):
        simulate_closed_loop(plant, K, 10, observer="ekf")
    with pytest.raises(ValidationError, match="xi_uncensored: observer 'tkf-moving' needs"):
        simulate_closed_loop(plant, K, 10, observer="tkf-moving")
    for xi in (0.0, 1.0):
        with pytest.raises(ValidationError, match=r"open interval \(0, 1\)"):
            simulate_closed_loop(plant, K, 10, observer="tkf-moving", xi_uncensored=xi)
    with pytest.raises(ValidationError, match="only used by the moving-limit"):
        simulate_closed_loop(plant, K, 10, observer="tkf", xi_uncensored=0.5)
    with pytest.raises(ValidationError, match="sets its own moving limit"):
        simulate_closed_loop(plant, K, 10, observer="tkf-moving", xi_uncensored=0.5, censoring=Censoring(upper=1.0))
    with pytest.raises(ShapeError, match=r"K: expected \(1, 3\)"):
        simulate_closed_loop(plant, K.T, 10)
    nou = LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(ValidationError, match="needs a control input matrix Bu"):
        simulate_closed_loop(nou, [[0.1]], 10)
    with pytest.raises(ValidationError, match="cannot track the reference"):
        zero = LinearSystem(
            A=np.diag([0.5, 0.8]), C=[[0.0, 1.0]], Q=np.eye(2), R=[[1.0]], x0=[0, 0], P0=np.eye(2), Bu=[[1.0], [0.0]]
        )
        simulate_closed_loop(zero, [[0.1, 0.0]], 10, reference=1.0)
    with pytest.raises(ShapeError, match="reference"):
        simulate_closed_loop(plant, K, 10, reference=np.ones((3, 2)))


def test_sstkf_loop_uses_the_modified_dare_gain_and_tracks(position):
    """§6.4: steady-state TKF-LQG at ED = 0.95 against the uncensored KF-LQG (Figs 6.10-6.13)."""
    from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter

    plant, K = position
    f = SteadyStateTobitKalmanFilter(plant, 0.95)
    g = tobit_dlqe(
        plant.transition(0), None, plant.measurement(1), plant.process_cov(0), V=[[0.05**2]], xi_uncensored=0.95
    )
    assert f.gain == pytest.approx(g.filter_gain, rel=1e-8)
    assert f.cov == pytest.approx(g.cov, rel=1e-8)
    r = step_reference()
    ss = simulate_closed_loop(plant, K, 3000, 4, observer="sstkf", xi_uncensored=0.95, reference=r, seed=4)
    kf = simulate_closed_loop(plant, K, 3000, 4, observer="kf", reference=r, seed=4)
    assert np.all(np.abs(ss.x[:, -1000:, 0].mean(axis=1) - 1.0) < 0.02)
    err_ss = np.sqrt(np.mean((ss.estimate[:, -1000:, 0] - ss.x[:, -1000:, 0]) ** 2))
    err_kf = np.sqrt(np.mean((kf.estimate[:, -1000:, 0] - kf.x[:, -1000:, 0]) ** 2))
    assert err_ss < 1.25 * err_kf  # "degradation is minimal" (spec [S]: 0.020 vs 0.020)
    assert np.all(ss.cov == f.cov)


def test_t15_with_the_steady_state_observer():
    plant = LinearSystem(A=[[1.05]], C=[[1.0]], Q=[[0.01]], R=[[0.01]], x0=[0.0], P0=[[0.01]], Bu=[[1.0]])
    K = dlqr([[1.05]], [[1.0]], [[1.0]], [[1.0]]).gain
    ok = simulate_closed_loop(plant, K, 2000, 10, observer="sstkf", xi_uncensored=0.8, reference=1.0, seed=0)
    bad = simulate_closed_loop(plant, K, 3000, 10, observer="sstkf", xi_uncensored=0.5, reference=1.0, seed=0)
    assert not ok.diverged.any() and bad.diverged.sum() >= 7


@pytest.mark.parametrize(
    "observer, kw",
    [
        ("kf", {"censoring": Censoring(upper=0.02)}),
        ("tkf", {"censoring": Censoring(upper=0.02)}),
        ("tkf-moving", {"xi_uncensored": 0.7}),
        ("sstkf", {"xi_uncensored": 0.7}),
    ],
)
def test_batched_equals_per_run(speed, observer, kw):
    plant, K = speed
    rng = np.random.default_rng(9)
    N, T = 3, 150
    noise = {
        "x0": rng.standard_normal((N, 2)) * 1e-3,
        "w": rng.standard_normal((N, T, 2)) @ np.linalg.cholesky(plant.process_cov(0) + 1e-30 * np.eye(2)).T,
        "v": rng.standard_normal((N, T, 1)) * 0.05,
    }
    r = np.full(T, 0.05)
    batch = simulate_closed_loop(plant, K, T, N, observer=observer, reference=r, noise=noise, **kw)
    for i in range(N):
        one = simulate_closed_loop(
            plant, K, T, 1, observer=observer, reference=r, noise={k: v[i : i + 1] for k, v in noise.items()}, **kw
        )
        assert one.x[0] == pytest.approx(batch.x[i], rel=1e-12, abs=1e-15)
        assert one.estimate[0] == pytest.approx(batch.estimate[i], rel=1e-12, abs=1e-15)
    with pytest.raises(ShapeError, match="noise"):
        simulate_closed_loop(plant, K, T, 2, observer=observer, reference=r, noise=noise, **kw)
    with pytest.raises(ValidationError, match="noise: expected keys"):
        simulate_closed_loop(plant, K, T, N, observer=observer, reference=r, noise={"x0": noise["x0"]}, **kw)
