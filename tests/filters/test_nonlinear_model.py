"""NonlinearSystem, discretize and the nonlinear draw of tk.simulate."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.models.nonlinear import jacobian_fd

DT = 0.1


def f(x, k):
    return np.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * np.sin(x[..., 0])], axis=-1)


def F(x, k):
    out = np.zeros(x.shape[:-1] + (2, 2))
    out[..., 0, 0] = 1.0
    out[..., 0, 1] = DT
    out[..., 1, 0] = -DT * np.cos(x[..., 0])
    out[..., 1, 1] = 1.0
    return out


def h(x, k):
    return np.stack([np.sin(x[..., 0]), x[..., 0] + 0.3 * x[..., 1] ** 2], axis=-1)


def H(x, k):
    out = np.zeros(x.shape[:-1] + (2, 2))
    out[..., 0, 0] = np.cos(x[..., 0])
    out[..., 1, 0] = 1.0
    out[..., 1, 1] = 0.6 * x[..., 1]
    return out


Q = np.diag([1e-3, 4e-3])
R = np.diag([0.05, 0.1])
X0 = np.array([0.8, 0.1])
P0 = np.diag([0.2, 0.3])


def pendulum(**kw):
    return tk.NonlinearSystem(f, h, Q, R, X0, P0, **kw)


def test_dimensions_and_maps():
    sys_ = pendulum()
    assert (sys_.n, sys_.m) == (2, 2)
    x = np.random.default_rng(0).normal(size=(5, 2))
    np.testing.assert_array_equal(sys_.transition_map(x, 3), f(x, 3))
    np.testing.assert_array_equal(sys_.measurement_map(x, 3), h(x, 3))


def test_central_differences_match_the_analytic_jacobians():
    # step eps^(1/3) max(1, |x|): truncation + rounding error ~ eps^(2/3) ~ 4e-11 for these O(1) functions
    x = np.random.default_rng(1).normal(size=(7, 2)) * 2
    sys_ = pendulum()
    np.testing.assert_allclose(sys_.transition_jacobian(x, 0), F(x, 0), rtol=0, atol=1e-9)
    np.testing.assert_allclose(sys_.measurement_jacobian(x, 1), H(x, 1), rtol=0, atol=1e-9)
    given = pendulum(F=F, H=H)
    np.testing.assert_array_equal(given.measurement_jacobian(x, 1), H(x, 1))
    # a polynomial of degree 2: central differences are exact up to rounding
    J = jacobian_fd(lambda z: z**2, x)
    np.testing.assert_allclose(J, np.eye(2) * 2 * x[:, :, None], rtol=0, atol=1e-8)


def test_discretize_is_rk4():
    # dx/dt = -x: one RK4 step of size h multiplies by 1 - h + h^2/2 - h^3/6 + h^4/24 exactly
    step = tk.discretize(lambda x, t: -x, dt=0.2, substeps=2)
    hh = 0.1
    g = 1 - hh + hh**2 / 2 - hh**3 / 6 + hh**4 / 24
    np.testing.assert_allclose(step(np.array([[1.0], [2.0]]), 0), np.array([[1.0], [2.0]]) * g**2, rtol=1e-14)
    # time enters as t = k dt: dx/dt = 1 integrates t-independent, dx/dt = t gives ((k+1)^2 - k^2) dt^2 / 2
    ramp = tk.discretize(lambda x, t: np.full_like(x, t), dt=0.5, substeps=3)
    np.testing.assert_allclose(ramp(np.zeros(1), 4), (25 - 16) * 0.25 / 2, rtol=1e-13)
    with pytest.raises(tk.ValidationError, match="dt"):
        tk.discretize(lambda x, t: x, dt=0.0)
    with pytest.raises(tk.ValidationError, match="fc"):
        tk.discretize(3.0, dt=1.0)


def test_refusals_name_the_argument():
    with pytest.raises(tk.ValidationError, match="^f:"):
        tk.NonlinearSystem(1.0, h, Q, R, X0, P0)
    with pytest.raises(tk.ShapeError, match="f\\(x0, 0\\)"):
        tk.NonlinearSystem(lambda x, k: x[..., :1], h, Q, R, X0, P0)
    with pytest.raises(tk.ShapeError, match="^R:"):
        tk.NonlinearSystem(f, h, Q, np.eye(3), X0, P0)
    with pytest.raises(tk.ShapeError, match="^Q:"):
        tk.NonlinearSystem(f, h, np.eye(3), R, X0, P0)
    with pytest.raises(tk.ShapeError, match="h\\(x, 1\\)"):  # not batched: (1, 2) in, (2,) out
        tk.NonlinearSystem(f, lambda x, k: np.array([np.sin(x.ravel()[0]), 1.0]), Q, R, X0, P0)
    with pytest.raises(tk.ShapeError, match="H\\(x, 1\\)"):
        tk.NonlinearSystem(f, h, Q, R, X0, P0, H=lambda x, k: np.zeros((1, 2)))


def test_simulate_draws_the_nonlinear_model():
    # with noiseless readings the latent readings are h of the drawn states, and the states follow f exactly
    # when Q = 0
    sys_ = tk.NonlinearSystem(f, h, np.zeros((2, 2)), np.zeros((2, 2)), X0, P0)
    d = tk.simulate(sys_, 20, 3, seed=4)
    for k in range(1, 21):
        np.testing.assert_allclose(d.x[:, k], f(d.x[:, k - 1], k - 1), rtol=0, atol=1e-14)
        np.testing.assert_allclose(d.y_latent[:, k - 1], h(d.x[:, k], k), rtol=0, atol=1e-14)


def test_simulate_noise_moments():
    # one step from a point prior: x_1 - f(x_0) ~ N(0, Q), y*_1 - h(x_1) ~ N(0, R); variance estimates over
    # 40 000 runs have relative standard error sqrt(2/40000) = 0.7%: 5 sigma is 3.5%
    sys_ = tk.NonlinearSystem(f, h, Q, R, X0, np.zeros((2, 2)))
    d = tk.simulate(sys_, 1, 40000, seed=5)
    w = d.x[:, 1] - f(d.x[:, 0], 0)
    v = d.y_latent[:, 0] - h(d.x[:, 1], 1)
    np.testing.assert_allclose(np.var(w, axis=0), np.diag(Q), rtol=0.035)
    np.testing.assert_allclose(np.var(v, axis=0), np.diag(R), rtol=0.035)


@pytest.mark.parametrize(
    "channel",
    [tk.Censoring(lower=-0.2, upper=0.6), tk.Quantizer(0.25)],
    ids=["censoring", "quantizer"],
)
def test_simulate_through_a_channel(channel):
    sys_ = pendulum()
    d = tk.simulate(sys_, 25, 4, channel=channel, seed=6)
    np.testing.assert_array_equal(d.y, channel.censor(d.y_latent))


def test_simulate_lost_readings_and_refused_drawers():
    class Lose(tk.Channel):
        def apply(self, rng, y, extras):
            y = y.copy()
            y[:, ::2] = np.nan
            return y

    sys_ = pendulum()
    d = tk.simulate(sys_, 10, 2, channel=[tk.Censoring(upper=0.5), Lose()], seed=7)
    assert np.isnan(d.y[:, ::2]).all() and not np.isnan(d.y[:, 1::2]).any()

    class FromC(tk.Channel):  # a drawer of its own reading from C x
        def draw(self, rng, x, system, noise, inputs=None):
            return x[:, 1:] @ system.C.at(1).T + noise, {}

    with pytest.raises(tk.ValidationError, match="NonlinearSystem"):
        tk.simulate(sys_, 5, channel=FromC())
    d = tk.simulate(sys_, 5, 2, channel=tk.RandomSaturation(level=1.0, mu=[0.5, 0.5], nu=[0.5, 0.5]), seed=1)
    assert d.y.shape == (2, 5, 2) and set(d.extras) >= {"alpha", "beta"}  # (2) at h(x_k, k): drawn
