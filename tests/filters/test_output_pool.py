"""The output pool (filters/_pool.py): a buffer is handed out again only when no array of its result lives.

What can go wrong and is checked here: a buffer handed out while a result (or any view cut from it) is still
alive would let the next call overwrite a result the caller holds; a pool that never reuses would keep
memory for nothing; the limit not respected; two threads taking the same buffer. Results with the pool are
compared with results without it (bitwise: the same kernel on the same data).
"""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters import _pool
from tobitkf.filters._backend import numba_available


def _addr(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


@pytest.fixture
def pool():
    """A pool with a known limit and no buffers of other tests; restored afterwards."""
    previous = tk.set_output_pool(0)  # drops every free buffer
    tk.set_output_pool(64 * _pool.MIN_BYTES)
    yield _pool
    tk.set_output_pool(previous)


def test_reused_only_when_free(pool):
    n = pool.MIN_BYTES // 8
    a = pool.take_buffer(n)
    first = _addr(a)
    b = pool.take_buffer(n)
    assert _addr(b) != first  # a is alive: not handed out again
    view = a[10:20].reshape(2, 5)
    del a
    gc.collect()
    c = pool.take_buffer(n)
    assert _addr(c) != first  # a view of it is alive
    view[...] = 7.0
    del view, c
    d = pool.take_buffer(n)
    assert _addr(d) == first  # nothing of it left: reused
    big = pool.take_buffer(4 * n)
    big_addr = _addr(big)
    del big
    e = pool.take_buffer(n)
    assert _addr(e) != big_addr  # a free buffer over twice the request is not used for it
    f = pool.take_buffer(3 * n)
    assert _addr(f) == big_addr  # but for one it fits


def test_small_requests_and_the_limit(pool):
    pool.take_buffer(pool.MIN_BYTES // 8 - 1)  # below MIN_BYTES: plain numpy, not pooled
    assert pool._held() == 0
    tk.set_output_pool(2 * pool.MIN_BYTES)
    big = pool.take_buffer(3 * pool.MIN_BYTES // 8)  # larger than the limit: plain
    assert pool._held() == 0
    a = pool.take_buffer(pool.MIN_BYTES // 8)
    b = pool.take_buffer(pool.MIN_BYTES // 8)
    assert pool._held() == 2 * pool.MIN_BYTES
    c = pool.take_buffer(pool.MIN_BYTES // 8)  # no room, nothing free to evict: plain
    assert pool._held() == 2 * pool.MIN_BYTES
    del a, b, c, big
    d = pool.take_buffer(pool.MIN_BYTES // 4)  # evicts the two free ones to make room
    assert pool._held() == 2 * pool.MIN_BYTES
    assert tk.set_output_pool(0) == 2 * pool.MIN_BYTES  # the previous limit; d is in use: kept until freed
    assert pool._held() == 2 * pool.MIN_BYTES
    d[:] = 1.0  # still usable
    del d
    tk.set_output_pool(0)  # evicts it now that it is free
    assert pool._held() == 0


@pytest.mark.parametrize("bad", [-1, 1.5, "1", True])
def test_bad_limit_raises(bad):
    with pytest.raises(ValueError, match="max_bytes"):
        tk.set_output_pool(bad)


@pytest.mark.skipif(not numba_available(), reason="the compiled loops take their outputs from the pool")
def test_filter_results_with_and_without_the_pool(pool):
    """The same TKF call with the pool off and on: equal; a held result is not overwritten by later calls;
    a freed one's memory is reused."""
    w = 0.05
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]],
        x0=[0.0, 0.0], P0=0.05 * np.eye(2),
    )  # fmt: skip
    cens = tk.Censoring(lower=0.0)
    y = tk.simulate(sys_, 100, 2000, censoring=cens, seed=0).y  # mean + cov: 2000 x 100 x 6 x 8 B = 9.6 MB
    tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba")
    tk.set_output_pool(0)
    ref = tkf.filter(y, outputs=("mean", "cov"))
    tk.set_output_pool(64 * _pool.MIN_BYTES)
    kept = tkf.filter(y, outputs=("mean", "cov"))
    mean_copy = kept.mean.copy()
    for _ in range(3):
        other = tkf.filter(y[::-1].copy(), outputs=("mean", "cov"))  # different numbers, same size
        assert not np.shares_memory(other.mean, kept.mean)
    np.testing.assert_array_equal(kept.mean, mean_copy)  # not written over
    np.testing.assert_array_equal(kept.mean, ref.mean)
    np.testing.assert_array_equal(kept.cov, ref.cov)
    addr = _addr(other.mean)
    del other
    again = tkf.filter(y, outputs=("mean", "cov"))
    assert _addr(again.mean) == addr  # the freed result's memory
    np.testing.assert_array_equal(again.cov, ref.cov)


@pytest.mark.skipif(not numba_available(), reason="the compiled loops take their outputs from the pool")
def test_threads_never_share_a_buffer(pool):
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.2]], x0=[0.0], P0=[[1.0]])
    cens = tk.Censoring(lower=0.0)
    ys = [tk.simulate(sys_, 200, 3000, censoring=cens, seed=s).y for s in range(4)]
    tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1)
    tk.set_output_pool(0)
    refs = [tkf.filter(y).mean for y in ys]
    tk.set_output_pool(64 * _pool.MIN_BYTES)
    errors: list[str] = []

    def work(i: int) -> None:
        for _ in range(5):
            got = tkf.filter(ys[i])
            if not np.array_equal(got.mean, refs[i]):
                errors.append(f"thread {i}")

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


def test_bypassed_leaves_the_pool(pool):
    n = pool.MIN_BYTES // 8
    a = pool.take_buffer(n)
    first = _addr(a)
    del a
    with pool.bypassed():
        b = pool.take_buffer(n)
        assert _addr(b) != first and pool._held() == pool.MIN_BYTES  # fresh; the free buffer kept
    del b
    assert _addr(pool.take_buffer(n)) == first


def test_default_limit_is_bounded_by_memory():
    assert 0 < _pool.DEFAULT_LIMIT <= 1 << 30
