"""The KF and the TKF vectorised over the runs (structure-of-arrays step) against the compiled loop's block path.

The oracle is the compiled loop (:func:`tobitkf.filters._compiled_loop.compiled_loop` through its KF and TKF
entries, itself tested against the numpy filters in test_kernels.py), called with the same arrays; every output
must agree to 1e-12 (relative to the output's scale): random systems, both covariance forms, every noise term,
lower and upper limits changing with the step, input terms, missing readings, priors 40 standard deviations
from the limit and run counts that are not a multiple of the block.
"""

import numpy as np
import pytest

import tobitkf as tk

pytest.importorskip("numba")

from tobitkf.filters import _compiled_soa as soa  # noqa: E402
from tobitkf.filters._compiled_entries import kalman_loop, tobit_loop  # noqa: E402


def _assert_close(a, b, rtol=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    if a.size == 0:
        return
    scale = max(1.0, float(np.max(np.abs(b))))
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


def _random_system(n, rng):
    """A stable random A (spectral radius 0.95), a random SPD Q, a random row c."""
    A = rng.normal(size=(n, n))
    A *= 0.95 / max(abs(np.linalg.eigvals(A)))
    G = rng.normal(size=(n, n))
    Q = 0.05 * (G @ G.T) + 0.01 * np.eye(n)
    c = rng.normal(size=(1, 1, n))
    return A, Q, c


def _outputs(N, T, n, cov_shape="full"):
    cov = {"full": (N, T, n, n), "var": (N, T, n, 1), "none": (N, 0, n, n)}[cov_shape]
    return [
        np.full((N, T, n), np.nan),
        np.full(cov, np.nan),
        np.full((N, T, n), np.nan),
        np.full((N, T, n, n), np.nan),
        np.full((N, T, 1), np.nan),
        np.full((N, T, 1), np.nan),
        np.full((N, n), np.nan),
        np.full((N, n, n), np.nan),
    ]


def _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0, cov_shape="full"):
    N, T, _ = y.shape
    n = A.shape[0]
    a, b = _outputs(N, T, n, cov_shape), _outputs(N, T, n, cov_shape)
    soa.soa_tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0, *a)
    tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0, *b)
    return a, b


def _case(n, N, T, seed, *, inputs=False):
    rng = np.random.default_rng(seed)
    A, Q, H = _random_system(n, rng)
    x0 = rng.normal(size=(N, n))
    G = rng.normal(size=(N, n, n))
    P0 = np.ascontiguousarray(0.1 * G @ G.transpose(0, 2, 1) + 0.05 * np.eye(n))
    y = rng.normal(0.2, 1.0, size=(N, T, 1))
    bu = rng.normal(0, 0.1, size=(N, T, n)) if inputs else np.empty((N, 0, n))
    du = rng.normal(0, 0.1, size=(N, T, 1)) if inputs else np.empty((N, 0, 1))
    return rng, A, Q, H, x0, P0, y, bu, du


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("joseph", [False, True])
@pytest.mark.parametrize("code", [0, 1, 2])
def test_tkf_equals_the_compiled_loop(n, joseph, code):
    """Random system, 130 runs (a block of 128 and a remainder of 2), lower limit, missing readings, inputs."""
    N, T = 130, 25
    rng, A, Q, H, x0, P0, y, bu, du = _case(n, N, T, 10 * n + code, inputs=True)
    lo, hi = np.zeros((1, 1)), np.full((1, 1), np.inf)
    y = np.maximum(y, 0.0)
    y[rng.random(size=y.shape) < 0.05] = np.nan
    sigma = np.array([[0.4]])
    a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0)
    for u, v in zip(a, b):
        _assert_close(u, v)
    assert np.isnan(y).any() and np.isfinite(a[0]).all()


@pytest.mark.parametrize("n", [2, 3])
def test_tkf_limits_changing_side_with_the_step(n):
    """Per-step limits: a lower limit on even steps, an upper limit on odd ones, at different levels; the
    variances-only covariance output."""
    N, T = 37, 30
    rng, A, Q, H, x0, P0, y, bu, du = _case(n, N, T, 7)
    lo = np.where(np.arange(T) % 2 == 0, rng.normal(0, 0.5, T), -np.inf)[:, None]
    hi = np.where(np.arange(T) % 2 == 1, rng.normal(0.5, 0.5, T), np.inf)[:, None]
    y = np.clip(y, lo[None], hi[None])
    sigma = np.array([[0.3]])
    for cov_shape in ("full", "var", "none"):
        a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, 0, False, x0, P0, cov_shape)
        for u, v in zip(a, b):
            _assert_close(u, v)


