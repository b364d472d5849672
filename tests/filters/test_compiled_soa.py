"""The KF and the TKF vectorised over the runs (structure-of-arrays step) against the compiled loop's block path.

The oracle is the compiled loop (:func:`tobitkf.filters._compiled_loop.compiled_loop` through its KF and TKF
entries, itself tested against the numpy filters in test_kernels.py), called with the same arrays; every output
must agree to 1e-12 (relative to the output's scale): random systems, both covariance forms, every noise term,
lower and upper limits changing with the step, input terms, missing readings, priors 40 standard deviations
from the limit and run counts that are not a multiple of the block.
"""

import re

import numpy as np
import pytest

import tobitkf as tk

pytest.importorskip("numba")

from tobitkf.filters import _compiled_soa as soa  # noqa: E402
from tobitkf.filters._compiled_entries import kalman_loop, tobit_loop  # noqa: E402

# the public filters route small problems to the runs-vectorised step here, as for a user (tests/conftest.py)
pytestmark = pytest.mark.vectorised_step

#: the state sizes every update is checked at in the default run. The step is compiled once per state size and
#: update (one version of ``soa_loop`` each, 15 to 40 s of CPU on a fresh numba cache), and only the tests of this
#: module compile it in the default run (elsewhere the public filters run the compiled loop: tests/conftest.py): each
#: update at n = 2 (the state loops unrolled with their cross terms); n = 1 and the larger sizes, up to
#: :data:`~tobitkf.filters._compiled_soa.SOA_MAX_N`, with the heavy tests (``-m heavy``, which CI runs too)
DEFAULT_SIZES = (2,)


def _sizes(*ns, default=DEFAULT_SIZES):
    """The parameters ``ns`` of a state size: those in ``default`` as they are, the others heavy."""
    return [n if n in default else pytest.param(n, marks=pytest.mark.heavy) for n in ns]


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


@pytest.mark.parametrize("n", _sizes(1, 2, 3))
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


@pytest.mark.parametrize("n", _sizes(2, 3))
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


def _tail_case():
    """9 runs x 6 steps of a precise two-state prior at the origin read through its first component with noise
    sd 0.2, no inputs: ``N, T, A, Q, H, sigma, x0, P0``, the (empty) input terms and the latent prediction's sd
    (for limits many sds away)."""
    n, N, T = 2, 9, 6
    x0 = np.zeros((N, n))
    P0 = np.broadcast_to(1e-4 * np.eye(n), (N, n, n)).copy()
    A, Q, H = np.array([[0.9, 0.1], [0.0, 0.8]]), 1e-4 * np.eye(n), np.array([[[1.0, 0.0]]])
    bu, du = np.empty((N, 0, n)), np.empty((N, 0, 1))
    return N, T, A, Q, H, np.array([[0.2]]), x0, P0, bu, du, float(np.sqrt(0.04 + 1e-4))


@pytest.mark.parametrize("dist", [-40.0, 40.0])
@pytest.mark.parametrize("upper", [False, True])
def test_tkf_prior_40_sigma_from_the_limit(dist, upper):
    """The latent prediction 40 standard deviations inside or outside the uncensored region, both sides: the
    tail routes of the statistics (the TKF's gamma near 0 or 1)."""
    N, T, A, Q, H, sigma, x0, P0, bu, du, sd = _tail_case()
    lim = -dist * sd if not upper else dist * sd
    lo = np.full((1, 1), -np.inf if upper else lim)
    hi = np.full((1, 1), lim if upper else np.inf)
    y = np.full((N, T, 1), lim)
    a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, 0, False, x0, P0)
    for u, v in zip(a, b):
        _assert_close(u, v)
    g = a[4]
    assert np.all(np.isfinite(g)) and (np.all(g < 1e-300) or np.all(g > 1 - 1e-12))


@pytest.mark.parametrize("n", _sizes(1, 2, 4))
@pytest.mark.parametrize("joseph", [False, True])
@pytest.mark.parametrize("code", [0, 1, 2])
def test_tkf_two_sided_equals_the_compiled_loop(n, joseph, code):
    """Two finite limits (the split step): 131 runs (a block and a remainder), missing readings, inputs, readings
    at both limits, and priors spread so that runs take every route of the window statistics (direct formulas,
    one side negligible in a tail, a window in a tail: quadrature)."""
    N, T = 131, 25
    rng, A, Q, H, x0, P0, y, bu, du = _case(n, N, T, 200 + 10 * n + code, inputs=True)
    x0 = x0 * rng.choice([1.0, 8.0, 30.0], size=(N, 1))  # some runs far from the window
    lo, hi = np.full((1, 1), -0.3), np.full((1, 1), 0.5)
    y = np.clip(y, lo[None], hi[None])
    y[rng.random(size=y.shape) < 0.05] = np.nan
    sigma = np.array([[0.4]])
    a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0)
    for u, v in zip(a, b):
        _assert_close(u, v)
    assert np.isfinite(a[0]).all() and (a[4] < 0.5).any()


