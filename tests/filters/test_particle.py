"""The particle filter (tobitkf.filters.particle): oracles, channels, online API, reproducibility, errors.

Monte Carlo tolerances. The particle mean of N_p particles estimates the posterior mean with a
variance kappa * V / N_p, V the posterior variance and kappa >= 1 the filter's asymptotic variance
factor (weights and resampling; it accumulates over steps when the state forgets slowly). The
tests bound the *average* of the squared standardized error z^2 = (m_pf - m)^2 / (V / N_p) over runs
and steps by KAPPA (measured 2-8 on these models) and check that it shrinks with N_p as 1/N_p.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk
from tobitkf.channels.laws import PMF, Uniform
from tobitkf.filters.particle import ParticleFilter, censored_log_likelihood, reweight, systematic_resample

KAPPA = 30.0


def oscillator(**kw):
    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    base = dict(A=A, C=[[1.0, 0.0]], Q=1e-2 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.5 * np.eye(2))
    base.update(kw)
    return tk.LinearSystem(**base)


def z2(mean, ref_mean, ref_var, Np):
    return (mean - ref_mean) ** 2 / (ref_var / Np)


def grid_filter(a, q, c, r, x0, p0, y, lower, upper, grid):
    """Exact (to the grid) Bayes filter of a scalar x_k = a x_{k-1} + w, y = clip(c x + v, lower, upper)."""
    dx = grid[1] - grid[0]
    K = np.exp(-0.5 * (grid[:, None] - a * grid[None, :]) ** 2 / q)  # p(x' | x), unnormalized in x'
    K /= K.sum(0, keepdims=True)
    post = np.exp(-0.5 * (grid - x0) ** 2 / p0)
    post /= post.sum()
    means, vars_ = [], []
    sd = np.sqrt(r)
    for yk in y:
        prior = K @ post
        if np.isnan(yk):
            ll = np.zeros_like(grid)
        elif yk <= lower:
            ll = log_ndtr((lower - c * grid) / sd)
        elif yk >= upper:
            ll = log_ndtr((c * grid - upper) / sd)
        else:
            ll = -0.5 * ((yk - c * grid) / sd) ** 2
        w = prior * np.exp(ll - ll.max())
        post = w / w.sum()
        m = post @ grid
        means.append(m)
        vars_.append(post @ (grid - m) ** 2)
    assert dx > 0
    return np.array(means), np.array(vars_)


# --------------------------------------------------------------------------- oracles


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_converges_to_the_kalman_filter_without_censoring(proposal):
    sys_ = oscillator(C=[[1.0, 0.0], [0.3, 1.0]], R=np.diag([0.1, 0.2]))
    d = tk.simulate(sys_, 25, 40, seed=1)
    y = d.y.copy()
    y[np.random.default_rng(0).random(y.shape) < 0.1] = np.nan  # missing readings too
    kf = tk.KalmanFilter(sys_).filter(y)
    var = np.diagonal(kf.cov, axis1=-2, axis2=-1)
    errs = {}
    for Np in (500, 2000):
        pf = ParticleFilter(sys_, particles=Np, proposal=proposal, seed=2).filter(y)
        errs[Np] = z2(pf.mean, kf.mean, var, Np).mean()
        assert errs[Np] < KAPPA
        np.testing.assert_allclose(pf.cov, kf.cov, rtol=0, atol=6 * np.sqrt(KAPPA / Np) * var.max())
        np.testing.assert_allclose(pf.pred_mean, kf.pred_mean, rtol=0, atol=6 * np.sqrt(KAPPA / Np * var.max()))
    # standardized by N_p, the error does not grow with N_p: it shrinks as 1/N_p (ratio ~1; 4x -> 4 if stuck)
    assert errs[2000] < 2.5 * errs[500]


def test_log_likelihood_estimate_matches_the_kalman_filter():
    sys_ = oscillator()
    d = tk.simulate(sys_, 30, 20, seed=3)
    kf = tk.KalmanFilter(sys_).filter(d.y)
    S = kf.pred_cov[..., 0, 0] + 0.1
    exact = (-0.5 * (d.y[..., 0] - kf.pred_mean[..., 0]) ** 2 / S - 0.5 * np.log(2 * np.pi * S)).sum(-1)
    ll = ParticleFilter(sys_, particles=4000, seed=4).log_likelihood(d.y)
    assert ll.shape == (20,)
    # log of an unbiased estimate: error of order sqrt(kappa T / N_p) per run (0.2 here), biased low by half
    # its variance; over 20 runs the mean error is within a few hundredths of zero
    assert np.abs(ll - exact).max() < 1.0 and abs((ll - exact).mean()) < 0.1


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_log_likelihood_is_shaped_as_the_kalman_filters_and_unbiased_in_the_likelihood(proposal):
    """Without censoring the exact value is the Kalman filter's. Shapes: (runs,), (runs, T) with
    ``per_step``, 0-d for one record, as KalmanFilter.log_likelihood. Accuracy, with tolerances from the
    particle count and the runs: the likelihood estimate is unbiased, so the ratio exp(ll - exact) has mean
    1, within 4 standard errors over R independent runs; the error's variance is O(T / N_p), so 4x the
    particles give about 1/4 of it (sampling spread of two variances over R = 200 runs: about 15 % each)."""
    sys_ = oscillator()
    R, T = 200, 20
    d = tk.simulate(sys_, T, R, seed=5)
    kf = tk.KalmanFilter(sys_)
    exact, exact_steps = kf.log_likelihood(d.y), kf.log_likelihood(d.y, per_step=True)
    var = {}
    for Np in (250, 1000):
        pf = ParticleFilter(sys_, particles=Np, proposal=proposal, seed=6)
        ll, steps = pf.log_likelihood(d.y), pf.log_likelihood(d.y, per_step=True)
        assert ll.shape == exact.shape == (R,) and steps.shape == exact_steps.shape == (R, T)
        np.testing.assert_allclose(steps.sum(-1), ll, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(steps, pf.filter(d.y).extras["log_likelihood"])
        ratio = np.exp(ll - exact)
        assert abs(ratio.mean() - 1.0) < 4 * ratio.std(ddof=1) / np.sqrt(R), (Np, ratio.mean())
        var[Np] = np.var(ll - exact, ddof=1)
    assert 2.0 < var[250] / var[1000] < 8.0, var
    one = pf.log_likelihood(d.y[0])
    assert np.ndim(one) == 0 and np.ndim(kf.log_likelihood(d.y[0])) == 0
    assert abs(float(one) - float(exact[0])) < 6 * np.sqrt(var[1000])


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_equals_a_grid_filter_on_a_censored_random_walk(proposal):
    a, q, r, T, runs = 0.98, 0.05, 0.02, 40, 12
    sys_ = tk.LinearSystem(A=[[a]], C=[[1.0]], Q=[[q]], R=[[r]], x0=[0.3], P0=[[0.5]])
    cens = tk.Censoring(lower=0.0, upper=1.2)
    d = tk.simulate(sys_, T, runs, censoring=cens, seed=5)
    assert 0.2 < float(((d.y <= 0) | (d.y >= 1.2)).mean()) < 0.9
    Np = 4000
    pf = ParticleFilter(sys_, cens, particles=Np, proposal=proposal, seed=6).filter(d.y)
    grid = np.linspace(-4, 4, 1201)
    z = []
    for i in range(runs):
        m, v = grid_filter(a, q, 1.0, r, 0.3, 0.5, d.y[i, :, 0], 0.0, 1.2, grid)
        z.append(z2(pf.mean[i, :, 0], m, v, Np))
        np.testing.assert_allclose(
            pf.var[i, :, 0] if pf.var is not None else pf.cov[i, :, 0, 0],
            v,
            rtol=6 * np.sqrt(2 * KAPPA / Np) + 0.02,
            atol=1e-4,
        )
    assert np.mean(z) < KAPPA


def test_deep_tail_reading_is_finite():
    """A reading at a limit 40 sigma from where the particles are: finite weights, estimate moves."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-4]], R=[[1e-2]], x0=[4.0], P0=[[1e-4]])
    for prop in ("optimal", "prior"):
        pf = ParticleFilter(sys_, tk.Censoring(lower=0.0), particles=500, proposal=prop, seed=0)
        out = pf.filter(np.array([[0.0]]))
        assert np.isfinite(out.mean).all() and np.isfinite(out.extras["log_likelihood"]).all()
        assert out.extras["log_likelihood"][0] < -700


