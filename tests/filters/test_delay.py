"""Tests of the delay-fading estimators (spec 002 §5): exact equivalences, reductions,
Monte Carlo consistency, orderings, reference values and input checks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tobitkf._validation import ValidationError
from tobitkf.filters.delay import second_moments
from tobitkf.filters.delay_augmented import AugmentedLMMSE, augmented_lmmse
from tobitkf.filters.delay_chain import ChainLMMSE, chain_lmmse, smooth_interval, smooth_point
from tobitkf.filters.delay_reorganized import ReorganizedInnovationLMMSE, reorganized_lmmse
from tobitkf.models.delay import DelayFadingSystem, FadingMoments, FadingPMF, HistoryPrior, paper_example, paper_prior
from tobitkf.simulate.delay import full_states, simulate_delay

TOL = 1e-10


def random_system(rng, n, m, d, *, S_scale=0.5, fading=None, h=1):
    """A random mean-square-stable delay system with correlated noises."""
    A = rng.standard_normal((n, n))
    A *= 0.7 / max(abs(np.linalg.eigvals(A)))
    H = rng.standard_normal((m, n))
    p = n
    Gamma = rng.standard_normal((n, p)) * 0.5
    Mv = rng.standard_normal((m, m))
    Qv = Mv @ Mv.T + 0.3 * np.eye(m)
    Mw = rng.standard_normal((p, p))
    Qw = Mw @ Mw.T + 0.2 * np.eye(p)
    # S = Qw^{1/2} C Qv^{1/2} with ||C|| < 1 keeps the joint covariance PSD
    C = rng.standard_normal((p, m))
    C *= S_scale / max(np.linalg.norm(C, 2), 1e-12)
    S = np.linalg.cholesky(Qw) @ C @ np.linalg.cholesky(Qv).T
    A_mult = 0.2 * rng.standard_normal((h, n, n))
    fading = fading if fading is not None else FadingPMF([0.3, 0.8, 1.0], [0.2, 0.3, 0.5])
    return DelayFadingSystem(A, H, Gamma, Qw, Qv, S, d, A_mult=A_mult, q_mult=[0.3] * h, fading=fading)


def random_prior(rng, n, d, *, correlated=False):
    means = rng.standard_normal((d + 1, n)) * 0.5
    if correlated:
        M = rng.standard_normal((n * (d + 1), n * (d + 1)))
        return HistoryPrior.joint(means, 0.3 * M @ M.T / (n * (d + 1)) + 0.05 * np.eye(n * (d + 1)))
    covs = []
    for _ in range(d + 1):
        M = rng.standard_normal((n, n))
        covs.append(M @ M.T / n + 0.1 * np.eye(n))
    return HistoryPrior.uncorrelated(means, covs)


def field(r, f):
    """A result's field or extra (the delay family's x̂(t+1|t) is ``extras["next_mean"]``)."""
    return getattr(r, f) if f in ("mean", "cov", "pred_mean", "pred_cov") else r.extras[f]


def assert_same(
    r1,
    r2,
    fields=(
        "mean",
        "cov",
        "pred_mean",
        "pred_cov",
        "next_mean",
        "next_cov",
        "measured_mean",
        "measured_cov",
        "innovation",
        "innovation_cov",
    ),
    tol=TOL,
):
    for f in fields:
        np.testing.assert_allclose(field(r1, f), field(r2, f), atol=tol, rtol=0, err_msg=f)


def correlated_kf(A, H, GQG, GS, Qv, x0, P0, ys):
    """Textbook one-step predictor with same-time correlated noises (Anderson & Moore), one run.

    x(t+1) = A x(t) + u, y(t) = H x(t) + v, E[u v^T] = GS. Returns filtered and predicted means/covs.
    """
    x, P = np.array(x0, float), np.array(P0, float)
    out = []
    for y in ys:
        Qe = H @ P @ H.T + Qv
        e = y - H @ x
        xf = x + P @ H.T @ np.linalg.solve(Qe, e)
        Pf = P - P @ H.T @ np.linalg.solve(Qe, H @ P)
        L = A @ P @ H.T + GS
        xn = A @ x + L @ np.linalg.solve(Qe, e)
        Pn = A @ P @ A.T + GQG - L @ np.linalg.solve(Qe, L.T)
        out.append((xf, Pf, xn, Pn))
        x, P = xn, Pn
    return out


# ----------------------------------------------------------------------------- §5 item 1: C ≡ A


@pytest.mark.parametrize("d,n,m", [(0, 1, 1), (1, 2, 1), (2, 2, 2), (3, 4, 1), (7, 2, 2), (3, 1, 2)])
def test_chain_equals_augmented(d, n, m):
    rng = np.random.default_rng(100 + 7 * d + n + m)
    sys = random_system(rng, n, m, d)
    prior = random_prior(rng, n, d)
    data = simulate_delay(sys, prior, 40, 3, seed=rng)
    lags = tuple(sorted({0, d, max(d - 1, 0), 2 * d + 1, 3 * d + 2}))
    c = chain_lmmse(sys, prior, data.y, lags=lags)
    a = augmented_lmmse(sys, prior, data.y, window=max(lags), lags=lags)
    assert_same(c, a)
    for L in lags:
        np.testing.assert_allclose(c.extras["lagged"][L][0], a.extras["lagged"][L][0], atol=TOL, rtol=0)
        np.testing.assert_allclose(c.extras["lagged"][L][1], a.extras["lagged"][L][1], atol=TOL, rtol=0)
    np.testing.assert_allclose(c.extras["second_moment"], a.extras["second_moment"], atol=TOL, rtol=0)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    d=st.integers(0, 4),
    n=st.integers(1, 3),
    m=st.integers(1, 2),
    s_scale=st.sampled_from([0.0, 0.5, 0.999]),
)
def test_chain_equals_augmented_property(seed, d, n, m, s_scale):
    rng = np.random.default_rng(seed)
    sys = random_system(rng, n, m, d, S_scale=s_scale)
    prior = random_prior(rng, n, d)
    data = simulate_delay(sys, prior, 15, 2, seed=rng)
    assert_same(chain_lmmse(sys, prior, data.y), augmented_lmmse(sys, prior, data.y), tol=1e-9)


# ----------------------------------------------------------------------------- §5 item 2: D ≡ A, errata guards


@pytest.mark.parametrize("d", [1, 2, 3, 5])
def test_reorganized_equals_augmented_with_correlated_prior(d):
    rng = np.random.default_rng(200 + d)
    sys = paper_example(S=0.2, q=0.3, d=d)
    prior = HistoryPrior.constant(np.zeros(2), [[1.0, 0.3], [0.3, 0.8]], d, jitter=0.01)
    data = simulate_delay(sys, prior, 50, 3, seed=rng)
    D = reorganized_lmmse(sys, prior, data.y)
    A = augmented_lmmse(sys, prior, data.y, lags=(d - 1,))
    assert_same(D, A)
    np.testing.assert_allclose(D.extras["lagged"][d - 1][0], A.extras["lagged"][d - 1][0], atol=TOL, rtol=0)
    np.testing.assert_allclose(D.extras["lagged"][d - 1][1], A.extras["lagged"][d - 1][1], atol=TOL, rtol=0)
    # the prior really is correlated: the filter gain is not zero (Ψ ≠ 0)
    assert np.abs(D.mean[..., 1:, :] - D.extras["next_mean"][..., :-1, :]).max() > 1e-4


def test_reorganized_general_random_prior_and_late_warmup():
    rng = np.random.default_rng(5)
    sys = random_system(rng, 2, 2, 3)
    prior = random_prior(rng, 2, 3, correlated=True)
    data = simulate_delay(sys, prior, 40, 2, seed=rng)
    A = augmented_lmmse(sys, prior, data.y)
    for warm in (None, 12):
        assert_same(reorganized_lmmse(sys, prior, data.y, warmup=warm), A)
    # an uncorrelated prior starts D at t = 0 (all Ψ zero) or after an augmented warm-up: same result
    prior_u = random_prior(rng, 2, 3)
    A_u = augmented_lmmse(sys, prior_u, data.y)
    for warm in (None, 0, 3, 7):
        assert_same(reorganized_lmmse(sys, prior_u, data.y, warmup=warm), A_u)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), d=st.integers(1, 4), n=st.integers(1, 3), m=st.integers(1, 2))
def test_reorganized_equals_augmented_property(seed, d, n, m):
    rng = np.random.default_rng(seed)
    sys = random_system(rng, n, m, d)
    prior = random_prior(rng, n, d, correlated=True)
    data = simulate_delay(sys, prior, 4 * d + 8, 2, seed=rng)
    assert_same(reorganized_lmmse(sys, prior, data.y), augmented_lmmse(sys, prior, data.y), tol=1e-9)


@pytest.mark.parametrize("erratum", ["E5", "E6", "E7"])
def test_printed_psi_recursion_is_not_optimal(erratum):
    """Each of the source's printed (30)/(58) errors, re-inserted, breaks the agreement with A."""
    d = 3
    sys = paper_example(S=0.2, q=0.3, d=d)
    prior = HistoryPrior.constant(np.zeros(2), [[1.0, 0.3], [0.3, 0.8]], d, jitter=0.01)
    data = simulate_delay(sys, prior, 40, 2, seed=3)
    A = augmented_lmmse(sys, prior, data.y)
    bad = reorganized_lmmse(sys, prior, data.y, reinsert_errata=[erratum])
    assert np.abs(bad.mean - A.mean).max() > 1e-5
    assert np.abs(bad.cov - A.cov).max() > 1e-7


