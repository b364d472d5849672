"""Compile each numba kernel once across the processes of a distributed test run (used by tests/conftest.py).

On a fresh numba cache every xdist worker compiles the kernels its tests call, and the workers call the same ones:
the whole-record loop alone takes about three minutes of CPU, paid once per worker. Two pieces fix that:

* :func:`install` (in every worker and in the warm-up processes) makes the processes take turns: a process that
  is about to compile a function (the outermost call of ``Dispatcher.compile``; the functions it calls are compiled
  inside it) first takes a file lock named after that function. A process that waited finds the function in the
  on-disk cache, which numba checks first inside ``compile``, and loads it instead of compiling it again. Each
  process holds at most one such lock at a time (none is taken inside another), so the processes cannot deadlock.
  The lock also closes a race of numba's cache: two processes saving different signatures of one function at the
  same moment can give both the same data file (``IndexDataCacheFile.save`` reads, extends and writes the index
  without a lock), so the saves take one shared lock.
* :func:`warm` (``python tests/_compile_once.py LOCKS CLAIMS START``, one process per worker, before the workers
  start) runs the targets of ``tobitkf warmup`` (the common kernels at the argument types a user's call passes),
  each target by the first process that claims it, the processes starting at different targets; a target that
  reaches a function another process is compiling is set aside and retried later, so the processes compile
  different kernels side by side instead of waiting for each other.

Without numba, ``fcntl`` (Windows) or the numba internals named above, :func:`install` does nothing and each
process compiles on first use, as before.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
from collections.abc import Iterator

ENV = "TOBITKF_TEST_COMPILE_LOCKS"
"""Environment variable naming the folder of the lock files (set by the controller for its workers)."""

PACKAGES = ["tobitkf"]
"""Packages whose functions take turns (the tests add a throw-away one); numba's own helpers and other packages
compile as usual."""

_STATE = threading.local()


class Busy(BaseException):
    """Another process is compiling this function (raised in a warm-up process, which then tries another target).
    A BaseException, so that a library's ``except Exception`` fallback cannot swallow it."""


@contextlib.contextmanager
def _locked(path: str, wait: bool = True) -> Iterator[None]:
    import fcntl

    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise Busy(path) from None
        yield
    finally:
        os.close(fd)  # releases the lock


def install(lock_dir: str) -> bool:
    """Serialise the compiles of each function and numba's cache saves across the processes sharing ``lock_dir``.
    False (nothing changed) when numba, fcntl or the numba internals are missing."""
    try:
        import fcntl  # noqa: F401

        from numba.core import caching, dispatcher

        import tobitkf._compiled  # noqa: F401 - the package's cache locator goes in when numba is imported
    except ImportError:
        return False
    disp = dispatcher.Dispatcher
    index = getattr(caching, "IndexDataCacheFile", None)
    if not callable(getattr(disp, "compile", None)) or not callable(getattr(index, "save", None)):
        return False
    if getattr(disp.compile, "_compile_once", False):
        return True
    compile_ = disp.compile
    save = index.save

    def compile_once(self, sig):
        if getattr(_STATE, "inside", False):  # a callee of a function being compiled: under the caller's lock
            return compile_(self, sig)
        func = getattr(self, "py_func", None)
        module = getattr(func, "__module__", None) or ""
        if not any(module == p or module.startswith(p + ".") for p in PACKAGES):
            return compile_(self, sig)
        name = f"{module}.{getattr(func, '__qualname__', '?')}"
        path = os.path.join(lock_dir, hashlib.sha1(name.encode()).hexdigest()[:16] + ".lock")
        wait = not getattr(_STATE, "defer", False)
        _STATE.inside = True
        try:
            with _locked(path, wait):
                return compile_(self, sig)
        finally:
            _STATE.inside = False

    def save_locked(self, key, data):
        with _locked(os.path.join(lock_dir, "cache-index.lock")):
            return save(self, key, data)

    compile_once._compile_once = True  # type: ignore[attr-defined]
    disp.compile = compile_once
    index.save = save_locked
    return True


def _run(target, defer: bool) -> bool:
    """Run a warm-up target; False when it stopped at a function another process is compiling (``defer``)."""
    _STATE.defer = defer
    try:
        target()
    except Busy:
        return False
    finally:
        _STATE.defer = False
    return True


def warm(lock_dir: str, claim_dir: str, start: int) -> int:
    """Run the targets of ``tobitkf warmup`` not yet claimed by another process, starting at target ``start``;
    returns the number of kernels this process compiled.

    A target that reaches a function another process is compiling is put back at the end of the queue (it is
    re-run later, loading what it already compiled), so the processes compile different functions side by side
    while there are any; when only such targets are left, the process waits for the lock."""
    install(lock_dir)
    from tobitkf import _compiled, _warmup

    targets = list(enumerate(_warmup.TARGETS))
    start %= max(len(targets), 1)
    deferred = []
    for i, (_label, target) in targets[start:] + targets[:start]:
        try:  # claimed when this process gets to it, so that the other processes take the targets ahead
            os.close(os.open(os.path.join(claim_dir, f"target-{i}"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            continue
        if not _run(target, defer=True):
            deferred.append(target)
    while deferred:
        left = [t for t in deferred if not _run(t, defer=True)]
        if len(left) == len(deferred):  # every one waits on another process: wait for the first
            _run(left.pop(0), defer=False)
        deferred = left
    return int(_compiled.compile_stats()["compiled"])


if __name__ == "__main__":
    print(warm(sys.argv[1], sys.argv[2], int(sys.argv[3])))
