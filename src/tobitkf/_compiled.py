"""Whether the compiled (numba) paths can run, how many threads they use, and the compile notice.

numba is imported lazily, on the first call that may use a kernel, so ``import tobitkf`` does
not pay for it. Each layer keeps its kernels beside its code (:mod:`tobitkf.filters._compiled_tobit`,
:mod:`tobitkf._compiled_linalg`); this module only answers the questions they share.

**The compile notice.** The kernels are compiled on their first call and kept in numba's on-disk
cache (``cache=True``), so only the first process after an install or an upgrade pays for it (about
a minute on two cores); later processes load them in a few seconds. When a kernel of tobitkf is
actually compiled (a cache miss: numba's ``"numba:compile"`` event, which a cache hit does not
fire), one line on stderr says so, once per process. The listener is registered as soon as numba
is imported, by whichever module imports it first (:func:`watch_compiles`; ``import tobitkf`` does
not import numba for it). ``tobitkf warmup`` compiles the common kernels ahead
(:mod:`tobitkf._warmup`).
"""

from __future__ import annotations

import sys
import threading
import time
from functools import lru_cache

from ._validation import ValidationError

__all__ = [
    "numba_available",
    "default_threads",
    "check_threads",
    "run_split",
    "watch_compiles",
    "compile_stats",
    "COMPILE_NOTICE",
]

COMPILE_NOTICE = (
    "tobitkf: compiling numerical kernels for their first use (once after an install or upgrade, then "
    "cached on disk: up to a minute or two per filter family; 'tobitkf warmup' compiles them all ahead)"
)
"""The line printed on stderr when the first kernel of a process is compiled."""

_STATS = {"compiled": 0, "seconds": 0.0, "announced": False, "watching": False}
_LOCK = threading.Lock()
_SHARED: list = []
"""A flag shared by the worker processes of one command (:func:`share_notice`), empty when there are none."""


def share_notice(flag) -> None:
    """Print the compile notice once across processes: ``flag`` is a ``multiprocessing.Value`` (a lock with
    it) given to every worker process of one command; the first process to compile sets it and prints the
    notice, the others stay silent."""
    _SHARED[:] = [flag]


def _claim_notice() -> bool:
    """Whether this compile is the first of the process, and of the command's processes (:func:`share_notice`)."""
    with _LOCK:
        first = not _STATS["announced"]
        _STATS["announced"] = True
    if first and _SHARED:
        flag = _SHARED[0]
        with flag.get_lock():
            first, flag.value = not flag.value, 1
    return first


def compile_stats() -> dict[str, float | int | bool]:
    """Kernels of tobitkf compiled in this process (cache misses), the seconds spent compiling them, and
    whether the notice was printed (a copy)."""
    with _LOCK:
        return dict(_STATS)


_PACKAGES = ["tobitkf"]
"""Packages whose kernels the notice is about (the tests add a throw-away one)."""


def _is_ours(event) -> bool:
    disp = (getattr(event, "data", None) or {}).get("dispatcher")
    module = getattr(getattr(disp, "py_func", None), "__module__", "") or ""
    return any(module == p or module.startswith(p + ".") for p in _PACKAGES)


def _make_listener():
    from numba.core import event as ev

    class _CompileNotice(ev.Listener):
        """Print :data:`COMPILE_NOTICE` at the first compile of a tobitkf kernel; time the compiles.

        numba compiles under one global lock, so compiles do not overlap; a kernel compiles the
        kernels it calls inside its own compile (``depth``): only the outermost is timed."""

        def __init__(self) -> None:
            self.depth = 0
            self.t0 = 0.0

        def on_start(self, event) -> None:
            if not _is_ours(event):
                return
            self.depth += 1
            if self.depth > 1:
                return
            self.t0 = time.perf_counter()
            if _claim_notice():
                try:
                    sys.stderr.write(COMPILE_NOTICE + "\n")
                    sys.stderr.flush()
                except (OSError, ValueError):  # a closed stderr must not stop the computation
                    pass

        def on_end(self, event) -> None:
            if not _is_ours(event) or self.depth == 0:
                return
            self.depth -= 1
            if self.depth == 0:
                with _LOCK:
                    _STATS["compiled"] += 1
                    _STATS["seconds"] += time.perf_counter() - self.t0

    return _CompileNotice()


def watch_compiles() -> bool:
    """Register the compile notice's listener with numba and key numba's on-disk cache of the package's
    functions on all its compiled modules (:mod:`tobitkf._compiled_cache`) (once; imports numba). False when
    numba does not import."""
    with _LOCK:
        if _STATS["watching"]:
            return True
    try:
        from numba.core import event as ev
    except ImportError:
        return False
    with _LOCK:
        if _STATS["watching"]:
            return True
        _STATS["watching"] = True
    ev.register("numba:compile", _make_listener())
    from ._compiled_cache import install

    install()  # the cache keyed on every compiled module of the package, before any of them is decorated
    return True


class _AfterNumbaImport:
    """A one-shot import hook: when numba is first imported (by any module), register the compile
    notice right after numba's own module has run (:func:`watch_compiles`). It finds numba's module
    through the other finders and only wraps the ``exec_module`` of that module's loader; every other import
    passes."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname != "numba":
            return None
        _unhook()
        import importlib.util

        spec = importlib.util.find_spec("numba")
        loader = getattr(spec, "loader", None)
        inner = getattr(loader, "exec_module", None)
        if inner is None:
            return spec

        def exec_module(module):
            inner(module)
            try:
                watch_compiles()
            except Exception:  # noqa: BLE001 - the notice is a courtesy: never break numba's import
                pass

        loader.exec_module = exec_module  # this loader instance only (numba's)
        return spec


_HOOK = _AfterNumbaImport()


def _unhook() -> None:
    try:
        sys.meta_path.remove(_HOOK)
    except ValueError:
        pass


def _hook() -> None:
    if "numba" in sys.modules:
        if sys.modules["numba"] is not None:
            watch_compiles()
        return
    sys.meta_path.insert(0, _HOOK)


_hook()


@lru_cache(maxsize=1)
def numba_available() -> bool:
    """True when numba imports (the kernels can be compiled)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def default_threads() -> int:
    """Threads for the compiled kernels: ``TOBITKF_NUM_THREADS``, else ``OMP_NUM_THREADS``
    (Dask sets it to 1 in its workers), else the number of CPUs."""
    import os

    for var in ("TOBITKF_NUM_THREADS", "OMP_NUM_THREADS"):
        val = os.environ.get(var, "")
        if val.isdigit() and int(val) >= 1:
            return int(val)
    return os.cpu_count() or 1


def check_threads(threads) -> int:
    """Validate a ``threads`` option (None = :func:`default_threads`)."""
    if threads is None:
        return default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValidationError(f"threads: expected a positive integer or None, got {threads!r}")
    return threads


def run_split(work, runs: int, threads: int, *, min_runs: int = 256) -> None:
    """Call ``work(a, b)`` on disjoint slices of the runs, in threads when worthwhile.

    The kernels release the GIL and runs are independent, so the result is the same
    bit for bit whatever the split; slices smaller than ``min_runs`` are not split.
    """
    parts = max(1, min(threads, runs // min_runs))
    if parts == 1:
        work(0, runs)
        return
    from concurrent.futures import ThreadPoolExecutor

    edges = [runs * i // parts for i in range(parts + 1)]
    with ThreadPoolExecutor(max_workers=parts) as pool:
        for fut in [pool.submit(work, a, b) for a, b in zip(edges[:-1], edges[1:])]:
            fut.result()