# ----------------------------------------------------------------------------- §5 item 15: time-varying pmf


def test_time_varying_fading_all_algorithms_agree():
    d, T = 2, 40
    laws = [FadingPMF([0.2, 1.0], [0.5 + 0.4 * np.sin(t), 0.5 - 0.4 * np.sin(t)]) for t in range(T)]
    sys = paper_example(S=0.25, d=d).replace(fading=lambda t: laws[t], q_mult=np.linspace(0.05, 0.3, T)[:, None])
    rng = np.random.default_rng(9)
    prior_u = random_prior(rng, 2, d)
    data = simulate_delay(sys, prior_u, T, 3, seed=rng)
    A = augmented_lmmse(sys, prior_u, data.y)
    assert_same(chain_lmmse(sys, prior_u, data.y), A)
    assert_same(reorganized_lmmse(sys, prior_u, data.y), A)
    prior_c = random_prior(rng, 2, d, correlated=True)
    assert_same(reorganized_lmmse(sys, prior_c, data.y), augmented_lmmse(sys, prior_c, data.y))
    # moments-only fading gives the same estimates as the pmf with those moments
    mom = FadingMoments([laws[t].mean for t in range(T)], [laws[t].variance for t in range(T)])
    assert_same(chain_lmmse(sys.replace(fading=mom), prior_u, data.y), A)


# ----------------------------------------------------------------------------- §5 item 3: filter ≡ predictor


@pytest.mark.parametrize("d", [1, 3])
def test_filter_equals_predictor_with_uncorrelated_history(d):
    sys = paper_example(S=0.3, d=d)
    data = simulate_delay(sys, paper_prior(d), 30, 4, seed=d)
    r = chain_lmmse(sys, paper_prior(d), data.y, lags=(d - 1,))
    np.testing.assert_array_equal(r.mean[:, 1:], r.extras["next_mean"][:, :-1])
    np.testing.assert_array_equal(r.cov[:, 1:], r.extras["next_cov"][:, :-1])
    # the paper's smoother x̂(t-d+1|t) is the one-step prediction x̂(t-d+1|t-d)
    np.testing.assert_array_equal(r.extras["lagged"][d - 1][0][:, d:], r.extras["next_mean"][:, :-d])


def test_filter_gain_vanishes_with_constant_history():
    d = 3
    sys = paper_example(S=0.3, d=d)
    prior = HistoryPrior.constant(np.zeros(2), 0.01 * np.eye(2), d)
    data = simulate_delay(sys, prior, 60, 200, seed=1)
    r = augmented_lmmse(sys, prior, data.y)
    diff = np.sqrt(np.mean((r.mean[:, 1:] - r.extras["next_mean"][:, :-1]) ** 2, axis=(0, 2)))  # index t-1 <-> time t
    assert diff[0] > 1e-4  # t = 1: nonzero gain
    assert diff[40:].max() < 1e-6  # then the gain dies out


# ----------------------------------------------------------------------------- §5 item 4: RTS, fixed point


@pytest.mark.parametrize("d", [0, 1, 3])
def test_interval_smoother_equals_big_window_augmentation(d):
    rng = np.random.default_rng(40 + d)
    sys = random_system(rng, 2, 1, d)
    prior = random_prior(rng, 2, d)
    T = 25
    data = simulate_delay(sys, prior, T, 2, seed=rng)
    sm = smooth_interval(sys, prior, data.y)
    big = augmented_lmmse(sys, prior, data.y, window=T + d)
    n = 2
    for idx, j in enumerate(sm.times):  # block k of X̂(T|T-1) is x(T-k)
        k = T - j
        np.testing.assert_allclose(sm.mean[:, idx], big.extras["final_mean"][:, k * n : (k + 1) * n], atol=TOL, rtol=0)
        np.testing.assert_allclose(
            sm.cov[0, idx], big.extras["final_cov"][k * n : (k + 1) * n, k * n : (k + 1) * n], atol=TOL, rtol=0
        )


@pytest.mark.parametrize("j0", [-2, 0, 5, 13])
def test_fixed_point_smoother_equals_rts(j0):
    sys = paper_example(S=0.2, q=0.6, d=3)
    prior = paper_prior(3)
    data = simulate_delay(sys, prior, 30, 3, seed=11)
    mean, cov = smooth_point(sys, prior, data.y, j0)
    sm = smooth_interval(sys, prior, data.y)
    idx = j0 + 3
    np.testing.assert_allclose(mean[:, -1], sm.mean[:, idx], atol=TOL, rtol=0)
    np.testing.assert_allclose(cov[0, -1], sm.cov[0, idx], atol=TOL, rtol=0)
    # it changes only at t = j0 + d + k(d+1)
    changes = [
        t for t in range(1, 30) if np.isfinite(mean[0, t - 1, 0]) and np.abs(mean[:, t] - mean[:, t - 1]).max() > 0
    ]
    assert all((t - j0 - 3) % 4 == 0 and t >= j0 + 3 for t in changes) and changes


# ----------------------------------------------------------------------------- §5 item 5, 6, 7: reductions


@pytest.mark.parametrize("S", [0.0, 0.2])
def test_d0_no_fading_is_correlated_kf(S):
    rng = np.random.default_rng(1)
    sys = DelayFadingSystem([[0.9, 0.2], [0.0, 0.7]], [[1.0, 0.5]], [[1.0], [0.5]], 0.4, 0.3, S, 0)
    prior = HistoryPrior.uncorrelated([[0.3, -0.2]], [[[0.5, 0.1], [0.1, 0.4]]])
    data = simulate_delay(sys, prior, 30, 2, seed=rng)
    r = chain_lmmse(sys, prior, data.y)
    for run in range(2):
        ref = correlated_kf(sys.A, sys.H, sys.GQG, sys.GS, sys.Qv, [0.3, -0.2], [[0.5, 0.1], [0.1, 0.4]], data.y[run])
        np.testing.assert_allclose(r.mean[run], [o[0] for o in ref], atol=TOL)
        np.testing.assert_allclose(r.cov[run], [o[1] for o in ref], atol=TOL)
        np.testing.assert_allclose(r.extras["next_mean"][run], [o[2] for o in ref], atol=TOL)
        np.testing.assert_allclose(r.extras["next_cov"][run], [o[3] for o in ref], atol=TOL)


def test_d0_uncorrelated_matches_filterpy():
    filterpy = pytest.importorskip("filterpy.kalman")
    sys = DelayFadingSystem(
        [[0.9, 0.2], [0.0, 0.7]], [[1.0, 0.5]], np.eye(2), 0.2 * np.eye(2), 0.3, np.zeros((2, 1)), 0
    )
    prior = HistoryPrior.uncorrelated([[0.3, -0.2]], [np.eye(2)])
    data = simulate_delay(sys, prior, 20, 1, seed=2)
    r = chain_lmmse(sys, prior, data.y[0])
    kf = filterpy.KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = (
        np.array([0.3, -0.2]),
        np.eye(2),
        sys.A,
        sys.H,
        0.2 * np.eye(2),
        np.array([[0.3]]),
    )
    for t in range(20):
        kf.update(data.y[0, t])
        np.testing.assert_allclose(r.mean[t], kf.x, atol=1e-10)
        np.testing.assert_allclose(r.cov[t], kf.P, atol=1e-10)
        kf.predict()


