"""Tests of the batched Kalman filter and the dropping ("IKF") baseline (``tobitkf.filters.kalman``).

The oracle is a plain per-run, per-step Kalman filter written here from Miller (2.3)–(2.6)
with the package's time convention (x_0 ~ N(x0, P0) is the prior, y_1 at index 0),
using explicit row removal for skipped channels.
"""

from __future__ import annotations

import numpy as np
import pytest

from tobitkf import (
    Censoring,
    DroppingKalmanFilter,
    KalmanFilter,
    LinearSystem,
    ShapeError,
    ValidationError,
    kalman_filter,
    simulate,
)

ATOL = 1e-12


def reference_kf(A, C, Q, R, x0, P0, y, *, Bu=None, D=None, u=None, G=None):
    """Per-run KF. A, C, Q, R, Bu, D, G are callables of k; y (T, m) with NaN = drop that row."""
    x, P = np.array(x0, float), np.array(P0, float)
    T = y.shape[0]
    means, covs, pmeans, pcovs = [], [], [], []
    for k in range(1, T + 1):
        Ak = A(k - 1)
        Qd = Q(k - 1) if G is None else G(k - 1) @ Q(k - 1) @ G(k - 1).T
        x = Ak @ x + (Bu(k) @ u[k - 1] if Bu is not None else 0.0)
        P = Ak @ P @ Ak.T + Qd
        pmeans.append(x.copy())
        pcovs.append(P.copy())
        keep = ~np.isnan(y[k - 1])
        if keep.any():
            Ck, Rk = C(k)[keep], R(k)[np.ix_(keep, keep)]
            yhat = Ck @ x + (D(k)[keep] @ u[k - 1] if D is not None else 0.0)
            S = Ck @ P @ Ck.T + Rk
            K = np.linalg.solve(S, Ck @ P).T
            x = x + K @ (y[k - 1][keep] - yhat)
            P = (np.eye(len(x)) - K @ Ck) @ P
        means.append(x.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), np.array(pmeans), np.array(pcovs)


def const(M):
    M = np.asarray(M, float)
    return lambda k: M


def _cv_system(**kw):
    dt = 0.1
    A = np.array([[1.0, dt], [0.0, 1.0]])
    C = np.array([[1.0, 0.0], [0.3, 1.0]])
    Q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) * 0.5
    R = np.array([[0.2, 0.05], [0.05, 0.1]])  # the KF allows correlated measurement noise
    return LinearSystem(A=A, C=C, Q=Q, R=R, x0=[0.5, -0.2], P0=np.diag([1.0, 2.0]), **kw), (A, C, Q, R)


def _assert_close(a, b, atol=ATOL):
    np.testing.assert_allclose(a, b, rtol=0, atol=atol)


def test_scalar_closed_form():
    """Prior N(0, 1), one measurement 2 with R = 1, Q = 0: posterior N(1, 0.5)."""
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    out = KalmanFilter(sys).filter(np.array([[2.0]]))
    assert out.mean.shape == (1, 1) and out.cov.shape == (1, 1, 1)
    assert out.mean[0, 0] == pytest.approx(1.0, abs=1e-15)
    assert out.cov[0, 0, 0] == pytest.approx(0.5, abs=1e-15)
    # time convention: index 0 holds the first measurement's posterior; the prediction is the prior
    assert out.pred_mean[0, 0] == 0.0 and out.pred_cov[0, 0, 0] == 1.0


@pytest.mark.parametrize(
    "P0,update,tol",
    [
        (1e4, "standard", 1e-9),
        # with a nearly flat prior the standard form (I - KC)P cancels catastrophically
        # (1e12 - 0.99999999999996e12); the Joseph form keeps the posterior accurate
        (1e12, "joseph", 1e-9),
    ],
)
def test_scalar_random_constant_is_running_average(P0, update, tol):
    """Random constant, Q = 0, flat prior: the KF estimate is the running average, variance R/k."""
    R = 0.04
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[R]], x0=[0.0], P0=[[P0]])
    y = np.array([1.0, 2.0, 6.0, -1.0])[:, None]
    out = KalmanFilter(sys, covariance_update=update).filter(y)
    k = np.arange(1, 5)
    # exact Bayesian posterior with prior N(0, P0): precision 1/P0 + k/R
    prec = 1 / P0 + k / R
    np.testing.assert_allclose(out.mean[:, 0], (np.cumsum(y[:, 0]) / R) / prec, rtol=tol)
    np.testing.assert_allclose(out.cov[:, 0, 0], 1 / prec, rtol=tol)