# --------------------------------------------------------------------------- every channel


def test_two_sided_time_varying_multi_region_proposals_agree():
    sys_ = oscillator(C=[[1.0, 0.0], [0.5, 1.0]], R=np.diag([0.05, 0.1]))
    T = 20
    lower = np.stack([np.linspace(-0.4, 0.2, T), np.full(T, -np.inf)], axis=1)
    upper = np.stack([np.full(T, 0.8), np.linspace(0.3, 0.0, T)], axis=1)
    cens = tk.Censoring(lower=lower, upper=upper)
    d = tk.simulate(sys_, T, 30, censoring=cens, seed=7)
    Np = 3000
    a = ParticleFilter(sys_, cens, particles=Np, proposal="optimal", seed=8).filter(d.y)
    b = ParticleFilter(sys_, cens, particles=Np, proposal="prior", seed=9).filter(d.y)
    var = np.diagonal(a.cov, axis1=-2, axis2=-1)
    assert z2(a.mean, b.mean, var, Np / 2).mean() < KAPPA  # two independent estimates
    # several regions of one output as stacked sensors (Miller §6.6)
    stacked, mr = tk.multi_region(oscillator(), [[(-np.inf, 0.0), (0.0, np.inf)]])
    d2 = tk.simulate(stacked, T, 20, censoring=mr, seed=10)
    c = ParticleFilter(stacked, mr, particles=Np, seed=11).filter(d2.y)
    e = ParticleFilter(stacked, mr, particles=Np, proposal="prior", seed=12).filter(d2.y)
    assert z2(c.mean, e.mean, np.diagonal(c.cov, axis1=-2, axis2=-1), Np / 2).mean() < KAPPA


