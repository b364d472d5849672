"""Continuous-time models read at irregular times: exact discretisation (analytic OU, a brute-force Euler
sum), equal spacing = the discrete model, a gap of 2Δ = two steps with a missing reading, the grid smoother."""

import numpy as np
import pytest
from scipy.linalg import expm

import tobitkf as tk
from tobitkf.models.continuous import expm_batch, time_values

AC2 = np.array([[-0.3, 1.0], [-0.5, -0.2]])
QC2 = np.array([[0.5, 0.1], [0.1, 0.3]])
BC2 = np.array([[0.4], [-1.0]])


def _model2(**kw):
    return tk.ContinuousLinearSystem(
        AC2, QC2, [[1.0, 0.0]], [[0.2]], [0.3, -0.1], [[1.0, 0.2], [0.2, 0.5]], Bc=BC2, **kw
    )


@pytest.mark.parametrize("dt", [0.0, 0.01, 0.5, 2.0, 17.0])
def test_ou_matches_the_analytic_transition_and_variance(dt):
    theta, sigma2 = 0.7, 1.9
    ou = tk.ContinuousLinearSystem([[-theta]], [[sigma2]], [[1.0]], [[0.1]], [0.0], [[1.0]])
    A, Q, B = ou.discretize(dt)
    assert B is None
    assert np.isclose(A[0, 0], np.exp(-theta * dt), rtol=1e-13, atol=0)
    assert np.isclose(Q[0, 0], sigma2 * (1 - np.exp(-2 * theta * dt)) / (2 * theta), rtol=1e-11, atol=1e-300)


def test_the_batched_exponential_equals_scipy():
    rng = np.random.default_rng(0)
    M = rng.normal(size=(60, 4, 4)) * rng.uniform(0, 30, size=(60, 1, 1))
    M[:5] = 0.0
    M[5:10] = np.triu(rng.normal(size=(5, 4, 4)), 1)  # nilpotent (a random walk's Van Loan block)
    ref = np.stack([expm(m) for m in M])
    scale = np.abs(ref).max(axis=(-1, -2), keepdims=True)
    assert np.all(np.abs(expm_batch(M) - ref) <= 1e-11 * scale)
    assert np.array_equal(expm_batch(np.zeros((2, 3, 3))), np.broadcast_to(np.eye(3), (2, 3, 3)))


def _euler_by_doubling(Ac, Qc, Bc, dt, levels=22):
    """The Euler recursion P <- F P F^T + Qc h, x <- F x + Bc h u with F = I + Ac h over 2**levels steps of
    h = dt / 2**levels, summed exactly by doubling (F_2N = F_N^2, P_2N = F_N P_N F_N^T + P_N, G_2N = F_N G_N + G_N)."""
    h = dt / 2**levels
    F = np.eye(len(Ac)) + Ac * h
    P = Qc * h
    G = Bc * h
    for _ in range(levels):
        P = F @ P @ F.T + P
        G = F @ G + G
        F = F @ F
    return F, P, G


def test_van_loan_and_zero_order_hold_match_a_fine_euler_sum_in_2d():
    dt = 0.7
    A, Q, B = _model2().discretize(dt)
    F, P, G = _euler_by_doubling(AC2, QC2, BC2, dt)
    # Euler's error is O(h) = O(dt / 4e6): relative 1e-5 is far above it and far below any real mistake
    assert np.allclose(A, F, rtol=0, atol=1e-5)
    assert np.allclose(Q, P, rtol=0, atol=1e-5 * np.abs(P).max())
    assert np.allclose(B, G, rtol=0, atol=1e-5 * np.abs(G).max())
    assert np.allclose(A, expm(AC2 * dt), rtol=0, atol=1e-14)


def test_batched_gaps_equal_one_at_a_time():
    sys_ = _model2()
    gaps = np.array([0.3, 1.2, 0.3, 0.0])
    A, Q, B = sys_.discretize(gaps)
    for i, d in enumerate(gaps):
        a, q, b = sys_.discretize(d)
        assert np.array_equal(A[i], a) and np.array_equal(Q[i], q) and np.array_equal(B[i], b)
    assert np.array_equal(A[3], np.eye(2)) and not Q[3].any() and not B[3].any()


def _data(T, seed=0, m=1):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(3, T, m)), rng.normal(size=(3, T, 1))