def test_matches_reference_two_by_two():
    sys, (A, C, Q, R) = _cv_system()
    data = simulate(sys, steps=40, runs=3, seed=11)
    out = KalmanFilter(sys).filter(data.y)
    for i in range(3):
        ref = reference_kf(const(A), const(C), const(Q), const(R), sys.x0, sys.P0, data.y[i])
        for got, want in zip((out.mean[i], out.cov[i], out.pred_mean[i], out.pred_cov[i]), ref):
            _assert_close(got, want)


def test_time_varying_and_callable_matrices():
    T = 25
    rng = np.random.default_rng(5)
    th = 0.1 * np.arange(T)
    A_arr = np.stack([[[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]] for t in th]) * 0.98
    C_fn = lambda k: np.array([[1.0, 0.1 * k], [0.0, 1.0]])  # noqa: E731
    R_arr = np.stack([np.diag([0.1 + 0.01 * k, 0.2]) for k in range(1, T + 1)])
    Q_fn = lambda k: np.eye(2) * (0.01 + 0.001 * k)  # noqa: E731
    sys = LinearSystem(A=A_arr, C=C_fn, Q=Q_fn, R=R_arr, x0=[1.0, 0.0], P0=np.eye(2))
    y = rng.standard_normal((2, T, 2))
    out = KalmanFilter(sys).filter(y)
    for i in range(2):
        ref = reference_kf(lambda k: A_arr[k], C_fn, Q_fn, lambda k: R_arr[k - 1], sys.x0, sys.P0, y[i])
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])


def test_control_inputs_and_noise_input_matrix():
    T = 20
    A = np.array([[1.0, 0.1], [0.0, 0.95]])
    Bu = np.array([[0.0], [0.1]])
    D = np.array([[0.5]])
    G = np.array([[0.05], [1.0]])
    sys = LinearSystem(A=A, C=[[1.0, 0.0]], Q=[[0.02]], R=[[0.1]], x0=[0.0, 0.0], P0=np.eye(2), B=G, Bu=Bu, D=D)
    u = np.sin(0.3 * np.arange(T))[:, None]
    data = simulate(sys, steps=T, runs=3, inputs=u, seed=2)
    out = KalmanFilter(sys).filter(data.y, u=u)
    for i in range(3):
        ref = reference_kf(
            const(A),
            const([[1.0, 0.0]]),
            const([[0.02]]),
            const([[0.1]]),
            sys.x0,
            sys.P0,
            data.y[i],
            Bu=const(Bu),
            D=const(D),
            u=u,
            G=const(G),
        )
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])
    # per-run inputs (N, T, p) equal the shared (T, p) input when they are the same
    out2 = KalmanFilter(sys).filter(data.y, u=np.broadcast_to(u, (3, T, 1)))
    _assert_close(out2.mean, out.mean, atol=0)


def test_batched_equals_per_run():
    sys, _ = _cv_system()
    rng = np.random.default_rng(0)
    y = rng.standard_normal((2, 3, 15, 2))
    y[0, 1, 4, 0] = np.nan  # a missing sample forces per-run covariances
    out = KalmanFilter(sys).filter(y)
    assert out.mean.shape == (2, 3, 15, 2) and out.cov.shape == (2, 3, 15, 2, 2)
    for i in range(2):
        for j in range(3):
            one = KalmanFilter(sys).filter(y[i, j])
            assert one.mean.shape == (15, 2)
            _assert_close(out.mean[i, j], one.mean)
            _assert_close(out.cov[i, j], one.cov)
            _assert_close(out.pred_cov[i, j], one.pred_cov)


def test_joseph_equals_standard():
    sys, _ = _cv_system()
    data = simulate(sys, steps=60, runs=4, seed=8)
    y = data.y.copy()
    y[1, 10, 1] = np.nan
    a = KalmanFilter(sys).filter(y)
    b = KalmanFilter(sys, covariance_update="joseph").filter(y)
    _assert_close(a.mean, b.mean)
    _assert_close(a.cov, b.cov)


def test_nan_is_a_skipped_channel():
    sys, (A, C, Q, R) = _cv_system()
    data = simulate(sys, steps=30, runs=2, seed=4)
    y = data.y.copy()
    y[0, 3, 0] = np.nan  # one channel missing
    y[0, 7, :] = np.nan  # the whole step missing: pure prediction
    y[1, 12, 1] = np.nan
    out = KalmanFilter(sys).filter(y)
    for i in range(2):
        ref = reference_kf(const(A), const(C), const(Q), const(R), sys.x0, sys.P0, y[i])
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])
    assert np.isfinite(out.mean).all()
    _assert_close(out.mean[0, 7], out.pred_mean[0, 7], atol=0)
    _assert_close(out.cov[0, 7], out.pred_cov[0, 7], atol=0)
    # the skip mask does the same as NaN
    skip = np.isnan(y)
    out2 = kalman_filter(sys, np.nan_to_num(y, nan=123.0), skip=skip)
    _assert_close(out2.mean, out.mean, atol=0)
    _assert_close(out2.cov, out.cov, atol=0)


