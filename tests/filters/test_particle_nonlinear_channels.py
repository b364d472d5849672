"""The particle filter of a NonlinearSystem read through Rice fading (of order 0 and 2: the window of past states) or
random saturation (each with an optional censoring): on a linear f, h it is the linear model's bootstrap filter,
draw for draw; one step from a
Gaussian prior matches the exact posterior mean and evidence by brute-force quadrature over the state (and the
fading gain); the online steps equal ``filter``; the channels it still refuses are named."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
C = np.array([[1.0, 0.5], [0.0, 1.0]])
Q, R = 0.05 * np.eye(2), np.diag([0.3, 0.2])
X0, P0 = np.array([1.0, 0.0]), np.eye(2)

FADING = tk.RiceFading.gaussian(0, [[0.8, 1.1]], [[0.05, 0.02]])
FADING_UNIFORM = tk.RiceFading(0, tk.laws.Uniform([[0.5, 0.9]], [[1.1, 1.3]]))  # gains drawn per particle
SATURATION = tk.RandomSaturation(mu=[0.3, 0.2], nu=[0.8, 0.9], level=[1.0, 0.8])
CENS = tk.Censoring(lower=[0.2, -0.3])

FADING2 = tk.RiceFading.gaussian(2, [[0.8, 1.1], [0.5, 0.3], [0.2, -0.4]], [[0.05, 0.02], [0.01, 0.03], [0.02, 0.0]])
FADING2_UNIFORM = tk.RiceFading(
    2, tk.laws.Uniform([[0.5, 0.9], [0.1, 0.2], [0.0, 0.1]], [[1.1, 1.3], [0.5, 0.6], [0.3, 0.2]])
)

PAIRS = {
    "fading": [FADING],
    "fading censored": [FADING, CENS],
    "fading drawn gains": [FADING_UNIFORM],
    "fading of order 2": [FADING2],
    "fading of order 2 censored": [FADING2, CENS],
    "fading of order 2 drawn gains": [FADING2_UNIFORM],
    "saturation": [SATURATION],
    "saturation censored": [SATURATION, CENS],
}


def _linear_pair():
    lin = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0)
    nl = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k: x @ C.T, Q=Q, R=R, x0=X0, P0=P0)
    return lin, nl


def _readings(lin, channel, seed=3):
    if isinstance(channel[0], tk.RandomSaturation):  # drawn from the linear model, then censored
        data = tk.simulate(lin, 15, 3, measurement=channel[0], seed=seed)
        y = data.y if len(channel) == 1 else channel[1].clip(data.y)
    else:
        y = tk.simulate(lin, 15, 3, channel=channel, seed=seed).y
    y = y.copy()
    y[1, 4, 0] = np.nan  # a lost reading
    return y


@pytest.mark.parametrize("name", list(PAIRS))
def test_linear_f_and_h_give_the_linear_bootstrap_filter(name):
    # the same generator draws the same numbers in the same order, and the weights are the linear model's
    # likelihood with C x computed as h(x): the two filters carry the same particles
    channel = PAIRS[name]
    lin, nl = _linear_pair()
    y = _readings(lin, channel)
    a = tk.ParticleFilter(nl, channel, particles=200, seed=4).filter(y)
    b = tk.ParticleFilter(lin, channel, particles=200, proposal="prior", seed=4, backend="numpy").filter(y)
    assert a.extras["resampled"].any()  # the resampling path is crossed too
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=0, atol=1e-12, err_msg=key)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a.extras["resampled"], b.extras["resampled"])


# --------------------------------------------------------------------------- one step against quadrature


def _h(x):
    """A scalar state read by two nonlinear sensors, (..., 1) -> (..., 2)."""
    return np.concatenate([x + 0.4 * x**2, np.sin(1.5 * x) + 0.2], axis=-1)


X_MEAN, X_VAR = 0.3, 1.0
R1 = np.array([0.1, 0.05])


def _system():
    return tk.NonlinearSystem(lambda x, k: x, lambda x, k: _h(x), [[0.0]], np.diag(R1), [X_MEAN], [[X_VAR]])


def _normal_logpdf(y, mean, var):
    return -0.5 * (y - mean) ** 2 / var - 0.5 * np.log(2 * np.pi * var)


def _posterior(loglik):
    """Posterior mean of x ~ N(X_MEAN, X_VAR) and the log evidence, given log p(y | x) on a grid of x, by a Riemann
    sum over +-10 standard deviations."""
    x = np.linspace(-10, 10, 4001) * np.sqrt(X_VAR) + X_MEAN
    logw = _normal_logpdf(x, X_MEAN, X_VAR) + loglik(x)
    top = logw.max()
    w = np.exp(logw - top)
    dx = x[1] - x[0]
    return (w @ x) / w.sum(), top + np.log(w.sum() * dx)


def _fading_loglik(y, lower, gains, x):
    """log p(y | x) of y* = theta h(x) + v, by quadrature over each channel's gain theta (its density on a grid);
    a reading at ``lower`` is censored."""
    hx = _h(x[:, None])
    out = np.zeros(x.shape)
    for l in range(2):
        theta, dens = gains[l]
        mean = theta[None, :] * hx[:, l : l + 1]
        if y[l] <= lower[l]:
            term = np.exp(log_ndtr((lower[l] - mean) / np.sqrt(R1[l])))
        else:
            term = np.exp(_normal_logpdf(y[l], mean, R1[l]))
        with np.errstate(divide="ignore"):  # far out in x no gain explains y: weight 0
            out += np.log(term @ dens * (theta[1] - theta[0]))
    return out


def _gaussian_gain(mean, var):
    t = np.linspace(mean - 10 * np.sqrt(var), mean + 10 * np.sqrt(var), 801)
    return t, np.exp(_normal_logpdf(t, mean, var))


def _uniform_gain(low, high):
    t = np.linspace(low, high, 801)
    d = np.full(t.shape, 1.0 / (high - low))
    d[[0, -1]] *= 0.5  # trapezoid ends: the Riemann sum of a density with jumps at the ends
    return t, d


def _saturation_loglik(y, lower, channel, x):
    """log p(y | x) of the three modes (saturated, linear, noise only) written from the channel's definition."""
    hx = _h(x[:, None])
    out = np.zeros(x.shape)
    for l in range(2):
        mu, nu, u = channel.mu[l], channel.nu[l], channel.level[l]
        means = (np.clip(hx[:, l], -u, u), hx[:, l], np.zeros(x.shape))
        probs = (mu, (1 - mu) * nu, (1 - mu) * (1 - nu))
        if y[l] <= lower[l]:
            terms = [p * np.exp(log_ndtr((lower[l] - m) / np.sqrt(R1[l]))) for p, m in zip(probs, means)]
        else:
            terms = [p * np.exp(_normal_logpdf(y[l], m, R1[l])) for p, m in zip(probs, means)]
        out += np.log(sum(terms))
    return out