def test_no_fading_delay_is_interleaved_kfs():
    d, T = 2, 30
    rng = np.random.default_rng(3)
    sys = random_system(rng, 2, 1, d).replace(A_mult=None, q_mult=None, fading=None)
    prior = random_prior(rng, 2, d)
    data = simulate_delay(sys, prior, T, 1, seed=rng)
    r = chain_lmmse(sys, prior, data.y[0])
    for rr in range(d + 1):  # chain of x(rr - d): measured at times rr, rr + d + 1, ...
        times = list(range(rr, T, d + 1))
        ref = correlated_kf(
            sys.A, sys.H, sys.GQG, sys.GS, sys.Qv, prior.block_mean(d - rr), prior.block_cov(d - rr), data.y[0, times]
        )
        np.testing.assert_allclose(r.extras["measured_mean"][times], [o[0] for o in ref], atol=TOL)
        np.testing.assert_allclose(r.extras["measured_cov"][times], [o[1] for o in ref], atol=TOL)
        np.testing.assert_allclose(r.extras["next_mean"][times], [o[2] for o in ref], atol=TOL)


def test_bernoulli_fading_is_nahi_lmmse():
    """Uncertain observations: Q_ε = p²HPH^T + p(1-p)HΛH^T + Q_v (Nahi 1969), written out directly."""
    pbar = 0.7
    A, H, Q, R = np.array([[0.95]]), np.array([[1.0]]), np.array([[0.5]]), np.array([[0.2]])
    sys = DelayFadingSystem(A, H, [[1.0]], Q, R, 0.0, 0, fading=FadingPMF.bernoulli(pbar))
    prior = HistoryPrior.uncorrelated([[1.0]], [[[2.0]]])
    data = simulate_delay(sys, prior, 25, 2, seed=4)
    r = chain_lmmse(sys, prior, data.y)
    x, P, Lam = np.full((2, 1), 1.0), np.array([[2.0]]), np.array([[3.0]])
    for t in range(25):
        Qe = pbar**2 * H @ P @ H.T + pbar * (1 - pbar) * H @ Lam @ H.T + R
        K = pbar * P @ H.T / Qe
        x = x + (data.y[:, t] - pbar * x @ H.T) @ K.T
        P = P - K @ Qe @ K.T
        np.testing.assert_allclose(r.mean[:, t], x, atol=TOL)
        np.testing.assert_allclose(r.cov[0, t], P, atol=TOL)
        x, P, Lam = x @ A.T, A @ P @ A.T + Q, A @ Lam @ A.T + Q


# ----------------------------------------------------------------------------- §5 item 8, 12: paper decorrelation


@pytest.mark.parametrize("case", ["S=0", "sigma2=0"])
def test_paper_decorrelation_equals_optimal_in_degenerate_cases(case):
    sys = paper_example(S=0.0, q=0.3) if case == "S=0" else paper_example(S=0.2).replace(fading=FadingPMF([0.9], [1.0]))
    data = simulate_delay(sys, paper_prior(), 40, 2, seed=6)
    assert_same(chain_lmmse(sys, paper_prior(), data.y, decorrelation="paper"), chain_lmmse(sys, paper_prior(), data.y))
    assert_same(
        reorganized_lmmse(sys, paper_prior(), data.y, decorrelation="paper"), chain_lmmse(sys, paper_prior(), data.y)
    )


def test_paper_decorrelation_same_in_chain_and_reorganized():
    """The constant-J mode is the source's own scheme: D and C agree on it, and it differs from optimal."""
    sys = paper_example(S=0.2, q=0.3)
    data = simulate_delay(sys, paper_prior(), 40, 2, seed=17)
    c = chain_lmmse(sys, paper_prior(), data.y, decorrelation="paper")
    assert_same(reorganized_lmmse(sys, paper_prior(), data.y, decorrelation="paper"), c)
    assert np.abs(c.extras["next_cov"] - chain_lmmse(sys, paper_prior(), data.y).extras["next_cov"]).max() > 1e-3


def test_paper_decorrelation_is_worse_and_overconfident():
    """q = 0.3, S = 0.29 (spec §2.6): the constant-J predictor has a larger MSE than the optimal one."""
    sys = paper_example(S=0.29, q=0.3)
    prior = paper_prior()
    data = simulate_delay(sys, prior, 120, 1500, seed=7)
    opt = chain_lmmse(sys, prior, data.y)
    pap = chain_lmmse(sys, prior, data.y, decorrelation="paper")
    truth = data.x[:, 1:]
    mse_opt = np.mean((opt.extras["next_mean"] - truth)[:, 60:] ** 2, axis=(0, 1))
    mse_pap = np.mean((pap.extras["next_mean"] - truth)[:, 60:] ** 2, axis=(0, 1))
    assert np.all(mse_pap > 1.1 * mse_opt)
    # at t = 119 P(t+1|t) is the spec's 0.2689, 0.1850; the paper mode claims 0.3178, 0.2578
    np.testing.assert_allclose(np.diagonal(opt.extras["next_cov"][0, 119]), [0.2689, 0.1850], atol=6e-5)
    np.testing.assert_allclose(np.diagonal(pap.extras["next_cov"][0, 119]), [0.3178, 0.2578], atol=6e-5)
    # ... and its claimed covariance is too small: the true MSE of the constant-J predictor exceeds it
    assert np.all(mse_pap > 1.04 * np.diagonal(pap.extras["next_cov"][0, 60:], axis1=-2, axis2=-1).mean(axis=0))
    # the optimal predictor's MSE matches its covariance (5 % at 1500 runs, pooled)
    np.testing.assert_allclose(
        mse_opt, np.diagonal(opt.extras["next_cov"][0, 60:], axis1=-2, axis2=-1).mean(axis=0), rtol=0.05
    )


# ----------------------------------------------------------------------------- §5 item 16: singular S


def test_singular_cross_covariance_runs_and_stays_psd():
    sys = paper_example(S=np.sqrt(0.3 * 0.3))
    assert np.allclose(sys.eta_cov, 0)
    prior = paper_prior()
    data = simulate_delay(sys, prior, 100, 3, seed=8)
    np.testing.assert_allclose(data.extras["w"], data.extras["v"], atol=1e-12)  # w ≡ v at S = sqrt(Qw Qv)
    for r in (
        chain_lmmse(sys, prior, data.y),
        augmented_lmmse(sys, prior, data.y),
        reorganized_lmmse(sys, prior, data.y),
    ):
        for P in (r.cov, r.extras["next_cov"], r.extras["measured_cov"]):
            assert np.isfinite(P).all() and np.linalg.eigvalsh(P).min() > -1e-12
    sm = smooth_interval(sys, prior, data.y)
    assert np.isfinite(sm.mean).all() and np.linalg.eigvalsh(sm.cov).min() > -1e-12


# ----------------------------------------------------------------------------- k-step prediction


def test_k_step_prediction_equals_uninformative_measurements():
    """With S = 0, a measurement with γ̄ = σ² = 0 carries no information: x̂(t+k|t) is the
    one-step prediction after k-1 such measurements."""
    d, T, t_cut, kmax = 2, 30, 20, 6
    base = paper_example(S=0.0, q=0.6, d=d)
    law = base.fading.source
    mean = [law.mean if t <= t_cut else 0.0 for t in range(T)]
    var = [law.variance if t <= t_cut else 0.0 for t in range(T)]
    blind = base.replace(fading=FadingMoments(mean, var))
    data = simulate_delay(base, paper_prior(d), T, 2, seed=10)
    r = chain_lmmse(base, paper_prior(d), data.y, horizons=range(1, kmax + 1))
    b = chain_lmmse(blind, paper_prior(d), data.y)
    for k in range(1, kmax + 1):
        np.testing.assert_allclose(r.extras["ahead"][k][0][:, t_cut], b.extras["next_mean"][:, t_cut + k - 1], atol=TOL)
        np.testing.assert_allclose(r.extras["ahead"][k][1][0, t_cut], b.extras["next_cov"][0, t_cut + k - 1], atol=TOL)


# ----------------------------------------------------------------------------- batch, classes