@pytest.mark.parametrize("dist", [-40.0, 40.0])
@pytest.mark.parametrize("upper", [False, True])
def test_tkf_prior_40_sigma_from_the_limit(dist, upper):
    """The latent prediction 40 standard deviations inside or outside the uncensored region, both sides: the
    tail routes of the statistics (the TKF's gamma near 0 or 1)."""
    n, N, T = 2, 9, 6
    A = np.array([[0.9, 0.1], [0.0, 0.8]])
    Q = 1e-4 * np.eye(n)
    H = np.array([[[1.0, 0.0]]])
    sigma = np.array([[0.2]])
    x0 = np.zeros((N, n))
    P0 = np.broadcast_to(1e-4 * np.eye(n), (N, n, n)).copy()
    sd = float(np.sqrt(0.04 + 1e-4))
    lim = -dist * sd if not upper else dist * sd
    lo = np.full((1, 1), -np.inf if upper else lim)
    hi = np.full((1, 1), lim if upper else np.inf)
    y = np.full((N, T, 1), lim)
    a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, np.empty((N, 0, n)), np.empty((N, 0, 1)), 0, False, x0, P0)
    for u, v in zip(a, b):
        _assert_close(u, v)
    g = a[4]
    assert np.all(np.isfinite(g)) and (np.all(g < 1e-300) or np.all(g > 1 - 1e-12))


@pytest.mark.parametrize("n", [1, 3])
@pytest.mark.parametrize("joseph", [False, True])
def test_kf_equals_the_compiled_loop(n, joseph):
    """The Kalman filter, a covariance per run, missing readings, 200 runs (one block and a remainder)."""
    N, T = 200, 20
    rng, A, Q, H, x0, P0, y, _, _ = _case(n, N, T, 3 + n)
    y[rng.random(size=y.shape) < 0.1] = np.nan
    R = np.array([[[0.3]]])
    a, b = _outputs(N, T, n), _outputs(N, T, n)
    soa.soa_kalman_loop(y, A, Q, H, R, joseph, x0, P0, *a[:4], *a[6:])
    kalman_loop(y, A, Q, H, R, joseph, x0, P0, *b[:4], *b[6:])
    for u, v in zip(a[:4] + a[6:], b[:4] + b[6:]):
        _assert_close(u, v)


def test_tkf_equals_the_public_filter():
    """The SoA entry with the arrays the estimator passes equals ``TobitKalmanFilter.filter`` (backend numba)."""
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.3, 0.0], P0=0.05 * np.eye(2))
    cens = tk.Censoring(lower=0.0)
    rng = np.random.default_rng(5)
    N, T = 131, 40
    y = cens.censor(rng.normal(0.2, 0.6, size=(N, T, 1)))
    y[4, 7] = np.nan
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numba").filter(y, outputs=("mean", "cov", "extras"))
    x0 = np.broadcast_to(np.array([0.3, 0.0]), (N, 2)).copy()
    P0 = np.broadcast_to(0.05 * np.eye(2), (N, 2, 2)).copy()
    out = _outputs(N, T, 2)
    out[2], out[3] = np.empty((N, 0, 2)), np.empty((N, 0, 2, 2))
    e = np.empty((N, 0, 2))
    soa.soa_tobit_loop(
        y, A, 0.01 * np.eye(2), np.array([[[1.0, 0.0]]]), np.array([[np.sqrt(0.1)]]), np.zeros((1, 1)),
        np.full((1, 1), np.inf), e, np.empty((N, 0, 1)), 0, False, x0, P0, *out,
    )  # fmt: skip
    _assert_close(out[0], ref.mean)
    _assert_close(out[1], ref.cov)
    _assert_close(out[4].reshape(N, T), np.reshape(ref.extras["p_uncensored"], (N, T)))


def test_covers():
    inf = np.inf
    assert soa.soa_covers(False, 1, 2, 5, 5, np.zeros((1, 1)), np.full((1, 1), inf))
    assert soa.soa_covers(False, 1, 4, 5, 5, np.array([[-inf], [0.0]]), np.array([[1.0], [inf]]))
    assert not soa.soa_covers(False, 1, 2, 5, 5, np.zeros((1, 1)), np.ones((1, 1)))  # two-sided
    assert not soa.soa_covers(False, 1, 2, 5, 5, np.full((1, 1), -inf), np.full((1, 1), inf))  # no limit
    assert not soa.soa_covers(False, 2, 2, 5, 5, np.zeros((1, 2)), np.full((1, 2), inf))  # two channels
    assert not soa.soa_covers(False, 1, 5, 5, 5, np.zeros((1, 1)), np.full((1, 1), inf))  # n too large
    assert soa.soa_covers(True, 1, 3, 5, 5)
    assert not soa.soa_covers(True, 1, 3, 1, 5)  # one shared covariance: the shared-gain path


def test_entries_choose_the_soa_path_only_where_covered():
    inf = np.inf
    assert soa.tobit_entry(tobit_loop, 1, 2, np.zeros((1, 1)), np.full((1, 1), inf)) is soa.soa_tobit_loop
    assert soa.tobit_entry(tobit_loop, 1, 2, np.zeros((1, 1)), np.ones((1, 1))) is tobit_loop
    assert soa.kalman_entry(kalman_loop, 1, 2, 7, 7) is soa.soa_kalman_loop
    assert soa.kalman_entry(kalman_loop, 2, 2, 7, 7) is kalman_loop