def test_fading_with_deterministic_gains_is_the_augmented_kalman_filter():
    sys_ = oscillator()
    fad = tk.RiceFading(1, [0.9, 0.6])  # no variance: linear in (x_k, x_{k-1})
    d = tk.simulate(sys_, 25, 30, measurement=fad, seed=13)
    exact = tk.FadingAssumedDensityFilter(sys_, fad).filter(d.y)  # = the KF of the augmented model
    Np = 2000
    pf = ParticleFilter(sys_, fad, particles=Np, seed=14).filter(d.y)
    assert pf.mean.shape == (30, 25, 2)
    assert z2(pf.mean, exact.mean, np.diagonal(exact.cov, axis1=-2, axis2=-1), Np).mean() < KAPPA


def test_fading_gaussian_coefficients_marginalized_or_drawn_agree():
    """The Gaussian coefficients marginalized exactly (the default) vs drawn per particle (the path of the
    other laws): two estimates of the same posterior."""
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    gauss = tk.RiceFading.gaussian(1, [0.9, 0.6], [0.02, 0.02])
    d = tk.simulate(sys_, 20, 20, censoring=cens, measurement=gauss, seed=15)
    Np = 3000
    a = ParticleFilter(sys_, [gauss, cens], particles=Np, seed=16).filter(d.y)
    drawn = ParticleFilter(sys_, [gauss, cens], particles=Np, seed=17)
    drawn.model.gaussian = False
    b = drawn.filter(d.y)
    assert z2(a.mean, b.mean, np.diagonal(a.cov, axis1=-2, axis2=-1), Np / 2).mean() < KAPPA
    unif = tk.RiceFading(1, Uniform([0.7, 0.4], [1.1, 0.8]))
    c = ParticleFilter(sys_, [unif, cens], particles=200, seed=18).filter(d.y)
    assert np.isfinite(c.mean).all()


def test_protocol_without_failures_or_censoring_is_the_augmented_kalman_filter():
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
    ch = tk.ProtocolChannel(2, window=1)
    d = tk.simulate(sys_, 20, 30, channel=ch, seed=18)
    exact = tk.ProtocolAssumedDensityFilter(sys_, ch).filter(d.y)
    Np = 2000
    for prop in ("optimal", "prior"):
        pf = ParticleFilter(sys_, ch, particles=Np, proposal=prop, seed=19).filter(d.y)
        assert z2(pf.mean, exact.mean, np.diagonal(exact.cov, axis1=-2, axis2=-1), Np).mean() < KAPPA


@pytest.mark.parametrize("law", [PMF([0.0, 0.5, 1.0], [0.05, 0.10, 0.85]), Uniform(0.3, 1.0)], ids=["pmf", "uniform"])
def test_protocol_with_failures_and_censoring_proposals_agree(law):
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]), x0=[1.0, 0.0])
    ch = tk.ProtocolChannel(2, window=2, failures=law, threshold=0.0)
    d = tk.simulate(sys_, 20, 30, channel=ch, seed=20)
    Np = 3000
    ref = tk.ProtocolAssumedDensityFilter(sys_, ch).filter(d.y)
    b = ParticleFilter(sys_, ch, particles=Np, proposal="prior", seed=22).filter(d.y)
    if isinstance(law, PMF):
        a = ParticleFilter(sys_, ch, particles=Np, proposal="optimal", seed=21).filter(d.y)
        # kappa is larger here (about 25 for either proposal, measured against 10^5 particles): the
        # pre-history blocks of the window are static and never rejuvenated
        assert z2(a.mean, b.mean, np.diagonal(a.cov, axis1=-2, axis2=-1), Np / 2).mean() < 4 * KAPPA
    else:
        with pytest.raises(tk.ValidationError, match="proposal: 'optimal' has no closed form"):
            ParticleFilter(sys_, ch, proposal="optimal")
    # the conditioning filter is close to the optimum: much closer than the source's PBTKF
    pb = tk.ProtocolTobitKalmanFilter(sys_, ch).filter(d.y)
    assert np.abs(ref.mean - b.mean).mean() < 0.5 * np.abs(pb.mean - b.mean).mean()


def test_random_saturation_reduces_to_the_kalman_filter_and_weights_the_modes():
    sys_ = oscillator(C=[[1.0, 0.0], [0.0, 1.0]], R=np.diag([0.05, 0.05]))
    lin = tk.RandomSaturation(mu=[0.0, 0.0], nu=[1.0, 1.0])  # never saturated, never missing
    d = tk.simulate(sys_, 20, 30, channel=lin, seed=23)
    kf = tk.KalmanFilter(sys_).filter(d.y)
    Np = 2000
    pf = ParticleFilter(sys_, lin, particles=Np, seed=24).filter(d.y)
    assert z2(pf.mean, kf.mean, np.diagonal(kf.cov, axis1=-2, axis2=-1), Np).mean() < KAPPA
    # the likelihood of one reading is the three-mode mixture of (2)
    ros = tk.RandomSaturation(mu=[0.3, 0.3], nu=[0.8, 0.8], level=0.5)
    model = ParticleFilter(sys_, ros, particles=4).model
    X = np.array([[[0.2, -0.9], [1.5, 0.1], [-0.7, 0.4], [0.0, 2.0]]])
    y = np.array([[0.45, -0.3]])
    got = model.log_likelihood(None, 1, X, y, 0.0)

    def npdf(v, m):
        return np.exp(-0.5 * (v - m) ** 2 / 0.05) / np.sqrt(2 * np.pi * 0.05)

    want = np.zeros(4)
    for i, j in np.ndindex(4, 2):
        c = X[0, i, j]
        want[i] += np.log(
            0.3 * npdf(y[0, j], np.clip(c, -0.5, 0.5)) + 0.7 * 0.8 * npdf(y[0, j], c) + 0.7 * 0.2 * npdf(y[0, j], 0.0)
        )
    np.testing.assert_allclose(got[0], want, rtol=1e-12)