def test_prior_override_per_run():
    sys, (A, C, Q, R) = _cv_system()
    y = np.random.default_rng(1).standard_normal((3, 10, 2))
    x0 = np.array([[0.0, 0.0], [1.0, 1.0], [-2.0, 3.0]])
    P0 = np.stack([np.eye(2) * s for s in (0.5, 1.0, 4.0)])
    out = KalmanFilter(sys).filter(y, x0=x0, P0=P0)
    for i in range(3):
        ref = reference_kf(const(A), const(C), const(Q), const(R), x0[i], P0[i], y[i])
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])


def test_covariance_shared_across_runs_is_read_only_but_equal():
    sys, _ = _cv_system()
    y = np.random.default_rng(1).standard_normal((4, 6, 2))
    out = KalmanFilter(sys).filter(y)
    for i in range(1, 4):
        _assert_close(out.cov[i], out.cov[0], atol=0)


# ---------------------------------------------------------------------------------------------
# DroppingKalmanFilter ("IKF": skip censored readings)
# ---------------------------------------------------------------------------------------------
def test_dropping_kf_holds_prediction_on_censored_steps():
    sys = LinearSystem(A=[[0.999]], C=[[1.0]], Q=[[0.01]], R=[[0.0025]], x0=[0.05], P0=[[0.05]])
    cens = Censoring(lower=0.0)
    data = simulate(sys, steps=200, runs=3, censoring=cens, seed=9)
    censored = data.y_latent <= 0.0
    assert censored.mean() > 0.2 and (~censored).mean() > 0.2  # both kinds of steps occur
    out = DroppingKalmanFilter(sys, cens).filter(data.y)
    np.testing.assert_array_equal(out.extras["censored"], censored)
    hold = censored[..., 0]
    _assert_close(out.mean[hold], out.pred_mean[hold], atol=0)
    _assert_close(out.cov[hold], out.pred_cov[hold], atol=0)
    # equals the reference KF with the censored samples removed
    for i in range(3):
        y = np.where(censored[i], np.nan, data.y[i])
        ref = reference_kf(const([[0.999]]), const([[1.0]]), const([[0.01]]), const([[0.0025]]), sys.x0, sys.P0, y)
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])


def test_dropping_kf_drops_only_censored_rows():
    sys, (A, C, Q, R) = _cv_system()
    cens = Censoring(lower=[0.0, -np.inf], upper=[np.inf, 0.3])
    data = simulate(sys, steps=40, runs=2, censoring=cens, seed=21)
    out = DroppingKalmanFilter(sys, cens).filter(data.y)
    at = (data.y_latent <= np.array([0.0, -np.inf])) | (data.y_latent >= np.array([np.inf, 0.3]))
    assert at.any() and (~at).any()
    for i in range(2):
        ref = reference_kf(const(A), const(C), const(Q), const(R), sys.x0, sys.P0, np.where(at[i], np.nan, data.y[i]))
        _assert_close(out.mean[i], ref[0])
        _assert_close(out.cov[i], ref[1])


def test_dropping_kf_without_censoring_is_the_kf():
    sys, _ = _cv_system()
    data = simulate(sys, steps=30, runs=2, seed=1)
    a = DroppingKalmanFilter(sys, Censoring()).filter(data.y)
    b = KalmanFilter(sys).filter(data.y)
    _assert_close(a.mean, b.mean, atol=0)
    _assert_close(a.cov, b.cov, atol=0)


def test_dropping_kf_batch_shape_restored():
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    y = np.clip(np.random.default_rng(0).standard_normal((2, 3, 8, 1)), 0.0, None)
    out = DroppingKalmanFilter(sys, Censoring(lower=0.0)).filter(y)
    assert out.mean.shape == (2, 3, 8, 1) and out.cov.shape == (2, 3, 8, 1, 1)
    assert out.extras["censored"].shape == (2, 3, 8, 1)
    one = DroppingKalmanFilter(sys, Censoring(lower=0.0)).filter(y[1, 2])
    _assert_close(out.mean[1, 2], one.mean, atol=0)