@pytest.mark.parametrize("sd", [0.05, 0.4, 3.0])
def test_tkf_limits_of_every_kind_per_step(sd):
    """Per-step limits cycling lower, upper, two-sided, none, a narrow window (quadrature for every run) and a
    wide one; the noise standard deviation from narrower than the window to wider (the routes of the window
    statistics); the three covariance outputs."""
    n, N, T = 2, 140, 36
    rng, A, Q, H, x0, P0, y, bu, du = _case(n, N, T, 31)
    kinds = [(0.0, np.inf), (-np.inf, 0.4), (-0.3, 0.5), (-np.inf, np.inf), (0.1, 0.15), (-2.0, 3.0)]
    lo = np.array([kinds[t % len(kinds)][0] for t in range(T)])[:, None]
    hi = np.array([kinds[t % len(kinds)][1] for t in range(T)])[:, None]
    y = np.clip(y, lo[None], hi[None])
    y[rng.random(size=y.shape) < 0.05] = np.nan
    sigma = np.array([[sd]])
    for cov_shape in ("full", "var", "none"):
        a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, 2, False, x0, P0, cov_shape)
        for u, v in zip(a, b):
            _assert_close(u, v)


@pytest.mark.parametrize("dist", [-40.0, 40.0])
def test_tkf_two_sided_prior_40_sigma_from_the_window(dist):
    """The latent prediction 40 standard deviations below or above a window of one standard deviation: the
    window in a tail (quadrature) for every run, a finite update."""
    N, T, A, Q, H, sigma, x0, P0, bu, du, sd = _tail_case()
    lo = np.full((1, 1), -dist * sd)
    hi = lo + sd
    y = np.full((N, T, 1), lo[0, 0] if dist < 0 else hi[0, 0])
    a, b = _tkf_both(y, A, Q, H, sigma, lo, hi, bu, du, 0, False, x0, P0)
    for u, v in zip(a, b):
        _assert_close(u, v)
    assert np.isfinite(a[0]).all() and np.isfinite(a[1]).all()


@pytest.mark.parametrize("n", _sizes(1, 2, 3))
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
    assert soa.soa_covers(False, 1, 2, 5, 5, np.zeros((1, 1)), np.ones((1, 1)))  # two-sided
    assert soa.soa_covers(False, 1, 2, 5, 5, np.full((1, 1), -inf), np.full((1, 1), inf))  # no limit
    assert not soa.soa_covers(False, 1, 2, 5, 5, np.ones((1, 1)), np.ones((1, 1)))  # lo == hi
    assert not soa.soa_covers(False, 1, 2, 5, 5, np.full((1, 1), np.nan), np.ones((1, 1)))  # a NaN limit
    assert soa.soa_covers(False, 2, 2, 5, 5, np.zeros((1, 2)), np.full((1, 2), inf)) == (
        (2, 2) in soa.TKF_JOINT_ROUTED
    )  # two channels: where measured faster
    assert not soa.soa_covers(False, 1, 5, 5, 5, np.zeros((1, 1)), np.full((1, 1), inf))  # n too large
    assert soa.soa_covers(True, 1, 3, 5, 5)
    assert not soa.soa_covers(True, 1, 3, 1, 5)  # one shared covariance: the shared-gain path


def test_entries_choose_the_soa_path_only_where_covered():
    inf = np.inf
    assert soa.tobit_entry(tobit_loop, 1, 2, np.zeros((1, 1)), np.full((1, 1), inf)) is soa.soa_tobit_loop
    assert soa.tobit_entry(tobit_loop, 1, 2, np.zeros((1, 1)), np.ones((1, 1))) is soa.soa_tobit_loop
    assert soa.tobit_entry(tobit_loop, 4, 2, np.zeros((1, 4)), np.ones((1, 4))) is tobit_loop  # four channels
    assert soa.kalman_entry(kalman_loop, 1, 2, 7, 7) is soa.soa_kalman_loop
    assert soa.kalman_entry(kalman_loop, 2, 4, 7, 7) is kalman_loop  # two channels, n = 4: measured slower


# ---- the censored assumed-density filter: the SoA step against the compiled loop ------------------------------------