def test_batched_equals_per_run_and_classes():
    sys = paper_example(S=0.15, q=0.6)
    prior = paper_prior()
    data = simulate_delay(sys, prior, 20, 4, seed=12)
    batch = ChainLMMSE(sys, prior).filter(data.y.reshape(2, 2, 20, 1), lags=(5,))
    assert batch.mean.shape == (2, 2, 20, 2) and batch.cov.shape == (2, 2, 20, 2, 2)
    for i in range(4):
        one = chain_lmmse(sys, prior, data.y[i], lags=(5,))
        np.testing.assert_allclose(batch.mean.reshape(4, 20, 2)[i], one.mean, atol=0)
        np.testing.assert_allclose(
            batch.extras["lagged"][5][0].reshape(4, 20, 2)[i], one.extras["lagged"][5][0], atol=0
        )
    assert_same(AugmentedLMMSE(sys, prior).filter(data.y), ReorganizedInnovationLMMSE(sys, prior).filter(data.y))


# ----------------------------------------------------------------------------- §5 item 9: Monte Carlo


def _pooled_ratio(err, P):
    """Pooled ratio of Σ_t e_t^T e_t to Σ_t tr P_t and its standard error across runs."""
    per_run = np.sum(err**2, axis=(1, 2)) / np.trace(P, axis1=-2, axis2=-1).sum()
    return per_run.mean(), per_run.std(ddof=1) / np.sqrt(per_run.size)


@pytest.mark.parametrize("S,q", [(0.3, 1.0), (0.15, 0.3)])
def test_monte_carlo_consistency(S, q):
    d, T, R = 3, 60, 2000
    sys = paper_example(S=S, q=q, d=d)
    prior = paper_prior(d)
    data = simulate_delay(sys, prior, T, R, seed=13)
    r = chain_lmmse(sys, prior, data.y, horizons=(3,))
    full = full_states(data)  # index j + d
    checks = [
        (r.extras["next_mean"] - data.x[:, 1:], r.extras["next_cov"][0]),
        (r.extras["measured_mean"] - full[:, :T], r.extras["measured_cov"][0]),
        (r.extras["ahead"][3][0][:, :-2] - data.x[:, 3 : T + 1], r.extras["ahead"][3][1][0, :-2]),
    ]
    for err, P in checks:
        ratio, se = _pooled_ratio(err[:, 10:], P[10:])
        assert abs(ratio - 1) < 5 * se + 1e-3, (ratio, se)
    # normalized innovation E[ε^T Q_ε^{-1} ε] ≈ m
    nis = np.einsum(
        "rti,tij,rtj->rt", r.extras["innovation"], np.linalg.inv(r.extras["innovation_cov"][0]), r.extras["innovation"]
    ).mean(axis=1)
    assert abs(nis.mean() - 1) < 5 * nis.std(ddof=1) / np.sqrt(R)
    # Λ(t) against the empirical E[x x^T] at the last step (sample variance for the tolerance)
    xx = data.x[:, T, 0] ** 2
    assert abs(xx.mean() - r.extras["second_moment"][T, 0, 0]) < 5 * xx.std(ddof=1) / np.sqrt(R)


def test_simulator_noise_cross_covariance():
    sys = paper_example(S=0.15)
    data = simulate_delay(sys, paper_prior(), 50, 400, seed=14)
    w, v = data.extras["w"].ravel(), data.extras["v"].ravel()
    prod = w * v
    assert abs(prod.mean() - 0.15) < 5 * prod.std() / np.sqrt(prod.size)
    assert abs(np.mean(w**2) - 0.3) < 5 * np.std(w**2) / np.sqrt(w.size)
    g = data.extras["gamma"]
    assert set(np.unique(g)) <= {0.95, 0.98, 1.0}
    assert abs(np.mean(g == 1.0) - 0.8) < 5 * np.sqrt(0.16 / g.size)


# ----------------------------------------------------------------------------- §5 item 10, 11, §3.3


def _loewner_ge(P1, P2, tol=1e-12):
    """P1 >= P2 in the Loewner order (all eigenvalues of the difference >= -tol)."""
    return np.linalg.eigvalsh(P1 - P2).min() >= -tol


def test_loewner_orderings():
    d, T = 3, 60
    sys = paper_example(S=0.2, q=0.6, d=d)
    prior = paper_prior(d)
    y = np.zeros((T, 1))
    r = chain_lmmse(sys, prior, y, lags=range(0, 3 * d + 3), horizons=(1, 2, 3, 5))
    sm = smooth_interval(sys, prior, y)
    # same target, more data: P(j|N) <= P(j|j+d) <= P(j|j-1); P(t-d|t) <= P(t-d|t-1)
    for j in range(0, T - d):
        PN = sm.cov[j + d]
        Pjd = r.extras["measured_cov"][j + d]
        Ppred = r.extras["next_cov"][j - 1] if j >= 1 else prior.block_cov(0)
        assert _loewner_ge(Pjd, PN) and _loewner_ge(Ppred, Pjd)
    for t in range(4 * d + 3, T):
        # x(t-L) for growing t, fixed element j = t - L: more data can only help
        for L in range(0, 3 * d + 2):
            assert _loewner_ge(r.extras["lagged"][L][1][t - 1], r.extras["lagged"][L + 1][1][t])
    # different targets, steady state: P(t+1|t) <= P(t+k|t)
    for k in (2, 3, 5):
        assert _loewner_ge(r.extras["ahead"][k][1][-1], r.extras["ahead"][1][1][-1])


@pytest.mark.parametrize(
    "q,S,filt,meas,Qe",
    [
        (1, 0, (0.44353, 0.36882), (0.11801, 0.09580), 1.16914),
        (1, 0.15, (0.25756, 0.23092), (0.09727, 0.08480), 0.82740),
        (1, 0.3, (0.02392, 0.01280), (0.02179, 0.01159), 0.33376),
        (0.6, 0, (0.57373, 0.43490), (0.25384, 0.19023), 0.86117),
        (0.6, 0.15, (0.34009, 0.26973), (0.19367, 0.15170), 0.66981),
        (0.6, 0.3, (0.08623, 0.06528), (0.07316, 0.05501), 0.44593),
        (0.3, 0, (0.85194, 0.57367), (0.56674, 0.38009), 0.82107),
        (0.3, 0.15, (0.55728, 0.38345), (0.41892, 0.28708), 0.72656),
        (0.3, 0.3, (0.24812, 0.17011), (0.21677, 0.14821), 0.62389),
    ],
)
def test_steady_state_reference_table(q, S, filt, meas, Qe):
    """Spec §3.3 (independent prototype): steady-state values to 4 decimals."""
    r = chain_lmmse(paper_example(S=S, q=q), paper_prior(), np.zeros((600, 1)))
    np.testing.assert_allclose(np.diagonal(r.cov[-1]), filt, atol=5e-5)
    np.testing.assert_allclose(np.diagonal(r.extras["measured_cov"][-1]), meas, atol=5e-5)
    np.testing.assert_allclose(r.extras["innovation_cov"][-1, 0, 0], Qe, atol=5e-5)


def test_transient_reference_values():
    r = chain_lmmse(paper_example(S=0.3), paper_prior(), np.zeros((151, 1)))
    np.testing.assert_allclose(np.diagonal(r.cov[0]), [0.01, 0.01], atol=5e-6)
    np.testing.assert_allclose(np.diagonal(r.extras["next_cov"][0]), [0.00101, 0.00243], atol=5e-6)
    for t, ref in [
        (25, (0.01770, 0.00874)),
        (50, (0.02237, 0.01181)),
        (100, (0.02382, 0.01274)),
        (150, (0.02391, 0.01280)),
    ]:
        np.testing.assert_allclose(np.diagonal(r.cov[t]), ref, atol=5e-6)


def test_steady_state_does_not_depend_on_delay():
    res = {}
    for d in (0, 1, 3, 6):
        r = chain_lmmse(paper_example(S=0.3, d=d), paper_prior(d), np.zeros((700, 1)))
        res[d] = r
    for d in (1, 3, 6):
        np.testing.assert_allclose(res[d].cov[-1], res[1].cov[-1], atol=1e-9)
        np.testing.assert_allclose(res[d].extras["measured_cov"][-1], res[0].cov[-1], atol=1e-9)
    np.testing.assert_allclose(np.diagonal(res[3].cov[-1]), [0.02392, 0.01280], atol=5e-6)


