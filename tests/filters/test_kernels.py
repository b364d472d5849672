"""The numba kernels of the KF and TKF against the numpy reference paths and censored_moments.

The numpy path is the reference (it is what the rest of the test-suite checks against
the sources); the kernel must reproduce it to rounding (1e-12) in every case it
covers, and the dispatcher must send every other case to numpy.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.censored import censored_moments
from tobitkf.filters import _backend
from tobitkf.filters import kalman as kalman_module
from tobitkf.filters.kalman import kalman_filter
from tobitkf.filters.tobit import tobit_kalman_filter

pytest.importorskip("numba")
from tobitkf.filters import _compiled_block, _compiled_censored, _compiled_tobit  # noqa: E402

VECTORS = Path("/work/shared/vectors/censoring_stats.json")
FIELDS = ("mean", "cov", "pred_mean", "pred_cov")


def kernel_moments(mu, sd, lo, hi):
    arrs = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (mu, sd, lo, hi)))
    flat = [np.ascontiguousarray(a.ravel()) for a in arrs]
    return _compiled_censored.censored_moments_array(*flat, _compiled_tobit.GL_X, _compiled_tobit.GL_W)


def assert_same(a, b, rtol=1e-12):
    """Equal to rounding: relative to each array's scale (entries may be tiny or zero)."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    scale = max(1.0, float(np.max(np.abs(b))))
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


def assert_results_equal(r1, r2, rtol=1e-12):
    for f in FIELDS:
        assert_same(getattr(r1, f), getattr(r2, f), rtol)
    assert r1.extras.keys() == r2.extras.keys()
    for key in r1.extras:
        assert_same(r1.extras[key], r2.extras[key], rtol)


def oscillator(m=1, r=0.1):
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    C = [[1.0, 0.0]] if m == 1 else [[1.0, 0.0], [0.4, 1.0]]
    R = np.diag([r] * m)
    return tk.LinearSystem(A=A, C=C, Q=0.01 * np.eye(2), R=R, x0=[0.3, 0.0], P0=0.05 * np.eye(2))


def three_state():
    A = [[0.9, 0.1, 0.0], [0.0, 0.95, 0.2], [0.05, 0.0, 0.8]]
    C = [[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]]
    return tk.LinearSystem(
        A=A, C=C, Q=0.02 * np.eye(3), R=np.diag([0.05, 0.2]), x0=[0.5, 0.0, -0.2], P0=0.1 * np.eye(3)
    )


def data(system, cens, runs=6, steps=150, seed=0):
    return tk.simulate(system, steps, runs, censoring=cens, seed=seed).y


# --- censored-normal statistics -------------------------------------------------------------


def test_stats_match_censored_moments_random():
    rng = np.random.default_rng(0)
    k = 4000
    mu = rng.normal(0, 3, k)
    sd = np.exp(rng.normal(0, 1, k))
    lo = np.where(rng.random(k) < 0.3, -np.inf, rng.normal(-1, 2, k))
    hi = np.where(rng.random(k) < 0.3, np.inf, lo + np.abs(rng.normal(0, 3, k)) + 1e-3)
    hi = np.where(np.isinf(lo) & np.isinf(hi), 0.5, hi)
    ref = censored_moments(mu, sd, lo, hi)
    got = kernel_moments(mu, sd, lo, hi)
    # both evaluate the same formulas; the direct formulas lose up to ~400 ulp near the
    # switch to quadrature (cancellation in 1 + (a phi(a) - b phi(b))/gamma - lambda^2)
    scale = np.maximum(np.maximum(np.abs(mu), sd), 1.0)
    for i, name in enumerate(ref._fields):
        np.testing.assert_allclose(
            got[i], ref[i], rtol=1e-11, atol=1e-13 * scale.max() if i > 2 else 1e-300, err_msg=name
        )


