"""The m > 1 path of the TKF/KF kernels (block gain solve, upper-triangle products) against numpy.

The numpy path is the reference. The kernel solves the gains of a whole block of runs at once
(unit-diagonal R_ee, elimination without pivoting, a per-run pivoted solve for a run whose
pivot fails); it must reproduce numpy to rounding (1e-12; 1e-9 with limits 40 sigma out in the
tails, where the statistics themselves agree to that) for one- and two-sided censoring, missing
readings in some channels, both covariance forms, every noise term and every batch shape.
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters.kalman import kalman_filter
from tobitkf.filters.tobit import tobit_kalman_filter

pytest.importorskip("numba")
from tobitkf.filters import _compiled_block  # noqa: E402

FIELDS = ("mean", "cov", "pred_mean", "pred_cov")


def assert_same(a, b, rtol):
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


def random_system(n, m, seed):
    """A stable random system: A = 0.95 x orthogonal, C with unit-scale rows, diagonal R."""
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    C = rng.standard_normal((m, n)) / np.sqrt(n)
    R = np.diag(rng.uniform(0.05, 0.3, m))
    return tk.LinearSystem(A=0.95 * Qo, C=C, Q=0.05 * np.eye(n), R=R, x0=np.zeros(n), P0=np.eye(n))


def censorings(m):
    lo = np.linspace(-0.3, 0.2, m)
    return {
        "one_sided": tk.Censoring(lower=lo),
        "two_sided": tk.Censoring(lower=lo, upper=lo + 0.8),
        "mixed": tk.Censoring(lower=np.where(np.arange(m) % 2 == 0, lo, -np.inf), upper=np.full(m, 0.5)),
    }


def records(system, cens, runs, steps, seed, nan_share=0.1):
    y = tk.simulate(system, steps, runs, censoring=cens, seed=seed).y
    rng = np.random.default_rng(seed + 100)
    y[rng.random(y.shape) < nan_share] = np.nan  # scattered missing readings
    y[:, ::7, 0] = np.nan  # channel 0 missing on every 7th step of every run
    return y


@pytest.mark.parametrize("kind", ["one_sided", "two_sided", "mixed"])
# "total_variance" is left out here: on these random systems it drives p_uncensored to 0 (the filter
# itself diverges, R_ee becomes ill-conditioned) and both kernels, the old per-run one as well,
# then differ from numpy by amplified rounding; tests/filters/test_kernels.py covers it on m = 2.
@pytest.mark.parametrize("noise_term", ["dissertation", "exact_pv"])
@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_tkf_m_gt_1_equals_numpy(kind, noise_term, cu):
    sys_ = random_system(5, 4, seed=1)
    cens = censorings(4)[kind]
    y = records(sys_, cens, runs=40, steps=60, seed=2)  # 40 runs: a full block and a partial one
    a = tobit_kalman_filter(sys_, cens, y, noise_term=noise_term, covariance_update=cu, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, noise_term=noise_term, covariance_update=cu, backend="numpy")
    assert_results_equal(a, b)


@pytest.mark.parametrize("kind", ["one_sided", "two_sided", "mixed"])
def test_tkf_total_variance_m_gt_1_each_step_equals_numpy(kind):
    """``noise_term="total_variance"`` on the systems above, where the filter itself diverges (means
    ~1e3 within 60 steps): the whole trajectories of the two paths then differ by up to ~2e-4 relative,
    but so does the numpy path with x0 moved by 1e-15 (measured: the same size), i.e. the recursion
    amplifies rounding (conditioning), it is not a difference of the kernel. What the kernel must do,
    one predict + update equal to numpy's from the same state, is checked here at every step of
    numpy's own trajectory (to rounding, 1e-12)."""
    sys_ = random_system(5, 4, seed=1)
    cens = censorings(4)[kind]
    y = records(sys_, cens, runs=40, steps=60, seed=2)
    ref = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend="numpy")
    fast = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend="numba")
    traj = ref.filter(y)
    assert np.abs(traj.mean).max() > 100.0  # the filter diverges (the case the note is about)
    for k in range(1, y.shape[1]):
        state = ref.init(batch_shape=(y.shape[0],), x0=traj.mean[:, k - 1], P0=traj.cov[:, k - 1])
        a, b = fast.step(state, y[:, k]), ref.step(state, y[:, k])
        assert_same(a.x, b.x, 1e-12)
        assert_same(a.P, b.P, 1e-12)


