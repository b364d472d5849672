"""The output pool: large output buffers of the compiled loops, kept for reuse once their results are freed.

A compiled ``filter`` call of 10^5 runs x 100 steps returns about 480 MB of means and covariances. Writing
that much *fresh* memory costs a page fault per page (a 2 MiB page where numpy asks for transparent huge
pages, a 4 KiB one otherwise) and the kernel's zeroing of the page, and on a virtual machine whose host
reclaims the guest's freed memory, the host's backing of it too: on the 2-core development VM that cost
swung from ~5 to ~60 ns per run-step of system time from call to call, against ~35 ns of arithmetic for the
core TKF (``benchmarks/bench_limit.py``). A program that calls ``filter`` again and again on batches of one
size (a Monte Carlo sweep in blocks, a likelihood in an optimiser's loop, a benchmark) frees each result and
allocates the next one's memory afresh.

The pool keeps the buffers it handed out (``numpy`` arrays of at least :data:`MIN_BYTES`) and hands one out
again once no array of the result that used it is alive any more: every output of a call is a view of its
buffer, a view holds a reference to it, and the pool's own references are the only ones left when the
result and everything cut from it have been freed (CPython's reference count, read under a lock, so that
two threads never take the same buffer). A buffer is never handed out while any view of it lives, so a
result kept by the caller is never written over. Buffers in use count against the limit as well as free
ones; a request that does not fit evicts free buffers first, and one larger than the limit (or with the pool
off) is an ordinary allocation. The default limit is 1 GiB, or an eighth of the machine's memory where that
is less. Cost: a process keeps up to the limit of resident memory after its results are freed
(:func:`set_output_pool` lowers it or turns the pool off, releasing the free buffers).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Iterator

import numpy as np

__all__ = ["set_output_pool", "output_pool_limit", "take_buffer", "bypassed", "MIN_BYTES", "DEFAULT_LIMIT"]

MIN_BYTES = 1 << 22  #: requests below 4 MiB go to numpy directly (the C allocator reuses small blocks itself)


def _default_limit() -> int:
    """1 GiB, or an eighth of the physical memory where that is less (4 GB: 512 MB)."""
    try:
        phys = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):  # pragma: no cover - no sysconf (Windows)
        return 1 << 30
    return int(min(1 << 30, phys // 8)) if phys > 0 else 1 << 30


DEFAULT_LIMIT = _default_limit()  #: bytes the pool may hold by default, in use and free together

_lock = threading.Lock()
_buffers: list[np.ndarray] = []
_limit = DEFAULT_LIMIT
_bypass = 0  # > 0 inside bypassed(): fresh memory for every request, the pool left as it is
# sys.getrefcount of a pooled buffer that nobody else holds: the list's reference, the loop variable's and
# getrefcount's argument's (measured at import, so that a different interpreter's count is not assumed)


def _free_count() -> int:
    probe = [np.empty(1)]
    for b in probe:
        return sys.getrefcount(b)
    raise AssertionError  # pragma: no cover


_FREE = _free_count()


def set_output_pool(max_bytes: int) -> int:
    """Set the most bytes the output pool holds (buffers in use and free together); 0 turns it off.

    Returns the previous limit. Lowering the limit releases free buffers until the pool fits (buffers in
    use are released when their results are freed). Raises ``ValueError`` for a negative or non-integer
    limit.

    Examples
    --------
    >>> import tobitkf as tk
    >>> previous = tk.set_output_pool(0)          # every call allocates fresh memory
    >>> _ = tk.set_output_pool(previous)          # back to the default
    """
    global _limit
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, np.integer)) or max_bytes < 0:
        raise ValueError(f"set_output_pool: max_bytes must be a non-negative integer, got {max_bytes!r}")
    with _lock:
        previous, _limit = _limit, int(max_bytes)
        _evict(0)
        return previous


@contextlib.contextmanager
def bypassed() -> Iterator[None]:
    """Within the block, every request gets fresh memory and the pool is left as it is (its free buffers are
    not released, unlike with :func:`set_output_pool`): for benchmarks that time a call with fresh outputs
    beside calls that reuse them. Not thread-local."""
    global _bypass
    with _lock:
        _bypass += 1
    try:
        yield
    finally:
        with _lock:
            _bypass -= 1


def output_pool_limit() -> int:
    """The output pool's limit in bytes (0: off)."""
    return _limit


def _held() -> int:
    return sum(b.nbytes for b in _buffers)


def _evict(need: int) -> None:
    """Drop free buffers until ``need`` more bytes fit under the limit (the caller holds the lock)."""
    held = _held()
    keep = []
    for b in _buffers:  # the same form as the probe of _FREE: the list's, the loop's and the argument's
        if held + need > _limit and sys.getrefcount(b) == _FREE:
            held -= b.nbytes
        else:
            keep.append(b)
    _buffers[:] = keep


def _find_free(nbytes: int) -> np.ndarray | None:
    """A free buffer of ``nbytes`` to twice that, or None (the caller holds the lock). A function of its own
    so that its loop variable, which holds a buffer, is gone before :func:`_evict` counts references."""
    for b in _buffers:
        if nbytes <= b.nbytes <= 2 * nbytes and sys.getrefcount(b) == _FREE:
            return b
    return None


def take_buffer(count: int) -> np.ndarray:
    """A float64 buffer of ``count`` numbers (1-D, C-contiguous, contents undefined, as ``numpy.empty``): a
    free pooled buffer of at least that size and at most twice it (its first ``count`` numbers), else a
    new one, pooled when it fits under the limit."""
    nbytes = 8 * count
    if nbytes < MIN_BYTES or nbytes > _limit or _bypass:
        return np.empty(count)
    with _lock:
        found = _find_free(nbytes)
        if found is not None:
            return found[: nbytes // 8]
        _evict(nbytes)
        buf = np.empty(count)
        if _held() + nbytes <= _limit:
            _buffers.append(buf)
        return buf