@pytest.mark.parametrize("dist", [4.5, 40.0, 1000.0])
@pytest.mark.parametrize("kind", ["left", "right", "two_sided", "narrow"])
def test_stats_match_in_the_tails(dist, kind):
    """Limits dist standard deviations away on the censored side: the continued-fraction route (one-sided)
    and the quadrature (two-sided, narrow)."""
    sd = np.array([0.05, 1.0, 3.0])
    mu = np.array([0.0, -2.0, 7.0])
    if kind == "left":  # mean far below a lower limit: almost always censored
        lo, hi = mu + dist * sd, np.full(3, np.inf)
    elif kind == "right":
        lo, hi = np.full(3, -np.inf), mu - dist * sd
    elif kind == "two_sided":
        lo, hi = mu - (dist + 2.0) * sd, mu - dist * sd
    else:  # narrow window straddling the mean, and far away
        lo, hi = mu + (dist - 0.25) * sd * (dist > 5), mu + (dist + 0.25) * sd * (dist > 5) + 0.5 * sd
    ref = censored_moments(mu, sd, lo, hi)
    got = kernel_moments(mu, sd, lo, hi)
    for i, name in enumerate(ref._fields):
        scale = max(1.0, float(np.max(np.abs(ref[i]))))
        np.testing.assert_allclose(got[i], ref[i], rtol=1e-12, atol=1e-14 * scale, err_msg=name)
        assert np.all(np.isfinite(got[i]))


def test_stats_quadrature_dense_grid():
    """The tail routes (the quadrature with the kernel's own vectorised exp for two-sided and narrow
    windows, the continued fraction for one-sided ones) over a dense grid of tail depths and widths."""
    a = np.geomspace(4.01, 1e3, 150)  # beyond _TAIL = 4: the quadrature branch
    w = np.geomspace(1e-3, 50.0, 150)
    A, W = (v.ravel() for v in np.meshgrid(a, w))
    mu, sd = np.zeros(A.size), np.ones(A.size)
    for lo, hi in ((A, A + W), (-A - W, -A), (A, np.full(A.size, np.inf)), (W - 0.9, W - 0.4)):
        ref = censored_moments(mu, sd, lo, hi)
        got = kernel_moments(mu, sd, lo, hi)
        # p_uncensored = exp(-a^2/2 - log sqrt(2 pi) + log I0): one ulp of an argument near -745
        # is 1.1e-13 relative in the result, whichever exp computes it
        for i, rtol in ((2, 2.5e-13), (3, 2e-14), (5, 2e-14)):
            np.testing.assert_allclose(got[i], ref[i], rtol=rtol, atol=0, err_msg=ref._fields[i])


def test_stats_one_sided_route_equals_numpy():
    """The continued-fraction route (one-sided windows beyond 4 sigma, left and right, out to 1e5 sigma,
    and two-sided ones whose far limit is negligible) and its switches: kernel == censored_moments."""
    x = np.concatenate([np.geomspace(3.5, 1e5, 400), [4.0 - 1e-12, 4.0, 4.0 + 1e-12, 40.0, 40.0 + 1e-9]])
    far = np.sqrt(100.0 + x * x)
    mu, sd = np.full(x.size, 0.7), np.full(x.size, 0.2)
    for lo, hi in ((x, np.inf), (-np.inf, -x), (x, far + 1e-9), (x, far - 1e-9), (-far - 1e-9, -x)):
        lo_, hi_ = (np.broadcast_to(v, x.shape) for v in (lo, hi))
        lo_, hi_ = mu + sd * lo_, mu + sd * hi_
        ref = censored_moments(mu, sd, lo_, hi_)
        got = kernel_moments(mu, sd, lo_, hi_)
        for i, name in enumerate(ref._fields):
            # (at or below 4 the reference takes the direct formulas, whose variance 1 + a lambda - lambda^2
            # cancels: its own error reaches ~1e-12 there, where the compiled tail fit stays within 2e-14 of
            # the converged continued fraction, tests/filters/test_kernels_censored.py)
            # (the tail probabilities: the reference's ndtr and exp lose ~x^2 eps relative far in a
            # tail, 1.8e-13 at 37 sigma, the compiled routes 6e-14: measured against 50-digit values; the
            # censored variance of a far window is gamma times a variance)
            cf = x > 4.0
            rtol = 3e-13 if name in ("p_lower", "p_upper", "p_uncensored", "censored_var") else 1e-13
            np.testing.assert_allclose(got[i][cf], ref[i][cf], rtol=rtol, atol=1e-300, err_msg=name)
            np.testing.assert_allclose(got[i], ref[i], rtol=1.5e-12, atol=1e-300, err_msg=name)
            assert np.all(np.isfinite(got[i]))