def test_equally_spaced_times_equal_the_discrete_model():
    dt, T = 0.4, 12
    cont = _model2()
    A, Q, B = cont.discretize(dt)
    disc = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=Q, R=[[0.2]], x0=cont.x0, P0=cont.P0, Bu=B)
    y, u = _data(T)
    times = dt * np.arange(1, T + 1)
    kf_c, kf_d = tk.KalmanFilter(cont), tk.KalmanFilter(disc)
    a = tk.KalmanFilter(cont.at_times(times, start=0.0)).filter(y, u=u)
    b = kf_d.filter(y, u=u)
    assert np.allclose(a.mean, b.mean, rtol=0, atol=1e-12) and np.allclose(a.cov, b.cov, rtol=0, atol=1e-12)
    sa = kf_c.smooth(y, u=u, times=times, start=0.0)
    sb = kf_d.smooth(y, u=u)
    assert np.allclose(sa.mean, sb.mean, rtol=0, atol=1e-12) and np.allclose(sa.cov, sb.cov, rtol=0, atol=1e-12)
    la = tk.kalman_log_likelihood(cont.at_times(times, start=0.0), y, u=u)
    assert np.allclose(la, kf_d.log_likelihood(y, u=u), rtol=0, atol=1e-10)
    # the unit-spaced view of the model is the discretisation over one time unit
    assert np.allclose(cont.transition(0), expm(AC2), rtol=0, atol=1e-14)


def _split(y, u, times, at):
    """The record with a missing reading inserted at time ``at`` (its input = the next reading's: the hold)."""
    i = int(np.searchsorted(times, at))
    y2 = np.insert(y, i, np.nan, axis=-2)
    u2 = np.insert(u, i, u[..., i, :], axis=-2)
    return y2, u2, np.insert(times, i, at), i


@pytest.mark.parametrize("family", ["kf", "tkf", "adf"])
def test_a_gap_of_two_steps_equals_two_steps_with_a_missing_reading(family):
    dt = 0.5
    times = dt * np.array([0.0, 1, 3, 4, 5, 7])
    y, u = _data(times.size, seed=3)
    y = np.maximum(y, -0.4)  # left-censored at -0.4
    cont = _model2()
    cens = tk.Censoring(lower=-0.4)
    make = {
        "kf": lambda: tk.KalmanFilter(cont),
        "tkf": lambda: tk.TobitKalmanFilter(cont, cens),
        "adf": lambda: tk.AssumedDensityTobitFilter(cont, cens, order="uncensored_first"),
    }[family]
    est = make()
    y2, u2, t2, i = _split(y, u, times, 2 * dt)
    keep = np.delete(np.arange(t2.size), i)
    f1, f2 = est.filter(y, u=u, times=times), est.filter(y2, u=u2, times=t2)
    assert np.allclose(f1.mean, f2.mean[:, keep], rtol=0, atol=1e-12)
    assert np.allclose(f1.cov, f2.cov[:, keep], rtol=0, atol=1e-12)
    s1, s2 = est.smooth(y, u=u, times=times), est.smooth(y2, u=u2, times=t2)
    assert np.allclose(s1.mean, s2.mean[:, keep], rtol=0, atol=1e-12)
    assert np.allclose(s1.cov, s2.cov[:, keep], rtol=0, atol=1e-12)
    l1, l2 = est.log_likelihood(y, u=u, times=times), est.log_likelihood(y2, u=u2, times=t2)
    assert np.allclose(l1, l2, rtol=0, atol=1e-11)
    if family == "adf":
        l3 = tk.log_likelihood(cont, y, u=u, censoring=cens, times=times)
        assert np.allclose(l1, l3, rtol=0, atol=1e-11)


def test_the_smoother_on_a_grid_equals_smoothing_on_the_union_by_hand():
    cont = _model2()
    cens = tk.Censoring(lower=-0.4)
    times = np.array([0.3, 1.0, 2.5, 4.0, 4.25])
    grid = np.arange(0.0, 6.0, 0.5)  # 1.0, 2.5 and 4.0 are both
    rng = np.random.default_rng(7)
    y = np.maximum(rng.normal(size=(times.size, 1)), -0.4)
    union = np.union1d(times, grid)
    yu = np.full((union.size, 1), np.nan)
    yu[np.searchsorted(union, times)] = y
    for est in (tk.KalmanFilter(cont), tk.AssumedDensityTobitFilter(cont, cens, order="uncensored_first")):
        on_grid = est.smooth(y, times=times, grid=grid)
        by_hand = est.smooth(yu, times=union)
        rows = np.searchsorted(union, grid)
        assert np.allclose(on_grid.mean, by_hand.mean[rows], rtol=0, atol=1e-12)
        assert np.allclose(on_grid.cov, by_hand.cov[rows], rtol=0, atol=1e-12)
        assert on_grid.mean.shape == (grid.size, 2) and np.array_equal(on_grid.times, grid)
    # through tk.smooth, with the censoring and inputs given on the grid (the sample times on the grid)
    times_g = grid[[1, 2, 5, 8, 9]]
    ug = rng.normal(size=(grid.size, 1))
    res = tk.smooth(cont, y, censoring=cens, times=times_g, grid=grid, u=ug)
    yg = np.full((grid.size, 1), np.nan)
    yg[[1, 2, 5, 8, 9]] = y
    ref = tk.smooth(cont, yg, censoring=cens, times=grid, u=ug)
    assert np.allclose(res.mean, ref.mean, rtol=0, atol=1e-12)


