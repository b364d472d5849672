"""numba's on-disk cache keyed on every compiled module of tobitkf together, not on one file.

numba keys a cached function on its own source file alone: a loop in one module that calls functions of another
(the compiled loop of :mod:`tobitkf.filters._compiled_loop` calls the moments of
:mod:`tobitkf.filters._compiled_moments`, the block algebra of :mod:`tobitkf.filters._compiled_block`, ...)
inlines them into its machine code, and an edit of the other module leaves the loop's stale machine code in the
cache, loaded by the next process as if nothing had changed. Here the cache of every function of the package is
keyed on its own file AND on :func:`package_stamp`, a hash of every module of numba-compiled functions of the
package: an edit of any of them invalidates the whole package's cache (the next process compiles afresh; an
installed package never changes, so this costs nothing outside development).

How: :func:`install` puts :class:`PackageStampLocator` first among numba's cache locators; for a function defined
in this package it wraps the locator numba would have chosen (same cache directory, same file names) and adds the
package stamp to its source stamp. Installed when numba is first imported (:func:`tobitkf._compiled.watch_compiles`),
before any function of the package is decorated. A module of numba-compiled functions is named ``_compiled_*.py``
(:data:`PATTERNS`; a test checks every module that defines one).
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path
from typing import Any

__all__ = ["PATTERNS", "compiled_modules", "package_stamp", "install", "PackageStampLocator"]

PACKAGE_DIR = Path(__file__).resolve().parent
PATTERNS = ("_compiled_*.py",)
"""File-name patterns of the package's modules of numba-compiled functions."""


def compiled_modules(root: Path = PACKAGE_DIR) -> list[Path]:
    """The modules of numba-compiled functions under ``root`` (:data:`PATTERNS`), sorted."""
    found: set[Path] = set()
    for pattern in PATTERNS:
        found.update(root.rglob(pattern))
    return sorted(p for p in found if p.is_file())


def _digest(paths: list[Path], root: Path) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(str(p.relative_to(root)).encode())
        h.update(b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


@lru_cache(maxsize=None)
def package_stamp(root: Path = PACKAGE_DIR) -> str:
    """A hash of the names and contents of :func:`compiled_modules` of ``root`` (computed once per process)."""
    return _digest(compiled_modules(root), root)


def _in_package(py_file: str) -> bool:
    try:
        Path(py_file).resolve().relative_to(PACKAGE_DIR)
    except (ValueError, OSError):
        return False
    return True


class PackageStampLocator:
    """A numba cache locator for the functions of this package: the locator numba would choose (``inner``), its
    source stamp extended by :func:`package_stamp`; everything else (cache path, disambiguator) is ``inner``'s."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def get_source_stamp(self) -> Any:
        return (self._inner.get_source_stamp(), package_stamp())

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> PackageStampLocator | None:
        if not _in_package(py_file):
            return None
        for other in _cache_impl()._locator_classes:
            if other is cls:
                continue
            inner = other.from_function(py_func, py_file)
            if inner is not None:
                return cls(inner)
        return None


def _cache_impl() -> Any:
    """numba's cache implementation base class, which holds the list of locators (``CacheImpl``; ``_CacheImpl``
    before numba 0.61)."""
    from numba.core import caching

    return getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")  # noqa: B009


def install() -> None:
    """Put :class:`PackageStampLocator` first among numba's cache locators (once; imports numba). Functions
    decorated before this keep the locator they have."""
    impl = _cache_impl()
    if PackageStampLocator not in impl._locator_classes:
        impl._locator_classes = [PackageStampLocator, *impl._locator_classes]