def test_second_moment_stationary_value():
    lam = second_moments(paper_example(), paper_prior(), 2000)
    np.testing.assert_allclose(lam[2000], [[2.157210, 1.600855], [1.600855, 1.212491]], atol=1e-6)


# ----------------------------------------------------------------------------- extra lags (generic engine)


def test_extra_lag_reduces_to_plain_kf_when_pure_markov():
    """x(t+1) = A0 x(t) with d = 1 measured as y(t) = H x(t-1): augmentation equals a KF on [x(t); x(t-1)]."""
    A0 = np.array([[0.9, 0.1], [0.0, 0.8]])
    sys = DelayFadingSystem(
        np.zeros((2, 2)), [[1.0, 0.0]], np.eye(2), 0.1 * np.eye(2), 0.2, np.zeros((2, 1)), 1, extra_lags={0: A0}
    )
    prior = HistoryPrior.uncorrelated(np.zeros((2, 2)), [np.eye(2), np.eye(2)])
    data = simulate_delay(sys, prior, 20, 1, seed=15)
    r = augmented_lmmse(sys, prior, data.y[0])
    AA = np.block([[A0, np.zeros((2, 2))], [np.eye(2), np.zeros((2, 2))]])
    HH = np.array([[0.0, 0.0, 1.0, 0.0]])
    GQG = np.zeros((4, 4))
    GQG[:2, :2] = 0.1 * np.eye(2)
    ref = correlated_kf(AA, HH, GQG, np.zeros((4, 1)), np.array([[0.2]]), np.zeros(4), np.eye(4), data.y[0])
    np.testing.assert_allclose(r.extras["next_mean"], [o[2][:2] for o in ref], atol=TOL)
    np.testing.assert_allclose(r.extras["measured_cov"], [o[1][2:, 2:] for o in ref], atol=TOL)
    with pytest.raises(ValueError, match="system"):
        chain_lmmse(sys, prior, data.y[0])


def test_shared_pmf_law_is_accepted_as_fading():
    from tobitkf.channels.laws import PMF

    sys = paper_example(S=0.2, q=0.6)
    shared = sys.replace(fading=PMF([0.95, 0.98, 0.6], [0.05, 0.15, 0.8]))
    data = simulate_delay(sys, paper_prior(), 30, 2, seed=16)
    assert_same(chain_lmmse(shared, paper_prior(), data.y), chain_lmmse(sys, paper_prior(), data.y))
    with pytest.raises(ValueError, match="fading"):
        sys.replace(fading=PMF([[0.5, 1.0], [0.2, 1.0]], [0.5, 0.5]))


# ----------------------------------------------------------------------------- bad input


def test_bad_input():
    sys = paper_example()
    prior = paper_prior()
    y = np.zeros((5, 1))
    with pytest.raises(ValueError, match="^d:"):
        paper_example(d=-1)
    with pytest.raises(ValueError, match="^d:"):
        HistoryPrior.repeated(np.zeros(2), np.eye(2), -2)
    with pytest.raises(ValueError, match="prior"):
        chain_lmmse(sys, paper_prior(2), y)
    with pytest.raises(ValueError, match="prior"):
        simulate_delay(sys, paper_prior(4), 5)
    with pytest.raises(ValueError, match="probs"):
        FadingPMF([0.5, 1.0], [1.2, -0.2])
    with pytest.raises(ValueError, match="probs"):
        FadingPMF([0.5, 1.0], [0.5, 0.3])
    with pytest.raises(ValueError, match="values"):
        FadingPMF([0.5, 1.5], [0.5, 0.5])
    with pytest.raises(ValueError, match="^S:"):
        paper_example(S=0.31)
    with pytest.raises(ValueError, match="prior"):
        chain_lmmse(sys, HistoryPrior.constant(np.zeros(2), np.eye(2), 3), y)
    with pytest.raises(ValueError, match="prior"):
        ChainLMMSE(sys, HistoryPrior.constant(np.zeros(2), np.eye(2), 3))
    with pytest.raises(ValueError, match="decorrelation"):
        chain_lmmse(sys, prior, y, decorrelation="constant")
    with pytest.raises(ValueError, match="reinsert_errata"):
        reorganized_lmmse(sys, prior, y, reinsert_errata=["E9"])
    with pytest.raises(ValueError, match="window"):
        augmented_lmmse(sys, prior, y, window=2)
    with pytest.raises(ValueError, match="warmup"):
        reorganized_lmmse(sys, HistoryPrior.constant(np.zeros(2), np.eye(2), 3), y, warmup=3)
    with pytest.raises(ValueError, match="^y:"):
        chain_lmmse(sys, prior, np.zeros((5, 2)))
    with pytest.raises(ValueError, match="Qv"):
        sys.replace(Qv=0.0)
    with pytest.raises(ValueError, match="fixed_point"):
        chain_lmmse(sys, prior, y, fixed_point=-4)
    with pytest.raises(ValueError, match="decorrelation"):
        chain_lmmse(sys, prior, y, lags=(7,), decorrelation="paper")
    with pytest.raises(ValueError, match="q_mult"):
        sys.replace(q_mult=None)


@pytest.mark.parametrize("form", ["joseph", "square_root"])
def test_augmented_covariance_forms_equal_the_standard_form(form):
    rng = np.random.default_rng(31)
    sys, prior = random_system(rng, 2, 1, 2), random_prior(rng, 2, 2, correlated=True)
    data = simulate_delay(sys, prior, 25, 3, seed=4)
    a = AugmentedLMMSE(sys, prior).filter(data.y)
    b = AugmentedLMMSE(sys, prior, covariance_update=form).filter(data.y)
    assert_same(a, b, tol=1e-9)


# ---------------------------------------------------------------- Algorithm D's compiled covariance step

_KERNEL_FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "measured_mean", "measured_cov", "next_mean", "next_cov")


def _uncorrelated(d):
    return HistoryPrior.uncorrelated([np.full(2, 0.1 * k) for k in range(d + 1)], [np.eye(2) * 0.01] * (d + 1))


def _assert_close_rel(r1, r2, fields=_KERNEL_FIELDS, tol=1e-12):
    for f in fields:
        a, b = np.asarray(field(r1, f)), np.asarray(field(r2, f))
        assert a.shape == b.shape, f
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol * max(1.0, float(np.abs(b).max())), err_msg=f)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
@pytest.mark.parametrize("prior_kind", ["paper", "uncorrelated"])
@pytest.mark.parametrize("mode", ["optimal", "paper"])
@pytest.mark.parametrize("errata", [(), ("E5",), ("E6",), ("E7",), ("E5", "E6", "E7")])
def test_reorganized_compiled_equals_numpy(d, prior_kind, mode, errata):
    pytest.importorskip("numba")
    sys_ = paper_example(d=d)
    prior = paper_prior(d=d) if prior_kind == "paper" else _uncorrelated(d)
    y = simulate_delay(sys_, prior, 40, 3, seed=d).y
    opts = dict(decorrelation=mode, reinsert_errata=errata)
    ref = ReorganizedInnovationLMMSE(sys_, prior, backend="numpy", **opts).filter(y)
    fast = ReorganizedInnovationLMMSE(sys_, prior, backend="numba", **opts).filter(y)
    _assert_close_rel(fast, ref)
    for L in ref.extras["lagged"]:
        for a, b in zip(fast.extras["lagged"][L], ref.extras["lagged"][L]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fast.extras["second_moment"], ref.extras["second_moment"], rtol=1e-12)


def test_reorganized_compiled_errata_reach_the_kernel():
    """Each re-inserted erratum changes the compiled result (the flags are not ignored by the kernel)."""
    pytest.importorskip("numba")
    # the case of test_printed_psi_recursion_is_not_optimal, where each erratum changes the result
    sys_ = paper_example(S=0.2, q=0.3, d=3)
    prior = HistoryPrior.constant(np.zeros(2), [[1.0, 0.3], [0.3, 0.8]], 3, jitter=0.01)
    y = simulate_delay(sys_, prior, 40, 2, seed=3).y
    base = ReorganizedInnovationLMMSE(sys_, prior, backend="numba").filter(y)
    for err in ("E5", "E6", "E7"):
        bad = ReorganizedInnovationLMMSE(sys_, prior, backend="numba", reinsert_errata=[err]).filter(y)
        ref = ReorganizedInnovationLMMSE(sys_, prior, backend="numpy", reinsert_errata=[err]).filter(y)
        assert np.abs(bad.mean - base.mean).max() > 1e-5, err
        _assert_close_rel(bad, ref)