def test_dates_are_converted_with_the_model_unit():
    days = np.array(["2020-01-01", "2020-01-03", "2020-01-10"], dtype="datetime64[D]")
    assert np.array_equal(time_values(days), [0.0, 2.0, 9.0])
    assert np.allclose(time_values(days, unit="Y"), np.array([0.0, 2.0, 9.0]) / 365.25)
    cont = _model2()
    y = np.array([[0.1], [0.2], [-0.3]])
    a = tk.KalmanFilter(cont).filter(y, times=days)
    b = tk.KalmanFilter(cont).filter(y, times=[0.0, 2.0, 9.0])
    assert np.allclose(a.mean, b.mean, rtol=0, atol=1e-14)
    weekly = tk.ContinuousLinearSystem(AC2 * 7, QC2 * 7, [[1.0, 0.0]], [[0.2]], cont.x0, cont.P0, unit="W")
    c = tk.KalmanFilter(weekly).filter(y, times=days)
    assert np.allclose(c.mean, b.mean, rtol=0, atol=1e-12)


def test_refusals_name_the_problem():
    cont = _model2()
    y = np.zeros((3, 1))
    with pytest.raises(tk.ValidationError, match="duplicate time"):
        tk.KalmanFilter(cont).filter(y, times=[0.0, 1.0, 1.0])
    with pytest.raises(tk.ValidationError, match="out of order"):
        tk.KalmanFilter(cont).filter(y, times=[0.0, 2.0, 1.0])
    with pytest.raises(tk.ShapeError, match="one time per reading"):
        tk.KalmanFilter(cont).filter(y, times=[0.0, 1.0])
    disc = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="continuous time"):
        tk.KalmanFilter(disc).filter(y, times=[0.0, 1.0, 2.0])
    with pytest.raises(tk.ValidationError, match="not a mix"):
        tk.KalmanFilter(cont).smooth(y, times=[0.0, 1.0, 2.0], grid=np.array(["2020-01-01"], dtype="datetime64[D]"))
    with pytest.raises(tk.ValidationError, match="on the grid"):
        tk.KalmanFilter(cont).smooth(y, times=[0.0, 1.0, 2.5], grid=[0.0, 1.0, 2.0, 3.0], u=np.zeros((4, 1)))
    with pytest.raises(tk.ValidationError, match="before the first"):
        cont.at_times([0.0, 1.0], start=0.5)


def test_per_reading_limits_move_onto_the_union_grid():
    cont = _model2()
    times = np.array([0.5, 1.0, 2.0, 3.5])
    lo = np.array([[-0.4], [-0.2], [-0.4], [-0.1]])
    y = np.array([[-0.4], [0.3], [0.1], [-0.1]])  # the first and last at their own limits
    grid = np.array([0.0, 1.0, 1.5, 3.0, 4.0])
    adf = tk.AssumedDensityTobitFilter(cont, tk.Censoring(lower=lo), order="uncensored_first")
    res = adf.smooth(y, times=times, grid=grid)
    union = np.union1d(times, grid)
    yu = np.full((union.size, 1), np.nan)
    lou = np.full((union.size, 1), -np.inf)
    rows = np.searchsorted(union, times)
    yu[rows], lou[rows] = y, lo
    ref = tk.AssumedDensityTobitFilter(cont, tk.Censoring(lower=lou), order="uncensored_first").smooth(yu, times=union)
    assert np.allclose(res.mean, ref.mean[np.searchsorted(union, grid)], rtol=0, atol=1e-12)
    # the readings at their limits were censored (the side recorded on the union), not exact
    assert (res.extras["smoothed"].extras["side"][rows, 0] == [-1, 0, 0, -1]).all()


@pytest.mark.parametrize("name", ["tobitkf.models.continuous", "tobitkf.inference.panel"])
def test_docstring_examples(name):
    import doctest
    import importlib

    res = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0 and res.attempted > 0