def test_stats_against_60_digit_vectors():
    """No less accurate than censored_moments on the mpmath vectors (shared/vectors)."""
    if not VECTORS.exists():
        pytest.skip("shared vectors not available")
    cases = json.loads(VECTORS.read_text())["cases"]
    keys = (
        "p_lower",
        "p_upper",
        "p_uncensored",
        "inverse_mills",
        "truncated_mean",
        "truncated_variance",
        "censored_mean",
        "censored_variance",
    )
    mu, sd, lo, hi = (np.array([float(c[k]) for c in cases]) for k in ("mu", "sigma", "lower", "upper"))
    exact = np.array([[float(c[k]) for c in cases] for k in keys])
    ref = np.array(censored_moments(mu, sd, lo, hi))
    got = kernel_moments(mu, sd, lo, hi)
    scale = np.maximum(np.abs(exact), 1e-300)
    err_ref = np.abs(ref - exact) / scale
    err_got = np.abs(got - exact) / scale
    # (where the exact value is 0 both return tiny non-zeros such as 6e-64: compared relatively)
    slack = err_ref * 1e-9 + 1e-12 * (1 + np.abs(mu) / sd)
    assert np.all(err_got <= err_ref + slack), np.argwhere(err_got > err_ref + slack)[:5]


@settings(max_examples=60, deadline=None)
@given(
    mu=st.floats(-1e3, 1e3),
    sd=st.floats(1e-3, 1e2),
    lo=st.floats(-50, 50),
    width=st.floats(1e-3, 100),
    sides=st.sampled_from(["left", "right", "both"]),
)
def test_stats_property(mu, sd, lo, width, sides):
    lo_, hi_ = lo * sd + mu, (lo + width) * sd + mu
    if sides == "left":
        hi_ = np.inf
    elif sides == "right":
        lo_ = -np.inf
    if not lo_ < hi_:
        return
    ref = np.array(censored_moments(mu, sd, lo_, hi_)).ravel()
    got = kernel_moments(mu, sd, lo_, hi_).ravel()
    lim = max(abs(v) for v in (lo_, hi_) if np.isfinite(v))
    loc = abs(mu) + sd + lim  # scale of the means; its square of the variances
    scale = np.array([1.0, 1.0, 1.0, 1.0 + lim / sd, loc, loc * loc, loc, loc * loc])
    assert np.all(np.abs(got - ref) <= 1e-10 * np.abs(ref) + 1e-12 * scale), (got, ref)


# --- the Tobit Kalman filter ------------------------------------------------------------------

TKF_CASES = {
    "left": tk.Censoring(lower=0.0),
    "right": tk.Censoring(upper=0.1),
    "two_sided": tk.Censoring(lower=-0.4, upper=0.5),
    "none": tk.Censoring(),
}


@pytest.mark.parametrize("noise_term", tk.filters.tobit.NOISE_TERMS)
@pytest.mark.parametrize("case", sorted(TKF_CASES))
def test_tkf_kernel_equals_numpy(case, noise_term):
    sys_ = oscillator()
    cens = TKF_CASES[case]
    y = data(sys_, cens)
    a = tobit_kalman_filter(sys_, cens, y, noise_term=noise_term, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, noise_term=noise_term, backend="numpy")
    assert_results_equal(a, b)