@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_reorganized_compiled_step_loop_equals_filter_and_resumes(batch):
    pytest.importorskip("numba")
    import pickle

    sys_, prior = paper_example(d=3), paper_prior(d=3)
    T = 30
    y = simulate_delay(sys_, prior, T, int(np.prod(batch, dtype=int)), seed=5).y.reshape(batch + (T, sys_.m))
    est = ReorganizedInnovationLMMSE(sys_, prior, backend="numba")
    res = est.filter(y)
    s = est.init(batch_shape=batch)
    for k in range(T):
        if k == 17:  # checkpoint mid-run and resume from the copy
            s = pickle.loads(pickle.dumps(s))
        s = est.step(s, y[..., k, :])
    np.testing.assert_array_equal(s.mean, res.mean[..., -1, :])
    np.testing.assert_array_equal(np.broadcast_to(s.cov, res.cov[..., -1, :, :].shape), res.cov[..., -1, :, :])
    # a numpy-path estimator continues a compiled state (one carry layout for both)
    half = est.filter(y[..., :12, :])
    rest = ReorganizedInnovationLMMSE(sys_, prior, backend="numpy").filter(y[..., 12:, :], state=half.final)
    np.testing.assert_allclose(rest.mean, res.mean[..., 12:, :], rtol=1e-12, atol=1e-12)


def test_reorganized_compiled_refuses_varying_laws():
    pytest.importorskip("numba")
    sys_ = paper_example(d=2).replace(fading=FadingMoments(np.linspace(0.5, 0.9, 50), 0.01))
    prior = paper_prior(d=2)
    with pytest.raises(ValidationError, match="change with t"):
        ReorganizedInnovationLMMSE(sys_, prior, backend="numba")
    y = simulate_delay(sys_, prior, 20, 2, seed=0).y
    a = ReorganizedInnovationLMMSE(sys_, prior).filter(y)  # "auto" runs the numpy step
    b = ReorganizedInnovationLMMSE(sys_, prior, backend="numpy").filter(y)
    np.testing.assert_array_equal(a.mean, b.mean)


# ---------------------------------------------------------------- Algorithm C's compiled moments


@pytest.mark.parametrize("d", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("mode", ["optimal", "paper"])
@pytest.mark.parametrize("S", [0.0, 0.2])
def test_chain_compiled_moments_equal_numpy(d, mode, S):
    """The compiled moments of Λ(t-d) (the reorganized LMMSE's kernel code) give the numpy chain's
    estimates, smoothed lags, predictions and fixed point to 1e-12, with and without the
    same-time noise correlation S (which J, Σ and the "optimal"/"paper" split depend on).

    Mutations tried on the kernel (3 Dec 2026): Σ's multiplicative term scaled by 0.999 failed 54 of the
    106 chain and reorganized kernel tests; J scaled by 1 + 1e-9 failed the 10 chain cases with S ≠ 0
    (J = 0 when S = 0)."""
    pytest.importorskip("numba")
    sys_ = paper_example(S=S, q=0.3, d=d)
    prior = _uncorrelated(d)
    y = simulate_delay(sys_, prior, 40, 3, seed=d + 7).y
    lags = (1, d + 1) if mode == "optimal" else (1,) if d else ()  # "paper": lags up to 2d
    opts = dict(lags=lags, horizons=(1, 2))
    if mode == "optimal":
        opts["fixed_point"] = 2
    ref = ChainLMMSE(sys_, prior, decorrelation=mode, backend="numpy").filter(y, **opts)
    fast = ChainLMMSE(sys_, prior, decorrelation=mode, backend="numba").filter(y, **opts)
    assert set(fast.extras) == set(ref.extras)
    _assert_close_rel(fast, ref, fields=("mean", "cov", "pred_mean", "pred_cov"))

    def leaves(x, path):  # the extras' arrays, through their dicts and tuples
        if isinstance(x, dict):
            return [leaf for k in sorted(x) for leaf in leaves(x[k], f"{path}.{k}")]
        if isinstance(x, (list, tuple)):
            return [leaf for i, e in enumerate(x) for leaf in leaves(e, f"{path}[{i}]")]
        return [(path, np.asarray(x, dtype=float))]

    got, want = leaves(fast.extras, "extras"), leaves(ref.extras, "extras")
    assert [p for p, _ in got] == [p for p, _ in want] and len(want) > 8
    for (path, a), (_, b) in zip(got, want):
        scale = max(1.0, float(np.nanmax(np.abs(b)))) if np.isfinite(b).any() else 1.0
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * scale, err_msg=path)


def test_chain_compiled_step_loop_equals_filter_and_refuses_varying_laws():
    pytest.importorskip("numba")
    sys_, prior = paper_example(d=3), _uncorrelated(3)
    y = simulate_delay(sys_, prior, 30, 6, seed=2).y.reshape(2, 3, 30, 1)
    est = ChainLMMSE(sys_, prior, backend="numba")
    res = est.filter(y)
    s = est.init(batch_shape=(2, 3))
    for k in range(30):
        s = est.step(s, y[..., k, :])
    np.testing.assert_array_equal(s.mean, res.mean[..., -1, :])
    varying = sys_.replace(fading=FadingMoments(np.linspace(0.5, 0.9, 50), 0.01))
    with pytest.raises(ValidationError, match="change with t"):
        ChainLMMSE(varying, prior, backend="numba")
    a = ChainLMMSE(varying, prior).filter(y)  # "auto": the moments on numpy, bitwise the numpy path's
    b = ChainLMMSE(varying, prior, backend="numpy").filter(y)
    np.testing.assert_array_equal(a.mean, b.mean)


# ---------------------------------------------------------------- whole-step kernels of Algorithms A and C


def _two_channel(d):
    """A pure-delay model with two measurement channels (the kernels' solve, not a division), S ≠ 0 and a
    multiplicative noise; the paper's fading pmf."""
    from tobitkf.models.delay import paper_fading

    return DelayFadingSystem(
        A=[[0.4, 0.7], [0.2, 0.6]], H=[[0.5, 1.0], [1.0, -0.3]], Gamma=[[1.0], [1.0]], Qw=0.3,
        Qv=[[0.3, 0.05], [0.05, 0.2]], S=[[0.2, 0.1]], d=d, A_mult=[[[0.1, 0.2], [0.2, -0.1]]], q_mult=[0.16],
        fading=paper_fading(0.3),
    )  # fmt: skip


def _whole_step_case(case, d):
    """The models of the whole-step kernel tests: the paper's (one channel, one multiplicative noise), two
    channels, and one without multiplicative noise (no A_i, Q_ζ among the packed constants)."""
    if case == "paper":
        return paper_example(S=0.2, q=0.3, d=d)
    if case == "two-channel":
        return _two_channel(d)
    from tobitkf.models.delay import paper_fading

    return DelayFadingSystem(
        A=[[0.4, 0.7], [0.2, 0.6]], H=[[0.5, 1.0]], Gamma=[[1.0], [1.0]], Qw=0.3, Qv=0.3, S=0.2, d=d,
        fading=paper_fading(0.3),
    )  # fmt: skip


def _leaves(x, path):
    """The arrays of a result's extras, through their dicts and tuples, with their paths."""
    if isinstance(x, dict):
        return [leaf for k in sorted(x) for leaf in _leaves(x[k], f"{path}.{k}")]
    if isinstance(x, (list, tuple)):
        return [leaf for i, e in enumerate(x) for leaf in _leaves(e, f"{path}[{i}]")]
    return [(path, np.asarray(x, dtype=float))]


def _assert_results_close(fast, ref, tol=1e-12):
    _assert_close_rel(fast, ref, fields=("mean", "cov", "pred_mean", "pred_cov"), tol=tol)
    got, want = _leaves(fast.extras, "extras"), _leaves(ref.extras, "extras")
    assert [p for p, _ in got] == [p for p, _ in want]
    for (path, a), (_, b) in zip(got, want):
        assert a.shape == b.shape, path
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol * max(1.0, float(np.abs(b).max())), err_msg=path)


