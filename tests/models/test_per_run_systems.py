"""A LinearSystem with one model per run (``batch_ndim``): every run of a batch filtered with its own A, C, Q, R
equals that run filtered alone with its own system (KF, TKF, the censored ADF, their smoothers and likelihoods;
numpy and compiled paths), limits given per run, and the errors for run axes that do not fit."""

import numpy as np
import pytest

import tobitkf as tk

N, T, n, m = 3, 12, 2, 1


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(0)
    A = np.stack([[[0.9, 0.1 * i], [0.0, 0.7]] for i in range(N)])
    A = A[:, None] * (1 + 0.05 * rng.standard_normal((N, T, 1, 1)))  # per run and per step
    Q = np.stack([np.diag([0.2 + 0.1 * i, 0.1]) for i in range(N)])  # per run, constant
    C = np.array([[1.0, 0.5]])[None] * (1.0 + np.arange(N))[:, None, None]  # per run
    R = (0.1 + np.arange(N))[:, None, None] * np.eye(1)
    y = rng.standard_normal((N, T, m))
    y[0, 3] = np.nan
    system = tk.LinearSystem(A, C, Q, R, [0.0, 0.0], np.eye(2), batch_ndim=1)
    alone = [tk.LinearSystem(A[i], C[i], Q[i], R[i], [0.0, 0.0], np.eye(2)) for i in range(N)]
    return system, alone, y


def _censored(y, lo=-0.3):
    return np.maximum(y, lo)


FILTERS = {
    "kf": (lambda s, b: tk.KalmanFilter(s, backend=b), False),
    "tkf": (lambda s, b: tk.TobitKalmanFilter(s, tk.Censoring(lower=-0.3), backend=b), True),
    "adf": (lambda s, b: tk.AssumedDensityTobitFilter(s, tk.Censoring(lower=-0.3), backend=b), True),
}


@pytest.mark.parametrize("backend", ["numpy", "auto"])
@pytest.mark.parametrize("family", sorted(FILTERS))
def test_batched_runs_equal_each_run_alone(case, family, backend):
    system, alone, y = case
    make, censored = FILTERS[family]
    y = _censored(y) if censored else y
    res, sm = make(system, backend).filter(y), make(system, backend).smooth(y)
    ll = make(system, backend).log_likelihood(y)
    assert system.per_run and system.batch_shape == (N,) and not system.time_invariant
    for i in range(N):
        one = make(alone[i], backend)
        r1, s1 = one.filter(y[i]), one.smooth(y[i])
        for got, want in ((res.mean[i], r1.mean), (res.cov[i], r1.cov), (sm.mean[i], s1.mean), (sm.cov[i], s1.cov)):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        assert ll[i] == pytest.approx(one.log_likelihood(y[i]), abs=1e-12)


def test_shared_axis_of_size_one_is_the_shared_system(case):
    """Run axes of size 1 are shared: the same numbers as the plain system."""
    _, alone, y = case
    s0 = alone[0]
    wide = tk.LinearSystem(
        s0.A.array[None], s0.C.array[None], s0.Q.array[None], s0.R.array[None], [0, 0], np.eye(2), batch_ndim=1
    )
    assert wide.batch_shape == (1,) and not wide.per_run
    a = tk.KalmanFilter(wide).filter(y).mean
    b = tk.KalmanFilter(s0).filter(y).mean
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)


def test_adf_compiled_equals_numpy_with_per_run_limits(case):
    """The censored ADF through the compiled loop (per-run A, C... here C per run is refused by the compiled
    spec, so a shared C) with limits given per run equals the numpy path, and each run alone."""
    system, alone, y = case
    shared_c = tk.LinearSystem(
        system.A.array, np.array([[1.0, 0.5]]), system.Q.array, system.R.array, [0, 0], np.eye(2), batch_ndim=1
    )
    lo = np.full((N, T, m), -0.3)
    lo[1] = -0.6
    hi = np.full((N, T, m), np.inf)
    hi[2] = 0.8
    yy = np.minimum(np.maximum(y, lo), hi)
    got = {}
    for backend in ("numba", "numpy"):
        f = tk.AssumedDensityTobitFilter(shared_c, tk.Censoring(), backend=backend, order="uncensored_first")
        got[backend] = f.filter(yy, lower=lo, upper=hi)
    for key in ("mean", "cov"):
        np.testing.assert_allclose(getattr(got["numba"], key), getattr(got["numpy"], key), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        got["numba"].extras["log_likelihood"], got["numpy"].extras["log_likelihood"], rtol=0, atol=1e-12
    )
    for i in range(N):
        s1 = tk.LinearSystem(system.A.array[i], [[1.0, 0.5]], system.Q.array[i], system.R.array[i], [0, 0], np.eye(2))
        cen = tk.Censoring(lower=lo[i], upper=hi[i])
        want = tk.adf_log_likelihood(s1, cen, yy[i], per_step=True)
        np.testing.assert_allclose(got["numpy"].extras["log_likelihood"][i], want, rtol=0, atol=1e-12)
    assert (yy == lo).any() and (yy == hi).any()


def test_per_run_likelihood_matches_adf_log_likelihood(case):
    system, _, y = case
    yc = _censored(y)
    a = tk.adf_log_likelihood(system, tk.Censoring(lower=-0.3), yc)
    b = tk.AssumedDensityTobitFilter(system, tk.Censoring(lower=-0.3), order="uncensored_first").log_likelihood(yc)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert a.shape == (N,)


def test_run_axes_that_do_not_fit_are_refused(case):
    system, _, y = case
    with pytest.raises(tk.ShapeError, match="run axes"):
        tk.KalmanFilter(system).filter(y[:2])
    with pytest.raises(tk.ShapeError, match="do not broadcast"):
        tk.LinearSystem(
            np.eye(2)[None].repeat(3, 0),
            [[1.0, 0.0]],
            np.eye(2)[None].repeat(2, 0),
            [[1.0]],
            [0, 0],
            np.eye(2),
            batch_ndim=1,
        )
    with pytest.raises(tk.ShapeError, match="A: expected"):
        tk.LinearSystem(np.zeros((2, 2, 2, 2, 2)), [[1.0, 0.0]], np.eye(2), [[1.0]], [0, 0], np.eye(2), batch_ndim=1)
    with pytest.raises(tk.ValidationError, match="batch_ndim"):
        tk.LinearSystem(np.eye(2), [[1.0, 0.0]], np.eye(2), [[1.0]], [0, 0], np.eye(2), batch_ndim=-1)


def test_reading_outside_its_per_run_limits_is_refused(case):
    system, _, y = case
    lo = np.full((N, T, m), 10.0)
    with pytest.raises(tk.ValidationError, match="outside its limits"):
        tk.AssumedDensityTobitFilter(system, tk.Censoring()).filter(y, lower=lo)


def test_per_run_noise_psd_is_checked():
    Q = np.stack([np.eye(2), -np.eye(2)])
    with pytest.raises(tk.ValidationError, match="Q"):
        tk.LinearSystem(np.eye(2), [[1.0, 0.0]], Q, [[1.0]], [0, 0], np.eye(2), batch_ndim=1)
