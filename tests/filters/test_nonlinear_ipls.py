"""The iterated posterior-linearisation smoother of the nonlinear assumed-density filter."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

DT = 0.1


def pendulum(x, k):
    return np.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * np.sin(x[..., 0])], -1)


@pytest.mark.parametrize("rule", ["unscented", "cubature"])
def test_on_a_linear_model_every_iteration_is_the_assumed_density_smoother(rule):
    # a linear f and h: every statistical linearisation is the model itself, so re-linearising changes nothing,
    # and the one-pass smoother is the linear assumed-density (ADF-RTS) smoother
    A = np.array([[0.9, 0.2], [0.0, 0.8]])
    C = np.array([[1.0, 0.5]])
    Q, R, x0, P0 = np.diag([0.1, 0.05]), [[0.5]], [0.0, 0.3], np.diag([1.0, 0.5])
    cens = tk.Censoring(lower=0.0)
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, Q, R, x0, P0)
    lin = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=x0, P0=P0)
    y = tk.simulate(lin, 30, 6, censoring=cens, seed=1).y.reshape(2, 3, 30, 1)
    y[0, 1, 4] = np.nan
    adf = tk.NonlinearAssumedDensityFilter(nl, cens, rule=rule)
    ref = tk.smooth(lin, y, censoring=cens, method="adf")
    for it in (1, 2, 4):
        out = adf.smooth(y, iterations=it)
        assert out.mean.shape == (2, 3, 30, 2)
        np.testing.assert_allclose(out.mean, ref.mean, rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.cov, ref.cov, rtol=0, atol=1e-10)
    two = adf.smooth(y, iterations=2)
    np.testing.assert_allclose(two.extras["initial_mean"], ref.extras["initial_mean"], rtol=0, atol=1e-10)


def test_on_a_nonlinear_model_no_worse_than_the_one_pass_smoother():
    # a cubic sensor clipping at 0.5: over R = 200 runs the mean paired difference of the per-run squared
    # errors (3 iterations minus 1) must not exceed 3 standard errors of that mean (one-sided, ~0.1 % false alarm)
    system = tk.NonlinearSystem(
        pendulum, lambda x, k: x[..., :1] ** 3 / 3, np.diag([1e-4, 4e-3]), [[0.01]], [0.8, 0.1], np.diag([0.3, 0.3])
    )
    clip = tk.Censoring(upper=0.5)
    data = tk.simulate(system, 40, 200, channel=clip, seed=2)
    adf = tk.NonlinearAssumedDensityFilter(system, clip)
    err = [((adf.smooth(data.y, iterations=it).mean - data.x[:, 1:]) ** 2).sum(-1).mean(-1) for it in (1, 3)]
    diff = err[1] - err[0]
    assert diff.mean() <= 3 * diff.std(ddof=1) / np.sqrt(diff.size)


def test_iterations_refused():
    system = tk.NonlinearSystem(pendulum, lambda x, k: x[..., :1], np.eye(2) * 0.01, [[0.1]], [0.0, 0.0], np.eye(2))
    adf = tk.NonlinearAssumedDensityFilter(system, tk.Censoring(lower=0.0))
    for bad in (0, 1.5, True):
        with pytest.raises(tk.ValidationError, match="iterations"):
            adf.smooth(np.zeros((5, 1)), iterations=bad)