@pytest.mark.parametrize("d", [0, 1, 3])
@pytest.mark.parametrize("case", ["paper", "two-channel", "no-mult"])
@pytest.mark.parametrize("batch", [(), (3,)], ids=str)
def test_augmented_whole_step_kernel_equals_numpy(d, case, batch):
    """The compiled step of Algorithm A (update, decorrelated predict, Λ_X(t+1) in one call) gives the numpy
    path's every output to 1e-12, for one run and a batch, one and two channels, a correlated prior; the step
    loop equals its filter bitwise."""
    pytest.importorskip("numba")
    sys_ = _whole_step_case(case, d)
    prior = HistoryPrior.constant(np.zeros(2), [[1.0, 0.3], [0.3, 0.8]], d, jitter=0.01)
    T = 25
    y = simulate_delay(sys_, prior, T, int(np.prod(batch, dtype=int)), seed=d + 11).y.reshape(batch + (T, sys_.m))
    ref = AugmentedLMMSE(sys_, prior, window=d + 1, backend="numpy").filter(y)
    est = AugmentedLMMSE(sys_, prior, window=d + 1, backend="numba")
    fast = est.filter(y)
    _assert_results_close(fast, ref)
    s = est.init(batch)
    for k in range(T):
        s = est.step(s, y[..., k, :])
    np.testing.assert_array_equal(s.mean, fast.mean[..., -1, :])


def test_augmented_whole_step_kernel_refuses_what_it_does_not_cover():
    """``backend="numba"`` refuses laws that change with t and the non-standard forms; ``"auto"`` then runs
    the step it ran before (the shared compiled update around the numpy moments: bitwise the numpy path for
    the laws, and the form's own numbers)."""
    pytest.importorskip("numba")
    sys_, prior = paper_example(d=2), paper_prior(d=2)
    varying = sys_.replace(fading=FadingMoments(np.linspace(0.5, 0.9, 50), 0.01))
    with pytest.raises(ValidationError, match="change with t"):
        AugmentedLMMSE(varying, prior, backend="numba")
    with pytest.raises(ValidationError, match="joseph"):
        AugmentedLMMSE(sys_, prior, covariance_update="joseph", backend="numba")
    y = simulate_delay(varying, prior, 20, 2, seed=0).y
    a = AugmentedLMMSE(varying, prior).filter(y)
    b = AugmentedLMMSE(varying, prior, backend="numpy").filter(y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)
    j = AugmentedLMMSE(sys_, prior, covariance_update="joseph").filter(y)
    s = AugmentedLMMSE(sys_, prior).filter(y)
    np.testing.assert_allclose(j.mean, s.mean, rtol=0, atol=1e-10)


@pytest.mark.parametrize("d", [0, 1, 2, 4])
@pytest.mark.parametrize("mode", ["optimal", "paper"])
@pytest.mark.parametrize("case", ["paper", "two-channel", "no-mult"])
def test_chain_plain_step_kernel_equals_numpy(d, mode, case):
    """Algorithm C without lags, horizons or a fixed point runs one compiled call per reading: every output
    (estimates, window, predictions, innovations, second moments) equals the numpy path's to 1e-12."""
    pytest.importorskip("numba")
    sys_ = _whole_step_case(case, d)
    prior = _uncorrelated(d)
    y = simulate_delay(sys_, prior, 30, 3, seed=d + 3).y
    ref = ChainLMMSE(sys_, prior, decorrelation=mode, backend="numpy").filter(y)
    fast = ChainLMMSE(sys_, prior, decorrelation=mode, backend="numba").filter(y)
    _assert_results_close(fast, ref)


