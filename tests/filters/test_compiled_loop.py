"""The one compiled loop: the KF and the TKF online step through it against the numpy step.

The whole-record filters through the loop are checked against numpy in test_kernels.py (every noise term, both
covariance forms, tails, inputs, output selections); here the online ``step`` of each form, including the
Kalman filter's shared covariance, the dropping filter and readings 40 standard deviations into the tails.
"""

import numpy as np
import pytest

import tobitkf as tk

pytest.importorskip("numba")


def _system(m=1, correlated=False):
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    C = [[1.0, 0.0]] if m == 1 else [[1.0, 0.0], [0.4, 1.0]]
    R = [[0.1]] if m == 1 else [[0.1, 0.02 if correlated else 0.0], [0.02 if correlated else 0.0, 0.2]]
    return tk.LinearSystem(A=A, C=C, Q=0.01 * np.eye(2), R=R, x0=[0.3, 0.0], P0=0.05 * np.eye(2))


def _record(sys_, runs, steps, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(0.2, 0.6, size=(runs, steps, sys_.m))


def _assert_close(a, b, rtol=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    scale = max(1.0, float(np.max(np.abs(b))))
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


def _steps_equal(fast, ref, y, **step_kw):
    sa = fast.init(batch_shape=y.shape[:1])
    sb = ref.init(batch_shape=y.shape[:1])
    for k in range(y.shape[1]):
        sa, sb = fast.step(sa, y[:, k], **step_kw), ref.step(sb, y[:, k], **step_kw)
        _assert_close(sa.x, sb.x)
        _assert_close(np.broadcast_to(sa.P, sb.P.shape), sb.P)
        for key in sb.extras:
            _assert_close(sa.extras[key], sb.extras[key])


@pytest.mark.parametrize("cu", ["standard", "joseph"])
@pytest.mark.parametrize("noise_term", ["dissertation", "total_variance", "exact_pv"])
@pytest.mark.parametrize("m", [1, 2])
def test_tkf_step_through_the_loop_equals_numpy(cu, noise_term, m):
    sys_ = _system(m)
    cens = tk.Censoring(lower=0.0, upper=1.0) if m == 2 else tk.Censoring(lower=0.0)
    y = cens.censor(_record(sys_, 5, 12))
    y[1, 3] = np.nan  # a missing reading
    kw = {"noise_term": noise_term, "covariance_update": cu}
    fast = tk.TobitKalmanFilter(sys_, cens, backend="numba", **kw)
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy", **kw)
    _steps_equal(fast, ref, y)


@pytest.mark.parametrize("dist", [-40.0, 40.0])
def test_tkf_step_with_the_prediction_40_sigma_from_the_limit(dist):
    """The latent prediction 40 σ inside or outside the uncensored region: the tails of the statistics."""
    sys_ = _system()
    sd = float(np.sqrt(0.1 + 0.05))
    cens = tk.Censoring(lower=0.3 - dist * sd)
    y = np.full((3, 4, 1), 0.3)
    y = np.where(y < cens.lower, cens.lower, y)
    fast = tk.TobitKalmanFilter(sys_, cens, backend="numba")
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy")
    _steps_equal(fast, ref, y)


@pytest.mark.parametrize("cu", ["standard", "joseph"])
@pytest.mark.parametrize("m", [1, 2])
def test_kf_step_through_the_loop_equals_numpy(cu, m):
    """One covariance shared by the runs (nothing missing), then per run (a NaN reading); a correlated R."""
    sys_ = _system(m, correlated=True)
    y = _record(sys_, 4, 10)
    fast = tk.KalmanFilter(sys_, backend="numba", covariance_update=cu)
    ref = tk.KalmanFilter(sys_, backend="numpy", covariance_update=cu)
    _steps_equal(fast, ref, y)
    y[2, 4, 0] = np.nan
    _steps_equal(fast, ref, y)


def test_dropping_kf_step_and_filter_through_the_loop_equal_numpy():
    sys_ = _system(2)
    cens = tk.Censoring(lower=0.0)
    y = cens.censor(_record(sys_, 4, 10))
    fast = tk.DroppingKalmanFilter(sys_, cens, backend="numba")
    ref = tk.DroppingKalmanFilter(sys_, cens, backend="numpy")
    _steps_equal(fast, ref, y)
    a, b = fast.filter(y), ref.filter(y)
    for f in ("mean", "cov", "pred_mean", "pred_cov"):
        _assert_close(getattr(a, f), getattr(b, f))
    np.testing.assert_array_equal(a.extras["censored"], b.extras["censored"])


@pytest.mark.vectorised_step  # the runs-vectorised steps too (n = 2: versions tests/filters/test_compiled_soa.py compiles)
def test_read_only_inputs_reach_the_loop_as_writable_arrays(monkeypatch):
    """numba types a read-only array apart from a writable one: each read-only argument (cached limits, a
    read-only record) compiled the whole loop once more. Every array reaching the loop is writable."""
    from tobitkf.filters import _compiled_entries, _compiled_loop, _compiled_soa

    flags = []

    def spy(real):
        def call(*args):
            flags.extend(a.flags.writeable for a in args if isinstance(a, np.ndarray))
            return real(*args)

        return call

    sys_ = _system()
    cens = tk.Censoring(lower=0.0)
    y = cens.censor(_record(sys_, 3, 6))
    y.setflags(write=False)
    tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba")

    def calls():
        tkf.filter(y)
        tkf.step(tkf.init(batch_shape=(3,)), y[:, 0])
        tk.KalmanFilter(sys_, backend="numba").filter(y)
        tk.AssumedDensityTobitFilter(sys_, cens, backend="numba").filter(y)

    # compiled first with the real entries: a compiled function that calls an entry reads it as a global when it
    # is compiled, and a spy is not compilable (a read-only argument still shows below as a False flag)
    calls()
    for name in ("tobit_loop", "kalman_loop", "tobit_step", "kalman_step"):  # the loop's entries, the step's too
        monkeypatch.setattr(_compiled_entries, name, spy(getattr(_compiled_entries, name)))
    monkeypatch.setattr(_compiled_loop, "compiled_loop", spy(_compiled_loop.compiled_loop))
    for name in ("soa_tobit_loop", "soa_kalman_loop", "soa_censored_loop"):  # the runs-vectorised steps
        monkeypatch.setattr(_compiled_soa, name, spy(getattr(_compiled_soa, name)))
    calls()
    assert len(flags) > 60 and all(flags)


def _disjoint(arrays):
    """No two non-empty arrays of the list share an element, and a write through one reaches no other."""
    on = [a for a in arrays if a.size]
    for i, a in enumerate(on):
        assert a.flags.c_contiguous
        assert all(not np.shares_memory(a, b) for b in on[i + 1 :])


def test_block_scratch_shapes_share_no_element():
    """The block scratch: the shapes the block functions expect, no two arrays sharing an element (a write to
    one cannot change another), the noise term zeroed; m = 0 leaves the gain's arrays empty (the
    assumed-density families, whose loop scratch is sized to the family)."""
    from numba import njit

    from tobitkf.filters._compiled_block import _mean_scratch, _update_scratch

    @njit
    def scratch(dim, ntop, m, B, G):
        return _mean_scratch(dim, m, B), _update_scratch(dim, ntop, m, B, G)

    (x, xp, e, ybar), (blk, run, solve, buf) = scratch(6, 2, 3, 5, 4)
    P, Pp, AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    assert [a.shape for a in (x, xp, e, ybar)] == [(6, 5), (6, 5), (3, 5), (3, 5)]
    assert [a.shape for a in blk] == [(6, 6, 5)] * 2 + [(6, 2, 5), (3, 6, 5), (6, 3, 5), (3, 3, 5)] + [
        (6, 3, 5)
    ] * 2 + [(3, 3, 5), (3, 5), (3, 5)]
    assert [a.shape for a in run] == [(3, 3), (3, 6), (6, 3), (3,), (6, 3), (3,)]
    assert [a.shape for a in solve] == [(3, 3, 5), (3, 6, 5), (3, 5), (5,)] and buf.shape == (2, 4)
    assert (noise == 0.0).all() and ok.dtype == np.bool_ and solve[3].dtype == np.bool_
    floats = [a for a in (x, xp, e, ybar, *blk, *run, *solve, buf) if a.dtype == np.float64]
    _disjoint(floats)
    for i, a in enumerate(floats):  # a write through one reaches no other
        a[...] = i
    assert all((a == i).all() for i, a in enumerate(floats))
    _, (blk0, run0, solve0, _) = scratch(4, 4, 0, 8, 0)
    assert blk0[0].shape == (4, 4, 8) and all(a.size == 0 for a in blk0[3:]) and all(a.size == 0 for a in solve0)