def _adf_both(y, A, Q, H, r, lo, hi, x0, P0, *, cls=None, bu=None, du=None, extras=True, covs=True, npass=1):
    """The SoA step and the compiled loop (the oracle) with the same arguments of ``compiled_loop``: ``r``, ``lo``,
    ``hi`` (1, steps or 1, 1); outputs all, or the means only (``extras``/``covs`` False)."""
    from tobitkf.filters._compiled_loop import compiled_loop
    from tobitkf.filters._compiled_moments import CENSORED, kind

    N, T, _ = y.shape
    n = A.shape[0]
    bu = np.empty((N, 0, n)) if bu is None else bu
    du = np.empty((N, 0, 1)) if du is None else du
    cls = np.empty((N, 0, 1), dtype=np.int8) if cls is None else cls
    res = []
    for fn in (soa.soa_censored_loop, compiled_loop):
        outs = [
            np.full((N, T, n), np.nan),
            np.full((N, T, n, n) if covs else (N, 0, n, n), np.nan),
            np.full((N, T, n), np.nan),
            np.full((N, T, n, n) if covs else (N, 0, n, n), np.nan),
            np.full((N, T if extras else 0, 1), np.nan),
            np.full((N, T if extras else 0), np.nan),
            np.full((N, n), np.nan),
            np.full((N, n, n), np.nan),
        ]
        means, cv, pm, pc, pu, ll, xl, Pl = outs
        fn(
            kind(CENSORED), y, cls, A[None, None], Q[None, None], H, np.zeros((1, 1, 0, n)), r, lo, hi, np.zeros((1, 1, 0)), 0,
            npass, 0, False, bu, du, x0, P0, means, cv, pm, pc, pu, np.empty((N, 0, 1)), ll,
            np.empty((N, 0, 1, 0)), xl, Pl,
        )  # fmt: skip
        res.append(outs)
    return res


_LIMITS = {
    "lower": (0.0, np.inf),
    "upper": (-np.inf, 0.4),
    "two-sided": (-0.3, 0.5),
    "none": (-np.inf, np.inf),
}


@pytest.mark.parametrize("n", _sizes(1, 2, 3, 4))
@pytest.mark.parametrize("kind", list(_LIMITS))
@pytest.mark.parametrize("extras", [True, False])
def test_adf_equals_the_compiled_loop(n, kind, extras):
    """Random system, 131 runs (a block and a remainder), missing readings, inputs, limits of each kind; every
    output (P(uncensored), the log-likelihood) or the means only."""
    N, T = 131, 25
    rng, A, Q, H, x0, P0, y, bu, du = _case(n, N, T, 100 + 10 * n + len(kind), inputs=True)
    a, b = _LIMITS[kind]
    y = np.clip(y, a, b)
    y[rng.random(size=y.shape) < 0.05] = np.nan
    lo, hi = np.full((1, 1, 1), a), np.full((1, 1, 1), b)
    r = np.full((1, 1, 1), 0.2)
    s, ref = _adf_both(y, A, Q, H, r, lo, hi, x0, P0, bu=bu, du=du, extras=extras, covs=extras)
    for u, v in zip(s, ref):
        _assert_close(u, v)
    assert np.isfinite(s[0]).all()
    if extras and kind != "none":
        assert np.isfinite(s[5]).all() and (s[4] < 1.0).any()  # censored readings took part


@pytest.mark.parametrize("n", _sizes(2, 3))
def test_adf_per_step_limits_and_noise_given_classes_and_two_passes(n):
    """Limits changing kind with the step (lower, upper, two-sided, none), a noise variance per step, the classes
    given (a reading at a limit declared uncensored), and the two-pass order (one channel: the same update)."""
    N, T = 40, 24
    rng, A, Q, H, x0, P0, y, _, _ = _case(n, N, T, 77)
    kinds = list(_LIMITS.values())
    lo = np.array([kinds[t % 4][0] for t in range(T)])[None, :, None]
    hi = np.array([kinds[t % 4][1] for t in range(T)])[None, :, None]
    y = np.clip(y, lo, hi)
    r = rng.uniform(0.05, 0.5, size=(1, T, 1))
    from tobitkf.filters._readings import classify_readings

    cls = classify_readings(y, lo, hi)
    cls[rng.random(size=cls.shape) < 0.2] = 1  # INTERIOR: a reading at its limit taken as it is
    cls = np.ascontiguousarray(cls, dtype=np.int8)
    for npass in (1, 2):
        for c in (None, cls):
            s, ref = _adf_both(y, A, Q, H, r, lo, hi, x0, P0, cls=c, npass=npass)
            for u, v in zip(s, ref):
                _assert_close(u, v)


@pytest.mark.parametrize("dist", [-40.0, 40.0])
@pytest.mark.parametrize("kind", ["lower", "upper", "two-sided"])
def test_adf_prior_40_sigma_from_the_limit(dist, kind):
    """The latent prediction 40 standard deviations from the limit, inside and outside: the tail routes of the
    statistics, a finite log-likelihood."""
    n, N, T = 2, 9, 6
    A = np.array([[0.9, 0.1], [0.0, 0.8]])
    Q = 1e-4 * np.eye(n)
    H = np.array([[[1.0, 0.0]]])
    x0 = np.zeros((N, n))
    P0 = np.broadcast_to(1e-4 * np.eye(n), (N, n, n)).copy()
    sd = float(np.sqrt(0.04 + 1e-4))
    d = dist * sd
    a, b = {"lower": (-d, np.inf), "upper": (-np.inf, d), "two-sided": (-d, -d + 1.0) if dist < 0 else (d - 1.0, d)}[
        kind
    ]
    y = np.full((N, T, 1), a if np.isfinite(a) else b)
    s, ref = _adf_both(y, A, Q, H, np.full((1, 1, 1), 0.04), np.full((1, 1, 1), a), np.full((1, 1, 1), b), x0, P0)
    for u, v in zip(s, ref):
        _assert_close(u, v)
    assert np.isfinite(s[5]).all()