# --------------------------------------------------------------------------- pure pieces


def _log_tail(x):
    """log Phi(-x) for large x by the asymptotic series (error below 1e-14 relative for x >= 40)."""
    s = 1 - 1 / x**2 + 3 / x**4 - 15 / x**6 + 105 / x**8 - 945 / x**10
    return -0.5 * x * x - np.log(x) - 0.5 * np.log(2 * np.pi) + np.log(s)


def test_censored_log_likelihood_cases_and_tails():
    got = censored_log_likelihood(
        [0.0, 0.5, 1.0, np.nan, 0.0], [40.0, 0.0, -40.0, 0.0, -40.0], 1.0, lower=0.0, upper=1.0
    )
    np.testing.assert_allclose(
        got[:4], [_log_tail(40.0), -0.5 * 0.25 - 0.5 * np.log(2 * np.pi), _log_tail(41.0), 0.0], rtol=1e-12
    )
    assert got[4] == pytest.approx(0.0, abs=1e-300)


def test_systematic_resampling_copies_floor_or_ceil_times():
    rng = np.random.default_rng(0)
    W = rng.random((50, 40)) ** 4
    W /= W.sum(1, keepdims=True)
    idx = systematic_resample(W, rng.random(50))
    counts = np.stack([np.bincount(r, minlength=40) for r in idx])
    assert (counts >= np.floor(40 * W) - 1e-9).all() and (counts <= np.ceil(40 * W) + 1e-9).all()
    assert (np.diff(idx, axis=1) >= 0).all()


# --------------------------------------------------------------------------- online API


def _run_steps(est, y, batch, start=None):
    state = est.init(batch) if start is None else start
    means = []
    for k in range(y.shape[-2]):
        state = est.step(state, y[..., k, :])
        means.append(state.mean)
    return state, np.stack(means, axis=-2)


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)], ids=str)
@pytest.mark.parametrize("channel", ["censoring", "protocol", "protocol-rb"])
def test_step_loop_equals_filter_and_pickled_state_resumes(channel, batch):
    rng = np.random.default_rng(1)
    N = int(np.prod(batch)) if batch else 1
    if channel == "censoring":
        sys_, ch = oscillator(), tk.Censoring(lower=0.0, upper=1.0)
        d = tk.simulate(sys_, 12, N, censoring=ch, seed=2)
    else:
        sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
        ch = tk.ProtocolChannel(2, window=1, failures=PMF([0.0, 1.0], [0.2, 0.8]), threshold=0.0)
        d = tk.simulate(sys_, 12, N, channel=ch, seed=2)
    y = d.y.copy()
    y[rng.random(y.shape) < 0.1] = np.nan
    y = y.reshape(batch + y.shape[1:])
    prop = "rao_blackwellised" if channel == "protocol-rb" else "auto"
    # step is the numpy path: bit-equal to the numpy loop (the compiled loop draws its numbers in its own
    # order: equal to the numpy path for the same numbers, tests/filters/test_compiled_particle.py)
    pf = ParticleFilter(sys_, ch, particles=200, proposal=prop, seed=3, backend="numpy")
    res = pf.filter(y)
    assert res.mean.shape == batch + (12, 2) and res.times.tolist() == list(range(1, 13))
    assert res.extras["ess"].shape == batch + (12,)
    state, means = _run_steps(pf, y, batch)
    np.testing.assert_array_equal(means, res.mean)
    np.testing.assert_array_equal(state.carry["particles"], res.final.carry["particles"])
    # pickle half-way and resume: the generator state travels in the FilterState
    half, _ = _run_steps(pf, y[..., :6, :], batch)
    revived = pickle.loads(pickle.dumps(half))
    _, a = _run_steps(pf, y[..., 6:, :], batch, start=half)
    _, b = _run_steps(pf, y[..., 6:, :], batch, start=revived)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(b, res.mean[..., 6:, :])
    cont = pf.filter(y[..., 6:, :], state=revived)
    np.testing.assert_array_equal(cont.mean, res.mean[..., 6:, :])
    assert cont.times.tolist() == list(range(7, 13))


