"""NonlinearSystem inputs f(x, k, u) and the square-root (Cholesky) forms of the nonlinear filters."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import tobitkf as tk

DT = 0.1
Q = np.diag([1e-3, 4e-3])
R = np.diag([0.05, 0.1])
X0 = np.array([0.8, 0.1])
P0 = np.diag([0.2, 0.3])
T = 25
U = np.random.default_rng(5).normal(size=(T, 1))  # u_1..u_T, row k-1 holds u_k


def f_u(x, k, u):  # a forced pendulum: the input is a torque
    return np.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * np.sin(x[..., 0]) + DT * np.tanh(u[..., 0])], -1)


def f_folded(x, k):  # the same model with the input sequence folded in: x_{k+1} = f(x_k, k, u_{k+1})
    return f_u(x, k, np.broadcast_to(U[k], x.shape[:-1] + (1,)))


def F(x, k):
    out = np.zeros(x.shape[:-1] + (2, 2))
    out[..., 0, 0] = out[..., 1, 1] = 1.0
    out[..., 0, 1] = DT
    out[..., 1, 0] = -DT * np.cos(x[..., 0])
    return out


def h(x, k):
    return np.stack([np.sin(x[..., 0]), x[..., 0] + 0.3 * x[..., 1] ** 2], axis=-1)


def H(x, k):
    out = np.zeros(x.shape[:-1] + (2, 2))
    out[..., 0, 0] = np.cos(x[..., 0])
    out[..., 1, 0] = 1.0
    out[..., 1, 1] = 0.6 * x[..., 1]
    return out


CENS = tk.Censoring(lower=[-0.5, -np.inf], upper=[0.5, 0.9])
FORCED = tk.NonlinearSystem(f_u, h, Q, R, X0, P0, inputs=1)
FOLDED = tk.NonlinearSystem(f_folded, h, Q, R, X0, P0)


def _families(system, **kw):
    return [
        tk.ExtendedKalmanFilter(system, **kw),
        tk.UnscentedKalmanFilter(system, **kw),
        tk.TobitExtendedKalmanFilter(system, CENS, **kw),
        tk.TobitUnscentedKalmanFilter(system, CENS, rule="cubature", **kw),
        tk.NonlinearAssumedDensityFilter(system, CENS, iterations=2, **kw),
    ]


# --------------------------------------------------------------------------- inputs


def test_signature_is_read_and_inputs_declared():
    assert FORCED.takes_input and FORCED.p == 1 and not FOLDED.takes_input
    with pytest.raises(tk.ValidationError, match="inputs"):  # f(x, k, u) without its length
        tk.NonlinearSystem(f_u, h, Q, R, X0, P0)
    with pytest.raises(tk.ValidationError, match="inputs"):  # a length for an f(x, k)
        tk.NonlinearSystem(f_folded, h, Q, R, X0, P0, inputs=1)
    with pytest.raises(tk.ValidationError, match="inputs"):
        tk.NonlinearSystem(f_u, h, Q, R, X0, P0, inputs=0)
    # an optional third parameter: no input unless declared
    assert not tk.NonlinearSystem(lambda x, k, u=None: x, h, Q, R, X0, P0).takes_input
    assert tk.NonlinearSystem(lambda x, k, u=None: x, h, Q, R, X0, P0, inputs=2).p == 2


def test_simulate_draws_the_input_model_as_the_folded_one():
    a = tk.simulate(FORCED, T, 3, channel=CENS, seed=4, inputs=U)
    b = tk.simulate(FOLDED, T, 3, channel=CENS, seed=4)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.y, b.y, rtol=0, atol=1e-13)
    with pytest.raises(tk.ShapeError, match="inputs"):
        tk.simulate(FORCED, T, 3, seed=4, inputs=U[:-1])
    with pytest.raises(tk.ShapeError, match="inputs"):
        tk.simulate(FOLDED, T, 3, seed=4, inputs=U)


@pytest.mark.parametrize("form", ["standard", "square_root"])
def test_filters_and_smoothers_with_inputs_equal_the_folded_model(form):
    y = tk.simulate(FORCED, T, 3, channel=CENS, seed=6, inputs=U).y
    y[1, 4, 0] = np.nan
    for a, b in zip(_families(FORCED, covariance_update=form), _families(FOLDED, covariance_update=form)):
        ra, rb = a.filter(y, u=U), b.filter(y)
        np.testing.assert_allclose(ra.mean, rb.mean, rtol=0, atol=1e-9, err_msg=type(a).__name__)
        np.testing.assert_allclose(ra.cov, rb.cov, rtol=0, atol=1e-9, err_msg=type(a).__name__)
        sa, sb = a.smooth(y, u=U), b.smooth(y)
        np.testing.assert_allclose(sa.mean, sb.mean, rtol=0, atol=1e-9, err_msg=type(a).__name__)


def test_step_and_predict_update_with_inputs_equal_filter():
    y = tk.simulate(FORCED, 8, 1, channel=CENS, seed=7, inputs=U[:8]).y[0]
    for est in _families(FORCED, covariance_update="square_root"):
        ref = est.filter(y, u=U[:8])
        state = est.init()
        for i in range(4):
            state = est.step(state, y[i], u=U[i])
            np.testing.assert_allclose(state.mean, ref.mean[i], rtol=0, atol=1e-12)
        state = est.update(est.predict(state, u=U[4]), y[4])
        np.testing.assert_allclose(state.mean, ref.mean[4], rtol=0, atol=1e-12)


def test_input_refusals():
    y = np.zeros((T, 2))
    with pytest.raises(tk.ShapeError, match="u"):
        tk.UnscentedKalmanFilter(FOLDED).filter(y, u=U)
    with pytest.raises(tk.ShapeError, match="u"):
        tk.UnscentedKalmanFilter(FORCED).filter(y, u=U[:, [0, 0]])
    with pytest.raises(tk.ShapeError, match="u"):
        tk.UnscentedKalmanFilter(FOLDED).step(tk.UnscentedKalmanFilter(FOLDED).init(), y[0], u=[1.0])


def test_discretize_holds_the_input_over_the_interval():
    # dx/dt = -x + u with u held: x(dt) = e^{-dt} x + (1 - e^{-dt}) u
    f = tk.discretize(lambda x, t, u: -x + u, dt=0.2, substeps=8)
    x, u = np.array([[1.0], [-2.0]]), np.array([[0.5], [3.0]])
    # RK4's error: about h^5/120 |u - x| per substep of h = 0.025, 8 substeps: 8 * 8e-11 * 5 ~ 3e-9
    np.testing.assert_allclose(f(x, 0, u), np.exp(-0.2) * x + (1 - np.exp(-0.2)) * u, rtol=0, atol=1e-8)


# --------------------------------------------------------------------------- square-root forms


@pytest.mark.parametrize(
    "make",
    [
        lambda s, c: tk.ExtendedKalmanFilter(s, covariance_update=c),
        lambda s, c: tk.UnscentedKalmanFilter(s, covariance_update=c),
        lambda s, c: tk.UnscentedKalmanFilter(s, alpha=0.5, covariance_update=c),  # a negative centre weight
        lambda s, c: tk.UnscentedKalmanFilter(s, rule="gauss_hermite", order=3, covariance_update=c),
        lambda s, c: tk.TobitExtendedKalmanFilter(s, CENS, covariance_update=c),
        lambda s, c: tk.TobitUnscentedKalmanFilter(s, CENS, covariance_update=c),
        lambda s, c: tk.NonlinearAssumedDensityFilter(s, CENS, covariance_update=c),
        lambda s, c: tk.NonlinearAssumedDensityFilter(s, CENS, rule="cubature", iterations=3, covariance_update=c),
    ],
)
def test_square_root_form_equals_the_standard_form(make):
    system = tk.NonlinearSystem(f_folded, h, Q, R, X0, P0, F=F, H=H)
    y = tk.simulate(system, T, 4, channel=CENS, seed=3).y
    y[1, 3, 0] = np.nan
    a, b = make(system, "standard").filter(y), make(system, "square_root").filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.pred_cov, a.pred_cov, rtol=0, atol=1e-10)


def test_square_root_form_stays_psd_where_the_standard_form_does_not():
    # two very precise readings (R = 1e-12) of a correlated prior of variance 1e6: the standard update
    # P̄ - K P_xy^T subtracts numbers of order 1e6 to leave ones of order 1e-12, and its rounding
    # (eps * 1e6 ~ 1e-10) makes the posterior indefinite; the factor of the array form cannot be
    def hh(x, k):
        return np.stack([x[..., 0] + 1e-6 * x[..., 0] ** 2, x[..., 1] + x[..., 0]], -1)

    P0ill = 1e6 * np.array([[1.0, 0.99], [0.99, 1.0]])
    system = tk.NonlinearSystem(lambda x, k: x, hh, np.zeros((2, 2)), 1e-12 * np.eye(2), [1.0, 2.0], P0ill)
    y = np.array([[1.5, 3.5]])
    eps = np.finfo(float).eps
    for make in (
        lambda c: tk.UnscentedKalmanFilter(system, covariance_update=c),
        lambda c: tk.NonlinearAssumedDensityFilter(system, tk.Censoring(upper=[1e3, 1e3]), covariance_update=c),
    ):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            std = make("standard").filter(y).cov[0]
        sq = make("square_root").filter(y).cov[0]
        scale = np.abs(sq).max()
        assert np.linalg.eigvalsh(sq).min() >= -4 * eps * scale  # PSD to the rounding of its eigenvalues
        assert np.linalg.eigvalsh(std).min() < -1e3 * eps * scale  # indefinite far beyond rounding