def test_adf_interval_readings_equal_the_compiled_loop():
    """Given classes with interval readings (flagged censored strictly inside two finite limits: the mass of the
    window, by quadrature) take the compiled loop's update: the SoA entry hands such a record to the loop."""
    n, N, T = 2, 131, 20
    rng, A, Q, H, x0, P0, y, _, _ = _case(n, N, T, 91)
    lo, hi = np.full((1, 1, 1), -0.3), np.full((1, 1, 1), 0.5)
    y = np.clip(y, -0.3, 0.5)
    from tobitkf.filters._readings import INTERVAL, classify_readings

    cls = classify_readings(y, lo, hi)
    inside = (y > -0.3) & (y < 0.5)
    cls[inside & (rng.random(size=y.shape) < 0.2)] = INTERVAL
    cls = np.ascontiguousarray(cls, dtype=np.int8)
    assert (cls == INTERVAL).any()
    s, ref = _adf_both(y, A, Q, H, np.full((1, 1, 1), 0.2), lo, hi, x0, P0, cls=cls)
    for u, v in zip(s, ref):
        _assert_close(u, v)


def test_log_pos_within_two_ulp_of_math_log():
    """The vectorisable logarithm of the log-likelihoods (no libm call) against ``numpy.log``: within 2 ulp from
    the smallest normal number to the largest finite one, exact at 1 and at powers of two, inf at inf."""
    from numba import njit

    from tobitkf.filters._compiled_censored import _log_pos

    @njit
    def logs(x):
        out = np.empty_like(x)
        for i in range(x.size):
            out[i] = _log_pos(x[i])
        return out

    rng = np.random.default_rng(0)
    tiny, big = np.finfo(float).tiny, np.finfo(float).max
    x = np.concatenate(
        [np.exp(rng.uniform(-708, 709, 100_000)), 1 + rng.normal(0, 1e-6, 1000), [tiny, big, np.sqrt(2.0)]]
    )
    x = np.concatenate([x, np.nextafter(x[-1], 2.0), np.ldexp(1.0, np.arange(-1022, 1024))[None]], axis=None)
    ref, got = np.log(x), logs(x)
    assert np.all(np.abs(got - ref) <= 2 * np.spacing(np.abs(ref)))
    assert logs(np.array([1.0]))[0] == 0.0 and logs(np.array([np.inf]))[0] == np.inf


def test_adf_covers():
    n = 2
    A, Q = np.eye(n)[None, None], np.eye(n)[None, None]
    H, F0, x0 = np.ones((1, 1, n)), np.zeros((1, 1, 0, n)), np.zeros((3, n))
    r, lim = np.ones((1, 1, 1)), np.zeros((1, 1, 1))
    inf = np.full((1, 1, 1), np.inf)
    assert soa.censored_covers(0, A, Q, H, F0, r, lim, inf, x0)
    assert not soa.censored_covers(1, A, Q, H, F0, r, lim, inf, x0)  # another family
    assert not soa.censored_covers(0, A, Q, np.ones((1, 2, n)), F0, r, lim, inf, x0)  # two channels
    assert not soa.censored_covers(0, A, Q, np.ones((5, 1, n)), F0, r, lim, inf, x0)  # rows per step
    assert not soa.censored_covers(0, np.ones((1, 5, n, n)), Q, H, F0, r, lim, inf, x0)  # A per step
    assert not soa.censored_covers(0, A, Q, H, np.zeros((1, 1, 1, n)), r, lim, inf, x0)  # fading rows
    assert not soa.censored_covers(0, A, Q, H, F0, np.ones((3, 1, 1)), lim, inf, x0)  # noise per run
    assert not soa.censored_covers(0, A, Q, H, F0, r, np.zeros((3, 1, 1)), inf, x0)  # limits per run
    assert not soa.censored_covers(0, A, Q, H, F0, r, np.full((1, 1, 1), np.nan), inf, x0)
    assert not soa.censored_covers(0, np.eye(5)[None, None], np.eye(5)[None, None], np.ones((1, 1, 5)), F0, r,
                                   lim, inf, np.zeros((3, 5)))  # fmt: skip


def _spy(monkeypatch, name):
    calls = []
    real = getattr(soa, name)

    def call(*args):
        calls.append(name)
        return real(*args)

    monkeypatch.setattr(soa, name, call)
    return calls