@pytest.mark.parametrize("shape", [(), (7,), (2, 3)])
def test_tkf_n16_m8_batch_shapes_equal_numpy(shape):
    sys_ = random_system(16, 8, seed=3)
    cens = censorings(8)["two_sided"]
    runs = int(np.prod(shape)) if shape else 1
    y = records(sys_, cens, runs=runs, steps=30, seed=4)
    y = y[0] if shape == () else y.reshape(shape + y.shape[1:])
    a = tobit_kalman_filter(sys_, cens, y, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, backend="numpy")
    assert a.mean.shape == shape + (30, 16)
    assert_results_equal(a, b)


def test_tkf_n16_outputs_across_chunks_and_blocks_equal_numpy():
    """n = 16: 256 numbers per run-step, the outputs flushed in tiles (``_flush`` for large blocks);
    50 runs (a full block of 40 and a partial one) x 150 steps (two full chunks of 64 and a partial one),
    every output compared with numpy."""

    sys_ = random_system(16, 8, seed=5)
    cens = censorings(8)["two_sided"]
    y = records(sys_, cens, runs=50, steps=150, seed=6)
    assert (
        16 * 16 >= _compiled_block.FLUSH_BY_STEP > 16
        and y.shape[1] > 2 * _compiled_block.CHUNK
        and y.shape[0] > _compiled_block.runs_per_block(16)
    )
    assert_results_equal(
        tobit_kalman_filter(sys_, cens, y, backend="numba"), tobit_kalman_filter(sys_, cens, y, backend="numpy")
    )


@pytest.mark.parametrize(("n", "m"), [(16, 8), (11, 6), (9, 5)])
@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_tkf_blocked_products_across_blocks_equal_numpy(n, m, cu):
    """The block products at larger n (A P and C Pbar over whole slabs of all lanes of the block, four rows x
    four terms at a time; (AP)A^T and the symmetric R_ee four entries x four terms at a time, the covariance
    update four terms; their remainders for n, m not multiples of 4) and the large outputs' flush in 8 x 8
    tiles (remainders of runs and numbers): a full block (``runs_per_block(n)``: 40 runs at n = 16, 64 at 11,
    128 at 9) and a partial one of 18 runs, whose spare lanes hold the first block's values, x 70 steps with
    missing readings, every output against numpy, both covariance forms."""

    sys_ = random_system(n, m, seed=7)
    cens = censorings(m)["one_sided"]
    y = records(sys_, cens, runs=_compiled_block.runs_per_block(n) + 18, steps=70, seed=8)
    a = tobit_kalman_filter(sys_, cens, y, covariance_update=cu, backend="numba")
    b = tobit_kalman_filter(sys_, cens, y, covariance_update=cu, backend="numpy")
    assert_results_equal(a, b)


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_tkf_m_gt_1_limits_40_sigma_out(sign, cu):
    """Channel limits about 40 measurement sigmas away from the readings: one channel always
    censored (window deep in a tail), one never, the others ordinary; agreement to 1e-9."""
    sys_ = random_system(4, 3, seed=5)
    sd = np.sqrt(np.diag(sys_.measurement_cov(1)))
    lo = np.array([sign * 40.0 * sd[0] if sign > 0 else -40.0 * sd[0], -40.0 * sd[1], 0.0])
    hi = np.array([np.inf, 40.0 * sd[1], np.inf]) if sign > 0 else np.array([-39.0 * sd[0], np.inf, 0.6])
    cens = tk.Censoring(lower=lo, upper=hi)
    y = records(sys_, cens, runs=20, steps=50, seed=6, nan_share=0.05)
    for nt in ("dissertation", "total_variance", "exact_pv"):
        a = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numba")
        b = tobit_kalman_filter(sys_, cens, y, noise_term=nt, covariance_update=cu, backend="numpy")
        assert_results_equal(a, b, rtol=1e-9)