# ---------------------------------------------------------------------------------------------
# input checks
# ---------------------------------------------------------------------------------------------
def test_kf_input_validation():
    sys, _ = _cv_system()
    kf = KalmanFilter(sys)
    with pytest.raises(ShapeError, match=r"y: expected last axis of length m=2"):
        kf.filter(np.zeros((5, 3)))
    with pytest.raises(ShapeError, match=r"y: expected \(\.\.\., T, 2\)"):
        kf.filter(np.zeros(5))
    with pytest.raises(ValidationError, match="y: expected finite numbers, found inf"):
        kf.filter(np.full((5, 2), np.inf))
    with pytest.raises(
        ValidationError, match="covariance_update: expected one of 'standard', 'joseph', 'square_root', got 'fast'"
    ):
        KalmanFilter(sys, covariance_update="fast")
    with pytest.raises(ValidationError, match="system: expected a LinearSystem, got dict"):
        KalmanFilter({})
    with pytest.raises(ShapeError, match="u: the system has no control input"):
        kf.filter(np.zeros((5, 2)), u=np.zeros((5, 1)))
    with pytest.raises(ValidationError, match=r"skip: expected \(\.\.\., 5, 2\)"):
        kalman_filter(sys, np.zeros((5, 2)), skip=np.zeros((4, 2), bool))
    with pytest.raises(ShapeError, match="x0/P0"):
        kf.filter(np.zeros((5, 2)), x0=np.zeros(3))
    with pytest.raises(ShapeError, match="A: time-indexed array has 3 steps, 5 needed"):
        KalmanFilter(
            LinearSystem(A=np.stack([np.eye(2)] * 3), C=np.eye(2), Q=np.eye(2), R=np.eye(2), x0=[0, 0], P0=np.eye(2))
        ).filter(np.zeros((5, 2)))


def test_dropping_kf_input_validation():
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(ValidationError, match="censoring: expected a Censoring, got float"):
        DroppingKalmanFilter(sys, 0.0)
    with pytest.raises(ValidationError, match="rtol: expected a non-negative tolerance"):
        DroppingKalmanFilter(sys, Censoring(lower=0.0), rtol=-1.0)
    with pytest.raises(ShapeError, match="censoring limits: expected 1 channel"):
        DroppingKalmanFilter(sys, Censoring(lower=[0.0, 0.0]))
    with pytest.raises(ValidationError, match="outside its censoring limits"):
        DroppingKalmanFilter(sys, Censoring(lower=0.0)).filter(np.array([[0.5], [-0.5]]))


def test_batched_without_missing_samples_shares_covariance():
    """No NaN: the shared-covariance path, with a two-axis batch, still equals per-run filtering."""
    sys, _ = _cv_system()
    y = np.random.default_rng(3).standard_normal((2, 3, 12, 2))
    out = KalmanFilter(sys).filter(y)
    assert out.cov.shape == (2, 3, 12, 2, 2)
    for i in range(2):
        for j in range(3):
            one = KalmanFilter(sys).filter(y[i, j])
            _assert_close(out.mean[i, j], one.mean)
            _assert_close(out.cov[i, j], one.cov)


@pytest.mark.parametrize("which", ["kf", "ikf"])
def test_prior_override_with_multi_axis_batch(which):
    """x0 (..., n) and P0 (..., n, n) with the same leading axes as y (..., T, m) (docstring of kalman_filter)."""
    sys, _ = _cv_system()
    rng = np.random.default_rng(2)
    y = np.clip(rng.standard_normal((2, 3, 10, 2)), -0.5, None)
    x0 = rng.standard_normal((2, 3, 2))
    P0 = np.eye(2) * rng.uniform(0.5, 2.0, (2, 3))[..., None, None]
    f = KalmanFilter(sys) if which == "kf" else DroppingKalmanFilter(sys, Censoring(lower=-0.5))
    out = f.filter(y, x0=x0, P0=P0)
    for i in range(2):
        for j in range(3):
            one = f.filter(y[i, j], x0=x0[i, j], P0=P0[i, j])
            _assert_close(out.mean[i, j], one.mean)
            _assert_close(out.cov[i, j], one.cov)
    with pytest.raises(ShapeError, match="x0/P0"):
        f.filter(y, x0=rng.standard_normal((3, 2, 2)))  # same number of runs, wrong layout


def test_callable_matrices_are_validated_over_the_horizon():
    """A callable returning NaN or a non-PSD covariance at a later step is rejected, as in simulate."""
    bad_r = LinearSystem(
        A=np.eye(1), C=np.eye(1), Q=np.eye(1), R=lambda k: np.array([[1.0 - 0.5 * k]]), x0=[0.0], P0=np.eye(1)
    )
    with pytest.raises(ValidationError, match=r"R\(3\): expected a positive semi-definite matrix"):
        KalmanFilter(bad_r).filter(np.zeros((4, 1)))
    nan_a = LinearSystem(
        A=lambda k: np.array([[np.nan if k == 2 else 1.0]]),
        C=np.eye(1),
        Q=np.eye(1),
        R=np.eye(1),
        x0=[0.0],
        P0=np.eye(1),
    )
    with pytest.raises(ValidationError, match=r"A\(2\): expected finite numbers, found NaN"):
        KalmanFilter(nan_a).filter(np.zeros((4, 1)))