def test_the_public_filters_take_the_soa_step(monkeypatch):
    """``filter`` of the KF (a covariance per run: missing readings) and of the censored assumed-density filter
    (both orders, two-sided limits) runs the SoA step, with the numbers of the numpy path."""
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.3, 0.0], P0=0.05 * np.eye(2))
    cens = tk.Censoring(lower=-0.2, upper=0.6)
    rng = np.random.default_rng(9)
    N, T = 133, 30
    y = cens.censor(rng.normal(0.2, 0.6, size=(N, T, 1)))
    y[5, 3] = np.nan
    kf_calls = _spy(monkeypatch, "soa_kalman_loop")
    adf_calls = _spy(monkeypatch, "soa_censored_loop")
    ref = tk.KalmanFilter(sys_, backend="numpy").filter(y)
    got = tk.KalmanFilter(sys_, backend="numba").filter(y)
    assert kf_calls
    for f in ("mean", "cov", "pred_mean", "pred_cov"):
        _assert_close(getattr(got, f), getattr(ref, f), rtol=1e-10)
    for order in ("channels", "uncensored_first"):
        ref = tk.AssumedDensityTobitFilter(sys_, cens, order=order, backend="numpy").filter(y, outputs="all")
        got = tk.AssumedDensityTobitFilter(sys_, cens, order=order, backend="numba")
        for outputs in (("mean", "cov", "pred_mean", "pred_cov"), "all"):
            res = got.filter(y, outputs=outputs)
            for f in ("mean", "cov", "pred_mean", "pred_cov"):
                _assert_close(getattr(res, f), getattr(ref, f), rtol=1e-10)
    assert len(adf_calls) == 4  # with and without the extras


# ---- the runs-vectorised step compiles to packed vector instructions --------------------------------------------------

#: a packed multiply (or fused multiply-add) of doubles on SSE/AVX/AVX-512 registers, AT&T syntax as numba prints it:
#: ``vmulpd %zmm1, %zmm2, %zmm3``, ``mulpd %xmm1, %xmm2``; the scalar forms (``vmulsd``) do not match
_PACKED_MUL = re.compile(r"^\s+v?(?:mul|fn?madd\d*|fn?msub\d*)pd\s[^\n]*%[xyz]mm", re.M)
#: the multiplications of the smallest step, the KF's at n = 1 in the standard form: the predicted mean 1, the
#: predicted covariance 2 (A P, then (A P) A^T), the reading's mean 1, h = P c 1, s = c h 1, K e 1 and K h 1. A
#: vectorised step holds each of them at least once as a packed instruction (more with the Joseph form, at larger
#: n and for the TKF and the assumed-density filter, whose statistics add their own); a step that stayed scalar
#: holds none (0 counted on every update when numba's wraparound of negative indices or a reference-count call was
#: left in the loop over the runs)
_MIN_PACKED = 8


def _step_asm(kind, n, m=1):
    """The assembly of the runs-vectorised step (:func:`~tobitkf.filters._compiled_soa._step`) of update ``kind``
    at state size ``n``, freshly compiled (numba shows no code of a function it loaded from its disk cache)."""
    from numba import njit, typeof

    B = soa.SOA_BLOCK
    step = njit(error_model="numpy", nogil=True)(soa._step.py_func)
    W = np.zeros(soa._offsets(n, m)[-1] * B)
    cst = np.zeros(2 * n * n + m * n + m * m)
    args = (soa.SIZES[n], soa.CHANS[m], soa.KINDS[kind], W, cst, B, 0.4, 0.0, np.inf, 0.0, 1.0, np.zeros(m),
            np.full(m, np.inf), 0, False, False, soa.GL_X, soa.GL_W, np.empty((2, soa.GL_X.shape[0])))  # fmt: skip
    step.compile(tuple(typeof(a) for a in args))
    return step.inspect_asm(step.signatures[0])


_KIND_NAMES = {soa.KALMAN: "KF", soa.TOBIT_ANY: "TKF", soa.CENSORED_ADF: "censored ADF",
               soa.CENSORED_ADF_STATS: "censored ADF with extras"}  # fmt: skip


@pytest.mark.parametrize(
    "kind",
    [soa.KALMAN]
    + [pytest.param(k, marks=pytest.mark.heavy) for k in (soa.TOBIT_ANY, soa.CENSORED_ADF_STATS)]
    + [
        pytest.param(
            soa.CENSORED_ADF,
            marks=[
                pytest.mark.heavy,
                pytest.mark.xfail(
                    strict=True,
                    reason="the assumed-density filter's loop without its log-likelihood and P(uncensored) stays "
                    "scalar (with them it vectorises; always computing them was no faster: 68.7 against 64 ns)",
                ),
            ],
        )
    ],
    ids=lambda k: _KIND_NAMES[k],
)
def test_each_update_compiles_to_packed_vector_instructions(kind):
    """Every update the runs-vectorised step serves is vectorised over the runs: its compiled step (n = 1, the
    smallest version and the quickest to compile) holds at least :data:`_MIN_PACKED` packed multiplications. The
    KF in the default run (about 15 s of compiling on a loaded machine), the others, whose statistics take one to
    two minutes each to compile afresh, with the heavy tests."""
    asm = _step_asm(kind, 1)
    found = len(_PACKED_MUL.findall(asm))
    assert found >= _MIN_PACKED, f"{_KIND_NAMES[kind]}: {found} packed multiplications in the step"


# ---- the Kalman filter with several channels: the joint update vectorised over the runs ----------------------------


