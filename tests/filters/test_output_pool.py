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
    del c
    del view
    d = pool.take_buffer(n)
    assert _addr(d) == first  # nothing of it left: reused (the latest freed of two of the size)
    big = pool.take_buffer(4 * n)
    big_addr = _addr(big)
    del big
    e = pool.take_buffer(n)
    assert _addr(e) != big_addr  # a free buffer over twice the request is not used for it
    f = pool.take_buffer(3 * n)
    assert _addr(f) == big_addr  # but for one it fits


def test_small_requests_and_the_limit(pool):
    """The limit bounds the free blocks kept, not the blocks in use (the caller's results)."""
    pool.take_buffer(pool.MIN_BYTES // 8 - 1)  # below MIN_BYTES: plain numpy, not pooled
    assert pool.pool_bytes() == (0, 0)
    tk.set_output_pool(2 * pool.MIN_BYTES)
    big = pool.take_buffer(3 * pool.MIN_BYTES // 8)  # larger than the limit: plain
    assert pool.pool_bytes() == (0, 0)
    a, b, c = (pool.take_buffer(pool.MIN_BYTES // 8) for _ in range(3))
    assert pool.pool_bytes() == (0, 3 * pool.MIN_BYTES)  # all three leased, over the limit: in use is not counted
    del a, b, c, big
    assert pool.pool_bytes() == (2 * pool.MIN_BYTES, 0)  # two kept (the limit), the oldest released
    d = pool.take_buffer(pool.MIN_BYTES // 4)  # twice as large: no free block fits, a new one
    assert pool.pool_bytes() == (2 * pool.MIN_BYTES, 2 * pool.MIN_BYTES)
    assert tk.set_output_pool(0) == 2 * pool.MIN_BYTES  # the previous limit; the free blocks released
    assert pool.pool_bytes() == (0, 2 * pool.MIN_BYTES)  # d is in use: kept until freed
    d[:] = 1.0  # still usable
    del d
    assert pool.pool_bytes() == (0, 0)  # given back and released at once (limit 0)


def test_a_freed_result_is_given_back_at_once(pool):
    """The last view's end files the block without a further call into the pool; a block freed while the pool's
    lock is held waits and is filed by the next call."""
    n = pool.MIN_BYTES // 8
    a = pool.take_buffer(n)
    view = a[5:]
    del a
    assert sum(b.nbytes for b in pool._free) == 0  # the view holds it
    del view
    assert sum(b.nbytes for b in pool._free) == pool.MIN_BYTES and not pool._returned
    b = pool.take_buffer(n)  # the free block, leased again
    assert pool.pool_bytes() == (0, pool.MIN_BYTES)
    with pool._lock:
        del b  # the finalizer cannot take the lock: queued
    assert len(pool._returned) == 1
    assert pool.pool_bytes() == (pool.MIN_BYTES, 0)  # filed by the next call


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
        assert _addr(b) != first and pool.pool_bytes() == (pool.MIN_BYTES, 0)  # fresh; the free block kept
    del b
    assert _addr(pool.take_buffer(n)) == first


def test_default_limit_is_bounded_by_memory():
    usable = _pool._usable_memory()
    assert _pool.DEFAULT_LIMIT == (min(2 << 30, usable // 8) if usable > 0 else 1 << 30)


@pytest.mark.skipif(not numba_available(), reason="the compiled loops take their outputs from the pool")
def test_a_plain_loop_takes_no_new_pages(pool):
    """``r = tkf.filter(y)`` in a loop holds the previous result during each call: two blocks, then no new pages.

    The outputs (38.4 MB) are above the C library's largest mmap threshold (32 MiB), so fresh ones are mapped
    and unmapped by every call (no reuse by malloc's heap); with numpy's transparent-huge-page advice off, first
    touching them costs one minor fault per 4 KiB page, ``S / 4096`` = 9375. With a limit of 1.5 S the old pool,
    which counted the result in use against its limit, gave fresh memory every second call."""
    import resource

    from numpy._core import multiarray

    w = 0.05
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]],
        x0=[0.0, 0.0], P0=0.05 * np.eye(2),
    )  # fmt: skip
    cens = tk.Censoring(lower=0.0)
    runs, steps = 8000, 100
    y = tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y
    tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba")
    size = runs * steps * 6 * 8  # mean + cov
    tk.set_output_pool(size * 3 // 2)
    advice = multiarray._get_madvise_hugepage()
    multiarray._set_madvise_hugepage(False)
    faults = []
    try:
        # The probe, independent of the pool: first touching a fresh block of the outputs' size must show as
        # minor faults. Where the kernel backs it with huge pages anyway (transparent huge pages 'always') or a
        # sandbox does not count minor faults, nothing here can be observed: skipped, not passed.
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        probe = np.empty(size // 8)
        probe[:] = 1.0
        touched = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
        del probe
        if touched < size // 4096 // 2:
            pytest.skip(f"first touch of a fresh {size} B block counted {touched} minor faults: not observable here")
        r = None
        for _ in range(6):
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            r = tkf.filter(y, outputs=("mean", "cov"))
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
            assert np.isfinite(r.mean[-1]).all()  # read
    finally:
        multiarray._set_madvise_hugepage(advice)
    fresh = size // 4096
    assert faults[1] > fresh // 2  # the second call's block is new (the first result is alive): the probe works
    assert max(faults[2:]) < fresh // 10, faults
