"""Tests of the TKF-FM (tobitkf.filters.fading) against spec 000 §8.

Oracles: an independent one-run, growing-dimension implementation written from the
source's Table 1 with ``scipy.stats.norm`` (``_reference``), the core Tobit Kalman filter
and Kalman filter on explicitly built (augmented) systems, ``scipy.stats.truncnorm`` and
the erfcx form of the inverse Mills ratio.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import special, stats

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.channels.fading import RiceFading
from tobitkf.filters.fading import (
    FadingKalmanFilter,
    FadingTobitKalmanFilter,
    augmented_measurement_matrix,
    fading_estimators,
    fading_kalman_filter,
    fading_tobit_kalman_filter,
)

MEANS = [0.95, 0.75, 0.85]
VARS = [0.0081, 0.0064, 0.0049]


def oscillator(P0=None):
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(
        A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2) if P0 is None else P0
    )


def data(system, fading, steps=40, runs=3, lower=0.0, seed=0):
    cens = tk.Censoring(lower=lower)
    return tk.simulate(system, steps, runs, censoring=cens, measurement=fading, seed=seed), cens


def _reference(system, thb, lower, y, L, T, *, thv=None, stale=False, exact=False, variance_term=False):
    """One run of Table 1 with the growing augmented state (tall A_k for k < L), written from the paper.

    thb: (L+1, m) mean gains. Uses the standard form P - K Syy K^T of (20').
    Options as in spec §4.6: ``stale`` is (6) with x̂_{j|j-1} (x̂_{0|-1} = x̄_0); ``exact`` the total
    variance gam R(1-psi) + gam(1-gam)(chi + sig lam - I)^2; ``variance_term`` adds gam^2 D_k.
    Returns per-step x̂_{k|k}, P_{k|k}, ŷ_{k|k-1}, K_k (first n rows) and ξ̂_{k|k}.
    """
    n = system.n
    A, Qd, C = system.A.at(0), system.process_cov(0), system.C.at(1)
    sig = np.sqrt(np.diag(system.R.at(1)))
    xi, P = system.x0.copy(), system.P0.copy()
    x_pred_hist = [system.x0.copy()]  # x̂_{j|j-1}, j = 0, 1, ...
    X = [np.outer(system.x0, system.x0) + system.P0]  # X_j = E[x_j x_j^T]
    out = {"x": [], "P": [], "yhat": [], "K": [], "xi": []}
    for k in range(1, T + 1):
        l_prev, l_k = min(L, k - 1), min(L, k)
        Aa = np.zeros((n * (l_k + 1), n * (l_prev + 1)))  # (7): tall while k <= L
        Aa[:n, :n] = A
        for i in range(1, l_k + 1):
            Aa[i * n : (i + 1) * n, (i - 1) * n : i * n] = np.eye(n)
        Ba = np.zeros((n * (l_k + 1), n))
        Ba[:n] = np.eye(n)
        xi = Aa @ xi  # (17)
        P = Aa @ P @ Aa.T + Ba @ Qd @ Ba.T  # (18)
        x_pred_hist.append(xi[:n].copy())
        X.append(A @ X[-1] @ A.T + Qd)
        H = np.hstack([thb[s][:, None] * C for s in range(l_k + 1)])
        chi = H @ xi
        z = (lower - chi) / sig
        lam = stats.norm.pdf(z) / stats.norm.sf(z)  # (14)
        psi = lam * (lam - z)  # (13)
        if stale:
            mu = sum(thb[s] * (C @ x_pred_hist[k - s]) for s in range(l_k + 1))
            gam = stats.norm.cdf((mu - lower) / sig)  # (6) as printed
        else:
            gam = stats.norm.cdf((chi - lower) / sig)  # (6) at the augmented prediction
        yhat = gam * (chi + sig * lam) + (1 - gam) * lower  # (21)
        noise = sig**2 * (1 - psi)  # (25)-(26)
        if exact:
            noise = gam * noise + gam * (1 - gam) * (chi + sig * lam - lower) ** 2
        if variance_term:
            noise = noise + gam**2 * sum(thv[s] * np.diag(C @ X[k - s] @ C.T) for s in range(l_k + 1))
        G = gam[:, None] * H
        Sxy = P @ G.T  # (24)
        Syy = G @ P @ G.T + np.diag(noise)  # (25)
        K = np.linalg.solve(Syy.T, Sxy.T).T  # (23)
        xi = xi + K @ (y[k - 1] - yhat)  # (19)
        P = P - K @ Syy @ K.T  # (20')
        out["x"].append(xi[:n].copy())
        out["P"].append(P[:n, :n].copy())
        out["yhat"].append(yhat)
        out["K"].append(K[:n].copy())
        out["xi"].append(xi.copy())
    return out


# --- exact reductions (spec §8 items 1-5), 1e-10 on the same data --------------------------------------------


@pytest.mark.parametrize("upper", [np.inf, 3.0])
def test_L0_unit_mean_equals_core_tkf(upper):
    # upper < inf: two-sided censoring, a non-source extension that must still reduce to the core TKF
    sys = oscillator()
    fad_data = RiceFading.gaussian(0, [1.0], [0.0])
    cens = tk.Censoring(lower=0.0, upper=upper)
    d = tk.simulate(sys, 40, 4, censoring=cens, measurement=fad_data, seed=0)
    a = FadingTobitKalmanFilter(sys, fad_data, cens).filter(d.y)
    b = tk.TobitKalmanFilter(sys, cens).filter(d.y)
    for f in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=0, atol=1e-10)
    for f in ("p_uncensored", "expected_y"):
        np.testing.assert_allclose(a.extras[f], b.extras[f], rtol=0, atol=1e-10)


@pytest.mark.parametrize("L", [0, 2])
def test_matches_independent_growing_reference_including_k_below_L(L):
    # covers item 1 (L=0: the Allik TKF written independently, incl. ŷ and K) and item 4 (fixed size = growing)
    sys = oscillator()
    fad = RiceFading.gaussian(L, MEANS[: L + 1], VARS[: L + 1])
    d, cens = data(sys, fad, steps=30, runs=2, seed=3)
    out = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, keep_augmented=True)
    n = 2
    for r in range(2):
        ref = _reference(sys, fad.mean_gains(1), 0.0, d.y[r], L, 30)
        np.testing.assert_allclose(out.mean[r], ref["x"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.cov[r], ref["P"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.extras["expected_y"][r], ref["yhat"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.extras["gain"][r, :, :n], ref["K"], rtol=0, atol=1e-10)
        for k in range(1, 31):  # the fixed-size state holds the growing one, padded with exact zeros
            size = n * (min(L, k) + 1)
            np.testing.assert_allclose(out.extras["aug_mean"][r, k - 1, :size], ref["xi"][k - 1], rtol=0, atol=1e-10)
            assert np.all(out.extras["aug_mean"][r, k - 1, size:] == 0.0)
            assert np.all(out.extras["aug_cov"][r, k - 1, size:, :] == 0.0)


@pytest.mark.parametrize(
    "options",
    [
        {"p_uncensored_mode": "eq6_stale"},
        {"exact_tobit_variance": True},
        {"fading_variance_term": True},
        {"p_uncensored_mode": "eq6_stale", "exact_tobit_variance": True, "fading_variance_term": True},
    ],
)
def test_options_match_independent_reference(options):
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=30, runs=2, seed=9)
    out = FadingTobitKalmanFilter(sys, fad, cens, **options).filter(d.y)
    base = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    assert np.abs(out.mean - base.mean).max() > 1e-6  # each option changes the estimates
    for r in range(2):
        ref = _reference(
            sys,
            fad.mean_gains(1),
            0.0,
            d.y[r],
            2,
            30,
            thv=fad.var_gains(1),
            stale=options.get("p_uncensored_mode") == "eq6_stale",
            exact=options.get("exact_tobit_variance", False),
            variance_term=options.get("fading_variance_term", False),
        )
        np.testing.assert_allclose(out.mean[r], ref["x"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.cov[r], ref["P"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.extras["expected_y"][r], ref["yhat"], rtol=0, atol=1e-10)


def test_inputs_and_time_varying_C_reduce_to_core_tkf():
    T = 25
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    Cs = np.stack([[[1.0 + 0.02 * k, 0.1]] for k in range(1, T + 1)])
    sys = tk.LinearSystem(
        A=A, C=Cs, Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2), Bu=[[0.0], [1.0]], D=[[0.3]]
    )
    u = np.random.default_rng(0).normal(size=(3, T, 1))
    fad = RiceFading(0, [1.0])
    cens = tk.Censoring(lower=0.0)
    d = tk.simulate(sys, T, 3, censoring=cens, measurement=fad, inputs=u, seed=4)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, u=u)
    b = tk.TobitKalmanFilter(sys, cens).filter(d.y, u=u)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-10)


def _augmented_system(sys, fad, T):
    """The augmented model (7)-(8) as a plain LinearSystem (square shift A, zero-padded prior)."""
    n, L = sys.n, fad.order
    nxi = n * (L + 1)
    Aa = np.zeros((nxi, nxi))
    Aa[:n, :n] = sys.A.at(0)
    for i in range(1, L + 1):
        Aa[i * n : (i + 1) * n, (i - 1) * n : i * n] = np.eye(n)
    Qa = np.zeros((nxi, nxi))
    Qa[:n, :n] = sys.process_cov(0)
    x0 = np.zeros(nxi)
    x0[:n] = sys.x0
    P0 = np.zeros((nxi, nxi))
    P0[:n, :n] = sys.P0
    Hs = np.stack([augmented_measurement_matrix(sys, fad, k) for k in range(1, T + 1)])
    return tk.LinearSystem(A=Aa, C=Hs, Q=Qa, R=sys.R.at(1), x0=x0, P0=P0)


@pytest.mark.parametrize("lower", [None, -1e6])
def test_no_censoring_equals_augmented_kalman_filter(lower):
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, 0.0)  # no fading variance: the exact optimal KF
    T = 40
    d = tk.simulate(sys, T, 3, measurement=fad, seed=5)
    cens = None if lower is None else tk.Censoring(lower=lower)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    b = tk.KalmanFilter(_augmented_system(sys, fad, T)).filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean[..., :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov[..., :2, :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.extras["p_uncensored"], 1.0, rtol=0, atol=1e-12)


def test_kf_fm_baseline_is_augmented_kf_on_censored_data():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, _ = data(sys, fad, steps=40)
    a = FadingKalmanFilter(sys, fad).filter(d.y)
    b = tk.KalmanFilter(_augmented_system(sys, fad, 40)).filter(d.y)
    np.testing.assert_array_equal(fading_kalman_filter(sys, fad, d.y).mean, a.mean)
    np.testing.assert_allclose(a.mean, b.mean[..., :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov[..., :2, :2], rtol=0, atol=1e-10)


def test_L0_no_censoring_is_kf_with_scaled_C():
    sys = oscillator()
    fad = RiceFading.gaussian(0, [0.8], [0.0])
    d = tk.simulate(sys, 30, 2, measurement=fad, seed=2)
    a = fading_tobit_kalman_filter(sys, fad, None, d.y)
    scaled = tk.LinearSystem(A=sys.A.at(0), C=0.8 * sys.C.at(1), Q=sys.Q.at(0), R=sys.R.at(1), x0=sys.x0, P0=sys.P0)
    b = tk.KalmanFilter(scaled).filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)


def test_L0_general_mean_is_tkf_with_scaled_C():
    sys = oscillator()
    fad = RiceFading.gaussian(0, [0.8], [0.0])
    d, cens = data(sys, fad, runs=3, seed=4)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    scaled = tk.LinearSystem(A=sys.A.at(0), C=0.8 * sys.C.at(1), Q=sys.Q.at(0), R=sys.R.at(1), x0=sys.x0, P0=sys.P0)
    b = tk.TobitKalmanFilter(scaled, cens).filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-10)


def test_zero_delayed_means_equal_L0():
    sys = oscillator()
    fad2 = RiceFading.gaussian(2, [0.95, 0.0, 0.0], [0.0081, 0.0, 0.0])
    fad0 = RiceFading.gaussian(0, [0.95], [0.0081])
    d, cens = data(sys, fad2, runs=3, seed=6)
    a = FadingTobitKalmanFilter(sys, fad2, cens).filter(d.y)
    b = FadingTobitKalmanFilter(sys, fad0, cens).filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-10)
    # the delayed blocks are still smoothed (x̂_{k-1|k} differs from x̂_{k-1|k-1})
    sm = a.extras["smoothed_mean"]
    assert np.abs(sm[:, 1:, 1] - a.mean[:, :-1]).max() > 1e-6


def test_smoothed_blocks_are_fixed_lag_estimates():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, runs=2)
    out = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, keep_augmented=True)
    sm, smc = out.extras["smoothed_mean"], out.extras["smoothed_cov"]
    np.testing.assert_array_equal(sm[:, :, 0], out.mean)
    np.testing.assert_array_equal(smc[:, :, 0], out.cov)
    np.testing.assert_array_equal(smc[:, 5, 2], out.extras["aug_cov"][:, 5, 4:6, 4:6])
    # index k-1 = 0 is k = 1: block 2 would be x_{-1} (undefined); from k = 2 on block 2 is x̂_{k-2|k}
    assert np.isnan(sm[:, 0, 2]).all() and np.isfinite(sm[:, 0, :2]).all() and np.isfinite(sm[:, 1:]).all()
    # at k = 1 block 1 is x̂_{0|1}: a smoothed estimate of x_0, tighter than P_0
    assert np.all(np.trace(smc[:, 0, 1], axis1=-2, axis2=-1) < 2.0)


def test_keep_smoothed_false_changes_nothing_else():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, runs=2)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    b = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, keep_smoothed=False)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.cov, b.cov)
    assert "smoothed_mean" not in b.extras and "smoothed_mean" in a.extras


def test_batched_equals_per_run_and_batch_shape_kept():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, runs=4)
    f = FadingTobitKalmanFilter(sys, fad, cens)
    full = f.filter(d.y)
    for r in range(4):
        one = f.filter(d.y[r])
        assert one.mean.shape == (40, 2)
        np.testing.assert_allclose(one.mean, full.mean[r], rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.cov, full.cov[r], rtol=0, atol=1e-12)
    assert f.filter(d.y.reshape(2, 2, 40, 1)).mean.shape == (2, 2, 40, 2)


def test_joseph_equals_standard_update():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, runs=3)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    b = FadingTobitKalmanFilter(sys, fad, cens, covariance_update="standard").filter(d.y)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-10)


# --- formulas (items 6-7) ------------------------------------------------------------------------------------


def _one_step(chi, sigma=1.3, lower=0.2, P0=0.5, **options):
    """Run one step of a scalar L=0 model whose predicted channel output is ``chi`` (one run per value)."""
    chi = np.atleast_1d(np.asarray(chi, dtype=float))
    sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[sigma**2]], x0=[0.0], P0=[[P0]])
    y = np.full((chi.size, 1, 1), lower + 1.0)
    out = fading_tobit_kalman_filter(
        sys, RiceFading(0, [1.0]), tk.Censoring(lower=lower), y, x0=chi[:, None], keep_augmented=True, **options
    )
    gam = out.extras["p_uncensored"][:, 0, 0]
    noise = out.extras["innovation_cov"][:, 0, 0, 0] - gam**2 * P0
    return out, gam, noise


def test_lemma1_against_truncnorm():
    chi = np.array([-2.0, -0.5, 0.2, 0.7, 1.5, 4.0])
    sigma, lower = 1.3, 0.2
    out, gam, noise = _one_step(chi, sigma, lower)
    a = (lower - chi) / sigma
    tn = stats.truncnorm(a, np.inf, loc=chi, scale=sigma)
    lam = out.extras["inverse_mills"][:, 0, 0]
    np.testing.assert_allclose(chi + sigma * lam, tn.mean(), rtol=1e-10)  # (34)
    np.testing.assert_allclose(noise, tn.var(), rtol=1e-9)  # (12): R(1-psi)
    np.testing.assert_allclose(gam, stats.norm.sf(a), rtol=1e-12)  # (33), (6)
    np.testing.assert_allclose(
        out.extras["expected_y"][:, 0, 0], gam * tn.mean() + (1 - gam) * lower, rtol=1e-10
    )  # (11), (37)


def test_tobit_mean_eq11_against_monte_carlo():
    chi, sigma, lower = 0.7, 1.3, 0.2
    out, _, _ = _one_step(chi, sigma, lower)
    draws = np.maximum(np.random.default_rng(0).normal(chi, sigma, 400_000), lower)
    se = draws.std() / np.sqrt(draws.size)
    assert abs(out.extras["expected_y"][0, 0, 0] - draws.mean()) < 5 * se


def test_eq12_is_not_the_censored_variance_and_exact_option_is():
    # spec §3: chi = 0.7, sigma = 1.3, I = 0.2: true Tobit variance 0.851, (12) gives 0.770
    _, _, paper = _one_step(0.7, 1.3, 0.2)
    _, _, exact = _one_step(0.7, 1.3, 0.2, exact_tobit_variance=True)
    draws = np.maximum(np.random.default_rng(1).normal(0.7, 1.3, 400_000), 0.2)
    np.testing.assert_allclose(paper, 0.770, atol=5e-4)
    np.testing.assert_allclose(exact, 0.851, atol=5e-4)
    assert abs(exact[0] - draws.var()) < 6 * draws.var() * np.sqrt(2 / draws.size) * 2


@pytest.mark.parametrize("z", [8.0, 10.0, 40.0])
def test_inverse_mills_stable_far_in_the_tail(z):
    sigma, lower = 1.0, 0.0
    out, gam, noise = _one_step(lower - z * sigma, sigma, lower)
    lam = out.extras["inverse_mills"][0, 0, 0]
    expected = np.sqrt(2 / np.pi) / special.erfcx(z / np.sqrt(2))  # independent form
    np.testing.assert_allclose(lam, expected, rtol=1e-12)
    assert abs(lam - (z + 1 / z)) < 2 / z**3 + 1e-12
    # 1 - psi = Var of the standardized truncated normal: scipy's truncnorm where it is accurate (z <= 10),
    # the asymptotic series 1/z^2 - 6/z^4 + 50/z^6 + O(z^-8) at z = 40 (next term ~ -500/z^8: rel 1.2e-7)
    if z <= 10:
        np.testing.assert_allclose(noise, stats.truncnorm(z, np.inf).var(), rtol=1e-8)
    else:
        np.testing.assert_allclose(noise, 1 / z**2 - 6 / z**4 + 50 / z**6, rtol=1e-6)
    assert np.all(np.isfinite(out.mean)) and np.all(np.isfinite(out.cov))
    assert 0.0 <= gam[0] < 1e-14


def test_yhat_above_limit_and_probabilities_in_range():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=60, runs=20)
    out = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, keep_augmented=True)
    assert np.all(out.extras["expected_y"] >= 0.0)
    gam = out.extras["p_uncensored"]
    assert np.all((gam >= 0) & (gam <= 1))
    # psi in [0, 1): the noise term R(1 - psi) lies in (0, R]
    G = gam[..., None] * augmented_measurement_matrix(sys, fad, 5)[None, None]
    GPG = np.einsum("ntmi,ntij,ntlj->ntml", G, out.extras["aug_pred_cov"], G)
    noise = (out.extras["innovation_cov"] - GPG)[..., 4:, 0, 0]
    assert np.all(noise > 0) and np.all(noise <= 1.0 + 1e-12)


@settings(max_examples=60, deadline=None)
@given(chi=st.floats(-60, 60), sigma=st.floats(0.05, 20), lower=st.floats(-10, 10))
def test_property_yhat_above_limit_gamma_and_psi_in_range(chi, sigma, lower):
    out, gam, noise = _one_step(chi, sigma, lower)
    yhat = out.extras["expected_y"][0, 0, 0]
    assert yhat >= lower - 1e-12 * max(1.0, abs(lower))  # §4.4: ŷ >= I
    assert 0.0 <= gam[0] <= 1.0
    # 0 <= psi < 1  <=>  0 < R(1 - psi) <= R
    assert 0.0 < noise[0] <= sigma**2 * (1 + 1e-12)
    assert np.isfinite(out.mean).all() and np.isfinite(out.cov).all()


# --- invariants (items 8-9) ----------------------------------------------------------------------------------


def test_covariance_invariants_every_step():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=50, runs=5)
    out = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y, keep_augmented=True)
    Pp, Pf = out.extras["aug_pred_cov"], out.extras["aug_cov"]
    for M in (Pp, Pf):
        assert np.abs(M - np.swapaxes(M, -1, -2)).max() < 1e-12
        tr = np.trace(M, axis1=-2, axis2=-1)
        assert np.all(np.linalg.eigvalsh(M).min(-1) >= -1e-10 * tr)
    assert np.all(np.linalg.eigvalsh(Pp - Pf).min(-1) >= -1e-10)
    assert np.all(np.linalg.eigvalsh(out.extras["innovation_cov"]).min(-1) > 0)
    np.testing.assert_array_equal(Pf[..., :2, :2], out.cov)
    # shift structure: block (i, i) of P_{k|k-1} = block (i-1, i-1) of P_{k-1|k-1}
    for i in (1, 2):
        np.testing.assert_allclose(
            Pp[:, 1:, 2 * i : 2 * i + 2, 2 * i : 2 * i + 2],
            Pf[:, :-1, 2 * i - 2 : 2 * i, 2 * i - 2 : 2 * i],
            rtol=0,
            atol=1e-14,
        )


# --- options: what each one changes --------------------------------------------------------------------------


def test_eq6_stale_equal_at_k1_then_differs_slightly():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=60, runs=200, seed=8)
    a = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y)
    b = FadingTobitKalmanFilter(sys, fad, cens, p_uncensored_mode="eq6_stale").filter(d.y)
    # at k = 1 the stale predictions x̂_{1|0}, x̂_{0|-1} = x̄_0 are the blocks of ξ̂_{1|0}
    np.testing.assert_allclose(a.mean[:, 0], b.mean[:, 0], rtol=0, atol=1e-12)
    assert np.abs(a.extras["p_uncensored"] - b.extras["p_uncensored"]).max() > 1e-4
    ra, rb = tk.metrics.rmse(d.x, a.mean).mean(0), tk.metrics.rmse(d.x, b.mean).mean(0)
    np.testing.assert_allclose(ra, rb, rtol=0.01)  # spec §6: under 0.1 % at M = 1000


def test_fading_variance_term_adds_gamma2_D():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=6, runs=2)
    base = FadingTobitKalmanFilter(sys, fad, cens).filter(d.y[:, :1], keep_augmented=True)
    var = FadingTobitKalmanFilter(sys, fad, cens, fading_variance_term=True).filter(d.y[:, :1], keep_augmented=True)
    # k = 1: D = thvar(0) [C X_1 C^T] + thvar(1) [C X_0 C^T], X_0 = x0 x0^T + P0, X_1 = A X_0 A^T + Q
    A = sys.A.at(0)
    X0 = np.outer(sys.x0, sys.x0) + sys.P0
    X1 = A @ X0 @ A.T + sys.process_cov(0)
    D = VARS[0] * X1[0, 0] + VARS[1] * X0[0, 0]
    gam = base.extras["p_uncensored"][:, 0, 0]
    np.testing.assert_allclose(
        var.extras["innovation_cov"][:, 0, 0, 0] - base.extras["innovation_cov"][:, 0, 0, 0], gam**2 * D, rtol=1e-12
    )
    # with zero fading variance the option changes nothing
    fad0 = RiceFading.gaussian(2, MEANS, 0.0)
    # (both on the numpy path: the option is not compiled, and the kernel equals numpy to rounding only)
    a = FadingTobitKalmanFilter(sys, fad0, cens, backend="numpy").filter(d.y)
    b = FadingTobitKalmanFilter(sys, fad0, cens, fading_variance_term=True, backend="numpy").filter(d.y)
    np.testing.assert_array_equal(a.mean, b.mean)


def test_exact_tobit_variance_changes_nothing_without_censoring():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d = tk.simulate(sys, 30, 2, measurement=fad, seed=1)
    a = fading_tobit_kalman_filter(sys, fad, None, d.y)
    b = fading_tobit_kalman_filter(sys, fad, None, d.y, exact_tobit_variance=True)
    np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-12)


def test_missing_samples_skip_the_update():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    d, cens = data(sys, fad, steps=10, runs=2)
    y = d.y.copy()
    y[:, 3] = np.nan
    out = FadingTobitKalmanFilter(sys, fad, cens).filter(y)
    np.testing.assert_allclose(out.mean[:, 3], out.pred_mean[:, 3], rtol=0, atol=1e-14)
    assert np.isfinite(out.mean).all()


def test_seed_determinism_bitwise():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    a = FadingTobitKalmanFilter(sys, fad, tk.Censoring(lower=0.0)).filter(data(sys, fad, seed=21)[0].y)
    b = FadingTobitKalmanFilter(sys, fad, tk.Censoring(lower=0.0)).filter(data(sys, fad, seed=21)[0].y)
    np.testing.assert_array_equal(a.mean, b.mean)


def test_estimator_set_keys():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    est = fading_estimators(sys, fad, tk.Censoring(lower=0.0))
    assert set(est) == {"tkf-fm", "tkf", "kf", "kf-fm"}
    assert isinstance(est["tkf"], tk.TobitKalmanFilter) and isinstance(est["kf"], tk.KalmanFilter)


# --- bad input ------------------------------------------------------------------------------------------------


def test_bad_input_names_the_argument():
    sys = oscillator()
    fad = RiceFading.gaussian(2, MEANS, VARS)
    cens = tk.Censoring(lower=0.0)
    with pytest.raises(ValidationError, match="p_uncensored_mode"):
        FadingTobitKalmanFilter(sys, fad, cens, p_uncensored_mode="eq6")
    with pytest.raises(ValidationError, match="fading_variance_term"):
        FadingTobitKalmanFilter(sys, fad, cens, fading_variance_term="yes")
    with pytest.raises(ValidationError, match="exact_tobit_variance"):
        fading_tobit_kalman_filter(sys, fad, cens, np.zeros((3, 1)), exact_tobit_variance=None)
    with pytest.raises(ValidationError, match="covariance_update"):
        FadingKalmanFilter(sys, fad, covariance_update="fast")
    with pytest.raises(ValidationError, match="fading"):
        FadingTobitKalmanFilter(sys, [1.0, 0.5], cens)
    with pytest.raises(ValidationError, match="system"):
        FadingTobitKalmanFilter("sys", fad, cens)
    with pytest.raises(ValidationError, match="censoring"):
        FadingTobitKalmanFilter(sys, fad, (0.0,))
    with pytest.raises(tk.ShapeError, match="coefficients"):
        FadingTobitKalmanFilter(sys, RiceFading(0, tk.channels.laws.Gaussian([[1.0, 1.0]], 0.0)), cens)
    with pytest.raises(ValidationError, match="R"):
        sys2 = tk.LinearSystem(
            A=np.eye(2), C=np.eye(2), Q=np.eye(2), R=[[1.0, 0.5], [0.5, 1.0]], x0=[0, 0], P0=np.eye(2)
        )
        FadingTobitKalmanFilter(sys2, RiceFading(0, [1.0]), None)
    with pytest.raises(ValidationError, match="y"):
        FadingTobitKalmanFilter(sys, fad, cens).filter(-np.ones((5, 1)))
    with pytest.raises(tk.ShapeError, match="y"):
        FadingTobitKalmanFilter(sys, fad, cens).filter(np.ones(5))
    with pytest.raises(TypeError):
        FadingTobitKalmanFilter(sys, fad, cens, joseph=True)
