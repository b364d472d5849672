"""Tests of the batched simulator (``tobitkf.simulate``).

Statistical checks compare sample moments over N runs with the model's exact moments
(mean A^k x0 + inputs, covariance P_k = A P_{k-1} A^T + B Q B^T; v ~ N(0, R_k)). Each
tolerance is 5 standard errors computed from N: SE(mean_i) = sqrt(S_ii / N) and
SE(S_ij) = sqrt((S_ii S_jj + S_ij^2) / N) for Gaussian data.
"""

from __future__ import annotations

import numpy as np
import pytest

from tobitkf import Censoring, LinearSystem, ShapeError, ValidationError, simulate
from tobitkf.simulate import as_generator, psd_sqrt

N = 20_000


def _check_moments(samples, mean, cov, what):
    """samples (N, d); compare the sample mean and covariance with 5-SE tolerances."""
    n = samples.shape[0]
    m = samples.mean(axis=0)
    S = np.cov(samples, rowvar=False).reshape(cov.shape)
    se_m = np.sqrt(np.diag(cov) / n)
    assert np.all(np.abs(m - mean) < 5 * se_m + 1e-15), (what, m, mean)
    d = np.diag(cov)
    se_S = np.sqrt((np.outer(d, d) + cov**2) / n)
    assert np.all(np.abs(S - cov) < 5 * se_S + 1e-15), (what, S, cov)


def _system(**kw):
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    base = dict(
        A=A,
        C=[[1.0, 0.5], [0.0, 1.0]],
        Q=[[0.3, 0.1], [0.1, 0.2]],
        R=[[0.5, 0.2], [0.2, 0.4]],
        x0=[1.0, -2.0],
        P0=[[1.0, 0.3], [0.3, 0.5]],
    )
    base.update(kw)
    return LinearSystem(**base)


def test_shapes_and_types():
    sys = _system()
    data = simulate(sys, steps=7, runs=5, seed=0)
    assert data.x.shape == (5, 8, 2)
    assert data.y.shape == data.y_latent.shape == (5, 7, 2)
    assert data.u is None and data.extras == {}
    assert data.runs == 5 and data.steps == 7
    assert data.x.dtype == np.float64
    one = simulate(sys, steps=3, seed=0)  # runs defaults to 1
    assert one.x.shape == (1, 4, 2)


def test_same_seed_same_numbers_and_generator_seed():
    sys = _system()
    a = simulate(sys, steps=10, runs=4, seed=123)
    b = simulate(sys, steps=10, runs=4, seed=123)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.y, b.y)
    c = simulate(sys, steps=10, runs=4, seed=124)
    assert not np.allclose(a.x, c.x)
    d = simulate(sys, steps=10, runs=4, seed=np.random.default_rng(123))
    np.testing.assert_array_equal(a.y, d.y)
    e = simulate(sys, steps=10, runs=4, seed=np.random.SeedSequence(123))
    np.testing.assert_array_equal(a.y, e.y)


def test_without_censoring_y_is_latent():
    data = simulate(_system(), steps=5, runs=3, seed=1)
    np.testing.assert_array_equal(data.y, data.y_latent)