@pytest.mark.parametrize("cu", ["standard", "joseph"])
def test_kf_m_gt_1_equals_numpy(cu):
    sys_ = random_system(6, 4, seed=7)
    y = tk.simulate(sys_, 50, 35, seed=8).y
    y[np.random.default_rng(9).random(y.shape) < 0.1] = np.nan  # per-run covariance (skipped channels)
    for yy in (y, np.nan_to_num(y)):  # with and without the shared covariance
        a = kalman_filter(sys_, yy, covariance_update=cu, backend="numba")
        b = kalman_filter(sys_, yy, covariance_update=cu, backend="numpy")
        for f in FIELDS:
            assert_same(getattr(a, f), getattr(b, f), 1e-12)


def _block(n, m, nb, seed):
    """Random block inputs of _gain / _gain_block: SPD R_ee per run, some channels masked."""
    rng = np.random.default_rng(seed)
    G = rng.standard_normal((nb, m, m))
    Ree = np.einsum("bij,bkj->ikb", G, G) + 0.1 * np.eye(m)[:, :, None]
    Ree *= np.exp(rng.uniform(-3, 3, m))[:, None, None] * np.exp(rng.uniform(-3, 3, m))[None, :, None]
    Ree = np.ascontiguousarray(Ree)
    Rxe = rng.standard_normal((n, m, nb))
    ok = rng.random((m, nb)) > 0.2
    e = np.where(ok, rng.standard_normal((m, nb)), 0.0)
    xp = rng.standard_normal((n, nb))
    return Ree, Rxe, ok, e, xp


def _run_both(Ree, Rxe, ok, e, xp):
    n, m, nb = Rxe.shape
    K1, x1, K2, x2 = (np.empty((n, m, nb)), np.empty((n, nb)), np.empty((n, m, nb)), np.empty((n, nb)))
    per_run = (np.empty((m, m)), np.empty((m, n)), np.empty((n, m)), np.empty(m, dtype=bool), np.empty((n, m)))
    _compiled_block._gain(Rxe, Ree.copy(), ok, K1, e, xp, x1, nb, *per_run, np.empty(m))
    before = Ree.copy()
    scratch = (np.empty((m, m, nb)), np.empty((m, n, nb)), np.empty((m, nb)), np.empty(nb, dtype=bool))
    _compiled_block._gain_block(Rxe, Ree, ok, K2, e, xp, x2, nb, *scratch, *per_run, np.empty(m))
    np.testing.assert_array_equal(Ree, before)  # R_ee left as it was
    return K1, x1, K2, x2


def test_gain_block_equals_per_run_solve():
    Ree, Rxe, ok, e, xp = _block(5, 6, 32, seed=10)
    K1, x1, K2, x2 = _run_both(Ree, Rxe, ok, e, xp)
    assert_same(K2, K1, 1e-12)
    assert_same(x2, x1, 1e-12)
    assert np.all(K2[:, ~ok] == 0.0)  # masked channels: zero gain column


def test_gain_block_falls_back_to_pivoting_for_a_failed_pivot():
    """An indefinite R_ee in run 3 (unit-diagonal, off-diagonal 2: second pivot 1 - 4 < 0) is solved by
    the pivoted per-run route: that run equals _gain exactly, the others to rounding."""
    Ree, Rxe, ok, e, xp = _block(3, 2, 8, seed=11)
    ok[:] = True
    Ree[:, :, 3] = [[1.0, 2.0], [2.0, 1.0]]
    K1, x1, K2, x2 = _run_both(Ree, Rxe, ok, e, xp)
    np.testing.assert_array_equal(K2[:, :, 3], K1[:, :, 3])
    assert_same(K2, K1, 1e-12)
    assert_same(x2, x1, 1e-12)