def test_tkf_kernel_time_varying_limits_and_two_channels():
    sys_ = three_state()
    T = 50
    k = np.arange(T)
    lo = np.stack([0.1 * np.sin(0.2 * k) - 0.1, np.full(T, -np.inf)], axis=1)
    hi = np.stack([np.full(T, np.inf), 0.3 + 0.05 * np.cos(0.3 * k)], axis=1)
    cens = tk.Censoring(lower=lo, upper=hi)
    y = data(sys_, cens, runs=5, steps=T, seed=3)
    for cu in ("standard", "joseph"):
        for nt in tk.filters.tobit.NOISE_TERMS:
            a = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numba")
            b = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numpy")
            assert_results_equal(a, b)


def test_tkf_kernel_joseph_nan_batch_shape_and_single_run():
    sys_ = oscillator(m=2)
    cens = tk.Censoring(lower=[0.0, -0.2], upper=[np.inf, 0.4])
    y = data(sys_, cens, runs=6, steps=40, seed=1)
    y[np.random.default_rng(2).random(y.shape) < 0.15] = np.nan  # missing samples
    y = y.reshape(2, 3, 40, 2)  # batch shape (2, 3)
    for cu in ("standard", "joseph"):
        a = tobit_kalman_filter(sys_, cens, y, covariance_update=cu, backend="numba")
        b = tobit_kalman_filter(sys_, cens, y, covariance_update=cu, backend="numpy")
        assert a.mean.shape == (2, 3, 40, 2) and a.cov.shape == (2, 3, 40, 2, 2)
        assert_results_equal(a, b)
    one = y[1, 2]
    a = tobit_kalman_filter(sys_, cens, one, backend="numba")
    b = tobit_kalman_filter(sys_, cens, one, backend="numpy")
    assert a.mean.shape == (40, 2)
    assert_results_equal(a, b)
    # batched == per run
    c = tobit_kalman_filter(sys_, cens, y, backend="numba")
    assert_same(c.mean[1, 2], a.mean, 1e-15)


@pytest.mark.parametrize("dist", [40.0, 1000.0])
def test_tkf_kernel_limits_far_in_the_tails(dist):
    """Lower limit far above the state: every reading censored, gamma underflows; and far below."""
    sys_ = oscillator()
    sd = np.sqrt(0.1)
    for lower in (dist * sd, -dist * sd):
        cens = tk.Censoring(lower=lower)
        y = cens.clip(data(sys_, tk.Censoring(), runs=4, steps=30))
        for nt in tk.filters.tobit.NOISE_TERMS:
            a = tobit_kalman_filter(sys_, cens, y, noise_term=nt, backend="numba")
            b = tobit_kalman_filter(sys_, cens, y, noise_term=nt, backend="numpy")
            assert_results_equal(a, b)
            assert np.all(np.isfinite(a.mean))


def test_tkf_kernel_per_run_prior():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    y = data(sys_, cens, runs=4, steps=30)
    x0 = np.random.default_rng(5).normal(size=(4, 2))
    P0 = np.array([np.eye(2) * s for s in (0.01, 0.1, 1.0, 2.0)])
    a = tobit_kalman_filter(sys_, cens, y, x0=x0, P0=P0, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, x0=x0, P0=P0, backend="numpy")
    assert_results_equal(a, b)


def test_tkf_kernel_many_runs_crosses_blocks():
    """More runs than one block of the kernel, not a multiple of it."""
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    y = data(sys_, cens, runs=2 * _compiled_block.runs_per_block(2) + 5, steps=20)
    a = tk.TobitKalmanFilter(sys_, cens, backend="numba").filter(y)
    b = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y)
    assert_results_equal(a, b)


