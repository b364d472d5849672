"""An output map with a known input, h(x, k, u): a feedthrough D u_k or an input-dependent reading.

The reference is the linear model: with f(x, k, u) = A x + B_u u and h(x, k, u) = C x + D u every nonlinear filter
is exactly the linear filter of the model with the input matrices B_u and D (the Kalman filter, the Tobit Kalman
filter, the assumed-density filter), and the compiled loop (numba f and h) equals the numpy path.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
BU = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0], [0.3, 1.0]])
D = np.array([[0.8], [-0.4]])
Q = np.diag([0.05, 0.08])
R = np.diag([0.2, 0.3])
X0, P0 = np.array([0.5, -0.2]), np.diag([1.0, 0.5])
T = 20
U = np.random.default_rng(11).normal(size=(T, 1))
CENS = tk.Censoring(lower=[-0.3, -np.inf], upper=[np.inf, 0.6])


def f_lin(x, k, u):
    return x @ A.T + u @ BU.T


def f_plain(x, k):
    return x @ A.T


def h_lin(x, k, u):
    return x @ C.T + u @ D.T


def H_lin(x, k, u):
    return np.broadcast_to(C, x.shape[:-1] + C.shape)


LIN = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0, Bu=BU, D=D)
NL = tk.NonlinearSystem(f_lin, h_lin, Q, R, X0, P0, inputs=1)


def _data(runs=3, seed=2):
    return tk.simulate(LIN, T, runs, channel=CENS, seed=seed, inputs=U)


def test_the_input_of_h_is_read_from_its_signature():
    assert NL.f_takes_input and NL.h_takes_input and NL.p == 1
    only_h = tk.NonlinearSystem(f_plain, h_lin, Q, R, X0, P0, inputs=1)
    assert not only_h.f_takes_input and only_h.h_takes_input and only_h.takes_input
    with pytest.raises(tk.ValidationError, match="h\\(x, k, u\\)"):  # h's input without its length
        tk.NonlinearSystem(f_plain, h_lin, Q, R, X0, P0)
    with pytest.raises(tk.ValidationError, match="neither f nor h"):
        tk.NonlinearSystem(f_plain, lambda x, k: x @ C.T, Q, R, X0, P0, inputs=1)
    with pytest.raises(tk.ShapeError, match="H\\(x, 1\\)"):  # the Jacobian of an h(x, k, u) takes u too
        tk.NonlinearSystem(f_lin, h_lin, Q, R, X0, P0, inputs=1, H=lambda x, k, u: np.zeros(x.shape[:-1] + (3, 2)))


def test_simulate_draws_h_with_the_input_of_its_step():
    a = tk.simulate(NL, T, 4, channel=CENS, seed=5, inputs=U)
    b = tk.simulate(LIN, T, 4, channel=CENS, seed=5, inputs=U)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.y_latent, b.y_latent, rtol=0, atol=1e-12)
    # without inputs an h(x, k, u) reads u = 0: the feedthrough vanishes
    c = tk.simulate(NL, T, 4, seed=5)
    d = tk.simulate(tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0), T, 4, seed=5)
    np.testing.assert_allclose(c.y_latent, d.y_latent, rtol=0, atol=1e-12)


@pytest.mark.parametrize("form", ["standard", "joseph", "square_root"])
def test_the_extended_and_unscented_filters_equal_the_kalman_filter_with_D(form):
    y = _data().y_latent.copy()
    y[0, 3, 1] = np.nan
    ref = tk.KalmanFilter(LIN).filter(y, u=U)
    ests = [tk.ExtendedKalmanFilter(NL, covariance_update=form)]
    ests.append(tk.ExtendedKalmanFilter(tk.NonlinearSystem(f_lin, h_lin, Q, R, X0, P0, inputs=1, H=H_lin)))
    if form != "joseph":
        ests += [tk.UnscentedKalmanFilter(NL, rule=r, covariance_update=form) for r in ("unscented", "cubature")]
    for est in ests:
        out = est.filter(y, u=U)
        np.testing.assert_allclose(out.mean, ref.mean, rtol=0, atol=1e-10, err_msg=repr(est))
        np.testing.assert_allclose(out.cov, np.broadcast_to(ref.cov, out.cov.shape), rtol=0, atol=1e-10)


def test_the_censored_filters_equal_their_linear_forms_with_D():
    y = _data().y
    tkf = tk.TobitKalmanFilter(LIN, CENS).filter(y, u=U)
    adf = tk.AssumedDensityFilter(LIN, CENS).filter(y, u=U)
    for est, ref in (
        (tk.TobitExtendedKalmanFilter(NL, CENS), tkf),
        (tk.TobitUnscentedKalmanFilter(NL, CENS, rule="cubature"), tkf),
        (tk.NonlinearAssumedDensityFilter(NL, CENS), adf),
        (tk.NonlinearAssumedDensityFilter(NL, CENS, covariance_update="square_root"), adf),
    ):
        out = est.filter(y, u=U)
        np.testing.assert_allclose(out.mean, ref.mean, rtol=0, atol=1e-10, err_msg=repr(est))
        np.testing.assert_allclose(out.cov, np.broadcast_to(ref.cov, out.cov.shape), rtol=0, atol=1e-10)


def test_the_smoothers_and_the_online_steps_read_the_input_of_h():
    y = _data().y_latent
    ref = tk.KalmanFilter(LIN).smooth(y, u=U)
    for est in (tk.ExtendedKalmanFilter(NL), tk.UnscentedKalmanFilter(NL)):
        np.testing.assert_allclose(est.smooth(y, u=U).mean, ref.mean, rtol=0, atol=1e-10)
    # the iterated posterior-linearisation smoother of a linear model is the RTS smoother at every iteration
    adf = tk.NonlinearAssumedDensityFilter(NL, tk.Censoring())
    np.testing.assert_allclose(adf.smooth(y, u=U, iterations=3).mean, ref.mean, rtol=0, atol=1e-9)
    est = tk.TobitUnscentedKalmanFilter(NL, CENS)
    yc = _data(1).y[0]
    full = est.filter(yc, u=U)
    state = est.init()
    for i in range(3):
        state = est.step(state, yc[i], u=U[i])
        np.testing.assert_allclose(state.mean, full.mean[i], rtol=0, atol=1e-12)
    state = est.update(est.predict(state, u=U[3]), yc[3])  # predict keeps u_k for the update's h(x, k, u_k)
    np.testing.assert_allclose(state.mean, full.mean[3], rtol=0, atol=1e-12)


def test_the_particle_filter_reads_the_input_of_h():
    # the same draws as the model with the input sequence folded into h: the particle filter's numbers agree
    def h_folded(x, k):
        return x @ C.T + U[k - 1] @ D.T

    def f_folded(x, k):
        return x @ A.T + U[k] @ BU.T

    folded = tk.NonlinearSystem(f_folded, h_folded, Q, R, X0, P0)
    y = _data(2).y
    a = tk.ParticleFilter(NL, channel=CENS, particles=200, seed=3).filter(y, u=U)
    b = tk.ParticleFilter(folded, channel=CENS, particles=200, seed=3).filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)


def test_the_compiled_loop_reads_the_input_of_h():
    numba = pytest.importorskip("numba")

    @numba.njit
    def f_c(x, k):  # no input in f: only h reads it
        out = np.empty(x.shape)
        out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
        out[..., 1] = x[..., 1] - 0.1 * np.sin(x[..., 0])
        return out

    @numba.njit
    def h_c(x, k, u):
        out = np.empty(x.shape[:-1] + (2,))
        out[..., 0] = np.sin(x[..., 0]) + 0.8 * u[..., 0]
        out[..., 1] = 0.5 * x[..., 1] + 0.1 * x[..., 0] ** 3 - 0.4 * u[..., 0]
        return out

    system = tk.NonlinearSystem(f_c, h_c, Q, R, X0, P0, inputs=1)
    assert not system.f_takes_input and system.h_takes_input
    y = tk.simulate(system, T, 70, channel=CENS, seed=8, inputs=U).y  # 70 runs: two blocks of the compiled loop
    y[3, 5, 0] = y[66, 2, 1] = np.nan
    for make in (
        lambda b: tk.ExtendedKalmanFilter(system, backend=b),
        lambda b: tk.UnscentedKalmanFilter(system, backend=b),
        lambda b: tk.TobitExtendedKalmanFilter(system, CENS, backend=b),
        lambda b: tk.TobitUnscentedKalmanFilter(system, CENS, rule="cubature", backend=b),
        lambda b: tk.NonlinearAssumedDensityFilter(system, CENS, iterations=2, backend=b),
    ):
        # numba's sin and numpy's may differ in the last bit; a central-difference Jacobian (step ~6e-6) turns that
        # into ~4e-11 of H, which a run's steps can grow a few times: 1e-9 for the extended filters
        tol = 1e-9 if make("numpy").rule is None else 1e-10
        for u in (U, None):  # no input given: u = 0 on both paths
            a, b = make("numpy").filter(y, u=u), make("numba").filter(y, u=u)
            np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=tol, err_msg=repr(make("numpy")))
            np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=tol)
    est = tk.NonlinearAssumedDensityFilter(system, CENS, backend="numba")
    assert est._use_compiled()