LOWER = np.array([0.0, -np.inf])
SAT = tk.RandomSaturation(mu=[0.4, 0.3], nu=[0.9, 0.7], level=[0.6, 0.5])
ONE_STEP = {
    # name: (channel pieces, reading y_1)
    "fading": ([tk.RiceFading.gaussian(0, [[0.9, 1.2]], [[0.09, 0.04]])], [0.8, 0.9]),
    "fading censored": (
        [tk.RiceFading.gaussian(0, [[0.9, 1.2]], [[0.09, 0.04]]), tk.Censoring(lower=LOWER)],
        [0.0, 0.9],
    ),
    "fading uniform gains": ([tk.RiceFading(0, tk.laws.Uniform([[0.5, 0.9]], [[1.1, 1.3]]))], [0.8, 0.9]),
    "saturation": ([SAT], [0.6, -0.2]),
    "saturation censored": ([SAT, tk.Censoring(lower=LOWER)], [0.0, 0.4]),
}


def _oracle(name, y):
    channel = ONE_STEP[name][0]
    lower = LOWER if len(channel) > 1 else np.full(2, -np.inf)
    if name.startswith("saturation"):
        return _posterior(lambda x: _saturation_loglik(y, lower, SAT, x))
    if name == "fading uniform gains":
        gains = [_uniform_gain(0.5, 1.1), _uniform_gain(0.9, 1.3)]
    else:
        gains = [_gaussian_gain(0.9, 0.09), _gaussian_gain(1.2, 0.04)]
    return _posterior(lambda x: _fading_loglik(y, lower, gains, x))


