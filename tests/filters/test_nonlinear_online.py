"""The online API of every nonlinear estimator: the loop over ``step`` equals ``filter``, states pickle and resume.

The same contract as ``tests/filters/test_online.py`` for the linear families, here for the estimators of a
:class:`~tobitkf.NonlinearSystem` (python ``f`` and ``h``, the numpy path): the EKF and the UKF under each
sigma-point rule, the Tobit EKF / UKF, the nonlinear assumed-density filter (censored, interval readings,
iterated), their square-root forms, the fading filters of order 2 (the window of past states) and the particle
filter (bootstrap and linearised proposals); a reading vector with one channel lost, a step with none, leading
batch axes of any rank. Tolerance 1e-12 absolute (the same arithmetic in another order of calls at most), exact
for the resume from a pickled state.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters.core import FilterState

from .test_nonlinear_model import pendulum

TOL = 1e-12
T = 14
CENS = tk.Censoring(lower=[-0.3, -np.inf], upper=[0.5, 0.9])
QUANT = tk.Quantizer([0.25, 0.3], lower=[-0.5, -1.0], upper=[0.5, 1.2])

FADING2 = tk.RiceFading.gaussian(2, [0.9, 0.4, 0.2], [0.01, 0.02, 0.01])  # the reading of x_k, x_(k-1), x_(k-2)

# the square-root forms (numpy): name -> (make(system, covariance_update), channel)
SQRT = {
    "ekf": (lambda s, c: tk.ExtendedKalmanFilter(s, covariance_update=c), None),
    "ukf": (lambda s, c: tk.UnscentedKalmanFilter(s, alpha=0.5, kappa=1.0, covariance_update=c), None),
    "tobit-ekf": (lambda s, c: tk.TobitExtendedKalmanFilter(s, CENS, covariance_update=c), CENS),
    "tobit-ukf-quantizer": (
        lambda s, c: tk.TobitUnscentedKalmanFilter(s, QUANT, rule="cubature", covariance_update=c),
        QUANT,
    ),
    "adf": (lambda s, c: tk.NonlinearAssumedDensityFilter(s, CENS, covariance_update=c), CENS),
    "adf-iterated": (lambda s, c: tk.NonlinearAssumedDensityFilter(s, CENS, iterations=3, covariance_update=c), CENS),
}

CASES = {
    "ekf": (lambda s: tk.ExtendedKalmanFilter(s), None),
    "ekf-joseph": (lambda s: tk.ExtendedKalmanFilter(s, covariance_update="joseph"), None),
    "ukf": (lambda s: tk.UnscentedKalmanFilter(s, alpha=0.5, beta=2.0, kappa=1.0), None),
    "ukf-cubature": (lambda s: tk.UnscentedKalmanFilter(s, rule="cubature"), None),
    "ukf-gauss-hermite": (lambda s: tk.UnscentedKalmanFilter(s, rule="gauss_hermite", order=3), None),
    "tobit-ekf": (lambda s: tk.TobitExtendedKalmanFilter(s, CENS), CENS),
    "tobit-ukf-quantizer": (lambda s: tk.TobitUnscentedKalmanFilter(s, QUANT, rule="cubature"), QUANT),
    "adf": (lambda s: tk.NonlinearAssumedDensityFilter(s, CENS), CENS),
    "adf-quantizer": (lambda s: tk.NonlinearAssumedDensityFilter(s, QUANT, rule="cubature"), QUANT),
    "adf-iterated": (lambda s: tk.NonlinearAssumedDensityFilter(s, CENS, iterations=3), CENS),
    "pf": (lambda s: tk.ParticleFilter(s, CENS, particles=64, seed=7), CENS),
    "pf-linearised": (lambda s: tk.ParticleFilter(s, CENS, particles=64, proposal="linearised", seed=7), CENS),
    "fading2-tobit-ukf": (lambda s: tk.FadingTobitUnscentedKalmanFilter(s, FADING2, CENS), [FADING2, CENS]),
    "fading2-ekf": (lambda s: tk.FadingExtendedKalmanFilter(s, FADING2), [FADING2]),
    "fading2-adf-iterated": (
        lambda s: tk.FadingNonlinearAssumedDensityFilter(s, FADING2, QUANT, rule="cubature", iterations=2),
        [FADING2, QUANT],
    ),
    **{
        f"{name}-sqrt": (lambda s, make=make: make(s, "square_root"), channel) for name, (make, channel) in SQRT.items()
    },
}


def readings(channel, batch, seed):
    """(*batch, T, 2) readings of the pendulum through ``channel``, one channel lost at some steps, both at one."""
    runs = int(np.prod(batch)) if batch else 1
    y = tk.simulate(pendulum(), T, runs, channel=channel, seed=seed).y
    rng = np.random.default_rng(seed)
    y[rng.random(y.shape) < 0.1] = np.nan
    y[:, 4] = np.nan  # a step with no reading at all
    return y.reshape(batch + (T, 2))


def run_steps(est, y, batch, start=None):
    state = est.init(batch_shape=batch) if start is None else start
    means, covs = [], []
    for i in range(y.shape[-2]):
        state = est.step(state, y[..., i, :])
        means.append(state.mean.copy())
        covs.append(state.cov.copy())
    return state, np.stack(means, axis=-2), np.stack(covs, axis=-3)


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)], ids=str)
@pytest.mark.parametrize("name", sorted(CASES))
def test_step_loop_equals_filter(name, batch):
    make, channel = CASES[name]
    est = make(pendulum())
    y = readings(channel, batch, seed=21)
    res = est.filter(y)
    state, means, covs = run_steps(est, y, batch)
    assert res.mean.shape == batch + (T, 2) and res.times.tolist() == list(range(1, T + 1))
    np.testing.assert_allclose(means, res.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(covs, res.cov, rtol=0, atol=TOL)
    assert state.k == T and res.final.k == T
    np.testing.assert_allclose(state.mean, res.final.mean, rtol=0, atol=TOL)
    if name.startswith(
        "pf"
    ):  # no reading: the weights stay, the step's likelihood term is 0 (its pred_mean is unscented)
        assert np.all(res.extras["log_likelihood"][..., 4] == 0.0)
    else:  # the step with no reading is the prediction alone
        np.testing.assert_array_equal(res.mean[..., 4, :], res.pred_mean[..., 4, :])
        np.testing.assert_array_equal(res.cov[..., 4, :, :], res.pred_cov[..., 4, :, :])


@pytest.mark.parametrize("name", sorted(n for n in CASES if not n.startswith("pf")))
def test_predict_then_update_equals_step(name):
    # the particle filter's predict and update draw from its generator in another order of calls; the Gaussian
    # filters' step is their predict followed by their update
    make, channel = CASES[name]
    est = make(pendulum())
    y = readings(channel, (3,), seed=22)
    a = b = est.init(batch_shape=(3,))
    for i in range(T):
        a = est.step(a, y[:, i])
        b = est.update(est.predict(b), y[:, i])
        np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=TOL)
        np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=TOL)


@pytest.mark.parametrize("name", sorted(CASES))
def test_pickled_state_resumes_identically(name):
    make, channel = CASES[name]
    est = make(pendulum())
    batch = (3,)
    y = readings(channel, batch, seed=23)
    half = T // 2
    state, _, _ = run_steps(est, y[..., :half, :], batch)
    revived = pickle.loads(pickle.dumps(state))
    assert isinstance(revived, FilterState) and revived.k == half
    a, ma, ca = run_steps(est, y[..., half:, :], batch, start=state)
    b, mb, cb = run_steps(est, y[..., half:, :], batch, start=revived)
    np.testing.assert_array_equal(ma, mb)
    np.testing.assert_array_equal(ca, cb)
    # filter() continues from a state too, and the two halves make the whole record
    whole = est.filter(y)
    second = est.filter(y[..., half:, :], state=pickle.loads(pickle.dumps(state)))
    assert second.times.tolist() == list(range(half + 1, T + 1))
    np.testing.assert_allclose(second.mean, whole.mean[..., half:, :], rtol=0, atol=TOL)
    np.testing.assert_allclose(second.cov, whole.cov[..., half:, :, :], rtol=0, atol=TOL)


@pytest.mark.parametrize("batch", [(), (3,)], ids=str)
@pytest.mark.parametrize("name", sorted(SQRT))
def test_square_root_step_loop_equals_the_standard_form(name, batch):
    """The square-root form's online step (numpy) carries the factor from step to step: its loop of steps is its
    ``filter`` and, on this well-conditioned case, the standard form's ``filter`` to 1e-10 (the same equations in
    QR array form)."""
    make, channel = SQRT[name]
    y = readings(channel, batch, seed=24)
    est = make(pendulum(), "square_root")
    state, means, covs = run_steps(est, y, batch)
    assert state.S is not None and np.allclose(state.S @ np.swapaxes(state.S, -1, -2), state.P, rtol=0, atol=1e-14)
    res = est.filter(y)
    np.testing.assert_allclose(means, res.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(covs, res.cov, rtol=0, atol=TOL)
    std = make(pendulum(), "standard").filter(y)
    np.testing.assert_allclose(means, std.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(covs, std.cov, rtol=0, atol=1e-10)
