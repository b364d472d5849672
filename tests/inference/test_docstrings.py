"""The docstring examples of tobitkf.inference, tobitkf.data and the filters' smoothing and likelihood modules run and hold."""

import doctest
import importlib

import pytest

MODULES = [
    "tobitkf.data",
    "tobitkf.inference.smoothing",
    "tobitkf.inference.likelihood",
    "tobitkf.inference.censored_ar",
    "tobitkf.inference.fitting",
    "tobitkf.inference.wrtds",
    "tobitkf.inference._results",
    "tobitkf.filters.smoothing",
    "tobitkf.filters.likelihood",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0
