"""Smoothers (tobitkf.inference.smoothing): reductions to the RTS smoother and to the brute-force
Gaussian posterior, pykalman's robot data, the censored smoothers' reductions, fixed lag."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.inference import FixedLagSmoother, rts_smooth, smooth


def _model(n=2, seed=0, R=0.3):
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])[:n, :n]
    C = np.array([[1.0, 0.5]])[:, :n]
    Q = np.array([[0.4, 0.1], [0.1, 0.3]])[:n, :n]
    return tk.LinearSystem(
        A=A, C=C, Q=Q, R=[[R]], x0=rng.normal(size=n), P0=np.eye(n) * 0.7, Bu=np.array([[0.5], [0.0]])[:n], D=[[0.2]]
    ), rng


def _stacked_posterior(system, y, u):
    """Brute force: the joint Gaussian of (x_0..x_T, y_1..y_T), conditioned on the present readings."""
    A, C, Q, R = (np.asarray(getattr(system, k).at(1)) for k in ("A", "C", "Q", "R"))
    Bu, D = system.Bu.at(1), system.D.at(1)
    T, n = y.shape[0], system.n
    # x_k = A^k x_0 + sum_j A^{k-j} (Bu u_j + w_{j-1}); stack z = (x_0, w_0..w_{T-1})
    dim = n * (T + 1)
    L = np.zeros((n * (T + 1), dim))  # x = L z + c
    c = np.zeros(n * (T + 1))
    L[:n, :n] = np.eye(n)
    c[:n] = system.x0
    for k in range(1, T + 1):
        L[k * n : (k + 1) * n] = A @ L[(k - 1) * n : k * n]
        L[k * n : (k + 1) * n, k * n : (k + 1) * n] += np.eye(n)
        c[k * n : (k + 1) * n] = A @ c[(k - 1) * n : k * n] + Bu @ u[k - 1]
    Sz = np.zeros((dim, dim))
    Sz[:n, :n] = system.P0
    for k in range(T):
        Sz[(k + 1) * n : (k + 2) * n, (k + 1) * n : (k + 2) * n] = Q
    Sx = L @ Sz @ L.T
    m = C.shape[0]
    H = np.zeros((T * m, n * (T + 1)))
    for k in range(1, T + 1):
        H[(k - 1) * m : k * m, k * n : (k + 1) * n] = C
    ym = H @ c + np.concatenate([D @ u[k] for k in range(T)])
    Sy = H @ Sx @ H.T + np.kron(np.eye(T), R)
    obs = ~np.isnan(y.ravel())
    K = np.linalg.solve(Sy[np.ix_(obs, obs)], (Sx @ H.T)[:, obs].T).T
    mean = c + K @ (y.ravel()[obs] - ym[obs])
    cov = Sx - K @ (H @ Sx)[obs]
    ll = -0.5 * (
        obs.sum() * np.log(2 * np.pi)
        + np.linalg.slogdet(Sy[np.ix_(obs, obs)])[1]
        + (y.ravel()[obs] - ym[obs]) @ np.linalg.solve(Sy[np.ix_(obs, obs)], y.ravel()[obs] - ym[obs])
    )
    return mean.reshape(T + 1, n), cov, ll


def test_rts_equals_the_stacked_gaussian_posterior_with_inputs_and_a_missing_reading():
    system, rng = _model()
    T = 7
    u = rng.normal(size=(T, 1))
    y = rng.normal(size=(T, 1))
    y[3] = np.nan
    mean, cov, _ = _stacked_posterior(system, y, u)
    sm = smooth(system, y, u=u)
    n = system.n
    np.testing.assert_allclose(sm.mean, mean[1:], atol=1e-10, rtol=0)
    np.testing.assert_allclose(sm.extras["initial_mean"], mean[0], atol=1e-10, rtol=0)
    for k in range(1, T + 1):
        np.testing.assert_allclose(sm.cov[k - 1], cov[k * n : (k + 1) * n, k * n : (k + 1) * n], atol=1e-10, rtol=0)
        np.testing.assert_allclose(
            sm.extras["cross_cov"][k - 1], cov[k * n : (k + 1) * n, (k - 1) * n : k * n], atol=1e-10, rtol=0
        )
    np.testing.assert_allclose(sm.extras["initial_cov"], cov[:n, :n], atol=1e-10, rtol=0)


def test_kalman_log_likelihood_equals_the_stacked_gaussian_density():
    system, rng = _model(seed=3)
    T = 6
    u = rng.normal(size=(T, 1))
    y = rng.normal(size=(T, 1))
    y[[1, 4]] = np.nan
    _, _, ll = _stacked_posterior(system, y, u)
    assert abs(float(tk.kalman_log_likelihood(system, y, u=u)) - ll) < 1e-10


def test_batched_smoother_equals_a_loop_over_runs():
    system, rng = _model(seed=5)
    y = rng.normal(size=(3, 6, 1))
    u = rng.normal(size=(3, 6, 1))
    y[1, 2] = np.nan
    sm = smooth(system, y, u=u)
    for r in range(3):
        one = smooth(system, y[r], u=u[r])
        np.testing.assert_allclose(sm.mean[r], one.mean, atol=1e-12, rtol=0)
        np.testing.assert_allclose(sm.cov[r], one.cov, atol=1e-12, rtol=0)
        np.testing.assert_allclose(sm.extras["cross_cov"][r], one.extras["cross_cov"], atol=1e-12, rtol=0)


def _robot():
    pk = pytest.importorskip("pykalman")
    from pykalman.datasets import load_robot

    d = load_robot()
    T = d.observations.shape[0] - 1
    system = tk.LinearSystem(
        A=d.transition_matrix,
        C=d.observation_matrix,
        Q=d.transition_covariance,
        R=d.observation_covariance,
        x0=d.initial_state_mean,
        P0=d.initial_state_covariance,
        Bu=np.c_[np.eye(5), np.zeros(5)],
        D=np.c_[np.zeros((2, 5)), d.observation_offset],
    )
    # pykalman's x_{t+1} = A x_t + b_t: our u_k = (b_{k-1}, 1) with Bu = [I 0], D = [0 d]
    u = np.c_[d.transition_offsets, np.ones(T)]
    return pk, d, system, np.asarray(d.observations[1:], dtype=float), u


def test_smoother_reproduces_pykalmans_robot_smoothed_means():
    # the data set's smoothed means were computed outside pykalman (MATLAB, per its DESCR); its first
    # reading is masked, so our y_1 is its z_1 and our prior its x_0 (the time conventions agree)
    _, d, system, y, u = _robot()
    sm = smooth(system, y, u=u)
    np.testing.assert_allclose(sm.mean, d.smoothed_state_means[1:], atol=1e-8, rtol=0)
    np.testing.assert_allclose(sm.cov, d.smoothed_state_covariances[1:], atol=1e-8, rtol=0)


def test_log_likelihood_matches_pykalman_on_the_robot_data():
    pk, d, system, y, u = _robot()
    kf = pk.KalmanFilter(
        transition_matrices=d.transition_matrix,
        observation_matrices=d.observation_matrix,
        transition_covariance=d.transition_covariance,
        observation_covariance=d.observation_covariance,
        transition_offsets=d.transition_offsets,
        observation_offsets=d.observation_offset,
        initial_state_mean=d.initial_state_mean,
        initial_state_covariance=d.initial_state_covariance,
    )
    assert abs(float(tk.kalman_log_likelihood(system, y, u=u)) - kf.loglikelihood(d.observations)) < 1e-8


@pytest.mark.parametrize("method", ["tobit", "adf", "dropping"])
def test_censored_smoothers_without_censoring_are_the_rts_smoother(method):
    system, rng = _model(seed=2)
    T = 8
    y = rng.normal(size=(T, 1))
    u = rng.normal(size=(T, 1))
    ref = smooth(system, y, u=u)
    got = smooth(system, y, u=u, censoring=tk.Censoring(), method=method)
    np.testing.assert_allclose(got.mean, ref.mean, atol=1e-12, rtol=0)
    np.testing.assert_allclose(got.cov, ref.cov, atol=1e-12, rtol=0)


def test_adf_smoother_at_the_last_step_is_the_adf_filter_and_censoring_pulls_below_the_limit():
    system, rng = _model(seed=4, R=0.05)
    y = np.array([[0.8], [0.0], [0.0], [0.0], [0.9]])  # three readings censored at 0
    cens = tk.Censoring(lower=0.0)
    f = tk.AssumedDensityTobitFilter(system, cens, order="uncensored_first").filter(y)
    sm = smooth(system, y, censoring=cens, method="adf")
    np.testing.assert_allclose(sm.mean[-1], f.mean[-1], atol=1e-12, rtol=0)
    C = system.C.at(1)
    assert np.all(sm.mean[1:4] @ C.T < 0.0)  # the latent readings sit below the limit


def test_dropping_smoother_with_the_indicator_is_the_kalman_smoother_without_the_flagged_readings():
    system, rng = _model(seed=6)
    y = np.abs(rng.normal(size=(6, 1)))
    y[2] = 0.0  # at the limit but recorded as uncensored
    y[4] = 0.0
    flags = np.zeros((6, 1), bool)
    flags[4] = True
    got = smooth(system, y, censoring=tk.Censoring(lower=0.0), censored=flags, method="dropping")
    ym = y.copy()
    ym[4] = np.nan
    ref = smooth(system, ym)
    np.testing.assert_allclose(got.mean, ref.mean, atol=1e-12, rtol=0)


def test_rts_handles_a_singular_predicted_covariance_exact_readings_of_an_ar2():
    from tobitkf.inference.censored_ar import ar_state_space

    system = ar_state_space([0.0], 1.0, [0.5, 0.3])  # Q = e1 e1' sigma^2 (singular), R = 0
    y = np.array([[0.3], [-0.2], [np.nan], [0.4], [0.1]])
    sm = smooth(system, y, u=np.ones((5, 1)))
    assert np.all(np.isfinite(sm.mean)) and np.all(np.isfinite(sm.cov))
    np.testing.assert_allclose(sm.mean[[0, 1, 3, 4], 0], y[[0, 1, 3, 4], 0], atol=1e-10)  # exact readings
    # the missing value: the Gaussian conditional of a stationary AR(2) given its neighbours
    from tobitkf.inference.censored_ar import ar_autocovariance

    g = ar_autocovariance([0.5, 0.3], 1.0, 6)
    G = g[np.abs(np.subtract.outer(range(5), range(5)))]
    o = [0, 1, 3, 4]
    m = G[2, o] @ np.linalg.solve(G[np.ix_(o, o)], y[o, 0])
    assert abs(sm.mean[2, 0] - m) < 1e-10


@pytest.mark.parametrize("lag", [0, 1, 3])
def test_fixed_lag_equals_the_fixed_interval_smoother_of_the_data_so_far(lag):
    system, rng = _model(seed=7)
    system = tk.LinearSystem(
        A=system.A.at(0), C=system.C.at(1), Q=system.Q.at(0), R=system.R.at(1), x0=system.x0, P0=system.P0
    )
    y = rng.normal(size=(9, 1))
    y[5] = np.nan
    fl = FixedLagSmoother(tk.KalmanFilter(system), lag=lag)
    st = fl.init()
    for K in range(1, 10):
        st = fl.step(st, y[K - 1])
        k, mean, cov = fl.estimate(st)
        assert k == max(K - lag, 0) or k == K - lag
        if k >= 1:
            ref = smooth(system, y[:K])
            np.testing.assert_allclose(mean, ref.mean[k - 1], atol=1e-10, rtol=0)
            np.testing.assert_allclose(cov, ref.cov[k - 1], atol=1e-10, rtol=0)
    run = fl.run(y)
    full = smooth(system, y)
    for k in range(1, 10):
        ref = smooth(system, y[: min(k + lag, 9)])
        np.testing.assert_allclose(run.mean[k - 1], ref.mean[k - 1], atol=1e-10, rtol=0)
    np.testing.assert_allclose(run.mean[-1], full.mean[-1], atol=1e-10, rtol=0)


def test_fixed_lag_runs_the_censored_filters_too():
    system, _ = _model(seed=8)
    system = tk.LinearSystem(
        A=system.A.at(0), C=system.C.at(1), Q=system.Q.at(0), R=system.R.at(1), x0=system.x0, P0=system.P0
    )
    y = np.array([[0.5], [0.0], [0.0], [0.7]])
    cens = tk.Censoring(lower=0.0)
    adf = tk.AssumedDensityTobitFilter(system, cens, order="uncensored_first")
    run = FixedLagSmoother(adf, lag=10).run(y)
    np.testing.assert_allclose(run.mean, smooth(system, y, censoring=cens, method="adf").mean, atol=1e-10, rtol=0)


def test_smoother_errors_name_the_argument():
    system, _ = _model()
    y = np.zeros((3, 1))
    with pytest.raises(ValidationError, match="method"):
        smooth(system, y, method="nope")
    with pytest.raises(ValidationError, match="censoring"):
        smooth(system, y, method="adf")
    with pytest.raises(ValidationError, match="lag"):
        FixedLagSmoother(tk.KalmanFilter(system), lag=-1)
    with pytest.raises(ValidationError, match="estimator"):
        FixedLagSmoother(object(), lag=1)
    res = tk.KalmanFilter(system).filter(y, u=np.zeros((3, 1)), outputs="last")
    with pytest.raises(ValidationError, match="filtered"):
        rts_smooth(res, system)
    with pytest.raises(ValidationError, match="censored"):
        smooth(
            system,
            np.array([[0.5], [1.0], [0.2]]),
            censoring=tk.Censoring(lower=0.0),
            censored=np.array([[True], [False], [False]]),
            method="adf",
        )