def _kf_multi_case(n, m, N, T, seed):
    """A random system with ``m`` channels, a full SPD noise covariance R (m, m), a covariance per run, readings
    with about 10 % missing on each channel independently (some runs lose every channel at a step)."""
    rng = np.random.default_rng(seed)
    A, Q, _ = _random_system(n, rng)
    H = rng.normal(size=(1, m, n))
    G = rng.normal(size=(m, m))
    R = (0.2 * (G @ G.T) + 0.1 * np.eye(m))[None]
    x0 = rng.normal(size=(N, n))
    G = rng.normal(size=(N, n, n))
    P0 = np.ascontiguousarray(0.1 * G @ G.transpose(0, 2, 1) + 0.05 * np.eye(n))
    y = rng.normal(0.2, 1.0, size=(N, T, m))
    y[rng.random(size=y.shape) < 0.1] = np.nan
    y[3, 4] = np.nan  # every channel lost
    return A, Q, H, R, x0, P0, y


def _kf_multi_both(n, m, N, T, seed, joseph):
    A, Q, H, R, x0, P0, y = _kf_multi_case(n, m, N, T, seed)
    a, b = _outputs(N, T, n), _outputs(N, T, n)
    soa.soa_kalman_loop(y, A, Q, H, R, joseph, x0, P0, *a[:4], *a[6:])
    kalman_loop(y, A, Q, H, R, joseph, x0, P0, *b[:4], *b[6:])
    return y, a[:4] + a[6:], b[:4] + b[6:]


@pytest.mark.parametrize(
    "n, m, joseph",
    [(2, 2, False)] + [pytest.param(*c, marks=pytest.mark.heavy) for c in [(2, 2, True), (3, 2, False), (1, 3, True),
                                                                        (3, 3, False), (4, 3, True)]],
)  # fmt: skip
def test_kf_several_channels_equals_the_compiled_loop(n, m, joseph):
    """The KF's joint update of m = 2 and 3 channels (full R, readings missing on each channel, a run losing
    every channel at a step) in the runs-vectorised step against the compiled loop's: every output to 1e-12,
    130 runs (a block of 128 and a remainder). Only (n, m) = (2, 2), the standard form, in the default run (one
    new compiled version); the others with the heavy tests."""
    N, T = 130, 20
    y, a, b = _kf_multi_both(n, m, N, T, 40 + 7 * n + m, joseph)
    for u, v in zip(a, b):
        _assert_close(u, v)
    assert np.isnan(y).any() and np.isfinite(a[0]).all()
    # the step where run 3 lost every channel leaves its prediction unchanged
    np.testing.assert_array_equal(a[0][3, 4], a[2][3, 4])
    np.testing.assert_array_equal(a[1][3, 4], a[3][3, 4])


def test_kf_several_channels_routing():
    """The KF's entry takes the joint runs-vectorised update only for the (m, n) of ``KF_JOINT_ROUTED`` (measured
    faster) with a covariance per run; the public filter then runs it, with the numpy path's numbers."""
    assert soa.kalman_entry(kalman_loop, 2, 2, 7, 7) is soa.soa_kalman_loop
    assert soa.kalman_entry(kalman_loop, 2, 2, 1, 7) is kalman_loop  # one shared covariance: the shared-gain path
    for m in (2, 3):
        for n in range(1, soa.SOA_MAX_N + 1):
            want = soa.soa_kalman_loop if (m, n) in soa.KF_JOINT_ROUTED else kalman_loop
            assert soa.kalman_entry(kalman_loop, m, n, 7, 7) is want
    assert soa.kalman_entry(kalman_loop, 3, 3, 7, 7) is kalman_loop  # measured slower
    assert soa.kalman_entry(kalman_loop, 4, 2, 7, 7) is kalman_loop
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0], [0.5, 1.0]], Q=0.01 * np.eye(2), R=[[0.1, 0.02], [0.02, 0.2]],
                           x0=[0.3, 0.0], P0=0.05 * np.eye(2))  # fmt: skip
    rng = np.random.default_rng(11)
    y = rng.normal(0.2, 0.6, size=(131, 30, 2))
    y[rng.random(size=y.shape) < 0.1] = np.nan  # a covariance per run: the runs lose different readings
    ref = tk.KalmanFilter(sys_, backend="numpy").filter(y)
    got = tk.KalmanFilter(sys_, backend="numba").filter(y)
    for f in ("mean", "cov", "pred_mean", "pred_cov"):
        _assert_close(getattr(got, f), getattr(ref, f), rtol=1e-10)


@pytest.mark.heavy
def test_kf_two_channels_compiles_to_packed_vector_instructions():
    """The KF's joint update of two channels (n = 1) is vectorised over the runs: its compiled step holds at least
    the one-channel minimum of packed multiplications (heavy: a version the default run does not compile)."""
    asm = _step_asm(soa.KALMAN, 1, 2)
    found = len(_PACKED_MUL.findall(asm))
    assert found >= _MIN_PACKED, f"KF, two channels: {found} packed multiplications in the step"


