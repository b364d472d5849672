"""PBTKF-IMSF (spec 003 §2, §5.1-5.3): fixtures, reductions R1-R5, invariants, bounds, Monte Carlo checks."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

import tobitkf as tk
from tobitkf.channels.laws import Constant, Uniform
from tobitkf.channels.protocol import LAMBDA_1, LAMBDA_BASE, ProtocolChannel
from tobitkf.design.protocol_bounds import analytic_p_uncensored, protocol_covariance_bounds
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter, protocol_tobit_kalman_filter
from tobitkf.filters.protocol_model import FAILURE_TERMS, augmented_transition, noise_input, stacked_measurement

W = 0.052 * np.pi
ROT = np.array([[np.cos(W), -np.sin(W)], [np.sin(W), np.cos(W)]])


def example(damped=False):
    A = 0.9 * ROT if damped else ROT
    return tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))


def example_channel(**kw):
    base = dict(window=2, failures=LAMBDA_BASE, threshold=0.0)
    base.update(kw)
    return ProtocolChannel(2, **base)


def printed(value, decimals):
    """Tolerance of spec §3.4 values: rtol 1e-6 or half a unit in the last printed digit."""
    return max(1e-6 * abs(value), 0.5 * 10.0**-decimals)


# --- §5.1 item 4: deterministic fixtures ----------------------------------------------------------
FIXTURES = {  # mode: x1, (trP-_1, trP_1), x2, (trP-_2, trP_2), x3, trP_3, P_y at k = 1
    "variance": (
        [4.451884, 0.773814],
        (2.005, 1.402357),
        [4.209122, 1.755206],
        (1.407357, 0.576613),
        [3.867620, 2.416397],
        0.581613,
        5.353888,
    ),
    "literal": (
        [4.658702, 0.790724],
        (2.005, 1.661185),
        [4.441005, 1.677854],
        (1.666185, 1.212130),
        [4.108996, 2.377787],
        1.217130,
        9.384344,
    ),
    "second_moment": (
        [4.803544, 0.802566],
        (2.005, 1.842452),
        [4.566755, 1.810621],
        (1.847452, 1.051151),
        [4.211479, 2.529238],
        1.056151,
        19.849364,
    ),
}


@pytest.mark.parametrize("mode", list(FIXTURES))
def test_spec_fixtures_k1_to_3(mode):
    x1, tr1, x2, tr2, x3, tr3, Py = FIXTURES[mode]
    r = protocol_tobit_kalman_filter(example(), example_channel(), np.array([[12.0], [3.0], [0.0]]), failure_term=mode)
    np.testing.assert_allclose(r.extras["aug_pred_mean"][0], [4.933430, 0.813186, 5, 0, 5, 0], atol=5e-7)
    assert r.extras["innovation_var"][0] == pytest.approx(Py, abs=printed(Py, 6))
    for k, x in ((0, x1), (1, x2), (2, x3)):
        np.testing.assert_allclose(r.mean[k], x, atol=5e-7)
    for k, (trp, tr) in ((0, tr1), (1, tr2)):
        assert np.trace(r.pred_cov[k]) == pytest.approx(trp, abs=printed(trp, 6))
        assert np.trace(r.cov[k]) == pytest.approx(tr, abs=printed(tr, 6))
    assert np.trace(r.cov[2]) == np.trace(r.pred_cov[2]) == pytest.approx(tr3, abs=printed(tr3, 6))
    assert r.extras["uncensored"].tolist() == [True, True, False]


def test_fixture_intermediate_quantities():
    r = protocol_tobit_kalman_filter(example(), example_channel(), np.array([[12.0]]), keep_augmented=True)
    Pm = r.extras["aug_pred_cov"][0]
    Cc = stacked_measurement([1.0, 0.0], 2)
    assert Cc @ Pm @ Cc == pytest.approx(4.975872, abs=5e-7)
    assert 0.81 * (Cc @ Pm @ Cc) == pytest.approx(4.030456, abs=5e-7)
    assert r.extras["theta_bar"][0] == pytest.approx(-13.440087, abs=5e-7)
    assert 0 < r.extras["inverse_mills"][0] < 1e-39


BOUND_FIXTURES = {  # (damped, upper/lower): traces at k = 1, 2, 3, 4, 5, 10, 50, 100
    (False, "upper"): [2.005, 1.708679, 1.302939, 1.030860, 0.811199, 0.327098, 0.089821, 0.088508],
    (False, "lower"): [2.005, 1.0075, 0.50875, 0.259375, 0.134687, 0.013896, 0.01, 0.01],
    (True, "upper"): [1.625, 1.130686, 0.707784, 0.465436, 0.311895, 0.075930, 0.024606, 0.024605],
    (True, "lower"): [1.625, 0.663125, 0.273566, 0.115794, 0.051897, 0.008877, 0.008403, 0.008403],
}


@pytest.mark.parametrize("damped, which", list(BOUND_FIXTURES))
def test_bound_fixtures_constant_gamma(damped, which):
    b = protocol_covariance_bounds(example(damped), example_channel(), 100, p_uncensored=0.5)
    tr = np.trace(getattr(b, which), axis1=1, axis2=2)
    for k, want in zip((1, 2, 3, 4, 5, 10, 50, 100), BOUND_FIXTURES[(damped, which)]):
        assert tr[k - 1] == pytest.approx(want, abs=printed(want, 6))


def test_lower_bound_closed_form_undamped():
    # (30) with gbar = 1/2 and A a rotation: tr N^l_{k+1} = tr N^l_k / 2 + 0.005, tr N^l_1 = 2.005
    b = protocol_covariance_bounds(example(), example_channel(), 30, p_uncensored=0.5)
    tr = np.trace(b.lower, axis1=1, axis2=2)
    want = 0.01 + (2.005 - 0.01) * 0.5 ** np.arange(30)
    np.testing.assert_allclose(tr, want, rtol=1e-12)


def test_analytic_p_uncensored_fixture():
    g = analytic_p_uncensored(example(), example_channel(), 100)
    want = [0.975, 0.7625, 0.975, 0.9613, 0.9749, 0.9746, 0.9702, 0.975, 0.8673, 0.975]
    np.testing.assert_allclose(g[:10], want, atol=5e-5)
    assert g[50:].mean() == pytest.approx(0.465, abs=5e-4)
    # the cap: Lambda = 0 (prob. 0.05) leaves y = v, above 0 with prob. 1/2
    assert g.max() <= 0.975 + 1e-12


def test_analytic_p_uncensored_uniform_law_by_quadrature():
    # Uniform gains: compare with a brute-force Monte Carlo average of the conditional probability
    ch = example_channel(failures=Uniform(0.2, 0.8))
    g = analytic_p_uncensored(example(), ch, 5)
    lam = np.linspace(0.2, 0.8, 200001)
    m = np.tile([5.0, 0.0], 3)
    S = np.eye(6)
    A = augmented_transition(ROT, 2)
    B = noise_input(2, 2)
    m, S = A @ m, A @ S @ A.T + B @ (0.0025 * np.eye(2)) @ B.T
    Cc = stacked_measurement([1.0, 0.0], 2)
    ref = np.trapezoid(norm.sf((0 - lam * (Cc @ m)) / np.sqrt(lam**2 * (Cc @ S @ Cc) + 1)), lam) / 0.6
    assert g[0] == pytest.approx(ref, rel=1e-9)


# --- §5.2 reductions ----------------------------------------------------------------------------------
def random_system(rng, n=2, p=1, T=10, varying=False):
    A = (
        rng.normal(size=(T, n, n)) * 0.4 + np.eye(n) * 0.7
        if varying
        else rng.normal(size=(n, n)) * 0.3 + 0.8 * np.eye(n)
    )
    C = rng.normal(size=(p, n))
    L = rng.normal(size=(n, n))
    return tk.LinearSystem(
        A=A,
        C=C,
        Q=0.1 * L @ L.T + 0.05 * np.eye(n),
        R=np.diag(rng.uniform(0.5, 2.0, p)),
        x0=rng.normal(size=n),
        P0=np.eye(n) * 1.5,
    )


@pytest.mark.parametrize("update", ["joseph", "standard"])
def test_R1_reduces_to_the_kalman_filter(update):
    rng = np.random.default_rng(1)
    sys_ = random_system(rng, n=3, p=1, T=15, varying=True)
    ch = ProtocolChannel(1, window=0, threshold=-1e12)
    y = rng.normal(size=(4, 15, 1)) * 3
    a = protocol_tobit_kalman_filter(sys_, ch, y, covariance_update=update)
    b = tk.KalmanFilter(sys_).filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.pred_cov, b.pred_cov, rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_control_inputs_enter_the_prediction_as_in_the_kalman_filter(backend):
    """With a control input (not in the source) the R1 reduction still holds: the protocol TKF with
    ``u`` equals the KF with the same ``u`` (filter and online step); ``u`` given to a system with a
    feedthrough D is refused (the received reading (4) has none)."""
    rng = np.random.default_rng(7)
    base = random_system(rng, n=3, p=1, T=15, varying=False)
    mats = dict(A=base.transition(0), C=base.measurement(1), Q=base.process_cov(0), R=base.measurement_cov(1))
    mats.update(x0=base.x0, P0=base.P0, Bu=rng.normal(size=(3, 2)))
    sys_ = tk.LinearSystem(**mats)
    ch = ProtocolChannel(1, window=0, threshold=-1e12)
    y = rng.normal(size=(4, 15, 1)) * 3
    u = rng.normal(size=(4, 15, 2))
    est = ProtocolTobitKalmanFilter(sys_, ch, backend=backend)
    a = est.filter(y, u=u)
    b = tk.KalmanFilter(sys_).filter(y, u=u)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-12)
    assert np.abs(a.mean - est.filter(y).mean).max() > 0.1  # the input is not ignored
    s = est.init((4,))
    for k in range(15):
        s = est.step(s, y[:, k], u=u[:, k])
    np.testing.assert_allclose(s.mean, b.mean[:, -1], rtol=0, atol=1e-12)
    with pytest.raises(tk.ValidationError, match="no feedthrough D u"):
        ProtocolTobitKalmanFilter(tk.LinearSystem(**mats, D=np.ones((1, 2))), ch).filter(y, u=u)


def test_R1_round_robin_equals_time_varying_kalman_filter():
    rng = np.random.default_rng(2)
    T = 12
    sys_ = random_system(rng, n=2, p=3, T=T)
    ch = ProtocolChannel(3, window=0, threshold=-1e12)
    y = rng.normal(size=(3, T, 1))
    h = ch.schedule.scheduled(T) - 1
    C = sys_.measurement(1)
    R = sys_.measurement_cov(1)
    kf_sys = tk.LinearSystem(
        A=sys_.transition(0),
        C=C[h][:, None, :],
        Q=sys_.process_cov(0),
        R=R[h, h][:, None, None],
        x0=sys_.x0,
        P0=sys_.P0,
    )
    a = protocol_tobit_kalman_filter(sys_, ch, y)
    b = tk.KalmanFilter(kf_sys).filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-12)


def test_R1_literal_mode_fails_the_reduction():
    # "literal": F = (mean^2 + var) C P C^T = C P C^T without failures, so P_y has C P C^T twice
    rng = np.random.default_rng(1)
    sys_ = random_system(rng, n=2, p=1, T=10)
    ch = ProtocolChannel(1, window=0, threshold=-1e12)
    y = rng.normal(size=(10, 1))
    a = protocol_tobit_kalman_filter(sys_, ch, y, failure_term="literal")
    b = tk.KalmanFilter(sys_).filter(y)
    assert np.abs(a.mean - b.mean).max() > 1e-3
    assert (np.trace(a.cov, axis1=-2, axis2=-1) > np.trace(b.cov, axis1=-2, axis2=-1) + 1e-6).all()


def batch_posterior(sys_, ch, y, T):
    """Oracle for R2: the joint Gaussian of (x_{-l}..x_T, y_1..y_T) conditioned on y_{1:k}."""
    n, ell = sys_.n, ch.window
    nu = n * (ell + 1) + n * T + T
    mu_u = np.concatenate([np.tile(sys_.x0, ell + 1), np.zeros(n * T + T)])
    cov_u = np.zeros((nu, nu))
    cov_u[: n * (ell + 1), : n * (ell + 1)] = np.kron(np.eye(ell + 1), sys_.P0)
    h = ch.schedule.scheduled(T) - 1
    for k in range(T):
        i = n * (ell + 1) + n * k
        cov_u[i : i + n, i : i + n] = sys_.process_cov(k)
        j = n * (ell + 1) + n * T + k
        cov_u[j, j] = sys_.measurement_cov(k + 1)[h[k], h[k]]
    S = {}
    for s in range(ell + 1):  # x_{-s} = block (ell - s)
        M = np.zeros((n, nu))
        M[:, n * (ell - s) : n * (ell - s + 1)] = np.eye(n)
        S[-s] = M
    for k in range(1, T + 1):
        M = np.zeros((n, nu))
        i = n * (ell + 1) + n * (k - 1)
        M[:, i : i + n] = np.eye(n)
        S[k] = sys_.transition(k - 1) @ S[k - 1] + M
    Y = np.zeros((T, nu))
    for k in range(1, T + 1):
        e = np.zeros(nu)
        e[n * (ell + 1) + n * T + k - 1] = 1
        Y[k - 1] = sys_.measurement(k)[h[k - 1]] @ sum(S[k - s] for s in range(ell + 1)) + e
    means, covs = [], []
    for k in range(1, T + 1):
        Xi = np.vstack([S[k - s] for s in range(ell + 1)])
        Yk = Y[:k]
        Syy = Yk @ cov_u @ Yk.T
        Sxy = Xi @ cov_u @ Yk.T
        G = np.linalg.solve(Syy, Sxy.T).T
        means.append(Xi @ mu_u + G @ (y[:k] - Yk @ mu_u))
        covs.append(Xi @ cov_u @ Xi.T - G @ Sxy.T)
    return np.array(means), np.array(covs)


@pytest.mark.parametrize("ell", [1, 2, 5])
def test_R2_augmented_filter_equals_batch_gaussian_posterior(ell):
    rng = np.random.default_rng(10 + ell)
    T = 9
    sys_ = random_system(rng, n=2, p=2, T=T, varying=True)
    ch = ProtocolChannel(2, window=ell, threshold=-np.inf)
    y = tk.simulate(sys_, T, 1, seed=ell, channel=ch).y[0]
    r = protocol_tobit_kalman_filter(sys_, ch, y, keep_augmented=True)
    m, P = batch_posterior(sys_, ch, y[:, 0], T)
    np.testing.assert_allclose(r.extras["aug_mean"], m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(r.extras["aug_cov"], P, rtol=0, atol=1e-9)


def test_R3_tobit_with_known_indicator_explicit_formulas():
    T = 25
    sys_ = tk.LinearSystem(
        A=[[0.95, 0.1], [0.0, 0.9]], C=[[1.0, 0.5]], Q=0.2 * np.eye(2), R=[[0.7]], x0=[1.0, 0.0], P0=np.eye(2)
    )
    tau = 0.8
    ch = ProtocolChannel(1, window=0, threshold=tau)
    y = tk.simulate(sys_, T, 1, seed=3, channel=ch).y[0, :, 0]
    assert 3 < (y == tau).sum() < T - 3
    r = protocol_tobit_kalman_filter(sys_, ch, y[:, None])
    A, C, Q, R = sys_.transition(0), sys_.measurement(1)[0], sys_.process_cov(0), 0.7
    x, P = sys_.x0.copy(), sys_.P0.copy()
    for k in range(T):
        x, P = A @ x, A @ P @ A.T + Q
        if y[k] > tau:
            a = (tau - C @ x) / np.sqrt(R)
            lam = norm.pdf(a) / norm.sf(a)
            phi = lam * (lam - a)
            S = C @ P @ C + R * (1 - phi)
            K = P @ C / S
            x = x + K * (y[k] - C @ x - np.sqrt(R) * lam)
            P = P - np.outer(K, C @ P)
        np.testing.assert_allclose(r.mean[k], x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(r.cov[k], P, rtol=0, atol=1e-10)


def test_R4_failures_only_lmmse_is_exact():
    # tau = -inf, random gains, lmmse_unconditional: the computed covariance is the true MSE
    sys_, ch = example(), example_channel(threshold=-np.inf)
    M = 2000
    d = tk.simulate(sys_, 60, M, seed=21, channel=ch)
    r = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term="lmmse_unconditional")
    err2 = ((d.x[:, 1:] - r.mean) ** 2).sum(-1)
    tr = np.trace(r.cov[0], axis1=-2, axis2=-1)  # deterministic: the same for every run
    np.testing.assert_allclose(np.trace(r.cov, axis1=-2, axis2=-1), np.broadcast_to(tr, (M, 60)), rtol=1e-12)
    for k in (1, 5, 20, 60):
        se = err2[:, k - 1].std(ddof=1) / np.sqrt(M)
        assert abs(err2[:, k - 1].mean() - tr[k - 1]) < 4 * se, k


def test_R5_modes_coincide_without_gain_variance():
    sys_ = example()
    ch = example_channel(failures=Constant(0.7))
    d = tk.simulate(sys_, 30, 6, seed=1, channel=ch)
    ref = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term="variance")
    for mode in ("second_moment", "lmmse_unconditional"):
        r = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term=mode)
        np.testing.assert_array_equal(r.mean, ref.mean)
        np.testing.assert_array_equal(r.cov, ref.cov)


# --- §5.1 items 5-6: censored step and structure -----------------------------------------------------
def test_censored_step_leaves_estimate_and_covariance_bit_exactly_unchanged():
    sys_, ch = example(), example_channel()
    d = tk.simulate(sys_, 40, 8, seed=2, channel=ch)
    gam = d.extras["uncensored"].copy()  # (N, T, 1), laid out like y
    gam[:, 5] = False  # also: a value above tau declared censored
    y = d.y.copy()
    y[:, 5] = 123.0
    r = protocol_tobit_kalman_filter(sys_, ch, y, uncensored=gam, keep_augmented=True)
    gam = gam[..., 0]
    assert (~gam).sum() > 20
    np.testing.assert_array_equal(r.extras["aug_mean"][~gam], r.extras["aug_pred_mean"][~gam])
    np.testing.assert_array_equal(r.extras["aug_cov"][~gam], r.extras["aug_pred_cov"][~gam])
    assert (r.extras["aug_cov"][gam] != r.extras["aug_pred_cov"][gam]).any(axis=(-1, -2)).all()


@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_structural_invariants(mode):
    sys_, ch = example(), example_channel()
    d = tk.simulate(sys_, 30, 5, seed=9, channel=ch)
    r = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term=mode, keep_augmented=True)
    P, Pm, xi, xim = (r.extras[k] for k in ("aug_cov", "aug_pred_cov", "aug_mean", "aug_pred_mean"))
    n = 2
    # shift structure: P^-_k blocks (i+1, j+1) = P_{k-1} blocks (i, j); mean blocks shifted
    np.testing.assert_array_equal(Pm[:, 1:, n:, n:], P[:, :-1, :-n, :-n])
    np.testing.assert_array_equal(xim[:, 1:, n:], xi[:, :-1, :-n])
    np.testing.assert_allclose(Pm[:, 1:, :n, :n], ROT @ P[:, :-1, :n, :n] @ ROT.T + 0.0025 * np.eye(2), atol=1e-14)
    # symmetry, PSD, P <= P^-
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    assert np.linalg.eigvalsh(P).min() > -1e-12
    assert np.linalg.eigvalsh(Pm - P).min() > -1e-12
    # undamped rotation: tr(Pi P^-_{k+1} Pi^T) = tr(Pi P_k Pi^T) + 0.005
    np.testing.assert_allclose(
        np.trace(r.pred_cov[:, 1:], axis1=-2, axis2=-1),
        np.trace(r.cov[:, :-1], axis1=-2, axis2=-1) + 0.005,
        rtol=0,
        atol=1e-12,
    )
    # Joseph form equals the standard form
    s = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term=mode, covariance_update="standard")
    np.testing.assert_allclose(s.cov, r.cov, rtol=0, atol=1e-10)
    np.testing.assert_allclose(s.mean, r.mean, rtol=0, atol=1e-10)


def test_batched_equals_per_run():
    sys_, ch = example(), example_channel()
    d = tk.simulate(sys_, 25, 4, seed=3, channel=ch)
    r = protocol_tobit_kalman_filter(sys_, ch, d.y.reshape(2, 2, 25, 1))
    assert r.mean.shape == (2, 2, 25, 2) and r.extras["uncensored"].shape == (2, 2, 25)
    for i in range(4):
        one = protocol_tobit_kalman_filter(sys_, ch, d.y[i])
        np.testing.assert_allclose(r.mean.reshape(4, 25, 2)[i], one.mean, rtol=0, atol=1e-13)
        np.testing.assert_allclose(r.cov.reshape(4, 25, 2, 2)[i], one.cov, rtol=0, atol=1e-13)


def test_prehistory_prior_option():
    sys_, ch = example(), example_channel()
    y = np.array([[12.0]])
    rep = protocol_tobit_kalman_filter(sys_, ch, y)
    zero = protocol_tobit_kalman_filter(sys_, ch, y, prehistory_prior="zero_mean")
    np.testing.assert_allclose(rep.extras["aug_pred_mean"][0], np.r_[ROT @ [5, 0], 5, 0, 5, 0], atol=1e-15)
    np.testing.assert_allclose(zero.extras["aug_pred_mean"][0], np.r_[ROT @ [5, 0], 5, 0, 0, 0], atol=1e-15)
    # the smaller predicted integral makes the zero-mean prior move the estimate up more
    assert zero.mean[0, 0] > rep.mean[0, 0]


def test_baseline_is_the_misspecified_filter():
    sys_, ch = example(), example_channel()
    d = tk.simulate(sys_, 20, 3, seed=0, channel=ch)
    a = ProtocolTobitKalmanFilter.baseline(sys_, ch).filter(d.y)
    b = protocol_tobit_kalman_filter(sys_, ProtocolChannel(2, window=0, threshold=0.0), d.y)
    np.testing.assert_array_equal(a.mean, b.mean)
    assert a.extras["aug_mean"].shape[-1] == 2


@settings(max_examples=20, deadline=None)
@given(
    ell=st.integers(0, 3),
    p=st.integers(1, 3),
    tau=st.floats(-3, 3),
    seed=st.integers(0, 10_000),
    mode=st.sampled_from(FAILURE_TERMS),
)
def test_property_covariances_psd_and_shrinking(ell, p, tau, seed, mode):
    rng = np.random.default_rng(seed)
    sys_ = random_system(rng, n=2, p=p, T=12)
    ch = ProtocolChannel(p, window=ell, failures=LAMBDA_BASE, threshold=tau)
    d = tk.simulate(sys_, 12, 3, seed=seed, channel=ch)
    r = protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term=mode, keep_augmented=True)
    P, Pm = r.extras["aug_cov"], r.extras["aug_pred_cov"]
    scale = np.abs(Pm).max()
    assert np.linalg.eigvalsh(P).min() > -1e-10 * scale
    assert np.linalg.eigvalsh(Pm - P).min() > -1e-10 * scale
    assert np.isfinite(r.mean).all()


# --- bounds: options and orderings -------------------------------------------------------------------
@pytest.mark.parametrize("damped", [False, True])
def test_bound_orderings(damped):
    sys_, ch = example(damped), example_channel()
    b = protocol_covariance_bounds(sys_, ch, 100)
    sub = protocol_covariance_bounds(sys_, ch, 100, upper_form="suboptimal_gain")
    proof = protocol_covariance_bounds(sys_, ch, 100, lower_form="paper_proof")
    np.testing.assert_array_equal(b.upper[0], b.lower[0])
    assert np.linalg.eigvalsh(b.upper - b.lower).min() > -1e-12
    assert np.linalg.eigvalsh(sub.upper_aug - b.upper_aug).min() > -1e-12  # suboptimal gain is looser
    assert np.linalg.eigvalsh(b.lower_aug - proof.lower_aug).min() > -1e-12  # the proof's version is looser
    np.testing.assert_allclose(proof.lower[0], 0.0025 * np.eye(2))


def test_bounds_with_gamma_one_and_no_failures_are_the_kalman_riccati():
    # gbar = 1, no failures, no censoring: M^u is the KF prior covariance of the augmented model
    sys_ = example()
    ch = ProtocolChannel(2, window=2, threshold=-np.inf)
    b = protocol_covariance_bounds(sys_, ch, 20, p_uncensored=1.0)
    r = protocol_tobit_kalman_filter(sys_, ch, np.zeros((20, 1)))
    np.testing.assert_allclose(b.upper, r.pred_cov, rtol=0, atol=1e-12)


# --- §5.3 Monte Carlo checks (fixed seeds, tolerances from the run count) ------------------------------------
@pytest.fixture(scope="module")
def mc_runs():
    out = {}
    for damped in (False, True):
        sys_, ch = example(damped), example_channel()
        d = tk.simulate(sys_, 100, 600, seed=100 + damped, channel=ch)
        out[damped] = (
            sys_,
            ch,
            d,
            {m: protocol_tobit_kalman_filter(sys_, ch, d.y, failure_term=m) for m in ("variance", "second_moment")},
            ProtocolTobitKalmanFilter.baseline(sys_, ch).filter(d.y),
        )
    return out


@pytest.mark.parametrize("damped", [False, True])
def test_mc_bounds_hold_at_every_k(mc_runs, damped):
    sys_, ch, d, res, _ = mc_runs[damped]
    r = res["variance"]
    b = protocol_covariance_bounds(sys_, ch, 100)
    tr_runs = np.trace(r.pred_cov, axis1=-2, axis2=-1)
    trN = tr_runs.mean(0)
    se = tr_runs.std(0, ddof=1) / np.sqrt(tr_runs.shape[0])
    tu, tl = np.trace(b.upper, axis1=1, axis2=2), np.trace(b.lower, axis1=1, axis2=2)
    assert (trN <= tu + 4 * se + 1e-12).all()
    assert (trN >= tl - 4 * se - 1e-12).all()
    Nbar = r.pred_cov.mean(0)
    # Loewner order, slack of the same size (the upper bound is tight at k = 2, spec notes)
    assert (np.linalg.eigvalsh(b.upper - Nbar).min(1) > -4 * se - 1e-12).all()
    assert (np.linalg.eigvalsh(Nbar - b.lower).min(1) > -4 * se - 1e-12).all()
    # (28) read literally is not a bound: it is exceeded in the transient (spec A2, a diagnostic)
    lit = protocol_covariance_bounds(sys_, ch, 100, upper_form="paper_literal")
    assert (trN > np.trace(lit.upper, axis1=1, axis2=2) + 4 * se).any()


@pytest.mark.parametrize("damped", [False, True])
def test_mc_uncensored_frequency_matches_analytic(mc_runs, damped):
    sys_, ch, d, res, _ = mc_runs[damped]
    g = analytic_p_uncensored(sys_, ch, 100)
    freq = d.extras["uncensored"][..., 0].mean(0)
    M = d.y.shape[0]
    # 4 binomial standard deviations at each of 100 steps: family-wise false alarm < 1 %
    assert (np.abs(freq - g) <= 4 * np.sqrt(g * (1 - g) / M) + 1e-12).all()


def test_mc_fig3_imsf_beats_pbtkf_undamped(mc_runs):
    sys_, ch, d, res, base = mc_runs[False]
    a = tk.metrics.rmse(d.x, res["variance"].mean).mean(0)
    b = tk.metrics.rmse(d.x, base.mean).mean(0)
    assert (a < b).all()


def test_mc_fig4_mect_ordering_damped(mc_runs):
    sys_, ch, d, res, base = mc_runs[True]
    a = np.trace(res["variance"].pred_cov, axis1=-2, axis2=-1).mean(0)
    b = np.trace(base.pred_cov, axis1=-2, axis2=-1).mean(0)
    assert (a[1:] < b[1:]).mean() >= 0.95
    assert a[0] == pytest.approx(b[0], rel=1e-12)  # equal at k = 1 (both P^-_1 = A P0 A' + Q)


@pytest.mark.parametrize("damped", [False, True])
def test_mc_consistency_finding(mc_runs, damped):
    """The 'variance' filter is overconfident (a finding, spec §5.3); 'second_moment' is about consistent."""
    sys_, ch, d, res, _ = mc_runs[damped]

    def ratio(r):
        mse = ((d.x[:, 1:] - r.mean) ** 2).sum(-1).mean(0)
        return mse.mean() / np.trace(r.cov, axis1=-2, axis2=-1).mean()

    assert 0.8 < ratio(res["second_moment"]) < 1.2
    assert ratio(res["variance"]) > (2.5 if not damped else 1.3)


def test_mc_fig6_threshold_ordering_damped():
    sys_ = example(True)
    M = 1000
    out = []
    for tau in (0.0, -5.0):
        ch = example_channel(threshold=tau)
        d = tk.simulate(sys_, 100, M, seed=31, channel=ch)
        out.append(tk.metrics.rmse(d.x, protocol_tobit_kalman_filter(sys_, ch, d.y).mean).mean())
    assert out[1] < out[0]


def test_mc_fig8_failure_ordering_is_opposite_to_the_text():
    # spec A9: the paper says Lambda_1 gives the lower RMSE; the pdfs (and the runs) say Lambda_2
    sys_ = example(True)
    out = []
    for law in (LAMBDA_1, LAMBDA_BASE):
        ch = example_channel(failures=law)
        d = tk.simulate(sys_, 100, 400, seed=41, channel=ch)
        out.append(tk.metrics.rmse(d.x, protocol_tobit_kalman_filter(sys_, ch, d.y).mean).mean())
    assert out[0] > out[1]


# --- bad input ---------------------------------------------------------------------------------------------
def test_bad_options_and_input():
    sys_, ch = example(), example_channel()
    y = np.ones((5, 1))
    with pytest.raises(ValueError, match="failure_term"):
        protocol_tobit_kalman_filter(sys_, ch, y, failure_term="second")
    with pytest.raises(ValueError, match="prehistory_prior"):
        ProtocolTobitKalmanFilter(sys_, ch, prehistory_prior="hold")
    with pytest.raises(ValueError, match="covariance_update"):
        ProtocolTobitKalmanFilter(sys_, ch, covariance_update="fast")
    with pytest.raises(ValueError, match=r"expected \(\.\.\., T, 1\)"):
        protocol_tobit_kalman_filter(sys_, ch, np.ones((3, 5)))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., T, 1\)"):  # a (T,) record: lay it out as (T, 1)
        protocol_tobit_kalman_filter(sys_, ch, np.ones(5))
    with pytest.raises(ValueError, match="below the threshold"):
        protocol_tobit_kalman_filter(sys_, ch, -y)
    with pytest.raises(ValueError, match="uncensored: expected shape"):
        protocol_tobit_kalman_filter(sys_, ch, y, uncensored=np.ones(4, bool))
    with pytest.raises(ValueError, match="p=3 rows"):
        protocol_tobit_kalman_filter(sys_, ProtocolChannel(3), y)
    with pytest.raises(ValueError, match="P0_aug"):
        protocol_tobit_kalman_filter(sys_, ch, y, P0_aug=np.eye(4))
    with pytest.raises(ValueError, match="channel: expected a ProtocolChannel"):
        ProtocolTobitKalmanFilter(sys_, "rr")
    with pytest.raises(TypeError, match="unexpected keyword"):
        protocol_covariance_bounds(sys_, ch, 10, gamma=0.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"p_uncensored": 1.5}, r"\[0, 1\]"),
        ({"p_uncensored": np.full(9, 0.5)}, r"shape \(10,\)"),
        ({"p_uncensored": "paper_eq8"}, "analytic"),
        ({"upper_form": "paper"}, "upper_form"),
        ({"lower_form": "proof"}, "lower_form"),
        ({"phi_upper": "one"}, "phi_upper"),
    ],
)
def test_bounds_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        protocol_covariance_bounds(example(), example_channel(), 10, **kwargs)


def test_analytic_gamma_needs_a_discrete_or_uniform_law():
    class Moments:
        mean, variance = 0.8, 0.01

        def sample(self, rng, shape=()):
            return np.full(shape, 0.8)

    with pytest.raises(ValueError, match="pass p_uncensored explicitly"):
        protocol_covariance_bounds(example(), example_channel(failures=Moments()), 10)
    b = protocol_covariance_bounds(example(), example_channel(failures=Moments()), 10, p_uncensored=0.9)
    assert b.upper.shape == (10, 2, 2)


def test_bound_phi_upper_mean_trajectory_is_tighter():
    sys_, ch = example(True), example_channel()
    a = protocol_covariance_bounds(sys_, ch, 60)
    b = protocol_covariance_bounds(sys_, ch, 60, phi_upper="mean_trajectory")
    assert (np.trace(b.upper, axis1=1, axis2=2) <= np.trace(a.upper, axis1=1, axis2=2) + 1e-12).all()


@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_square_root_form_reports_the_innovation_variance_of_24(mode):
    """``innovation_var`` is P_y of (24), H P H^T + F + R(1 - phi), in every covariance form: the square-root
    form reported the noise R(1 - phi) alone before."""
    w = 0.052 * np.pi
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=[[1.0, 0.0], [0.3, 1.0]], Q=0.0025 * np.eye(2),
        R=np.diag([1.0, 0.5]), x0=[5.0, 0.0], P0=np.eye(2),
    )  # fmt: skip
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    y = tk.simulate(sys_, 25, 3, seed=2, channel=ch).y
    res = {
        form: ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode, covariance_update=form, backend="numpy").filter(y)
        for form in ("joseph", "square_root")
    }
    a, b = res["square_root"].extras, res["joseph"].extras
    np.testing.assert_allclose(a["innovation_var"], b["innovation_var"], rtol=1e-10)
    g = b["uncensored"]
    # where gamma = 1 it exceeds the noise term by H P H^T + F > 0
    r = np.where(b["scheduled"] == 1, 1.0, 0.5)
    noise = r * (1.0 - b["trunc_var_factor"])
    assert (a["innovation_var"][g] > noise[g] * (1 + 1e-9)).all()