def test_tkf_subnormal_channel_is_skipped_in_both_paths():
    """A channel 38 sigma into its censored side: gamma ~ 1e-315, R_ee ~ 1e-319 (subnormal).

    Before gain_update treated a subnormal R_ee as 0 the numpy path returned NaN here
    (LAPACK's reciprocal pivot overflows). Both paths now drop the channel, which
    carries no information: the update equals the one-channel TKF on channel 0."""
    sys2 = tk.LinearSystem(
        A=np.eye(2),
        C=[[1.0, 0.0], [0.3, 1.0]],
        Q=np.zeros((2, 2)),
        R=np.diag([0.1, 0.2]),
        x0=[3.8, -18.4],
        P0=[[0.044, -0.033], [-0.033, 0.233]],
    )
    cens = tk.Censoring(lower=[0.0, -0.3], upper=[np.inf, 0.5])
    y = np.array([[[0.19, -0.3]]])
    sys1 = tk.LinearSystem(
        A=np.eye(2),
        C=[[1.0, 0.0]],
        Q=np.zeros((2, 2)),
        R=[[0.1]],
        x0=[3.8, -18.4],
        P0=[[0.044, -0.033], [-0.033, 0.233]],
    )
    one = tobit_kalman_filter(sys1, tk.Censoring(lower=0.0), y[..., :1], noise_term="total_variance", backend="numpy")
    for be in ("numpy", "numba"):
        out = tobit_kalman_filter(sys2, cens, y, noise_term="total_variance", backend=be)
        assert out.extras["p_uncensored"][0, 0, 1] < 1e-300
        assert_same(out.mean, one.mean, 1e-14)
        assert_same(out.cov, one.cov, 1e-14)


@pytest.mark.parametrize("seed", range(12))
def test_tkf_kernel_random_systems(seed):
    """Random stable systems, n, m in 1..3, random one/two-sided limits, NaN samples."""
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 4, size=2)
    A = rng.normal(size=(n, n))
    A *= 0.95 / max(1e-9, np.max(np.abs(np.linalg.eigvals(A))))
    sys_ = tk.LinearSystem(
        A=A,
        C=rng.normal(size=(m, n)),
        Q=np.diag(rng.uniform(0.01, 0.1, n)),
        R=np.diag(rng.uniform(0.05, 0.5, m)),
        x0=rng.normal(size=n),
        P0=np.eye(n) * rng.uniform(0.1, 1.0),
    )
    lo = np.where(rng.random(m) < 0.5, -np.inf, rng.normal(0, 0.5, m))
    hi = np.where(rng.random(m) < 0.5, np.inf, np.where(np.isfinite(lo), lo, -0.5) + rng.uniform(0.5, 2, m))
    cens = tk.Censoring(lower=lo, upper=hi)
    y = data(sys_, cens, runs=4, steps=60, seed=seed)
    y[rng.random(y.shape) < 0.05] = np.nan
    # not "total_variance": on 4 of these 12 systems it diverges (|x| up to 1e88 in 60 steps: a
    # reading uncensored while the prior mean sits deep in the censored tail meets a gain
    # ~ a^2 / sigma^2), and after that the two paths agree only in that both blow up.
    # 5e-12: the two paths compute Phi differently (scipy's ndtr; the compiled erfcx fits), so a window's
    # truncated variance, whose direct formula cancels, differs by up to ~1e-13 (either may be the closer
    # to 60-digit values), and the filter carries that through the steps (seed 5: 2.3e-12 in gamma)
    for nt in ("dissertation", "exact_pv"):
        for cu in ("standard", "joseph"):
            a = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numba")
            b = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numpy")
            assert np.all(np.isfinite(b.mean))
            assert_results_equal(a, b, rtol=5e-12)


def test_tkf_kernel_threads_give_the_same_results():
    """The kernels release the GIL; concurrent calls must not share scratch state."""
    from concurrent.futures import ThreadPoolExecutor

    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    ys = [data(sys_, cens, runs=40, steps=150, seed=s) for s in range(4)]
    serial = [tobit_kalman_filter(sys_, cens, y, backend="numba").mean for y in ys]
    with ThreadPoolExecutor(max_workers=4) as pool:
        threaded = list(pool.map(lambda y: tobit_kalman_filter(sys_, cens, y, backend="numba").mean, ys))
    for a, b in zip(threaded, serial):
        np.testing.assert_array_equal(a, b)


# --- the Kalman filter -------------------------------------------------------------------------