def test_reproducible_from_a_seed():
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 10, 5, censoring=cens, seed=4)
    a = ParticleFilter(sys_, cens, particles=100, seed=5).filter(d.y).mean
    b = ParticleFilter(sys_, cens, particles=100, seed=5).filter(d.y).mean
    c = ParticleFilter(sys_, cens, particles=100, seed=6).filter(d.y).mean
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    pf = ParticleFilter(sys_, cens, particles=100)  # fresh entropy once: filter() repeats
    np.testing.assert_array_equal(pf.filter(d.y).mean, pf.filter(d.y).mean)
    g = ParticleFilter(sys_, cens, particles=100, seed=np.random.default_rng(7)).filter(d.y).mean
    np.testing.assert_array_equal(
        g, ParticleFilter(sys_, cens, particles=100, seed=np.random.default_rng(7)).filter(d.y).mean
    )


def test_outputs_on_request_and_resampling_extras():
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 15, 6, censoring=cens, seed=8)
    pf = ParticleFilter(sys_, cens, particles=300, resample_threshold=1.0, seed=9)
    full = pf.filter(d.y)
    assert full.extras["resampled"].all()  # threshold 1: every step
    last = pf.filter(d.y, outputs="last")
    assert last.mean is None
    np.testing.assert_array_equal(last.final.mean, full.mean[:, -1])
    never = ParticleFilter(sys_, cens, particles=300, resample_threshold=0.0, seed=9).filter(d.y)
    assert not never.extras["resampled"].any()
    assert (never.extras["ess"] <= 300 + 1e-9).all() and (never.extras["ess"] >= 1 - 1e-9).all()


# --------------------------------------------------------------------------- errors


def test_bad_arguments_are_refused():
    sys_ = oscillator()
    with pytest.raises(tk.ValidationError, match="particles: expected a positive integer"):
        ParticleFilter(sys_, particles=0)
    with pytest.raises(tk.ValidationError, match="resample_threshold: expected a fraction"):
        ParticleFilter(sys_, resample_threshold=1.5)
    with pytest.raises(tk.ValidationError, match="proposal: expected one of"):
        ParticleFilter(sys_, proposal="best")
    with pytest.raises(tk.ValidationError, match="channel: expected Censoring, RiceFading"):
        ParticleFilter(sys_, "censoring")
    with pytest.raises(tk.ValidationError, match="at most one reading model"):
        ParticleFilter(sys_, [tk.RiceFading(0, [1.0]), tk.RandomSaturation([0.1], [0.9])])
    with pytest.raises(tk.ValidationError, match="at most one Censoring"):
        ParticleFilter(sys_, tk.Censoring(lower=0.0), censoring=tk.Censoring(upper=1.0))
    with pytest.raises(tk.ValidationError, match="R: the particle filter needs a diagonal R"):
        ParticleFilter(oscillator(C=np.eye(2), R=[[1.0, 0.5], [0.5, 1.0]]))
    with pytest.raises(tk.ValidationError, match="R: the particle filter needs positive"):
        ParticleFilter(oscillator(R=[[0.0]]))
    with pytest.raises(tk.ValidationError, match="proposal: 'optimal' has no closed form for fading"):
        ParticleFilter(sys_, tk.RiceFading(0, [1.0]), proposal="optimal")
    with pytest.raises(tk.ValidationError, match="seed: expected"):
        ParticleFilter(sys_, seed="zero")
    with pytest.raises(tk.ValidationError, match="the protocol channel carries its own threshold"):
        ParticleFilter(oscillator(C=np.eye(2), R=np.eye(2)), [tk.ProtocolChannel(2), tk.Censoring(lower=0.0)])
    pf = ParticleFilter(sys_, tk.Censoring(lower=0.0), particles=10, seed=0)
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        pf.filter(np.array([[-1.0]]))
    with pytest.raises(tk.ShapeError, match="y: expected last axis of length m=1"):
        pf.filter(np.zeros((3, 2)))
    with pytest.raises(tk.ValidationError, match="state: expected a FilterState"):
        pf.step("prior", [0.0])


# --------------------------------------------------------------------------- saturation: the optimal proposal

SAT = dict(mu=0.3, nu=0.8, level=0.5, r=0.05)


def _sat_lik(x, y, lo, hi):
    """p(y | x) of one saturated sensor (state x, the three modes of (2)), on a grid; written from the model."""
    mu, nu, u, r = SAT["mu"], SAT["nu"], SAT["level"], SAT["r"]
    means = [np.clip(x, -u, u), x, 0.0 * x]
    pis = [mu, (1 - mu) * nu, (1 - mu) * (1 - nu)]
    sr = np.sqrt(r)
    if y <= lo:
        parts = [np.exp(log_ndtr((lo - mm) / sr)) for mm in means]
    elif y >= hi:
        parts = [np.exp(log_ndtr((mm - hi) / sr)) for mm in means]
    else:
        parts = [np.exp(-0.5 * (y - mm) ** 2 / r) / np.sqrt(2 * np.pi * r) for mm in means]
    return sum(p * q for p, q in zip(pis, parts, strict=True))