def test_state_and_noise_moments_match_the_model():
    sys = _system()
    T = 4
    data = simulate(sys, steps=T, runs=N, seed=77)
    A, C = sys.transition(0), sys.measurement(1)
    Qd, R = sys.process_cov(0), sys.measurement_cov(1)
    mean, P = sys.x0.copy(), sys.P0.copy()
    _check_moments(data.x[:, 0], mean, P, "x0")
    for k in range(1, T + 1):
        P_prev = P
        mean, P = A @ mean, A @ P @ A.T + Qd
        _check_moments(data.x[:, k], mean, P, f"x{k}")
        v = data.y_latent[:, k - 1] - data.x[:, k] @ C.T
        _check_moments(v, np.zeros(2), R, f"v{k}")
        # x_k and x_{k-1}: Cov = A P_{k-1}
        joint = np.concatenate([data.x[:, k], data.x[:, k - 1]], axis=1)
        cross = np.cov(joint, rowvar=False)[:2, 2:]
        se = np.sqrt(np.outer(np.diag(P), np.diag(P_prev)) / N)
        assert np.all(np.abs(cross - A @ P_prev) < 5 * se)
        # v_k independent of x_k
        joint = np.concatenate([v, data.x[:, k]], axis=1)
        cross = np.cov(joint, rowvar=False)[:2, 2:]
        assert np.all(np.abs(cross) < 5 * np.sqrt(np.outer(np.diag(R), np.diag(P)) / N))
    # v independent over time
    v1 = data.y_latent[:, 0] - data.x[:, 1] @ C.T
    v2 = data.y_latent[:, 1] - data.x[:, 2] @ C.T
    cross = np.cov(np.concatenate([v1, v2], axis=1), rowvar=False)[:2, 2:]
    assert np.all(np.abs(cross) < 5 * np.sqrt(np.outer(np.diag(R), np.diag(R)) / N))


def test_noise_input_matrix_and_control_inputs():
    T = 3
    G = np.array([[0.5], [1.0]])
    Bu = np.array([[1.0], [0.0]])
    D = np.array([[2.0], [-1.0]])
    sys = _system(Q=[[0.09]], B=G, Bu=Bu, D=D)
    u = np.array([[1.0], [-2.0], [0.5]])
    data = simulate(sys, steps=T, runs=N, inputs=u, seed=5)
    np.testing.assert_array_equal(data.u, np.broadcast_to(u, (N, T, 1)))
    A, C, R = sys.transition(0), sys.measurement(1), sys.measurement_cov(1)
    mean, P = sys.x0.copy(), sys.P0.copy()
    for k in range(1, T + 1):
        mean, P = A @ mean + Bu @ u[k - 1], A @ P @ A.T + 0.09 * G @ G.T
        _check_moments(data.x[:, k], mean, P, f"x{k}")
        v = data.y_latent[:, k - 1] - data.x[:, k] @ C.T - D @ u[k - 1]
        _check_moments(v, np.zeros(2), R, f"v{k}")
    # rank-one noise: the state noise lies along G exactly
    w = data.x[:, 1] - data.x[:, 0] @ A.T - Bu @ u[0]
    np.testing.assert_allclose(w[:, 0], 0.5 * w[:, 1], rtol=0, atol=1e-12)


def test_per_run_inputs():
    """(N, T, p) inputs: each run gets its own; the state difference obeys d_k = A d_{k-1} + Bu u_k."""
    Bu = np.array([[1.0], [0.0]])
    sys = _system(Bu=Bu)
    u = np.zeros((3, 4, 1))
    u[1] = 100.0
    u[2, 2] = -5.0
    a = simulate(sys, steps=4, runs=3, inputs=u, seed=0)
    b = simulate(sys, steps=4, runs=3, seed=0)  # same noise draws
    A = sys.transition(0)
    for i in range(3):
        d = np.zeros(2)
        for k in range(1, 5):
            d = A @ d + Bu @ u[i, k - 1]
            np.testing.assert_allclose(a.x[i, k] - b.x[i, k], d, rtol=0, atol=1e-11)


def test_censoring_is_applied():
    sys = _system()
    cens = Censoring(lower=[0.0, -np.inf], upper=[np.inf, -1.5])
    data = simulate(sys, steps=30, runs=50, censoring=cens, seed=2)
    np.testing.assert_array_equal(data.y, cens.clip(data.y_latent))
    assert (data.y[..., 0] >= 0).all() and (data.y[..., 1] <= -1.5).all()
    # both channels were censored sometimes and uncensored sometimes
    for ch, lim in ((0, 0.0), (1, -1.5)):
        frac = np.mean(data.y[..., ch] == lim)
        assert 0.05 < frac < 0.95