@pytest.mark.parametrize("name", list(ONE_STEP))
def test_one_step_matches_the_exact_posterior_by_quadrature(name):
    # the particle mean's Monte Carlo error is about sd / sqrt(ESS); the evidence estimate (the weights' mean) has
    # a relative standard error sqrt((Np / ESS - 1) / Np); both within five standard errors
    channel, y = ONE_STEP[name]
    y = np.array(y)
    Np = 40000
    out = tk.ParticleFilter(_system(), channel, particles=Np, resample_threshold=0.0, seed=5).filter(y[None])
    mean, log_evidence = _oracle(name, y)
    ess = out.extras["ess"][0]
    assert ess > 0.1 * Np
    se = np.sqrt(out.cov[0, 0, 0] / ess)
    assert abs(out.mean[0, 0] - mean) < 5 * se, (out.mean[0, 0], mean, se)
    se_ll = np.sqrt((Np / ess - 1) / Np)
    assert abs(out.extras["log_likelihood"][0] - log_evidence) < 5 * se_ll, (out.extras["log_likelihood"], log_evidence)


# --------------------------------------------------------------------------- online use and refusals


@pytest.mark.parametrize("name", ["fading censored", "saturation censored"])
def test_steps_equal_filter(name):
    channel = PAIRS[name]
    lin, nl = _linear_pair()
    y = _readings(lin, channel)
    pf = tk.ParticleFilter(nl, channel, particles=100, seed=9)
    res = pf.filter(y)
    state = pf.init(batch_shape=(3,))
    for k in range(y.shape[1]):
        state = pf.step(state, y[:, k])
        np.testing.assert_allclose(state.x, res.mean[:, k], rtol=0, atol=1e-12)


def test_refusals_name_what_is_wrong():
    _, nl = _linear_pair()
    nl_u = tk.NonlinearSystem(lambda x, k: x @ A.T, lambda x, k, u: x @ C.T + u, Q=Q, R=R, x0=X0, P0=P0, inputs=2)
    with pytest.raises(tk.ValidationError, match="past inputs"):  # a delayed term would need h(x_(k-s), k-s, u_(k-s))
        tk.ParticleFilter(nl_u, tk.RiceFading.gaussian(1, [[0.9, 0.9], [0.5, 0.5]], 0.0))
    with pytest.raises(tk.ValidationError, match="'linearised' .* not for nonlinear saturation"):
        tk.ParticleFilter(nl, SATURATION, proposal="linearised")
    with pytest.raises(tk.ValidationError, match="'linearised' .* not for linear"):
        tk.ParticleFilter(_linear_pair()[0], CENS, proposal="linearised")
    with pytest.raises(tk.ValidationError, match="or 'linearised'"):
        tk.ParticleFilter(nl, CENS, proposal="optimal")
    with pytest.raises(tk.ValidationError, match="one channel piece"):
        tk.ParticleFilter(nl, [FADING, SATURATION])
    with pytest.raises(tk.ValidationError, match="one channel piece"):
        tk.ParticleFilter(nl, [SATURATION, CENS, tk.Censoring(upper=2.0)])
    with pytest.raises(tk.ValidationError, match="'optimal' has no closed form for nonlinear saturation"):
        tk.ParticleFilter(nl, SATURATION, proposal="optimal")
    with pytest.raises(tk.ShapeError):
        tk.ParticleFilter(nl, tk.RandomSaturation(mu=[0.3], nu=[0.8]))
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        tk.ParticleFilter(nl, [FADING, CENS], particles=10).filter(np.array([[0.0, 0.0]]))
