"""Compile a test module's own model functions with numba once per process.

The compiled nonlinear loop is specialised on the functions it is given, and every ``numba.njit(fn)`` call makes a
new dispatcher, a new type: a test that wraps its model functions itself compiles the whole loop again (about 20 s
of CPU) for each call. :func:`jitted` hands back the same dispatchers for the same functions, so that the tests of
one model share one specialisation. Skips the test when numba is not installed.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import pytest


@functools.cache
def jitted(*functions: Callable) -> tuple:
    """``numba.njit`` of each of ``functions``, made once per process and then returned again."""
    numba = pytest.importorskip("numba")
    return tuple(numba.njit(fn) for fn in functions)