@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_kf_kernel_equals_numpy(cu):
    sys_ = three_state()
    y = data(sys_, tk.Censoring(), runs=2 * _compiled_block.runs_per_block(3) + 3, steps=2 * _compiled_block.CHUNK + 7)
    a = kalman_filter(sys_, y, covariance_update=cu, backend="numba")
    b = kalman_filter(sys_, y, covariance_update=cu, backend="numpy")
    assert_results_equal(a, b)
    assert not a.cov.flags.writeable  # shared covariance returned as a broadcast view, as numpy
    ynan = y.copy()
    ynan[np.random.default_rng(1).random(y.shape) < 0.2] = np.nan
    a = kalman_filter(sys_, ynan, covariance_update=cu, backend="numba")
    b = kalman_filter(sys_, ynan, covariance_update=cu, backend="numpy")
    assert_results_equal(a, b)
    a = kalman_filter(sys_, y[0], covariance_update=cu, x0=[1.0, 2.0, 3.0], backend="numba")
    b = kalman_filter(sys_, y[0], covariance_update=cu, x0=[1.0, 2.0, 3.0], backend="numpy")
    assert_results_equal(a, b)


def test_kf_kernel_per_run_prior_and_dropping_filter():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    y = data(sys_, cens, runs=5, steps=50)
    x0 = np.random.default_rng(6).normal(size=(5, 2))
    a = kalman_filter(sys_, y, x0=x0, backend="numba")
    b = kalman_filter(sys_, y, x0=x0, backend="numpy")
    assert_results_equal(a, b)
    skip = np.any(cens.censored_mask(y), axis=0)
    a = kalman_filter(sys_, y, skip=skip, backend="numba")
    b = kalman_filter(sys_, y, skip=skip, backend="numpy")
    assert_results_equal(a, b)
    drop = tk.DroppingKalmanFilter(sys_, cens).filter(y)  # "auto": the kernel
    assert_same(drop.mean, b.mean)


def test_kf_kernel_degenerate_channel_is_skipped():
    """R = 0 and P0 = 0 on the measured direction: Ree = 0 at the first step, no update (as numpy)."""
    sys_ = tk.LinearSystem(
        A=np.eye(2), C=[[1.0, 0.0]], Q=np.diag([0.0, 0.1]), R=[[0.0]], x0=[0.0, 0.0], P0=np.diag([0.0, 1.0])
    )
    y = np.random.default_rng(0).normal(size=(3, 5, 1))
    a = kalman_filter(sys_, y, backend="numba")
    b = kalman_filter(sys_, y, backend="numpy")
    assert_results_equal(a, b)
    assert np.all(a.mean == 0.0)


def test_kf_kernel_singular_innovation_covariance_raises_like_numpy():
    """Two identical noise-free channels: R_ee singular with a positive diagonal."""
    sys_ = tk.LinearSystem(
        A=np.eye(2), C=[[1.0, 0.0], [1.0, 0.0]], Q=0.1 * np.eye(2), R=np.zeros((2, 2)), x0=[0.0, 0.0], P0=np.eye(2)
    )
    y = np.zeros((2, 3, 2))
    for be in ("numpy", "numba"):
        with pytest.raises(np.linalg.LinAlgError, match="Singular matrix"):
            kalman_filter(sys_, y, backend=be)


# --- dispatch -----------------------------------------------------------------------------------


class _Trap:
    """Stands in for the kernel module: any use of a kernel fails the test."""

    NOISE_CODES = _compiled_tobit.NOISE_CODES
    GL_X, GL_W = _compiled_tobit.GL_X, _compiled_tobit.GL_W

    def __getattr__(self, name):
        raise AssertionError(f"kernel {name} used")


def test_auto_uses_the_kernel_when_covered(monkeypatch):
    monkeypatch.setattr(_backend, "_load", lambda: _Trap())
    monkeypatch.setattr(kalman_module, "_load_entries", lambda: _Trap())
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    y = data(sys_, cens, runs=2, steps=5)
    with pytest.raises(AssertionError, match="kernel tobit_loop used"):
        tk.TobitKalmanFilter(sys_, cens).filter(y)
    with pytest.raises(AssertionError, match="kernel kalman_entry used"):  # its choice of the vectorised step
        tk.KalmanFilter(sys_).filter(y)
    tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y)  # numpy never touches it


