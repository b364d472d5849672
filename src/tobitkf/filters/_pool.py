"""The output pool: large output buffers of the compiled loops, kept for reuse once their results are freed.

A compiled ``filter`` call of 10^5 runs x 100 steps returns about 480 MB of means and covariances (1.1 GB with
every output). Writing that much *fresh* memory costs a page fault per page (a 2 MiB page where numpy asks for
transparent huge pages, a 4 KiB one otherwise), the kernel's zeroing of the page and, where transparent huge
pages are on, the kernel's compaction of memory to find them: on the 2-core development VM from ~5 to ~150 ns
per run-step of system time, varying from call to call, against ~40 ns of arithmetic for the core TKF. numpy
takes an array of 32 MiB or more from the C library's ``mmap`` and returns it to the system with ``munmap`` when
it is freed, so a program that calls ``filter`` again and again on batches of one size (a Monte Carlo sweep in
blocks, a likelihood in an optimiser's loop, a benchmark) pays all of that in every call.

How the pool works. Every large output buffer (``numpy`` arrays of at least :data:`MIN_BYTES`) is *leased*: the
caller gets an array over a pooled block through a ``memoryview`` of it, and every output of a call is a view of
that array, so the ``memoryview`` lives exactly as long as some array of the result (or a view cut from one)
does. When the last of them is freed, a finalizer on the ``memoryview`` gives the block back to the pool at
once, which keeps it (up to the limit) and hands it to the next request of its size (at most twice it). A block
is never handed out while any view of it lives, so a result kept by the caller is never written over, and the
pool's reuse does not depend on when the caller asks for its next result: a loop ``r = f.filter(y)`` that holds
the previous result during each call takes two blocks and then alternates between them.

The limit bounds the memory the pool *keeps*: the bytes of free blocks, which a process keeps resident after its
results are freed. Blocks in use are the caller's results and are not counted (so a result larger than half the
limit is pooled too; one larger than the limit is an ordinary allocation). When a returned block does not fit,
the oldest free blocks are released (to the system: large blocks are unmapped). The default limit is 2 GiB (the
1.1 GB of every output of a call of 10^5 runs x 100 steps of an n = 2 filter fits), or an eighth of the memory the
process may use (the machine's, or its control group's) where that is less: every process keeps its own pool,
so that a few worker processes of a sweep keep at most a few eighths of the memory between their calls.
:func:`set_output_pool` lowers or raises it, or turns the pool off, releasing the free blocks.

Thread safety: the pool's lists change under a lock; a block returned while another thread holds the lock (or
during a garbage collection inside the pool) waits in a queue that the next call into the pool files.
"""

from __future__ import annotations

import contextlib
import os
import threading
import weakref
from collections import deque
from collections.abc import Iterator

import numpy as np

__all__ = [
    "set_output_pool",
    "output_pool_limit",
    "take_buffer",
    "bypassed",
    "pool_bytes",
    "MIN_BYTES",
    "DEFAULT_LIMIT",
]

MIN_BYTES = 1 << 22  #: requests below 4 MiB go to numpy directly (the C allocator reuses small blocks itself)


def _usable_memory() -> int:
    """Bytes of memory the process may use: the machine's, or its cgroup's (v2 ``memory.max``) where less; 0
    when unknown."""
    try:
        phys = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):  # pragma: no cover - no sysconf (Windows)
        phys = 0
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            text = f.read().strip()
        cap = int(text) if text.isdigit() else 0
    except OSError:
        cap = 0
    if cap > 0 and (phys <= 0 or cap < phys):
        return cap
    return max(phys, 0)


def _default_limit() -> int:
    """2 GiB, or an eighth of the memory the process may use (:func:`_usable_memory`) where less; 1 GiB when
    that is unknown."""
    usable = _usable_memory()
    return min(2 << 30, usable // 8) if usable > 0 else 1 << 30


DEFAULT_LIMIT = _default_limit()  #: bytes of free blocks the pool keeps by default

_lock = threading.Lock()
_free: list[np.ndarray] = []  # blocks no result uses, oldest first (the lock held)
_returned: deque[np.ndarray] = deque()  # blocks given back and not yet filed (appended without the lock)
_in_use = 0  # bytes of leased blocks (the lock held)
_limit = DEFAULT_LIMIT
_bypass = 0  # > 0 inside bypassed(): fresh memory for every request, the pool left as it is


def _file_returned() -> None:
    """Move the returned blocks to the free list and release the oldest free blocks beyond the limit (the caller
    holds the lock)."""
    global _in_use
    while _returned:
        block = _returned.popleft()
        _in_use -= block.nbytes
        _free.append(block)
    kept = sum(b.nbytes for b in _free)
    while _free and kept > _limit:
        kept -= _free.pop(0).nbytes


def _give_back(block: np.ndarray) -> None:
    """The finalizer of a lease: the last view of ``block`` is gone. Filed now when the lock is free, else by the
    next call into the pool (a finalizer may run inside the pool itself, during a garbage collection)."""
    _returned.append(block)
    if _lock.acquire(blocking=False):
        try:
            _file_returned()
        finally:
            _lock.release()


def _lease(block: np.ndarray, count: int) -> np.ndarray:
    """The first ``count`` numbers of ``block`` as a new array whose last view's end gives ``block`` back."""
    arr = np.frombuffer(memoryview(block), dtype=np.float64, count=count)  # type: ignore[arg-type]
    fin = weakref.finalize(arr.base, _give_back, block)  # arr.base: the memoryview every view of arr holds
    fin.atexit = False
    return arr


def set_output_pool(max_bytes: int) -> int:
    """Set the most bytes of free blocks the output pool keeps for reuse; 0 turns it off.

    Returns the previous limit. Lowering the limit releases the oldest free blocks until the pool fits (blocks in
    use are results the caller holds: they are not counted, and are kept or released when freed). Raises
    ``ValueError`` for a negative or non-integer limit.

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
        _file_returned()
        return previous


@contextlib.contextmanager
def bypassed() -> Iterator[None]:
    """Within the block, every request gets fresh memory and the pool is left as it is (its free blocks are
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
    """The output pool's limit in bytes: the most bytes of free blocks it keeps (0: off)."""
    return _limit


def pool_bytes() -> tuple[int, int]:
    """``(free, in_use)``: bytes of the blocks the pool keeps for reuse and of those leased to live results."""
    with _lock:
        _file_returned()
        return sum(b.nbytes for b in _free), _in_use


def take_buffer(count: int) -> np.ndarray:
    """A float64 array of ``count`` numbers (1-D, C-contiguous, contents undefined, as ``numpy.empty``): from a
    free pooled block of at least that size and at most twice it (the smallest such, the latest freed of
    equals: its pages the likeliest in cache), else from a new block;
    either way leased (given back to the pool when the array and every view of it are freed). Plain
    ``numpy.empty`` below :data:`MIN_BYTES`, above the limit, with the pool off or inside :func:`bypassed`."""
    global _in_use
    nbytes = 8 * count
    if nbytes < MIN_BYTES or nbytes > _limit or _bypass:
        return np.empty(count)
    with _lock:
        _file_returned()
        best = -1
        for i, b in enumerate(_free):
            if nbytes <= b.nbytes <= 2 * nbytes and (best < 0 or b.nbytes <= _free[best].nbytes):
                best = i
        block = _free.pop(best) if best >= 0 else None
        if block is None:
            block = np.empty(count)
        _in_use += block.nbytes
    return _lease(block, count)
