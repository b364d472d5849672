"""Tests of the Rice fading channel (tobitkf.channels.fading); spec 000 §1.2, §1.6, §2."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ShapeError, ValidationError
from tobitkf.channels.fading import RiceFading, measurement_matrix_at
from tobitkf.channels.laws import PMF, Gaussian, Uniform


def _system(m=1, C=None, R=None):
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    C = np.array([[1.0, 0.0]]) if C is None else C
    R = np.eye(C.shape[0]) if R is None else R
    return tk.LinearSystem(A=A, C=C, Q=0.0025 * np.eye(2), R=R, x0=[5.0, 0.0], P0=np.eye(2))


def _loop_oracle(x, theta, C_of, noise, L):
    """(2) written straight from the source, one run and step at a time."""
    N, T1, _ = x.shape
    y = noise.copy()
    for i in range(N):
        for k in range(1, T1):
            for s in range(min(L, k) + 1):
                y[i, k - 1] += theta[i, k - 1, s] * (C_of(k - s) @ x[i, k - s])
    return y


def test_draw_matches_equation_2_loop():
    sys = _system()
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    rng = np.random.default_rng(3)
    x = rng.standard_normal((4, 8, 2))
    noise = rng.standard_normal((4, 7, 1))
    y, extras = fad.draw(np.random.default_rng(5), x, sys, noise)
    theta = extras["fading"]
    assert theta.shape == (4, 7, 3, 1)
    np.testing.assert_allclose(y, _loop_oracle(x, theta, lambda j: np.array([[1.0, 0.0]]), noise, 2), atol=1e-13)


def test_zero_padding_for_delays_beyond_k():
    fad = RiceFading.gaussian(3, [1.0, 1.0, 1.0, 1.0], 0.01)
    theta = fad.sample(np.random.default_rng(0), 2, 5, 1)
    # index k-1; term s exists only for s <= k
    for k in range(1, 6):
        for s in range(4):
            assert (theta[:, k - 1, s] == 0).all() == (s > k)


def test_draw_time_varying_C_and_two_channels():
    T = 6
    Cs = np.stack([np.array([[1.0 + 0.1 * k, 0.0], [0.0, 2.0 - 0.1 * k]]) for k in range(1, T + 1)])
    sys = _system(C=Cs, R=np.eye(2))
    law = Uniform(np.array([[0.5, 0.6], [0.1, 0.2]]), np.array([[0.9, 1.0], [0.3, 0.4]]))
    fad = RiceFading(1, law)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((3, T + 1, 2))
    noise = np.zeros((3, T, 2))
    y, ex = fad.draw(np.random.default_rng(2), x, sys, noise)
    # C_0 := C_1 for per-step arrays (module docstring)
    np.testing.assert_allclose(y, _loop_oracle(x, ex["fading"], lambda j: Cs[max(j, 1) - 1], noise, 1), atol=1e-13)
    np.testing.assert_array_equal(measurement_matrix_at(sys, 0), Cs[0])


def test_fresh_draw_per_k_and_s_and_channel():
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    th = fad.sample(np.random.default_rng(0), 1, 200, 2)[0, 2:]  # (198, 3, 2), all s present
    assert len(np.unique(th)) == th.size
    # independence over channels and delays: sample correlation ~ 0 within 5/sqrt(n)
    c = np.corrcoef(th[:, 0, 0], th[:, 0, 1])[0, 1]
    assert abs(c) < 5 / np.sqrt(th.shape[0])
    np.testing.assert_allclose(th.std(0)[:, 0], [0.09, 0.08, 0.07], rtol=0.3)


def test_simulate_composes_fading_then_censoring():
    sys = _system()
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    d = tk.simulate(sys, 30, 5, censoring=tk.Censoring(lower=0.0), measurement=fad, seed=11)
    np.testing.assert_array_equal(d.y, np.maximum(d.y_latent, 0.0))
    theta = d.extras["fading"]
    # latent = fading of the simulated truth + v, where v = y_latent - sum theta C x
    clean = _loop_oracle(d.x, theta, lambda j: np.array([[1.0, 0.0]]), np.zeros_like(d.y), 2)
    v = d.y_latent - clean
    assert abs(v.mean()) < 5 / np.sqrt(v.size) and abs(v.var() - 1.0) < 0.2
    d2 = tk.simulate(sys, 30, 5, censoring=tk.Censoring(lower=0.0), measurement=fad, seed=11)
    np.testing.assert_array_equal(d.y, d2.y)


def test_latent_mean_is_sum_of_mean_gains_monte_carlo():
    # E[y*_k | x] = sum_s thbar(s) C x_{k-s}: fix x, average over fading and noise draws
    sys = _system()
    fad = RiceFading(2, PMF([[0.9, 1.0], [0.5, 0.7], [0.0, 1.0]], [[0.5, 0.5], [0.25, 0.75], [0.2, 0.8]]))
    N = 20000
    x = np.broadcast_to(np.array([[1.0, 0.0], [2.0, 1.0], [-1.0, 0.0], [3.0, 0.0]]), (N, 4, 2))
    y, _ = fad.draw(np.random.default_rng(9), x, sys, np.zeros((N, 3, 1)))
    mg = fad.mean_gains(1)[:, 0]
    expect = [mg[0] * 2 + mg[1] * 1, mg[0] * -1 + mg[1] * 2 + mg[2] * 1, mg[0] * 3 + mg[1] * -1 + mg[2] * 2]
    var = [4 * 0.0025 + 1 * 0.01, 1 * 0.0025 + 4 * 0.01 + 0.16, 9 * 0.0025 + 0.01 + 4 * 0.16]
    se = np.sqrt(np.array(var) / N)
    assert np.all(np.abs(y[:, :, 0].mean(0) - expect) < 6 * se)


def test_mean_and_var_gains_shapes():
    fad = RiceFading(1, Gaussian([[0.9, 0.8], [0.5, 0.4]], [[0.01, 0.02], [0.03, 0.04]]))
    assert fad.channels == 2
    np.testing.assert_array_equal(fad.var_gains(2), [[0.01, 0.02], [0.03, 0.04]])
    np.testing.assert_array_equal(RiceFading(1, [0.3, 0.2]).mean_gains(3), [[0.3] * 3, [0.2] * 3])


@pytest.mark.parametrize("order", [-1, 1.5, "2", True, None])
def test_bad_order_names_argument(order):
    with pytest.raises(ValidationError, match="order"):
        RiceFading(order, [1.0, 0.5])


def test_bad_coefficients_name_argument():
    with pytest.raises(ShapeError, match="coefficients"):
        RiceFading(2, Gaussian([0.9, 0.8], [0.01, 0.01]))  # length L+1 = 3 expected
    with pytest.raises(ValidationError, match="variance"):
        RiceFading.gaussian(1, [0.9, 0.8], [0.01, -0.01])
    with pytest.raises(ValidationError, match="probs"):
        RiceFading(0, PMF([[0.0, 1.0]], [[0.4, 0.4]]))
    with pytest.raises(ValidationError, match="coefficients"):
        RiceFading(0, "gaussian")
    with pytest.raises(ShapeError, match="coefficients"):
        RiceFading(0, Gaussian([[0.9, 0.8]], 0.0)).check(3)
    with pytest.raises(ShapeError, match="coefficients"):
        RiceFading(0, Gaussian(np.ones((1, 2, 2)), 0.0))


def test_order_accepts_integral_float():
    assert RiceFading(2.0, [1.0, 0.0, 0.0]).order == 2