def _time_varying():
    sys_ = oscillator()
    A = np.stack([sys_.transition(0)] * 20)
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.3, 0.0], P0=0.05 * np.eye(2))


def _with_input(**inputs):
    """The oscillator with a control input (default B^u = [0.1, 0]^T; ``inputs`` give Bu and/or D)."""
    return tk.LinearSystem(
        A=oscillator().transition(0),
        C=[[1.0, 0.0]],
        Q=0.01 * np.eye(2),
        R=[[0.1]],
        x0=[0.3, 0.0],
        P0=0.05 * np.eye(2),
        **({"Bu": [[0.1], [0.0]]} | inputs),
    )


@pytest.mark.parametrize("which", ["time_varying", "input"])
def test_uncovered_cases_fall_back_to_numpy(which, monkeypatch):
    cens = tk.Censoring(lower=0.0)
    if which == "time_varying":
        sys_, u, match = _time_varying(), None, "time-varying"
    else:
        sys_, u, match = _with_input(), np.ones((20, 1)), "control inputs"
    y = data(oscillator(), cens, runs=2, steps=20)
    ref_t = tobit_kalman_filter(sys_, cens, y, u=u, backend="numpy")
    ref_k = kalman_filter(sys_, y, u=u, backend="numpy")
    if which == "time_varying":  # the TKF kernel covers control inputs (test_tkf_kernel_with_inputs_equals_numpy)
        with pytest.raises(
            ValidationError, match=f"backend: the compiled path of the Tobit Kalman filter does not cover {match}"
        ):
            tobit_kalman_filter(sys_, cens, y, u=u, backend="numba")
    with pytest.raises(ValidationError, match=f"does not cover {match}"):
        kalman_filter(sys_, y, u=u, backend="numba")
    monkeypatch.setattr(_backend, "_load", lambda: _Trap())
    monkeypatch.setattr(kalman_module, "_load_entries", lambda: _Trap())
    # not the block kernel (the trap), but the compiled shared step around the numpy moments: equal to rounding
    if which == "time_varying":
        assert_results_equal(tobit_kalman_filter(sys_, cens, y, u=u), ref_t, 1e-12)
    else:
        with pytest.raises(AssertionError, match="kernel tobit_loop used"):
            tobit_kalman_filter(sys_, cens, y, u=u)
    assert_results_equal(kalman_filter(sys_, y, u=u), ref_k, 1e-12)


@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_tkf_kernel_with_inputs_equals_numpy(cu):
    """Control inputs through B^u (predict) and D (feedthrough of the latent mean), per run, online too;
    an input matrix indexed by k is refused by backend='numba' and runs on numpy under 'auto'."""
    sys_ = _with_input(Bu=[[0.1], [0.05]], D=[[0.2]])
    cens = tk.Censoring(lower=0.0, upper=1.2)
    u = np.random.default_rng(2).normal(size=(5, 40, 1))
    y = cens.clip(data(oscillator(), tk.Censoring(), runs=5, steps=40) + 0.2 * u)
    y[1, 3:6] = np.nan
    a = tobit_kalman_filter(sys_, cens, y, u=u, covariance_update=cu, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, u=u, covariance_update=cu, backend="numpy")
    assert_results_equal(a, b)
    fast, ref = tk.TobitKalmanFilter(sys_, cens, backend="numba"), tk.TobitKalmanFilter(sys_, cens, backend="numpy")
    sa, sb = fast.init((5,)), ref.init((5,))
    for k in range(10):
        sa, sb = fast.step(sa, y[:, k], u=u[:, k]), ref.step(sb, y[:, k], u=u[:, k])
    assert_same(sa.x, sb.x)
    assert_same(sa.x, b.mean[:, 9])
    varying = _with_input(Bu=np.stack([[[0.1], [0.05]]] * 40))
    with pytest.raises(ValidationError, match="does not cover time-varying input matrices"):
        tobit_kalman_filter(varying, cens, y, u=u, backend="numba")
    assert_results_equal(
        tobit_kalman_filter(varying, cens, y, u=u), tobit_kalman_filter(varying, cens, y, u=u, backend="numpy")
    )