def test_time_varying_limits_follow_the_time_axis():
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-12]], R=[[1e-12]], x0=[0.0], P0=[[0.0]])
    lo = np.arange(5, dtype=float)[:, None] - 2.0  # -2, -1, 0, 1, 2
    data = simulate(sys, steps=5, runs=2, censoring=Censoring(lower=lo), seed=0)
    np.testing.assert_allclose(data.y[0, :, 0], [0, 0, 0, 1, 2], atol=1e-5)


def test_time_varying_and_callable_matrices():
    T = 3
    A_arr = np.stack([np.array([[0.5 * (k + 1)]]) for k in range(T)])
    Q_fn = lambda k: np.array([[0.1 * (k + 1)]])  # noqa: E731
    R_arr = np.stack([np.array([[0.2 * k]]) for k in range(1, T + 1)])
    C_fn = lambda k: np.array([[float(k)]])  # noqa: E731
    sys = LinearSystem(A=A_arr, C=C_fn, Q=Q_fn, R=R_arr, x0=[1.0], P0=[[0.5]])
    data = simulate(sys, steps=T, runs=N, seed=9)
    mean, P = 1.0, 0.5
    for k in range(1, T + 1):
        a = 0.5 * k
        mean, P = a * mean, a * a * P + 0.1 * k
        _check_moments(data.x[:, k], np.array([mean]), np.array([[P]]), f"x{k}")
        v = data.y_latent[:, k - 1, 0] - k * data.x[:, k, 0]
        _check_moments(v[:, None], np.zeros(1), np.array([[0.2 * k]]), f"v{k}")


def test_custom_measurement_and_post_pieces():
    class Scaled:
        def draw(self, rng, x, system, noise, inputs):
            theta = rng.uniform(1.0, 2.0, size=noise.shape)
            return theta * x[:, 1:, :1] + noise, {"theta": theta}

    class DropEven:
        def apply(self, rng, y, extras):
            out = y.copy()
            out[:, ::2] = np.nan
            extras["dropped"] = True
            return out

    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[0.01]], x0=[1.0], P0=[[0.0]])
    data = simulate(
        sys, steps=6, runs=3, measurement=Scaled(), post=[DropEven()], seed=1, censoring=Censoring(upper=1.2)
    )
    assert data.extras["theta"].shape == (3, 6, 1) and data.extras["dropped"] is True
    assert np.isnan(data.y[:, ::2]).all()
    np.testing.assert_array_equal(data.y[:, 1::2], np.minimum(data.y_latent[:, 1::2], 1.2))

    class Bad:
        def draw(self, rng, x, system, noise, inputs):
            return noise[:, :-1], {}

    with pytest.raises(ShapeError, match=r"measurement: draw\(\) returned shape \(3, 5, 1\), expected \(3, 6, 1\)"):
        simulate(sys, steps=6, runs=3, measurement=Bad(), seed=1)


def test_psd_sqrt_and_generator():
    cov = np.array([[4.0, 2.0], [2.0, 1.0]])  # singular
    S = psd_sqrt(cov)
    np.testing.assert_allclose(S @ S.T, cov, rtol=0, atol=1e-14)
    g = np.random.default_rng(0)
    assert as_generator(g) is g
    with pytest.raises(ValidationError, match="seed: expected an int, SeedSequence or Generator"):
        as_generator(None)
    with pytest.raises(ValidationError, match="seed: expected an int, SeedSequence or Generator, got 'x'"):
        as_generator("x")


