"""Randomly saturated readings of a NonlinearSystem: the assumed-density filter against the linear saturation
filter (linear h), against the unfaded ADF (sensors that never saturate), the compiled loop against the numpy path,
and the errors."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

from ._jit import jitted

TOL = 1e-12
A = np.array([[0.95, 0.1], [-0.1, 0.9]])
C = np.array([[1.0, 0.5], [0.0, 1.0]])
Q, R = 0.05 * np.eye(2), np.diag([0.05, 0.04])
X0, P0 = np.array([1.0, 0.0]), np.eye(2)
SAT = tk.RandomSaturation(mu=[0.4, 0.2], nu=[0.8, 0.9], level=[0.8, 0.6])


def _f(x, k):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
    out[..., 1] = x[..., 1] - 0.1 * np.sin(x[..., 0]) - 0.02 * x[..., 1]
    return out


def _h(x, k):
    out = np.empty(x.shape[:-1] + (2,))
    out[..., 0] = np.sin(x[..., 0]) + 0.3
    out[..., 1] = 0.5 * x[..., 1] + 0.1 * x[..., 0] ** 3
    return out


def _saturated(x, h, channel, rng, R):
    T = x.shape[1] - 1
    hx = np.stack([h(x[:, k], k) for k in range(1, T + 1)], axis=1)
    alpha, beta = channel.draw_modes(rng, hx.shape[:2])
    return channel.measure(hx, alpha, beta, rng.standard_normal(hx.shape) * np.sqrt(np.diag(R)))


@pytest.mark.parametrize("rule", ["unscented", "cubature"])
def test_linear_h_is_the_linear_saturation_adf(rule):
    lin = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0)
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, Q=Q, R=R, x0=X0, P0=P0)
    data = tk.simulate(lin, steps=25, runs=6, channel=SAT, seed=3)
    y = data.y.copy()
    y[2, 5, 0] = np.nan
    a = tk.SaturationAssumedDensityFilter(lin, SAT, backend="numpy").filter(y)
    b = tk.SaturationNonlinearAssumedDensityFilter(nl, SAT, rule=rule, backend="numpy").filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.extras["log_likelihood"], a.extras["log_likelihood"], rtol=0, atol=1e-10)


def test_sensors_that_never_saturate_give_the_plain_adf():
    sys_ = tk.NonlinearSystem(_f, _h, Q=np.diag([1e-3, 4e-3]), R=R, x0=[0.8, 0.0], P0=0.1 * np.eye(2))
    data = tk.simulate(sys_, steps=20, runs=5, seed=2)
    plain = tk.RandomSaturation(mu=[0.0, 0.0], nu=[1.0, 1.0], level=1.0)
    a = tk.NonlinearAssumedDensityFilter(sys_, tk.Censoring(), iterations=2).filter(data.y)
    b = tk.SaturationNonlinearAssumedDensityFilter(sys_, plain, iterations=2).filter(data.y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    c = tk.SaturationNonlinearAssumedDensityFilter(sys_, SAT, iterations=2).filter(data.y)
    assert np.abs(c.mean - a.mean).max() > 1e-3  # the saturation changes the numbers (the test above can fail)


@pytest.mark.parametrize("iterations", [1, 3])
def test_compiled_loop_equals_numpy_path(iterations):
    f, h = jitted(_f, _h)  # the same compiled functions for both parameters: one specialisation of the loop
    sys_ = tk.NonlinearSystem(f, h, Q=np.diag([1e-3, 4e-3]), R=R, x0=[0.8, 0.0], P0=0.1 * np.eye(2))
    data = tk.simulate(sys_, steps=15, runs=5, seed=6)
    y = _saturated(data.x, h, SAT, np.random.default_rng(7), R)
    y[1, 3, 1] = np.nan
    a = tk.SaturationNonlinearAssumedDensityFilter(sys_, SAT, iterations=iterations, backend="numpy").filter(y)
    est = tk.SaturationNonlinearAssumedDensityFilter(sys_, SAT, iterations=iterations, backend="numba")
    b = est.filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.extras["log_likelihood"], a.extras["log_likelihood"], rtol=0, atol=1e-9)
    state = est.init(batch_shape=(5,))
    for t in range(15):
        state = est.step(state, y[:, t])
    np.testing.assert_allclose(state.x, a.mean[:, -1], rtol=0, atol=1e-10)


def test_errors_name_the_argument():
    sys_ = tk.NonlinearSystem(_f, _h, Q=np.diag([1e-3, 4e-3]), R=R, x0=[0.8, 0.0], P0=0.1 * np.eye(2))
    with pytest.raises(tk.ValidationError, match="channel"):
        tk.SaturationNonlinearAssumedDensityFilter(sys_, tk.Censoring(lower=0.0))
    with pytest.raises(tk.ShapeError, match="channels"):
        tk.SaturationNonlinearAssumedDensityFilter(sys_, tk.RandomSaturation(mu=[0.1], nu=[0.9]))
    with pytest.raises(tk.ValidationError, match="covariance_update"):
        tk.SaturationNonlinearAssumedDensityFilter(sys_, SAT, covariance_update="square_root")
    zero = tk.NonlinearSystem(_f, _h, Q=np.diag([1e-3, 4e-3]), R=np.diag([0.05, 0.0]), x0=[0.8, 0.0], P0=np.eye(2))
    with pytest.raises(tk.ValidationError, match="R"):
        tk.SaturationNonlinearAssumedDensityFilter(zero, SAT)
