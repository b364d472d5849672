"""numba's on-disk cache of the package keyed on every compiled module together (tobitkf._compiled_cache).

numba alone keys a cached function on its own source file: an edit of _compiled_moments.py, whose functions
the compiled loop inlines, used to leave the loop's stale machine code in the cache for the next process.
"""

import re
from pathlib import Path

import pytest

pytest.importorskip("numba")
from tobitkf import _compiled_cache  # noqa: E402
from tobitkf.filters import _compiled_loop  # noqa: E402


def test_the_loop_is_cached_on_every_compiled_module():
    """compiled_loop's cache entry names its own file and the hash of every compiled module: an edit of
    _compiled_moments.py (inlined into the loop) changes the key."""
    locator = _compiled_loop.compiled_loop._cache._impl.locator
    assert isinstance(locator, _compiled_cache.PackageStampLocator)
    own, pkg = locator.get_source_stamp()
    assert pkg == _compiled_cache.package_stamp()
    names = {p.name for p in _compiled_cache.compiled_modules()}
    assert {"_compiled_loop.py", "_compiled_moments.py", "_compiled_block.py", "_compiled_tobit.py"} <= names


def test_package_stamp_changes_with_any_compiled_module(tmp_path):
    (tmp_path / "sub").mkdir()
    loop = tmp_path / "_compiled_loop.py"
    moments = tmp_path / "sub" / "_compiled_moments.py"
    other = tmp_path / "plain.py"
    for p in (loop, moments, other):
        p.write_text("x = 1\n")
    stamp = _compiled_cache._digest(_compiled_cache.compiled_modules(tmp_path), tmp_path)
    other.write_text("x = 2\n")  # not a compiled module: the same key
    assert _compiled_cache._digest(_compiled_cache.compiled_modules(tmp_path), tmp_path) == stamp
    moments.write_text("x = 2\n")
    assert _compiled_cache._digest(_compiled_cache.compiled_modules(tmp_path), tmp_path) != stamp


def test_every_module_of_compiled_functions_is_in_the_key():
    root = Path(_compiled_cache.__file__).parent
    keyed = set(_compiled_cache.compiled_modules(root))
    jitted = {p for p in root.rglob("*.py") if re.search(r"^@(numba\.)?njit", p.read_text(), re.M)}
    assert jitted <= keyed, sorted(str(p.relative_to(root)) for p in jitted - keyed)