@pytest.mark.parametrize(
    "kwargs,exc,match",
    [
        (dict(steps=0), ValidationError, "steps: expected a positive integer, got 0"),
        (dict(steps=2.5), ValidationError, "steps: expected a positive integer, got 2.5"),
        (dict(steps=True), ValidationError, "steps: expected a positive integer, got True"),
        (dict(steps=3, runs=-1), ValidationError, "runs: expected a positive integer, got -1"),
        (dict(steps=3, seed=None), ValidationError, "seed: expected an int"),
        (dict(steps=3, censoring=(0.0, 1.0)), ValidationError, "censoring: expected a Censoring, got tuple"),
        (dict(steps=3, censoring=Censoring(lower=[0.0, 0.0, 0.0])), ShapeError, "censoring limits: expected 2 channel"),
        (dict(steps=3, censoring=Censoring(lower=np.zeros((2, 2)))), ShapeError, "time-varying limits have 2 steps, 3"),
        (dict(steps=3, inputs=np.zeros((3, 1))), ShapeError, "inputs: the system has no control input"),
    ],
)
def test_simulate_validation(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        simulate(_system(), **kwargs)


def test_simulate_validation_inputs_and_horizon():
    sys = _system(Bu=[[1.0], [0.0]])
    with pytest.raises(ShapeError, match=r"inputs: expected \(\.\.\., 3, 1\)"):
        simulate(sys, steps=3, inputs=np.zeros((4, 1)))
    with pytest.raises(ShapeError, match=r"inputs: expected \(T, p\) or \(2, T, p\)"):
        simulate(sys, steps=3, runs=2, inputs=np.zeros((5, 3, 1)))
    with pytest.raises(ValidationError, match="system: expected a LinearSystem, got dict"):
        simulate({}, steps=3)
    short = LinearSystem(A=np.stack([np.eye(2)] * 2), C=np.eye(2), Q=np.eye(2), R=np.eye(2), x0=[0, 0], P0=np.eye(2))
    with pytest.raises(ShapeError, match="A: time-indexed array has 2 steps, 3 needed"):
        simulate(short, steps=3)
    bad_q = LinearSystem(A=np.eye(1), C=np.eye(1), Q=lambda k: np.array([[1.0 - k]]), R=np.eye(1), x0=[0], P0=np.eye(1))
    with pytest.raises(ValidationError, match=r"Q\(2\): expected a positive semi-definite matrix"):
        simulate(bad_q, steps=3)
    nan_c = LinearSystem(
        A=np.eye(1), C=lambda k: np.array([[np.nan if k == 2 else 1.0]]), Q=np.eye(1), R=np.eye(1), x0=[0], P0=np.eye(1)
    )
    with pytest.raises(ValidationError, match=r"C\(2\): expected finite numbers, found NaN"):
        simulate(nan_c, steps=3)


def test_random_saturation_of_a_nonlinear_system_is_the_linear_draw_for_a_linear_h():
    # (2) with h(x_k, k) = C x_k and f(x, k) = A x drawn through tk.simulate equals the linear system's draw for the
    # same seed: the same states, modes and readings (the draw order of the linear case unchanged)
    import tobitkf as tk

    A, C = np.array([[0.95, 0.1], [-0.1, 0.9]]), np.array([[1.0, 0.5], [0.0, 1.0]])
    kw = dict(Q=0.05 * np.eye(2), R=np.diag([0.05, 0.04]), x0=[1.0, 0.0], P0=np.eye(2))
    sat = tk.RandomSaturation(mu=[0.4, 0.2], nu=[0.8, 0.9], level=[0.8, 0.6])
    lin = tk.simulate(tk.LinearSystem(A=A, C=C, **kw), 30, 4, channel=sat, seed=7)
    nl_sys = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, **kw)
    nl = tk.simulate(nl_sys, 30, 4, channel=sat, seed=7)
    np.testing.assert_allclose(nl.x, lin.x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(nl.extras["alpha"], lin.extras["alpha"])
    np.testing.assert_array_equal(nl.extras["beta"], lin.extras["beta"])
    np.testing.assert_allclose(nl.y, lin.y, rtol=0, atol=1e-12)
    assert 0.2 < nl.extras["alpha"].mean() < 0.4  # both modes occur