@pytest.mark.parametrize(
    "prev, y",
    [(0.2, 0.45), (1.5, 0.48), (-0.9, -0.1), (0.6, 1.3), (0.0, 0.02), (0.7, -0.6), (-0.4, 0.7)],
)
def test_saturation_optimal_proposal_is_the_one_step_posterior(prev, y):
    """(a) One step, scalar state: x_k ~ N(a x_{k-1}, q), one saturated sensor, censored at [-0.6, 0.7].
    The weight must be p(y | x_{k-1}) and the draws' (weighted) law p(x_k | x_{k-1}, y), both by quadrature.
    Uncensored readings: the weight is exact (to quadrature tolerance, every particle); censored ones carry
    a random weight (the middle saturated piece) whose mean is the likelihood (Monte Carlo tolerance)."""
    a, q, lo, hi = 0.9, 0.3, -0.6, 0.7
    sys_ = tk.LinearSystem(A=[[a]], C=[[1.0]], Q=[[q]], R=[[SAT["r"]]], x0=[0.0], P0=[[1.0]])
    ch = tk.RandomSaturation(mu=[SAT["mu"]], nu=[SAT["nu"]], level=SAT["level"])
    pf = ParticleFilter(sys_, ch, censoring=tk.Censoring(lower=lo, upper=hi), particles=4, seed=0)
    assert pf.proposal == "optimal"
    Np = 200_000
    X = np.full((1, Np, 1), prev)
    Xn, logw = pf.model.propose(np.random.default_rng(7), 1, X, np.array([[y]]), 0.0, 0.0)
    grid = np.linspace(a * prev - 14 * np.sqrt(q), a * prev + 14 * np.sqrt(q), 400_001)
    joint = np.exp(-0.5 * (grid - a * prev) ** 2 / q) / np.sqrt(2 * np.pi * q) * _sat_lik(grid, y, lo, hi)
    lik = np.trapezoid(joint, grid)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (joint[1:] + joint[:-1]) * np.diff(grid))]) / lik
    w = np.exp(logw[0])
    censored = y <= lo or y >= hi
    if censored:
        se = w.std() / np.sqrt(Np)
        assert abs(w.mean() - lik) < 4.5 * se + 1e-12
    else:
        np.testing.assert_allclose(w, lik, rtol=1e-7)
    # the weighted empirical CDF against the quadrature CDF (Kolmogorov distance, ~ 1/sqrt(ESS))
    order = np.argsort(Xn[0, :, 0])
    xs, ws = Xn[0, order, 0], w[order] / w.sum()
    ess = 1.0 / np.sum(ws * ws)
    emp = np.cumsum(ws)
    dist = np.abs(emp - np.interp(xs, grid, cdf)).max()
    assert dist < 1.95 / np.sqrt(ess)  # the Kolmogorov 0.1 % point is 1.95 / sqrt(n)
    if not censored:
        assert ess > 0.999 * Np  # every particle has the same weight: the draws are the posterior itself


@pytest.mark.parametrize("censored", [False, True])
def test_saturation_optimal_proposal_agrees_with_a_long_bootstrap_run(censored):
    """(b) Posterior means with 1000 particles (optimal proposal) against the bootstrap filter with 100k,
    on the same readings: the averaged standardized squared error is O(1) (KAPPA, module docstring);
    (c) the optimal proposal's effective sample size is over twice the bootstrap filter's."""
    sys_ = oscillator(C=np.eye(2), Q=0.1 * np.eye(2), R=0.01 * np.eye(2), P0=np.eye(2))
    ch = tk.RandomSaturation(mu=[0.7, 0.6], nu=[0.7, 0.75])
    cens = tk.Censoring(lower=-0.8, upper=0.9) if censored else None
    d = tk.simulate(sys_, 12, 8, channel=[ch] + ([cens] if cens else []), seed=31)
    ref = ParticleFilter(sys_, ch, censoring=cens, particles=100_000, proposal="prior", seed=32).filter(d.y)
    Np = 1000
    opt = ParticleFilter(sys_, ch, censoring=cens, particles=Np, seed=33).filter(d.y)
    assert opt.extras["ess"].shape == (8, 12)
    V = np.diagonal(ref.cov, axis1=-2, axis2=-1)
    err = z2(opt.mean, ref.mean, V, Np).mean()
    assert 0.05 < err < KAPPA / 3  # measured 3.5 and 3.9; the bootstrap filter with Np particles: 23 and 18
    # (c) the effective sample size on the same readings: measured 618 vs 212 (2.9x) uncensored, 582 vs
    # 247 (2.4x) censored, mean over runs and steps
    boot = ParticleFilter(sys_, ch, censoring=cens, particles=Np, proposal="prior", seed=33).filter(d.y)
    assert opt.extras["ess"].mean() > 2.0 * boot.extras["ess"].mean()


# --------------------------------------------------------------------------- protocol: Rao-Blackwellised