# ---- the Tobit Kalman filter with several channels: the joint update vectorised over the runs -----------------------

#: the limits a channel may have at a step: lower, upper, two-sided, none, a narrow window (the window statistics'
#: quadrature for most runs) and a wide one
_TKF_LIMIT_KINDS = [(0.0, np.inf), (-np.inf, 0.4), (-0.3, 0.5), (-np.inf, np.inf), (0.1, 0.15), (-2.0, 3.0)]


def _tkf_multi_case(n, m, N, T, seed, per_step):
    """A random system read through ``m`` random rows with noise sds spread from narrower than the windows to
    wider, inputs (``B^u u_k``, ``D u_k``), a covariance per run, priors spread so that runs take every route of the
    statistics; limits of every kind (``per_step``: each channel cycling through :data:`_TKF_LIMIT_KINDS`, shifted
    by the channel; else channel 0 lower, 1 two-sided, 2 upper, fixed); readings clipped to them, about 10 %
    missing on each channel independently and run 3 losing every channel at step 4."""
    rng = np.random.default_rng(seed)
    A, Q, _ = _random_system(n, rng)
    H = rng.normal(size=(1, m, n))
    sigma = np.array([[0.05, 0.4, 3.0][l % 3] for l in range(m)])[None]
    x0 = rng.normal(size=(N, n)) * rng.choice([1.0, 8.0, 30.0], size=(N, 1))
    G = rng.normal(size=(N, n, n))
    P0 = np.ascontiguousarray(0.1 * G @ G.transpose(0, 2, 1) + 0.05 * np.eye(n))
    if per_step:
        k = len(_TKF_LIMIT_KINDS)
        lo = np.array([[_TKF_LIMIT_KINDS[(t + 2 * l) % k][0] for l in range(m)] for t in range(T)])
        hi = np.array([[_TKF_LIMIT_KINDS[(t + 2 * l) % k][1] for l in range(m)] for t in range(T)])
    else:
        fixed = [(0.0, np.inf), (-0.3, 0.5), (-np.inf, 0.4)]
        lo, hi = np.array([[fixed[l][0] for l in range(m)]]), np.array([[fixed[l][1] for l in range(m)]])
    y = np.clip(rng.normal(0.2, 1.0, size=(N, T, m)), lo[None], hi[None])
    y[rng.random(size=y.shape) < 0.1] = np.nan
    y[3, 4] = np.nan  # every channel lost
    bu, du = rng.normal(0, 0.1, size=(N, T, n)), rng.normal(0, 0.1, size=(N, T, m))
    return A, Q, H, sigma, lo, hi, x0, P0, y, bu, du


def _tkf_multi_outputs(N, T, n, m, cov_shape):
    out = _outputs(N, T, n, cov_shape)
    out[4], out[5] = np.full((N, T, m), np.nan), np.full((N, T, m), np.nan)
    return out


def _check_tkf_multi(n, m, seed, joseph, code, per_step, cov_shape="full"):
    """The SoA step against the compiled loop on :func:`_tkf_multi_case`: every output to 1e-12, a finite
    result, and the step where run 3 lost every channel leaving its prediction unchanged."""
    N, T = 131, 24
    A, Q, H, sigma, lo, hi, x0, P0, y, bu, du = _tkf_multi_case(n, m, N, T, seed, per_step)
    a, b = _tkf_multi_outputs(N, T, n, m, cov_shape), _tkf_multi_outputs(N, T, n, m, cov_shape)
    soa.soa_tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0, *a)
    tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, code, joseph, x0, P0, *b)
    for u, v in zip(a, b):
        _assert_close(u, v)
    assert np.isfinite(a[0]).all() and (a[4] < 0.5).any() and np.isnan(y).any()
    np.testing.assert_array_equal(a[0][3, 4], a[2][3, 4])
    if cov_shape == "full":
        np.testing.assert_array_equal(a[1][3, 4], a[3][3, 4])


#: (n, m) of the TKF's joint update in the default run: two channels at n = 2, the one size the entry routes there
#: (:data:`~tobitkf.filters._compiled_soa.TKF_JOINT_ROUTED`, so the public filters compile it too); each other size
#: is a compiled version of its own that only these tests would compile in the default run: one channel more,
#: one state less or more with the heavy tests
_TKF_MULTI_DEFAULT = [(2, 2)]
_TKF_MULTI_HEAVY = [(1, 2), (1, 3), (2, 3), (3, 2), (4, 2), (3, 3), (4, 3)]


