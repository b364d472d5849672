"""The calibrated test of "the MSE lies above a lower bound at every step" (tobitkf.design.pcrlb.bound_test) and
the particle filter's convergence check with its Monte Carlo error (experiments._optimum.convergence),
on synthetic data where the truth is known."""

from __future__ import annotations

import numpy as np
from scipy import stats

from tobitkf.design.pcrlb import bound_test
from tobitkf.experiments._optimum import convergence


def _errors(rng, reps, N, T, n, rho, scale):
    """Gaussian errors (reps, N, T, n), AR(1) over steps with correlation rho, variance ``scale`` (T, n)."""
    e = np.empty((reps, N, T, n))
    e[:, :, 0] = rng.standard_normal((reps, N, n))
    for k in range(1, T):
        e[:, :, k] = rho * e[:, :, k - 1] + np.sqrt(1 - rho * rho) * rng.standard_normal((reps, N, n))
    return e * np.sqrt(scale)


def test_bound_test_is_calibrated_when_the_mse_equals_the_bound():
    """Null at its boundary (MSE = bound at every step), steps strongly dependent: the family-wise verdict
    rejects at most its 1 % level (binomial tolerance over the repetitions), and the per-step p-values at
    most their level over all steps (the naive normal test does not: it rejects about 2.5 % at 1 %)."""
    rng = np.random.default_rng(0)
    reps, N, T, n = 400, 200, 50, 2
    B = np.linspace(0.5, 2.0, T * n).reshape(T, n)
    fails, p_small, naive = 0, 0, 0
    for chunk in range(4):
        e = _errors(rng, reps // 4, N, T, n, 0.9, B)
        for r in range(reps // 4):
            t = bound_test(e[r] ** 2, B, 0.01)
            fails += not t["holds"]
            p_small += int((t["p"] < 0.01).sum())
            naive += t["naive_steps_rejected"]
    tol = stats.binom.ppf(0.999, reps, 0.01)  # 99.9 % point of the count if the level were exact
    assert fails <= tol
    assert p_small / (reps * T * n) <= 0.01
    assert naive / (reps * T) > 0.015  # what the verdict was before: an uncorrected per-step 1 % test


def test_bound_test_detects_a_bound_above_the_mse():
    rng = np.random.default_rng(1)
    T, n = 40, 2
    e = _errors(rng, 1, 200, T, n, 0.5, np.ones((T, n)))[0]
    B = np.ones((T, n))
    B[10, 1] = 1.8  # one step where the "bound" is 80 % above the true MSE
    t = bound_test(e**2, B, 0.01)
    assert not t["holds"] and t["rejected"][10, 1] and t["steps_rejected"] == 1
    t2 = bound_test(e**2, np.full((T, n), 1.15), 0.01)  # 15 % too high everywhere: the time average sees it
    assert t2["mean_ratio_p"] < 1e-3 and t2["mean_ratio"] < 0.9
    assert bound_test(e**2, np.full((T, n), 0.5), 0.01)["holds"]


def test_convergence_error_matches_the_spread_of_the_change():
    """Two filters of the same error law (no change on doubling): the jackknife standard error of the
    relative change equals its spread over repetitions (to the sampling error of 300 repetitions), the
    check says converged; a real 2 % change with a small error is refused."""
    rng = np.random.default_rng(2)
    reps, N, T, n = 300, 100, 30, 1
    common = _errors(rng, reps, N, T, n, 0.8, np.ones((T, n)))
    own = [_errors(rng, reps, N, T, n, 0.8, np.full((T, n), 0.05)) for _ in range(2)]
    cs, ses, conv = [], [], 0
    for r in range(reps):
        out = convergence((common[r] + own[0][r]) ** 2, (common[r] + own[1][r]) ** 2)
        cs.append(out["signed_change"][0])
        ses.append(out["stderr"][0])
        conv += out["converged"]
    sd = np.std(cs, ddof=1)
    rel = 1 / np.sqrt(2 * (reps - 1))  # relative sampling error of a standard deviation
    assert abs(np.median(ses) / sd - 1) < 4 * rel + 0.05
    assert conv >= reps * 0.98
    c = _errors(rng, 1, N, T, n, 0.8, np.ones((T, n)))[0]
    o = _errors(rng, 2, N, T, n, 0.8, np.full((T, n), 0.0005))  # particle noise of 2 % in standard deviation
    shifted = convergence((1.02 * (c + o[0])) ** 2, (c + o[1]) ** 2)
    assert shifted["resolved"] and not shifted["converged"]
    assert abs(shifted["signed_change"][0] - 0.02) < 5 * shifted["stderr"][0] + 1e-12


def test_bound_test_is_calibrated_with_few_runs():
    """12 runs (the default suite's experiment size): without the B^2 floor on the plug-in second moment a
    nominal 1 % per step rejects 4.6 % of true nulls; with it, at most the level."""
    rng = np.random.default_rng(3)
    reps, N, T, n = 2000, 12, 25, 1
    B = np.ones((T, n))
    e = _errors(rng, reps, N, T, n, 0.9, B)
    p = np.stack([bound_test(e[r] ** 2, B, 0.01)["p"] for r in range(reps)])
    holds = [bound_test(e[r] ** 2, B, 0.01)["holds"] for r in range(reps)]
    assert (p < 0.01).mean() <= 0.01
    assert reps - sum(holds) <= stats.binom.ppf(0.999, reps, 0.01)
