"""The particle filter's linearised optimal proposal (``proposal="linearised"``) on a NonlinearSystem: for a linear h
and exact readings it is the linear model's optimal proposal draw for draw; one step from a Gaussian prior matches
the exact posterior mean and evidence by quadrature, exact and censored readings (its weights are exact however poor
the linearisation); linearised about the mode it keeps more effective particles than the bootstrap proposal; over a
record it converges to the bootstrap filter's estimate."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
C = np.array([[1.0, 0.5], [0.0, 1.0]])
Q, R = 0.05 * np.eye(2), np.diag([0.3, 0.2])
X0, P0 = np.array([1.0, 0.0]), np.eye(2)


def _linear_pair():
    lin = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0)
    nl = tk.NonlinearSystem(
        lambda x, k: x @ A.T, lambda x, k: x @ C.T, Q=Q, R=R, x0=X0, P0=P0,
        H=lambda x, k: np.broadcast_to(C, x.shape[:-1] + C.shape),
    )  # fmt: skip
    return lin, nl


@pytest.mark.parametrize("steps", [1, 3])
def test_linear_h_gives_the_linear_optimal_proposal(steps):
    # the same generator draws the same numbers in the same order; the linearisation of a linear h is h itself
    # wherever it is taken, so the proposal is the linear one and the weights' correction vanishes: the same
    # particles, weights and resamplings for exact readings (some lost)
    lin, nl = _linear_pair()
    y = tk.simulate(lin, 15, 3, seed=3).y.copy()
    y[1, 4, 0] = np.nan  # a lost reading
    y[2, 6] = np.nan  # a step without any
    a = tk.ParticleFilter(nl, particles=200, proposal="linearised", linearisation_steps=steps, seed=4).filter(y)
    b = tk.ParticleFilter(lin, particles=200, proposal="optimal", seed=4, backend="numpy").filter(y)
    assert a.extras["resampled"].any()
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=0, atol=1e-10, err_msg=key)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.extras["ess"], b.extras["ess"], rtol=1e-10, atol=0)
    np.testing.assert_array_equal(a.extras["resampled"], b.extras["resampled"])


# --------------------------------------------------------------------------- one step against quadrature

X_MEAN, X_VAR, QS = 0.3, 1.0, 0.5
R1 = np.array([0.05, 0.05])
LOWER = np.array([0.0, -np.inf])


def _h(x):
    """A scalar state read by two curved, monotone sensors (a posterior of one mode), (..., 1) -> (..., 2)."""
    return np.concatenate([x + 0.3 * np.sin(2.0 * x), np.exp(0.5 * x)], axis=-1)


def _system():
    f = lambda x, k: 0.9 * x  # noqa: E731
    return tk.NonlinearSystem(f, lambda x, k: _h(x), [[QS]], np.diag(R1), [X_MEAN], [[X_VAR]])


def _oracle(y):
    """Posterior mean of x_1 ~ N(0.9 X_MEAN, 0.81 X_VAR + QS) given y_1 (the first channel censored below at 0 when
    y sits there; NaN: no reading) and the log evidence, by a Riemann sum over +-10 standard deviations."""
    m, v = 0.9 * X_MEAN, 0.81 * X_VAR + QS
    x = np.linspace(-10, 10, 8001) * np.sqrt(v) + m
    hx = _h(x[:, None])
    logw = -0.5 * (x - m) ** 2 / v - 0.5 * np.log(2 * np.pi * v)
    for l in range(2):
        if np.isnan(y[l]):
            continue
        if y[l] <= LOWER[l]:
            logw = logw + log_ndtr((LOWER[l] - hx[:, l]) / np.sqrt(R1[l]))
        else:
            logw = logw - 0.5 * (y[l] - hx[:, l]) ** 2 / R1[l] - 0.5 * np.log(2 * np.pi * R1[l])
    top = logw.max()
    w = np.exp(logw - top)
    return (w @ x) / w.sum(), top + np.log(w.sum() * (x[1] - x[0]))


@pytest.mark.parametrize("steps", [1, 3])
@pytest.mark.parametrize("y", [[0.8, 1.5], [0.0, 0.9], [1.9, np.nan], [np.nan, 0.6], [0.0, np.nan]], ids=str)
def test_one_step_matches_the_exact_posterior_by_quadrature(y, steps):
    # the particle mean's Monte Carlo error is about sd / sqrt(ESS); the evidence estimate (the weights' mean) has a
    # relative standard error sqrt((Np / ESS - 1) / Np); both within five standard errors
    y = np.array(y)
    Np = 40000
    cens = tk.Censoring(lower=LOWER)
    pf = tk.ParticleFilter(
        _system(), cens, particles=Np, resample_threshold=0.0, proposal="linearised", linearisation_steps=steps, seed=5
    )
    res = pf.filter(y[None])
    mean, log_evidence = _oracle(y)
    ess = res.extras["ess"][0]
    assert ess > 100  # enough for the standard errors below (the extended update about mu can be poor: ~270 here)
    se = np.sqrt(res.cov[0, 0, 0] / ess)
    assert abs(res.mean[0, 0] - mean) < 5 * se, (res.mean[0, 0], mean, se)
    se_ll = np.sqrt((Np / ess - 1) / Np)
    assert abs(res.extras["log_likelihood"][0] - log_evidence) < 5 * se_ll, (res.extras["log_likelihood"], log_evidence)


def test_linearising_about_the_mode_keeps_more_of_the_particles():
    """Two exact readings of one mode: the proposal linearised about the mode (three steps) keeps far more effective
    particles than the bootstrap proposal, and a censored reading alone leaves the proposal the prior's (the
    interval enters the weight only): the same effective sample size as the bootstrap filter's, to within the
    spread of two runs of the same size."""
    cens = tk.Censoring(lower=LOWER)

    def ess(y, **kw):
        pf = tk.ParticleFilter(_system(), cens, particles=40000, resample_threshold=0.0, seed=5, **kw)
        return pf.filter(np.array([y])).extras["ess"][0]

    assert ess([0.8, 1.5], proposal="linearised", linearisation_steps=3) > 2 * ess([0.8, 1.5])
    a, b = ess([0.0, np.nan], proposal="linearised"), ess([0.0, np.nan])
    assert abs(a - b) < 0.05 * b, (a, b)


# --------------------------------------------------------------------------- a record


def _f2(x, k):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
    out[..., 1] = 0.95 * x[..., 1] - 0.3 * np.sin(x[..., 0])
    return out


def _h2(x, k):
    return np.stack([x[..., 0] + 0.3 * np.sin(2.0 * x[..., 0]), np.exp(0.4 * x[..., 1])], axis=-1)


def _record_system():
    return tk.NonlinearSystem(_f2, _h2, Q=np.diag([0.02, 0.2]), R=np.diag([0.003, 0.003]), x0=[0.5, 0.0], P0=np.eye(2))


def _mse_against(est, y, ref):
    return ((est.filter(y, outputs=("mean",)).mean - ref) ** 2).sum(-1).mean(-1)  # per run


@pytest.mark.heavy
def test_record_converges_to_the_bootstrap_estimate_with_fewer_particles():
    """Precise readings of a nonlinear model (a few censored): with 1000 particles both proposals estimate the
    same posterior mean (the squared error of each against the truth differs by no more than three standard errors
    of the paired difference), and against a 20 000-particle bootstrap reference the linearised proposal with 100
    particles is closer than the bootstrap filter with 100."""
    sys_ = _record_system()
    cens = tk.Censoring(upper=[np.inf, 1.6])
    N, T = 60, 25
    data = tk.simulate(sys_, T, N, channel=cens, seed=9)
    truth = data.x[:, 1:]
    lin = _mse_against(
        tk.ParticleFilter(sys_, cens, particles=1000, proposal="linearised", linearisation_steps=3, seed=1),
        data.y,
        truth,
    )
    boot = _mse_against(tk.ParticleFilter(sys_, cens, particles=1000, seed=2), data.y, truth)
    d = lin - boot
    assert abs(d.mean()) < 3 * d.std(ddof=1) / np.sqrt(N), (lin.mean(), boot.mean())
    ref = tk.ParticleFilter(sys_, cens, particles=20000, seed=3).filter(data.y, outputs=("mean",)).mean
    small_lin = _mse_against(
        tk.ParticleFilter(sys_, cens, particles=100, proposal="linearised", linearisation_steps=3, seed=4), data.y, ref
    )
    small_boot = _mse_against(tk.ParticleFilter(sys_, cens, particles=100, seed=5), data.y, ref)
    d = small_boot - small_lin
    assert d.mean() > 3 * d.std(ddof=1) / np.sqrt(N), (small_lin.mean(), small_boot.mean())