@pytest.mark.parametrize(
    "n, m", _TKF_MULTI_DEFAULT + [pytest.param(*c, marks=pytest.mark.heavy) for c in _TKF_MULTI_HEAVY]
)
def test_tkf_several_channels_equals_the_compiled_loop(n, m):
    """The TKF's joint update of m = 2 and 3 channels in the runs-vectorised step against the compiled loop's: every
    noise term in both covariance forms on fixed limits of different kinds per channel (lower, two-sided, upper),
    and limits changing kind with the step and the channel (lower, upper, two-sided, none, narrow and wide
    windows) with the three covariance outputs; missing readings, a run losing every channel, inputs, 131 runs."""
    for joseph in (False, True):
        for code in (0, 1, 2):
            _check_tkf_multi(n, m, 500 + 10 * n + m + code, joseph, code, per_step=False)
    for cov_shape in ("full", "var", "none"):
        _check_tkf_multi(n, m, 600 + 10 * n + m, True, 2, per_step=True, cov_shape=cov_shape)
        _check_tkf_multi(n, m, 700 + 10 * n + m, False, 0, per_step=True, cov_shape=cov_shape)


@pytest.mark.parametrize("dist", [-40.0, 40.0])
def test_tkf_several_channels_prior_40_sigma_from_the_limits(dist):
    """Two channels, the latent predictions 40 standard deviations inside or outside their limits (a lower limit on
    one, a window of one standard deviation on the other): the tail routes, P(uncensored) near 0 or 1, finite."""
    N, T, A, Q, _, _, x0, P0, bu, _, sd = _tail_case()
    H = np.array([[[1.0, 0.0], [1.0, 0.0]]])
    sigma = np.array([[0.2, 0.2]])
    lo = np.array([[-dist * sd, -dist * sd]])
    hi = np.array([[np.inf, -dist * sd + sd]])
    y = np.broadcast_to(lo[None], (N, T, 2)).copy()
    du = np.empty((N, 0, 2))
    a, b = _tkf_multi_outputs(N, T, 2, 2, "full"), _tkf_multi_outputs(N, T, 2, 2, "full")
    soa.soa_tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, 0, False, x0, P0, *a)
    tobit_loop(y, A, Q, H, sigma, lo, hi, bu, du, 0, False, x0, P0, *b)
    for u, v in zip(a, b):
        _assert_close(u, v)
    g = a[4][..., 0]
    assert np.isfinite(a[0]).all() and np.isfinite(a[1]).all()
    assert np.all(g < 1e-300) if dist < 0 else np.all(g > 1 - 1e-12)


def test_tkf_several_channels_routing(monkeypatch):
    """The TKF's entry takes the joint runs-vectorised update only for the measured (m, n) of
    ``TKF_JOINT_ROUTED`` (measured faster), with limits without NaN and ``lo < hi``; the public filter with two
    channels and two states runs it, with the numpy path's numbers."""
    inf = np.inf
    lo, hi = np.array([[0.0, -inf]]), np.array([[inf, 0.4]])
    for m in (2, 3):
        for n in range(1, soa.SOA_MAX_N + 1):
            lo_m, hi_m = np.zeros((1, m)), np.full((1, m), inf)
            want = soa.soa_tobit_loop if (m, n) in soa.TKF_JOINT_ROUTED else tobit_loop
            assert soa.tobit_entry(tobit_loop, m, n, lo_m, hi_m) is want
    assert soa.tobit_entry(tobit_loop, 4, 2, np.zeros((1, 4)), np.ones((1, 4))) is tobit_loop  # m > SOA_MAX_M
    for m, n in soa.TKF_JOINT_ROUTED:
        assert soa.tobit_entry(tobit_loop, m, n, np.ones((1, m)), np.ones((1, m))) is tobit_loop  # lo == hi
    assert soa.tobit_entry(tobit_loop, 2, 4, np.zeros((1, 2)), np.ones((1, 2))) is tobit_loop  # measured slower
    spy = _spy(monkeypatch, "soa_tobit_loop")
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0], [0.5, 1.0]], Q=0.01 * np.eye(2), R=[[0.1, 0.0], [0.0, 0.2]],
                           x0=[0.3, 0.0], P0=0.05 * np.eye(2))  # fmt: skip
    cens = tk.Censoring(lower=lo[0], upper=hi[0])
    rng = np.random.default_rng(12)
    y = cens.censor(rng.normal(0.2, 0.6, size=(131, 30, 2)))
    y[rng.random(size=y.shape) < 0.1] = np.nan
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y, outputs=("mean", "cov", "extras"))
    got = tk.TobitKalmanFilter(sys_, cens, backend="numba").filter(y, outputs=("mean", "cov", "extras"))
    assert spy  # (m, n) = (2, 2): routed
    for f in ("mean", "cov"):
        _assert_close(getattr(got, f), getattr(ref, f), rtol=1e-10)
    for k in ("p_uncensored", "expected_y"):
        _assert_close(got.extras[k], ref.extras[k], rtol=1e-10)


@pytest.mark.heavy
def test_tkf_two_channels_compiles_to_packed_vector_instructions():
    """The TKF's joint update of two channels (n = 1) is vectorised over the runs: its compiled step holds at least
    the one-channel minimum of packed multiplications (heavy: a version the default run does not compile)."""
    asm = _step_asm(soa.TOBIT_ANY, 1, 2)
    found = len(_PACKED_MUL.findall(asm))
    assert found >= _MIN_PACKED, f"TKF, two channels: {found} packed multiplications in the step"