def test_chain_plain_steps_continue_a_smoothing_run():
    """A state from a run with lags beyond the window and a fixed point (its carry keeps older elements) goes
    on by plain compiled steps as by numpy steps, and a plain compiled state continues a smoothing run."""
    pytest.importorskip("numba")
    sys_, prior = paper_example(S=0.2, q=0.3, d=2), _uncorrelated(2)
    y = simulate_delay(sys_, prior, 30, 2, seed=4).y
    fast, ref = ChainLMMSE(sys_, prior, backend="numba"), ChainLMMSE(sys_, prior, backend="numpy")
    first = ref.filter(y[:, :12], lags=(1, 4), fixed_point=3)
    a, b = fast.filter(y[:, 12:], state=first.final), ref.filter(y[:, 12:], state=first.final)
    _assert_results_close(a, b)
    plain = fast.filter(y[:, :12]).final
    c = ref.filter(y[:, 12:], lags=(1, 2), state=plain)
    e = ref.filter(y, lags=(1, 2))
    np.testing.assert_allclose(c.mean, e.mean[:, 12:], rtol=0, atol=1e-12)
    for L in (1, 2):
        np.testing.assert_allclose(c.extras["lagged"][L][0], e.extras["lagged"][L][0][:, 12:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
@pytest.mark.parametrize("case", ["paper", "two-channel", "no-mult"])
def test_reorganized_whole_step_kernel_step_loop_equals_numpy(d, case):
    """Algorithm D's compiled whole step (covariances, means, pruning in one call) driven online for one run,
    from a correlated prior (the warm-up steps by Algorithm A, whose means are column blocks), equals the numpy
    step loop to 1e-12 in every per-step output, and its own filter bitwise."""
    pytest.importorskip("numba")
    sys_ = _whole_step_case(case, d)
    prior = HistoryPrior.constant(np.zeros(2), [[1.0, 0.3], [0.3, 0.8]], d, jitter=0.01)
    T = 4 * d + 12
    y = simulate_delay(sys_, prior, T, 1, seed=d + 21).y[0]
    fast, ref = (ReorganizedInnovationLMMSE(sys_, prior, backend=b) for b in ("numba", "numpy"))
    sf, sr = fast.init(), ref.init()
    keys = ("measured_mean", "measured_cov", "next_mean", "next_cov", "innovation", "innovation_cov")
    for k in range(T):
        sf, sr = fast.step(sf, y[k]), ref.step(sr, y[k])
        np.testing.assert_allclose(sf.mean, sr.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sf.cov, sr.cov, rtol=1e-12, atol=1e-12)
        for key in keys + (f"lag{d - 1}_mean", f"lag{d - 1}_cov"):
            np.testing.assert_allclose(sf.extras[key], sr.extras[key], rtol=1e-12, atol=1e-12, err_msg=key)
    res = fast.filter(y)
    np.testing.assert_array_equal(sf.mean, res.mean[-1])


@pytest.mark.parametrize("name", ["chain", "augmented", "reorganized"])
def test_compiled_online_step_of_a_diverging_model_warns_like_numpy(name):
    """An unstable model whose covariances overflow: the compiled online step (no floating-point context,
    a check of the covariance's trace) hands the step to the checked one, which warns and makes the means NaN
    from there on, as the numpy step loop (within a step: the paths round differently), and each path warns
    once (the chain LMMSE's new carry used to drop the online check's "warned" flag and warned at every step
    after the overflow)."""
    pytest.importorskip("numba")
    cls = {"chain": ChainLMMSE, "augmented": AugmentedLMMSE, "reorganized": ReorganizedInnovationLMMSE}[name]
    sys_ = paper_example(d=1).replace(A=[[60.0, 0.0], [0.0, 40.0]])
    prior = _uncorrelated(1)
    y = np.full((1, 300, 1), 0.5)
    runs = {}
    for backend in ("numba", "numpy"):
        est = cls(sys_, prior, backend=backend)
        s, means = est.init((1,)), []
        with pytest.warns(RuntimeWarning, match="stopped being finite") as rec:
            for k in range(300):
                s = est.step(s, y[:, k])
                means.append(s.mean[0])
        runs[backend] = np.array(means), sum("stopped being finite" in str(w.message) for w in rec)
    # the two paths round differently, so the overflow may come one step apart
    (fast, warned_f), (ref, warned_n) = runs["numba"], runs["numpy"]
    assert warned_n == 1 and warned_f == 1
    nan_f, nan_n = np.isnan(fast).any(axis=1), np.isnan(ref).any(axis=1)
    assert nan_n.any() and not nan_n[:50].any()
    first_f, first_n = int(np.argmax(nan_f)), int(np.argmax(nan_n))
    assert abs(first_f - first_n) <= 1 and nan_f[first_f:].all() and nan_n[first_n:].all()
    np.testing.assert_allclose(fast[: min(first_f, first_n) - 5], ref[: min(first_f, first_n) - 5], rtol=1e-9)


@pytest.mark.parametrize("cls", [ChainLMMSE, ReorganizedInnovationLMMSE])
def test_many_runs_keep_the_vectorised_path(cls, monkeypatch):
    """Above ``_WHOLE_STEP_MAX_RUNS`` runs (lowered to 2 here) C and D keep the compiled covariances with the
    vectorised numpy means and shared update: equal to the numpy path and to the whole-step kernel to 1e-12,
    and the step loop equals the filter."""
    pytest.importorskip("numba")
    import tobitkf.filters.delay as delay_mod

    sys_, prior = paper_example(S=0.2, q=0.3, d=3), _uncorrelated(3)
    y = simulate_delay(sys_, prior, 30, 3, seed=9).y
    whole = cls(sys_, prior, backend="numba").filter(y)
    monkeypatch.setattr(delay_mod, "_WHOLE_STEP_MAX_RUNS", 2)
    est = cls(sys_, prior, backend="numba")
    many = est.filter(y)
    ref = cls(sys_, prior, backend="numpy").filter(y)
    _assert_results_close(many, ref)
    _assert_results_close(many, whole)
    s = est.init((3,))
    for k in range(30):
        s = est.step(s, y[:, k])
    np.testing.assert_array_equal(s.mean, many.mean[:, -1])


def _carry_keys(c):
    return {k: sorted(v) for k, v in c.items() if isinstance(v, dict)}


@pytest.mark.parametrize("d", [1, 2, 3])
def test_chain_online_plain_steps_keep_the_numpy_steps_carry(d):
    """The compiled online step of Algorithm C builds its new carry by copying the dicts and deleting their one
    stale entry when the carry is the plain steps' window, else by the scan of the numpy step: driven through
    steps with lags beyond the window, a horizon (Λ kept ahead), a fixed point and back to plain steps, every
    carry holds the numpy step's entries (the same times, values to 1e-12), and a state pickled mid-run
    resumes bitwise."""
    pytest.importorskip("numba")
    import pickle

    sys_, prior = paper_example(S=0.2, q=0.3, d=d), _uncorrelated(d)
    T = 8 * d + 16
    y = simulate_delay(sys_, prior, T, 1, seed=d + 40).y[0]
    fast, ref = ChainLMMSE(sys_, prior, backend="numba"), ChainLMMSE(sys_, prior, backend="numpy")

    def options(k):
        if k < 2 * d + 3:
            return {"lags": (1, 2 * d + 1)}
        if k == 3 * d + 4:
            return {"horizons": (1, 3)}
        if 4 * d + 5 <= k < 4 * d + 7:
            return {"point": 1}
        return {}

    sf, sr = fast.init(), ref.init()
    for k in range(T):
        sf, sr = fast.step(sf, y[k], **options(k)), ref.step(sr, y[k], **options(k))
        assert _carry_keys(sf.carry) == _carry_keys(sr.carry), k
        for key in ("xb", "Pb", "D", "lam"):
            for j, v in sr.carry[key].items():
                np.testing.assert_allclose(sf.carry[key][j], v, rtol=1e-12, atol=1e-14, err_msg=f"{k} {key}[{j}]")
        np.testing.assert_allclose(sf.mean, sr.mean, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(sf.cov, sr.cov, rtol=1e-12, atol=1e-14)
        if k == T // 2:
            mid = sf
    revived = pickle.loads(pickle.dumps(mid))
    s1, s2 = mid, revived
    for k in range(T // 2 + 1, T):
        s1, s2 = fast.step(s1, y[k]), fast.step(s2, y[k])
    np.testing.assert_array_equal(s1.mean, s2.mean)
    np.testing.assert_array_equal(s1.cov, s2.cov)
    np.testing.assert_array_equal(s1.mean, sf.mean)


@pytest.mark.parametrize("cls", [ChainLMMSE, AugmentedLMMSE, ReorganizedInnovationLMMSE])
def test_compiled_online_steps_of_one_estimator_for_several_batch_shapes(cls):
    """The compiled online step keeps the layout of its kernel's output per number of runs: one estimator
    stepping one run, then three, then one again gives, for each, bitwise what a fresh estimator gives (a
    layout of another number of runs would cut the wrong views or fail)."""
    pytest.importorskip("numba")
    sys_, prior = paper_example(S=0.2, q=0.3, d=2), _uncorrelated(2)
    y = simulate_delay(sys_, prior, 15, 3, seed=7).y
    shared = cls(sys_, prior)
    for batch, rec in (((), y[0]), ((3,), y), ((), y[1])):  # rec: (..., T, m)
        a, b = shared.init(batch), cls(sys_, prior).init(batch)
        fresh = cls(sys_, prior)
        for k in range(15):
            a, b = shared.step(a, rec[..., k, :]), fresh.step(b, rec[..., k, :])
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)
        for key, v in b.extras.items():
            np.testing.assert_array_equal(a.extras[key], v, err_msg=key)
        res = cls(sys_, prior).filter(rec)
        np.testing.assert_allclose(a.mean, res.mean[..., -1, :], rtol=1e-12, atol=1e-14)


def test_augmented_online_step_with_lags_equals_its_filter():
    """Algorithm A's online step with lags (which the compiled online step hands to the general step, the same
    compiled kernel inside) records the filter's lagged estimates."""
    pytest.importorskip("numba")
    sys_, prior = paper_example(S=0.2, q=0.3, d=2), _uncorrelated(2)
    y = simulate_delay(sys_, prior, 20, 1, seed=8).y[0]
    est = AugmentedLMMSE(sys_, prior, window=3)
    res = est.filter(y, lags=(1, 3))
    s = est.init()
    for k in range(20):
        s = est.step(s, y[k], lags=(1, 3))
        for L in (1, 3):
            np.testing.assert_allclose(
                s.extras[f"lag{L}_mean"][0], res.extras["lagged"][L][0][k], rtol=1e-12, atol=1e-14
            )
    np.testing.assert_allclose(s.mean, res.mean[-1], rtol=1e-12, atol=1e-14)


# d = 5 with the heavy tests: its whole step is a compiled version of its own (three earlier innovations); d = 4 (two)
# runs in the default run (test_reorganized_compiled_equals_numpy, test_reorganized_whole_step_kernel_step_loop_equals_numpy)
@pytest.mark.parametrize("n, m", [(2, 1), (3, 2), (4, 3)])
@pytest.mark.parametrize("d", [1, 2, 3, pytest.param(5, marks=pytest.mark.heavy)])
@pytest.mark.parametrize("mode", ["optimal", "paper"])
def test_reorganized_preallocated_kernel_equals_numpy_over_long_runs(n, m, d, mode):
    """The compiled covariance step (its products written into preallocated arrays, no array per product) keeps
    every field of the ring (Ψ, K H, the covariances, Λ, Ā, Σ, J, Q_ε and the gains) equal to the numpy step's
    to 1e-12 over 150 steps of random systems of several n, m, d (from an uncorrelated prior, so the first steps
    take the t < d branches, and a correlated one, after the warm-up); and the compiled whole step driven online
    gives the numpy step loop's estimates and per-step outputs to 1e-12 at every step."""
    pytest.importorskip("numba")
    from tobitkf.filters.delay import _ring_views

    rng = np.random.default_rng(100 * n + 10 * m + d)
    sys_ = random_system(rng, n, m, d)
    T = 150
    for prior in (random_prior(rng, n, d), random_prior(rng, n, d, correlated=True)):
        fast, ref = (ReorganizedInnovationLMMSE(sys_, prior, decorrelation=mode, backend=b) for b in ("numba", "numpy"))
        y = simulate_delay(sys_, prior, T, 1, seed=n + m + d).y[0]
        W, layout = ref._layout
        sf, sr = fast.init(), ref.init()
        for k in range(T):
            t = sr.k + 1
            if t >= sr.carry["t0"]:
                rk, rn = sr.carry["ring"].copy(), sr.carry["ring"].copy()
                fast._compiled_cov(rk, t, *fast._compiled_cov_args)
                ref._cov_step(t, _ring_views(rn, layout))
                np.testing.assert_allclose(rk, rn, rtol=1e-12, atol=1e-12 * max(1.0, float(np.abs(rn).max())))
            sf, sr = fast.step(sf, y[k]), ref.step(sr, y[k])
            np.testing.assert_allclose(sf.mean, sr.mean, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(sf.cov, sr.cov, rtol=1e-12, atol=1e-12)
            for key, v in sr.extras.items():
                np.testing.assert_allclose(sf.extras[key], v, rtol=1e-12, atol=1e-12, err_msg=key)