def test_rao_blackwellised_protocol_without_failures_or_censoring_is_the_augmented_kalman_filter():
    """No failures, no censoring: every particle is the augmented Kalman filter itself (nothing is sampled),
    so the RB filter equals the exact filter to rounding, with any particle count (missing readings too)."""
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
    for prehistory in ("prior", "hold", "zero"):
        ch = tk.ProtocolChannel(2, window=2, prehistory=prehistory)
        d = tk.simulate(sys_, 15, 4, channel=ch, seed=30)
        y = d.y.copy()
        y[:, 3] = np.nan
        exact = tk.ProtocolAssumedDensityFilter(sys_, ch).filter(y)
        rb = ParticleFilter(sys_, ch, particles=7, proposal="rao_blackwellised", seed=31).filter(y)
        np.testing.assert_allclose(rb.mean, exact.mean, rtol=0, atol=1e-10)
        np.testing.assert_allclose(rb.cov, exact.cov, rtol=0, atol=1e-10)
        assert (rb.extras["ess"] > 7 - 1e-9).all()


def _enumerated_mixture_kalman(sys_, ch, y):
    """Exact posterior means of x_k for the protocol channel without censoring (tau = -inf), by enumerating
    every sequence of failure outcomes (J^T Kalman filters on the window (x_k, .., x_{k-ell}), each weighted
    by pi(sequence) p(y_{1:k} | sequence)); written from the model, prehistory iid from the prior."""
    import itertools

    n, ell = sys_.n, ch.window
    nx = n * (ell + 1)
    A, Q = np.asarray(sys_.A.at(0)), np.asarray(sys_.Q.at(0))
    F = np.zeros((nx, nx))
    F[:n, :n] = A
    F[n:, :-n] = np.eye(nx - n)
    G = np.zeros((nx, nx))
    G[:n, :n] = Q
    vals, probs = np.asarray(ch.laws[0].values), np.asarray(ch.laws[0].probs)
    C, R = np.asarray(sys_.C.at(0)), np.diagonal(np.asarray(sys_.R.at(0)))
    T = y.shape[0]
    logw_all, means_all = [], []
    for seq in itertools.product(range(vals.size), repeat=T):
        m = np.tile(np.asarray(sys_.x0, float), ell + 1)
        P = np.kron(np.eye(ell + 1), np.asarray(sys_.P0, float))
        lw, means = np.zeros(T), np.zeros((T, n))
        acc = 0.0
        for k in range(T):
            m, P = F @ m, F @ P @ F.T + G
            h = k % ch.sensors
            if not np.isnan(y[k, 0]):
                H = vals[seq[k]] * np.tile(C[h], ell + 1)
                S = H @ P @ H + R[h]
                K = P @ H / S
                e = y[k, 0] - H @ m
                acc += np.log(probs[seq[k]]) - 0.5 * e * e / S - 0.5 * np.log(2 * np.pi * S)
                m, P = m + K * e, P - np.outer(K, K) * S
            else:
                acc += np.log(probs[seq[k]])
            lw[k], means[k] = acc, m[:n]
        logw_all.append(lw)
        means_all.append(means)
    lw = np.array(logw_all)  # (J^T, T): the weight of each sequence's first k outcomes given y_{1:k}
    W = np.exp(lw - lw.max(0))
    W /= W.sum(0)
    M = np.array(means_all)  # (J^T, T, n)
    mean = np.einsum("st,stn->tn", W, M)
    var = np.einsum("st,stn->tn", W, (M - mean) ** 2)  # the spread over sequences (a lower bound of Var)
    top = lw[:, -1].max()
    return mean, var, top + np.log(np.exp(lw[:, -1] - top).sum())  # and log p(y_{1:T})


def test_rao_blackwellised_protocol_with_failures_equals_the_enumerated_mixture_of_kalman_filters():
    """Failures {0, 0.5, 1}, ell = 1, no censoring, T = 6: the exact posterior mean is a mixture of 3^6 Kalman
    filters (enumerated); the RB particle mean must match it within its Monte Carlo error (kappa measured
    about 1 here), and a wrong weight (e.g. dropping the outcome posterior) would be off by far more."""
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]), x0=[1.0, 0.0])
    ch = tk.ProtocolChannel(2, window=1, failures=PMF([0.0, 0.5, 1.0], [0.2, 0.3, 0.5]))
    d = tk.simulate(sys_, 6, 3, channel=ch, seed=32)
    y = d.y.copy()
    y[1, 2] = np.nan
    Np = 2000
    pf = ParticleFilter(sys_, ch, particles=Np, proposal="rao_blackwellised", seed=33)
    rb = pf.filter(y)
    ll = pf.log_likelihood(y)
    for r in range(y.shape[0]):
        mean, spread, exact_ll = _enumerated_mixture_kalman(sys_, ch, y[r])
        # the likelihood estimate: log-scale error of order sqrt(kappa T / N_p), kappa about 1 here
        assert abs(ll[r] - exact_ll) < 4 * np.sqrt(y.shape[1] / Np)
        # standardize by the posterior variance (within + between; the RB filter's own estimate of it)
        var = np.diagonal(rb.cov[r], axis1=-2, axis2=-1)
        assert z2(rb.mean[r], mean, var, Np).mean() < KAPPA / 3
        assert (var >= spread - 1e-9).all()


