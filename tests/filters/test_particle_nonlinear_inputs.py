"""The particle filter of a NonlinearSystem whose transition takes a known input, f(x, k, u)."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

DT = 0.1
Q = np.diag([1e-3, 4e-3])
R = np.diag([0.05, 0.1])
X0 = np.array([0.8, 0.1])
P0 = np.diag([0.2, 0.3])
T = 12
RUNS = 3
U = np.random.default_rng(5).normal(size=(T, 1))  # u_1..u_T, row k-1 holds u_k
U_RUNS = np.random.default_rng(6).normal(size=(RUNS, T, 1))  # a different input sequence per run


def f_u(x, k, u):  # a forced pendulum: the input is a torque (broadcasts over matching leading axes)
    return np.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * np.sin(x[..., 0]) + DT * np.tanh(u[..., 0])], -1)


def h(x, k):
    return np.stack([np.sin(x[..., 0]), x[..., 0] + 0.3 * x[..., 1] ** 2], axis=-1)


def folded_per_run(useq):
    """The model with the inputs (runs, T, p) folded into f(x, k): the rows of x are run-outermost, as the
    particle filter lays out its particles and sigma points; a single unbatched state takes run 0's input."""

    def f(x, k):
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return f_u(x, k, useq[0, k])
        runs = useq.shape[0] if x.shape[0] % useq.shape[0] == 0 else 1
        z = x.reshape(runs, -1, x.shape[-1])
        return f_u(z, k, useq[:runs, k][:, None, :]).reshape(x.shape)

    return f


CENS = tk.Censoring(lower=[-0.5, -np.inf], upper=[0.5, 0.9])
FORCED = tk.NonlinearSystem(f_u, h, Q, R, X0, P0, inputs=1)


def _pf(system, **kw):
    return tk.ParticleFilter(system, CENS, particles=64, seed=11, **kw)


OUT = ("mean", "cov", "pred_mean", "pred_cov", "extras")


def _same(a, b, atol=1e-12):
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol, err_msg=name)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=0, atol=1e-10)


def test_inputs_equal_the_model_with_the_inputs_folded_into_f():
    y = tk.simulate(FORCED, T, RUNS, channel=CENS, seed=3, inputs=U).y
    folded = tk.NonlinearSystem(folded_per_run(np.broadcast_to(U, (RUNS, T, 1))), h, Q, R, X0, P0)
    _same(_pf(FORCED).filter(y, u=U, outputs=OUT), _pf(folded).filter(y, outputs=OUT))


def test_per_run_inputs_equal_the_folded_model():
    y = tk.simulate(FORCED, T, RUNS, channel=CENS, seed=4, inputs=U_RUNS).y
    folded = tk.NonlinearSystem(folded_per_run(U_RUNS), h, Q, R, X0, P0)
    a = _pf(FORCED).filter(y, u=U_RUNS, outputs=OUT)
    _same(a, _pf(folded).filter(y, outputs=OUT))
    # the inputs matter: dropping them (u = 0) moves the estimate
    b = _pf(FORCED).filter(y, outputs=OUT)
    assert np.abs(a.mean - b.mean).max() > 1e-3


def test_no_input_means_zero_input():
    y = tk.simulate(FORCED, T, 2, channel=CENS, seed=5).y
    zero = _pf(FORCED).filter(y, u=np.zeros((T, 1)), outputs=OUT)
    _same(_pf(FORCED).filter(y, outputs=OUT), zero)


def test_step_with_inputs_equals_filter():
    y = tk.simulate(FORCED, T, RUNS, channel=CENS, seed=6, inputs=U_RUNS).y
    pf = _pf(FORCED)
    ref = pf.filter(y, u=U_RUNS)
    state = pf.init(batch_shape=(RUNS,))
    for i in range(T):
        state = pf.step(state, y[:, i], u=U_RUNS[:, i])
        np.testing.assert_allclose(state.mean, ref.mean[:, i], rtol=0, atol=1e-12)


def test_log_likelihood_takes_the_inputs():
    y = tk.simulate(FORCED, T, RUNS, channel=CENS, seed=8, inputs=U).y
    folded = tk.NonlinearSystem(folded_per_run(np.broadcast_to(U, (RUNS, T, 1))), h, Q, R, X0, P0)
    np.testing.assert_allclose(_pf(FORCED).log_likelihood(y, u=U), _pf(folded).log_likelihood(y), rtol=0, atol=1e-10)


def test_input_refusals():
    y = np.zeros((T, 2))
    unforced = tk.NonlinearSystem(lambda x, k: x, h, Q, R, X0, P0)
    with pytest.raises(tk.ShapeError, match="u"):  # an f(x, k) takes no input
        _pf(unforced).filter(y, u=U)
    with pytest.raises(tk.ShapeError, match="u"):  # the wrong input length
        _pf(FORCED).filter(y, u=U[:, [0, 0]])
    with pytest.raises(tk.ShapeError, match="u"):
        pf = _pf(FORCED)
        pf.step(pf.init(), y[0], u=[1.0, 2.0])