def test_without_numba(monkeypatch):
    monkeypatch.setattr(_backend, "_load", lambda: None)
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    y = data(sys_, cens, runs=2, steps=10)
    assert not _backend.numba_available()
    with pytest.raises(ImportError, match="backend='numba' needs the numba package"):
        tk.TobitKalmanFilter(sys_, cens, backend="numba").filter(y)
    with pytest.raises(ImportError, match="needs the numba package"):
        tk.KalmanFilter(sys_, backend="numba").filter(y)
    auto = tk.TobitKalmanFilter(sys_, cens).filter(y)  # auto runs numpy
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y)
    assert_results_equal(auto, ref, 0.0)


def test_backend_option_is_checked():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    with pytest.raises(ValidationError, match="backend: expected one of 'auto', 'numpy', 'numba', got 'cuda'"):
        tk.TobitKalmanFilter(sys_, cens, backend="cuda")
    with pytest.raises(ValidationError, match="backend: expected one of"):
        tk.KalmanFilter(sys_, backend="jax")
    with pytest.raises(ValidationError, match="backend: expected one of"):
        tobit_kalman_filter(sys_, cens, np.zeros((3, 1)), backend="NUMBA")


def test_threaded_kernel_is_bit_identical_to_one_thread():
    """Runs are independent and the kernel releases the GIL: any split gives the same bits."""
    pytest.importorskip("numba")
    import tobitkf as tk

    w = 0.05
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]],
        C=[[1.0, 0.0]],
        Q=0.01 * np.eye(2),
        R=[[0.1]],
        x0=[0.0, 0.0],
        P0=0.05 * np.eye(2),
    )
    cens = tk.Censoring(lower=0.0, upper=2.0)
    data = tk.simulate(sys_, 40, 1500, censoring=cens, seed=3)
    one = tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1).filter(data.y)
    for threads in (2, 5):
        many = tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=threads).filter(data.y)
        np.testing.assert_array_equal(one.mean, many.mean)
        np.testing.assert_array_equal(one.cov, many.cov)
        np.testing.assert_array_equal(one.extras["p_uncensored"], many.extras["p_uncensored"])


@pytest.mark.parametrize("threads", [0, -1, 1.5, True, "2"])
def test_threads_option_is_checked(threads):
    import tobitkf as tk

    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.1]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="threads"):
        tk.TobitKalmanFilter(sys_, tk.Censoring(lower=0.0), threads=threads)


@pytest.mark.parametrize("outputs", ["last", ("mean",), ("cov",), ("var",), ("pred_mean", "extras"), "all"])
@pytest.mark.parametrize("m", [1, 2])
def test_kernels_honour_the_output_selection(outputs, m):
    """Each selection gives, through the kernels, exactly the fields the numpy path gives, equal to 1e-12,
    and the same final state (the kernels stage and write only what was requested)."""
    sys_ = oscillator(m=m)
    cens = tk.Censoring(lower=[0.0] * m)
    y = data(sys_, cens, runs=40, steps=70)
    for make in (lambda be: tk.TobitKalmanFilter(sys_, cens, backend=be), lambda be: tk.KalmanFilter(sys_, backend=be)):
        a = make("numba").filter(y, outputs=outputs)
        b = make("numpy").filter(y, outputs=outputs)
        for f in FIELDS + ("var",):
            va, vb = getattr(a, f), getattr(b, f)
            assert (va is None) == (vb is None), f
            if va is not None:
                assert_same(va, vb)
        assert a.extras.keys() == b.extras.keys()
        for key in a.extras:
            assert_same(a.extras[key], b.extras[key])
        assert_same(a.final.x, b.final.x)
        assert_same(np.broadcast_to(a.final.P, b.final.P.shape), b.final.P)