def _window_grid_filter(a, q, r, x0, p0, vals, probs, tau, y, grid):
    """Exact (to the grid) filter of a scalar x_k = a x_{k-1} + w, ell = 1, one sensor:
    y = max(lambda (x_k + x_{k-1}) + v, tau), lambda ~ PMF(vals, probs), x_{-1} iid N(x0, p0). The joint of
    the window (x_k, x_{k-1}) lives on grid x grid; written from the model."""
    g = grid
    K = np.exp(-0.5 * (g[:, None] - a * g[None, :]) ** 2 / q)  # p(x_k = g_i | x_{k-1} = g_j), unnormalized
    K /= K.sum(0, keepdims=True)
    prior1 = np.exp(-0.5 * (g - x0) ** 2 / p0)
    joint = np.outer(prior1, prior1)  # (x_0, x_{-1})
    joint /= joint.sum()
    s = g[:, None] + g[None, :]
    sr = np.sqrt(r)
    means, vars_ = [], []
    for yk in y:
        marg = joint.sum(1)  # p(x_{k-1} | y_{1:k-1})
        joint = K * marg[None, :]  # (x_k, x_{k-1})
        if not np.isnan(yk):
            if yk <= tau:
                lik = sum(p * np.exp(log_ndtr((tau - v * s) / sr)) for v, p in zip(vals, probs, strict=True))
            else:
                lik = sum(p * np.exp(-0.5 * (yk - v * s) ** 2 / r) for v, p in zip(vals, probs, strict=True))
            joint = joint * lik
        joint /= joint.sum()
        px = joint.sum(1)
        m = px @ g
        means.append(m)
        vars_.append(px @ (g - m) ** 2)
    return np.array(means), np.array(vars_)


def test_rao_blackwellised_protocol_with_censoring_equals_a_grid_filter():
    """Scalar state, ell = 1, failures {0, 0.5, 1}, censored at tau = 0 (about half the readings): the RB
    mean matches a grid filter of the window's joint within the Monte Carlo error; so does the locally optimal
    proposal (with its larger kappa). Same seed, same numbers."""
    a, q, r, x0, p0 = 0.95, 0.05, 0.1, 0.3, 0.5
    sys_ = tk.LinearSystem(A=[[a]], C=[[1.0]], Q=[[q]], R=[[r]], x0=[x0], P0=[[p0]])
    law = PMF([0.0, 0.5, 1.0], [0.1, 0.2, 0.7])
    ch = tk.ProtocolChannel(1, window=1, failures=law, threshold=0.0)
    d = tk.simulate(sys_, 15, 4, channel=ch, seed=34)
    assert 0.2 < (d.y <= 0.0).mean() < 0.8
    grid = np.linspace(-4.0, 4.5, 700)
    Np = 2000
    rb_pf = ParticleFilter(sys_, ch, particles=Np, proposal="rao_blackwellised", seed=35)
    rb = rb_pf.filter(d.y)
    np.testing.assert_array_equal(rb.mean, rb_pf.filter(d.y).mean)
    opt = ParticleFilter(sys_, ch, particles=Np, proposal="optimal", seed=36).filter(d.y)
    for run in range(d.y.shape[0]):
        mean, var = _window_grid_filter(a, q, r, x0, p0, law.values, law.probs, 0.0, d.y[run, :, 0], grid)
        assert z2(rb.mean[run, :, 0], mean, var, Np).mean() < KAPPA / 3
        assert z2(opt.mean[run, :, 0], mean, var, Np).mean() < 4 * KAPPA
        assert np.abs(rb.cov[run, :, 0, 0] / var - 1).mean() < 0.1  # the mixture's variance too, on average


def test_rao_blackwellised_is_refused_where_it_is_not_implemented():
    sys_ = oscillator(C=np.eye(2), R=np.diag([0.1, 0.2]))
    with pytest.raises(tk.ValidationError, match="'rao_blackwellised' is implemented for the protocol channel"):
        ParticleFilter(oscillator(), tk.Censoring(lower=0.0), proposal="rao_blackwellised")
    with pytest.raises(tk.ValidationError, match="'rao_blackwellised' is implemented for the protocol channel"):
        ParticleFilter(sys_, tk.ProtocolChannel(2, failures=Uniform(0.3, 1.0)), proposal="rao_blackwellised")


def test_reweight_is_the_bayes_step_and_keeps_the_weights_of_a_run_no_member_explains():
    """Run 0: weights (1/2, 1/2), likelihoods (1, 3): the step's likelihood 2 and the weights (1/4, 3/4).
    Run 1: no member explains the reading (all -inf): its weights stay, its log-likelihood is -inf."""
    lw = np.log(np.array([[0.5, 0.5], [0.2, 0.8]]))
    inc = np.array([[0.0, np.log(3.0)], [-np.inf, -np.inf]])
    E, tot, new, ll = reweight(lw, inc)
    np.testing.assert_allclose(ll[0], np.log(2.0), rtol=1e-14)
    np.testing.assert_allclose(np.exp(new[0]), [0.25, 0.75], rtol=1e-14)
    np.testing.assert_allclose(E[0] / tot[0], [0.25, 0.75], rtol=1e-14)
    assert ll[1] == -np.inf
    np.testing.assert_allclose(np.exp(new[1]), [0.2, 0.8], rtol=1e-14)
